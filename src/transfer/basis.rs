//! How a transfer's node values are read between nodes: the basis function each node stands for.
//! The fit ([`super::fit`]) chooses node values for the basis the renderer reads them with, so
//! the two must agree; a transfer records its basis and the cache stores it (docs/model.md,
//! "Reading the nodes").
//!
//! - [`Basis::Tent`]: trilinear interpolation between the eight nodes around a point, each node's
//!   function a tent reaching the next node. Node values can be point values of the light.
//! - [`Basis::Quadratic`]: the quadratic B-spline, each node's function a smooth bump reaching
//!   1.5 node spacings, 27 nodes around a point. Its read-out has continuous first derivatives,
//!   where trilinear's slope jumps at every cell face. Its node values are coefficients, not
//!   values of the light at the node, so only a fitted transfer can use it: a bake on finer cells
//!   ([`super::refine`]). Where a transfer voxel is optically thick the light falls or peaks
//!   within it, a trilinear fit draws its cell faces as lines across a lit surface (the eye
//!   finds slope jumps), and the B-spline does not (docs/accuracy.md, "Soft light: thick voxels
//!   read as quadratic B-splines").

use glam::{IVec3, Vec3};
use serde::{Deserialize, Serialize};

use crate::math::floor::floor_split;

/// The basis functions of a transfer's nodes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Basis {
    /// Trilinear: 2³ nodes around a point.
    #[default]
    Tent,
    /// The quadratic B-spline: 3³ nodes around a point.
    Quadratic,
}

/// Most nodes a point reads along an axis, over every basis.
pub const MAX_EDGE: usize = 3;
/// Entries of a window of nodes ([`Basis::window`]) as the renderer keeps it: [`MAX_EDGE`] planes
/// of x, each a [`window_row`] of the y–z nodes.
pub const WINDOW: usize = MAX_EDGE * window_row(MAX_EDGE);

/// Entries of one x plane of a window `edge` nodes wide: its edge² nodes, padded to a multiple of
/// four so that the renderer adds a step's weights to a plane four at a time.
pub const fn window_row(edge: usize) -> usize {
    (edge * edge).div_ceil(4) * 4
}

/// The entry of node (x, y, z) of a window `edge` nodes wide (from its lowest node).
#[inline(always)]
pub const fn window_index(edge: usize, x: usize, y: usize, z: usize) -> usize {
    x * window_row(edge) + y * edge + z
}

impl Basis {
    /// Nodes a point reads along each axis.
    pub const fn edge(self) -> usize {
        match self {
            Basis::Tent => 2,
            Basis::Quadratic => 3,
        }
    }

