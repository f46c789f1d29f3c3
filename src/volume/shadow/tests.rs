use super::*;
use crate::volume::bricks::BrickSampler;
use crate::volume::grid::{add_hashed_leaves, block_box, Transform};

fn tile_grid(value: f32) -> SparseGrid {
    let mut g = SparseGrid::new(Transform::default(), 0.0);
    g.insert_tile(TileLevel::Node, IVec3::ZERO, value);
    g
}

/// The depth a ray march with 0.05-voxel steps finds from `p` toward `dir`: the reference.
fn marched(field: &DensityField, sigma_t: f32, p: Vec3, dir: Vec3) -> f32 {
    let v = dir * field.grid.transform.scale.as_vec3().recip();
    let step = 0.05f32;
    let mut sampler = field.sampler();
    let mut tau = 0.0;
    let mut t = 0.5 * step;
    // Far enough to leave any test grid.
    while t < 600.0 {
        tau += sigma_t * sampler.sample(p + v * t) * step;
        t += step;
    }
    tau
}

#[test]
fn a_uniform_tile_along_an_axis_has_the_exact_chord_depth() {
    // Light from +X: from voxel x the trilinear density integrates to (127 − x) + ½ (the ramp
    // to the empty voxel 128), which Simpson's rule on a linear ramp gets exactly.
    let field = DensityField::new(tile_grid(1.0));
    let sigma_t = 0.02;
    let vol = ShadowVolume::build(&field, sigma_t, Vec3::X);
    let mut r = ShadowCursor::default();
    let mut sampler = field.sampler();
    for x in [0, 5, 64, 120, 127] {
        let p = Vec3::new(x as f32, 40.0, 77.0);
        let want = sigma_t * ((127 - x) as f32 + 0.5);
        let got = vol.optical_depth(p, 1.0, &mut sampler, &mut r);
        assert!(
            (got - want).abs() < 1e-4 * want.max(1.0),
            "x {x}: {got} vs {want}"
        );
    }
    // Between voxels the depth is trilinear: halfway is the mean.
    let mid = vol.optical_depth(Vec3::new(10.5, 3.25, 9.0), 1.0, &mut sampler, &mut r);
    assert!((mid - sigma_t * 117.0).abs() < 1e-4, "{mid}");
}

#[test]
fn oblique_light_matches_a_fine_ray_march() {
    let field = DensityField::new(tile_grid(0.5));
    let sigma_t = 0.03;
    for dir in [
        Vec3::new(0.3, 0.8, -0.5),
        Vec3::new(-0.9, 0.2, 0.1),
        Vec3::new(0.577, -0.577, 0.577),
    ] {
        let dir = dir.normalize();
        let vol = ShadowVolume::build(&field, sigma_t, dir);
        let mut r = ShadowCursor::default();
        let mut sampler = field.sampler();
        for p in [
            Vec3::new(64.0, 64.0, 64.0),
            Vec3::new(3.5, 120.25, 17.0),
            Vec3::new(100.0, 10.0, 126.5),
        ] {
            let want = marched(&field, sigma_t, p, dir);
            let got = vol.optical_depth(p, 1.0, &mut sampler, &mut r);
            // Bilinear resampling per slice is exact for a uniform field; what remains is the
            // faces' ramps, crossed obliquely.
            assert!(
                (got - want).abs() < 0.01 * want + 0.01,
                "{dir} {p}: {got} vs {want}"
            );
        }
    }
}

#[test]
fn a_gap_still_carries_the_shadow_of_what_lies_beyond_it() {
    // Two 8³ tiles 40 voxels apart along +Y; the lower one sees the light only through the upper.
    let mut g = SparseGrid::new(Transform::default(), 0.0);
    g.insert_tile(TileLevel::Block, IVec3::new(0, 0, 0), 1.0);
    g.insert_tile(TileLevel::Block, IVec3::new(0, 48, 0), 1.0);
    let field = DensityField::new(g);
    let sigma_t = 0.1;
    let vol = ShadowVolume::build(&field, sigma_t, Vec3::Y);
    let mut r = ShadowCursor::default();
    let mut sampler = field.sampler();
    // From the lower tile's top voxel: ½ voxel of its own ramp, then the whole upper tile (8).
    let got = vol.optical_depth(Vec3::new(4.0, 7.0, 4.0), 1.0, &mut sampler, &mut r);
    let want = sigma_t * (0.5 + 8.0);
    assert!((got - want).abs() < 0.02 * want, "{got} vs {want}");
}

