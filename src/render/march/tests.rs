//! Tests of `march`.

use super::*;
use crate::math::ray::Ray;
use crate::render::film::{each_direction, Frame};
use crate::render::relight::Radiance;
use crate::transfer::shape::TransferShape;
use crate::volume::grid::{add_hashed_leaves, block_box, TileLevel, LEAF_VOXELS};
use crate::volume::visibility::Resolution;
use crate::volume::{SparseGrid, Transform};
use glam::IVec3;

/// A test source given by its value at a point, summed step by step.
struct Pointwise<F>(F);

impl<F: Fn(Vec3) -> [[f32; 3]; 2] + Sync> InScatter for Pointwise<F> {
    type Sum = [[f32; 3]; 2];
    fn begin(&self) -> Self::Sum {
        [[0.0; 3]; 2]
    }
    fn add(&self, step: &Step, sum: &mut Self::Sum, _: &mut BrickSampler) {
        let (ls, c) = ((self.0)(step.p), step.weight());
        for part in 0..2 {
            for ch in 0..3 {
                sum[part][ch] += c * ls[part][ch];
            }
        }
    }
    fn total(&self, sum: &mut Self::Sum) -> [[f32; 3]; 2] {
        std::mem::take(sum)
    }
}

/// Ls the same everywhere.
fn uniform(ls: [[f32; 3]; 2]) -> Pointwise<impl Fn(Vec3) -> [[f32; 3]; 2] + Sync> {
    Pointwise(move |_| ls)
}

/// Ls varying smoothly with position, so misplaced steps would show.
fn smooth() -> Pointwise<impl Fn(Vec3) -> [[f32; 3]; 2] + Sync> {
    Pointwise(|p: Vec3| {
        let s = (p * 0.1).to_array().map(f32::sin);
        [
            [1.0 + s[0], 1.0 + s[1], 1.0 + s[2]],
            [0.5 + 0.3 * s[1], 0.2, 0.1],
        ]
    })
}

/// A step at `p` (density `rho`) whose source is weighted by `c`, as a source's unit tests feed it.
fn step_at(p: Vec3, rho: f32, c: f32) -> Step {
    Step {
        p,
        span: Vec3::X,
        rho,
        scatter: c,
        front: 1.0,
        tau: f32::INFINITY,
        tr: 0.0,
    }
}

/// `src`'s light from `steps`, summed as one ray's.
fn ray_sum<S: InScatter>(src: &S, steps: &[Step]) -> [[f32; 3]; 2] {
    let field = DensityField::new(SparseGrid::new(Transform::default(), 0.0));
    let mut sampler = field.sampler();
    let mut sum = src.begin();
    for step in steps {
        src.add(step, &mut sum, &mut sampler);
    }
    src.total(&mut sum)
}

fn medium(sigma_t: f32, albedo: f32) -> Medium {
    Medium { sigma_t, albedo }
}

/// Per-axis voxel sizes and an offset, so world↔index conversions are exercised.
fn anisotropic() -> Transform {
    Transform {
        scale: DVec3::new(0.01, 0.012, 0.008),
        translation: DVec3::new(1.0, -2.0, 0.5),
    }
}

fn world_box(g: &SparseGrid, lo: f64, hi: f64) -> (Vec3, Vec3) {
    let a = g.transform.index_to_world(DVec3::splat(lo)).as_vec3();
    let b = g.transform.index_to_world(DVec3::splat(hi)).as_vec3();
    (a.min(b), a.max(b))
}

fn cameras(g: &SparseGrid, w: u32, h: u32) -> Vec<Camera> {
    let (lo, hi) = world_box(g, 0.0, 127.0);
    let c = 0.5 * (lo + hi);
    vec![
        Camera::framing(lo, hi, w, h, 45.0).unwrap(),
        Camera::look_at(
            c + Vec3::new(2.0, 1.4, 1.7),
            c + Vec3::new(0.05, -0.02, 0.0),
            Vec3::Y,
            38.0,
            w,
            h,
        )
        .unwrap(),
    ]
}

fn unit_tile(transform: Transform, value: f32) -> SparseGrid {
    let mut g = SparseGrid::new(transform, 0.0);
    g.insert_tile(TileLevel::Node, IVec3::ZERO, value);
    g
}