    /// How the nodes are read, for people.
    pub fn name(self) -> &'static str {
        match self {
            Basis::Tent => "trilinearly",
            Basis::Quadratic => "as quadratic B-splines",
        }
    }

    /// Half the width of a node's function, in density voxels when nodes are `k` voxels apart,
    /// rounded up.
    pub fn reach(self, k: i32) -> i32 {
        match self {
            Basis::Tent => k,
            Basis::Quadratic => (3 * k + 1) / 2,
        }
    }

    /// The nodes a point reads and their weights: at `q` (in node spacings), its lowest node,
    /// and per axis the weights of that node and the next ones along it ([`Self::edge`] of them;
    /// the rest 0). The weights along an axis sum to 1.
    #[inline]
    pub fn window(self, q: Vec3) -> (IVec3, [Vec3; MAX_EDGE]) {
        match self {
            Basis::Tent => {
                let (b, f) = floor_split(q);
                (b, [Vec3::ONE - f, f, Vec3::ZERO])
            }
            Basis::Quadratic => {
                // The nearest node is the middle one; d ∈ [−½, ½) the offset from it.
                let (r, d) = floor_split(q + 0.5);
                let d = d - 0.5;
                let (below, above) = (Vec3::splat(0.5) - d, Vec3::splat(0.5) + d);
                (
                    r - IVec3::ONE,
                    [
                        0.5 * below * below,
                        Vec3::splat(0.75) - d * d,
                        0.5 * above * above,
                    ],
                )
            }
        }
    }

    /// Per axis, the function of a node along it at `q` node spacings from the node: the
    /// weight [`Self::window`] gives it there.
    #[inline]
    fn node_weights(self, q: Vec3) -> Vec3 {
        let (first, weights) = self.window(q);
        // The node is the window's node −first on each axis, if the window holds it.
        Vec3::from_array(std::array::from_fn(|a| {
            let i = -first[a];
            match (0..self.edge() as i32).contains(&i) {
                true => weights[i as usize][a],
                false => 0.0,
            }
        }))
    }

    /// The function of a node at `t` node spacings from it, along one axis.
    pub fn along(self, t: f32) -> f32 {
        self.node_weights(Vec3::splat(t)).x
    }

    /// The function of a node at offset `o` from it (density voxels), nodes `k` voxels apart:
    /// the product of its function along each axis, from one window.
    #[inline]
    pub fn at(self, o: Vec3, k: i32) -> f32 {
        self.node_weights(o / k as f32).element_product()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn weights_sum_to_one_and_reproduce_a_linear_field() {
        // Both bases reproduce constants and linear functions: Σ w = 1 and Σ w·x_node = x.
        for basis in [Basis::Tent, Basis::Quadratic] {
            for t in [-2.3f32, -0.5, -0.25, 0.0, 0.49, 0.5, 0.75, 3.999] {
                let (first, w) = basis.window(Vec3::new(t, t * 0.5, -t));
                let sum: Vec3 = w.iter().copied().sum();
                assert!(
                    (sum - Vec3::ONE).abs().max_element() < 1e-6,
                    "{basis:?} {t}"
                );
                let mean: Vec3 = w
                    .iter()
                    .enumerate()
                    .map(|(i, w)| *w * (first + IVec3::splat(i as i32)).as_vec3())
                    .sum();
                let want = Vec3::new(t, t * 0.5, -t);
                assert!((mean - want).abs().max_element() < 1e-5, "{basis:?} {t}");
            }
        }
    }

    #[test]
    fn a_nodes_function_is_the_tent_or_the_quadratic_b_spline() {
        let k = 4;
        let along = |basis: Basis, x: f32| basis.along(x / k as f32);
        // Tent: 1 at the node, ½ halfway, 0 at the next node.
        assert_eq!(along(Basis::Tent, 0.0), 1.0);
        assert!((along(Basis::Tent, 2.0) - 0.5).abs() < 1e-6);
        assert_eq!(along(Basis::Tent, 4.0), 0.0);
        // B-spline: ¾ at the node, ½ at half a spacing, ⅛ at one, 0 from 1.5 on, symmetric.
        assert!((along(Basis::Quadratic, 0.0) - 0.75).abs() < 1e-6);
        assert!((along(Basis::Quadratic, 2.0) - 0.5).abs() < 1e-6);
        assert!((along(Basis::Quadratic, -4.0) - 0.125).abs() < 1e-6);
        assert_eq!(along(Basis::Quadratic, 6.0), 0.0);
        assert_eq!(along(Basis::Quadratic, -7.0), 0.0);
        // A product over the axes.
        let o = Vec3::new(1.0, -2.0, 3.0);
        let product: f32 = (0..3).map(|a| along(Basis::Quadratic, o[a])).product();
        assert!((Basis::Quadratic.at(o, k) - product).abs() < 1e-6);
        assert_eq!(Basis::Quadratic.reach(k), 6);
        assert_eq!(Basis::Quadratic.reach(3), 5);
    }

    #[test]
    fn the_quadratic_read_out_has_a_continuous_slope() {
        // Nodes 0, 1, 0 along x: read just either side of a window's change (q = 0.5), the
        // value and its slope match; trilinear's slope jumps at the node.
        let read = |basis: Basis, x: f32| {
            let (first, w) = basis.window(Vec3::new(x, 0.0, 0.0));
            (0..basis.edge())
                .map(|i| w[i].x * f32::from(first.x + i as i32 == 1))
                .sum::<f32>()
        };
        let slope = |basis: Basis, x: f32| (read(basis, x + 1e-3) - read(basis, x - 1e-3)) / 2e-3;
        for x in [0.5f32, 1.5] {
            let (below, above) = (
                slope(Basis::Quadratic, x - 0.005),
                slope(Basis::Quadratic, x + 0.005),
            );
            assert!((below - above).abs() < 0.03, "{x}: {below} {above}");
        }
        let (below, above) = (slope(Basis::Tent, 0.99), slope(Basis::Tent, 1.01));
        assert!((below - above).abs() > 1.9);
    }
}
