//! Output images: a linear-light RGBA buffer with optional extra layers of channels, written as OpenEXR
//! (f32 or half, every channel kept) or as a tonemapped 8-bit sRGB PNG — always atomically.

use std::io::{self, BufWriter, Seek, Write};
use std::ops::Range;
use std::path::Path;

use exr::block::chunk::Chunk;
use exr::block::writer::ChunksWriter;
use exr::block::{enumerate_ordered_header_block_indices, BlockIndex, UncompressedBlock};
use exr::meta::attribute::{ChannelDescription, LineOrder, SampleType, Text};
use exr::meta::header::Header;
use exr::meta::BlockDescription;
use exr::prelude::{f16, Compression, LayerAttributes, SmallVec};
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::io::atomic::{start_writeback, write_atomic};

/// Lines of an EXR compressed together before they are written: enough blocks to keep every core
/// busy, few enough that the compressed batch stays a few megabytes.
const EXR_BATCH_LINES: usize = 64;

/// A linear-light image. `rgba` is row-major with row 0 at the top, colour premultiplied by alpha
/// (the OpenEXR convention: a pixel the volume half covers over no background is (c·a, a)).
#[derive(Debug, Clone, PartialEq)]
pub struct ImageBuf {
    pub width: usize,
    pub height: usize,
    pub rgba: Vec<[f32; 4]>,
    /// Extra EXR layers (`direct`, `depth`, …). PNG output ignores them.
    pub layers: Vec<Layer>,
}

/// Extra channels of one EXR layer, written as `name.channel` (`direct.R`, `depth.Z`), with
/// their values interleaved pixel by pixel as a renderer keeps them: the writer reads them in
/// place, where splitting a 1080p frame into planes first copied (and faulted in) 60 MB.
#[derive(Debug, Clone, PartialEq)]
pub struct Layer {
    pub name: &'static str,
    pub channels: &'static [&'static str],
    /// `width·height·channels.len()` values, row-major like `rgba`.
    pub values: Vec<f32>,
}

/// One EXR channel read in place: sample i is `values[i·stride + offset]`.
struct ChannelView<'a> {
    name: String,
    values: &'a [f32],
    stride: usize,
    offset: usize,
}

/// Sample precision of EXR output.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ExrPrecision {
    #[default]
    Float,
    /// Half floats: half the size, 11 bits of mantissa, maximum 65504.
    Half,
}

/// How [`ImageBuf::write`] encodes the file it chooses by extension.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct WriteOptions {
    /// PNG only: exposure in stops (EV) applied before the tonemap.
    pub exposure: f32,
    /// EXR only.
    pub precision: ExrPrecision,
    /// A fingerprint of what made the image, stored in it (an EXR attribute, a PNG text chunk)
    /// so a sequence render can tell a current image from a stale one ([`read_fingerprint`]).
    pub fingerprint: Option<u64>,
}

/// The name of the fingerprint in an EXR header and a PNG text chunk.
const FINGERPRINT_KEY: &str = "vscatterFingerprint";

/// The fingerprint stored in the image at `path` by [`ImageBuf::write`]; `None` when the file is
/// missing, unreadable or has none.
pub fn read_fingerprint(path: &Path) -> Option<u64> {
    let text = match path
        .extension()?
        .to_string_lossy()
        .to_ascii_lowercase()
        .as_str()
    {
        "exr" => {
            let meta = exr::meta::MetaData::read_from_file(path, false).ok()?;
            match meta
                .headers
                .first()?
                .own_attributes
                .other
                .get(&Text::from(FINGERPRINT_KEY))?
            {
                exr::meta::attribute::AttributeValue::Text(t) => t.to_string(),
                _ => return None,
            }
        }
        "png" => {
            let file = std::io::BufReader::new(std::fs::File::open(path).ok()?);
            let reader = png::Decoder::new(file).read_info().ok()?;
            let chunk = reader
                .info()
                .uncompressed_latin1_text
                .iter()
                .find(|c| c.keyword == FINGERPRINT_KEY)?;
            chunk.text.clone()
        }
        _ => return None,
    };
    u64::from_str_radix(&text, 16).ok()
}

impl ImageBuf {
    /// A transparent black image.
    pub fn new(width: usize, height: usize) -> Self {
        ImageBuf {
            width,
            height,
            rgba: vec![[0.0; 4]; width * height],
            layers: Vec::new(),
        }
    }

