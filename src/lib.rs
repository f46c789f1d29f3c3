//! vscatter: read sparse OpenVDB fog volumes, bake a light-independent spherical-harmonic transfer
//! with multiple scattering, and relight it with any HDR environment.
//!
//! The modules follow the data: [`volume`] (the VDB reader and the sparse density), [`light`]
//! (environments, SH, the lighting of a render), [`transfer`] (the bake and its cache),
//! [`render`] (camera, relight, march), [`pathtrace`] (the ground truth), and [`scene`], the
//! pipeline the commands call. [`io`] and [`math`] serve them all.

pub mod batch;
pub mod compare;
pub mod error;
pub mod io;
pub mod light;
mod math;
mod pathtrace;
pub mod render;
pub mod scene;
pub mod sequence;
pub mod transfer;
pub mod volume;

pub use error::{Error, Result};
