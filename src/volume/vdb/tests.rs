//! The reader against `vdb-rs` voxel for voxel, against damaged bytes, and on tiles.

use std::collections::BTreeMap;
use std::path::PathBuf;

use glam::IVec3;
use serde_json::Value;

use super::VdbFile;
use crate::volume::grid::slot_offset;
use crate::volume::TileLevel;

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("fixtures")
        .join(name)
}

/// What Debian's OpenVDB tools say of every fixture (`tools/make_fixtures.sh` wrote it).
fn expected() -> Value {
    let text = std::fs::read_to_string(fixture("expected.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

/// Fixtures `vdb-rs` 0.6 cannot read correctly, and why (the reason the product has its own reader).
const VDB_RS_CANNOT: &[(&str, &str)] = &[
    (
        "small_cloud_half.vdb",
        "vdb-rs panics or misreads half-float grids",
    ),
    (
        "smoke_double_openvdb7.vdb",
        "vdb-rs returns double grids empty",
    ),
];

#[test]
fn own_reader_agrees_with_vdb_rs_voxel_for_voxel() {
    let exp = expected();
    let mut compared = 0;
    for (file, want) in exp["files"].as_object().unwrap() {
        if VDB_RS_CANNOT.iter().any(|(f, _)| f == file) {
            continue;
        }
        let ours = VdbFile::open(&fixture(file)).unwrap();
        let reader = std::fs::File::open(fixture(file)).unwrap();
        let mut theirs = vdb_rs::VdbReader::new(std::io::BufReader::new(reader)).unwrap();
        for (i, w) in want["grids"].as_array().unwrap().iter().enumerate() {
            if w["value_type"] != "float" {
                continue;
            }
            let grid = ours.read_grid(i).unwrap();
            let name = w["name"].as_str().unwrap();
            let other = theirs.read_grid::<f32>(name).unwrap();
            // Every active voxel and tile vdb-rs yields, keyed by origin and level.
            let mut seen = BTreeMap::new();
            for (pos, value, level) in other.iter() {
                let p = pos.as_ivec3();
                let lvl = match level {
                    vdb_rs::VdbLevel::Voxel => 0,
                    vdb_rs::VdbLevel::Node3 => 3,
                    vdb_rs::VdbLevel::Node4 => 7,
                };
                assert!(seen.insert((p.to_array(), lvl), value).is_none());
            }
            let mut ours_n = 0;
            for leaf in grid.leaves() {
                for slot in 0..512 {
                    if leaf.is_active(slot) {
                        let p = leaf.origin + slot_offset(slot);
                        let v = seen.get(&(p.to_array(), 0));
                        assert_eq!(
                            v.copied(),
                            Some(leaf.values.get(slot)),
                            "{file}/{name} voxel {p}"
                        );
                        ours_n += 1;
                    }
                }
            }
            for (level, lvl) in [(TileLevel::Block, 3), (TileLevel::Node, 7)] {
                for (origin, value) in grid.tiles(level) {
                    assert_eq!(
                        seen.get(&(origin.to_array(), lvl)),
                        Some(&value),
                        "{file}: tile {origin}"
                    );
                    ours_n += 1;
                }
            }
            assert_eq!(
                ours_n,
                seen.len(),
                "{file}/{name}: same number of active items"
            );
            compared += 1;
        }
    }
    assert!(compared >= 10, "compared {compared} grids");
}

/// Deterministic byte flips through the library: every outcome is a value or an error, never a
/// panic (the measured weakness of vdb-rs: 26 of 200 flips panicked or aborted).
#[test]
fn byte_flips_never_panic() {
    // From memory, as the fuzz target reads; the same bytes on disk read alike (checked below).
    let original = std::fs::read(fixture("small_cloud.vdb")).unwrap();
    let (a, b) = (
        VdbFile::open(&fixture("small_cloud.vdb")).unwrap(),
        VdbFile::from_bytes("small_cloud.vdb", original).unwrap(),
    );
    assert_eq!(a.grids.len(), b.grids.len());
    let (ga, gb) = (a.read_grid(0).unwrap(), b.read_grid(0).unwrap());
    assert_eq!(ga.active_voxels(), gb.active_voxels());
    assert_eq!(ga.value_stats(), gb.value_stats());
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    for file in [
        "small_cloud.vdb",
        "small_cloud_zip.vdb",
        "small_cloud_half.vdb",
        "block_tiles.vdb",
    ] {
        let original = std::fs::read(fixture(file)).unwrap();
        for _ in 0..100 {
            let mut bytes = original.clone();
            for _ in 0..1 + next() % 3 {
                let at = (next() % bytes.len() as u64) as usize;
                bytes[at] ^= 1 << (next() % 8);
            }
            let outcome = std::panic::catch_unwind(|| {
                if let Ok(vdb) = VdbFile::from_bytes(file, bytes) {
                    for i in 0..vdb.grids.len() {
                        let _ = vdb.read_grid(i);
                    }
                }
            });
            assert!(outcome.is_ok(), "{file}: a byte flip made the reader panic");
        }
    }
}

#[test]
fn tiles_stay_tiles() {
    let vdb = VdbFile::open(&fixture("block_tiles.vdb")).unwrap();
    let grid = vdb.read_grid(0).unwrap();
    assert_eq!(grid.leaf_count(), 0);
    assert_eq!(grid.tiles(TileLevel::Node).count(), 1);
    assert_eq!(grid.tiles(TileLevel::Block).count(), 817);
    // A point deep inside the 128³ tile, and one on the block's 8³-tile rim.
    assert_eq!(grid.value(IVec3::new(64, 64, 64)), 0.5);
    assert_eq!(grid.value(IVec3::new(135, 135, 135)), 0.5);
    assert_eq!(grid.value(IVec3::new(136, 0, 0)), 0.0);
}