#[test]
fn zero_density_shows_the_background_exactly() {
    let constant = each_direction(|_| [0.3f32, 0.6, 1.2]);
    let directional = each_direction(|d| [d.x + 1.0, 2.0 * d.y + 3.0, d.z.abs()]);
    let backgrounds: [Background; 2] = [&constant, &directional];
    // Active but zero: a node tile and a leaf; and a grid with nothing active at all.
    let mut zeros = unit_tile(anisotropic(), 0.0);
    let mut mask = [u64::MAX; 8];
    mask[3] = 0;
    zeros.insert_leaf(IVec3::new(128, 0, 0), mask, [0.0; LEAF_VOXELS]);
    let empty = SparseGrid::new(anisotropic(), 0.0);
    for g in [&zeros, &empty] {
        let field = DensityField::new(g.clone());
        let source = uniform([[5.0; 3]; 2]);
        for bg in backgrounds {
            let scene = Scene::new(&field, medium(3.0, 0.9), &source, Some(bg));
            for skip_empty in [true, false] {
                let settings = MarchSettings {
                    skip_empty,
                    ..MarchSettings::default()
                };
                for cam in cameras(&zeros, 24, 16) {
                    let (frame, _) = render_whole(&scene, &cam, &settings);
                    for (i, px) in frame.rgba.iter().enumerate() {
                        let (x, y) = (i as u32 % 24, i as u32 / 24);
                        let (_, dir) = cam.ray(x as f32 + 0.5, y as f32 + 0.5);
                        let mut e = [[0.0; 3]];
                        bg(&[dir], &mut e);
                        let e = e[0];
                        assert_eq!(*px, [e[0], e[1], e[2], 1.0]);
                        assert_eq!(frame.direct[i], [0.0; 3]);
                        assert_eq!(frame.depth[i], 0.0);
                    }
                }
            }
        }
    }
}

/// 1D profile of the trilinear density of voxels [0, 127] = 1 along one axis: a linear ramp
/// over one voxel on each side.
fn profile(x: f64) -> f64 {
    (x + 1.0).min(128.0 - x).clamp(0.0, 1.0)
}

/// ∫ ρ ds along the world ray, exactly: ρ is the product of the three axis profiles, a cubic
/// between the t where any coordinate crosses −1, 0, 127 or 128, so two-point Gauss–Legendre
/// per piece is exact. Also says whether the ray is "face only": wherever ρ > 0, at most one
/// axis is on its ramp.
fn exact_integral(g: &SparseGrid, origin: Vec3, dir: Vec3) -> (f64, bool) {
    let Ray {
        origin: o, dir: d, ..
    } = g.transform.ray_to_index(origin, dir);
    let mut ts = vec![0.0];
    for a in 0..3 {
        for c in [-1.0, 0.0, 127.0, 128.0] {
            if d[a] != 0.0 && (c - o[a]) / d[a] > 0.0 {
                ts.push((c - o[a]) / d[a]);
            }
        }
    }
    ts.sort_by(f64::total_cmp);
    let rho = |t: f64| {
        let p = o + d * t;
        profile(p.x) * profile(p.y) * profile(p.z)
    };
    let gl = 0.5 / 3f64.sqrt();
    let (mut sum, mut face_only) = (0.0, true);
    for w in ts.windows(2) {
        let (a, b) = (w[0], w[1]);
        let m = 0.5 * (a + b);
        sum += 0.5 * (b - a) * (rho(m - gl * (b - a)) + rho(m + gl * (b - a)));
        let p = o + d * m;
        let ramps = (0..3).filter(|&i| p[i] < 0.0 || p[i] > 127.0).count();
        if rho(m) > 0.0 && ramps > 1 {
            face_only = false;
        }
    }
    (sum, face_only)
}

#[test]
fn pure_absorber_is_transmittance_times_background() {
    // Albedo 0 ⇒ L = Tr·E exactly (docs/model.md, "Facts the tests check"). A 128³ tile of density 1: its trilinear
    // density is 1 on [0, 127]³ and falls linearly to 0 over one voxel outside. Along a ray
    // that crosses each ramp through a face (the other two coordinates on the plateau), ρ
    // rises linearly over the ramp and ∫ramp = ½·(ramp chord), which is the chord from the
    // ramp's midplane: so ∫ρ ds = the chord through the box [−0.5, 127.5]³ exactly. Rays
    // through edges and corners multiply two or three ramps; for them the reference is the
    // exact piecewise-cubic integral instead.
    let g = unit_tile(anisotropic(), 1.0);
    let field = DensityField::new(g.clone());
    let sigma_t = 1.5f32; // longest chord ≈ 2.2 world units: optical depth ≤ 3.4 < 5
    let source = uniform([[7.0; 3]; 2]);
    let e = [1.0f32, 0.5, 2.0];
    let bg = each_direction(|_| e);
    let scene = Scene::new(&field, medium(sigma_t, 0.0), &source, Some(&bg));
    let settings = MarchSettings {
        step_voxels: 0.25,
        ..MarchSettings::default()
    };
    let (w, h) = (48u32, 32u32);
    let blo = g.transform.index_to_world(DVec3::splat(-0.5));
    let bhi = g.transform.index_to_world(DVec3::splat(127.5));
    let (mut face_rays, mut hits) = (0, 0);
    for cam in cameras(&g, w, h) {
        let (frame, _) = render_whole(&scene, &cam, &settings);
        for (i, px) in frame.rgba.iter().enumerate() {
            let (x, y) = (i as u32 % w, i as u32 / w);
            let (origin, dir) = cam.ray(x as f32 + 0.5, y as f32 + 0.5);
            let (integral, face_only) = exact_integral(&g, origin, dir);
            if face_only {
                // The analytic chord of the world box [−0.5, 127.5]³.
                let chord = Ray::new(origin.as_dvec3(), dir.as_dvec3())
                    .clip(0.0, f64::INFINITY, blo, bhi)
                    .map_or(0.0, |(a, b)| b - a);
                assert!((chord - integral).abs() < 1e-9, "{chord} vs {integral}");
                face_rays += 1;
            }
            hits += (integral > 0.0) as u32;
            let tr = (-(sigma_t as f64) * integral).exp();
            for c in 0..3 {
                let want = e[c] as f64 * tr;
                let rel = (px[c] as f64 - want).abs() / want;
                assert!(rel < 1e-3, "pixel ({x},{y}) {px:?}: want {want}");
            }
            assert_eq!(frame.direct[i], [0.0; 3]);
            assert!((px[3] - 1.0).abs() < 1e-6);
        }
    }
    // Most rays hit, and most of those cross faces only: the chord check is not vacuous.
    assert!(hits > (w * h), "hits {hits}");
    assert!(face_rays > (w * h) / 2, "face rays {face_rays}");
}

