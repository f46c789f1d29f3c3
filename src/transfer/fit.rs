//! Node values of T_ri fitted to what the renderer does with them: least squares over the density.
//!
//! The renderer reads a transfer voxel's radiance between nodes K voxels apart with the
//! transfer's [`Basis`] (trilinearly, below; a transfer baked finer as quadratic B-splines, the
//! same sums with that basis's functions as w_n), and only where there is density. A node's
//! *point* value T_ri(x_n, ω) is the wrong thing to interpolate across a thin structure: along
//! each direction T_ri = e^{−τ} bends with the path length through the medium, so the straight
//! line between two nodes lies far above it, and a node in the empty apron next to a tube sees
//! the environment almost unshadowed while the tube it lights does not. Measured against the
//! path tracer (torus, σt 0.08, K = 6, single scattering) the point values were +4.7 % too
//! bright on average even with geometric interpolation of the brightness, which corrects the sum
//! over directions but not each one.
//!
//! So the stored values L_n minimise the density-weighted squared error of the interpolant,
//! Σ_p ρ(p)·|Σ_n w_n(p)·L_n − T_ri(p)|² over the points p of a [`Quadrature`] (ρ trilinear, as
//! the renderer samples it), w_n the trilinear weights — the error the march makes, sample by
//! sample — plus a pull toward each node's footprint mean ([`FIT_REGULARISATION`]). The normal
//! equations are (M + λ·S)·L = (1 + λ)·b with M_nm = Σ_p ρ w_n w_m (a 27-point stencil, 125 for
//! the B-spline, the same for every SH coefficient), S the diagonal of S_n = Σ_p ρ w_n and
//! b_n = Σ_p ρ w_n T_ri(p) = S_n·t̄_n, t̄_n the mean of T_ri over the distribution ρ·w_n. `single`
//! estimates t̄_n with the same number of rays as a point value: each direction draws its own
//! point of that distribution ([`spread_starts`]) and averages T_ri along the footprint's chord
//! through it in that direction.
//!
//! Nodes whose footprint holds no density (S_n = 0) never reach a rendered sample: they keep the
//! value they were given. The system is solved by Jacobi-preconditioned conjugate gradients.

use glam::{IVec3, Vec3};
use rand::{Rng, SeedableRng};
use rayon::prelude::*;

use super::basis::{Basis, MAX_EDGE};
use super::layout::TransferLayout;
use crate::volume::grid::{Block, Leaf, LEAF_LOG2};
use crate::volume::visibility::{from_stored, VisibilitySampler};
use crate::volume::SparseGrid;

/// Conjugate-gradient iterations. The mass matrix of trilinear hats is well conditioned (its
/// eigenvalues lie within a factor 27 of each other where the density is full); measured on the
/// torus and cloud, the images stop changing after 5 iterations and 20 agree with 50.
const CG_ITERATIONS: usize = 20;

/// How strongly the fit is pulled toward each node's footprint mean: λ in
/// min Σ_p ρ(p)·|Σ_n w_n(p)·L_n − T_ri(p)|² + λ·Σ_n S_n·|L_n − t̄_n|², S_n = Σ_p ρ w_n.
///
/// Least squares amplifies the footprint means' Monte Carlo noise (a checkerboard 33× at K = 4,
/// white noise about 2.6× per node), and a node whose footprint holds only the fringe of a
/// surface, or density only where its weight equals a neighbour's, is barely determined at all:
/// such nodes ran off to values that lit pixels many times too bright (at `--scale 3`, the torus
/// at σt 0.368 was 171 % off the path tracer). The pull bounds the amplification by about
/// (1 + λ)/λ. Measured (studio, single scattering, 256×144, against the path tracer), λ 0 / 0.05 /
/// 0.1 / 0.2 / 0.3: the torus at 1.92 optical depths per transfer voxel 25.8 / 12.0 / 9.0 / 9.8 /
/// 12.0 % (bias +15.2 / +5.1 / +0.9 / −3.9 / −6.6 %), the cloud at σt 1 45.1 / 21.0 / 14.8 / 18.1
/// / 23.7 %. A multiple-scattering transfer's image holds the fitted T_ri only as its share
/// 1 − albedo (F_ms holds albedo × (point − fitted)): the cloud at σt 1 was 22.8 % off before the
/// fit summed over the fringe and was pulled, 23.4 % after.
pub const FIT_REGULARISATION: f64 = 0.1;

/// The points the fit sums over around a node: the (2R)³ midpoints between voxel centres in the
/// support of its function w_n ([`Basis`]; R its [`Basis::reach`], K for the tent), at offsets
/// −R + ½ + j (j < 2R) voxels from the node, listed
/// in Z-order so that points near each other in the list are near each other in space
/// ([`spread_starts`]). The trilinear density there is the mean of the eight voxels around, so the
/// sums reach the fringe one voxel past the last active voxel, which the renderer samples and a
/// camera sees most of at a dense medium's silhouette: summed at voxel centres the fit never saw
/// it and lit it too dark. Measured (studio, single scattering, 256×144, against the path tracer):
/// the torus at 1.92 optical depths per transfer voxel 9.9 → 9.0 % (bias −4.3 → +0.9 %), the
/// cloud at σt 1 18.9 → 14.8 % (−10.9 → +0.3 %), for the same bake time; two points per voxel
/// edge gave 8.3 and 14.9 % for 30–45 % more bake on torus300.
pub struct Quadrature {
    k: i32,
    basis: Basis,
    /// Half the footprint's width, in voxels ([`Basis::reach`]).
    reach: i32,
    n: usize,
    /// Per axis, point j's offset from the node, its factor of w_n, and the nodes it reads.
    axis: Vec<AxisPoint>,
    /// The points' coordinates (j per axis), in Z-order.
    order: Vec<[u8; 3]>,
}

