//! Point sets on the unit sphere shared by the bake's direction sets, the lattice's inflow
//! quadrature and the visibility sweep.

use glam::Vec3;

/// `n` points of the spherical Fibonacci lattice: equal-area, so each carries weight 4π/n.
pub fn fibonacci(n: usize) -> Vec<Vec3> {
    let golden = (1.0 + 5f64.sqrt()) / 2.0;
    (0..n)
        .map(|i| {
            let z = 1.0 - (2.0 * i as f64 + 1.0) / n as f64;
            let r = (1.0 - z * z).max(0.0).sqrt();
            let phi = std::f64::consts::TAU * (i as f64 / golden).fract();
            Vec3::new((r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fibonacci_points_are_unit_and_balanced() {
        let d = fibonacci(512);
        assert!(d.iter().all(|v| (v.length() - 1.0).abs() < 1e-5));
        let mean: Vec3 = d.iter().copied().sum::<Vec3>() / 512.0;
        assert!(mean.length() < 1e-3, "mean {mean}");
    }
}
