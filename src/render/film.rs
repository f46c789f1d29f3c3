//! The film: image tiles rendered in parallel, `spp` samples per pixel placed by
//! [`pixel_offset`] and averaged with a box filter, the environment added behind what each ray
//! leaves visible. Every renderer (the transfer march, the path tracer) supplies only what one
//! camera ray returns, so both share the same pixels, filter, layers and progress bar.

use std::ops::Range;
use std::time::{Duration, Instant};

use glam::Vec3;
use indicatif::ProgressBar;
use rayon::prelude::*;

use crate::render::camera::{pixel_offset, Camera};

/// Edge of the square image tiles handed to rayon: big enough to amortise scheduling, small enough
/// that both cores stay busy until the last tile even when the volume covers a corner of the frame.
const TILE: u32 = 32;

/// Pixels of a frame rendered together and handed on to be written ([`band_rows`]): 64 rows of a
/// 1080p frame, 5.5 MB of film with its layers and 120 tiles, enough to keep both cores busy to
/// the band's end, where holding a whole 1080p frame took 87 MB.
const BAND_PIXELS: u32 = 1 << 17;

/// Rows of a frame rendered at once when it is streamed to a file: about [`BAND_PIXELS`] pixels,
/// whole tiles tall.
pub fn band_rows(width: u32) -> u32 {
    (BAND_PIXELS / width.max(1) / TILE).max(1) * TILE
}

/// A frame's rows rendered on demand: rows `range` of the camera's image, as a [`Frame`] of
/// `range.len()` rows, with its layers when `layers` is true (else their vectors are empty). What
/// a renderer hands an image writer, which asks for one band at a time.
pub type Rows<'a> = dyn FnMut(Range<u32>, bool) -> Frame + Send + 'a;

/// The environment seen behind the volume: the radiance arriving along each world direction of
/// a batch (`out[i]` for `dirs[i]`). A tile row's samples are looked up together, so the map's
/// angles vectorise ([`crate::light::env::Environment::lookup_batch`]).
pub type Background<'a> = &'a (dyn Fn(&[Vec3], &mut [[f32; 3]]) + Sync);

/// A background from a function of one direction, looked up direction by direction (tests).
#[cfg(test)]
pub fn each_direction(
    f: impl Fn(Vec3) -> [f32; 3] + Sync,
) -> impl Fn(&[Vec3], &mut [[f32; 3]]) + Sync {
    move |dirs, out| {
        for (o, &d) in out.iter_mut().zip(dirs) {
            *o = f(d);
        }
    }
}

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

/// A rendered frame, or a band of one's rows: row-major, its first row at the top.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    /// Linear RGB (volume + Tr·background) and alpha (1 with a background, else 1 − Tr).
    pub rgba: Vec<[f32; 4]>,
    /// The layers, each empty in a frame rendered without them.
    pub direct: Vec<[f32; 3]>,
    pub indirect: Vec<[f32; 3]>,
    /// Opacity-weighted mean distance from the camera, world units; 0 where the ray hits nothing.
    pub depth: Vec<f32>,
}

/// A run of pixels of a frame's layers, the same pixels as a run of its `rgba`.
struct LayerRun<'a> {
    direct: &'a mut [[f32; 3]],
    indirect: &'a mut [[f32; 3]],
    depth: &'a mut [f32],
}

