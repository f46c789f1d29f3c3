//! Relighting: the per-transfer-voxel in-scattered radiance Ls = (1/4π) Σᵢ Tᵢ Eᵢ (docs/model.md
//! "Pixel radiance"), for the unscattered part T_ri ("direct") and the multiply scattered part F_ms
//! ("indirect") separately, so the renderer can write them as their own EXR layers. This is the
//! step that makes a new environment cost milliseconds: a dot product per voxel and channel.

use std::borrow::Cow;
use std::time::{Duration, Instant};

use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::transfer::coefficients::MAX_COEFFS;
use crate::transfer::{Coefficients, RelitMap, Transfer, TransferLight, PHASE};

/// Slots per rayon task: large enough that scheduling costs nothing next to the dot products.
const SLOTS_PER_TASK: usize = 1024;

/// Independent partial sums per dot product: eight f32 lanes fill one AVX or two SSE registers.
const LANES: usize = 8;

/// RGB in-scattered radiance per transfer voxel, in slot order of the transfer layout: one record
/// per slot, direct then indirect — what the march reads of a corner, in one cache line — and a
/// last all-zero record that the march's missing corners point at.
#[derive(Debug, Clone, PartialEq)]
pub struct Radiance {
    pub nodes: Vec<[f32; 6]>,
}

impl Radiance {
    /// From each slot's direct and indirect parts.
    pub fn new(direct: &[[f32; 3]], indirect: &[[f32; 3]]) -> Radiance {
        let records = direct.iter().zip(indirect);
        Radiance {
            nodes: records
                .map(|(d, i)| [d[0], d[1], d[2], i[0], i[1], i[2]])
                .chain([[0.0; 6]])
                .collect(),
        }
    }

    /// Slots (the last, all-zero record not counted).
    pub fn len(&self) -> usize {
        self.nodes.len() - 1
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn direct(&self, slot: usize) -> [f32; 3] {
        let n = &self.nodes[slot];
        [n[0], n[1], n[2]]
    }

    pub fn indirect(&self, slot: usize) -> [f32; 3] {
        let n = &self.nodes[slot];
        [n[3], n[4], n[5]]
    }

    pub fn memory_bytes(&self) -> usize {
        self.nodes.capacity() * std::mem::size_of::<[f32; 6]>()
    }
}

/// Ls per slot from `env_coeffs` — the environment's RGB SH coefficients (index i = l(l+1)+m,
/// already windowed and rotated). A transfer relit as it was read lends the radiance of the map it
/// was read for; another map is an error, as there are no coefficients to relight.
///
/// The sum runs over the coefficients both sides have: with orthonormal SH a missing coefficient is
/// zero, so a shorter side simply truncates the product — no mismatch error is needed.
///
/// Results below zero are clamped to 0. Both factors are band-limited approximations of
/// non-negative functions; truncation rings (Gibbs), so a voxel in deep shadow can get a slightly
/// negative dot product; and the direct part is a least-squares fit (`transfer::fit`) whose
/// difference from the point values F_ms carries, so either part may dip below zero at a node
/// where the fit departs far from the point value. Negative radiance has no physical meaning and,
/// multiplied by the march's positive weights, would print as dark fringes or negative pixels.
/// So the *sum* is clamped to 0 and a negative part is taken from the other one: clamping each
/// part alone added light and broke the white furnace by 17 % at σt 1. Both EXR layers and their
/// sum stay non-negative; light is only added where the truth is ~0.
///
/// Each slot's sums run in a fixed order (eight interleaved partial sums, then the tail) inside one
/// task, so the output is bit-identical for any thread count, and for a transfer relit as read.
///
/// Also returns the time relighting took: now, or, for a transfer relit as read, then.
pub fn relight<'a>(
    transfer: &'a Transfer,
    env_coeffs: &[[f32; 3]],
) -> Result<(Cow<'a, Radiance>, Duration)> {
    let clock = Instant::now();
    let (t_ri, f_ms) = match &transfer.light {
        TransferLight::Coefficients { t_ri, f_ms } => (t_ri, f_ms),
        TransferLight::Relit(maps) => {
            return maps
                .iter()
                .find(|m| m.env == env_coeffs)
                .map(|m| {
                    let then = Duration::from_secs_f64(m.seconds);
                    (Cow::Borrowed(&m.radiance), then + clock.elapsed())
                })
                .ok_or_else(|| {
                    Error::Runtime(
                        "the transfer was relit for other maps as it was read: open it again"
                            .into(),
                    )
                })
        }
    };
    let stride = transfer.coeffs();
    let env = EnvPlanes::new(env_coeffs, stride);
    let n = transfer.layout.len();
    let (direct, indirect) = rayon::join(
        || env.each_voxel(t_ri, n, stride).collect(),
        || env.each_voxel(f_ms, n, stride).collect(),
    );
    Ok((Cow::Owned(clamped(direct, indirect)), clock.elapsed()))
}

