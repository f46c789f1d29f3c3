//! The bake on the fixtures: white furnace, direction, T_ri against a brute-force reference,
//! skipping.

use glam::{IVec3, Vec3};

use super::single::{bake_single, Origins, SingleSettings};
use super::{bake, lattice::LatticeKind, BakeSettings, Medium, Transfer, TransferLayout};
use crate::light::sh;
use crate::volume::transmittance::OpticalDepth;
use crate::volume::vdb::VdbFile;
use crate::volume::{DensityField, SparseGrid};

/// A fixture's density grid.
pub fn load(name: &str) -> SparseGrid {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("fixtures")
        .join(name);
    let vdb = VdbFile::open(&path).unwrap();
    vdb.read_grid(vdb.choose_grid(None).unwrap()).unwrap()
}

fn settings(bands: usize, scale: i32) -> BakeSettings {
    BakeSettings {
        bands,
        scale,
        samples: 256,
        lattice: LatticeKind::All,
        single_scatter: false,
        fit_direct: false,
        seed: 1,
    }
}

/// Worst relative deviation of T_ri,₀ + F_ms,₀ from √(4π) (the white-furnace value), over the
/// transfer voxels `select` picks, and their count.
fn furnace_deviation(t: &Transfer, select: impl Fn(IVec3) -> bool) -> (f32, usize) {
    let full = (4.0 * std::f32::consts::PI).sqrt();
    let mut worst = 0f32;
    let mut count = 0;
    let n = t.coeffs();
    let (t_ri, f_ms) = (
        t.coefficients().unwrap().0.to_f32(n),
        t.coefficients().unwrap().1.to_f32(n),
    );
    // The DC coefficient as the renderer reads it at a node's point, with the transfer's basis.
    let read = |coeffs: &[f32], v: IVec3| -> f32 {
        let (first, w) = t.basis.window(v.as_vec3());
        let e = t.basis.edge() as i32;
        let mut sum = 0.0;
        for x in 0..e {
            for y in 0..e {
                for z in 0..e {
                    let weight = w[x as usize].x * w[y as usize].y * w[z as usize].z;
                    let node = first + IVec3::new(x, y, z);
                    sum += weight * t.layout.slot(node).map_or(0.0, |s| coeffs[s * n]);
                }
            }
        }
        sum
    };
    for v in t.layout.voxels() {
        if select(*v) {
            let dev = (read(&t_ri, *v) + read(&f_ms, *v)) / full - 1.0;
            worst = if dev.abs() > worst.abs() { dev } else { worst };
            count += 1;
        }
    }
    (worst, count)
}

/// Transfer voxels at least `depth` transfer voxels inside the density: their (2·depth + 1)³
/// neighbourhood of transfer voxels sits inside.
fn inside_by(density: &SparseGrid, k: i32, depth: i32) -> impl Fn(IVec3) -> bool + '_ {
    let inside = move |v: IVec3| density.sample_index((v * k).as_vec3()) > 0.05;
    let side = 2 * depth + 1;
    let around = move |i: i32| IVec3::new(i / (side * side), (i / side) % side, i % side) - depth;
    move |v| (0..side.pow(3)).all(|i| inside(v + around(i)))
}

/// torus.vdb's rings (tools/vdbgen.py `rings_box`): major radius 24, tube radius 7, ring A in the
/// XY plane around (34, 34, 34), ring B in the XZ plane around (58, 34, 34); each passes through
/// the other's centre, so facing tube surfaces are 24 − 2·7 = 10 voxels apart.
const RING_GAP: f32 = 10.0;

/// Signed distances of index point `p` to the surfaces of rings A and B.
fn ring_distances(p: Vec3) -> (f32, f32) {
    let (c, major, tube) = (Vec3::splat(34.0), 24.0f32, 7.0f32);
    let a = ((p.x - c.x).hypot(p.y - c.y) - major).hypot(p.z - c.z) - tube;
    let b = ((p.x - c.x - major).hypot(p.z - c.z) - major).hypot(p.y - c.y) - tube;
    (a, b)
}

