//! Volumes: the OpenVDB reader and the sparse grid it decodes into.

pub mod dda;
pub mod sampler;
pub mod sparse;
pub mod transmittance;
pub mod vdb;

pub use sparse::{SparseGrid, TileLevel, Transform};
