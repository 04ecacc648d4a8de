//! AAC's slot gates g (ACA-GS, spec §12.1): one flag per Neural-Gaussian slot, [N · K], row
//! `a·K + k` for anchor a, slot k. A gated slot is never rasterized and its offset is not priced.
//!
//! The flags live on the host, where AAC's relocation, the codec and checkpoints read and change
//! them (at refinement steps only). Every training step needs them on the device, as a [N, K]
//! multiplier of the decoded opacity and as the rate term's offset mask; building that mask from
//! the flags on the host and uploading it each step was a host loop over the anchors and an
//! upload of N·3K floats per rate step. So the set keeps a device mirror, rebuilt only when the
//! flags change: the flags can only be changed through this type, which rebuilds it.

use std::ops::Deref;

use burn::tensor::{Device, Float, Tensor, TensorData};

use crate::device_io::upload;

#[derive(Clone, Debug)]
pub struct SlotGates {
    slots: usize,
    flags: Vec<bool>,
    active: usize,
    device: Device,
    /// [N, K] 1.0 where a slot is active, 0.0 where it is gated; None while every slot is
    /// active (then nothing is multiplied).
    mirror: Option<Tensor<2>>,
}

impl SlotGates {
    /// No anchors yet.
    pub fn empty(slots: usize, device: &Device) -> Self {
        Self::from_flags(Vec::new(), slots, device)
    }

    /// Gates from `flags` [N · `slots`].
    pub fn from_flags(flags: Vec<bool>, slots: usize, device: &Device) -> Self {
        assert!(slots > 0, "an anchor has at least one slot");
        assert_eq!(
            flags.len() % slots,
            0,
            "{} slot gates for {slots} slots per anchor",
            flags.len()
        );
        let mut gates = Self {
            slots,
            flags,
            active: 0,
            device: device.clone(),
            mirror: None,
        };
        gates.flags_changed();
        gates
    }

    /// K, the slots per anchor.
    pub fn slots(&self) -> usize {
        self.slots
    }

    /// The flags, [N · K].
    pub fn flags(&self) -> &[bool] {
        &self.flags
    }

    /// Anchor `anchor`'s K flags.
    pub fn of_anchor(&self, anchor: usize) -> &[bool] {
        &self.flags[anchor * self.slots..(anchor + 1) * self.slots]
    }

    /// Active slots over all anchors (counted when the flags change, not per call).
    pub fn active_count(&self) -> usize {
        self.active
    }

    /// [N, K] on the set's device, 1.0 on active slots and 0.0 on gated ones; None while every
    /// slot is active. No upload: the mirror of the current flags.
    pub fn mirror(&self) -> Option<&Tensor<2>> {
        self.mirror.as_ref()
    }

    /// The flags edited by `edit` on the host, then the mirror rebuilt once (AAC's relocation
    /// switches many slots in one step).
    pub fn edit<R>(&mut self, edit: impl FnOnce(&mut [bool]) -> R) -> R {
        let out = edit(&mut self.flags);
        self.flags_changed();
        out
    }

    /// Rows for `anchors` new anchors, their first `active` slots on.
    pub fn append_anchors(&mut self, anchors: usize, active: usize) {
        let k = self.slots;
        self.flags
            .extend((0..anchors).flat_map(|_| (0..k).map(move |s| s < active)));
        self.flags_changed();
    }

    /// Keeps the listed anchors' rows, in that order.
    pub fn keep_anchors(&mut self, keep: &[usize]) {
        self.flags = super::anchors::keep_row_values(&self.flags, keep, self.slots);
        self.flags_changed();
    }

    fn flags_changed(&mut self) {
        self.active = self.flags.iter().filter(|&&g| g).count();
        self.mirror = (self.active < self.flags.len()).then(|| {
            let values: Vec<f32> = self.flags.iter().map(|&g| f32::from(u8::from(g))).collect();
            let shape = [self.flags.len() / self.slots, self.slots];
            upload::<2, Float>(TensorData::new(values, shape), &self.device)
        });
    }
}

/// Read access as a flag slice (`gates[j]`, `gates.iter()`); writes go through [`SlotGates::edit`]
/// so that the device mirror follows.
impl Deref for SlotGates {
    type Target = [bool];

    fn deref(&self) -> &[bool] {
        &self.flags
    }
}

/// Equal flags (the mirror follows from them).
impl PartialEq for SlotGates {
    fn eq(&self, other: &Self) -> bool {
        self.slots == other.slots && self.flags == other.flags
    }
}

#[cfg(test)]
mod tests {
    #![allow(deprecated)] // Device::ndarray
    use super::*;

    fn mirror_values(gates: &SlotGates) -> Option<Vec<f32>> {
        gates
            .mirror()
            .map(|t| crate::model::anchors::host_values(t))
    }

    fn expected(flags: &[bool]) -> Option<Vec<f32>> {
        flags
            .iter()
            .any(|&g| !g)
            .then(|| flags.iter().map(|&g| if g { 1.0 } else { 0.0 }).collect())
    }

    /// After every kind of change the mirror holds the flags (None while all are on) and the
    /// count is theirs.
    #[test]
    fn the_mirror_and_the_count_follow_every_change() {
        let device = Device::ndarray();
        let mut gates = SlotGates::empty(3, &device);
        assert_eq!((gates.len(), gates.active_count()), (0, 0));
        assert!(gates.mirror().is_none());
        gates.append_anchors(2, 3);
        assert_eq!(gates.active_count(), 6);
        assert!(gates.mirror().is_none(), "all on: nothing to multiply");
        gates.append_anchors(2, 1);
        assert_eq!(
            gates.flags(),
            &[
                true, true, true, true, true, true, true, false, false, true, false, false
            ]
        );
        check(&gates);
        let switched = gates.edit(|flags| {
            flags[0] = false;
            flags[7] = true;
            2
        });
        assert_eq!(switched, 2);
        assert_eq!(gates.of_anchor(0), &[false, true, true]);
        assert_eq!(gates.of_anchor(2), &[true, true, false]);
        check(&gates);
        gates.keep_anchors(&[3, 0]);
        assert_eq!(gates.flags(), &[true, false, false, false, true, true]);
        check(&gates);
        gates.keep_anchors(&[]);
        check(&gates);
        assert!(gates.mirror().is_none());
        let restored = SlotGates::from_flags(vec![false, true, true, true], 2, &device);
        assert_eq!(restored.active_count(), 3);
        check(&restored);
    }

    fn check(g: &SlotGates) {
        assert_eq!(mirror_values(g), expected(g.flags()));
        assert_eq!(g.active_count(), g.iter().filter(|&&f| f).count());
        if let Some(m) = g.mirror() {
            assert_eq!(m.dims(), [g.len() / g.slots(), g.slots()]);
        }
    }

    #[test]
    #[should_panic(expected = "5 slot gates for 2 slots per anchor")]
    fn flags_must_fill_whole_anchors() {
        SlotGates::from_flags(vec![true; 5], 2, &Device::ndarray());
    }
}