/// A fixture's density and its one-band bake at albedo 1 (the white furnace) with extinction
/// `sigma_t` and transfer scale `k`.
fn furnace_bake(file: &str, sigma_t: f32, k: i32) -> (SparseGrid, Transfer) {
    let d = load(file);
    let medium = Medium {
        sigma_t,
        albedo: 1.0,
    };
    let (t, _) = bake(
        &mut DensityField::new(d.clone()),
        medium,
        &settings(1, k),
        &crate::io::progress::Bars { quiet: true },
    );
    (d, t)
}

#[test]
fn white_furnace_where_transfer_voxels_are_optically_thin() {
    // Albedo 1 and at most ~0.5 optical depth per transfer voxel: the lattice must put back all
    // the light the unscattered transfer misses. Measured worst deviations: cloud −0.8 % (limit
    // 3 %, the issue's); torus −5.4 % — the lattice's ray effect: its unscattered light runs on
    // 26 beams, and along the rings' axis-aligned tubes some voxels see long dense columns on a
    // beam where the fine T_ri sees the tube's round section (docs/method.md). Its limit is a
    // regression guard just above what is achieved, not a target.
    for (file, sigma_t, k, limit) in [("cloud.vdb", 0.08, 6, 0.03), ("torus.vdb", 0.15, 3, 0.06)] {
        let (d, t) = furnace_bake(file, sigma_t, k);
        let (worst, count) = furnace_deviation(&t, inside_by(&d, k, 1));
        assert!(count > 50, "{file}: only {count} interior voxels");
        assert!(worst.abs() < limit, "{file}: furnace off by {worst}");
    }
}

#[test]
fn white_furnace_where_the_volume_is_optically_thick() {
    // Issue 4: albedo 1, more than 20 optical depths through the centre, every transfer voxel two
    // or more transfer voxels inside within 3 %. Cloud: ~60 voxels of density 1 across, so σt 1
    // gives ~60, at the default K = 6 (6 optical depths per face link). Torus: tubes 14 voxels
    // across, σt 2 gives 28; no transfer voxel lies two inside a tube at K = 3 or 6, so K = 2.
    // Measured: within 0.1 % (the lattice is driven by the environment at its boundary, module
    // doc of `lattice`); it was −17 % (cloud) before. Both bakes are on finer cells, fitted back
    // as quadratic B-splines (`refine`), and are read here as the renderer reads them. Every voxel
    // inside, surface included: cloud −2.5 %, torus +5.0 % (where T_ri and the lattice's own
    // unscattered light differ; on the transfer's own cells −4.7 % and −8.5 %); those limits are
    // regression guards just above what is achieved. The torus voxels of one ring facing the
    // other across the gap, lit across it through gap-jumping links: +2.7 % on the transfer's
    // cells, +4.2 % baked on cells of 1 and fitted back (3.5 optical depths per transfer voxel),
    // whose 256×144 furnace render is closer, 0.71 % (max 6.8 %) against 1.12 % (max 8.0 %).
    for (file, sigma_t, k, surface) in [("cloud.vdb", 1.0, 6, 0.03), ("torus.vdb", 2.0, 2, 0.055)] {
        let (d, t) = furnace_bake(file, sigma_t, k);
        let (worst, count) = furnace_deviation(&t, inside_by(&d, k, 2));
        assert!(count > 40, "{file}: only {count} voxels two inside");
        assert!(worst.abs() < 0.03, "{file}: furnace off by {worst}");
        let (worst, _) = furnace_deviation(&t, inside_by(&d, k, 0));
        assert!(
            worst.abs() < surface,
            "{file}: furnace off by {worst} at the surface"
        );
        if file == "torus.vdb" {
            let facing = |v: IVec3| {
                let (a, b) = ring_distances((v * k).as_vec3());
                a.min(b) <= 0.0 && a.max(b) <= RING_GAP + k as f32
            };
            let (worst, count) = furnace_deviation(&t, facing);
            assert!(count > 100, "only {count} voxels face the other ring");
            assert!(worst.abs() < 0.045, "furnace off by {worst} across the gap");
        }
    }
}

