//! Training targets kept on the device: a view's target image (and its moving-pixel weights,
//! when `loss.moving_weight` is on) is uploaded at its first use and reused while it fits the
//! budget (`data.device_frame_cache_mib`), least recently used dropped first. A step then sends
//! its target only on a cache miss (issue 21: "target frames are cached on the device").
//!
//! On the CPU backend the device's memory is the host's, which the host frame cache
//! (`data.frame_cache_mib`) already holds the frames in: there the budget is 0 unless set, and
//! every step builds its target from the host frame (a copy within the same memory, no
//! transfer), rather than holding every frame twice.

use std::sync::Mutex;

use burn::tensor::Tensor;

use crate::byte_budget::ByteBudgetLru;
use crate::data::ViewId;
use crate::eval::motion_mask::MotionMaskConfig;

/// What a step compares its render with: [H, W, 3] colours and, when on, [H, W, 1] per-pixel
/// weights of the photometric term.
#[derive(Clone, Debug)]
pub struct DeviceTarget {
    pub rgb: Tensor<3>,
    pub pixel_weights: Option<Tensor<3>>,
    /// The settings the pixel weights were made with (`loss.moving_weight` and the motion mask's
    /// parameters): an entry made under other settings is stale.
    pub weighted_by: PixelWeighting,
}

/// What decides a target's pixel weights.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PixelWeighting {
    pub moving_weight: f32,
    pub mask: MotionMaskConfig,
}

impl DeviceTarget {
    /// Device memory the entry holds (f32 elements).
    pub fn bytes(&self) -> usize {
        let elements = |t: &Tensor<3>| t.dims().iter().product::<usize>();
        4 * (elements(&self.rgb) + self.pixel_weights.as_ref().map_or(0, elements))
    }
}

/// `data.device_frame_cache_mib` when unset, on a device whose memory is not the host's.
pub const DEFAULT_DEVICE_FRAME_CACHE_MIB: usize = 1024;

struct CacheState {
    entries: ByteBudgetLru<ViewId, DeviceTarget>,
    hits: u64,
    misses: u64,
}

/// Device-resident targets of the training views, bounded by a byte budget.
pub struct DeviceTargets {
    state: Mutex<CacheState>,
}

impl DeviceTargets {
    pub fn new(budget_bytes: usize) -> Self {
        Self {
            state: Mutex::new(CacheState {
                entries: ByteBudgetLru::new(budget_bytes),
                hits: 0,
                misses: 0,
            }),
        }
    }

    /// The cached target of `view` if it was made under `weighting` (a hit); a miss otherwise,
    /// a stale entry dropped.
    pub fn get(&self, view: ViewId, weighting: PixelWeighting) -> Option<DeviceTarget> {
        let mut state = self.state.lock().unwrap();
        let found = state.entries.get(&view).cloned();
        match found {
            Some(target) if target.weighted_by == weighting => {
                state.hits += 1;
                Some(target)
            }
            stale => {
                if stale.is_some() {
                    state.entries.remove(&view);
                }
                state.misses += 1;
                None
            }
        }
    }

    /// Keeps `target` as `view`'s (replacing an entry it had) when it fits the budget, dropping
    /// the least recently used entries to make room. An entry larger than the whole budget is
    /// not kept.
    pub fn insert(&self, view: ViewId, target: DeviceTarget) {
        let bytes = target.bytes();
        self.state.lock().unwrap().entries.insert(view, target, bytes);
    }

    /// (bytes held, entries held, hits, misses).
    pub fn usage(&self) -> (usize, usize, u64, u64) {
        let state = self.state.lock().unwrap();
        (state.entries.bytes(), state.entries.len(), state.hits, state.misses)
    }

    pub fn budget_bytes(&self) -> usize {
        self.state.lock().unwrap().entries.budget_bytes()
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

    fn weighting(moving_weight: f32) -> PixelWeighting {
        PixelWeighting {
            moving_weight,
            mask: MotionMaskConfig::default(),
        }
    }

    fn target(value: f32, weights: bool) -> DeviceTarget {
        let device = Device::ndarray();
        DeviceTarget {
            rgb: Tensor::full([2, 3, 3], value, &device),
            pixel_weights: weights.then(|| Tensor::full([2, 3, 1], value, &device)),
            weighted_by: weighting(if weights { 2.0 } else { 1.0 }),
        }
    }

    #[test]
    fn keeps_the_most_recent_targets_within_the_budget() {
        let entry = target(0.0, false).bytes();
        assert_eq!(entry, 4 * 18);
        assert_eq!(target(0.0, true).bytes(), 4 * 24);
        let cache = DeviceTargets::new(2 * entry);
        assert!(cache.get(view(0, 0), weighting(1.0)).is_none());
        cache.insert(view(0, 0), target(1.0, false));
        cache.insert(view(0, 1), target(2.0, false));
        // A hit returns the stored tensor and makes (0, 0) the most recent.
        let hit = cache.get(view(0, 0), weighting(1.0)).expect("cached");
        assert_eq!(hit.rgb.into_data().to_vec::<f32>().unwrap(), vec![1.0; 18]);
        // A third entry drops the least recently used one, (0, 1).
        cache.insert(view(1, 0), target(3.0, false));
        assert!(cache.get(view(0, 1), weighting(1.0)).is_none());
        assert!(
            cache.get(view(0, 0), weighting(1.0)).is_some()
                && cache.get(view(1, 0), weighting(1.0)).is_some()
        );
        let (bytes, entries, hits, misses) = cache.usage();
        assert_eq!((bytes, entries, hits, misses), (2 * entry, 2, 3, 2));
        // Re-inserting a cached view replaces its entry.
        cache.insert(view(0, 0), target(9.0, false));
        assert_eq!(cache.usage().0, 2 * entry);
        let kept = cache.get(view(0, 0), weighting(1.0)).unwrap().rgb.into_data();
        let kept = kept.to_vec::<f32>().unwrap();
        assert_eq!(kept, vec![9.0; 18]);
        // An entry made under other pixel weights is stale: a miss, and dropped.
        assert!(cache.get(view(0, 0), weighting(1.0)).is_some());
        let (_, _, hits, misses) = cache.usage();
        assert!(cache.get(view(0, 0), weighting(3.0)).is_none());
        assert_eq!(cache.usage(), (entry, 1, hits, misses + 1));
        // An entry larger than the whole budget is not kept, and evicts nothing.
        let small = DeviceTargets::new(entry);
        small.insert(view(0, 0), target(1.0, true));
        assert_eq!(small.usage().1, 0);
        // A zero budget keeps nothing.
        let none = DeviceTargets::new(0);
        none.insert(view(0, 0), target(1.0, false));
        assert!(none.get(view(0, 0), weighting(1.0)).is_none() && none.usage().0 == 0);
    }
}