/// One axis of a [`Quadrature`]: a point's offset from the node (voxels), its factor of the
/// node's function, and the nodes it reads along the axis.
#[derive(Clone, Copy)]
struct AxisPoint {
    offset: f32,
    weight: f32,
    /// In node spacings from the node, the first node the point reads, and the weights of it
    /// and the next ones ([`Basis::window`]).
    first: i32,
    weights: [f64; MAX_EDGE],
}

impl Quadrature {
    pub fn new(k: i32, basis: Basis) -> Quadrature {
        let reach = basis.reach(k);
        let n = (2 * reach) as usize;
        let axis = (0..n)
            .map(|j| {
                let offset = -reach as f32 + j as f32 + 0.5;
                let (first, weights) = basis.window(Vec3::splat(offset / k as f32));
                AxisPoint {
                    offset,
                    weight: basis.along(offset / k as f32),
                    first: first.x,
                    weights: weights.map(|w| w.x as f64),
                }
            })
            .collect();
        // n ≤ 2·MAX_SCALE = 128: a byte and Z-order's 10 bits hold it.
        let mut keyed: Vec<(u32, [u8; 3])> = Vec::with_capacity(n * n * n);
        for x in 0..n {
            for y in 0..n {
                for z in 0..n {
                    let key = morton3(IVec3::new(x as i32, y as i32, z as i32));
                    keyed.push((key, [x as u8, y as u8, z as u8]));
                }
            }
        }
        keyed.sort_unstable();
        Quadrature {
            k,
            basis,
            reach,
            n,
            axis,
            order: keyed.into_iter().map(|(_, p)| p).collect(),
        }
    }

    /// Offset from the node, in voxels, of the point at `j`.
    fn offset(&self, j: [u8; 3]) -> Vec3 {
        Vec3::new(
            self.axis[j[0] as usize].offset,
            self.axis[j[1] as usize].offset,
            self.axis[j[2] as usize].offset,
        )
    }

    /// The node's function w_n at the point at `j`.
    fn weight(&self, j: [u8; 3]) -> f32 {
        self.axis[j[0] as usize].weight
            * self.axis[j[1] as usize].weight
            * self.axis[j[2] as usize].weight
    }

    /// Index of the point at `j` in [`Self::values`].
    fn flat(&self, j: [u8; 3]) -> usize {
        (j[0] as usize * self.n + j[1] as usize) * self.n + j[2] as usize
    }

    /// The trilinear values of `grid` at every point around node `v`, by flat index: the voxels of
    /// the cube −R..=R around the node read a block at a time, then, since point j of an axis lies
    /// midway between voxels j and j + 1 of the cube, averaged in pairs one axis after another.
    fn values(&self, grid: &SparseGrid, v: IVec3) -> Vec<f32> {
        self.values_of(grid, v, |x| x)
    }

    /// [`Self::values`] of `map` applied to every voxel of `grid`.
    fn values_of(&self, grid: &SparseGrid, v: IVec3, map: impl Fn(f32) -> f32) -> Vec<f32> {
        let (k, r) = (self.k, self.reach);
        let (n, m) = (self.n, self.n + 1);
        let lo = v * k - r;
        let mut cube = vec![0f32; m * m * m];
        let (first, last) = (lo >> LEAF_LOG2, (lo + 2 * r) >> LEAF_LOG2);
        for bx in first.x..=last.x {
            for by in first.y..=last.y {
                for bz in first.z..=last.z {
                    let key = IVec3::new(bx, by, bz);
                    let block = grid.block(key);
                    let b_lo = (key << LEAF_LOG2).max(lo) - lo;
                    let b_hi = (((key + 1) << LEAF_LOG2) - 1).min(lo + 2 * r) - lo;
                    for x in b_lo.x..=b_hi.x {
                        for y in b_lo.y..=b_hi.y {
                            for z in b_lo.z..=b_hi.z {
                                let at = (x as usize * m + y as usize) * m + z as usize;
                                cube[at] = map(match block {
                                    Block::Leaf(leaf) => {
                                        leaf.values.get(Leaf::slot(lo + IVec3::new(x, y, z)))
                                    }
                                    Block::Constant(c) => c,
                                });
                            }
                        }
                    }
                }
            }
        }
        // m³ voxels → n·m² → n²·m → n³ points.
        let mut ax = vec![0f32; n * m * m];
        for (j, row) in ax.chunks_exact_mut(m * m).enumerate() {
            let (a, b) = (
                &cube[j * m * m..][..m * m],
                &cube[(j + 1) * m * m..][..m * m],
            );
            row.iter_mut()
                .zip(a.iter().zip(b))
                .for_each(|(o, (a, b))| *o = 0.5 * (a + b));
        }
        let mut ay = vec![0f32; n * n * m];
        for (xj, row) in ay.chunks_exact_mut(m).enumerate() {
            let (x, j) = (xj / n, xj % n);
            let (a, b) = (&ax[(x * m + j) * m..][..m], &ax[(x * m + j + 1) * m..][..m]);
            row.iter_mut()
                .zip(a.iter().zip(b))
                .for_each(|(o, (a, b))| *o = 0.5 * (a + b));
        }
        let mut out = vec![0f32; n * n * n];
        for (row, a) in out.chunks_exact_mut(n).zip(ay.chunks_exact(m)) {
            for (j, o) in row.iter_mut().enumerate() {
                *o = 0.5 * (a[j] + a[j + 1]);
            }
        }
        out
    }

