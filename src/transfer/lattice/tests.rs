//! Tests of `lattice`.

use super::*;
use glam::Vec3;

use crate::volume::grid::block_box;

fn unit(d: IVec3) -> Vec3 {
    d.as_vec3().normalize()
}

#[test]
fn lattice_weights_are_voronoi_shares() {
    // Re-derive the shares by a (cos θ, φ) midpoint quadrature, nearest direction wins.
    for kind in [
        LatticeKind::Faces,
        LatticeKind::FacesEdges,
        LatticeKind::All,
        LatticeKind::FacesSkew,
    ] {
        let dirs = Directions::new(kind);
        let count = kind.directions();
        let units: Vec<Vec3> = dirs.offsets.iter().map(|d| unit(*d)).collect();
        let (nu, nphi) = (600, 1200);
        let mut share = vec![0f64; count];
        for i in 0..nu {
            let z = -1.0 + (i as f32 + 0.5) * 2.0 / nu as f32;
            let r = (1.0 - z * z).sqrt();
            for k in 0..nphi {
                let p = (k as f32 + 0.5) * std::f32::consts::TAU / nphi as f32;
                let w = Vec3::new(r * p.cos(), r * p.sin(), z);
                let best = (0..count)
                    .max_by(|&a, &b| units[a].dot(w).total_cmp(&units[b].dot(w)))
                    .unwrap();
                share[best] += 1.0 / (nu * nphi) as f64;
            }
        }
        for (s, w) in share.iter().zip(&dirs.weights) {
            assert!((s - *w as f64).abs() < 2e-4, "{count}: {s} vs {w}");
        }
        let sum: f64 = dirs.weights.iter().map(|w| *w as f64).sum();
        assert!((sum - 1.0).abs() < 1e-6);
    }
}

#[test]
fn half_range_moment_is_near_a_quarter() {
    // Σ_{d·n>0} w·(d·n) is ¼ for the true sphere: how well a flat surface's in- and out-flow
    // are represented ([docs/model.md](../../docs/model.md)). 26 directions: 0.2317; 6 directions: 1/6.
    let moment = |kind| {
        let dirs = Directions::new(kind);
        dirs.offsets
            .iter()
            .zip(&dirs.weights)
            .map(|(d, w)| w * unit(*d).z.max(0.0))
            .sum::<f32>()
    };
    assert!((moment(LatticeKind::All) - 0.2317).abs() < 1e-3);
    // The suns' set: no direction but the faces in an axis plane.
    assert!((moment(LatticeKind::FacesSkew) - 0.2472).abs() < 1e-3);
    assert!((moment(LatticeKind::FacesEdges) - 0.2163).abs() < 1e-3);
    assert!((moment(LatticeKind::Faces) - 1.0 / 6.0).abs() < 1e-6);
}

#[test]
fn inflow_is_the_environment_seen_from_each_line() {
    // Summed over the lines (times ℓ_j, fluence per flux), an environment of radiance 1 from
    // every direction: ∫ y_i dω, √(4π) for the DC term and 0 for the others. Each line's
    // share peaks where its light comes from, −d_j.
    let (bands, coeffs) = (3, 9);
    let dirs = Directions::new(LatticeKind::All);
    // Cells of edge h = 2: links 2, 2√2, 2√3 long.
    let lengths: Vec<f32> = dirs
        .offsets
        .iter()
        .map(|d| 2.0 * d.as_vec3().length())
        .collect();
    let flux = inflow(&dirs, &lengths, bands);
    for c in 0..coeffs {
        let total: f32 = (0..dirs.len())
            .map(|j| flux[j * coeffs + c] * lengths[j])
            .sum();
        let expected = if c == 0 {
            (4.0 * std::f32::consts::PI).sqrt()
        } else {
            0.0
        };
        assert!((total - expected).abs() < 1e-3, "coefficient {c}: {total}");
    }
    let mut basis = vec![0f64; coeffs];
    let mut value = |row: &[f32], w: Vec3| {
        crate::light::sh::eval_basis(w.as_dvec3().to_array(), bands, &mut basis);
        row.iter()
            .zip(&basis)
            .map(|(f, y)| *f as f64 * y)
            .sum::<f64>()
    };
    for (j, d) in dirs.offsets.iter().enumerate() {
        let row = &flux[j * coeffs..(j + 1) * coeffs];
        assert!(value(row, -unit(*d)) > value(row, unit(*d)) + 1e-3, "{d}");
    }
    // Each band's power, carried by the lines' means ȳ_ij = P_ij·ℓ_j/(4π·w_j) weighted by their
    // shares, is its power over the sphere, (2ℓ + 1)/4π.
    for band in 0..bands {
        let carried: f64 = (0..dirs.len())
            .map(|j| {
                let w = dirs.weights[j] as f64;
                let per_mean = lengths[j] as f64 / (4.0 * std::f64::consts::PI * w);
                (band * band..(band + 1) * (band + 1))
                    .map(|i| w * (flux[j * coeffs + i] as f64 * per_mean).powi(2))
                    .sum::<f64>()
            })
            .sum();
        let power = (2 * band + 1) as f64 / (4.0 * std::f64::consts::PI);
        assert!(
            (carried / power - 1.0).abs() < 1e-4,
            "band {band}: {carried} of {power}"
        );
    }
}

