//! Tests of `dda`.

use super::*;
use crate::volume::grid::{Leaf, LEAF_VOXELS};
use crate::volume::Transform;

const EPS: f64 = 1e-5;

/// A leaf holding one active voxel `ijk` of value `v`.
fn add_voxel(g: &mut SparseGrid, ijk: IVec3, v: f32) {
    let mut mask = [0u64; 8];
    let mut values = [0.0; LEAF_VOXELS];
    let s = Leaf::slot(ijk);
    mask[s >> 6] |= 1 << (s & 63);
    values[s] = v;
    g.insert_leaf(ijk & !(LEAF_DIM - 1), mask, values);
}

/// A leaf at `origin` with one active voxel of value `v` at `origin + (3, 3, 3)`.
fn add_leaf(g: &mut SparseGrid, origin: IVec3, v: f32) {
    add_voxel(g, origin + IVec3::splat(3), v);
}

fn grid() -> SparseGrid {
    SparseGrid::new(Transform::default(), 0.0)
}

fn check(got: &[Span], want: &[(f64, f64, f32)]) {
    assert_eq!(got.len(), want.len(), "spans {got:?}, want {want:?}");
    for (s, w) in got.iter().zip(want) {
        assert!(
            (s.t0 - w.0).abs() < EPS && (s.t1 - w.1).abs() < EPS,
            "span {s:?}, want {w:?}"
        );
        assert_eq!(s.max_density, w.2);
    }
}

fn dv(x: f64, y: f64, z: f64) -> DVec3 {
    DVec3::new(x, y, z)
}

#[test]
fn one_leaf_along_an_axis() {
    let mut g = grid();
    add_leaf(&mut g, IVec3::ZERO, 0.7);
    let occ = Occupancy::build(&g);
    // Voxel 3 is seen by samples in (2, 4); with the slack, [1, 5] on each axis.
    let s = occ.spans(dv(-20.0, 3.5, 3.5), DVec3::X, 0.0, 100.0);
    check(&s, &[(21.0, 25.0, 0.7)]);
    // Backwards, and the same ray cut short by t1.
    let s = occ.spans(dv(40.0, 3.5, 3.5), -DVec3::X, 0.0, 37.0);
    check(&s, &[(35.0, 37.0, 0.7)]);
    // Parameter scaled by a non-unit direction.
    let s = occ.spans(dv(-20.0, 3.5, 3.5), dv(2.0, 0.0, 0.0), 0.0, 100.0);
    check(&s, &[(10.5, 12.5, 0.7)]);
    // Beside the voxel's support: y = 5.5 is past [1, 5], though inside the leaf's block.
    assert!(occ
        .spans(dv(-20.0, 5.5, 3.5), DVec3::X, 0.0, 100.0)
        .is_empty());
}

#[test]
fn a_leaf_part_is_the_box_of_its_positive_voxels() {
    // Two positive voxels and a negative one: the part is [2, 6] × [1, 5] × [1, 7] around the
    // positive ones, the negative voxel (x = 6) adds nothing.
    let mut g = grid();
    let mut mask = [0u64; 8];
    let mut values = [0.0; LEAF_VOXELS];
    for (ijk, v) in [((4, 3, 3), 1.0), ((4, 3, 5), 0.5), ((6, 3, 3), -2.0)] {
        let s = Leaf::slot(IVec3::from(ijk));
        mask[s >> 6] |= 1 << (s & 63);
        values[s] = v;
    }
    g.insert_leaf(IVec3::ZERO, mask, values);
    let occ = Occupancy::build(&g);
    check(
        &occ.spans(dv(-20.0, 3.5, 3.5), DVec3::X, 0.0, 100.0),
        &[(22.0, 26.0, 1.0)],
    );
    check(
        &occ.spans(dv(4.5, 3.5, -10.0), DVec3::Z, 0.0, 100.0),
        &[(11.0, 17.0, 1.0)],
    );
}

#[test]
fn two_leaves_with_a_gap_and_touching() {
    let mut g = grid();
    add_leaf(&mut g, IVec3::ZERO, 0.5);
    add_leaf(&mut g, IVec3::new(32, 0, 0), 2.0);
    let occ = Occupancy::build(&g);
    // [1, 5] and [33, 37].
    let s = occ.spans(dv(-20.0, 3.5, 3.5), DVec3::X, 0.0, 100.0);
    check(&s, &[(21.0, 25.0, 0.5), (53.0, 57.0, 2.0)]);
    // Voxels 6 and 10 in neighbouring blocks: parts [4, 8] and [8, 12] touch on the block
    // face and merge into one span.
    let mut g = grid();
    add_voxel(&mut g, IVec3::new(6, 3, 3), 0.5);
    add_voxel(&mut g, IVec3::new(10, 3, 3), 2.0);
    let s = Occupancy::build(&g).spans(dv(-20.0, 3.5, 3.5), DVec3::X, 0.0, 100.0);
    check(&s, &[(24.0, 32.0, 2.0)]);
}

