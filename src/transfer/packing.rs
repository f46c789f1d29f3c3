//! How a `.vtc` stores its arrays compactly: numbers at a chosen [`Precision`], byte-shuffled in
//! chunks (the bytes of like significance side by side, as Blosc does for VDB files) and
//! compressed with zstd, one frame per section.
//!
//! Measured on the quarter-size bench cloud (21.4 M active voxels, 125 679 transfer voxels): the
//! shuffle takes zstd from 15.3 to 13.6 MB on the f32 density and from 22.2 to 20.7 MB on f16
//! coefficients; zstd levels 1–15 all land within 4 % of level 3, which compresses 25 MB in 0.3 s.

use std::io::{BufRead, Read, Write};

use serde::{Deserialize, Serialize};

use super::coefficients::{bands_of, Coefficients, Q8_MAX};

/// zstd's level: the default, as fast as level 1 on these arrays and as small as level 15.
const ZSTD_LEVEL: i32 = 3;
/// Values shuffled together: large enough that each byte plane is a long run for zstd, small
/// enough that writing never holds more than a chunk uncompressed.
const CHUNK_VALUES: usize = 1 << 14;

/// How a cache stores the transfer's coefficients (and with them, where it fits, the density).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    /// 32-bit floats: the bake exactly.
    F32,
    /// 16-bit floats, the density too: half the size; images move by about 0.01 %
    /// (docs/cache-format.md).
    F16,
    /// 8 bits per coefficient scaled per voxel and band, the DC term and the density as 16-bit
    /// floats: a third of the size; images move by 0.01–0.07 % (docs/cache-format.md).
    ///
    /// The default: no render measured moved by more than 0.07 % relative RMSE (the fixtures at
    /// σt 1 and 0.1 under studio, split and the built-in sky; the quarter-size bench cloud), while
    /// a cache is a third of f32's (1.86× the quarter-size cloud's VDB, against 5.7×) and a render
    /// holds the density as f16. A bake is held at its precision before it renders
    /// ([`super::cache::as_stored`]), so a render of a VDB and one of its cache are the same image.
    #[default]
    Q8,
}

impl Precision {
    /// The name in the cache header and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Precision::F32 => "f32",
            Precision::F16 => "f16",
            Precision::Q8 => "q8",
        }
    }

    /// Whether the density may be stored as f16 (it then is, if every value fits).
    pub fn density_f16(self) -> bool {
        self != Precision::F32
    }
}

/// The f16 nearest `v` (infinite beyond f16's range: [`fits_f16`] tells before the density is
/// stored so; the transfer's coefficients, fractions of √(4π), are far inside it).
fn to_f16(v: f32) -> half::f16 {
    half::f16::from_f32(v)
}

/// Whether every value survives as a finite f16 (density stored as f16 only then).
pub fn fits_f16(values: impl IntoIterator<Item = f32>) -> bool {
    values.into_iter().all(|v| to_f16(v).is_finite())
}

/// One section being written: raw bytes and shuffled values go in, a zstd frame comes out.
pub struct SectionWriter {
    encoder: zstd::stream::Encoder<'static, Vec<u8>>,
}

impl SectionWriter {
    pub fn new() -> std::io::Result<Self> {
        Ok(SectionWriter {
            encoder: zstd::stream::Encoder::new(Vec::new(), ZSTD_LEVEL)?,
        })
    }

    /// Bytes as they are.
    pub fn bytes(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        self.encoder.write_all(bytes)
    }

    /// Values of `W` bytes each, shuffled chunk by chunk: byte 0 of every value of the chunk, then
    /// byte 1, and so on.
    pub fn shuffled<const W: usize>(
        &mut self,
        values: impl IntoIterator<Item = [u8; W]>,
    ) -> std::io::Result<()> {
        let mut chunk: Vec<[u8; W]> = Vec::with_capacity(CHUNK_VALUES);
        let mut planes = Vec::with_capacity(CHUNK_VALUES * W);
        let mut flush = |chunk: &mut Vec<[u8; W]>, encoder: &mut zstd::stream::Encoder<_>| {
            planes.clear();
            for b in 0..W {
                planes.extend(chunk.iter().map(|v| v[b]));
            }
            chunk.clear();
            encoder.write_all(&planes)
        };
        for v in values {
            chunk.push(v);
            if chunk.len() == CHUNK_VALUES {
                flush(&mut chunk, &mut self.encoder)?;
            }
        }
        if !chunk.is_empty() {
            flush(&mut chunk, &mut self.encoder)?;
        }
        Ok(())
    }