#[test]
fn opposite_directions_pair_up() {
    let dirs = Directions::new(LatticeKind::All);
    for (j, d) in dirs.offsets.iter().enumerate() {
        assert_eq!(dirs.offsets[dirs.opposite[j]], -*d);
    }
}

/// A slab 64 voxels thick (y in 0..64, density 1) and 192 wide, lit straight from above: the
/// lattice's fluence per unit irradiance down the slab's middle column, at K = 6.
fn slab_fluence(sigma_t: f32) -> Vec<(i32, f32)> {
    let (thick, wide, k) = (64, 192, 6);
    let field = DensityField::new(block_box(IVec3::new(wide, thick, wide)));
    let layout = TransferLayout::build(&field.grid, k);
    let medium = Medium {
        sigma_t,
        albedo: 1.0,
    };
    // The sun's first scattering per cell volume, as the renderer seeds it: the footprint's mean of
    // σt·ρ·e^(−τ), τ the midpoint depth of a voxel below the top face at y = 63.5.
    let seed: Vec<f32> = layout
        .voxels()
        .iter()
        .map(|a| {
            let rows = (a.y * k - k / 2..a.y * k - k / 2 + k).filter(|y| (0..thick).contains(y));
            let sum: f32 = rows
                .map(|y| (-(sigma_t * (thick as f32 - 0.5 - y as f32))).exp())
                .sum();
            sigma_t * sum / k as f32
        })
        .collect();
    let fluence = Lattice::build(&field, &layout, LatticeKind::All, medium, 1)
        .solve_emission(&seed)
        .0;
    let centre = wide / k / 2;
    let mut column: Vec<(i32, f32)> = layout
        .voxels()
        .iter()
        .zip(&fluence)
        .filter(|(a, _)| a.x == centre && a.z == centre)
        .map(|(a, f)| (a.y * k, *f))
        .collect();
    column.sort_by_key(|c| c.0);
    column
}

#[test]
fn a_thick_slab_conducts_light_as_diffusion_does() {
    // Inside a non-absorbing slab the scattered fluence falls linearly away from the lit face,
    // with the slope of the diffusion flux. The reference solves the same slab (trilinear faces,
    // collimated light from above, σt 1: 6 optical depths per transfer voxel) by the exact
    // integral equation of isotropic scattering in a slab (the E1 kernel, 100 points per voxel):
    // a slope of 0.0770 per voxel. Without the thick cells' reflection the lattice's cells
    // exchange light as opaque uniform emitters and conduct it far too well: the slope comes out
    // 0.051 (−34 %), the slab's interior too flat, too little light kept near the lit face. With
    // reflection above one optical depth per cell edge it is 0.0721 (−6.4 %), above the 26
    // directions' t₀ of 0.75 0.0768 (−0.2 %).
    let reference = 0.0770f32;
    let column = slab_fluence(1.0);
    let at = |y: i32| column.iter().find(|c| c.0 == y).map(|c| c.1).unwrap();
    let slope = (at(48) - at(12)) / 36.0;
    assert!(
        (slope / reference - 1.0).abs() < 0.03,
        "slope {slope} against {reference}"
    );
}

