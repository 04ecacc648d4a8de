//! Training targets kept on the device: a view's target image (and its moving-pixel weights,
//! when `loss.moving_weight` is on) is uploaded at its first use and reused while it fits the
//! budget (`data.device_frame_cache_mib`), least recently used dropped first. A step then sends
//! its target only on a cache miss (issue 21: "target frames are cached on the device").
//!
//! On the CPU backend the device's memory is the host's, which the host frame cache
//! (`data.frame_cache_mib`) already holds the frames in: there the budget is 0 and every step
//! builds its target from the host frame (a copy within the same memory, no transfer), rather
//! than holding every frame twice.

use std::sync::Mutex;

use burn::tensor::Tensor;
use lru::LruCache;

use crate::data::ViewId;

/// What a step compares its render with: [H, W, 3] colours and, when on, [H, W, 1] per-pixel
/// weights of the photometric term.
#[derive(Clone, Debug)]
pub struct DeviceTarget {
    pub rgb: Tensor<3>,
    pub pixel_weights: Option<Tensor<3>>,
}

impl DeviceTarget {
    /// Device memory the entry holds (f32 elements).
    pub fn bytes(&self) -> usize {
        let elements = |t: &Tensor<3>| t.dims().iter().product::<usize>();
        4 * (elements(&self.rgb) + self.pixel_weights.as_ref().map_or(0, elements))
    }
}

struct CacheState {
    entries: LruCache<ViewId, DeviceTarget>,
    bytes: usize,
    hits: u64,
    misses: u64,
}

/// Device-resident targets of the training views, bounded by a byte budget.
pub struct DeviceTargets {
    budget_bytes: usize,
    state: Mutex<CacheState>,
}

impl DeviceTargets {
    pub fn new(budget_bytes: usize) -> Self {
        Self {
            budget_bytes,
            state: Mutex::new(CacheState {
                entries: LruCache::unbounded(),
                bytes: 0,
                hits: 0,
                misses: 0,
            }),
        }
    }

    /// The cached target of `view`, if any (counted as a hit or a miss).
    pub fn get(&self, view: ViewId) -> Option<DeviceTarget> {
        let mut state = self.state.lock().unwrap();
        let found = state.entries.get(&view).cloned();
        match found {
            Some(_) => state.hits += 1,
            None => state.misses += 1,
        }
        found
    }

    /// Keeps `target` as `view`'s when it fits the budget, dropping the least recently used
    /// entries to make room. An entry larger than the whole budget is not kept.
    pub fn insert(&self, view: ViewId, target: DeviceTarget) {
        let bytes = target.bytes();
        let mut state = self.state.lock().unwrap();
        if bytes > self.budget_bytes || state.entries.contains(&view) {
            return;
        }
        state.bytes += bytes;
        state.entries.put(view, target);
        while state.bytes > self.budget_bytes {
            let Some((_, old)) = state.entries.pop_lru() else {
                break;
            };
            state.bytes -= old.bytes();
        }
    }

    /// (bytes held, entries held, hits, misses).
    pub fn usage(&self) -> (usize, usize, u64, u64) {
        let state = self.state.lock().unwrap();
        (state.bytes, state.entries.len(), state.hits, state.misses)
    }

    pub fn budget_bytes(&self) -> usize {
        self.budget_bytes
    }
}

#[cfg(test)]
mod tests {
    #![allow(deprecated)] // Device::ndarray
    use super::*;
    use burn::tensor::Device;

    fn view(camera: usize, frame: usize) -> ViewId {
        ViewId { camera, frame }
    }

    fn target(value: f32, weights: bool) -> DeviceTarget {
        let device = Device::ndarray();
        DeviceTarget {
            rgb: Tensor::full([2, 3, 3], value, &device),
            pixel_weights: weights.then(|| Tensor::full([2, 3, 1], value, &device)),
        }
    }

    #[test]
    fn keeps_the_most_recent_targets_within_the_budget() {
        let entry = target(0.0, false).bytes();
        assert_eq!(entry, 4 * 18);
        assert_eq!(target(0.0, true).bytes(), 4 * 24);
        let cache = DeviceTargets::new(2 * entry);
        assert!(cache.get(view(0, 0)).is_none());
        cache.insert(view(0, 0), target(1.0, false));
        cache.insert(view(0, 1), target(2.0, false));
        // A hit returns the stored tensor and makes (0, 0) the most recent.
        let hit = cache.get(view(0, 0)).expect("cached");
        assert_eq!(hit.rgb.into_data().to_vec::<f32>().unwrap(), vec![1.0; 18]);
        // A third entry drops the least recently used one, (0, 1).
        cache.insert(view(1, 0), target(3.0, false));
        assert!(cache.get(view(0, 1)).is_none());
        assert!(cache.get(view(0, 0)).is_some() && cache.get(view(1, 0)).is_some());
        let (bytes, entries, hits, misses) = cache.usage();
        assert_eq!((bytes, entries, hits, misses), (2 * entry, 2, 3, 2));
        // Re-inserting a cached view keeps the first entry and its bytes.
        cache.insert(view(0, 0), target(9.0, false));
        assert_eq!(cache.usage().0, 2 * entry);
        let kept = cache.get(view(0, 0)).unwrap().rgb.into_data().to_vec::<f32>().unwrap();
        assert_eq!(kept, vec![1.0; 18]);
        // An entry larger than the whole budget is not kept, and evicts nothing.
        let small = DeviceTargets::new(entry);
        small.insert(view(0, 0), target(1.0, true));
        assert_eq!(small.usage().1, 0);
        // A zero budget keeps nothing.
        let none = DeviceTargets::new(0);
        none.insert(view(0, 0), target(1.0, false));
        assert!(none.get(view(0, 0)).is_none() && none.usage().0 == 0);
    }
}
