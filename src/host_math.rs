//! Scalar functions the host side of every layer shares (model, codec, training, file formats),
//! so each is written once: the tensor versions are `acags_kernels::activation` (Burn's values).

/// σ(x) = 1 / (1 + e^(−x)).
pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// The inverse of [`sigmoid`], ln(p / (1 − p)); ±∞ at p = 1 or 0 (callers clamp where they
/// need a finite logit).
pub fn logit(p: f32) -> f32 {
    (p / (1.0 - p)).ln()
}
