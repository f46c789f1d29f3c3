//! Tests of `lattice`.

use super::*;
use glam::Vec3;

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
}

#[test]
fn opposite_directions_pair_up() {
    let dirs = Directions::new(LatticeKind::All);
    for (j, d) in dirs.offsets.iter().enumerate() {
        assert_eq!(dirs.offsets[dirs.opposite[j]], -*d);
    }
}