#[test]
fn leaf_dilation_crosses_a_node_face() {
    let mut g = grid();
    // Voxel 127 is the last of node 0; its part [125, 129] reaches into node 1.
    add_voxel(&mut g, IVec3::new(127, 3, 3), 1.0);
    let s = Occupancy::build(&g).spans(dv(100.0, 3.5, 3.5), DVec3::X, 0.0, 100.0);
    check(&s, &[(25.0, 29.0, 1.0)]);
}

#[test]
fn node_tile_is_one_dense_span_with_its_shell() {
    let mut g = grid();
    g.insert_tile(TileLevel::Node, IVec3::ZERO, 0.25);
    let occ = Occupancy::build(&g);
    // Node voxels [0, 127] are seen by samples in (−1, 128); with the slack, [−2, 129].
    let s = occ.spans(dv(-50.0, 64.0, 64.0), DVec3::X, 0.0, 1000.0);
    check(&s, &[(48.0, 179.0, 0.25)]);
    // A voxel right beside the tile extends the span and raises its majorant.
    add_voxel(&mut g, IVec3::new(131, 67, 67), 3.0);
    let s = Occupancy::build(&g).spans(dv(-50.0, 67.5, 67.5), DVec3::X, 0.0, 1000.0);
    check(&s, &[(48.0, 183.0, 3.0)]);
}

#[test]
fn neighbouring_node_tiles_raise_each_other_and_mark_only_their_outer_shell() {
    let mut g = grid();
    g.insert_tile(TileLevel::Node, IVec3::ZERO, 0.25);
    g.insert_tile(TileLevel::Node, IVec3::new(128, 0, 0), 0.75);
    let occ = Occupancy::build(&g);
    // The 0.75 tile's dilation reaches into the 0.25 node, whose majorant rises to 0.75; the span
    // runs on through both, with the shell beyond each far face.
    let s = occ.spans(dv(-50.0, 64.0, 64.0), DVec3::X, 0.0, 1000.0);
    check(&s, &[(48.0, 307.0, 0.75)]);
    // A box of 4³ node tiles marks blocks only outside the box (16³ blocks a node): the shell of
    // one block around a 64³-block box, none inside.
    let mut g = grid();
    for n in 0..64 {
        let o = IVec3::new(n % 4, (n / 4) % 4, n / 16) * 128;
        g.insert_tile(TileLevel::Node, o, 0.5);
    }
    let (blocks, _, _) = mark_occupied(&g);
    assert_eq!(blocks.len(), 66usize.pow(3) - 64usize.pow(3));
}

#[test]
fn root_tile_is_dense_with_a_ring_of_nodes() {
    let mut g = grid();
    g.insert_tile(TileLevel::Root, IVec3::ZERO, 0.125);
    let occ = Occupancy::build(&g);
    // Root [0, 4096) plus a ring of one node: [−128, 4224).
    let s = occ.spans(dv(-1000.0, 100.0, 2000.0), DVec3::X, 0.0, 1e9);
    check(&s, &[(872.0, 5224.0, 0.125)]);
    let s = occ.spans(dv(-1000.0, -500.0, 2000.0), DVec3::X, 0.0, 1e9);
    check(&s, &[]);
}

#[test]
fn diagonal_ray_through_two_leaves() {
    let mut g = grid();
    add_leaf(&mut g, IVec3::ZERO, 1.0);
    add_leaf(&mut g, IVec3::new(16, 32, 8), 4.0);
    let occ = Occupancy::build(&g);
    // p(t) = (−1.5, −6.5, 1) + t·(0.5, 1, 0.25), through both voxels' centres.
    // Voxel (3,3,3), part [1,5]³: x → t∈[5,13], y → [7.5,11.5], z → [0,16]: [7.5, 11.5].
    // Voxel (19,35,11), part [17,21]×[33,37]×[9,13]: x → [37,45], y → [39.5,43.5],
    // z → [32,48]: [39.5, 43.5].
    let s = occ.spans(dv(-1.5, -6.5, 1.0), dv(0.5, 1.0, 0.25), -100.0, 200.0);
    check(&s, &[(7.5, 11.5, 1.0), (39.5, 43.5, 4.0)]);
}