    /// The points around node `v` with positive ρ·w_n, in Z-order: their coordinates, and the
    /// cumulative ρ·w_n.
    fn footprint(&self, density: &SparseGrid, v: IVec3) -> (Vec<[u8; 3]>, Vec<f64>) {
        let rho = self.values(density, v);
        let (mut points, mut cumulative, mut total) = (Vec::new(), Vec::new(), 0.0);
        for &j in &self.order {
            let r = rho[self.flat(j)];
            if r > 0.0 {
                total += (r * self.weight(j)) as f64;
                points.push(j);
                cumulative.push(total);
            }
        }
        (points, cumulative)
    }
}

/// Interleaves the bits of three 10-bit coordinates: a Z-order (Morton) key.
fn morton3(o: IVec3) -> u32 {
    // Spreads the low 10 bits of `v` two zeros apart (the usual magic-number shifts): a few
    // instructions instead of a loop over the bits, since every node sorts its footprint by it.
    fn spread(v: i32) -> u32 {
        let mut x = v as u32 & 0x3ff;
        x = (x | (x << 16)) & 0x0300_00ff;
        x = (x | (x << 8)) & 0x0300_f00f;
        x = (x | (x << 4)) & 0x030c_30c3;
        (x | (x << 2)) & 0x0924_9249
    }
    spread(o.x) << 2 | spread(o.y) << 1 | spread(o.z)
}

/// A Z-order key of a unit direction over the octahedral map, so that nearby directions have
/// nearby keys.
fn direction_key(d: Vec3) -> u32 {
    let l1 = d.x.abs() + d.y.abs() + d.z.abs();
    let (mut u, mut w) = (d.x / l1, d.y / l1);
    if d.z < 0.0 {
        (u, w) = ((1.0 - w.abs()) * u.signum(), (1.0 - u.abs()) * w.signum());
    }
    let q = |t: f32| (((t * 0.5 + 0.5) * 1023.0) as i32).clamp(0, 1023);
    morton3(IVec3::new(q(u), q(w), 0))
}

/// The smallest importance g a point is drawn with ([`importance`]): deep under a thick surface V
/// falls to nothing (f16 keeps it to 6·10⁻⁸), and a point no draw could reach, or a chord whose
/// ∫ρ·w·g vanished, would break the estimate; at 10⁻⁶ of a lit point's share such points are
/// still drawn, rarely.
const MIN_IMPORTANCE: f32 = 1e-6;

/// The importance g of index point `p` (density `rho`) for drawing T_ri's starts: the density's
/// visibility V there, the mean of T_ri over all directions, so draws go where light gets in.
pub fn importance(visibility: &mut VisibilitySampler, p: Vec3, rho: f32) -> f32 {
    visibility.at(p, rho).unwrap_or(0.0).max(MIN_IMPORTANCE)
}

/// Where a node's rays start ([`spread_starts`]).
pub struct Starts {
    /// One index point per direction.
    pub points: Vec<Vec3>,
    /// Σ ρ·w_n·g / Σ ρ·w_n over the footprint (1 without importance): a chord's
    /// ∫ρ·w_n·T / ∫ρ·w_n·g times this estimates t̄_n.
    pub mean_importance: f32,
}

/// Ray origins for the directions `dirs` of node `v`: one point per direction, drawn from ρ·w_n
/// over the `quadrature`'s points, or, with the density's visibility, from ρ·w_n·g
/// ([`importance`]).
/// The chord along a direction through its point is then drawn in proportion to the chord's own
/// ∫ρ·w_n·g, so ∫ρ·w_n·T / ∫ρ·w_n·g over it, times [`Starts::mean_importance`], estimates t̄_n
/// without bias. Drawn by ρ·w_n alone, a thick footprint's rays mostly start where no light
/// reaches and the few near its lit face carry the whole mean: two bake seeds of the cloud at
/// σt 1 under the studio map are then 16 % apart in the `--single-scatter` image; drawn by V, 6 %
/// ([docs/accuracy.md](../../docs/accuracy.md#soft-light-the-fit)). `None` when the footprint
/// holds no density.
///
/// Stratified jointly in position and direction: a bright light covers only a handful of the
/// directions, and independent random points would leave its light at the mercy of a few draws
/// (measured: 4.7 % error on the torus under the studio lights, 4.3 % stratified). Directions are
/// ranked along a Z-order curve of the sphere, the quadrature points along a Z-order curve of the
/// footprint, and rank r takes the radical inverse of r (randomly shifted) in the cumulative
/// weight: any 2ʲ directions in a row — a patch of the sphere — get 2ʲ points spread over the
/// footprint.
pub fn spread_starts(
    density: &SparseGrid,
    quadrature: &Quadrature,
    v: IVec3,
    dirs: &[Vec3],
    seed: u64,
    visibility: Option<&mut VisibilitySampler>,
) -> Option<Starts> {
    let (points, mut cumulative) = quadrature.footprint(density, v);
    let mass = *cumulative.last()?;
    let centre = (v * quadrature.k).as_vec3();
    if let Some(visibility) = visibility {
        let rho = quadrature.values(density, v);
        let mut sum = 0.0f64;
        for (c, &j) in cumulative.iter_mut().zip(&points) {
            let r = rho[quadrature.flat(j)];
            let g = importance(visibility, centre + quadrature.offset(j), r);
            sum += (r * quadrature.weight(j) * g) as f64;
            *c = sum;
        }
    }
    let total = *cumulative.last()?;
    let mut ranks: Vec<usize> = (0..dirs.len()).collect();
    ranks.sort_by_cached_key(|&i| direction_key(dirs[i]));
    let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(super::single::voxel_hash(v, seed));
    let shift: f64 = rng.random();
    let mut starts = vec![centre; dirs.len()];
    for (r, &d) in ranks.iter().enumerate() {
        let radical_inverse = (r as u32).reverse_bits() as f64 / 2f64.powi(32);
        let u = (radical_inverse + shift).fract() * total;
        let i = cumulative.partition_point(|&c| c < u).min(points.len() - 1);
        // Uniform within the point's cell: the density is continuous, its samples are not points.
        let jitter = Vec3::new(rng.random(), rng.random(), rng.random()) - 0.5;
        starts[d] = centre + quadrature.offset(points[i]) + jitter;
    }
    Some(Starts {
        points: starts,
        mean_importance: (total / mass) as f32,
    })
}