#[test]
fn each_line_passes_light_to_the_next_active_cell_along_it() {
    // Blocks with gaps between them along every axis and diagonal, so lines jump empty space and
    // hold several cells. Every direction's sweep must hold each cell once, start a line exactly
    // where no active cell lies upstream, follow each cell by the next active cell along d_j (a
    // march of unit steps through the layout finds it), and start every task at a line.
    use crate::volume::grid::{SparseGrid, TileLevel, Transform};
    let mut g = SparseGrid::new(Transform::default(), 0.0);
    // A 6³ grid of blocks a block apart, and one off the grid: over TASK_LINKS cells, so the
    // sweeps split into tasks.
    for i in 0..216 {
        let origin = IVec3::new(i % 6, i / 6 % 6, i / 36) * 16;
        g.insert_tile(TileLevel::Block, origin, 1.0);
    }
    g.insert_tile(TileLevel::Block, IVec3::new(104, 40, 8), 1.0);
    let layout = TransferLayout::build(&g, 2);
    let n = layout.len();
    let (lo, hi) = layout
        .voxels()
        .iter()
        .fold((IVec3::MAX, IVec3::MIN), |(a, b), v| (a.min(*v), b.max(*v)));
    let next_along = |v: IVec3, off: IVec3| {
        let mut step = v + off;
        while step.cmpge(lo).all() && step.cmple(hi).all() {
            if let Some(s) = layout.slot(step) {
                return Some(s as u32);
            }
            step += off;
        }
        None
    };
    // Each direction's lines come with its opposite's: both are checked.
    let laid = Directions::new(LatticeKind::All)
        .offsets
        .into_iter()
        .flat_map(|off| lines(&layout, off).into_iter().zip([off, -off]));
    for ((sweep, place), off) in laid {
        let slots: Vec<u32> = sweep.links.iter().map(|l| l.node & SLOT).collect();
        let mut seen = vec![false; n];
        for (i, &s) in slots.iter().enumerate() {
            assert!(!seen[s as usize], "{off}: cell {s} twice");
            seen[s as usize] = true;
            assert_eq!(place[s as usize] as usize, i);
            let v = layout.voxels()[s as usize];
            let starts = sweep.links[i].node & LINE_START != 0;
            assert_eq!(starts, next_along(v, -off).is_none(), "{off}: {v}");
            let follower = sweep
                .links
                .get(i + 1)
                .filter(|l| l.node & LINE_START == 0)
                .map(|l| l.node);
            assert_eq!(follower, next_along(v, off), "{off}: {v}");
        }
        assert!(seen.iter().all(|&s| s));
        assert!(sweep.tasks.len() > 2, "{off}: one task");
        assert_eq!(sweep.tasks.first(), Some(&0));
        assert_eq!(sweep.tasks.last(), Some(&n));
        for &t in &sweep.tasks[..sweep.tasks.len() - 1] {
            assert!(sweep.links[t].node & LINE_START != 0);
        }
    }
}

/// F_ms of a cube of `edge` voxels (density 1, σt 0.2) at transfer cells of 6, `bands` bands,
/// the generations stopped at `convergence`, and the lattice's stats.
fn cube_f_ms(edge: i32, albedo: f32, bands: usize, convergence: f64) -> (Vec<f32>, LatticeStats) {
    let field = DensityField::new(block_box(IVec3::splat(edge)));
    let layout = TransferLayout::build(&field.grid, 6);
    let medium = Medium {
        sigma_t: 0.2,
        albedo,
    };
    let mut lattice = Lattice::build(&field, &layout, LatticeKind::All, medium, bands);
    lattice.convergence = convergence;
    let mut f_ms = vec![0f32; layout.len() * bands * bands];
    let stats = lattice.bake_multiple(bands, 1.0, &mut f_ms);
    (f_ms, stats)
}