#[test]
fn ray_starting_inside() {
    let mut g = grid();
    add_leaf(&mut g, IVec3::ZERO, 1.0);
    let occ = Occupancy::build(&g);
    check(
        &occ.spans(dv(4.0, 4.0, 4.0), DVec3::Z, 0.0, 100.0),
        &[(0.0, 1.0, 1.0)],
    );
    check(
        &occ.spans(dv(4.0, 4.0, 4.0), -DVec3::Z, 0.0, 100.0),
        &[(0.0, 3.0, 1.0)],
    );
}

#[test]
fn rays_missing_everything() {
    let mut g = grid();
    add_leaf(&mut g, IVec3::ZERO, 1.0);
    let occ = Occupancy::build(&g);
    assert!(occ
        .spans(dv(-20.0, 40.0, 4.0), DVec3::X, 0.0, 100.0)
        .is_empty());
    // Pointing away, and too short to arrive.
    assert!(occ
        .spans(dv(-20.0, 4.0, 4.0), -DVec3::X, 0.0, 100.0)
        .is_empty());
    assert!(occ
        .spans(dv(-20.0, 4.0, 4.0), DVec3::X, 0.0, 11.0)
        .is_empty());
    // An empty grid, and a grid whose only leaf holds zeros.
    assert!(Occupancy::build(&grid())
        .spans(DVec3::ZERO, DVec3::X, -1e9, 1e9)
        .is_empty());
    let mut g = grid();
    add_leaf(&mut g, IVec3::ZERO, 0.0);
    assert!(Occupancy::build(&g)
        .spans(dv(-20.0, 3.5, 3.5), DVec3::X, 0.0, 100.0)
        .is_empty());
}

#[test]
fn breaking_stops_the_walk() {
    let mut g = grid();
    add_leaf(&mut g, IVec3::ZERO, 1.0);
    add_leaf(&mut g, IVec3::new(32, 0, 0), 1.0);
    let occ = Occupancy::build(&g);
    let mut seen = 0;
    occ.visit_spans(&Ray::new(dv(-20.0, 3.5, 3.5), DVec3::X), 0.0, 100.0, |_| {
        seen += 1;
        ControlFlow::Break(())
    });
    assert_eq!(seen, 1);
}

#[test]
fn dense_and_hashed_marks_agree() {
    // Overlapping boxes with different maxima and parts, compact enough for the dense marks, and
    // the same boxes spread far apart, which go to the map: both give each box's blocks exactly
    // as marking them one by one into a map does.
    let compact = [
        (IVec3::new(0, 0, 0), IVec3::new(7, 7, 7), 0.5),
        (IVec3::new(8, 2, 3), IVec3::new(9, 5, 15), 2.0),
        (IVec3::new(-5, 4, 1), IVec3::new(-1, 4, 1), 1.5),
    ];
    let far = |i: i32| IVec3::new(i * 4096, -i * 2048, i * 1024);
    let spread: Vec<_> = (0..)
        .zip(compact)
        .map(|(i, (lo, hi, v))| (lo + far(i), hi + far(i), v))
        .collect();
    for boxes in [&compact[..], &spread[..]] {
        let mut one_by_one = HashMap::new();
        let d = IVec3::splat(DILATION);
        for &(lo, hi, v) in boxes {
            mark_box(&mut one_by_one, lo - d, hi + d, v);
        }
        assert_eq!(mark_boxes(boxes), one_by_one);
    }
    assert!(mark_boxes(&[]).is_empty());
}

#[test]
fn a_long_run_of_occupied_blocks_comes_in_spans_of_a_few_blocks_end_to_end() {
    // Twelve block tiles in a row along x, voxels [0, 95]: with the slack, one stretch [−2, 97]
    // over 14 blocks, handed on SPAN_BLOCKS blocks at a time, each span starting where the last
    // ended.
    let mut g = grid();
    for i in 0..12 {
        g.insert_tile(TileLevel::Block, IVec3::new(8 * i, 0, 0), 1.0);
    }
    let s = Occupancy::build(&g).spans(dv(-20.0, 3.5, 3.5), DVec3::X, 0.0, 200.0);
    assert_eq!(s.len(), 14usize.div_ceil(SPAN_BLOCKS as usize), "{s:?}");
    assert_eq!((s[0].t0, s[s.len() - 1].t1), (18.0, 117.0));
    for w in s.windows(2) {
        assert_eq!(w[0].t1, w[1].t0);
    }
    assert!(s.iter().all(|s| s.t1 - s.t0 <= 8.0 * SPAN_BLOCKS as f64));
}
