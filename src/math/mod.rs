//! Small numeric pieces the volume, the bake and the renderers share: rays and box clipping, fast
//! floors and inverse trigonometry, stateless hashes, a Krylov solver.

pub mod arc;
pub mod floor;
pub mod hash;
pub mod krylov;
pub mod ray;
pub mod sphere;
