//! Training (the trainer itself lands with issue "GIFStream baseline"); for now its losses.

pub mod losses;
pub mod row_adam;