/// Three overlapping smooth blobs (peak density 2) with a hole between them, as leaves over
/// [0, 96)³: cloud-like structure at the scale of a few voxels and more.
/// The leaves of the 96³ box whose voxels `rho` makes positive, each voxel holding `rho` at its
/// centre.
fn leaves_of(rho: impl Fn(Vec3) -> f32) -> SparseGrid {
    let mut g = SparseGrid::new(Transform::default(), 0.0);
    for b in 0..12 * 12 * 12 {
        let origin = IVec3::new(b / 144, (b / 12) % 12, b % 12) * 8;
        let mut values = [0.0; crate::volume::grid::LEAF_VOXELS];
        for (i, v) in values.iter_mut().enumerate() {
            *v = rho((origin + crate::volume::grid::slot_offset(i)).as_vec3());
        }
        if values.iter().any(|v| *v > 0.0) {
            g.insert_leaf(origin, [u64::MAX; 8], values);
        }
    }
    g
}

fn blobs() -> SparseGrid {
    let centres = [
        (Vec3::new(40.0, 40.0, 40.0), 14.0),
        (Vec3::new(60.0, 55.0, 45.0), 9.0),
        (Vec3::new(30.0, 62.0, 58.0), 6.0),
    ];
    leaves_of(|p| {
        let v = centres
            .iter()
            .map(|(c, r)| 2.0 * (-(p - *c).length_squared() / (r * r)).exp())
            .sum::<f32>();
        if v < 1e-3 {
            0.0
        } else {
            v
        }
    })
}

#[test]
fn smooth_density_agrees_with_ray_marching_where_the_density_is() {
    let field = DensityField::new(blobs());
    let sigma_t = 0.15;
    let dir = Vec3::new(0.4, 0.7, 0.59).normalize();
    let vol = ShadowVolume::build(&field, sigma_t, dir);
    let mut r = ShadowCursor::default();
    let mut sampler = field.sampler();
    let (mut checked, mut worst, mut sum) = (0, 0.0f32, 0.0f32);
    for i in 0..4000u32 {
        let h = |s: u32| crate::math::hash::hash_unit(i, s, 7, 3) * 96.0;
        let p = Vec3::new(h(0), h(1), h(2));
        if sampler.sample(p) < 0.05 {
            continue;
        }
        // Compare transmittances: what the render multiplies by.
        let err = ((-vol.optical_depth(p, 1.0, &mut sampler, &mut r)).exp()
            - (-marched(&field, sigma_t, p, dir)).exp())
        .abs();
        worst = worst.max(err);
        sum += err;
        checked += 1;
    }
    assert!(checked > 300, "{checked}");
    let mean = sum / checked as f32;
    assert!(mean < 0.003 && worst < 0.02, "mean {mean}, worst {worst}");
}

#[test]
fn a_voxel_whose_line_toward_the_light_meets_no_brick_is_lit_without_a_march() {
    // Every empty voxel the test passes has depth 0 by the ray march too; and it passes most of
    // those around the blobs, so the march is kept for the ones behind them.
    let field = DensityField::new(blobs());
    let keys = keys(&field.grid);
    for dir in [
        Vec3::new(0.4, 0.7, 0.59),
        Vec3::new(-0.9, 0.2, -0.3),
        Vec3::Z,
    ] {
        let dir = dir.normalize();
        let vol = ShadowVolume::build(&field, 0.15, dir);
        let casters = Casters::new(&keys, vol.axis, vol.u);
        let (mut passed, mut zero) = (0, 0);
        for i in 0..3000u32 {
            let h = |s: u32| (crate::math::hash::hash_unit(i, s, 5, 1) * 120.0 - 12.0) as i32;
            let v = IVec3::new(h(0), h(1), h(2));
            if vol.entries.get(v >> LEAF_LOG2 as i32).is_some() {
                continue;
            }
            let depth = marched(&field, 0.15, v.as_vec3(), dir);
            zero += (depth == 0.0) as u32;
            if casters.none_toward_light(v) {
                passed += 1;
                assert_eq!(depth, 0.0, "{v} toward {dir}");
            }
        }
        assert!(passed > zero / 2 && passed > 300, "{passed} of {zero}");
    }
}