#[test]
fn furnace_albedo_one_gives_the_background() {
    // Albedo 1 with Ls = E = c everywhere: Σ Tr_k (1 − e^{−τ_k}) c + Tr c telescopes to c,
    // early termination included (what is cut off is added back as Tr·E).
    let g = unit_tile(anisotropic(), 1.0);
    let field = DensityField::new(g.clone());
    let c = [0.8f32, 1.0, 1.7];
    let source = uniform([[c[0], c[1], 0.0], [0.0, 0.0, c[2]]]);
    let bg = each_direction(|_| c);
    for sigma_t in [0.5f32, 4.0, 200.0] {
        let scene = Scene::new(&field, medium(sigma_t, 1.0), &source, Some(&bg));
        for cam in cameras(&g, 16, 12) {
            let (frame, _) = render_whole(&scene, &cam, &MarchSettings::default());
            for px in &frame.rgba {
                for ch in 0..3 {
                    assert!((px[ch] - c[ch]).abs() < 1e-5 * c[ch], "{px:?}");
                }
            }
        }
    }
}

/// A sparse, cloud-like grid: hashed leaf values, gaps between leaves, a node tile.
fn lumpy() -> SparseGrid {
    let mut g = SparseGrid::new(anisotropic(), 0.0);
    g.insert_tile(TileLevel::Node, IVec3::new(128, 0, 0), 0.4);
    g.insert_tile(TileLevel::Block, IVec3::new(40, 80, 40), 1.5);
    add_hashed_leaves(&mut g, 60);
    g
}

#[test]
fn skipping_changes_nothing() {
    let g = lumpy();
    let field = DensityField::new(g.clone());
    let directional = each_direction(|d| [d.x.abs(), 0.5 + d.y, 1.0 - d.z]);
    for (sigma_t, bg) in [(3.0f32, Some(&directional as Background)), (40.0, None)] {
        let source = smooth();
        let scene = Scene::new(&field, medium(sigma_t, 0.8), &source, bg);
        let (lo, hi) = world_box(&g, 0.0, 256.0);
        let cams = [
            Camera::framing(lo, hi, 40, 30, 45.0).unwrap(),
            Camera::look_at(hi * 1.3, 0.5 * (lo + hi), Vec3::Y, 30.0, 40, 30).unwrap(),
        ];
        for cam in cams {
            let settings = MarchSettings {
                spp: 2,
                ..MarchSettings::default()
            };
            let plain = MarchSettings {
                skip_empty: false,
                ..settings
            };
            let (a, sa) = render_whole(&scene, &cam, &settings);
            let (b, sb) = render_whole(&scene, &cam, &plain);
            assert_eq!(a, b);
            assert_eq!(sb.samples_skipped, 0);
            assert_eq!(sa.samples_taken + sa.samples_skipped, sb.samples_taken);
            assert!(sa.samples_skipped > sa.samples_taken / 10, "{sa:?}");
            assert!(a.rgba.iter().any(|p| p[3] > 0.5));
        }
    }
}