    /// An opaque image from RGB pixels (row-major, row 0 at the top).
    pub fn from_rgb(width: usize, height: usize, rgb: &[[f32; 3]]) -> Self {
        ImageBuf {
            width,
            height,
            rgba: rgb.iter().map(|&[r, g, b]| [r, g, b, 1.0]).collect(),
            layers: Vec::new(),
        }
    }

    /// Writes EXR or PNG according to the extension of `path` (case-insensitive). Consumes the
    /// image: the EXR writer reads its channels in place instead of copying them.
    pub fn write(self, path: &Path, options: &WriteOptions) -> Result<()> {
        let height = self.height;
        let mut whole = Some(self);
        write_bands(path, options, height, height, &mut |_| {
            whole
                .take()
                .ok_or_else(|| Error::Runtime("an image asked for twice".into()))
        })
    }

    /// Checks the buffer sizes, so a caller's mistake is an error instead of a corrupt file.
    fn check(&self) -> Result<()> {
        let n = self.width * self.height;
        if n == 0 {
            return Err(Error::Runtime(format!(
                "cannot write an empty {}x{} image",
                self.width, self.height
            )));
        }
        if self.rgba.len() != n {
            return Err(Error::Runtime(format!(
                "image has {} pixels, expected {n}",
                self.rgba.len()
            )));
        }
        let mut names = vec![];
        for layer in &self.layers {
            if layer.values.len() != n * layer.channels.len()
                || layer.name.is_empty()
                || layer.channels.is_empty()
                || layer.channels.iter().any(|c| c.is_empty())
            {
                return Err(Error::Runtime(format!(
                    "extra layer {:?}: bad name or {} values, expected {n} per channel",
                    layer.name,
                    layer.values.len()
                )));
            }
            names.extend(layer.channels.iter().map(|c| (layer.name, *c)));
        }
        names.sort();
        if names.windows(2).any(|w| w[0] == w[1]) {
            return Err(Error::Runtime("extra layers repeat a channel".into()));
        }
        Ok(())
    }

    /// Checks that `self`, asked for as rows `rows` of an image whose first band is `first`, fits
    /// it: as wide, as many rows as asked, the same layers.
    fn check_band(self, first: (usize, &[(&str, &[&str])]), rows: &Range<usize>) -> Result<Self> {
        self.check()?;
        let layers: Vec<(&str, &[&str])> =
            self.layers.iter().map(|l| (l.name, l.channels)).collect();
        if self.width != first.0 || self.height != rows.len() || layers != first.1 {
            return Err(Error::Runtime(format!(
                "rows {rows:?} came as {}x{} with other layers than the image's",
                self.width, self.height
            )));
        }
        Ok(self)
    }

    /// Every channel as a strided view of the buffers, in name order (as EXR stores them).
    fn channel_views(&self) -> Vec<ChannelView<'_>> {
        let rgba = self.rgba.as_flattened();
        let mut views: Vec<ChannelView> = ["R", "G", "B", "A"]
            .iter()
            .enumerate()
            .map(|(offset, name)| ChannelView {
                name: name.to_string(),
                values: rgba,
                stride: 4,
                offset,
            })
            .collect();
        for layer in &self.layers {
            for (offset, channel) in layer.channels.iter().enumerate() {
                views.push(ChannelView {
                    name: format!("{}.{channel}", layer.name),
                    values: &layer.values,
                    stride: layer.channels.len(),
                    offset,
                });
            }
        }
        views.sort_by(|a, b| a.name.cmp(&b.name));
        views
    }
}

/// Where [`write_bands`] gets an image's rows: rows `range` as an [`ImageBuf`] `range.len()` rows
/// tall, as wide and with the same layers as every other band of the image.
pub type BandSource<'a> = dyn FnMut(Range<usize>) -> Result<ImageBuf> + Send + 'a;

