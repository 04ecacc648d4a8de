//! `[eval]`: how test images are scored (the motion mask and the perceptual metric). Training
//! never reads it, so it may differ between runs that are compared.

use serde::{Deserialize, Serialize};

use super::lpips::LpipsInput;
use super::motion_mask::MotionMaskConfig;

/// When LPIPS-VGG is computed (LPIPS-Alex always is: its weights ship with acags).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum VggLpips {
    /// When its weights are present (`bash scripts/fetch_lpips_vgg.sh`); a note otherwise.
    #[default]
    Auto,
    /// Always: missing weights are an error.
    On,
    /// Never (VGG costs ~10× AlexNet on a CPU).
    Off,
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EvalConfig {
    /// Max-channel departure from the temporal median that marks a pixel as moving, in 8-bit
    /// levels (see [`super::motion_mask`]).
    pub motion_threshold: f32,
    /// Dilation radius of the motion mask in pixels.
    pub motion_dilation: usize,
    /// LPIPS input convention: `normalized` ([0, 1] mapped to [−1, 1], the correct value and the
    /// default) or `unscaled` (GIFStream's evaluator, for comparisons with its numbers).
    pub lpips_input: LpipsInput,
    pub lpips_vgg: VggLpips,
}

impl Default for EvalConfig {
    fn default() -> Self {
        let mask = MotionMaskConfig::default();
        Self {
            motion_threshold: mask.motion_threshold,
            motion_dilation: mask.motion_dilation,
            lpips_input: LpipsInput::default(),
            lpips_vgg: VggLpips::default(),
        }
    }
}

impl EvalConfig {
    pub fn motion_mask(&self) -> MotionMaskConfig {
        MotionMaskConfig {
            motion_threshold: self.motion_threshold,
            motion_dilation: self.motion_dilation,
        }
    }
}
