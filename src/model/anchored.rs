//! The anchored dynamic model: the anchor set and the shared decoders, and rendering a camera at
//! a frame with them (the path evaluation, `render` and FPS measurements take).

use anyhow::Result;
use burn::tensor::Tensor;

use super::anchors::{AnchorSet, AnchorTensors};
use super::culling::FirstDrawnFrames;
use super::decoders::Decoders;
use super::view::{
    AnchorCulling, DecodedView, StepCulling, ViewTime, cull_anchors, cull_and_decode,
    decode_all_masked, decode_view,
};
use crate::raster::{IntersectionCapacity, RasterCamera, RasterOutput, rasterize_with};

/// Black, as GIFStream trains and evaluates.
pub const BACKGROUND: [f32; 3] = [0.0; 3];

#[derive(Clone, Debug)]
pub struct AnchoredModel {
    pub anchors: AnchorSet,
    pub decoders: Decoders,
    /// How anchors are culled before decoding (a property of the trained model: a model trained
    /// with motion-aware culling renders its moved anchors only with it).
    pub culling: AnchorCulling,
}

/// A rendered view.
pub struct RenderedView {
    pub raster: RasterOutput,
    pub decoded: DecodedView,
}

impl RenderedView {
    /// [H, W, 3] clamped to [0, 1] on the host (evaluation clamps renders, spec §11).
    pub fn image_host(&self) -> Vec<f32> {
        super::anchors::host_values(&self.raster.image.clone().clamp(0.0, 1.0))
    }
}

/// What a forward pass decodes with.
#[derive(Clone, Copy)]
pub enum ForwardValues<'a> {
    /// The model's own values, untracked (evaluation, `render`).
    Model,
    /// Tracked copies (training): the anchors' as the step simulates their quantisation, and the
    /// decoders'. Culled on the device on those values, or on the host on the model's plain
    /// values (`culling`).
    Tracked {
        anchors: &'a AnchorTensors,
        decoders: &'a Decoders,
        /// Where the step culls.
        culling: StepCulling,
        /// The frames before which an anchor is not drawn (`None`: every anchor at every frame).
        first_frames: Option<&'a FirstDrawnFrames>,
    },
}

impl AnchoredModel {
    /// Culls, decodes and rasterizes `camera` at `when`: the one forward pass of training and
    /// evaluation.
    pub fn forward(
        &self,
        camera: &RasterCamera,
        when: ViewTime,
        values: ForwardValues,
    ) -> Result<RenderedView> {
        self.forward_with(camera, when, values, IntersectionCapacity::Exact)
    }

    /// [`Self::forward`] with the rasterizer's intersection buffers sized by `capacity` (the
    /// caller then checks [`RasterOutput::overflowed`] before using the render).
    pub fn forward_with(
        &self,
        camera: &RasterCamera,
        when: ViewTime,
        values: ForwardValues,
        capacity: IntersectionCapacity,
    ) -> Result<RenderedView> {
        let plain = self.anchors.untracked();
        let decoded = match values {
            ForwardValues::Model => cull_and_decode(
                &self.anchors,
                &plain,
                &self.decoders,
                camera,
                when,
                self.culling,
            ),
            // Every row decoded once, the culled ones masked on the device.
            ForwardValues::Tracked {
                anchors,
                decoders,
                culling,
                first_frames,
            } if !self.anchors.is_empty() && culling.on_device(self.culling) => decode_all_masked(
                &self.anchors,
                anchors,
                decoders,
                camera,
                when,
                self.culling,
                first_frames,
            ),
            // Culling on the plain values, decoding the tracked ones (under deformed culling
            // this decodes the motion twice, which the fused path above avoids for plain values).
            ForwardValues::Tracked {
                anchors,
                decoders,
                first_frames,
                ..
            } => {
                let mut visible = cull_anchors(
                    &self.anchors,
                    &plain,
                    &self.decoders,
                    camera,
                    when,
                    self.culling,
                );
                if let Some(first) = first_frames {
                    visible.retain(|&a| first.draws(a, when.frame));
                }
                decode_view(&self.anchors, anchors, decoders, visible, when)
            }
        };
        let raster = rasterize_with(&decoded.gaussians, camera, BACKGROUND, capacity)?;
        Ok(RenderedView { raster, decoded })
    }

    /// Culls, decodes and rasterizes without tracking gradients.
    pub fn render(&self, camera: &RasterCamera, when: ViewTime) -> Result<RenderedView> {
        self.forward(camera, when, ForwardValues::Model)
    }

    /// Gaussians with opacity > 0 in a decode (the ones the rasterizer may draw).
    pub fn spawned(view: &DecodedView) -> usize {
        let gates: Tensor<1> = view.gaussians.gates.clone();
        super::anchors::host_values(&gates.sum())[0].round() as usize
    }
}