/// Entries of a node's mass-matrix row under `basis`: the nodes whose functions overlap its own,
/// itself and the 26 around it for the tent, the 5³ within two nodes for the B-spline.
pub const fn stencil(basis: Basis) -> usize {
    let width = 2 * basis.edge() - 1;
    width * width * width
}

/// Bytes per node of the fit's mass-matrix row under `basis` ([`Row`]).
pub const fn row_bytes(basis: Basis) -> u64 {
    (16 + stencil(basis) * (4 + 8)) as u64
}

/// One node's row of the mass matrix: S_n and the M_nm toward its stencil neighbours m
/// ([`stencil`]: at most `S`), the `len` that exist and have weight first. Fixed arrays, not a
/// list per row: a million rows allocated one by one stayed in the allocator's heap after the fit
/// and under every later phase of a bake.
struct Row<const S: usize> {
    mass: f64,
    len: usize,
    nodes: [u32; S],
    weights: [f64; S],
}

impl<const S: usize> Row<S> {
    /// The (slot, M_nm) entries, in stencil order.
    fn entries(&self) -> impl Iterator<Item = (u32, f64)> + '_ {
        self.nodes[..self.len]
            .iter()
            .zip(&self.weights[..self.len])
            .map(|(m, a)| (*m, *a))
    }

    /// The row of node `v`: M_nm = Σ_p ρ·w_n·w_m over the points p of its footprint, w_m the
    /// weights the point reads its nodes with ([`Basis::window`]).
    fn new(
        density: &SparseGrid,
        layout: &TransferLayout,
        quadrature: &Quadrature,
        v: IVec3,
    ) -> Self {
        let (edge, reach) = (quadrature.basis.edge(), quadrature.basis.edge() as i32 - 1);
        let width = 2 * reach + 1;
        debug_assert_eq!((width * width * width) as usize, S);
        let at = |d: IVec3| ((d.x + reach) * width + d.y + reach) * width + d.z + reach;
        let (points, cumulative) = quadrature.footprint(density, v);
        let mut stencil = [0f64; S];
        let mut previous = 0.0;
        for (&j, c) in points.iter().zip(&cumulative) {
            let weight = c - previous; // ρ·w_n of this point
            previous = *c;
            let [x, y, z] = j.map(|j| quadrature.axis[j as usize]);
            let first = IVec3::new(x.first, y.first, z.first);
            for (i, wx) in x.weights[..edge].iter().enumerate() {
                for (j, wy) in y.weights[..edge].iter().enumerate() {
                    for (k, wz) in z.weights[..edge].iter().enumerate() {
                        let wm = wx * wy * wz;
                        if wm > 0.0 {
                            let d = first + IVec3::new(i as i32, j as i32, k as i32);
                            stencil[at(d) as usize] += weight * wm;
                        }
                    }
                }
            }
        }
        let (mut nodes, mut weights, mut len) = ([0; S], [0.0; S], 0);
        for (i, m) in stencil.into_iter().enumerate() {
            let i = i as i32;
            let d = IVec3::new(i / (width * width), (i / width) % width, i % width) - reach;
            if let (true, Some(s)) = (m > 0.0, layout.slot(v + d)) {
                (nodes[len], weights[len]) = (s as u32, m);
                len += 1;
            }
        }
        Row {
            mass: previous,
            len,
            nodes,
            weights,
        }
    }
}

/// Least-squares node values of the visibility V kept as `kept` (on the density's topology, as
/// [`crate::volume::visibility::Visibility`] keeps it), fitted as a single-scattering transfer's
/// T_ri is: each node's footprint mean of V over ρ·w_n, exact from the quadrature's points (V
/// read there as the renderer reads it), then [`least_squares`] with [`FIT_REGULARISATION`].
pub fn fitted_visibility(
    density: &SparseGrid,
    layout: &TransferLayout,
    kept: &SparseGrid,
) -> Vec<f32> {
    let quadrature = Quadrature::new(layout.k, Basis::Tent);
    let mut means: Vec<f32> = layout
        .voxels()
        .par_iter()
        .map(|v| {
            let (points, cumulative) = quadrature.footprint(density, *v);
            let mass = cumulative.last().copied().unwrap_or(0.0);
            if mass <= 0.0 {
                return 0.0;
            }
            let rho = quadrature.values(density, *v);
            let sum = quadrature.values(kept, *v);
            // The corners a point's V is read over: where the density is above 0 (`stored`).
            let cover = quadrature.values_of(density, *v, |r| (r > 0.0) as u8 as f32);
            let total: f64 = points
                .iter()
                .map(|&j| {
                    // A footprint point has ρ > 0, so a corner above 0 and cover > 0.
                    let i = quadrature.flat(j);
                    (quadrature.weight(j) * rho[i] * from_stored(sum[i], cover[i])) as f64
                })
                .sum();
            (total / mass) as f32
        })
        .collect();
    least_squares(
        density,
        layout,
        Basis::Tent,
        &mut means,
        1,
        FIT_REGULARISATION,
    );
    means
}

