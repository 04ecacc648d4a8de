//! acags: a trainer and codec for compact dynamic radiance fields (ACA-GS on GIFStream).
//!
//! The rasterizer lives in the `acags-kernels` crate (re-exported as [`raster`]); this crate holds
//! the command-line tool and everything around it.

pub use acags_kernels as raster;

pub mod bench;
pub mod byte_budget;
pub mod codec;
pub mod compute_backend;
pub mod config;
pub mod data;
pub mod device_io;
pub mod eval;
pub mod experiments;
pub mod export;
pub mod host_math;
pub mod io;
pub mod model;
pub mod panics;
pub mod run;
pub mod train;
pub mod view;