#[test]
fn thick_transfer_voxels_are_baked_finer() {
    // `refine`: a bake that keeps point values bakes on cells of ⌈K/2⌉ where its transfer voxels
    // are more than REFINE_CELL_DEPTH optical depths across (the torus at σt 1: 5.2), and on its
    // own cells where they are thinner, where it fits, or where its image is single scattering.
    let d = load("torus.vdb");
    let s = settings(2, 6);
    let thick = Medium {
        sigma_t: 1.0,
        albedo: 0.9,
    };
    assert_eq!(super::refine::fine_scale(&d, thick, &s), Some(3));
    let depth = super::cell_optical_depth(&d, 1.0, s.scale);
    let thinner = Medium {
        sigma_t: (0.99 * super::refine::REFINE_CELL_DEPTH / depth) as f32,
        ..thick
    };
    assert_eq!(super::refine::fine_scale(&d, thinner, &s), None);
    let fitting = Medium {
        albedo: 0.5,
        ..thick
    };
    assert_eq!(super::refine::fine_scale(&d, fitting, &s), None);
    let single = BakeSettings {
        single_scatter: true,
        ..s
    };
    assert_eq!(super::refine::fine_scale(&d, thick, &single), None);
    assert_eq!(super::refine::fine_scale(&d, thick, &settings(2, 1)), None);
    // The bake says so, and its transfer stays on the transfer's own voxels.
    let bars = crate::io::progress::Bars { quiet: true };
    let (t, stats) = bake(&mut DensityField::new(d.clone()), thick, &s, &bars);
    assert_eq!(stats.lattice_scale, 3);
    assert_eq!(t.layout.len(), TransferLayout::build(&d, 6).len());
    let (_, stats) = bake(&mut DensityField::new(d.clone()), thinner, &s, &bars);
    assert_eq!(stats.lattice_scale, 6);
}

#[test]
fn albedo_zero_scatters_nothing() {
    let d = load("torus.vdb");
    let mut f = DensityField::new(d.clone());
    let medium = Medium {
        sigma_t: 0.5,
        albedo: 0.0,
    };
    let (t, _) = bake(
        &mut f,
        medium,
        &settings(2, 6),
        &crate::io::progress::Bars { quiet: true },
    );
    assert!(t
        .coefficients()
        .unwrap()
        .1
        .to_f32(t.coeffs())
        .iter()
        .all(|v| *v == 0.0));
    assert!(t
        .coefficients()
        .unwrap()
        .0
        .to_f32(t.coeffs())
        .iter()
        .any(|v| *v != 0.0));
}