impl<'a> LayerRun<'a> {
    /// Cuts `run` into `count` runs of `len` pixels (the last may be shorter); a frame without
    /// layers (`None`) into `count` runs without.
    fn split(run: Option<LayerRun<'a>>, len: usize, count: usize) -> Vec<Option<LayerRun<'a>>> {
        match run {
            None => (0..count).map(|_| None).collect(),
            Some(r) => r
                .direct
                .chunks_mut(len)
                .zip(r.indirect.chunks_mut(len))
                .zip(r.depth.chunks_mut(len))
                .map(|((direct, indirect), depth)| {
                    Some(LayerRun {
                        direct,
                        indirect,
                        depth,
                    })
                })
                .collect(),
        }
    }
}

/// Renders rows `rows` of `camera`'s image (the whole frame: `0..camera.height`) with `spp`
/// samples (at least 1) per pixel, with the direct, indirect and depth layers when `layers` is
/// true (without, their vectors stay empty: 28 of a pixel's 44 bytes, faulted in and written for
/// nothing), calling `trace` for each camera ray with a per-tile statistics
/// accumulator and a scratch made by `scratch`, which a thread keeps across its tiles;
/// `background` (`None`: alpha only) is added behind each ray's transmittance. `progress` counts
/// the whole frame's tiles, advances by one per finished tile and is cleared with the last row.
#[allow(clippy::too_many_arguments)]
pub fn render_rows<St, Sc, F>(
    camera: &Camera,
    spp: u32,
    background: Option<Background>,
    progress: &ProgressBar,
    rows: Range<u32>,
    layers: bool,
    scratch: impl Fn() -> Sc + Sync + Send,
    trace: F,
) -> (Frame, St)
where
    St: Default + std::ops::AddAssign + Send,
    F: Fn(CameraSample, &mut St, &mut Sc) -> RayResult + Sync,
{
    let w = camera.width;
    let rows = rows.start.min(camera.height)..rows.end.min(camera.height);
    let (first_row, h) = (rows.start, rows.len() as u32);
    let spp = spp.max(1);
    let n = (w as usize) * (h as usize);
    let per_layer = if layers { n } else { 0 };
    let mut frame = Frame {
        width: w,
        height: h,
        rgba: vec![[0.0; 4]; n],
        direct: vec![[0.0; 3]; per_layer],
        indirect: vec![[0.0; 3]; per_layer],
        depth: vec![0.0; per_layer],
    };
    progress.set_length((w.div_ceil(TILE) * camera.height.div_ceil(TILE)) as u64);
    // Pixels go straight into the frame: each band of TILE rows is cut into the row segments of
    // its tiles, and the tiles of every band run in parallel. (Rendering tiles into buffers of
    // their own and copying them over cost a second 90 MB at 1080p, faulted in and copied.)
    let (band, width, tile) = ((TILE * w) as usize, w as usize, TILE as usize);
    let Frame {
        rgba,
        direct,
        indirect,
        depth,
        ..
    } = &mut frame;
    let layer_run = layers.then_some(LayerRun {
        direct,
        indirect,
        depth,
    });
    let layer_bands = LayerRun::split(layer_run, band, n.div_ceil(band));
    let tile_stats: Vec<St> = rgba
        .par_chunks_mut(band)
        .zip(layer_bands)
        .enumerate()
        .flat_map(|(b, (rgba, layers))| {
            let tiles_across = w.div_ceil(TILE) as usize;
            let mut tiles: Vec<Vec<Row>> = (0..tiles_across).map(|_| Vec::new()).collect();
            let layer_rows = LayerRun::split(layers, width, rgba.len() / width);
            for (rgba, layers) in rgba.chunks_mut(width).zip(layer_rows) {
                let segments =
                    rgba.chunks_mut(tile)
                        .zip(LayerRun::split(layers, tile, tiles_across));
                for (tile, (rgba, layers)) in tiles.iter_mut().zip(segments) {
                    tile.push(Row { rgba, layers });
                }
            }
            let y0 = first_row + b as u32 * TILE;
            tiles
                .into_par_iter()
                .enumerate()
                .map(move |(t, rows)| (t as u32 * TILE, y0, rows))
        })
        .map_init(&scratch, |scratch, (x0, y0, rows)| {
            let mut stats = St::default();
            let mut trace = |sample, stats: &mut St| trace(sample, stats, scratch);
            // One row of the tile at a time: its samples' rays, then their background in one
            // batch, then the march.
            let (n, spp) = ((TILE * spp) as usize, spp as usize);
            let (mut origins, mut dirs, mut behind) = (
                Vec::with_capacity(n),
                Vec::with_capacity(n),
                Vec::with_capacity(n),
            );
            for (dy, mut row) in rows.into_iter().enumerate() {
                let y = y0 + dy as u32;
                origins.clear();
                dirs.clear();
                for x in x0..x0 + row.rgba.len() as u32 {
                    for index in 0..spp as u32 {
                        let off = pixel_offset(x, y, index, spp as u32);
                        let (origin, dir) = camera.ray(x as f32 + off.x, y as f32 + off.y);
                        origins.push(origin);
                        dirs.push(dir);
                    }
                }
                if let Some(e) = background {
                    behind.clear();
                    behind.resize(dirs.len(), [0.0f32; 3]);
                    e(&dirs, &mut behind);
                }
                for (dx, rgba) in row.rgba.iter_mut().enumerate() {
                    let x = x0 + dx as u32;
                    let at = dx * spp..(dx + 1) * spp;
                    let samples = Samples {
                        origins: &origins[at.clone()],
                        dirs: &dirs[at.clone()],
                        behind: background.map(|_| &behind[at]),
                    };
                    let p = pixel(x, y, &samples, &mut trace, &mut stats);
                    *rgba = p.rgba;
                    if let Some(layers) = &mut row.layers {
                        layers.direct[dx] = p.direct;
                        layers.indirect[dx] = p.indirect;
                        layers.depth[dx] = p.depth;
                    }
                }
            }
            progress.inc(1);
            stats
        })
        .collect();
    if rows.end == camera.height {
        progress.finish_and_clear();
    }
    // Summed in tile order, so the totals never depend on scheduling.
    let mut stats = St::default();
    for s in tile_stats {
        stats += s;
    }
    (frame, stats)
}

/// Hands `consume` `camera`'s image row by row ([`Rows`]), each band it asks for rendered by
/// [`render_rows`] with `scratch` and `trace`. Returns what `consume` made, the statistics of every
/// row it asked for (summed in the order asked), and the time spent rendering them.
pub fn stream_rows<St, Sc, F, R>(
    camera: &Camera,
    spp: u32,
    background: Option<Background>,
    progress: &ProgressBar,
    scratch: impl Fn() -> Sc + Sync + Send,
    trace: F,
    consume: impl FnOnce(&mut Rows) -> R,
) -> (R, St, Duration)
where
    St: Default + std::ops::AddAssign + Send,
    F: Fn(CameraSample, &mut St, &mut Sc) -> RayResult + Sync,
{
    let (mut stats, mut time) = (St::default(), Duration::ZERO);
    let out = consume(&mut |rows, layers| {
        let t = Instant::now();
        let (frame, s) = render_rows(
            camera, spp, background, progress, rows, layers, &scratch, &trace,
        );
        stats += s;
        time += t.elapsed();
        frame
    });
    (out, stats, time)
}

/// One image row's part of a tile, in the frame's buffers.
struct Row<'a> {
    rgba: &'a mut [[f32; 4]],
    layers: Option<LayerRun<'a>>,
}

