//! Rendering: the camera, relighting of the baked transfer under an environment, and the
//! empty-space-skipping ray march that turns both into an image.

pub mod camera;
pub mod march;
pub mod relight;

pub use camera::Camera;
pub use march::{render, Frame, MarchSettings, MarchStats, Scene};
pub use relight::{relight, Radiance};
