//! Evaluation: image metrics (PSNR, SSIM, LPIPS; full image and moving / static pixels), test
//! renders and timing.

pub mod capacity_maps;
pub mod config;
pub mod evaluate;
pub mod image_pair;
pub mod lpips;
pub mod metrics;
pub mod motion_mask;
