//! ACA-GS post-hoc step after training (paper §4 "as a post-hoc step, we prune deactivated
//! Neural Gaussians and masked anchor features"; spec §13.4): anchors with no active slot are
//! removed, the offsets of gated slots and the F_adapt channels of masked anchors are zeroed so
//! the stored model holds nothing that cannot reach the image.
//!
//! Zeroing changes no render: a gated slot's opacity is multiplied by 0 and a masked anchor's
//! F_adapt by a forward-exact 0. Removing anchors without active slots does change the kNN
//! neighbour lists of the anchors around them (they averaged those anchors' features), so the
//! test metrics are computed after this step, on the model that is stored. After a full schedule
//! it finds no such anchor: training prunes them with the closed anchors up to its last step
//! (`refine::ClosedAnchorPruning`), so their neighbours had steps to adapt.

use super::anchor_state::{AnchorState, RowEdit};
use crate::model::anchors::{AnchorSet, Column, FeatureMasking};

/// What the post-hoc step removed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct PostHocReport {
    /// Anchors removed because every slot was gated.
    pub removed_anchors: usize,
    /// Anchors whose F_adapt was dropped.
    pub masked_anchors: usize,
}

/// Applies the post-hoc step; idempotent.
/// Anchors are removed from `set` and `state` together (the checkpoint written after it holds both).
pub fn prune_capacity(set: &mut AnchorSet, state: &mut AnchorState) -> PostHocReport {
    let d = set.dims;
    let n = set.len();
    let keep: Vec<usize> = (0..n).filter(|&a| set.cardinality(a) > 0).collect();
    let removed_anchors = n - keep.len();
    if removed_anchors > 0 {
        state.edit(set, RowEdit::Keep(&keep));
        set.rebuild_neighbors();
    }
    if set.slot_gates.iter().any(|&g| !g) {
        let mut offsets = set.host(Column::Offsets);
        for (j, &active) in set.slot_gates.iter().enumerate() {
            if !active {
                offsets[j * 3..(j + 1) * 3].fill(0.0);
            }
        }
        set.set_host(Column::Offsets, offsets);
    }
    let masked = set.adapt_masked();
    let masked_anchors = masked.iter().filter(|&&m| m).count();
    if let FeatureMasking::Adaptive { base, .. } = d.feature_masking
        && masked_anchors > 0
    {
        let c = d.feature_dim;
        let mut features = set.host(Column::Features);
        for (a, &m) in masked.iter().enumerate() {
            if m {
                features[a * c + base..(a + 1) * c].fill(0.0);
            }
        }
        set.set_host(Column::Features, features);
    }
    PostHocReport {
        removed_anchors,
        masked_anchors,
    }
}
