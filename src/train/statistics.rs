//! The per-view statistics densification and AAC read (spec §8.1, §12.2), gathered on the
//! device: a training step adds its view's contributions with scatter-adds into device tensors
//! and reads nothing back. The host copy in [`AnchorState`](super::anchor_state::AnchorState) is
//! brought up to date, in one read-back, only when something reads it: a refiner that acts, a
//! row edit, a checkpoint ([`AnchorState::settle`](super::anchor_state::AnchorState::settle)).
//! Before, every step in the densification window read the Gaussians' gates, radii, screen
//! gradients and opacities back (four synchronisations) to add them up on the host.
//!
//! The device tensors hold the full values (the host copy is moved into them when a window of
//! gathering starts), not increments since the last read: every element then receives the same
//! f32 additions in the same order as under the host functions these replace
//! ([`update_stats`](super::densify::update_stats) and
//! [`accumulate_importance`](super::adaptive_cardinality::accumulate_importance), which stay as
//! the reference the tests compare with), so training on the CPU is unchanged to the bit. On a
//! GPU the scatter-add's atomics add a repeated row's values in their own order (as every
//! atomic accumulation of the backward does), so the last bits may vary from run to run.

use burn::tensor::{Device, Int, Tensor, TensorData, s};

use super::anchor_state::AnchorStats;
use crate::device_io::{read_back, upload};
use crate::model::anchors::AnchorDims;
use crate::raster::gather::add_rows_at;

/// One training view's contribution to the densification statistics, on the device.
pub struct DensifyView {
    /// [M] the decoded anchors' rows (Gaussian row i·K + k belongs to anchor `visible[i]`).
    pub visible: Tensor<1, Int>,
    /// [M] 1.0 where the row's anchor was visible, 0.0 where a device-culled decode masked it
    /// ([`VisibleRows::weights`](crate::model::view::VisibleRows::weights)): what a row adds to
    /// the anchor's view count. A masked row's opacity is 0, so it adds nothing else.
    pub seen: Tensor<1>,
    /// The view's GOP frame.
    pub frame: usize,
    /// [M, K] opacity after the pruning gate and the slot gates.
    pub opacity: Tensor<2>,
    /// [M·K] 1 where a Gaussian was spawned (the rasterizer's gates).
    pub gates: Tensor<1>,
    /// [M·K, 2] screen half extents, (0, 0) where culled.
    pub radii: Tensor<2, Int>,
    /// [M·K, 2] ∂L/∂μ2D in pixels; `None` when the loss did not reach the screen means.
    pub grad2d: Option<Tensor<2>>,
    /// Half the image's width and height: gsplat's normalisation of the screen gradient.
    pub half_size: [f32; 2],
}

/// The densification statistics while they are gathered on the device (flat, row-major as
/// [`AnchorStats`]).
#[derive(Clone, Debug)]
struct DensifyTensors {
    offset_grad2d: Tensor<1>,
    offset_visible_count: Tensor<1>,
    opacity_accum: Tensor<1>,
    anchor_visible_count: Tensor<1>,
}

/// AAC's importance window while it is gathered on the device.
#[derive(Clone, Debug)]
struct ImportanceTensors {
    importance: Tensor<1>,
    visits: Tensor<1>,
}

/// Statistics gathered on the device since the host copy was last brought up to date; each group
/// is `None` while the host copy is current.
#[derive(Clone, Debug, Default)]
pub struct DeviceStatistics {
    densify: Option<DensifyTensors>,
    importance: Option<ImportanceTensors>,
}

/// Moves a host vector onto the device (the host copy is left empty until settled: a read of it
/// in between fails on its length instead of returning stale values).
fn take_up(values: &mut Vec<f32>, device: &Device) -> Tensor<1> {
    let values = std::mem::take(values);
    let n = values.len();
    upload::<1, burn::tensor::Float>(TensorData::new(values, [n]), device)
}

/// `into[at[i]] += values[i]`: `select_assign(.., Add)`'s additions in index order, done in place
/// on ndarray (Burn's ndarray `select_assign` walks the index with a view per element, which
/// cost 10-24 ms per step over these tables); on a GPU one atomic per element (Burn's CubeCL
/// `select_assign` walks the index in a single unit).
fn add_at(into: Tensor<1>, at: Tensor<1, Int>, values: Tensor<1>) -> Tensor<1> {
    let (n, m) = (into.dims()[0], values.dims()[0]);
    add_rows_at(into.reshape([n, 1]), at, values.reshape([m, 1])).reshape([n])
}

/// [M·K] row `row_from_slot(visible[i]·K + k)` for every slot k of every visible anchor.
fn slot_rows(visible: &Tensor<1, Int>, slots: usize) -> Tensor<1, Int> {
    let m = visible.dims()[0];
    let first = visible.clone().mul_scalar(slots as i64).reshape([m, 1]);
    let k = Tensor::<1, Int>::arange(0..slots as i64, &visible.device()).reshape([1, slots]);
    (first + k).reshape([m * slots])
}

impl DeviceStatistics {
    /// Whether nothing is pending: the host copy is current.
    pub fn is_settled(&self) -> bool {
        self.densify.is_none() && self.importance.is_none()
    }

