//! One frame of a trained model as plain neural Gaussians: every anchor decoded (no camera
//! culling: an export is seen from anywhere), then the slots a renderer would never draw dropped.

use crate::model::anchored::AnchoredModel;
use crate::model::anchors::host_values;
use crate::model::view::{ViewTime, decode_view};
use crate::raster::conventions::ALPHA_MIN;

/// The drawable Gaussians of one frame, activated (linear scales, opacities in (0, 1]).
#[derive(Clone, Debug, Default)]
pub struct FrameGaussians {
    /// [N, 3]
    pub means: Vec<f32>,
    /// [N, 4] unit (w, x, y, z).
    pub quats: Vec<f32>,
    /// [N, 3]
    pub scales: Vec<f32>,
    /// [N] opacity after every gate (pruning, AAC slot gates).
    pub opacities: Vec<f32>,
    /// [N, 3] RGB in [0, 1].
    pub colours: Vec<f32>,
    /// Slots decoded (anchors × Gaussians per anchor) before dropping.
    pub slots: usize,
}

impl FrameGaussians {
    pub fn len(&self) -> usize {
        self.opacities.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// The smallest scale written: a slot whose scale underflowed to 0 still renders as the
/// rasterizer's 0.3 px² blur, and a log-scale of −inf would not survive a PLY round trip.
const MIN_SCALE: f32 = 1e-12;

/// Decodes every anchor of `model` at `when` and keeps the slots that any renderer following the
/// 3DGS conventions draws: not gated off (AAC slot gates, pruning gate: opacity exactly 0) and
/// opacity ≥ 1/255 (below it a Gaussian's alpha is under 1/255 at every pixel, which gsplat, the
/// Inria renderer and ours all skip), with finite parameters.
pub fn decode_frame(model: &AnchoredModel, when: ViewTime) -> FrameGaussians {
    let set = &model.anchors;
    let mut out = FrameGaussians::default();
    if set.is_empty() {
        return out;
    }
    let all: Vec<u32> = (0..set.len() as u32).collect();
    let view = decode_view(set, &set.untracked(), &model.decoders, all, when);
    let g = &view.gaussians;
    let (means, quats, scales) = (
        host_values(&g.means),
        host_values(&g.quats),
        host_values(&g.scales),
    );
    let (opacities, gates, colours) = (
        host_values(&g.opacities),
        host_values(&g.gates),
        host_values(&g.colors),
    );
    out.slots = opacities.len();
    for i in 0..out.slots {
        let opacity = opacities[i] * gates[i];
        let q = &quats[4 * i..4 * i + 4];
        let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt();
        let finite = means[3 * i..3 * i + 3]
            .iter()
            .chain(&scales[3 * i..3 * i + 3])
            .chain(&colours[3 * i..3 * i + 3])
            .all(|v| v.is_finite());
        if !(opacity >= ALPHA_MIN && norm > 0.0 && norm.is_finite() && finite) {
            continue;
        }
        out.means.extend_from_slice(&means[3 * i..3 * i + 3]);
        out.quats.extend(q.iter().map(|v| v / norm));
        out.scales
            .extend(scales[3 * i..3 * i + 3].iter().map(|s| s.max(MIN_SCALE)));
        out.opacities.push(opacity.min(1.0));
        out.colours.extend_from_slice(&colours[3 * i..3 * i + 3]);
    }
    out
}