#[test]
fn the_estimate_bounds_the_built_bytes() {
    let mut g = SparseGrid::new(Transform::default(), 0.0);
    add_hashed_leaves(&mut g, 60);
    g.insert_tile(TileLevel::Node, IVec3::new(256, 0, 0), 0.3);
    let field = DensityField::new(g);
    let built = ShadowVolume::build(&field, 0.1, Vec3::Y).memory_bytes();
    let estimate = ShadowVolume::estimate_bytes(&field.grid);
    assert!(
        estimate >= built && estimate < 2 * built,
        "{estimate} vs {built}"
    );
}

#[test]
fn a_face_on_a_block_boundary_has_the_depth_of_its_ramp() {
    // A slab of 8³ tiles, voxels z ∈ [0, 23]: its top face lies on a block boundary, and the
    // trilinear density falls linearly to 0 over the voxel above it, so from a point at height
    // h ∈ [0, 1] under z = 24 the depth toward a sun overhead is σt·h²/2 (and under the plateau's
    // top, σt·(h − ½)). The same from below, through the ramp under z = 0.
    let field = DensityField::new(block_box(IVec3::splat(24)));
    let sigma_t = 1.0;
    let depth = |h: f32| sigma_t * if h <= 1.0 { h * h / 2.0 } else { h - 0.5 };
    for (light, face) in [(Vec3::Z, 24.0f32), (-Vec3::Z, -1.0)] {
        let vol = ShadowVolume::build(&field, sigma_t, light);
        let mut r = ShadowCursor::default();
        let mut sampler = field.sampler();
        for h in [0.25f32, 0.5, 0.75, 1.0, 1.5] {
            let p = Vec3::new(9.5, 13.0, face - light.z * h);
            let got = vol.optical_depth(p, 1.0, &mut sampler, &mut r);
            assert!(
                (got - depth(h)).abs() < 1e-4,
                "light {light}, h {h}: {got} vs {}",
                depth(h)
            );
        }
    }
}

#[test]
fn across_a_shadow_edge_a_lookup_walks_on_until_the_depths_agree() {
    // A block tile hangs over a slab, lit obliquely at σt 1: its shadow's edge on the slab's top
    // is a fraction of a voxel wide, and the four depths around a landing point near it can
    // differ by several optical depths. Walking on until they agree (across the empty gap and
    // through the tile) keeps the transmittance within 0.1 of a fine ray march (measured 0.08:
    // what is left is the sweep's blur of the edge); landing at once (a lookup seen through so
    // little transmittance that walking on could not show) misses it by 0.37.
    let mut g = block_box(IVec3::new(48, 16, 48));
    g.insert_tile(TileLevel::Block, IVec3::new(16, 32, 16), 1.0);
    let field = DensityField::new(g);
    let sigma_t = 1.0;
    let dir = Vec3::new(0.35, 1.0, 0.2).normalize();
    let vol = ShadowVolume::build(&field, sigma_t, dir);
    let mut r = ShadowCursor::default();
    let mut sampler = field.sampler();
    let (mut walked, mut landed) = (0.0f32, 0.0f32);
    for i in 0..200 {
        let p = Vec3::new(4.0 + 0.2 * i as f32, 15.25, 20.3);
        let want = (-marched(&field, sigma_t, p, dir)).exp();
        let light = |shown: f32, r: &mut ShadowCursor, s: &mut BrickSampler| {
            (-vol.optical_depth(p, shown, s, r)).exp()
        };
        let w1 = light(1.0, &mut r, &mut sampler);
        walked = walked.max((w1 - want).abs());
        landed = landed.max((light(1e-6, &mut r, &mut sampler) - want).abs());
    }
    assert!(walked < 0.1, "walking on: {walked}");
    assert!(
        landed > 3.0 * walked,
        "landing at once: {landed}, walking on: {walked}"
    );
}