#[test]
fn no_background_is_premultiplied_with_alpha() {
    let g = unit_tile(Transform::default(), 1.0);
    let field = DensityField::new(g.clone());
    let source = uniform([[1.0, 2.0, 3.0], [0.5, 0.5, 0.5]]);
    let scene = Scene::new(&field, medium(0.01, 0.5), &source, None);
    let cam = Camera::framing(Vec3::ZERO, Vec3::splat(127.0), 20, 20, 45.0).unwrap();
    let (frame, stats) = render_whole(&scene, &cam, &MarchSettings::default());
    assert_eq!(stats.rays, 400);
    // The framing camera sees the tile fill most of the frame: the checks below run on them.
    let covered = frame.rgba.iter().filter(|px| px[3] > 0.0).count();
    assert!(covered > 200, "{covered} of 400 pixels see the tile");
    for (i, px) in frame.rgba.iter().enumerate() {
        let alpha = px[3];
        if alpha == 0.0 {
            assert_eq!(*px, [0.0; 4]);
            continue;
        }
        // L = albedo·(1 − Tr)·Ls for a constant Ls: colour / alpha = albedo·Ls.
        let want = [0.75f32, 1.25, 1.75];
        for c in 0..3 {
            assert!((px[c] / alpha - want[c]).abs() < 1e-4 * want[c]);
            assert!((frame.direct[i][c] + frame.indirect[i][c] - px[c]).abs() < 1e-6);
        }
        // Depth lies inside the tile, seen from the camera.
        let d = frame.depth[i];
        assert!(
            d > cam.position.z - 128.0 && d < cam.position.z + 1.0,
            "{d}"
        );
    }
}

#[test]
fn a_degenerate_step_ends_instead_of_hanging() {
    let g = unit_tile(Transform::default(), 1.0);
    let field = DensityField::new(g.clone());
    let source = uniform([[1.0; 3]; 2]);
    let scene = Scene::new(&field, medium(1.0, 0.5), &source, None);
    let mut stats = MarchStats::default();
    for step_voxels in [0.0, f32::NAN, -1.0] {
        let settings = MarchSettings {
            step_voxels,
            ..MarchSettings::default()
        };
        let r = march_ray(
            &scene,
            Vec3::new(64.0, 64.0, 500.0),
            -Vec3::Z,
            0.5,
            &settings,
            &mut scene.scratch(),
            &mut stats,
        );
        assert_eq!(r.transmittance, 1.0);
    }
    assert_eq!(stats.samples_taken, 0);
}

#[test]
fn transfer_radiance_interpolates_slots() {
    let g = unit_tile(Transform::default(), 1.0);
    let layout = TransferLayout::build(&g, 6);
    // Direct: red = the transfer voxel's x, green 1; one plane of voxels (x = 0) unlit.
    let direct: Vec<[f32; 3]> = layout
        .voxels()
        .iter()
        .map(|v| {
            if v.x == 0 {
                [0.0; 3]
            } else {
                [v.x as f32, 1.0, 0.0]
            }
        })
        .collect();
    let radiance = Radiance::new(&direct, &vec![[0.25; 3]; layout.len()]);
    let src = TransferRadiance::new(&layout, Basis::Tent, &radiance, None);
    let at = |q: Vec3| ray_sum(&src, &[step_at(q, 1.0, 1.0)]);
    // The layout's own trilinear weights, direct red.
    let want = |q: Vec3| -> f32 {
        layout
            .corners(q)
            .iter()
            .map(|(s, w)| s.map_or(0.0, |s| w * radiance.direct(s)[0]))
            .sum()
    };
    // Between x = 5 and 6, next to the unlit plane, and at a corner.
    let points = [
        Vec3::new(33.0, 20.5, 70.25),
        Vec3::new(3.0, 20.5, 70.25),
        Vec3::new(1.0, 9.7, 3.0),
    ];
    for q in points {
        let [d, i] = at(q);
        assert!((d[0] - want(q)).abs() < 1e-5, "{q}");
        assert!((i[0] - 0.25).abs() < 1e-6);
    }
    let [d, _] = at(points[0]);
    assert!(
        (d[0] - 5.5).abs() < 1e-5 && (d[1] - 1.0).abs() < 1e-6,
        "{d:?}"
    );
    // A weighted sum over steps that leave a cell and come back to it is the sum of the
    // weighted point values: no cell's weights are lost or counted twice.
    let steps = [
        (points[0], 0.5),
        (points[0] + 0.5, 0.25),
        (points[1], 2.0),
        (points[0], 1.0),
    ];
    let [d, i] = ray_sum(&src, &steps.map(|(q, c)| step_at(q, 1.0, c)));
    let expect: f32 = steps.iter().map(|&(q, c)| c * want(q)).sum();
    assert!(
        (d[0] - expect).abs() < 1e-5 * expect,
        "{} vs {expect}",
        d[0]
    );
    assert!((i[2] - 0.25 * 3.75).abs() < 1e-6);
}