/// Least-squares node values for `basis` of fields given at the nodes of a finer layout `fine`
/// (each `fine.len() × coeffs` point values, read trilinearly between them), fitted as T_ri is:
/// each node's footprint mean of a field over ρ·w_n, exact from the quadrature's points, then
/// [`least_squares`] pulled by `lambda`. The light baked on cells finer than the transfer's comes
/// back to the transfer's nodes this way, so that their read-out matches it where the density is
/// ([`crate::transfer::refine`]).
///
/// A node's mean is Σ_b G_b·F_b over the fine nodes b around it, G_b = Σ_p ρ·w_n·u_b(p) with u_b
/// the fine nodes' trilinear weights: gathered once per point for every field's coefficients,
/// which are fitted side by side, so the mass matrix is built once.
pub fn fitted_from_finer<const F: usize>(
    density: &SparseGrid,
    layout: &TransferLayout,
    basis: Basis,
    fine: &TransferLayout,
    fields: [(&[f32], usize); F],
    lambda: f64,
) -> [Vec<f32>; F] {
    let coeffs: usize = fields.iter().map(|f| f.1).sum();
    let quadrature = Quadrature::new(layout.k, basis);
    let (k, kf) = (layout.k, fine.k);
    let mut means: Vec<f32> = layout
        .voxels()
        .par_iter()
        .flat_map_iter(|&v| {
            let mut mean = vec![0f32; coeffs];
            let (points, cumulative) = quadrature.footprint(density, v);
            let mass = cumulative.last().copied().unwrap_or(0.0);
            if mass <= 0.0 {
                return mean.into_iter();
            }
            // Per axis and point, the fine cell below it (from the box's low corner) and the
            // fraction across it: point j lies at K·v + offset_j, fine node b at K_f·b.
            let place = |a: usize, j: usize| {
                let x = (v[a] * k) as f64 + quadrature.axis[j].offset as f64;
                let q = x / kf as f64;
                (q.floor() as i32, q - q.floor())
            };
            let low = IVec3::from_array(std::array::from_fn(|a| place(a, 0).0));
            let high = IVec3::from_array(std::array::from_fn(|a| place(a, quadrature.n - 1).0 + 1));
            let dim = (high - low + 1).as_uvec3();
            let at = |b: IVec3| {
                let l = (b - low).as_uvec3();
                ((l.x * dim.y + l.y) * dim.z + l.z) as usize
            };
            let axes: [Vec<(i32, f64)>; 3] =
                std::array::from_fn(|a| (0..quadrature.n).map(|j| place(a, j)).collect());
            let mut gathered = vec![0f64; (dim.x * dim.y * dim.z) as usize];
            let mut previous = 0.0;
            for (&j, c) in points.iter().zip(&cumulative) {
                let weight = c - previous; // ρ·w_n of this point
                previous = *c;
                let [x, y, z] = [0, 1, 2].map(|a| axes[a][j[a] as usize]);
                let cell = IVec3::new(x.0, y.0, z.0);
                for n in 0..8 {
                    let corner = crate::volume::grid::corner(n);
                    let w = |bit: i32, f: f64| if bit == 1 { f } else { 1.0 - f };
                    let u = w(corner.x, x.1) * w(corner.y, y.1) * w(corner.z, z.1);
                    gathered[at(cell + corner)] += weight * u;
                }
            }
            let mut sum = vec![0f64; coeffs];
            for x in low.x..=high.x {
                for y in low.y..=high.y {
                    for z in low.z..=high.z {
                        let b = IVec3::new(x, y, z);
                        let g = gathered[at(b)];
                        if let (true, Some(slot)) = (g > 0.0, fine.slot(b)) {
                            let f = fields
                                .iter()
                                .flat_map(|(values, c)| &values[slot * c..][..*c]);
                            sum.iter_mut().zip(f).for_each(|(s, f)| *s += g * *f as f64);
                        }
                    }
                }
            }
            mean.iter_mut()
                .zip(&sum)
                .for_each(|(m, s)| *m = (s / mass) as f32);
            mean.into_iter()
        })
        .collect();
    least_squares(density, layout, basis, &mut means, coeffs, lambda);
    // Each field's columns apart again.
    let mut first = 0;
    fields.map(|(_, c)| {
        let columns = first..first + c;
        first += c;
        means
            .chunks_exact(coeffs)
            .flat_map(|node| &node[columns.clone()])
            .copied()
            .collect()
    })
}

