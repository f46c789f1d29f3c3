//! Times the SH projection of a 4096×2048 latlong map (the built-in sky, generated in memory) at
//! 10 and 20 bands, its reconstruction, and one `eval_basis` call: `cargo bench --bench sh_project`, or tools/bench.sh.

use std::time::Instant;

use vscatter::light::env::Environment;
use vscatter::light::sh;

/// 4k latlong: the common size of production HDRIs (target: well under a second at 10 bands).
const WIDTH: usize = 4096;
const HEIGHT: usize = 2048;
/// Best of a few runs: the machine is shared, so the minimum is the least disturbed figure.
const RUNS: usize = 5;

fn best_ms(mut f: impl FnMut()) -> f64 {
    (0..RUNS)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64() * 1e3
        })
        .fold(f64::INFINITY, f64::min)
}

/// Directions per `eval_basis` timing: enough for a stable per-call figure.
const EVAL_CALLS: usize = 1_000_000;

fn main() {
    for bands in [10, 20] {
        let mut out = vec![0.0f32; sh::coeff_count(bands)];
        let ms = best_ms(|| {
            for i in 0..EVAL_CALLS {
                // A spiral over the sphere: every call a different direction.
                let t = 1.0 - 2.0 * (i as f64 + 0.5) / EVAL_CALLS as f64;
                let phi = i as f64 * 2.399_963;
                let d = sh::direction(t.acos(), phi);
                sh::eval_basis(std::hint::black_box(d), bands, &mut out);
                std::hint::black_box(&out);
            }
        });
        println!(
            "sh_eval_basis bands={bands:>2} single thread: {:6.1} ns per direction (best of {RUNS})",
            ms * 1e6 / EVAL_CALLS as f64
        );
    }
    let threads = rayon::current_num_threads();
    let env = Environment::sky_with_size(WIDTH, HEIGHT);
    for bands in [10, 20] {
        let mut sh = env.project(bands);
        let project = best_ms(|| sh = env.project(bands));
        let reconstruct = best_ms(|| {
            std::hint::black_box(sh.reconstruct_latlong(WIDTH, HEIGHT));
        });
        println!(
            "sh_project {WIDTH}x{HEIGHT} bands={bands:>2} threads={threads}: project {project:8.1} ms, \
             reconstruct {reconstruct:8.1} ms (best of {RUNS})"
        );
    }
}