/// One environment's SH coefficients as channel planes, cut to what a transfer of `stride`
/// coefficients per voxel has, so the dot products run as LANES independent sums the compiler
/// vectorises.
struct EnvPlanes {
    planes: [Vec<f32>; 3],
}

impl EnvPlanes {
    fn new(env_coeffs: &[[f32; 3]], stride: usize) -> EnvPlanes {
        let n = stride.min(env_coeffs.len());
        EnvPlanes {
            planes: std::array::from_fn(|c| env_coeffs[..n].iter().map(|e| e[c]).collect()),
        }
    }

    /// Ls of each of the `voxels` voxels of `all` (`stride` coefficients each), in parallel: each
    /// voxel's coefficients decode into a buffer on the stack (they are held as the cache stores
    /// them), then one dot product per channel.
    fn each_voxel<'a>(
        &'a self,
        all: &'a Coefficients,
        voxels: usize,
        stride: usize,
    ) -> impl IndexedParallelIterator<Item = [f32; 3]> + 'a {
        (0..voxels)
            .into_par_iter()
            .with_min_len(SLOTS_PER_TASK)
            .map(move |slot| {
                if stride == 0 {
                    return [0.0; 3];
                }
                let mut voxel = [0.0f32; MAX_COEFFS];
                all.voxel(slot, &mut voxel[..stride]);
                self.ls(&voxel[..stride])
            })
    }

    /// (1/4π) Σᵢ Tᵢ Eᵢ per channel for one voxel's coefficients `t`.
    fn ls(&self, t: &[f32]) -> [f32; 3] {
        let n = self.planes[0].len();
        let t = &t[..n];
        let split = n - n % LANES;
        std::array::from_fn(|c| {
            let e = &self.planes[c];
            let mut lanes = [0.0f32; LANES];
            for (tc, ec) in t[..split]
                .chunks_exact(LANES)
                .zip(e[..split].chunks_exact(LANES))
            {
                for k in 0..LANES {
                    lanes[k] += tc[k] * ec[k];
                }
            }
            let tail: f32 = t[split..].iter().zip(&e[split..]).map(|(a, b)| a * b).sum();
            let sum = lanes.iter().sum::<f32>() + tail;
            sum * PHASE
        })
    }
}

/// The two parts with their sum clamped to 0 and a negative part taken from the other
/// ([`relight`]).
fn clamped(mut direct: Vec<[f32; 3]>, mut indirect: Vec<[f32; 3]>) -> Radiance {
    for (d, i) in direct.iter_mut().zip(indirect.iter_mut()) {
        for c in 0..3 {
            let sum = (d[c] + i[c]).max(0.0);
            d[c] = d[c].clamp(0.0, sum);
            i[c] = sum - d[c];
        }
    }
    Radiance::new(&direct, &indirect)
}

/// Relights a transfer's coefficients under several maps as they stream in, a batch of voxels at
/// a time (T_ri's, then F_ms's), so a render from a cache never holds the coefficients: the same
/// radiance as [`relight`], bit for bit.
pub struct StreamRelight {
    envs: Vec<(Vec<[f32; 3]>, EnvPlanes)>,
    stride: usize,
    /// Per map, the unclamped parts so far: T_ri's, then F_ms's.
    parts: Vec<[Vec<[f32; 3]>; 2]>,
    /// Per map, the time relighting has taken so far.
    seconds: Vec<f64>,
}

impl StreamRelight {
    /// For `stride` coefficients per voxel under each of `envs` (SH coefficients as [`relight`]
    /// takes them).
    pub fn new(envs: &[Vec<[f32; 3]>], stride: usize) -> StreamRelight {
        StreamRelight {
            envs: envs
                .iter()
                .map(|e| (e.clone(), EnvPlanes::new(e, stride)))
                .collect(),
            stride,
            parts: envs.iter().map(|_| Default::default()).collect(),
            seconds: vec![0.0; envs.len()],
        }
    }

    /// Takes the next voxels' coefficients of part `part` (0: T_ri, 1: F_ms).
    pub fn take(&mut self, part: usize, voxels: &Coefficients) {
        let stride = self.stride;
        let count = voxels.len() / stride.max(1);
        for (((_, env), parts), seconds) in
            self.envs.iter().zip(&mut self.parts).zip(&mut self.seconds)
        {
            let clock = Instant::now();
            parts[part].par_extend(env.each_voxel(voxels, count, stride));
            *seconds += clock.elapsed().as_secs_f64();
        }
    }