/// Least-squares node values for `basis` from the footprint means `means` (`layout.len() ×
/// coeffs`, t̄_n per node over ρ·w_n of that basis; nodes without density keep theirs), in place,
/// pulled toward the means by `lambda` (λ of [`FIT_REGULARISATION`]; 0: plain least squares).
pub fn least_squares(
    density: &SparseGrid,
    layout: &TransferLayout,
    basis: Basis,
    means: &mut [f32],
    coeffs: usize,
    lambda: f64,
) {
    const TENT: usize = stencil(Basis::Tent);
    const QUADRATIC: usize = stencil(Basis::Quadratic);
    const TENT_BLOCK: usize = block(Basis::Tent);
    const QUADRATIC_BLOCK: usize = block(Basis::Quadratic);
    match basis {
        Basis::Tent => solve::<TENT, TENT_BLOCK>(density, layout, basis, means, coeffs, lambda),
        Basis::Quadratic => {
            solve::<QUADRATIC, QUADRATIC_BLOCK>(density, layout, basis, means, coeffs, lambda)
        }
    }
}

/// Columns (SH coefficients) the fit solves together under `basis`: the mass matrix's rows are
/// read once per block of them in each iteration, not once per column, and the block's vectors
/// take as many times one column's memory. The B-spline's rows of 125 entries make its fit
/// bound by reading them: baking the bench cloud at σt 1.6 (its fit back on B-spline rows),
/// blocks of 1 / 4 / 8 / 16 columns took 15.4 / 10.8 / 9.9 / 12.5 s. The tent's rows of 27 are
/// read in a quarter of the time, and its fits are the large ones (footprint means over every
/// transfer voxel of a bake), so it solves two columns at a time.
pub const fn block(basis: Basis) -> usize {
    match basis {
        Basis::Tent => 2,
        Basis::Quadratic => 8,
    }
}

/// Bytes per node of the conjugate-gradient solve of one block of columns under `basis`
/// ([`block`]): four f64 vectors per column.
pub const fn solve_bytes(basis: Basis) -> u64 {
    (4 * 8 * block(basis)) as u64
}

/// [`least_squares`] with rows of `S` entries ([`stencil`] of `basis`), `B` columns at a time.
fn solve<const S: usize, const B: usize>(
    density: &SparseGrid,
    layout: &TransferLayout,
    basis: Basis,
    means: &mut [f32],
    coeffs: usize,
    lambda: f64,
) {
    let quadrature = Quadrature::new(layout.k, basis);
    let rows: Vec<Row<S>> = layout
        .voxels()
        .par_iter()
        .map(|v| Row::new(density, layout, &quadrature, *v))
        .collect();
    let n = rows.len();
    let free: Vec<bool> = rows.iter().map(|r| r.mass > 0.0).collect();
    // The Jacobi preconditioner, 0 on the fixed nodes so that they stay out of the search.
    let inverse_diagonal: Vec<f64> = rows
        .iter()
        .enumerate()
        .map(|(s, r)| match free[s] {
            true => {
                let m = r.entries().find(|e| e.0 as usize == s).map_or(1.0, |e| e.1);
                1.0 / (m + lambda * r.mass)
            }
            false => 0.0,
        })
        .collect();
    // y = (M + λ·S)·x over the free nodes, S the diagonal of the nodes' masses, for a block of
    // columns at once: a row is read once for all of them.
    let apply = |x: &[[f64; B]], y: &mut [[f64; B]]| {
        for (s, (yi, r)) in y.iter_mut().zip(&rows).enumerate() {
            *yi = [0.0; B];
            if free[s] {
                for (m, a) in r.entries() {
                    for (y, x) in yi.iter_mut().zip(&x[m as usize]) {
                        *y += a * x;
                    }
                }
                for (y, x) in yi.iter_mut().zip(&x[s]) {
                    *y += lambda * r.mass * x;
                }
            }
        }
    };
    let preconditioned = |s: usize| inverse_diagonal[s];
    // Each block of columns is read from `means` when its solve starts and written back when it
    // ends (under a lock, one block's copy), so the fit holds the blocks in flight, not a second
    // copy of every coefficient in f64.
    let means = std::sync::Mutex::new(means);
    let blocks: Vec<std::ops::Range<usize>> = (0..coeffs)
        .step_by(B)
        .map(|c| c..(c + B).min(coeffs))
        .collect();
    blocks.into_par_iter().for_each(|columns| {
        let column = |values: &[f32], s: usize| -> [f64; B] {
            std::array::from_fn(|l| match columns.start + l < columns.end {
                true => values[s * coeffs + columns.start + l] as f64,
                false => 0.0,
            })
        };
        // x: a free node's value, starting from its mean (already close, as the mass matrix is
        // diagonally dominant); `fixed`: a fixed node's, entering the free rows' equations as
        // known values.
        let (mut x, mut residual) = {
            let means = means.lock().unwrap_or_else(|e| e.into_inner());
            let x: Vec<[f64; B]> = (0..n).map(|s| column(&means, s)).collect();
            (x, vec![[0.0; B]; n])
        };
        // r = (1 + λ)·S·mean − (M + λ·S)·x over the free rows, x holding the fixed nodes too;
        // then the fixed nodes leave x, and their part of the products stays in r.
        apply(&x, &mut residual);
        for (s, r) in residual.iter_mut().enumerate() {
            for (r, x) in r.iter_mut().zip(&x[s]) {
                *r = match free[s] {
                    true => (1.0 + lambda) * rows[s].mass * x - *r,
                    false => 0.0,
                };
            }
        }
        for (s, x) in x.iter_mut().enumerate() {
            if !free[s] {
                *x = [0.0; B];
            }
        }
        // z = D⁻¹·r is read as it is needed, not kept.
        let mut p: Vec<[f64; B]> = residual
            .iter()
            .enumerate()
            .map(|(s, r)| r.map(|r| r * inverse_diagonal[s]))
            .collect();
        let mut rz = dot(&residual, &residual, preconditioned);
        let mut ap = vec![[0.0; B]; n];
        // A column stops where its search runs out (p·Ap or r·z no longer positive).
        let mut running = [true; B];
        for _ in 0..CG_ITERATIONS {
            apply(&p, &mut ap);
            let pap = dot(&p, &ap, |_| 1.0);
            let alpha: [f64; B] = std::array::from_fn(|l| {
                running[l] &= pap[l] > 0.0 && rz[l] > 0.0;
                if running[l] {
                    rz[l] / pap[l]
                } else {
                    0.0
                }
            });
            if !running.contains(&true) {
                break;
            }
            for s in 0..n {
                for l in 0..B {
                    x[s][l] += alpha[l] * p[s][l];
                    residual[s][l] -= alpha[l] * ap[s][l];
                }
            }
            let rz_next = dot(&residual, &residual, preconditioned);
            let beta: [f64; B] = std::array::from_fn(|l| match running[l] {
                true => rz_next[l] / rz[l],
                false => 0.0,
            });
            rz = rz_next;
            for (s, (p, r)) in p.iter_mut().zip(&residual).enumerate() {
                for l in 0..B {
                    p[l] = r[l] * inverse_diagonal[s] + beta[l] * p[l];
                }
            }
        }
        let mut means = means.lock().unwrap_or_else(|e| e.into_inner());
        for (s, x) in x.iter().enumerate().filter(|(s, _)| free[*s]) {
            for (l, c) in columns.clone().enumerate() {
                means[s * coeffs + c] = x[l] as f32;
            }
        }
    });
}