    /// The compressed section.
    pub fn finish(self) -> std::io::Result<Vec<u8>> {
        self.encoder.finish()
    }
}

/// One section being read, decompressed as it streams in: exactly the bytes its writer put in,
/// or an error.
pub struct SectionReader<'a> {
    decoder: zstd::stream::read::Decoder<'static, Box<dyn BufRead + 'a>>,
}

type Parse<T> = std::result::Result<T, String>;

impl<'a> SectionReader<'a> {
    /// Reads the compressed section `frame` yields, to its end.
    pub fn new(frame: impl BufRead + 'a) -> Parse<Self> {
        zstd::stream::read::Decoder::with_buffer(Box::new(frame) as Box<dyn BufRead + 'a>)
            .map(|decoder| SectionReader { decoder })
            .map_err(|e| format!("a compressed section is damaged: {e}"))
    }

    /// The next `n` bytes. The buffer grows only as data arrives, so a count that lies costs no
    /// more memory than the section really holds.
    pub fn bytes(&mut self, n: usize) -> Parse<Vec<u8>> {
        self.values::<1, u8>(n, |[b]| b)
    }

    /// `n` values of `W` bytes, shuffled as [`SectionWriter::shuffled`] wrote them, each decoded
    /// by `decode`. The output grows a chunk at a time up to `n`, doubling at most, so a count
    /// that lies costs no more than twice what the section really holds and a true count ends
    /// with nothing spare.
    pub fn values<const W: usize, T>(
        &mut self,
        n: usize,
        decode: impl Fn([u8; W]) -> T,
    ) -> Parse<Vec<T>> {
        let mut out: Vec<T> = Vec::new();
        self.each_chunk(n, decode, |chunk| {
            let m = chunk.len();
            if out.capacity() - out.len() < m {
                out.reserve_exact((n - out.len()).min(out.len().max(m)));
            }
            out.append(chunk);
            Ok(())
        })?;
        Ok(out)
    }

    /// `n` values as [`SectionReader::values`] decodes them, handed to `take` a chunk at a time
    /// as they arrive, so a caller can put each where it belongs without holding them all.
    pub fn each_chunk<const W: usize, T>(
        &mut self,
        n: usize,
        decode: impl Fn([u8; W]) -> T,
        mut take: impl FnMut(&mut Vec<T>) -> Parse<()>,
    ) -> Parse<()> {
        let mut planes = vec![0u8; n.min(CHUNK_VALUES) * W];
        let mut chunk = Vec::with_capacity(n.min(CHUNK_VALUES));
        let mut done = 0;
        while done < n {
            let m = (n - done).min(CHUNK_VALUES);
            let planes = &mut planes[..m * W];
            self.decoder
                .read_exact(planes)
                .map_err(|e| match e.kind() {
                    std::io::ErrorKind::UnexpectedEof => {
                        "a compressed section is shorter than the header says".to_string()
                    }
                    _ => format!("a compressed section is damaged: {e}"),
                })?;
            // One slice per byte plane, each m long, so the gather below needs no bounds checks.
            let planes: [&[u8]; W] = std::array::from_fn(|b| &planes[b * m..(b + 1) * m]);
            chunk.clear();
            chunk.extend((0..m).map(|i| decode(std::array::from_fn(|b| planes[b][i]))));
            take(&mut chunk)?;
            done += m;
        }
        Ok(())
    }

    /// Checks that the section holds nothing more.
    pub fn finish(mut self) -> Parse<()> {
        let mut extra = [0u8; 1];
        match self.decoder.read(&mut extra) {
            Ok(0) => Ok(()),
            Ok(_) => Err("a compressed section is longer than the header says".into()),
            Err(e) => Err(format!("a compressed section is damaged: {e}")),
        }
    }
}

/// `values`, `coeffs` per voxel, held at `precision` as a cache stores them. For q8, each voxel's
/// DC term is an f16; each higher band l has an f16 scale s ≥ max |c| over its 2l + 1
/// coefficients and stores round(127·c/s) in a signed byte.
pub fn encode(values: &[f32], coeffs: usize, precision: Precision) -> Coefficients {
    match precision {
        Precision::F32 => Coefficients::F32(values.to_vec()),
        Precision::F16 => Coefficients::F16(values.iter().map(|v| to_f16(*v)).collect()),
        Precision::Q8 => {
            let bands = bands_of(coeffs);
            let voxels = || values.chunks_exact(coeffs);
            // Each band's scale once: the scales and the bytes both use it.
            let scales: Vec<half::f16> = voxels()
                .flat_map(|c| (1..bands).map(move |l| scale(band(c, l))))
                .collect();
            let mut s = scales.iter();
            let bytes: Vec<i8> = voxels()
                .flat_map(|c| (1..bands).map(move |l| band(c, l)))
                .flat_map(|band| {
                    let s = s.next().map_or(0.0, |s| s.to_f32());
                    band.iter().map(move |v| quantise(*v, s))
                })
                .collect();
            Coefficients::Q8 {
                dc: voxels().map(|c| to_f16(c[0])).collect(),
                scales,
                bytes,
            }
        }
    }
}

/// Writes coefficients held as [`encode`] holds them, laid out for q8 as all DC terms, all
/// scales, then all bytes.
pub fn put_coefficients(w: &mut SectionWriter, held: &Coefficients) -> std::io::Result<()> {
    match held {
        Coefficients::F32(v) => w.shuffled(v.iter().map(|v| v.to_le_bytes())),
        Coefficients::F16(v) => w.shuffled(v.iter().map(|v| v.to_le_bytes())),
        Coefficients::Q8 { dc, scales, bytes } => {
            w.shuffled(dc.iter().map(|v| v.to_le_bytes()))?;
            w.shuffled(scales.iter().map(|v| v.to_le_bytes()))?;
            let bytes: Vec<u8> = bytes.iter().map(|&b| b as u8).collect();
            w.bytes(&bytes)
        }
    }
}

/// Reads what [`put_coefficients`] wrote for `voxels` voxels, held at the precision it was
/// stored in.
pub fn get_coefficients(
    r: &mut SectionReader,
    voxels: usize,
    coeffs: usize,
    precision: Precision,
) -> Parse<Coefficients> {
    let n = voxels
        .checked_mul(coeffs)
        .ok_or("the header's counts are impossible")?;
    let f16s = |r: &mut SectionReader, n| r.values(n, half::f16::from_le_bytes);
    Ok(match precision {
        Precision::F32 => Coefficients::F32(r.values(n, f32::from_le_bytes)?),
        Precision::F16 => Coefficients::F16(f16s(r, n)?),
        Precision::Q8 => Coefficients::Q8 {
            dc: f16s(r, voxels)?,
            scales: f16s(r, voxels * (bands_of(coeffs) - 1))?,
            bytes: r.values(voxels * (coeffs - 1), i8::from_le_bytes)?,
        },
    })
}

/// Voxels per batch [`each_voxel_batch`] hands over: enough for its consumer's parallel work to
/// pay, few enough (1.6 MB of f32 at ten bands) to stay in cache.
pub const BATCH_VOXELS: usize = 4096;

/// Reads what [`put_coefficients`] wrote for `voxels` voxels as [`get_coefficients`] does, but
/// hands `take` up to [`BATCH_VOXELS`] voxels at a time, in order and held as stored, and holds
/// no more than that (and, for q8, the DC terms and scales): a render relights a cache's
/// coefficients as they stream in, never holding them all, and decodes each batch in parallel.
pub fn each_voxel_batch(
    r: &mut SectionReader,
    voxels: usize,
    coeffs: usize,
    precision: Precision,
    mut take: impl FnMut(&Coefficients) -> Parse<()>,
) -> Parse<()> {
    let n = voxels
        .checked_mul(coeffs)
        .ok_or("the header's counts are impossible")?;
    let per_batch = BATCH_VOXELS * coeffs.max(1);
    match precision {
        Precision::F32 => batches(r, n, per_batch, f32::from_le_bytes, |v| {
            take(&Coefficients::F32(v))
        }),
        Precision::F16 => batches(r, n, per_batch, half::f16::from_le_bytes, |v| {
            take(&Coefficients::F16(v))
        }),
        Precision::Q8 => {
            let per_voxel = bands_of(coeffs) - 1;
            let dc = r.values(voxels, half::f16::from_le_bytes)?;
            let scales = r.values(voxels * per_voxel, half::f16::from_le_bytes)?;
            let mut first = 0;
            let mut hand = |bytes: Vec<i8>, count: usize| {
                let batch = Coefficients::Q8 {
                    dc: dc[first..first + count].to_vec(),
                    scales: scales[first * per_voxel..(first + count) * per_voxel].to_vec(),
                    bytes,
                };
                first += count;
                take(&batch)
            };
            match coeffs - 1 {
                // A single band stores no bytes: each voxel is its DC term alone.
                0 => (0..voxels)
                    .step_by(BATCH_VOXELS)
                    .try_for_each(|start| hand(Vec::new(), (voxels - start).min(BATCH_VOXELS))),
                q => batches(r, voxels * q, BATCH_VOXELS * q, i8::from_le_bytes, |b| {
                    let count = b.len() / q;
                    hand(b, count)
                }),
            }
        }
    }
}

/// `n` values decoded by `decode`, handed to `full` `per_batch` at a time (the last batch may be
/// shorter).
fn batches<const W: usize, T: Copy>(
    r: &mut SectionReader,
    n: usize,
    per_batch: usize,
    decode: impl Fn([u8; W]) -> T,
    mut full: impl FnMut(Vec<T>) -> Parse<()>,
) -> Parse<()> {
    let mut batch = Vec::with_capacity(per_batch.min(n));
    r.each_chunk(n, decode, |chunk| {
        let mut chunk = &chunk[..];
        while !chunk.is_empty() {
            let (now, later) = chunk.split_at((per_batch - batch.len()).min(chunk.len()));
            batch.extend_from_slice(now);
            chunk = later;
            if batch.len() == per_batch {
                full(std::mem::replace(&mut batch, Vec::with_capacity(per_batch)))?;
            }
        }
        Ok(())
    })?;
    if !batch.is_empty() {
        full(batch)?;
    }
    Ok(())
}

/// Band l's 2l + 1 coefficients of one voxel.
fn band(c: &[f32], l: usize) -> &[f32] {
    &c[l * l..(l + 1) * (l + 1)]
}

/// An f16 no smaller than the band's largest magnitude, so every quantised value lies in ±127.
fn scale(band: &[f32]) -> half::f16 {
    let m = band.iter().fold(0f32, |m, v| m.max(v.abs()));
    let s = to_f16(m);
    if s.to_f32() >= m {
        s
    } else {
        half::f16::from_bits(s.to_bits() + 1)
    }
}

/// round(127·v/s) as a signed byte (0 where the whole band is 0).
fn quantise(v: f32, s: f32) -> i8 {
    if s > 0.0 {
        (v / s * Q8_MAX).round().clamp(-Q8_MAX, Q8_MAX) as i8
    } else {
        0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn round_trip(values: &[f32], coeffs: usize, precision: Precision) -> Vec<f32> {
        let mut w = SectionWriter::new().unwrap();
        put_coefficients(&mut w, &encode(values, coeffs, precision)).unwrap();
        let frame = w.finish().unwrap();
        let mut r = SectionReader::new(&frame[..]).unwrap();
        let out = get_coefficients(&mut r, values.len() / coeffs, coeffs, precision).unwrap();
        r.finish().unwrap();
        // Held as stored: bytes per voxel at the precision (q8: f16 DC and scales, a byte each).
        let per_voxel = match precision {
            Precision::F32 => 4 * coeffs,
            Precision::F16 => 2 * coeffs,
            Precision::Q8 => 2 * bands_of(coeffs) + coeffs - 1,
        };
        assert_eq!(out.memory_bytes(), values.len() / coeffs * per_voxel);
        out.to_f32(coeffs).into_owned()
    }

    /// Pseudo-random coefficients of `voxels` voxels at 3 bands, spanning several magnitudes.
    fn sample(voxels: usize) -> Vec<f32> {
        (0..voxels * 9)
            .map(|i| {
                let h = crate::math::hash::hash_unit(i as u32, 0, 0, 0);
                (h - 0.4) * 10f32.powi((i % 5) as i32 - 3)
            })
            .collect()
    }

    #[test]
    fn voxel_batches_decode_as_the_coefficients_held() {
        // Across batches and byte chunks, at every precision, and a single band (q8: no bytes).
        for (coeffs, voxels) in [(9, BATCH_VOXELS * 2 + 123), (1, 1000)] {
            let v: Vec<f32> = sample(voxels).into_iter().take(voxels * coeffs).collect();
            for precision in [Precision::F32, Precision::F16, Precision::Q8] {
                let mut w = SectionWriter::new().unwrap();
                let encoded = encode(&v, coeffs, precision);
                put_coefficients(&mut w, &encoded).unwrap();
                let frame = w.finish().unwrap();
                let mut r = SectionReader::new(&frame[..]).unwrap();
                let held = get_coefficients(&mut r, voxels, coeffs, precision).unwrap();
                // What is read back is what was held before it was written.
                assert_eq!(held, encoded, "{precision:?}");
                let mut r = SectionReader::new(&frame[..]).unwrap();
                let mut streamed = Vec::new();
                each_voxel_batch(&mut r, voxels, coeffs, precision, |batch| {
                    let f = batch.to_f32(coeffs);
                    assert!(f.len() <= BATCH_VOXELS * coeffs && f.len() % coeffs == 0);
                    streamed.extend_from_slice(&f);
                    Ok(())
                })
                .unwrap();
                r.finish().unwrap();
                assert_eq!(streamed, held.to_f32(coeffs).into_owned(), "{precision:?}");
            }
        }
    }

    #[test]
    fn f32_is_exact_across_chunks() {
        let v = sample(CHUNK_VALUES / 3 + 7);
        assert_eq!(round_trip(&v, 9, Precision::F32), v);
    }

    #[test]
    fn f16_is_within_half_an_ulp() {
        let v = sample(1000);
        for (a, b) in round_trip(&v, 9, Precision::F16).iter().zip(&v) {
            assert!(
                (a - b).abs() <= b.abs() * 2f32.powi(-11) + 1e-7,
                "{a} vs {b}"
            );
        }
    }

    #[test]
    fn q8_is_within_half_a_step_of_each_band_scale() {
        let v = sample(1000);
        let out = round_trip(&v, 9, Precision::Q8);
        for (x, (a, b)) in out.chunks(9).zip(v.chunks(9)).enumerate() {
            // f16 keeps 11 bits, and an absolute 2⁻²⁴ among its subnormals.
            assert!(
                (a[0] - b[0]).abs() <= b[0].abs() * 2f32.powi(-11) + 2f32.powi(-24),
                "voxel {x} DC"
            );
            for l in 1..3 {
                let m = band(b, l).iter().fold(0f32, |m, v| m.max(v.abs()));
                for (p, q) in band(a, l).iter().zip(band(b, l)) {
                    // Half a step of 127 over a scale at most one f16 ulp above the maximum.
                    assert!(
                        (p - q).abs() <= m * (1.0 + 2f32.powi(-10)) / 254.0 + 1e-9,
                        "voxel {x}"
                    );
                }
            }
        }
        // An all-zero band stays zero.
        assert_eq!(
            round_trip(&[1.0, 0.0, 0.0, 0.0], 4, Precision::Q8),
            vec![1.0, 0.0, 0.0, 0.0]
        );
    }

    #[test]
    fn a_short_or_long_section_is_an_error() {
        let mut w = SectionWriter::new().unwrap();
        w.bytes(&[1, 2, 3]).unwrap();
        let frame = w.finish().unwrap();
        assert!(SectionReader::new(&frame[..]).unwrap().bytes(4).is_err());
        let mut r = SectionReader::new(&frame[..]).unwrap();
        r.bytes(2).unwrap();
        assert!(r.finish().is_err());
        // A damaged frame reads as an error, never a panic.
        let mut bad = frame.clone();
        let mid = bad.len() / 2;
        bad[mid] ^= 0xff;
        bad.truncate(bad.len() - 1);
        let outcome =
            SectionReader::new(&bad[..]).and_then(|mut r| r.bytes(3).and_then(|_| r.finish()));
        assert!(outcome.is_err());
    }
}