#[test]
fn quadratic_b_spline_radiance_reproduces_a_linear_field() {
    // Node values linear in the node's x (red = x, green 1) read as quadratic B-splines give the
    // linear field itself wherever the 27 nodes around a point exist: red = x / K. Steps that
    // leave a window and come back to it lose no weight.
    let g = unit_tile(Transform::default(), 1.0);
    let layout = TransferLayout::build(&g, 6);
    let direct: Vec<[f32; 3]> = layout
        .voxels()
        .iter()
        .map(|v| [v.x as f32, 1.0, 0.0])
        .collect();
    let radiance = Radiance::new(&direct, &vec![[0.25; 3]; layout.len()]);
    let src = TransferRadiance::new(&layout, Basis::Quadratic, &radiance, None);
    let points = [
        Vec3::new(33.0, 20.5, 70.25),
        Vec3::new(35.9, 20.5, 70.25),
        Vec3::new(36.1, 40.0, 11.0),
        Vec3::new(60.0, 9.7, 30.0),
    ];
    for q in points {
        let [d, i] = ray_sum(&src, &[step_at(q, 1.0, 1.0)]);
        assert!((d[0] - q.x / 6.0).abs() < 1e-4, "{q}: {d:?}");
        assert!((d[1] - 1.0).abs() < 1e-5 && (i[0] - 0.25).abs() < 1e-6);
    }
    let steps = [
        (points[0], 0.5),
        (points[1], 0.25),
        (points[2], 2.0),
        (points[0], 1.0),
        (points[3], 0.125),
    ];
    let [d, _] = ray_sum(&src, &steps.map(|(q, c)| step_at(q, 1.0, c)));
    let expect: f32 = steps.iter().map(|&(q, c)| c * q.x / 6.0).sum();
    assert!(
        (d[0] - expect).abs() < 1e-4 * expect,
        "{} vs {expect}",
        d[0]
    );
}

#[test]
fn the_suns_multiple_scattering_is_interpolated_between_their_own_nodes() {
    // The suns' lattice at an edge of 3, its nodes' RGB (x, 1, 0), one plane (x = 0) dark: a
    // step adds weight()·(trilinear radiance) to `indirect`, nothing to `direct`, and steps that
    // leave a cell and come back to it lose no weight.
    let g = unit_tile(Transform::default(), 1.0);
    let layout = TransferLayout::build(&g, 3);
    let mut nodes: Vec<[f32; 3]> = layout
        .voxels()
        .iter()
        .map(|v| match v.x {
            0 => [0.0; 3],
            x => [x as f32, 1.0, 0.0],
        })
        .collect();
    nodes.push([0.0; 3]);
    let src = SunRadiance::new([], Some((&layout, &nodes)));
    let want = |q: Vec3, ch: usize| -> f32 {
        layout
            .corners(q)
            .iter()
            .map(|(s, w)| s.map_or(0.0, |s| w * nodes[s][ch]))
            .sum()
    };
    let steps = [
        (Vec3::new(33.0, 20.5, 70.25), 0.5),
        (Vec3::new(34.5, 21.0, 70.75), 0.25),
        (Vec3::new(2.0, 20.5, 70.25), 2.0),
        (Vec3::new(33.0, 20.5, 70.25), 1.0),
    ];
    let [direct, indirect] = ray_sum(&src, &steps.map(|(q, c)| step_at(q, 1.0, c)));
    assert_eq!(direct, [0.0; 3]);
    for (ch, got) in indirect.into_iter().enumerate() {
        let expect: f32 = steps.iter().map(|&(q, c)| c * want(q, ch)).sum();
        assert!(
            (got - expect).abs() <= 1e-5 * expect,
            "{ch}: {got} vs {expect}"
        );
    }
    // Halfway between nodes 11 and 12 on x (34.5 / 3 = 11.5): red 11.5; beside the dark plane
    // (2 / 3 of the way from node 0 to node 1), green 2/3.
    assert!((want(Vec3::new(34.5, 21.0, 70.5), 0) - 11.5).abs() < 1e-4);
    assert!((want(Vec3::new(2.0, 21.0, 70.5), 1) - 2.0 / 3.0).abs() < 1e-5);
}

#[test]
fn a_transfer_shaped_like_the_visibility_is_reproduced_at_the_density_resolution() {
    // A 32³ cube at 12.8 optical depths across: V falls several-fold within a transfer voxel
    // under its faces. Direct light equal to c × the fitted node values of V must come out as
    // c × V at any point, at either resolution V is kept at, where plain interpolation gives a
    // straight line.
    let mut g = SparseGrid::new(Transform::default(), 0.0);
    for l in 0..64 {
        let origin = IVec3::new(l / 16, (l / 4) % 4, l % 4) * 8;
        g.insert_leaf(origin, [u64::MAX; 8], [1.0; LEAF_VOXELS]);
    }
    let field = DensityField::new(g);
    let layout = TransferLayout::build(&field.grid, 6);
    let coarse = Resolution {
        level: 1,
        directions: 8,
    };
    for resolution in [Resolution::FINE, coarse] {
        let shape = TransferShape::build(&field, &layout, 0.4, resolution);
        let c = 3.0;
        let direct: Vec<[f32; 3]> = shape.fitted.iter().map(|v| [c * v; 3]).collect();
        let radiance = Radiance::new(&direct, &vec![[0.5; 3]; layout.len()]);
        let shaped = TransferRadiance::new(
            &layout,
            Basis::Tent,
            &radiance,
            Some(Shaping {
                visibility: &shape.visibility,
                fitted: &shape.fitted,
            }),
        );
        let plain = TransferRadiance::new(&layout, Basis::Tent, &radiance, None);
        let at = |src: &TransferRadiance, q: Vec3| {
            ray_sum(src, &[step_at(q, field.grid.sample_index(q), 1.0)])
        };
        let mut plain_error = 0.0f32;
        for q in [
            Vec3::new(0.5, 16.0, 16.0),
            Vec3::new(2.25, 13.5, 20.0),
            Vec3::new(16.0, 16.0, 16.0),
            Vec3::new(30.0, 4.5, 29.75),
        ] {
            let rho = field.grid.sample_index(q);
            let v = shape.visibility.sampler().at(q, rho).unwrap();
            let [d, i] = at(&shaped, q);
            assert!(
                (d[0] - c * v).abs() < 1e-4 * c,
                "{resolution:?} {q}: {} vs {}",
                d[0],
                c * v
            );
            assert!(
                (i[0] - 0.5).abs() < 1e-6,
                "the indirect light is not reshaped"
            );
            plain_error = plain_error.max((at(&plain, q)[0][0] / (c * v) - 1.0).abs());
        }
        // Without the shape the straight line between nodes misses the fall by far.
        assert!(plain_error > 0.1, "{resolution:?}: {plain_error}");
    }
}

