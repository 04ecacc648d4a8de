//! A least-recently-used map bounded by the bytes its entries hold: the host frame cache
//! (`data::frames::FrameCache`) and the training targets on the device
//! (`train::device_targets::DeviceTargets`).

use std::hash::Hash;

use lru::LruCache;

pub struct ByteBudgetLru<K: Hash + Eq, V> {
    budget_bytes: usize,
    /// Each value with the bytes it was inserted as.
    entries: LruCache<K, (V, usize)>,
    bytes: usize,
}

impl<K: Hash + Eq, V> ByteBudgetLru<K, V> {
    pub fn new(budget_bytes: usize) -> Self {
        Self {
            budget_bytes,
            entries: LruCache::unbounded(),
            bytes: 0,
        }
    }

    /// The value of `key`, made the most recently used.
    pub fn get(&mut self, key: &K) -> Option<&V> {
        self.entries.get(key).map(|(value, _)| value)
    }

    /// Keeps `value` (holding `bytes`) as `key`'s, replacing what the key had, and drops the
    /// least recently used entries until the budget holds. A value larger than the whole budget
    /// is not kept (and evicts nothing).
    pub fn insert(&mut self, key: K, value: V, bytes: usize) {
        self.remove(&key);
        if bytes > self.budget_bytes {
            return;
        }
        self.bytes += bytes;
        self.entries.put(key, (value, bytes));
        while self.bytes > self.budget_bytes {
            let Some((_, (_, old))) = self.entries.pop_lru() else {
                break;
            };
            self.bytes -= old;
        }
    }

    /// Drops `key`'s entry, if any.
    pub fn remove(&mut self, key: &K) {
        if let Some((_, bytes)) = self.entries.pop(key) {
            self.bytes -= bytes;
        }
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.bytes
    }

    /// Entries held.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    pub fn budget_bytes(&self) -> usize {
        self.budget_bytes
    }
}