#[test]
fn a_medium_that_scatters_most_of_its_light_keeps_the_point_values() {
    // At albedo ≥ POINT_DIRECT_ALBEDO the stored T_ri is the nodes' point values — the same
    // rays as a node pass traced on its own — and F_ms is the lattice's scattered light alone,
    // never negative; below it T_ri is fitted to the footprint means, which differ.
    let d = load("torus.vdb");
    let f = DensityField::new(d.clone());
    let s = settings(4, 6);
    let coeffs = s.bands * s.bands;
    // 1.3 optical depths per transfer voxel: point values, on the transfer's own cells.
    let sigma_t = 0.25;
    let depth = super::cell_optical_depth(&d, sigma_t, s.scale);
    assert!((super::POINT_DIRECT_CELL_DEPTH..super::refine::REFINE_CELL_DEPTH).contains(&depth));
    let layout = TransferLayout::build(&d, s.scale);
    let single = SingleSettings {
        bands: s.bands,
        samples: s.samples,
        seed: s.seed,
        origins: Origins::Node,
        chord_step: super::single::chord_step(&d, sigma_t),
    };
    // The far field the bake's node pass marches.
    let (near, levels) = super::single::far_field(&d, sigma_t, s.samples);
    let mip = crate::volume::mip::DensityMip::build(&d, levels);
    let far = crate::volume::transmittance::FarField { mip: &mip, near };
    let point = bake_single(
        &d,
        &layout,
        &OpticalDepth::new(&f, sigma_t, true)
            .with_far_field(far)
            .with_dark_test(),
        single,
        None,
        &indicatif::ProgressBar::hidden(),
    );
    let baked = |albedo: f32| {
        let medium = Medium { sigma_t, albedo };
        let (t, _) = bake(
            &mut DensityField::new(d.clone()),
            medium,
            &s,
            &crate::io::progress::Bars { quiet: true },
        );
        let (t_ri, f_ms) = t.coefficients().unwrap();
        (t_ri.to_f32(coeffs).to_vec(), f_ms.to_f32(coeffs).to_vec())
    };
    let medium = |albedo, sigma_t| Medium { sigma_t, albedo };
    assert!(!s.fits_footprints(&d, medium(super::POINT_DIRECT_ALBEDO, sigma_t)));
    // Where a transfer voxel is thin the fit stays, at any albedo.
    let thin = sigma_t * (0.99 * super::POINT_DIRECT_CELL_DEPTH / depth) as f32;
    assert!(s.fits_footprints(&d, medium(0.9, thin)));
    assert!(!s.fits_footprints(&d, medium(0.9, 1.02 * thin)));
    // There the footprint pass, whose light reaches the image as the share 1 − albedo, traces a
    // share of the directions; where the fit is asked for or the albedo is low, all of them.
    let share = s.samples / super::THIN_FOOTPRINT_SHARE;
    assert_eq!(s.footprint_samples(medium(0.9, thin)), share);
    assert_eq!(s.footprint_samples(medium(0.5, thin)), s.samples);
    let asked = BakeSettings {
        fit_direct: true,
        ..s
    };
    assert_eq!(asked.footprint_samples(medium(0.9, thin)), s.samples);
    let (t_ri, f_ms) = baked(0.9);
    assert_eq!(t_ri, point);
    let least = f_ms
        .iter()
        .step_by(coeffs)
        .fold(f32::INFINITY, |a, &b| a.min(b));
    assert!(least >= -1e-6, "F_ms's DC reaches {least}");
    let (fitted, _) = baked(0.5);
    let apart = fitted.iter().zip(&point).filter(|(a, b)| a != b).count();
    assert!(apart > point.len() / 2, "only {apart} fitted values differ");
}

/// Mean of the SH dot product T·E over the voxels above and below the sphere's centre.
fn upper_lower(t: &[f32], layout: &TransferLayout, env: &[f32], coeffs: usize) -> (f32, f32) {
    let (mut up, mut down, mut nu, mut nd) = (0.0, 0.0, 0, 0);
    for (slot, v) in layout.voxels().iter().enumerate() {
        let l: f32 = t[slot * coeffs..(slot + 1) * coeffs]
            .iter()
            .zip(env)
            .map(|(a, b)| a * b)
            .sum();
        if v.y > 0 {
            up += l;
            nu += 1;
        } else if v.y < 0 {
            down += l;
            nd += 1;
        }
    }
    (up / nu as f32, down / nd as f32)
}