#[test]
fn real_cloud_skip_equals_plain() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/cloud.vdb");
    let vdb = crate::volume::vdb::VdbFile::open(std::path::Path::new(path)).unwrap();
    let g = vdb.read_grid(vdb.choose_grid(None).unwrap()).unwrap();
    let field = DensityField::new(g.clone());
    let (lo, hi) = g.active_bbox().unwrap();
    let (wlo, whi) = (
        g.transform.index_to_world(lo.as_dvec3()).as_vec3(),
        g.transform.index_to_world(hi.as_dvec3()).as_vec3(),
    );
    let cam = Camera::framing(wlo.min(whi), wlo.max(whi), 64, 48, 45.0).unwrap();
    let sky = each_direction(|d| [0.2 + d.y.max(0.0), 0.4, 0.9]);
    // An optical depth of about 8 across the cloud's 96-voxel width at density 1.
    let sigma_t = 8.0 / (96.0 * g.transform.voxel_size().x as f32);
    let source = smooth();
    let scene = Scene::new(&field, medium(sigma_t, 0.9), &source, Some(&sky));
    let (a, sa) = render_whole(&scene, &cam, &MarchSettings::default());
    let plain = MarchSettings {
        skip_empty: false,
        ..MarchSettings::default()
    };
    let (b, _) = render_whole(&scene, &cam, &plain);
    assert_eq!(a, b);
    assert!(sa.samples_skipped > 0);
    // The cloud blocks part of the sky: some pixels are mostly volume.
    assert!(a.direct.iter().any(|d| d[0] > 0.1));
}

#[test]
fn bands_of_rows_make_the_whole_frame() {
    // An image written band by band must be the image rendered at once, statistics included,
    // whatever rows a band starts at.
    let g = unit_tile(Transform::default(), 1.0);
    let field = DensityField::new(g);
    let source = uniform([[1.0, 2.0, 3.0], [0.5, 0.5, 0.5]]);
    let scene = Scene::new(&field, medium(0.01, 0.5), &source, None);
    let cam = Camera::framing(Vec3::ZERO, Vec3::splat(127.0), 20, 45, 45.0).unwrap();
    let settings = MarchSettings::default();
    let bar = ProgressBar::hidden();
    let (whole, ws) = render_whole(&scene, &cam, &settings);
    let (rgba, s, _) = stream(&scene, &cam, &settings, &bar, |rows| {
        let mut rgba = Vec::new();
        // Bands with and without their layers: the same pixels, and no layer where none was
        // asked for.
        for (range, layers) in [(0..7, true), (7..40, false), (40..45, true)] {
            let band = rows(range.clone(), layers);
            assert_eq!((band.width, band.height), (20, range.len() as u32));
            let pixels = if layers { 20 * range.len() } else { 0 };
            assert_eq!(band.depth.len(), pixels);
            assert_eq!((band.direct.len(), band.indirect.len()), (pixels, pixels));
            rgba.extend(band.rgba);
        }
        rgba
    });
    let rays = s.rays;
    assert_eq!(rgba, whole.rgba);
    assert_eq!(rays, ws.rays);
    assert!(whole.rgba.iter().any(|p| p[3] > 0.0));
}

/// The whole frame of `cam`, rendered at once.
fn render_whole<S: InScatter>(
    scene: &Scene<S>,
    cam: &Camera,
    settings: &MarchSettings,
) -> (Frame, MarchStats) {
    let (frame, stats, _) = stream(scene, cam, settings, &ProgressBar::hidden(), |rows| {
        rows(0..cam.height, true)
    });
    (frame, stats)
}