/// Writes an image `height` rows tall, EXR or PNG by the extension of `path` (case-insensitive),
/// asking `rows` for `band_rows` rows at a time, top to bottom, so only a few bands are ever held:
/// a renderer renders each band while the one before is compressed and written. An error from
/// `rows` aborts the write and is returned as it is; the final name is never half-written.
pub fn write_bands(
    path: &Path,
    options: &WriteOptions,
    height: usize,
    band_rows: usize,
    rows: &mut BandSource,
) -> Result<()> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase());
    let png = match ext.as_deref() {
        Some("exr") => false,
        Some("png") => true,
        _ => {
            return Err(Error::usage(format!(
                "{}: output must end in .exr or .png",
                path.display()
            )))
        }
    };
    if height == 0 {
        return Err(Error::Runtime("cannot write an image with no rows".into()));
    }
    let band_rows = band_rows.clamp(1, height);
    let first_rows = 0..band_rows;
    let first = rows(first_rows.clone())?;
    let layers: Vec<(&'static str, &'static [&'static str])> =
        first.layers.iter().map(|l| (l.name, l.channels)).collect();
    let width = first.width;
    let first = first.check_band((width, &layers), &first_rows)?;
    let mut next = |y0: usize| -> Result<Option<ImageBuf>> {
        if y0 >= height {
            return Ok(None);
        }
        let range = y0..(y0 + band_rows).min(height);
        rows(range.clone())?
            .check_band((width, &layers), &range)
            .map(Some)
    };
    let bands = Bands {
        height,
        first,
        next: &mut next,
    };
    match png {
        true => write_png(path, options, bands),
        false => write_exr(path, options, bands),
    }
}

/// The band starting at row `y0`, or `None` past the last row.
type NextBand<'a> = dyn FnMut(usize) -> Result<Option<ImageBuf>> + Send + 'a;

/// An image's bands as a format's writer takes them: the first, already checked, and the rest
/// on demand.
struct Bands<'a, 'b> {
    height: usize,
    first: ImageBuf,
    next: &'a mut NextBand<'b>,
}

/// Writes a single-part scanline EXR, RLE-compressed, with channels R, G, B, A and every layer's.
///
/// Through the `exr` crate's block interface rather than its image writer: scanline blocks are
/// assembled from the bands in place and compressed in parallel, [`EXR_BATCH_LINES`] at a time,
/// while the previous batch is written out and the next band is made.
/// The image writer extracts every line on one thread, which made a 1080p frame's write a quarter
/// of the render's wall time.
fn write_exr(path: &Path, options: &WriteOptions, bands: Bands) -> Result<()> {
    let Bands {
        height,
        first,
        next,
    } = bands;
    let (width, precision) = (first.width, options.precision);
    let sample_type = match precision {
        ExrPrecision::Float => SampleType::F32,
        ExrPrecision::Half => SampleType::F16,
    };
    let channels = first
        .channel_views()
        .iter()
        .map(|v| ChannelDescription::named(v.name.as_str(), sample_type))
        .collect();
    // RLE: lossless and several times faster to write than ZIP on 1080p frames with eleven
    // float channels (ZIP took 0.6–1.1 s, as long as the march); compositors read both.
    let header = Header::new(Text::default(), (width, height), channels)
        .with_encoding(
            Compression::RLE,
            BlockDescription::ScanLines,
            LineOrder::Increasing,
        )
        .with_attributes(layer_attributes(options.fingerprint));
    // The bands' own error, kept apart from the writer's I/O errors.
    let mut failure: Option<Error> = None;
    let written = write_atomic(path, |w: &mut BufWriter<std::fs::File>| {
        // The same open file, for starting each band's writeback while the writer holds `w`.
        let file = w.get_ref().try_clone()?;
        exr::block::write(w, SmallVec::from_elem(header, 1), true, |meta, chunks| {
            let blocks: Vec<(usize, BlockIndex)> =
                enumerate_ordered_header_block_indices(&meta.headers).collect();
            let per_batch = EXR_BATCH_LINES
                .div_ceil(meta.headers[0].compression.scan_lines_per_block())
                .max(1);
            let compress = |batch: &[(usize, BlockIndex)], views: &[ChannelView], y0: usize| {
                batch
                    .par_iter()
                    .map(|&(i, index)| {
                        let block = UncompressedBlock {
                            index,
                            data: block_bytes(views, width, y0, precision, &index),
                        };
                        (i, block.compress_to_chunk(&meta.headers))
                    })
                    .collect::<Vec<_>>()
            };
            // A band's lines are compressed and written while the next band is made, so the
            // cores a band's last tiles leave idle compress, and none waits at a band's end.
            let mut store = |band: ImageBuf, y0: usize, at: usize| -> exr::error::Result<usize> {
                let y1 = y0 + band.height;
                let end = blocks[at..]
                    .iter()
                    .position(|(_, b)| b.pixel_position.y() >= y1)
                    .map_or(blocks.len(), |p| at + p);
                let views = band.channel_views();
                let mut written: Vec<(usize, exr::error::Result<Chunk>)> = Vec::new();
                let mut flush = |written: &mut Vec<(usize, exr::error::Result<Chunk>)>| {
                    for (i, chunk) in written.drain(..) {
                        chunks.write_chunk(i, chunk?)?;
                    }
                    exr::error::UnitResult::Ok(())
                };
                // Batch k is written while batch k + 1 is compressed: writing is one thread's
                // work.
                for batch in blocks[at..end].chunks(per_batch) {
                    let (done, compressed) =
                        rayon::join(|| flush(&mut written), || compress(batch, &views, y0));
                    done?;
                    written = compressed;
                }
                flush(&mut written)?;
                start_writeback(&file);
                Ok(end)
            };
            let (mut band, mut y0, mut at) = (first, 0, 0);
            loop {
                let y1 = y0 + band.height;
                let (stored, made) = rayon::join(|| store(band, y0, at), || next(y1));
                at = stored?;
                match made {
                    Ok(Some(b)) => (band, y0) = (b, y1),
                    Ok(None) => return Ok(()),
                    Err(e) => {
                        failure = Some(e);
                        return Err(exr::error::Error::Aborted);
                    }
                }
            }
        })
        .map_err(exr_to_io)
    });
    match failure {
        Some(e) => Err(e),
        None => written,
    }
}

/// Writes an 8-bit sRGB PNG: exposure 2^EV, the ACES filmic tonemap, then the sRGB curve. Fully
/// opaque images become RGB; otherwise RGBA with straight (un-premultiplied) alpha, as PNG
/// expects. The bands are tonemapped as they come, so only the 8-bit pixels are held.
fn write_png(path: &Path, options: &WriteOptions, bands: Bands) -> Result<()> {
    let Bands {
        height,
        first,
        next,
    } = bands;
    let scale = options.exposure.exp2();
    let width = first.width;
    let (Ok(w32), Ok(h32)) = (u32::try_from(width), u32::try_from(height)) else {
        return Err(Error::Runtime(format!(
            "{width}x{height} is too large for PNG"
        )));
    };
    let mut bytes = vec![0u8; width * height * 4];
    let mut opaque = true;
    let (mut band, mut y0) = (first, 0);
    loop {
        let out = &mut bytes[y0 * width * 4..(y0 + band.height) * width * 4];
        out.par_chunks_mut(width * 4)
            .zip(band.rgba.par_chunks(width))
            .for_each(|(out, row)| {
                for (o, p) in out.chunks_exact_mut(4).zip(row) {
                    let a = p[3].clamp(0.0, 1.0);
                    let unpremultiply = if a <= 0.0 { 1.0 } else { 1.0 / a };
                    for (o, &c) in o.iter_mut().zip(&p[..3]) {
                        *o = to_u8(srgb_encode(tonemap_aces(c * unpremultiply * scale)));
                    }
                    o[3] = to_u8(a);
                }
            });
        opaque &= band.rgba.iter().all(|p| p[3] >= 1.0);
        y0 += band.height;
        match next(y0)? {
            Some(b) => band = b,
            None => break,
        }
    }
    if opaque {
        // RGBA to RGB in place: pixel i's three bytes move down to 3i, never past unread ones.
        for i in 0..width * height {
            bytes.copy_within(4 * i..4 * i + 3, 3 * i);
        }
        bytes.truncate(width * height * 3);
    }
    write_atomic(path, |out| {
        encode_png(out, w32, h32, opaque, &bytes, options.fingerprint)
    })
}

/// One EXR block's bytes: for each of its lines, each channel's samples (native endian), read
/// from `views` of the band whose first row is `y0`.
fn block_bytes(
    views: &[ChannelView],
    width: usize,
    y0: usize,
    precision: ExrPrecision,
    index: &BlockIndex,
) -> Vec<u8> {
    let (x, w) = (index.pixel_position.x(), index.pixel_size.x());
    let rows = index.pixel_position.y()..index.pixel_position.y() + index.pixel_size.y();
    let bytes = match precision {
        ExrPrecision::Float => 4,
        ExrPrecision::Half => 2,
    };
    let mut data = vec![0u8; rows.len() * w * views.len() * bytes];
    // Line by line, channel by channel: one output line per (row, channel).
    let lines = rows.flat_map(|y| views.iter().map(move |v| (y, v)));
    for (line, (y, v)) in data.chunks_exact_mut(w * bytes).zip(lines) {
        let first = ((y - y0) * width + x) * v.stride + v.offset;
        let row = v.values[first..].iter().step_by(v.stride);
        let samples = line.chunks_exact_mut(bytes).zip(row);
        match precision {
            ExrPrecision::Float => samples.for_each(|(o, v)| o.copy_from_slice(&v.to_ne_bytes())),
            ExrPrecision::Half => {
                samples.for_each(|(o, v)| o.copy_from_slice(&f16::from_f32(*v).to_ne_bytes()))
            }
        }
    }
    data
}

/// The EXR layer's attributes: the fingerprint, when there is one.
fn layer_attributes(fingerprint: Option<u64>) -> LayerAttributes {
    let mut attributes = LayerAttributes::default();
    if let Some(f) = fingerprint {
        attributes.other.insert(
            Text::from(FINGERPRINT_KEY),
            exr::meta::attribute::AttributeValue::Text(Text::from(format!("{f:016x}").as_str())),
        );
    }
    attributes
}

fn encode_png<W: Write + Seek>(
    out: &mut W,
    w: u32,
    h: u32,
    opaque: bool,
    bytes: &[u8],
    fingerprint: Option<u64>,
) -> io::Result<()> {
    let mut enc = png::Encoder::new(out, w, h);
    enc.set_color(if opaque {
        png::ColorType::Rgb
    } else {
        png::ColorType::Rgba
    });
    enc.set_depth(png::BitDepth::Eight);
    // fdeflate's fast mode: PNG is the preview format, written after the last band on one thread.
    // On the bench cloud's 1920×1080 frame it took the write's tail from 0.19 to 0.06 s for a
    // file of 452 KB instead of 362 KB.
    enc.set_compression(png::Compression::Fast);
    enc.set_source_srgb(png::SrgbRenderingIntent::Perceptual);
    if let Some(f) = fingerprint {
        enc.add_text_chunk(FINGERPRINT_KEY.into(), format!("{f:016x}"))
            .map_err(png_to_io)?;
    }
    let mut writer = enc.write_header().map_err(png_to_io)?;
    writer.write_image_data(bytes).map_err(png_to_io)?;
    writer.finish().map_err(png_to_io)
}

/// The first RGB(A) layer of an OpenEXR file (alpha 1 where the file has none), after `check`
/// has accepted the size of every part — before the pixel reader allocates anything.
pub fn read_exr_rgba(
    path: &Path,
    check: impl Fn(usize, usize) -> Result<()>,
) -> Result<(usize, usize, Vec<[f32; 4]>)> {
    use exr::prelude::{read_first_rgba_layer_from_file, MetaData};
    let bad = |e: exr::error::Error| match e {
        exr::error::Error::Io(io) if io.kind() != std::io::ErrorKind::UnexpectedEof => {
            Error::io(path, io)
        }
        exr::error::Error::Io(_) => Error::format(path, "truncated OpenEXR file"),
        other => Error::format(
            path,
            format!("unreadable OpenEXR file (truncated or corrupt?): {other}"),
        ),
    };
    // Check the sizes in the headers before the pixel reader allocates anything; every part, since
    // the reader takes the first one with R, G, B channels, which need not be the first.
    let meta = MetaData::read_from_file(path, false).map_err(bad)?;
    if meta.headers.is_empty() {
        return Err(Error::format(path, "OpenEXR file has no image part"));
    }
    for header in &meta.headers {
        check(header.layer_size.width(), header.layer_size.height())?;
    }
    let image = read_first_rgba_layer_from_file(
        path,
        |size, _| {
            (
                size.width(),
                vec![[0.0f32; 4]; size.width() * size.height()],
            )
        },
        |(w, px): &mut (usize, Vec<[f32; 4]>), pos, (r, g, b, a): (f32, f32, f32, f32)| {
            px[pos.y() * *w + pos.x()] = [r, g, b, a];
        },
    )
    .map_err(|e| match e {
        // exr's words for "no part has the channels asked for".
        exr::error::Error::Invalid(msg) if msg.contains("no layer") => {
            Error::format(path, "OpenEXR file has no layer with R, G and B channels")
        }
        other => bad(other),
    })?;
    let size = image.layer_data.size;
    Ok((
        size.width(),
        size.height(),
        image.layer_data.channel_data.pixels.1,
    ))
}

fn exr_to_io(e: exr::error::Error) -> io::Error {
    match e {
        exr::error::Error::Io(e) => e,
        other => io::Error::other(other.to_string()),
    }
}

fn png_to_io(e: png::EncodingError) -> io::Error {
    match e {
        png::EncodingError::IoError(e) => e,
        other => io::Error::other(other.to_string()),
    }
}

fn to_u8(x: f32) -> u8 {
    // NaN maps to 0: `as` saturates and sends NaN to 0.
    (x.clamp(0.0, 1.0) * 255.0 + 0.5) as u8
}

/// The ACES filmic tonemap as fitted by Narkowicz (2015, "ACES Filmic Tone Mapping Curve"): a
/// rational curve close to the ACES reference rendering transform, with a gentle toe, a long
/// shoulder that keeps bright sun-lit cloud tops from clipping abruptly, and mid-grey 0.18 ↦ ≈0.27.
/// Input linear scene values, output display-linear in [0, 1].
pub fn tonemap_aces(x: f32) -> f32 {
    const A: f32 = 2.51;
    const B: f32 = 0.03;
    const C: f32 = 2.43;
    const D: f32 = 0.59;
    const E: f32 = 0.14;
    let x = x.max(0.0);
    ((x * (A * x + B)) / (x * (C * x + D) + E)).clamp(0.0, 1.0)
}

/// The sRGB transfer curve (IEC 61966-2-1): display-linear [0, 1] to encoded [0, 1].
pub fn srgb_encode(x: f32) -> f32 {
    if x <= 0.003_130_8 {
        12.92 * x.max(0.0)
    } else {
        1.055 * x.powf(1.0 / 2.4) - 0.055
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use exr::prelude::read_all_flat_layers_from_file;

    fn test_image() -> ImageBuf {
        let mut img = ImageBuf::new(3, 2);
        for (i, p) in img.rgba.iter_mut().enumerate() {
            *p = [i as f32, 0.5, 2.0, 1.0];
        }
        img.layers.push(Layer {
            name: "depth",
            channels: &["Z"],
            values: (0..6).map(|i| i as f32 * 10.0).collect(),
        });
        img.layers.push(Layer {
            name: "direct",
            channels: &["R", "G", "B"],
            values: (0..18).map(|i| i as f32).collect(),
        });
        img
    }

    #[test]
    fn exr_round_trips_with_extra_channels() {
        let dir = tempfile::tempdir().unwrap();
        for precision in [ExrPrecision::Float, ExrPrecision::Half] {
            let path = dir.path().join("t.exr");
            test_image()
                .write(
                    &path,
                    &WriteOptions {
                        precision,
                        ..WriteOptions::default()
                    },
                )
                .unwrap();
            let image = read_all_flat_layers_from_file(&path).unwrap();
            let channels = &image.layer_data[0].channel_data.list;
            let names: Vec<String> = channels.iter().map(|c| c.name.to_string()).collect();
            assert_eq!(
                names,
                ["A", "B", "G", "R", "depth.Z", "direct.B", "direct.G", "direct.R"]
            );
            let r: Vec<f32> = channels[3].sample_data.values_as_f32().collect();
            assert_eq!(r, [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]);
            let z: Vec<f32> = channels[4].sample_data.values_as_f32().collect();
            assert_eq!(z[5], 50.0);
            // Interleaved layer values land in their own channels.
            let g: Vec<f32> = channels[6].sample_data.values_as_f32().collect();
            assert_eq!(g, [1.0, 4.0, 7.0, 10.0, 13.0, 16.0]);
        }
    }

    #[test]
    fn png_is_written_and_extension_checked() {
        let dir = tempfile::tempdir().unwrap();
        let img = test_image();
        let path = dir.path().join("t.png");
        img.clone().write(&path, &WriteOptions::default()).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(&bytes[1..4], b"PNG");
        assert!(matches!(
            img.write(&dir.path().join("t.jpg"), &WriteOptions::default()),
            Err(Error::Usage(_))
        ));
    }

    #[test]
    fn fingerprints_are_stored_in_exr_and_png() {
        let dir = tempfile::tempdir().unwrap();
        for name in ["f.exr", "f.png"] {
            let path = dir.path().join(name);
            let options = WriteOptions {
                fingerprint: Some(0xfeed_beef_0123_4567),
                ..WriteOptions::default()
            };
            test_image().write(&path, &options).unwrap();
            assert_eq!(
                read_fingerprint(&path),
                Some(0xfeed_beef_0123_4567),
                "{name}"
            );
            test_image().write(&path, &WriteOptions::default()).unwrap();
            assert_eq!(read_fingerprint(&path), None, "{name}");
        }
        assert_eq!(read_fingerprint(&dir.path().join("missing.exr")), None);
    }

    /// Rows `range` of `image`, as a band of it.
    fn band_of(image: &ImageBuf, range: Range<usize>) -> ImageBuf {
        let w = image.width;
        ImageBuf {
            width: w,
            height: range.len(),
            rgba: image.rgba[range.start * w..range.end * w].to_vec(),
            layers: image
                .layers
                .iter()
                .map(|l| {
                    let c = l.channels.len();
                    Layer {
                        values: l.values[range.start * w * c..range.end * w * c].to_vec(),
                        ..l.clone()
                    }
                })
                .collect(),
        }
    }

    #[test]
    fn bands_write_the_same_file_as_the_whole_image() {
        let dir = tempfile::tempdir().unwrap();
        let mut image = test_image();
        image.rgba[4][3] = 0.5;
        for name in ["b.exr", "b.png"] {
            for opaque in [true, false] {
                let mut image = image.clone();
                if opaque {
                    image.rgba.iter_mut().for_each(|p| p[3] = 1.0);
                }
                let (whole, bands) = (dir.path().join(name), dir.path().join(format!("1{name}")));
                image
                    .clone()
                    .write(&whole, &WriteOptions::default())
                    .unwrap();
                let mut asked = Vec::new();
                write_bands(&bands, &WriteOptions::default(), 2, 1, &mut |r| {
                    asked.push(r.clone());
                    Ok(band_of(&image, r))
                })
                .unwrap();
                assert_eq!(asked, [0..1, 1..2]);
                assert_eq!(
                    std::fs::read(&whole).unwrap(),
                    std::fs::read(&bands).unwrap()
                );
            }
        }
    }

    #[test]
    fn a_failing_or_misfit_band_aborts_the_write() {
        let dir = tempfile::tempdir().unwrap();
        let image = test_image();
        for name in ["f.exr", "f.png"] {
            let path = dir.path().join(name);
            let failed = write_bands(
                &path,
                &WriteOptions::default(),
                2,
                1,
                &mut |r| match r.start {
                    0 => Ok(band_of(&image, r)),
                    _ => Err(Error::Runtime("the renderer stopped".into())),
                },
            );
            assert_eq!(failed.unwrap_err().to_string(), "the renderer stopped");
            // A band of the wrong height is refused, not written.
            let misfit = write_bands(&path, &WriteOptions::default(), 2, 1, &mut |_| {
                Ok(band_of(&image, 0..2))
            });
            assert!(misfit.unwrap_err().to_string().contains("rows 0..1"));
        }
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn mismatched_extra_layer_is_an_error() {
        let bad = [
            Layer {
                name: "bad",
                channels: &["Z"],
                values: vec![1.0],
            },
            Layer {
                name: "",
                channels: &["Z"],
                values: vec![1.0; 6],
            },
            Layer {
                name: "depth",
                channels: &["Z"],
                values: vec![1.0; 6],
            },
        ];
        let dir = tempfile::tempdir().unwrap();
        for layer in bad {
            let mut img = test_image();
            img.layers.push(layer);
            assert!(img
                .write(&dir.path().join("x.exr"), &WriteOptions::default())
                .is_err());
        }
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn tonemap_and_srgb_are_monotone_and_bounded() {
        assert_eq!(tonemap_aces(0.0), 0.0);
        assert!((tonemap_aces(1e6) - 1.0).abs() < 1e-3);
        assert!((srgb_encode(1.0) - 1.0).abs() < 1e-6);
        let mut last = -1.0;
        for i in 0..1000 {
            let v = srgb_encode(tonemap_aces(i as f32 * 0.01));
            assert!(v >= last);
            last = v;
        }
    }
}