#[test]
fn light_from_the_zenith_lights_the_top() {
    // An environment bright only near +Y: E(ω) = max(0, ω·y)⁸, projected by Gauss-free brute force.
    let bands = 4;
    let coeffs = bands * bands;
    let mut env = vec![0f32; coeffs];
    let mut basis = vec![0f64; coeffs];
    let n = 20_000;
    for i in 0..n {
        let z = 1.0 - (2.0 * i as f64 + 1.0) / n as f64;
        let r = (1.0 - z * z).sqrt();
        let phi = 2.399_963 * i as f64;
        let dir = [r * phi.cos(), z, r * phi.sin()];
        sh::eval_basis(dir, bands, &mut basis);
        let e = z.max(0.0).powi(8) * 4.0 * std::f64::consts::PI / n as f64;
        env.iter_mut()
            .zip(&basis)
            .for_each(|(c, y)| *c += (e * y) as f32);
    }
    let d = load("sphere_fog.vdb");
    let mut f = DensityField::new(d.clone());
    let medium = Medium {
        sigma_t: 0.3,
        albedo: 0.9,
    };
    let (t, _) = bake(
        &mut f,
        medium,
        &settings(bands, 4),
        &crate::io::progress::Bars { quiet: true },
    );
    let (up, down) = upper_lower(
        &t.coefficients().unwrap().0.to_f32(coeffs),
        &t.layout,
        &env,
        coeffs,
    );
    assert!(up > 2.0 * down, "T_ri: upper {up} lower {down}");
    let (up, down) = upper_lower(
        &t.coefficients().unwrap().1.to_f32(coeffs),
        &t.layout,
        &env,
        coeffs,
    );
    assert!(up > down, "F_ms: upper {up} lower {down}");
}