#[test]
fn a_thick_sunlit_step_is_split_so_its_light_falls_within_it() {
    // The camera inside a uniform slab, half a voxel under its plateau's top, looking down, the
    // sun overhead: at distance s the sun's depth is τ₀ + σt·s, so
    // L = ∫ σs·p·E·e^{−σt·s}·e^{−τ₀−σt·s} ds = albedo·p·E·e^{−τ₀}/2. A jitter of ½ puts the first
    // step's start at the camera (its midpoint is half a step in). At two optical depths a step
    // the sun's light falls by e^{−2} across each one: held at the midpoint it comes out 35 %
    // too dark; split into sub-steps it is within 2 % (1 % with every thick step split; past
    // the first step, which has 98 % of the light, `SPLIT_ABOVE` leaves them whole).
    let field = DensityField::new(block_box(IVec3::new(32, 32, 24)));
    let (sigma_t, albedo, e) = (2.0f32, 0.8f32, [1.0f32, 2.0, 4.0]);
    let shadow = ShadowVolume::build(&field, sigma_t, Vec3::Z);
    let source = SunRadiance::new([(&shadow, e)], None);
    let scene = Scene::new(&field, medium(sigma_t, albedo), &source, None);
    // Half a voxel of plateau above z = 22.5, then the face's ramp: ∫ρ = 1.
    let tau0 = sigma_t * 1.0;
    for x in [4.0f32, 13.0, 17.25] {
        let mut stats = MarchStats::default();
        let ray = march_ray(
            &scene,
            Vec3::new(x, 17.5, 22.5),
            -Vec3::Z,
            0.5,
            &MarchSettings::default(),
            &mut scene.scratch(),
            &mut stats,
        );
        for (got, e) in ray.direct.iter().zip(e) {
            let want = albedo * PHASE * e * (-tau0).exp() / 2.0;
            assert!((got / want - 1.0).abs() < 0.02, "x {x}: {got} vs {want}");
        }
        assert_eq!(ray.indirect, [0.0; 3]);
    }
}

#[test]
fn a_threads_scratch_carries_nothing_from_one_ray_to_the_next() {
    // Rays marched one after another with one scratch, as a thread marches its tiles, give
    // bit for bit what each gives with a fresh one: the caches kept (the last block, shadow brick
    // and lattice cell) only save lookups, and every ray's sums start empty.
    let field = DensityField::new(block_box(IVec3::new(32, 32, 24)));
    let shadow = ShadowVolume::build(&field, 1.0, Vec3::new(0.3, 0.2, 1.0).normalize());
    let layout = TransferLayout::build(&field.grid, 3);
    let mut nodes: Vec<[f32; 3]> = layout
        .voxels()
        .iter()
        .map(|v| [v.x as f32, v.y as f32, 1.0])
        .collect();
    nodes.push([0.0; 3]);
    let source = SunRadiance::new([(&shadow, [1.0, 2.0, 3.0])], Some((&layout, &nodes)));
    let scene = Scene::new(&field, medium(1.0, 0.8), &source, None);
    let settings = MarchSettings::default();
    let rays = [
        (Vec3::new(4.0, 17.5, 40.0), -Vec3::Z),
        (Vec3::new(4.5, 17.0, 40.0), -Vec3::Z),
        (Vec3::new(-10.0, 16.0, 12.0), Vec3::X),
        (Vec3::new(4.0, 17.5, 40.0), -Vec3::Z),
    ];
    let mut shared = scene.scratch();
    let mut stats = MarchStats::default();
    for (origin, dir) in rays {
        let kept = march_ray(&scene, origin, dir, 0.3, &settings, &mut shared, &mut stats);
        let fresh = march_ray(
            &scene,
            origin,
            dir,
            0.3,
            &settings,
            &mut scene.scratch(),
            &mut stats,
        );
        assert_eq!(kept, fresh);
        assert!(kept.direct[0] > 0.0 && kept.indirect[0] > 0.0, "{kept:?}");
    }
}

#[test]
fn a_suns_depth_along_a_step_follows_a_parabola_and_never_overshoots() {
    // Through three points of τ(s) = 0.5 + s + 2s² (a depth growing into a lit surface's ramp)
    // the parabola is τ itself; where the depth jumps (a shadow's edge between the midpoint and
    // the end) it stays within the three values.
    let exact = |s: f32| 0.5 + s + 2.0 * s * s;
    let depth = sun_depth_along(exact(0.0), exact(0.5), exact(1.0));
    for s in [0.0, 0.1, 0.25, 0.5, 0.8, 1.0] {
        assert!((depth(s) - exact(s)).abs() < 1e-5, "{s}");
    }
    let edge = sun_depth_along(0.0, 0.0, 4.0);
    for s in [0.0, 0.2, 0.4, 0.6, 0.9, 1.0] {
        assert!((0.0..=4.0).contains(&edge(s)), "{s}: {}", edge(s));
    }
    assert_eq!((edge(0.25), edge(1.0)), (0.0, 4.0));
}