    /// Each map with its radiance, once both parts are in.
    pub fn finish(self) -> Vec<RelitMap> {
        self.envs
            .into_iter()
            .zip(self.parts)
            .zip(self.seconds)
            .map(|(((env, _), [direct, indirect]), seconds)| {
                let clock = Instant::now();
                let radiance = clamped(direct, indirect);
                RelitMap {
                    env,
                    radiance,
                    seconds: seconds + clock.elapsed().as_secs_f64(),
                }
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transfer::{Medium, TransferLayout};
    use crate::volume::grid::TileLevel;
    use crate::volume::{SparseGrid, Transform};
    use glam::IVec3;

    fn transfer_with(bands: usize, fill: impl Fn(usize, usize) -> (f32, f32)) -> Transfer {
        let mut g = SparseGrid::new(Transform::default(), 0.0);
        g.insert_tile(TileLevel::Node, IVec3::ZERO, 1.0);
        let layout = TransferLayout::build(&g, 4);
        let n = bands * bands;
        let len = layout.len();
        let (mut t_ri, mut f_ms) = (vec![0.0; len * n], vec![0.0; len * n]);
        for slot in 0..len {
            for i in 0..n {
                (t_ri[slot * n + i], f_ms[slot * n + i]) = fill(slot, i);
            }
        }
        Transfer {
            layout,
            bands,
            medium: Medium {
                sigma_t: 1.0,
                albedo: 1.0,
            },
            light: TransferLight::Coefficients {
                t_ri: Coefficients::F32(t_ri),
                f_ms: Coefficients::F32(f_ms),
            },
            lattice: None,
            shape: None,
            basis: crate::transfer::Basis::Tent,
        }
    }

    #[test]
    fn white_furnace_dc_term() {
        // T₀ = √(4π) is a transfer of 1 from every direction; E₀ = c·√(4π) a constant environment
        // c. Ls = (1/4π)·T₀·E₀ = c: a fully lit voxel sees exactly the environment's radiance.
        let sqrt_4pi = (4.0 * std::f32::consts::PI).sqrt();
        let t = transfer_with(3, |_, i| if i == 0 { (sqrt_4pi, 0.0) } else { (0.0, 0.0) });
        let c = [0.25f32, 1.0, 3.5];
        let mut env = vec![[0.0f32; 3]; 9];
        env[0] = c.map(|v| v * sqrt_4pi);
        let (r, _) = relight(&t, &env).unwrap();
        assert_eq!(r.len(), t.layout.len());
        for (d, i) in (0..r.len()).map(|s| (r.direct(s), r.indirect(s))) {
            for ch in 0..3 {
                assert!((d[ch] - c[ch]).abs() < 1e-6 * c[ch]);
            }
            assert_eq!(i, [0.0; 3]);
        }
    }

    #[test]
    fn parts_are_truncated_and_their_sum_clamped() {
        // Direct has only band 1, indirect only DC; the environment has 2 bands (4 coefficients)
        // against the transfer's 3 (9): the product truncates at 4.
        // Odd slots' direct part is negative (−2/(4π) etc.): clamped, and taken from the
        // indirect part (4/(4π) etc.), so their sum is kept.
        let t = transfer_with(3, |slot, i| match i {
            1 => (if slot % 2 == 0 { 2.0 } else { -0.5 }, 0.0),
            0 => (0.0, 1.0),
            2 | 3 => (0.0, 0.0),
            // Band 2 lies beyond the environment's coefficients: it must not contribute.
            _ => (100.0, 100.0),
        });
        let env = vec![[4.0, 8.0, 12.0]; 4];
        let (r, _) = relight(&t, &env).unwrap();
        let inv = 1.0 / (4.0 * std::f32::consts::PI);
        for (slot, (d, i)) in (0..r.len())
            .map(|s| (r.direct(s), r.indirect(s)))
            .enumerate()
        {
            let (want_d, want_i) = if slot % 2 == 0 {
                ([8.0, 16.0, 24.0], [4.0, 8.0, 12.0])
            } else {
                ([0.0; 3], [2.0, 4.0, 6.0])
            };
            for c in 0..3 {
                assert!((d[c] - want_d[c] * inv).abs() < 1e-6, "{slot}: {d:?}");
                assert!((i[c] - want_i[c] * inv).abs() < 1e-6, "{slot}: {i:?}");
            }
        }
    }

    #[test]
    fn deterministic_across_thread_counts() {
        let t = transfer_with(10, |slot, i| {
            (
                ((slot * 31 + i * 7) % 13) as f32 * 0.37 - 2.0,
                ((slot * 17 + i * 3) % 11) as f32 * 0.21 - 1.0,
            )
        });
        let env: Vec<[f32; 3]> = (0..100)
            .map(|i| [i as f32 * 0.01, 1.0 - i as f32 * 0.005, 0.3])
            .collect();
        let (a, _) = relight(&t, &env).unwrap();
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let (b, _) = pool.install(|| relight(&t, &env).unwrap());
        assert_eq!(a, b);
    }
}
