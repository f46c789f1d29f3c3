//! Volumes: the OpenVDB reader, the sparse grid it decodes into, and the density field every ray
//! samples (the grid with its empty-space and sampling accelerators).

pub(crate) mod bricks;
pub(crate) mod dda;
mod dense_box;
mod field;
pub mod grid;
pub(crate) mod keys;
pub(crate) mod mip;
mod sampler;
pub mod shadow;
pub(crate) mod transmittance;
pub mod vdb;
pub mod visibility;

pub use field::DensityField;
pub use grid::{SparseGrid, TileLevel, Transform};

use std::path::Path;

use crate::error::{Error, Result};

/// A density chosen from a VDB file and checked for rendering.
pub struct Density {
    pub grid: SparseGrid,
    pub name: String,
}

/// Reads the density grid of `path` (`--grid NAME`, else `density`, else the first scalar grid)
/// and checks its values: non-finite values are refused; a level set (signed distances, negative
/// inside) is refused with the conversion that fixes it; small negative values — the noise a fluid
/// solver leaves — are clamped to zero with a warning.
pub fn load_density(path: &Path, grid: Option<&str>) -> Result<Density> {
    let vdb = vdb::VdbFile::open(path)?;
    let index = vdb.choose_grid(grid)?;
    let info = &vdb.grids[index];
    if info.class == "level set" {
        return Err(Error::format(
            path,
            format!(
                "grid {:?} is a level set (signed distance), not a density; convert it first, e.g. `vdb_tool -read IN -ls2fog -write OUT`",
                info.name
            ),
        ));
    }
    let mut grid = vdb.read_grid(index)?;
    let mut negative = 0u64;
    let mut bad = 0u64;
    for leaf in grid.leaves_mut() {
        for v in leaf.values.f32_mut().into_iter().flatten() {
            if !v.is_finite() {
                bad += 1;
            } else if *v < 0.0 {
                negative += 1;
                *v = 0.0;
            }
        }
        leaf.max = leaf.max.max(0.0);
    }
    for level in TileLevel::ALL {
        for (_, v) in grid.tiles(level) {
            if !v.is_finite() {
                bad += 1;
            } else if v < 0.0 {
                negative += 1;
            }
        }
    }
    if bad > 0 || !grid.background.is_finite() {
        return Err(Error::format(
            path,
            format!("grid {:?} holds {bad} NaN or infinite values", info.name),
        ));
    }
    if negative > 0 {
        grid.clamp_negative_tiles();
        eprintln!(
            "vscatter: warning: {}: {negative} negative density values in grid {:?} clamped to 0",
            path.display(),
            info.name
        );
    }
    Ok(Density {
        grid,
        name: info.name.clone(),
    })
}
