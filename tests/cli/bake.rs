//! The bake: white furnace, direction, and cache behaviour.

use glam::IVec3;
use vscatter::transfer::{bake, lattice::LatticeKind, BakeSettings, Medium, Transfer};
use vscatter::volume::vdb::VdbFile;
use vscatter::volume::SparseGrid;

use crate::fixture;

pub fn load(name: &str) -> SparseGrid {
    let vdb = VdbFile::open(&fixture(name)).unwrap();
    vdb.read_grid(vdb.choose_grid(None).unwrap()).unwrap()
}

/// DC of T_ri + F_ms relative to √(4π), for voxels whose 5³ neighbourhood is all inside density.
fn furnace_deviation(density: &SparseGrid, t: &Transfer) -> (f32, f32, usize) {
    let dc = (4.0 * std::f32::consts::PI).sqrt();
    let k = t.layout.k;
    let inside = |v: IVec3| {
        let p = (v * k).as_vec3();
        density.sample_index(p) > 0.0
    };
    let (mut worst, mut sum, mut n) = (0f32, 0f32, 0);
    for (slot, v) in t.layout.voxels().iter().enumerate() {
        let deep =
            (0..125).all(|i| inside(*v + IVec3::new(i / 25 - 2, (i / 5) % 5 - 2, i % 5 - 2)));
        if deep {
            let total = t.t_ri(slot)[0] + t.f_ms(slot)[0];
            let dev = total / dc - 1.0;
            if dev.abs() > worst.abs() {
                worst = dev;
            }
            sum += dev;
            n += 1;
        }
    }
    (worst, sum / n.max(1) as f32, n)
}

#[test]
fn white_furnace_scratch() {
    for (file, sigma, k) in [
        ("cloud.vdb", 0.25, 6),
        ("cloud.vdb", 0.5, 6),
        ("cloud.vdb", 1.0, 6),
        ("cloud.vdb", 2.0, 6),
        ("torus.vdb", 2.0, 6),
        ("torus.vdb", 2.0, 3),
    ] {
        let d = load(file);
        let settings = BakeSettings {
            bands: 1,
            scale: k,
            samples: 256,
            lattice: LatticeKind::All,
            single_scatter: false,
            seed: 1,
        };
        let (t, stats) = bake(
            &d,
            Medium {
                sigma_t: sigma,
                albedo: 1.0,
            },
            &settings,
            true,
        );
        let (worst, mean, n) = furnace_deviation(&d, &t);
        let l = stats.lattice.unwrap();
        println!("{file} s{sigma} k{k}: voxels {} deep {n} worst {worst:.3} mean {mean:.3} gens {} rem {:.1e} E1 {:.0} Ems {:.0} t {:.1} {:.1}", t.layout.len(), l.generations, l.remaining, l.energy_single, l.energy_multiple, stats.single_seconds, stats.lattice_seconds);
    }
}

#[test]
fn furnace_profile_scratch() {
    let d = load("block_tiles.vdb");
    for sigma in [0.3f32, 1.0] {
        let settings = BakeSettings {
            bands: 1,
            scale: 6,
            samples: 128,
            lattice: LatticeKind::All,
            single_scatter: false,
            seed: 1,
        };
        let (t, stats) = bake(
            &d,
            Medium {
                sigma_t: sigma,
                albedo: 1.0,
            },
            &settings,
            true,
        );
        let dc = (4.0 * std::f32::consts::PI).sqrt();
        let mut line = String::new();
        for x in -1..=23 {
            let s = t.layout.slot(IVec3::new(x, 11, 11)).unwrap();
            line += &format!(
                "{:.2}/{:.2} ",
                t.t_ri(s)[0] / dc,
                (t.t_ri(s)[0] + t.f_ms(s)[0]) / dc
            );
        }
        println!(
            "sigma {sigma} gens {:?}\n{line}",
            stats.lattice.map(|l| l.generations)
        );
        let mut line = String::new();
        for x in -1..=23 {
            let s = t.layout.slot(IVec3::new(x, x.clamp(0, 22), 11)).unwrap();
            line += &format!("{:.2} ", (t.t_ri(s)[0] + t.f_ms(s)[0]) / dc);
        }
        println!("diag {line}");
    }
}
