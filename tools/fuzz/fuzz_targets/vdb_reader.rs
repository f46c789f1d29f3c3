//! Any bytes through the VDB reader as `info` and `bake --dry-run` take them: index the file, read
//! every grid, and plan a bake of each one read. A panic, an abort, a runaway allocation or a hang
//! is a finding; an error is the right answer to a damaged file.
#![no_main]

use libfuzzer_sys::fuzz_target;
use vscatter::transfer::lattice::LatticeKind;
use vscatter::transfer::memory::BakePlan;
use vscatter::transfer::BakeSettings;
use vscatter::volume::vdb::VdbFile;
use vscatter::volume::DensityField;

fuzz_target!(|data: &[u8]| {
    let Ok(vdb) = VdbFile::from_bytes("fuzz.vdb", data.to_vec()) else {
        return;
    };
    let settings = BakeSettings {
        bands: 10,
        scale: 6,
        samples: 512,
        lattice: LatticeKind::All,
        single_scatter: false,
        seed: 0,
    };
    for i in 0..vdb.grids.len() {
        if let Ok(grid) = vdb.read_grid(i) {
            let _ = grid.value_stats();
            let _ = BakePlan::new(&DensityField::new(grid), &settings).describe();
        }
    }
});
