//! The film: image tiles rendered in parallel, `spp` samples per pixel placed by
//! [`pixel_offset`] and averaged with a box filter, the environment added behind what each ray
//! leaves visible. Every renderer (the transfer march, the path tracer) supplies only what one
//! camera ray returns, so both share the same pixels, filter, layers and progress bar.

use glam::Vec3;
use indicatif::ProgressBar;
use rayon::prelude::*;

use crate::render::camera::{pixel_offset, Camera};

/// Edge of the square image tiles handed to rayon: big enough to amortise scheduling, small enough
/// that both cores stay busy until the last tile even when the volume covers a corner of the frame.
const TILE: u32 = 32;

/// The environment seen behind the volume: radiance arriving along a world direction.
pub type Background<'a> = &'a (dyn Fn(Vec3) -> [f32; 3] + Sync);

/// One camera sample: pixel (`x`, `y`), sample `index` of the pixel, and its world-space ray.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraSample {
    pub x: u32,
    pub y: u32,
    pub index: u32,
    pub origin: Vec3,
    /// Unit length.
    pub dir: Vec3,
}

/// What one camera ray returns.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RayResult {
    /// Volume radiance from light scattered once (the transfer's T_ri).
    pub direct: [f32; 3],
    /// Volume radiance from light scattered more than once (the transfer's F_ms).
    pub indirect: [f32; 3],
    /// Tr(0, ∞), or an unbiased estimate of it (the path tracer's 0 or 1).
    pub transmittance: f32,
    /// Opacity-weighted distance of what the ray meets, world units; 0 when nothing is hit.
    pub depth: f32,
}

impl RayResult {
    /// A ray that meets nothing.
    pub const CLEAR: RayResult = RayResult {
        direct: [0.0; 3],
        indirect: [0.0; 3],
        transmittance: 1.0,
        depth: 0.0,
    };
}

/// A rendered frame: row-major, row 0 at the top.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    /// Linear RGB (volume + Tr·background) and alpha (1 with a background, else 1 − Tr).
    pub rgba: Vec<[f32; 4]>,
    pub direct: Vec<[f32; 3]>,
    pub indirect: Vec<[f32; 3]>,
    /// Opacity-weighted mean distance from the camera, world units; 0 where the ray hits nothing.
    pub depth: Vec<f32>,
}

/// Renders every pixel of `camera` with `spp` samples (at least 1), calling `trace` for each camera
/// ray with a per-tile statistics accumulator; `background` (`None`: alpha only) is added behind
/// each ray's transmittance. `progress` advances by one per finished tile (its length is set here).
pub fn render_frame<St, F>(
    camera: &Camera,
    spp: u32,
    background: Option<Background>,
    progress: &ProgressBar,
    trace: F,
) -> (Frame, St)
where
    St: Default + std::ops::AddAssign + Send,
    F: Fn(CameraSample, &mut St) -> RayResult + Sync,
{
    let (w, h) = (camera.width, camera.height);
    let spp = spp.max(1);
    let tiles: Vec<(u32, u32)> = (0..h.div_ceil(TILE))
        .flat_map(|ty| (0..w.div_ceil(TILE)).map(move |tx| (tx * TILE, ty * TILE)))
        .collect();
    progress.set_length(tiles.len() as u64);
    let rendered: Vec<(Vec<Pixel>, St)> = tiles
        .par_iter()
        .map(|&(x0, y0)| {
            let mut stats = St::default();
            let mut pixels = Vec::with_capacity((TILE * TILE) as usize);
            for y in y0..(y0 + TILE).min(h) {
                for x in x0..(x0 + TILE).min(w) {
                    pixels.push(pixel(camera, spp, background, x, y, &trace, &mut stats));
                }
            }
            progress.inc(1);
            (pixels, stats)
        })
        .collect();
    progress.finish_and_clear();
    let n = (w as usize) * (h as usize);
    let mut frame = Frame {
        width: w,
        height: h,
        rgba: vec![[0.0; 4]; n],
        direct: vec![[0.0; 3]; n],
        indirect: vec![[0.0; 3]; n],
        depth: vec![0.0; n],
    };
    let (tile_pixels, tile_stats): (Vec<Vec<Pixel>>, Vec<St>) = rendered.into_iter().unzip();
    let mut stats = St::default();
    for s in tile_stats {
        stats += s;
    }
    let tiles_per_row = w.div_ceil(TILE) as usize;
    // Each band of TILE image rows is filled by one task: a 1080p frame's four buffers are 90 MB,
    // too much to copy (and fault in) on one thread while the other cores wait.
    let band = (TILE * w) as usize;
    frame
        .rgba
        .par_chunks_mut(band)
        .zip(frame.direct.par_chunks_mut(band))
        .zip(frame.indirect.par_chunks_mut(band))
        .zip(frame.depth.par_chunks_mut(band))
        .zip(tile_pixels.par_chunks(tiles_per_row))
        .for_each(|((((rgba, direct), indirect), depth), tiles)| {
            for (t, pixels) in tiles.iter().enumerate() {
                let x0 = t * TILE as usize;
                let tw = (TILE as usize).min(w as usize - x0);
                for (i, p) in pixels.iter().enumerate() {
                    let at = (i / tw) * w as usize + x0 + i % tw;
                    rgba[at] = p.rgba;
                    direct[at] = p.direct;
                    indirect[at] = p.indirect;
                    depth[at] = p.depth;
                }
            }
        });
    (frame, stats)
}

/// One finished pixel.
struct Pixel {
    rgba: [f32; 4],
    direct: [f32; 3],
    indirect: [f32; 3],
    depth: f32,
}

fn pixel<St, F>(
    camera: &Camera,
    spp: u32,
    background: Option<Background>,
    x: u32,
    y: u32,
    trace: &F,
    stats: &mut St,
) -> Pixel
where
    F: Fn(CameraSample, &mut St) -> RayResult,
{
    let mut px = Pixel {
        rgba: [0.0; 4],
        direct: [0.0; 3],
        indirect: [0.0; 3],
        depth: 0.0,
    };
    let (mut depth_sum, mut alpha_sum) = (0.0f32, 0.0f32);
    let inv = 1.0 / spp as f32;
    for index in 0..spp {
        let off = pixel_offset(x, y, index, spp);
        let (origin, dir) = camera.ray(x as f32 + off.x, y as f32 + off.y);
        let sample = CameraSample {
            x,
            y,
            index,
            origin,
            dir,
        };
        let r = trace(sample, stats);
        let alpha = 1.0 - r.transmittance;
        let bg = background.map(|e| e(dir));
        for c in 0..3 {
            let behind = bg.map_or(0.0, |e| r.transmittance * e[c]);
            px.rgba[c] += inv * (r.direct[c] + r.indirect[c] + behind);
            px.direct[c] += inv * r.direct[c];
            px.indirect[c] += inv * r.indirect[c];
        }
        px.rgba[3] += inv * if bg.is_some() { 1.0 } else { alpha };
        depth_sum += r.depth * alpha;
        alpha_sum += alpha;
    }
    if alpha_sum > 0.0 {
        px.depth = depth_sum / alpha_sum;
    }
    px
}
