//! Small numeric pieces the volume, the bake and the renderers share: rays and box clipping, fast
//! floors.

pub mod floor;
pub mod ray;