/// A ball of density 1 and radius `r` about (48, 48, 48): a one-voxel edge from 1 to 0 that
/// curves through the slices.
fn ball(r: f32) -> SparseGrid {
    leaves_of(|p| f32::from((p - Vec3::splat(48.0)).length() < r))
}

#[test]
fn under_a_lit_face_the_walk_does_not_brighten_the_light() {
    // Points within two voxels under the lit side of a ball at one optical depth per voxel: their
    // mean light e^(−τ) from lookups against a fine ray march's. With one density sample per slice
    // of the walk it was +1.0, +0.4 and +1.7 % too bright; with two on its first two parts +0.5,
    // +0.2 and +0.8 % (`WALK_SAMPLES`).
    let field = DensityField::new(ball(20.0));
    let sigma_t = 1.0;
    for dir in [
        Vec3::new(0.5, 0.8, 0.3),
        Vec3::new(0.3, 0.2, 0.9),
        Vec3::new(-0.6, 0.3, 0.7),
    ] {
        let dir = dir.normalize();
        let vol = ShadowVolume::build(&field, sigma_t, dir);
        let (mut cursor, mut sampler) = (ShadowCursor::default(), field.sampler());
        let (mut got, mut want, mut n) = (0.0f64, 0.0f64, 0u32);
        for i in 0..20000u32 {
            let h = |s: u32| crate::math::hash::hash_unit(i, s, 9, 2) * 2.0 - 1.0;
            let normal = Vec3::new(h(0), h(1), h(2));
            if normal.length() > 1.0 || normal.normalize().dot(dir) < 0.3 {
                continue;
            }
            let p = Vec3::splat(48.0) + normal.normalize() * (19.0 + 1.5 * h(3));
            got += (-vol.optical_depth(p, 1.0, &mut sampler, &mut cursor)).exp() as f64;
            want += (-marched(&field, sigma_t, p, dir)).exp() as f64;
            n += 1;
        }
        assert!(n > 3000);
        assert!((got / want - 1.0).abs() < 0.012, "{dir}: {got} vs {want}");
    }
}

#[test]
fn after_a_deep_lookup_the_next_walks_short_and_a_new_ray_walks_in_full() {
    // Points in the ball's shadowed half: a lookup after a deep one walks to the next slice only,
    // whose depth stays within a few percent of the full walk's; `end_ray` forgets it, and the
    // lookup is the full one again, exactly.
    let field = DensityField::new(ball(20.0));
    let dir = Vec3::new(0.5, 0.8, 0.3).normalize();
    let vol = ShadowVolume::build(&field, 1.0, dir);
    let mut sampler = field.sampler();
    let (mut tested, mut shortened) = (0, 0);
    for i in 0..400u32 {
        let h = |s: u32| crate::math::hash::hash_unit(i, s, 3, 7) * 2.0 - 1.0;
        let p = Vec3::splat(48.0) - dir * 10.0 + Vec3::new(h(0), h(1), h(2)) * 6.0;
        let mut cursor = ShadowCursor::default();
        let full = vol.optical_depth(p, 1.0, &mut sampler, &mut cursor);
        if full <= DEEP_DEPTH {
            continue;
        }
        tested += 1;
        let short = vol.optical_depth(p, 1.0, &mut sampler, &mut cursor);
        assert!((short / full - 1.0).abs() < 0.05, "{p}: {short} vs {full}");
        shortened += (short != full) as u32;
        cursor.end_ray();
        assert_eq!(vol.optical_depth(p, 1.0, &mut sampler, &mut cursor), full);
    }
    assert!(
        tested > 300 && shortened > tested / 2,
        "{shortened} of {tested}"
    );
}
