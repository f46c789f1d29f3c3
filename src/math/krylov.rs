//! Restarted GMRES (Saad and Schultz 1986) for the fixed point x = A·x + b of a linear map A known
//! only by what it does to a vector: the lattice's one generation of scattering
//! ([`crate::transfer::lattice`]). Summing generations one by one (x = b + A·b + A²·b + …)
//! converges as the largest eigenvalue of A, which in a bright medium of thin cells is close to
//! 1; GMRES minimises the residual over every combination of the vectors it has seen, so it needs
//! a fraction of the applications of A.
//!
//! Written here rather than taken from a crate: the ones found either take an assembled sparse
//! matrix (`gmres`) or bring a PETSc-like framework whose vectors are f64 (`kryst`), which would
//! double the basis this keeps in f32, the solve's largest cost in memory beside A's own links.
//! Reductions are summed in f64, in fixed chunks, so results do not depend on the thread count.

use rayon::prelude::*;

/// Elements per chunk of a parallel reduction or update: large enough to amortise a task, and
/// fixed, so every sum is added up in the same order whatever the threads.
const CHUNK: usize = 1 << 14;

/// What a solve did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Solved {
    /// Applications of A.
    pub applications: usize,
    /// ‖b − (x − A·x)‖ / ‖b‖ at the end (0 for b = 0).
    pub residual: f64,
    pub converged: bool,
}

/// Solves x = A·x + b to a relative residual `tolerance`, `restart` basis vectors at a time, with
/// at most `max_applications` calls of `apply(v, out)`, which must write A·v into `out`. Starts
/// from x = b, the first term of the generations' sum. Holds `restart` + 4 vectors as long as `b`
/// besides `b` ([`working_vectors`]).
pub fn solve_fixed_point(
    b: &[f32],
    restart: usize,
    tolerance: f64,
    max_applications: usize,
    mut apply: impl FnMut(&[f32], &mut [f32]),
) -> (Vec<f32>, Solved) {
    let restart = restart.max(1);
    let mut x = b.to_vec();
    let b_norm = dot(b, b).sqrt();
    let mut solved = Solved {
        applications: 0,
        residual: 0.0,
        converged: true,
    };
    if b_norm == 0.0 {
        return (x, solved);
    }
    let target = tolerance * b_norm;
    let mut image = vec![0f32; b.len()];
    let mut basis: Vec<Vec<f32>> = Vec::with_capacity(restart + 1);
    while solved.applications < max_applications {
        // r = b − (x − A·x).
        apply(&x, &mut image);
        solved.applications += 1;
        let mut r = b.to_vec();
        update(&mut r, |i, r| r - x[i] + image[i]);
        let beta = dot(&r, &r).sqrt();
        solved.residual = beta / b_norm;
        if beta <= target {
            return (x, solved);
        }
        scale(&mut r, 1.0 / beta);
        basis.clear();
        basis.push(r);
        // The Arnoldi process on (I − A), its Hessenberg matrix column by column, reduced to
        // triangular by Givens rotations as it grows; g is the rotated right-hand side β·e₁,
        // whose last entry is the residual norm of the best combination so far.
        let mut h: Vec<Vec<f64>> = Vec::with_capacity(restart);
        let mut rotations: Vec<(f64, f64)> = Vec::with_capacity(restart);
        let mut g = vec![beta];
        while h.len() < restart && solved.applications < max_applications {
            let k = h.len();
            apply(&basis[k], &mut image);
            solved.applications += 1;
            let mut w = basis[k].clone();
            update(&mut w, |i, v| v - image[i]);
            // Modified Gram–Schmidt against the basis so far.
            let mut column = vec![0f64; k + 2];
            for (c, v) in column.iter_mut().zip(&basis) {
                *c = dot(&w, v);
                let c = *c;
                update(&mut w, |i, wi| wi - (c * v[i] as f64) as f32);
            }
            let norm = dot(&w, &w).sqrt();
            column[k + 1] = norm;
            for (i, &(c, s)) in rotations.iter().enumerate() {
                let (a, b) = (column[i], column[i + 1]);
                column[i] = c * a + s * b;
                column[i + 1] = c * b - s * a;
            }
            let (a, b) = (column[k], column[k + 1]);
            let radius = a.hypot(b);
            let (c, s) = match radius > 0.0 {
                true => (a / radius, b / radius),
                false => (1.0, 0.0),
            };
            rotations.push((c, s));
            column[k] = radius;
            column.truncate(k + 1);
            h.push(column);
            g.push(-s * g[k]);
            g[k] *= c;
            solved.residual = g[k + 1].abs() / b_norm;
            // A basis that stops growing (norm 0) has found the exact solution in its span.
            if g[k + 1].abs() <= target || norm == 0.0 {
                break;
            }
            scale(&mut w, 1.0 / norm);
            basis.push(w);
        }
        // x += V·y, y solving the triangular system H·y = g by back substitution.
        let m = h.len();
        let mut y = vec![0f64; m];
        for i in (0..m).rev() {
            let sum: f64 = (i + 1..m).map(|j| h[j][i] * y[j]).sum();
            // A zero pivot (a map with 1 as an eigenvalue, which no absorbing medium has) adds
            // nothing rather than infinities.
            y[i] = match h[i][i] != 0.0 {
                true => (g[i] - sum) / h[i][i],
                false => 0.0,
            };
        }
        for (v, &yi) in basis.iter().zip(&y) {
            update(&mut x, |i, xi| xi + (yi * v[i] as f64) as f32);
        }
        if solved.residual * b_norm <= target {
            return (x, solved);
        }
    }
    solved.converged = false;
    (x, solved)
}