/// One finished pixel.
struct Pixel {
    rgba: [f32; 4],
    direct: [f32; 3],
    indirect: [f32; 3],
    depth: f32,
}

/// A pixel's camera samples: each one's ray (origin and unit direction) and, with a
/// background, the radiance behind it.
struct Samples<'a> {
    origins: &'a [Vec3],
    dirs: &'a [Vec3],
    behind: Option<&'a [[f32; 3]]>,
}

fn pixel<St>(
    x: u32,
    y: u32,
    samples: &Samples,
    trace: &mut impl FnMut(CameraSample, &mut St) -> RayResult,
    stats: &mut St,
) -> Pixel {
    let mut px = Pixel {
        rgba: [0.0; 4],
        direct: [0.0; 3],
        indirect: [0.0; 3],
        depth: 0.0,
    };
    let (mut depth_sum, mut alpha_sum) = (0.0f32, 0.0f32);
    let inv = 1.0 / samples.dirs.len() as f32;
    for (index, (&origin, &dir)) in samples.origins.iter().zip(samples.dirs).enumerate() {
        let sample = CameraSample {
            x,
            y,
            index: index as u32,
            origin,
            dir,
        };
        let r = trace(sample, stats);
        let alpha = 1.0 - r.transmittance;
        let bg = samples.behind.map(|b| b[index]);
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