    /// Adds one view's densification statistics (as [`update_stats`](super::densify::update_stats)).
    pub fn gather_densify(
        &mut self,
        host: &mut AnchorStats,
        dims: &AnchorDims,
        anchors: usize,
        view: DensifyView,
    ) {
        let (k, t) = (dims.slots, dims.frames);
        assert!(view.frame < t, "frame {} outside the GOP", view.frame);
        let m = view.visible.dims()[0];
        assert_eq!(view.opacity.dims(), [m, k], "opacity is [M, K]");
        let device = view.visible.device();
        let mut acc = self.densify.take().unwrap_or_else(|| DensifyTensors {
            offset_grad2d: take_up(&mut host.offset_grad2d, &device),
            offset_visible_count: take_up(&mut host.offset_visible_count, &device),
            opacity_accum: take_up(&mut host.opacity_accum, &device),
            anchor_visible_count: take_up(&mut host.anchor_visible_count, &device),
        });
        assert_eq!(
            acc.opacity_accum.dims()[0],
            anchors * t,
            "statistics of another anchor set"
        );
        let frame = view.frame as i64;
        let anchor_rows = view.visible.clone().mul_scalar(t as i64).add_scalar(frame);
        // Σ_k max(α, 0), slot after slot: the host loop's order of additions.
        let opacity = view.opacity.detach().clamp_min(0.0);
        let opacity_sum = (1..k).fold(opacity.clone().slice(s![.., 0..1]), |sum, slot| {
            sum + opacity.clone().slice(s![.., slot..slot + 1])
        });
        acc.opacity_accum = add_at(
            acc.opacity_accum,
            anchor_rows.clone(),
            opacity_sum.reshape([m]),
        );
        assert_eq!(view.seen.dims(), [m], "one weight per row");
        acc.anchor_visible_count = add_at(acc.anchor_visible_count, anchor_rows.clone(), view.seen);

        // A slot counts where it was spawned and is on screen; adding 0 elsewhere leaves the
        // value as the host loop, which skips it, does.
        let n = m * k;
        let radii = view.radii;
        let on_screen = (radii.clone().slice(s![.., 0..1]).greater_elem(0))
            .bool_or(radii.slice(s![.., 1..2]).greater_elem(0))
            .reshape([n]);
        let counted = view.gates.detach().greater_elem(0.0).bool_and(on_screen);
        let rows = slot_rows(&view.visible, k)
            .mul_scalar(t as i64)
            .add_scalar(frame);
        acc.offset_visible_count = add_at(
            acc.offset_visible_count,
            rows.clone(),
            counted.clone().float(),
        );
        if let Some(grad) = view.grad2d {
            let [w, h] = view.half_size;
            let gx = grad.clone().slice(s![.., 0..1]).mul_scalar(w);
            let gy = grad.slice(s![.., 1..2]).mul_scalar(h);
            let norm = (gx.clone() * gx + gy.clone() * gy).sqrt().reshape([n]);
            acc.offset_grad2d = add_at(
                acc.offset_grad2d,
                rows,
                norm.mask_fill(counted.bool_not(), 0.0),
            );
        }
        self.densify = Some(acc);
    }

    /// Adds one view's slot opacities before the slot gates to AAC's importance window (as
    /// [`accumulate_importance`](super::adaptive_cardinality::accumulate_importance)).
    pub fn gather_importance(
        &mut self,
        host_importance: &mut Vec<f32>,
        host_visits: &mut Vec<f32>,
        dims: &AnchorDims,
        anchors: usize,
        visible: Tensor<1, Int>,
        seen: Tensor<1>,
        slot_opacity: Tensor<2>,
    ) {
        let k = dims.slots;
        let m = visible.dims()[0];
        assert_eq!(slot_opacity.dims(), [m, k], "opacity is [M, K]");
        assert_eq!(seen.dims(), [m], "one weight per row");
        let device = visible.device();
        let mut acc = self.importance.take().unwrap_or_else(|| ImportanceTensors {
            importance: take_up(host_importance, &device),
            visits: take_up(host_visits, &device),
        });
        assert_eq!(
            acc.visits.dims()[0],
            anchors,
            "importance of another anchor set"
        );
        acc.importance = add_at(
            acc.importance,
            slot_rows(&visible, k),
            slot_opacity.detach().clamp_min(0.0).reshape([m * k]),
        );
        acc.visits = add_at(acc.visits, visible, seen);
        self.importance = Some(acc);
    }

    /// Forgets the importance gathered on the device (the window restarts from zero).
    pub fn drop_importance(&mut self) {
        self.importance = None;
    }

    /// Writes what is pending back into the host copy, in one read-back.
    pub fn settle(
        &mut self,
        host: &mut AnchorStats,
        host_importance: &mut Vec<f32>,
        host_visits: &mut Vec<f32>,
    ) {
        let densify = self.densify.take();
        let importance = self.importance.take();
        let mut pending: Vec<(Tensor<1>, &mut Vec<f32>)> = Vec::new();
        if let Some(d) = densify {
            pending.push((d.offset_grad2d, &mut host.offset_grad2d));
            pending.push((d.offset_visible_count, &mut host.offset_visible_count));
            pending.push((d.opacity_accum, &mut host.opacity_accum));
            pending.push((d.anchor_visible_count, &mut host.anchor_visible_count));
        }
        if let Some(i) = importance {
            pending.push((i.importance, host_importance));
            pending.push((i.visits, host_visits));
        }
        if pending.is_empty() {
            return;
        }
        let lengths: Vec<usize> = pending.iter().map(|(t, _)| t.dims()[0]).collect();
        let (tensors, hosts): (Vec<_>, Vec<_>) = pending.into_iter().unzip();
        let all = read_back(Tensor::cat(tensors, 0))
            .convert::<f32>()
            .try_into_vec::<f32>()
            .expect("float statistics");
        let mut rest = all.as_slice();
        for (len, host) in lengths.into_iter().zip(hosts) {
            let (values, tail) = rest.split_at(len);
            *host = values.to_vec();
            rest = tail;
        }
    }
}