#[test]
fn a_split_step_across_a_shadows_edge_reads_each_sub_steps_depth() {
    // A slab lit from straight above, its half x < 16 under an occluder eight voxels over it. A
    // thick step along x through x = 16 crosses the shadow's edge: the sun's depth falls from the
    // occluder's and the slab's to the slab's alone within the step, which no parabola through the
    // step's ends and midpoint follows, so each sub-step reads its own depth (`MAX_BEND`).
    let mut g = block_box(IVec3::new(32, 32, 24));
    for x in [0, 8] {
        for y in [0, 8, 16, 24] {
            g.insert_tile(TileLevel::Block, IVec3::new(x, y, 32), 1.0);
        }
    }
    let field = DensityField::new(g);
    let sigma_t = 2.0f32;
    let shadow = ShadowVolume::build(&field, sigma_t, Vec3::Z);
    let mut sampler = field.sampler();
    let mut cursor = ShadowCursor::default();
    let (p, span) = (Vec3::new(16.0, 16.5, 20.5), Vec3::X);
    let rho = sampler.sample(p);
    let tau = sigma_t * rho;
    let step = Step {
        p,
        span,
        rho,
        front: 1.0,
        scatter: 0.8,
        tau,
        tr: (-tau).exp(),
    };
    let mut depth_at =
        |s: f32| shadow.optical_depth(p + span * (s - 0.5), 1.0, &mut sampler, &mut cursor);
    let (start, middle, end) = (depth_at(0.0), depth_at(0.5), depth_at(1.0));
    assert!(
        (start + end - 2.0 * middle).abs() > MAX_BEND,
        "{start} {middle} {end}"
    );
    // The step's sun light summed over its sub-steps (uniform density: equal shares of τ), from
    // each sub-step's own depth, and from the parabola through the three.
    let n = (tau / MAX_STEP_DEPTH).ceil() as usize;
    let sum = |depth: &mut dyn FnMut(f32) -> f32| {
        let sub_tr = (-tau / n as f32).exp();
        let (mut tr, mut sum) = (1.0f32, 0.0f32);
        for j in 0..n {
            sum += tr * (1.0 - sub_tr) * (-depth((j as f32 + 0.5) / n as f32)).exp();
            tr *= sub_tr;
        }
        step.scatter * sum
    };
    let looked_up = sum(&mut depth_at);
    let along = sun_depth_along(start, middle, end);
    let parabola = sum(&mut |s| along(s));
    assert!(
        (parabola / looked_up - 1.0).abs() > 0.05,
        "{parabola} vs {looked_up}"
    );
    let mut track = SunTrack::default();
    let got = Split {
        step: &step,
        volume: &shadow,
        middle,
    }
    .light(&mut field.sampler(), &mut track);
    assert!((got / looked_up - 1.0).abs() < 1e-5, "{got} vs {looked_up}");
    // The next step starts where this one ended and takes the depth read there, not a lookup of
    // its own: its light is the same.
    let next = Step {
        p: p + span,
        ..step
    };
    let split = Split {
        step: &next,
        volume: &shadow,
        middle: shadow.optical_depth(next.p, 1.0, &mut sampler, &mut cursor),
    };
    assert!(track.last_end.is_some());
    let taken = split.light(&mut field.sampler(), &mut track);
    let fresh = split.light(&mut field.sampler(), &mut SunTrack::default());
    assert!((taken / fresh - 1.0).abs() < 1e-6, "{taken} vs {fresh}");
}

#[test]
fn a_surface_entry_is_marched_in_pieces() {
    // The sun behind the camera, which looks into a block's top face at an angle: the sun's depth
    // at every point is the camera's, so L = albedo·p·E·∫e^{−2τ}dτ = albedo·p·E/2 for a block
    // this thick, wherever the face's ramp falls between the steps. With one density sample per
    // step the worst of 50 jitters is 7.5 % off at one optical depth per voxel and 17 % at two;
    // with the entry in pieces, 3.7 and 3.4 %.
    let field = DensityField::new(block_box(IVec3::new(32, 32, 24)));
    let dir = Vec3::new(0.3, 0.0, 1.0).normalize();
    for sigma_t in [1.0f32, 2.0] {
        let albedo = 0.8;
        let shadow = ShadowVolume::build(&field, sigma_t, dir);
        let source = SunRadiance::new([(&shadow, [1.0; 3])], None);
        let scene = Scene::new(&field, medium(sigma_t, albedo), &source, None);
        let want = albedo * PHASE / 2.0;
        for j in 0..50 {
            let jitter = j as f32 / 50.0;
            let ray = march_ray(
                &scene,
                Vec3::new(16.0, 16.0, 40.0) + 20.0 * dir,
                -dir,
                jitter,
                &MarchSettings::default(),
                &mut scene.scratch(),
                &mut MarchStats::default(),
            );
            let got = ray.direct[0];
            assert!(
                (got / want - 1.0).abs() < 0.05,
                "σt {sigma_t}, jitter {jitter}: {got} vs {want}"
            );
        }
    }
}