#[test]
fn the_tail_gives_what_the_generations_not_swept_would() {
    // A 48³ cube at albedo 0.99 under a sky whose every coefficient is lit (so the chunks after
    // the DC term, which stop with its generations and its ratio, carry light too): F_ms stopped
    // at CONVERGENCE with the tail added against a run to 1e-9: 4e-6 of the DC fluence's norm.
    // Dropping the tail leaves it 3.6e-3 off at this tolerance, far outside the bound.
    let bands = 3;
    let coeffs = bands * bands;
    let (short, quick) = cube_f_ms(48, 0.99, bands, CONVERGENCE);
    let (long, slow) = cube_f_ms(48, 0.99, bands, 1e-9);
    assert!(quick.converged && slow.converged);
    assert!(
        2 * quick.generations < slow.generations,
        "{} against {} generations",
        quick.generations,
        slow.generations
    );
    for c in 0..coeffs {
        let column = |f: &[f32]| -> Vec<f64> {
            f.iter()
                .skip(c)
                .step_by(coeffs)
                .map(|&v| v as f64)
                .collect()
        };
        let (a, b) = (column(&short), column(&long));
        let scale = b.iter().map(|v| v * v).sum::<f64>().sqrt();
        let error = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (x - y) * (x - y))
            .sum::<f64>()
            .sqrt();
        assert!(scale > 0.0, "coefficient {c} carries no light");
        assert!(
            error < 1e-4 * scale,
            "coefficient {c}: {:.2e} of its norm",
            error / scale
        );
    }
}

#[test]
fn the_lattice_transports_its_own_bands_and_no_more() {
    // A bake of more bands than LATTICE_BANDS: its lower coefficients are exactly those of a bake
    // of LATTICE_BANDS, its highest carried band carries light, and nothing is added above it
    // (F_ms's higher coefficients are the fit's correction alone).
    let bake = |bands: usize| cube_f_ms(24, 0.9, bands, CONVERGENCE).0;
    // Six beams carry bands 0 and 1 alone; the others, LATTICE_BANDS.
    let kinds = [
        LatticeKind::Faces,
        LatticeKind::FacesEdges,
        LatticeKind::All,
        LatticeKind::FacesSkew,
    ];
    assert_eq!(kinds.map(|k| k.bands(10)), [2, 4, 4, 4]);
    assert_eq!(kinds.map(|k| k.bands(1)), [1; 4]);
    let (carried, wide) = (LATTICE_BANDS, LATTICE_BANDS + 2);
    let (own, more) = (bake(carried), bake(wide));
    let top = (carried - 1) * (carried - 1)..carried * carried;
    let mut top_light = 0.0f32;
    for (a, b) in own
        .chunks_exact(carried * carried)
        .zip(more.chunks_exact(wide * wide))
    {
        assert_eq!(a, &b[..carried * carried]);
        assert!(b[carried * carried..].iter().all(|&v| v == 0.0));
        top_light += a[top.clone()].iter().map(|v| v.abs()).sum::<f32>();
    }
    assert!(top_light > 0.0);
}

#[test]
fn a_suns_gmres_solve_gives_what_the_generations_give() {
    // A 32³ cube of thin voxel cells (no cell reflects, so the solve takes GMRES) at albedo 0.99,
    // lit from above: the fluence against generations summed to 1e-9, and never negative.
    let field = DensityField::new(block_box(IVec3::splat(32)));
    let layout = TransferLayout::build(&field.grid, 1);
    let medium = Medium {
        sigma_t: 0.2,
        albedo: 0.99,
    };
    let lattice = Lattice::build(&field, &layout, LatticeKind::All, medium, 1);
    assert_eq!(lattice.links.reflecting_cells, 0);
    let seed: Vec<f32> = layout
        .voxels()
        .iter()
        .map(|a| 0.2 * (-0.2 * (31.5 - a.y as f32)).exp())
        .collect();
    let (krylov, sweeps) = lattice.solve_emission(&seed);
    let first = Source {
        energy_single: seed.iter().map(|&e| e as f64).sum(),
        convergence: 1e-9,
        bands: 1,
        medium,
    };
    let (summed, stats) =
        transport_chunk::<f32>(&lattice.links, &first, Drive::Emission(&seed), None);
    assert!(stats.converged && stats.generations > 100, "{stats:?}");
    assert!(sweeps < stats.generations / 2, "{sweeps} sweeps");
    let norm = |f: &dyn Fn(usize) -> f64| (0..seed.len()).map(|i| f(i).powi(2)).sum::<f64>().sqrt();
    let error = norm(&|i| (krylov[i] - summed[i]) as f64) / norm(&|i| summed[i] as f64);
    assert!(error < 1e-4, "{error:e} of the fluence's norm");
    assert!(krylov.iter().all(|&f| f >= 0.0));
}