#[test]
fn t_ri_agrees_with_a_brute_force_reference() {
    // 10 000 Fibonacci directions, no skipping, projected directly; the bake's 512-direction
    // estimate must sit within 4 standard errors of plain Monte Carlo at 512 samples (the
    // rotated Fibonacci sets do better than Monte Carlo, so this cannot pass by luck alone).
    let d = load("cloud.vdb");
    let f = DensityField::new(d.clone());
    let bands = 6;
    let coeffs = bands * bands;
    let medium = Medium {
        sigma_t: 0.2,
        albedo: 0.9,
    };
    let layout = TransferLayout::build(&d, 6);
    let single = SingleSettings {
        bands,
        samples: 512,
        seed: 3,
        origins: Origins::Node,
        chord_step: 1.0,
    };
    let t = bake_single(
        &d,
        &layout,
        &OpticalDepth::new(&f, medium.sigma_t, true),
        single,
        None,
        &indicatif::ProgressBar::hidden(),
    );
    let plain = OpticalDepth::new(&f, medium.sigma_t, false);
    let n = 10_000;
    let mut basis = vec![0f64; coeffs];
    for &v in layout.voxels().iter().step_by(layout.len() / 6) {
        let x = layout.position(v);
        let slot = layout.slot(v).unwrap();
        let (mut mean, mut sq) = (vec![0f64; coeffs], vec![0f64; coeffs]);
        for i in 0..n {
            let z = 1.0 - (2.0 * i as f64 + 1.0) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = 2.399_963_229_728_653 * i as f64;
            let dir = Vec3::new((r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32);
            let tr = plain.transmittance(x, dir) as f64;
            sh::eval_basis(dir.as_dvec3().to_array(), bands, &mut basis);
            for c in 0..coeffs {
                let f = 4.0 * std::f64::consts::PI * tr * basis[c];
                mean[c] += f / n as f64;
                sq[c] += f * f / n as f64;
            }
        }
        for c in 0..coeffs {
            let se = ((sq[c] - mean[c] * mean[c]).max(0.0) / 512.0).sqrt();
            let got = t[slot * coeffs + c] as f64;
            assert!(
                (got - mean[c]).abs() <= 4.0 * se + 1e-4,
                "voxel {v} coefficient {c}: {got} vs {} (se {se})",
                mean[c]
            );
        }
    }
}

#[test]
fn empty_space_skipping_changes_no_result() {
    let d = load("multi.vdb");
    let f = DensityField::new(d.clone());
    let layout = TransferLayout::build(&d, 4);
    let medium = Medium {
        sigma_t: 0.5,
        albedo: 0.9,
    };
    let run = |skip_empty| {
        let s = SingleSettings {
            bands: 3,
            samples: 64,
            seed: 5,
            origins: Origins::Footprint,
            chord_step: 1.0,
        };
        let depth = OpticalDepth::new(&f, medium.sigma_t, skip_empty);
        bake_single(
            &d,
            &layout,
            &depth,
            s,
            None,
            &indicatif::ProgressBar::hidden(),
        )
    };
    let (a, b) = (run(true), run(false));
    assert_eq!(a, b);
}

/// √(4π)·mean T over `n` Fibonacci directions: the DC coefficient of the transmittance from `x`,
/// without skipping (a reference independent of the bake's direction sets).
fn brute_force_dc(depth: &OpticalDepth, x: Vec3, n: usize) -> f64 {
    let sum: f64 = (0..n)
        .map(|i| {
            let z = 1.0 - (2.0 * i as f64 + 1.0) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = 2.399_963_229_728_653 * i as f64;
            let dir = Vec3::new((r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32);
            depth.transmittance(x, dir) as f64
        })
        .sum();
    (4.0 * std::f64::consts::PI).sqrt() * sum / n as f64
}

/// The relative residual of node `v`'s normal equation for the DC coefficient `dc(slot)`:
/// (Σ_p ρ w_v (Σ_m w_m L_m − T(p)) + λ·Σ_p ρ w_v (L_v − T(p))) / Σ_p ρ w_v T(p) over the
/// midpoints p between the density's voxels in `v`'s footprint (the fit's quadrature), ρ the
/// trilinear density, w the trilinear weights between nodes K apart, T the brute-force
/// transmittance and λ the fit's pull toward the footprint mean. Zero for the fit the renderer's
/// interpolation wants.
fn normal_residual(
    density: &SparseGrid,
    layout: &TransferLayout,
    plain: &OpticalDepth,
    v: IVec3,
    dc: impl Fn(usize) -> f64,
) -> f64 {
    let k = layout.k;
    let lambda = super::fit::FIT_REGULARISATION;
    let tent = |t: f32| (1.0 - t.abs()).max(0.0);
    let (mut residual, mut total) = (0.0, 0.0);
    let own = layout.slot(v).map_or(0.0, &dc);
    for o in (0..(2 * k).pow(3)).map(|i| {
        let s = 2 * k;
        IVec3::new(i / (s * s), (i / s) % s, i % s) - k
    }) {
        let p = (v * k + o).as_vec3() + 0.5;
        let rho = density.sample_index(p) as f64;
        if rho <= 0.0 {
            continue;
        }
        let q = p / k as f32;
        let base = q.floor().as_ivec3();
        let mut interpolated = 0.0;
        for c in 0..8 {
            let m = base + IVec3::new(c >> 2, (c >> 1) & 1, c & 1);
            let w = (0..3).map(|a| tent(q[a] - m[a] as f32)).product::<f32>() as f64;
            interpolated += w * layout.slot(m).map_or(0.0, &dc);
        }
        let w_v = (0..3).map(|a| tent(q[a] - v[a] as f32)).product::<f32>() as f64;
        let t = brute_force_dc(plain, p, 1024);
        residual += rho * w_v * (interpolated - t + lambda * (own - t));
        total += rho * w_v * t;
    }
    residual / total
}

#[test]
fn fitted_t_ri_solves_the_least_squares_problem_of_the_brute_force_transmittance() {
    // The rendered T_ri is fitted so that its trilinear interpolant matches the transmittance
    // where the density is: each node's normal equation has zero residual. Checked against a
    // brute-force transmittance on the thin torus, where the nodes' point values do not satisfy
    // it (their interpolant is too bright around the tubes).
    let d = load("torus.vdb");
    let mut f = DensityField::new(d.clone());
    let medium = Medium {
        sigma_t: 0.1,
        albedo: 0.9,
    };
    let settings = BakeSettings {
        single_scatter: true,
        samples: 1024,
        ..settings(1, 6)
    };
    let (t, _) = bake(
        &mut f,
        medium,
        &settings,
        &crate::io::progress::Bars { quiet: true },
    );
    let plain = OpticalDepth::new(&f, medium.sigma_t, false);
    let point = bake_single(
        &d,
        &t.layout,
        &OpticalDepth::new(&f, medium.sigma_t, true),
        SingleSettings {
            bands: 1,
            samples: 1024,
            seed: 1,
            origins: Origins::Node,
            chord_step: 1.0,
        },
        None,
        &indicatif::ProgressBar::hidden(),
    );
    let t_ri = t.coefficients().unwrap().0.to_f32(t.coeffs());
    let (mut fitted_worst, mut point_mean, mut n) = (0f64, 0f64, 0);
    for &v in t.layout.voxels().iter().step_by(t.layout.len() / 12) {
        let fitted = normal_residual(&d, &t.layout, &plain, v, |s| t_ri[s * t.coeffs()] as f64);
        let points = normal_residual(&d, &t.layout, &plain, v, |s| point[s] as f64);
        if fitted.is_finite() && points.is_finite() {
            fitted_worst = fitted_worst.max(fitted.abs());
            point_mean += points;
            n += 1;
        }
    }
    point_mean /= n as f64;
    assert!(n >= 8, "{n} nodes with density in their footprint");
    assert!(fitted_worst < 0.02, "fitted: worst residual {fitted_worst}");
    assert!(
        point_mean > 0.03,
        "point values: mean residual {point_mean}"
    );
}

#[test]
fn footprint_means_drawn_by_visibility_keep_their_value_with_less_noise() {
    // The torus at one optical depth per voxel: most of a surface node's footprint sees no light,
    // and starts drawn by ρ·w alone leave its mean to the few that land near the lit face. Drawn
    // by ρ·w·V, the estimate must keep the means (no bias against a 16× larger plain run) and
    // scatter less around them.
    use crate::volume::visibility::{Resolution, Visibility};
    let d = load("torus.vdb");
    let f = DensityField::new(d.clone());
    let sigma_t = 1.0;
    let layout = TransferLayout::build(&d, 6);
    let depth = OpticalDepth::new(&f, sigma_t, true);
    let visibility = Visibility::build(&f, sigma_t, Resolution::FINE);
    let bands = 3;
    let coeffs = bands * bands;
    let t_ri = |samples: usize, seed: u64, visibility: Option<&Visibility>| -> Vec<f64> {
        let s = SingleSettings {
            bands,
            samples,
            seed,
            origins: Origins::Footprint,
            chord_step: 1.0,
        };
        let hidden = indicatif::ProgressBar::hidden();
        bake_single(&d, &layout, &depth, s, visibility, &hidden)
            .into_iter()
            .map(f64::from)
            .collect()
    };
    let reference = t_ri(2048, 1, None);
    // The RMS error of every coefficient over the nodes and the bias of the DC terms' sum, both
    // relative to the reference's mean DC term.
    let measure = |t: &[f64]| {
        let dc = |t: &[f64]| t.iter().step_by(coeffs).sum::<f64>();
        let n = (t.len() / coeffs) as f64;
        let scale = dc(&reference) / n;
        let sq: f64 = t.iter().zip(&reference).map(|(a, b)| (a - b).powi(2)).sum();
        (
            (sq / n).sqrt() / scale,
            (dc(t) - dc(&reference)) / (n * scale),
        )
    };
    let plain = measure(&t_ri(128, 2, None));
    let drawn = measure(&t_ri(128, 2, Some(&visibility)));
    // Measured: 6.4 % against 8.4 %, biases −0.27 % and −0.02 %.
    assert!(
        drawn.0 < 0.85 * plain.0,
        "error: by V {drawn:?}, plain {plain:?}"
    );
    assert!(
        drawn.1.abs() < 0.01,
        "bias: by V {drawn:?}, plain {plain:?}"
    );
}