/// Vectors as long as `b` that a solve with `restart` basis vectors takes, `b` included: the basis
/// (`restart` + 1), the solution, A's image and the vector being orthogonalised.
pub fn working_vectors(restart: usize) -> usize {
    restart.max(1) + 5
}

/// Σ a·b in f64, summed chunk by chunk in a fixed order.
fn dot(a: &[f32], b: &[f32]) -> f64 {
    let partial: Vec<f64> = a
        .par_chunks(CHUNK)
        .zip(b.par_chunks(CHUNK))
        .map(|(a, b)| a.iter().zip(b).map(|(&x, &y)| x as f64 * y as f64).sum())
        .collect();
    partial.iter().sum()
}

/// v[i] = f(i, v[i]) for every i, in parallel chunks.
fn update(v: &mut [f32], f: impl Fn(usize, f32) -> f32 + Sync) {
    v.par_chunks_mut(CHUNK).enumerate().for_each(|(c, chunk)| {
        for (i, x) in chunk.iter_mut().enumerate() {
            *x = f(c * CHUNK + i, *x);
        }
    });
}

fn scale(v: &mut [f32], by: f64) {
    update(v, |_, x| (x as f64 * by) as f32);
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A = ρ·(0.6 of each value passed one place up, 0.4 one place down, lost past the ends): a
    /// non-symmetric contraction, light drifting through a slab of thin cells, whose largest
    /// eigenvalue is 2ρ·√0.24·cos(π/(n + 1)) ≈ 0.98ρ.
    fn drift(rho: f32) -> impl FnMut(&[f32], &mut [f32]) {
        move |v, out| {
            let n = v.len();
            for i in 0..n {
                let below = if i > 0 { v[i - 1] } else { 0.0 };
                let above = if i + 1 < n { v[i + 1] } else { 0.0 };
                out[i] = rho * (0.6 * below + 0.4 * above);
            }
        }
    }

    fn residual(x: &[f32], b: &[f32], mut apply: impl FnMut(&[f32], &mut [f32])) -> f64 {
        let mut ax = vec![0f32; x.len()];
        apply(x, &mut ax);
        let r: f64 = (0..x.len())
            .map(|i| (b[i] - x[i] + ax[i]) as f64)
            .map(|r| r * r)
            .sum();
        r.sqrt() / dot(b, b).sqrt()
    }

    #[test]
    fn a_contraction_is_solved_in_fewer_applications_than_its_series() {
        // 200 cells at ρ = 0.99, largest eigenvalue 0.97: the series b + A·b + … needs
        // ln(1e-5)/ln(0.97) ≈ 380 terms for 1e-5; GMRES(20) takes 225 applications. The true
        // residual of the f32 solution is near the one the rotations track (1.4e-5 against
        // 0.93e-5): f32 vectors hold about that much, plenty for a tolerance of 1e-4.
        let b: Vec<f32> = (0..200).map(|i| ((i * 37) % 11) as f32 + 1.0).collect();
        let (x, solved) = solve_fixed_point(&b, 20, 1e-5, 5000, drift(0.99));
        assert!(solved.converged, "{solved:?}");
        assert!(solved.applications < 260, "{solved:?}");
        let r = residual(&x, &b, drift(0.99));
        assert!(
            r < 5e-5,
            "true residual {r:e}, reported {}",
            solved.residual
        );
    }

    #[test]
    fn the_identity_map_is_solved_at_once_and_zero_returns_zero() {
        // A = 0: x = b, found by the first residual.
        let b = vec![1.0f32, 2.0, 3.0];
        let (x, solved) = solve_fixed_point(&b, 5, 1e-9, 10, |_, out| out.fill(0.0));
        assert_eq!((x, solved.applications), (b, 1));
        let (x, solved) = solve_fixed_point(&[0.0; 4], 5, 1e-9, 10, drift(0.5));
        assert_eq!((x, solved.applications), (vec![0.0; 4], 0));
    }

    #[test]
    fn the_budget_of_applications_is_kept() {
        let b: Vec<f32> = (0..64).map(|i| (i % 5) as f32).collect();
        let (_, solved) = solve_fixed_point(&b, 4, 1e-12, 7, drift(1.0));
        assert!(!solved.converged);
        assert_eq!(solved.applications, 7);
    }
}
