//! Training views in a seeded order: every epoch is a fresh permutation (sampling without
//! replacement), reproducible from (seed, epoch, position) so a resumed run continues exactly.

use rand::{SeedableRng, rngs::StdRng, seq::SliceRandom};
use serde::{Deserialize, Serialize};

use super::scene::ViewId;

/// Where a sampler is: enough to restore it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct SamplerState {
    pub epoch: u64,
    pub position: usize,
}

pub struct ViewSampler {
    views: Vec<ViewId>,
    seed: u64,
    state: SamplerState,
    order: Vec<usize>,
}

impl ViewSampler {
    pub fn new(views: Vec<ViewId>, seed: u64) -> Self {
        assert!(!views.is_empty(), "a view sampler needs at least one view");
        let mut sampler = Self {
            order: Vec::new(),
            views,
            seed,
            state: SamplerState {
                epoch: 0,
                position: 0,
            },
        };
        sampler.shuffle();
        sampler
    }

    fn shuffle(&mut self) {
        // One independent stream per epoch: restoring needs only (seed, epoch).
        let mut rng =
            StdRng::seed_from_u64(self.seed ^ self.state.epoch.wrapping_mul(0x9E37_79B9_7F4A_7C15));
        self.order = (0..self.views.len()).collect();
        self.order.shuffle(&mut rng);
    }

    pub fn next_view(&mut self) -> ViewId {
        if self.state.position == self.order.len() {
            self.state = SamplerState {
                epoch: self.state.epoch + 1,
                position: 0,
            };
            self.shuffle();
        }
        let view = self.views[self.order[self.state.position]];
        self.state.position += 1;
        view
    }

    pub fn state(&self) -> SamplerState {
        self.state
    }

    pub fn restore(&mut self, state: SamplerState) {
        assert!(
            state.position <= self.views.len(),
            "sampler position beyond the epoch"
        );
        self.state = state;
        self.shuffle();
    }

    pub fn epoch_len(&self) -> usize {
        self.views.len()
    }
}