/// Σ_s a·b·weight(s) per column of a block.
#[inline]
fn dot<const B: usize>(a: &[[f64; B]], b: &[[f64; B]], weight: impl Fn(usize) -> f64) -> [f64; B] {
    let mut sum = [0.0; B];
    for (s, (a, b)) in a.iter().zip(b).enumerate() {
        let w = weight(s);
        for ((sum, a), b) in sum.iter_mut().zip(a).zip(b) {
            *sum += a * b * w;
        }
    }
    sum
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn morton_interleaves_bits() {
        assert_eq!(morton3(IVec3::new(1, 0, 0)), 0b100);
        assert_eq!(morton3(IVec3::new(0, 1, 0)), 0b010);
        assert_eq!(morton3(IVec3::new(0, 0, 1)), 0b001);
        assert_eq!(morton3(IVec3::new(3, 0, 0)), 0b100_100);
        assert_eq!(morton3(IVec3::splat(1023)), (1 << 30) - 1);
        // Only the low 10 bits count.
        assert_eq!(
            morton3(IVec3::new(1024 + 5, 0, 0)),
            morton3(IVec3::new(5, 0, 0))
        );
    }
    use crate::volume::grid::TileLevel;

    #[test]
    fn a_field_the_interpolant_can_hold_is_fitted_exactly() {
        // If T_ri is trilinear between the nodes, the least-squares fit is T_ri at the nodes,
        // whatever the density: the error Σ ρ |W·L − T|² is then zero. So for the B-spline,
        // which holds a linear field with node values on it. A linear field f(p) over three
        // uniform 8³ blocks (nodes at their edge have part-empty footprints), its exact footprint
        // means as the input, unpulled (λ 0). Nodes that only the blocks' fringe reaches (S_n
        // below 1 % of a full footprint's) move a rendered sample by a fraction of a percent of
        // their value, and conjugate gradients leave them converging: they are not checked, and
        // nodes the fringe alone reaches along one axis come within 0.2 % of f in the fit's
        // iterations.
        let mut density = SparseGrid::new(Default::default(), 0.0);
        for origin in [IVec3::ZERO, IVec3::new(8, 0, 0), IVec3::new(0, 8, 8)] {
            density.insert_tile(TileLevel::Block, origin, 0.7);
        }
        let k = 4;
        let layout = TransferLayout::build(&density, k);
        let f = |p: Vec3| 0.3 + 0.02 * p.x - 0.01 * p.y + 0.015 * p.z;
        // The B-spline's mass matrix is less well conditioned (its eigenvalues lie within a factor
        // 7.5 per axis, the tent's 3) and unpulled its nodes converge more slowly in the fit's
        // iterations: those with a fifth of a full footprint's mass or more come within 0.5 %,
        // the fringe's within 8 % (rendered, a bake's pulled fit reads the same after 20 and 80
        // iterations, to 0.01 %).
        let checked = |basis, mass: f64| match basis {
            Basis::Tent => (mass >= 0.01).then_some(2e-3),
            Basis::Quadratic => (mass >= 0.2).then_some(5e-3),
        };
        for basis in [Basis::Tent, Basis::Quadratic] {
            let quadrature = Quadrature::new(k, basis);
            let (mut means, masses): (Vec<f32>, Vec<f64>) = layout
                .voxels()
                .iter()
                .map(|v| {
                    let (points, cumulative) = quadrature.footprint(&density, *v);
                    let (mut sum, mut previous) = (0.0, 0.0);
                    for (i, c) in points.iter().zip(&cumulative) {
                        let p = (*v * k).as_vec3() + quadrature.offset(*i);
                        sum += (c - previous) * f(p) as f64;
                        previous = *c;
                    }
                    match previous > 0.0 {
                        true => ((sum / previous) as f32, previous),
                        false => (-1.0, 0.0),
                    }
                })
                .unzip();
            least_squares(&density, &layout, basis, &mut means, 1, 0.0);
            let full = masses.iter().cloned().fold(0.0, f64::max);
            let mut count = 0;
            for ((v, m), mass) in layout.voxels().iter().zip(&means).zip(&masses) {
                if let Some(tolerance) = checked(basis, mass / full) {
                    let want = f((*v * k).as_vec3());
                    let error = (m - want).abs() / want;
                    assert!(error < tolerance, "{basis:?} {v}: {m} vs {want}");
                    count += 1;
                }
            }
            assert!(count >= 27, "{basis:?}: {count} nodes checked");
        }
    }

    #[test]
    fn a_field_on_finer_nodes_comes_back_to_the_transfers_nodes() {
        // A linear field f given at the nodes of cells of 2 is trilinear between them, so each
        // node of cells of 4 whose footprint, and its neighbours', lie inside a uniform 48³ block
        // reads f at its own point as its footprint mean (its function is symmetric about it),
        // and the fit, which can hold f exactly with either basis, keeps it there to 0.1 % (the
        // boundary's partial footprints pull a little through the fit's coupling): per
        // coefficient, f and 2f + 1.
        let density = crate::volume::grid::block_box(IVec3::splat(48));
        let (layout, fine) = (
            TransferLayout::build(&density, 4),
            TransferLayout::build(&density, 2),
        );
        let f = |p: Vec3| 0.3 + 0.02 * p.x - 0.01 * p.y + 0.015 * p.z;
        let values: Vec<f32> = fine
            .voxels()
            .iter()
            .flat_map(|b| {
                let v = f((*b * fine.k).as_vec3());
                [v, 2.0 * v + 1.0]
            })
            .collect();
        for basis in [Basis::Tent, Basis::Quadratic] {
            let lambda = FIT_REGULARISATION;
            let halves: [Vec<f32>; 2] =
                std::array::from_fn(|h| values.iter().skip(h).step_by(2).copied().collect());
            let fields = [(&halves[0][..], 1), (&halves[1][..], 1)];
            let [a, b] = fitted_from_finer(&density, &layout, basis, &fine, fields, lambda);
            let fitted: Vec<f32> = a.iter().zip(&b).flat_map(|(a, b)| [*a, *b]).collect();
            let reach = 2 * basis.reach(4);
            let mut checked = 0;
            for (v, got) in layout.voxels().iter().zip(fitted.chunks_exact(2)) {
                let inside = (*v * 4 - reach).cmpge(IVec3::ZERO).all()
                    && (*v * 4 + reach).cmple(IVec3::splat(47)).all();
                if inside {
                    let want = f((*v * 4).as_vec3());
                    assert!(
                        (got[0] - want).abs() < 5e-4,
                        "{basis:?} {v}: {} vs {want}",
                        got[0]
                    );
                    assert!(
                        (got[1] - (2.0 * want + 1.0)).abs() < 1e-3,
                        "{basis:?} {v}: {}",
                        got[1]
                    );
                    checked += 1;
                }
            }
            assert!(checked >= 27, "{checked} nodes checked");
        }
    }

    #[test]
    fn the_pull_bounds_how_far_the_fit_amplifies_a_checkerboard() {
        // Footprint means 0.5 ± δ alternating node by node, over a uniform medium: the mode the
        // mass matrix damps most. Per axis, the tent weights at the midpoints between voxels
        // (K = 4: 7/8, 5/8, 3/8, 1/8 on each side) give a node's row 2.625 on the diagonal and
        // 0.6875 toward each neighbour over a mass of 4, so the checkerboard's eigenvalue is
        // μ = ((2.625 − 2·0.6875)/4)³ = 0.3125³, and the fit turns δ into
        // δ·(1 + λ)/(μ + λ): 32.8 δ unpulled, 8.43 δ at λ 0.1.
        let mut density = SparseGrid::new(Default::default(), 0.0);
        for x in 0..8 {
            for y in 0..8 {
                for z in 0..8 {
                    density.insert_tile(TileLevel::Block, IVec3::new(x, y, z) * 8, 0.3);
                }
            }
        }
        let k = 4;
        let layout = TransferLayout::build(&density, k);
        let delta = 0.01f32;
        let sign = |v: IVec3| {
            if (v.x + v.y + v.z) % 2 == 0 {
                1.0
            } else {
                -1.0
            }
        };
        let mut means: Vec<f32> = layout
            .voxels()
            .iter()
            .map(|v| 0.5 + delta * sign(*v))
            .collect();
        least_squares(
            &density,
            &layout,
            Basis::Tent,
            &mut means,
            1,
            FIT_REGULARISATION,
        );
        let mu = 0.3125f64.powi(3);
        let lambda = FIT_REGULARISATION;
        let want = (1.0 + lambda) / (mu + lambda);
        // Nodes two or more from the medium's faces (nodes 0..=16 per axis): the boundary's
        // influence has died away there.
        let inner = |v: IVec3| v.min_element() >= 6 && v.max_element() <= 10;
        let mut checked = 0;
        for (v, m) in layout.voxels().iter().zip(&means) {
            if inner(*v) {
                let gain = ((m - 0.5) / (delta * sign(*v))) as f64;
                assert!(
                    (gain / want - 1.0).abs() < 0.02,
                    "{v}: gain {gain}, want {want}"
                );
                checked += 1;
            }
        }
        assert_eq!(checked, 125);
    }
}
