//! The `.vtc` transfer cache: self-contained (medium, bake settings, source, transform, the sparse
//! density, and the transfer as T_ri and F_ms), compressed, checksummed, written atomically.
//!
//! Layout, little-endian:
//! ```text
//! magic "VSCTRCACHE\0\0"  12 bytes
//! u32   format version
//! u64   header length H;  H bytes of JSON: everything descriptive, and the section counts
//! f32   density background
//! six sections, each a u64 length and a zstd frame of ([`packing`]):
//!   leaves:  per leaf origin 3×i32, mask 8×u64
//!   values:  the active values of every leaf in leaf and voxel order, f32 or f16 (`density`)
//!   tiles:   per tile level (8³, 128³, 4096³): per tile origin 3×i32, value f32
//!   layout:  per transfer voxel 3×i32, in slot order
//!   t_ri, f_ms: voxels × bands² coefficients at the header's `coefficients` precision
//! u64   xxh3-64 of every byte before it
//! ```
//! The reader checks the checksum before it decodes anything, takes each section's length from
//! the file and its contents' sizes from the header's counts, and decompresses no more than a
//! section really holds, so a truncated, padded or corrupted cache is a clear error.

use std::io::{BufRead, Read, Seek, SeekFrom, Write};
use std::path::Path;
use std::sync::Arc;

use glam::{DVec3, IVec3};
use serde::{Deserialize, Serialize};
use xxhash_rust::xxh3::Xxh3;

use super::packing::{self, Precision, SectionReader, SectionWriter};
use super::shape::TransferShape;
use super::{
    lattice::LatticeKind, BakeSettings, Basis, Medium, Transfer, TransferLayout, TransferLight,
};
use crate::error::{Error, Result};
use crate::render::relight::StreamRelight;
use crate::volume::grid::{Leaf, SparseGrid, TileLevel, Transform, LEAF_VOXELS};
use crate::volume::visibility::{Resolution, Visibility};

const MAGIC: &[u8; 12] = b"VSCTRCACHE\0\0";
/// Bumped whenever the layout or the meaning of the data changes; older caches are refused with a
/// message to re-bake. 2: T_ri holds values fitted for trilinear interpolation (`transfer::fit`),
/// not point values, and F_ms what the fit took from them. 3: the source is identified by size,
/// modification time in nanoseconds and a hash of its first bytes; the grid asked for and the
/// framing box are recorded. 4: compressed sections, active density values only, and the q8
/// precision. 5: T_ri fitted over the trilinear fringe and pulled toward the footprint means
/// (a version-4 fit could light hot pixels). 6: the visibility that shapes the direct light
/// (`transfer::shape`), baked and stored. 7: the visibility interpolated in −ln V, and its node
/// values fitted so. 8: the basis the nodes are read with (a transfer baked finer holds quadratic
/// B-spline coefficients).
pub const VERSION: u32 = 8;
/// Longest JSON header accepted: far above any real one, small enough to allocate safely.
const MAX_HEADER: u64 = 1 << 20;
/// Bytes of a leaf's origin and mask in the leaves section, and of a tile in the tiles section.
const LEAF_BYTES: usize = 12 + 64;
const TILE_BYTES: usize = 16;
/// Sections after the background: leaves, values, tiles, layout, t_ri, f_ms, the fitted
/// visibility, the visibility.
const SECTIONS: usize = 8;

/// Bytes at the start of a source file hashed into its identity: a VDB's header and grid
/// descriptors, where a re-export differs even when size and time do not.
const IDENTITY_BYTES: u64 = 64 << 10;

/// The identity of a bake's source file: what tells, without reading the volume, whether a cache
/// was baked from the file as it is now.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Source {
    pub name: String,
    pub size: u64,
    /// Nanoseconds since the Unix epoch (0 when unknown): a rewrite within one second still counts.
    pub mtime_ns: u64,
    /// xxh3 of the first [`IDENTITY_BYTES`] bytes.
    pub header_hash: u64,
}

impl Source {
    /// The identity of the file at `path` as it is now.
    pub fn of(path: &Path) -> Result<Source> {
        let io = |e| Error::io(path, e);
        let file = std::fs::File::open(path).map_err(io)?;
        let meta = file.metadata().map_err(io)?;
        let mtime_ns = meta
            .modified()
            .ok()
            .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
            .map_or(0, |d| d.as_nanos() as u64);
        let mut head = Vec::new();
        file.take(IDENTITY_BYTES)
            .read_to_end(&mut head)
            .map_err(io)?;
        Ok(Source {
            name: path
                .file_name()
                .map_or_else(String::new, |n| n.to_string_lossy().into_owned()),
            size: meta.len(),
            mtime_ns,
            header_hash: xxhash_rust::xxh3::xxh3_64(&head),
        })
    }
}

/// The JSON header: what `info` shows, and the counts the reader checks sizes against.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Header {
    pub sigma_t: f32,
    pub albedo: f32,
    pub bands: usize,
    pub scale: i32,
    pub samples: usize,
    pub lattice: usize,
    pub single_scatter: bool,
    /// `--fit-direct` (absent in caches written before the flag: false).
    #[serde(default)]
    pub fit_direct: bool,
    pub seed: u64,
    pub source: Source,
    /// The grid baked, and the one `--grid` asked for (`None`: the default choice).
    pub grid: String,
    pub requested_grid: Option<String>,
    /// World box a framing camera looks at ([`crate::render::framing_bounds`]), so a sequence's
    /// camera can frame every frame from the headers alone.
    pub framing: Option<[[f32; 3]; 2]>,
    pub voxel_scale: [f64; 3],
    pub translation: [f64; 3],
    pub leaves: u64,
    /// Active tiles at the 8³, 128³ and 4096³ levels.
    pub tiles: [u64; 3],
    pub transfer_voxels: u64,
    /// How the nodes are read between them ([`Basis`]).
    pub basis: Basis,
    /// How the coefficients are stored.
    pub coefficients: Precision,
    /// How the leaves' density values are stored: f32, or f16 when the precision allows it and
    /// every value fits.
    pub density: Precision,
    /// The visibility's density level and directions ([`Resolution`]), and how many values it
    /// stores.
    pub visibility_level: usize,
    pub visibility_directions: usize,
    pub visibility_voxels: u64,
}

/// A cache's contents.
pub struct Cache {
    pub header: Header,
    pub density: SparseGrid,
    pub transfer: Transfer,
}

impl Header {
    /// The cache at `path` (`size` bytes) described for people, one aspect a line.
    pub fn describe(&self, path: &Path, size: u64) -> String {
        let h = self;
        format!(
        "{}: vscatter transfer cache, format {}, {}\n  source      {} (grid {:?}, {} bytes)\n  medium      sigma_t {} per world unit, albedo {}\n  bake        {} bands, 1/{} resolution, {} samples, lattice {}{}, seed {}\n  transform   scale {:?}, translation {:?}\n  density     {} leaves, tiles {:?} (8³, 128³, 4096³)\n  transfer    {} voxels read {}, {} coefficients, {} density\n  visibility  {}\n",
        path.display(),
        VERSION,
        indicatif::HumanBytes(size),
        h.source.name,
        h.grid,
        h.source.size,
        h.sigma_t,
        h.albedo,
        h.bands,
        h.scale,
        h.samples,
        h.lattice,
        match (h.single_scatter, h.fit_direct) {
            (true, _) => " (single scattering only)",
            (false, true) => " (direct light fitted)",
            (false, false) => "",
        },
        h.seed,
        h.voxel_scale,
        h.translation,
        h.leaves,
        h.tiles,
        h.transfer_voxels,
        h.basis.name(),
        h.coefficients.name(),
        h.density.name(),
        match h.visibility_directions {
            0 => "none (only single scattering is shaped)".to_string(),
            d => format!(
                "{} values at 1/{} resolution, {d} directions",
                h.visibility_voxels,
                1u64 << h.visibility_level.min(63)
            ),
        },
    )
    }

    pub fn settings(&self) -> Option<BakeSettings> {
        let lattice = match self.lattice {
            6 => LatticeKind::Faces,
            18 => LatticeKind::FacesEdges,
            26 => LatticeKind::All,
            _ => return None,
        };
        Some(BakeSettings {
            bands: self.bands,
            scale: self.scale,
            samples: self.samples,
            lattice,
            single_scatter: self.single_scatter,
            fit_direct: self.fit_direct,
            seed: self.seed,
        })
    }
}

/// A writer that hashes everything passing through it.
struct Hashing<W: Write> {
    inner: W,
    hash: Xxh3,
}

impl<W: Write> Write for Hashing<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.hash.update(&buf[..n]);
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

/// Writes one section: its compressed length, then the frame `fill` produced.
fn put_section(
    w: &mut impl Write,
    fill: impl FnOnce(&mut SectionWriter) -> std::io::Result<()>,
) -> std::io::Result<()> {
    let mut section = SectionWriter::new()?;
    fill(&mut section)?;
    let frame = section.finish()?;
    w.write_all(&(frame.len() as u64).to_le_bytes())?;
    w.write_all(&frame)
}

fn ivec_bytes(v: IVec3) -> impl Iterator<Item = u8> {
    v.to_array().into_iter().flat_map(i32::to_le_bytes)
}

/// Where a bake's density came from: the file, the grid read, and the grid asked for.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Origin {
    pub source: Source,
    pub grid: String,
    pub requested_grid: Option<String>,
}

/// Builds the header for a bake of `density` into `transfer`.
pub fn header(
    density: &SparseGrid,
    transfer: &Transfer,
    settings: &BakeSettings,
    origin: Origin,
    precision: Precision,
) -> Header {
    let t = density.transform;
    // A transfer with multiple scattering has no visibility: no directions, no values.
    let visibility = transfer.shape.as_ref().map(|s| &s.visibility);
    Header {
        sigma_t: transfer.medium.sigma_t,
        albedo: transfer.medium.albedo,
        bands: settings.bands,
        scale: settings.scale,
        samples: settings.samples,
        lattice: settings.lattice.directions(),
        single_scatter: settings.single_scatter,
        fit_direct: settings.fit_direct,
        seed: settings.seed,
        source: origin.source,
        grid: origin.grid,
        requested_grid: origin.requested_grid,
        framing: crate::render::framing_bounds(density)
            .map(|(lo, hi)| [lo.to_array(), hi.to_array()]),
        voxel_scale: t.scale.to_array(),
        translation: t.translation.to_array(),
        leaves: density.leaf_count() as u64,
        tiles: TileLevel::ALL.map(|l| density.tiles(l).count() as u64),
        transfer_voxels: transfer.layout.len() as u64,
        basis: transfer.basis,
        coefficients: precision,
        density: match density_f16(density, precision) {
            true => Precision::F16,
            false => Precision::F32,
        },
        visibility_level: visibility.map_or(0, |v| v.resolution.level),
        visibility_directions: visibility.map_or(0, |v| v.resolution.directions),
        visibility_voxels: visibility.map_or(0, |v| v.values().len() as u64),
    }
}

/// Writes a cache atomically (temporary file, then rename).
pub fn write(
    path: &Path,
    header: &Header,
    density: &SparseGrid,
    transfer: &Transfer,
) -> Result<()> {
    let json = serde_json::to_vec(header).map_err(|e| Error::Runtime(e.to_string()))?;
    let coeffs = transfer.coeffs();
    let Some((t_ri, f_ms)) = transfer.coefficients() else {
        return Err(Error::Runtime(format!(
            "{}: a transfer relit as it was read has no coefficients to write",
            path.display()
        )));
    };
    crate::io::atomic::write_atomic(path, |file| {
        let mut w = Hashing {
            inner: std::io::BufWriter::new(file),
            hash: Xxh3::new(),
        };
        w.write_all(MAGIC)?;
        w.write_all(&VERSION.to_le_bytes())?;
        w.write_all(&(json.len() as u64).to_le_bytes())?;
        w.write_all(&json)?;
        w.write_all(&density.background.to_le_bytes())?;
        let leaves = density.leaves();
        put_section(&mut w, |s| {
            leaves.iter().try_for_each(|leaf| {
                let bytes: Vec<u8> = ivec_bytes(leaf.origin)
                    .chain(leaf.mask.iter().flat_map(|m| m.to_le_bytes()))
                    .collect();
                s.bytes(&bytes)
            })
        })?;
        put_section(&mut w, |s| {
            let values = leaves.iter().flat_map(active_values);
            match header.density {
                Precision::F16 => s.shuffled(values.map(|v| half::f16::from_f32(v).to_le_bytes())),
                _ => s.shuffled(values.map(f32::to_le_bytes)),
            }
        })?;
        put_section(&mut w, |s| {
            TileLevel::ALL.into_iter().try_for_each(|level| {
                // Sorted so that two bakes of one input give identical files whatever the map order.
                let mut tiles: Vec<(IVec3, f32)> = density.tiles(level).collect();
                tiles.sort_by_key(|(o, _)| o.to_array());
                let bytes: Vec<u8> = tiles
                    .into_iter()
                    .flat_map(|(origin, value)| ivec_bytes(origin).chain(value.to_le_bytes()))
                    .collect();
                s.bytes(&bytes)
            })
        })?;
        put_section(&mut w, |s| {
            let bytes: Vec<u8> = transfer
                .layout
                .voxels()
                .iter()
                .flat_map(|v| ivec_bytes(*v))
                .collect();
            s.bytes(&bytes)
        })?;
        for values in [t_ri, f_ms] {
            put_section(&mut w, |s| {
                match values.precision() == header.coefficients {
                    true => packing::put_coefficients(s, values),
                    false => packing::put_coefficients(
                        s,
                        &packing::encode(&values.to_f32(coeffs), coeffs, header.coefficients),
                    ),
                }
            })?;
        }
        let shape = transfer.shape.as_deref();
        put_section(&mut w, |s| {
            s.shuffled(
                shape
                    .iter()
                    .flat_map(|s| &s.fitted)
                    .map(|v| v.to_le_bytes()),
            )
        })?;
        put_section(&mut w, |s| {
            let values = shape.iter().flat_map(|s| s.visibility.values());
            s.shuffled(values.map(|v| v.to_le_bytes()))
        })?;
        let sum = w.hash.digest();
        w.inner.write_all(&sum.to_le_bytes())?;
        w.inner.flush()
    })
}

/// The values of a leaf's active voxels, in voxel order: all a cache stores of a leaf's values
/// (the inactive ones read back as the background).
fn active_values(leaf: &Leaf) -> impl Iterator<Item = f32> + '_ {
    (0..LEAF_VOXELS)
        .filter(|&i| leaf.is_active(i))
        .map(|i| leaf.values.get(i))
}

/// A leaf as a cache reads it back: its `active` values in voxel order, the background
/// elsewhere, held as f16 when the cache stores the density so.
fn stored_leaf(
    origin: IVec3,
    mask: [u64; 8],
    active: impl Iterator<Item = f32>,
    background: f32,
    f16: bool,
) -> Leaf {
    let mut array = [background; LEAF_VOXELS];
    let slots = (0..LEAF_VOXELS).filter(|&i| Leaf::is_set(&mask, i));
    for (slot, v) in slots.zip(active) {
        array[slot] = v;
    }
    let leaf = Leaf::new(origin, mask, array, background);
    match f16 {
        true => leaf.into_f16(),
        false => leaf,
    }
}

/// Whether a cache of `precision` stores `density`'s values as f16: when its coefficients are
/// reduced and every active value is a finite f16.
fn density_f16(density: &SparseGrid, precision: Precision) -> bool {
    precision.density_f16() && packing::fits_f16(density.leaves().iter().flat_map(active_values))
}

/// The density and transfer of a bake as a cache of `precision` holds them once read back, so a
/// render of the bake equals, bit for bit, a render of the cache it writes: the transfer in place
/// and the density anew (`None` at f32, where both are held as they are).
pub fn as_stored(
    density: &SparseGrid,
    transfer: &mut Transfer,
    precision: Precision,
) -> Option<SparseGrid> {
    if precision == Precision::F32 {
        return None;
    }
    let coeffs = transfer.bands * transfer.bands;
    if let TransferLight::Coefficients { t_ri, f_ms } = &mut transfer.light {
        for values in [t_ri, f_ms] {
            if values.precision() != precision {
                *values = packing::encode(&values.to_f32(coeffs), coeffs, precision);
            }
        }
    }
    let f16 = density_f16(density, precision);
    let background = density.background;
    Some(density.map_leaves(|leaf| {
        let active = active_values(leaf).map(|v| match f16 {
            true => half::f16::from_f32(v).to_f32(),
            false => v,
        });
        stored_leaf(leaf.origin, leaf.mask, active, background, f16)
    }))
}

/// Active voxels in a leaf's mask.
fn active_count(mask: &[u64; 8]) -> usize {
    mask.iter().map(|w| w.count_ones() as usize).sum()
}

/// Leaves built from their active values as those stream in, in leaf order.
struct LeafFill {
    /// The leaves still to build: origin, active mask, count of active values.
    leaves: std::iter::Peekable<std::vec::IntoIter<(IVec3, [u64; 8], usize)>>,
    /// The next leaf's values so far.
    pending: Vec<f32>,
    /// The values are f16s: the leaves hold them so ([`Leaf::into_f16`]).
    f16: bool,
}

impl LeafFill {
    /// Takes the next `values`, adding each leaf to `grid` once its values are all in (a leaf
    /// with no active value at once).
    fn take(
        &mut self,
        mut values: &[f32],
        grid: &mut SparseGrid,
    ) -> std::result::Result<(), String> {
        loop {
            while let Some((origin, mask, _)) =
                self.leaves.next_if(|(_, _, n)| *n == self.pending.len())
            {
                let leaf = stored_leaf(
                    origin,
                    mask,
                    self.pending.drain(..),
                    grid.background,
                    self.f16,
                );
                grid.push_leaf(leaf);
            }
            if values.is_empty() {
                return Ok(());
            }
            let Some((_, _, n)) = self.leaves.peek() else {
                return Err("the density holds more values than its leaves".into());
            };
            let (now, later) = values.split_at((n - self.pending.len()).min(values.len()));
            self.pending.extend_from_slice(now);
            values = later;
        }
    }
}

/// The cache body after the header, read section by section from a reader that has `left`
/// bytes of it before the checksum: each section is decompressed as it streams in, so a read
/// holds the decoded data and a buffer, never the file or a compressed section.
struct Body<R: BufRead> {
    reader: R,
    left: u64,
}

impl<R: BufRead> Body<R> {
    /// The next `N` bytes.
    fn fixed<const N: usize>(&mut self) -> std::result::Result<[u8; N], String> {
        if N as u64 > self.left {
            return Err("cache sections are shorter than their lengths say".into());
        }
        self.left -= N as u64;
        let mut out = [0u8; N];
        self.reader
            .read_exact(&mut out)
            .map_err(|e| format!("cannot read the cache: {e}"))?;
        Ok(out)
    }

    /// The next section, decoded by `parse`, which must read all of it.
    fn section<T>(
        &mut self,
        parse: impl FnOnce(&mut SectionReader) -> std::result::Result<T, String>,
    ) -> std::result::Result<T, String> {
        let len = u64::from_le_bytes(self.fixed()?);
        if len > self.left {
            return Err("cache sections are shorter than their lengths say".into());
        }
        self.left -= len;
        let mut frame = (&mut self.reader).take(len);
        let value = {
            let mut reader = SectionReader::new(&mut frame)?;
            let value = parse(&mut reader)?;
            reader.finish()?;
            value
        };
        if frame.limit() != 0 {
            return Err("a compressed section holds bytes past its data".into());
        }
        Ok(value)
    }
}

/// Little-endian i32 triples from `bytes` (a multiple of 12 long).
fn ivecs(bytes: &[u8]) -> impl Iterator<Item = IVec3> + '_ {
    bytes.chunks_exact(12).map(|b| {
        let c = |i: usize| i32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]);
        IVec3::new(c(0), c(4), c(8))
    })
}

/// `count` records of `size` bytes from a section, with the count checked against overflow.
fn records(r: &mut SectionReader, count: u64, size: usize) -> std::result::Result<Vec<u8>, String> {
    let n = usize::try_from(count)
        .ok()
        .and_then(|c| c.checked_mul(size))
        .ok_or("the header's counts are impossible")?;
    r.bytes(n)
}

/// Whether `path` starts with the cache magic (a short or unreadable file is not a cache here; the
/// VDB reader then reports what is wrong with it).
pub fn is_cache(path: &Path) -> Result<bool> {
    let mut magic = [0u8; MAGIC.len()];
    let mut file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    Ok(file.read_exact(&mut magic).is_ok() && &magic == MAGIC)
}

/// The format version of the cache at `path`; `None` when it does not start with the cache magic.
pub fn format_version(path: &Path) -> Result<Option<u32>> {
    let mut fixed = [0u8; MAGIC.len() + 4];
    let mut file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    if file.read_exact(&mut fixed).is_err() || &fixed[..MAGIC.len()] != MAGIC {
        return Ok(None);
    }
    let v = &fixed[MAGIC.len()..];
    Ok(Some(u32::from_le_bytes([v[0], v[1], v[2], v[3]])))
}

/// What to do about a cache that cannot be used, said with what is wrong with it.
const ADVICE: &str = "delete it or bake it again";

fn damaged(path: &Path, what: String) -> Error {
    Error::format(path, format!("{what} ({ADVICE})"))
}

/// Bytes before the JSON header: magic, version, header length.
const FIXED: usize = 12 + 4 + 8;

/// Parses the header from the file's first bytes `data` and checks it against the file's length.
fn parse_header(data: &[u8], file_len: u64) -> std::result::Result<(Header, usize), String> {
    let fixed = FIXED;
    if data.len() < fixed || &data[..MAGIC.len()] != MAGIC {
        return Err("not a vscatter transfer cache (wrong magic)".into());
    }
    let version = u32::from_le_bytes([data[12], data[13], data[14], data[15]]);
    if version != VERSION {
        return Err(format!(
            "cache format version {version}, this vscatter reads version {VERSION}"
        ));
    }
    let mut len = [0u8; 8];
    len.copy_from_slice(&data[16..24]);
    let hlen = u64::from_le_bytes(len);
    if hlen > MAX_HEADER || hlen > (data.len() - fixed) as u64 || file_len < data.len() as u64 {
        return Err(format!("header length {hlen} is impossible for this file"));
    }
    let end = fixed + hlen as usize;
    let header: Header =
        serde_json::from_slice(&data[fixed..end]).map_err(|e| format!("damaged header: {e}"))?;
    // Background, each section's length, checksum: the least a body can be.
    let least = (end + 4 + 8 * SECTIONS + 8) as u64;
    if file_len < least {
        return Err(format!(
            "truncated: {file_len} bytes cannot hold the sections the header describes"
        ));
    }
    if !(1..=crate::light::sh::MAX_BANDS).contains(&header.bands)
        || header.scale < 1
        || header.visibility_level > crate::volume::visibility::MAX_LEVEL
    {
        return Err("the header's bake settings are invalid".into());
    }
    Ok((header, end))
}

/// Reads only the header of the cache at `path`, checked against the file's length (not the
/// checksum): enough to tell whether the cache is current without reading its data. `None` for
/// a cache of an older format (stale: what a bake computes changed); an error for anything else
/// that is not a cache of this format.
pub fn read_header(path: &Path) -> Result<Option<Header>> {
    if format_version(path)?.is_some_and(|v| v < VERSION) {
        return Ok(None);
    }
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let len = file.metadata().map_err(|e| Error::io(path, e))?.len();
    let mut head = Vec::new();
    file.take(FIXED as u64 + MAX_HEADER)
        .read_to_end(&mut head)
        .map_err(|e| Error::io(path, e))?;
    let (header, _) = parse_header(&head, len).map_err(|m| damaged(path, m))?;
    Ok(Some(header))
}

/// Reads and verifies a whole cache.
pub fn read(path: &Path) -> Result<Cache> {
    let (file, len) = open(path)?;
    read_from(file, len, None).map_err(|m| damaged(path, m))
}

/// Reads and verifies a cache for rendering under maps whose SH coefficients are `envs` only: its
/// transfer is [`TransferLight::Relit`], its coefficients relit as they stream in and never held
/// (on a big cloud they are most of what a render would hold beside the density).
pub fn read_relit(path: &Path, envs: &[Vec<[f32; 3]>]) -> Result<Cache> {
    let (file, len) = open(path)?;
    read_from(file, len, Some(envs)).map_err(|m| damaged(path, m))
}

/// Reads a cache's header and verifies the checksum over the whole file, without decoding the
/// data (for `info`: a damaged cache is reported as damaged, not described).
pub fn verify(path: &Path) -> Result<Header> {
    let (mut file, len) = open(path)?;
    verified_header(&mut file, len)
        .map(|(header, _)| header)
        .map_err(|m| damaged(path, m))
}

/// The cache at `path`, buffered, and its length.
fn open(path: &Path) -> Result<(std::io::BufReader<std::fs::File>, u64)> {
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let len = file.metadata().map_err(|e| Error::io(path, e))?.len();
    Ok((std::io::BufReader::new(file), len))
}

/// Bytes hashed per read while the checksum is verified.
const HASH_CHUNK: usize = 1 << 20;

/// The header of the `len`-byte cache `source`, and where it ends, once the xxh3 of everything
/// before the last 8 bytes has been checked against those bytes: streamed, so the check holds a
/// chunk of the file, not the file.
fn verified_header(
    source: &mut (impl Read + Seek),
    len: u64,
) -> std::result::Result<(Header, usize), String> {
    let io = |e: std::io::Error| format!("cannot read the cache: {e}");
    let mut head = Vec::new();
    source
        .by_ref()
        .take(FIXED as u64 + MAX_HEADER)
        .read_to_end(&mut head)
        .map_err(io)?;
    let parsed = parse_header(&head, len)?;
    // parse_header has checked that `len` holds the checksum.
    let split = len - 8;
    source.seek(SeekFrom::Start(0)).map_err(io)?;
    let mut hash = Xxh3::new();
    let mut chunk = vec![0u8; HASH_CHUNK];
    let mut left = split;
    while left > 0 {
        let n = left.min(HASH_CHUNK as u64) as usize;
        source.read_exact(&mut chunk[..n]).map_err(io)?;
        hash.update(&chunk[..n]);
        left -= n as u64;
    }
    let mut sum = [0u8; 8];
    source.read_exact(&mut sum).map_err(io)?;
    if hash.digest() != u64::from_le_bytes(sum) {
        return Err("checksum mismatch: the cache is corrupted".into());
    }
    Ok(parsed)
}

/// Reads the `len`-byte cache `source`: the checksum first ([`verified_header`]), then the
/// sections in order.
fn read_from(
    mut source: impl BufRead + Seek,
    len: u64,
    envs: Option<&[Vec<[f32; 3]>]>,
) -> std::result::Result<Cache, String> {
    let (header, start) = verified_header(&mut source, len)?;
    source
        .seek(SeekFrom::Start(start as u64))
        .map_err(|e| format!("cannot read the cache: {e}"))?;
    let body = Body {
        reader: source,
        left: len - 8 - start as u64,
    };
    decode(header, body, envs)
}

/// The cache's data from `body`, which starts after the header: the coefficients as stored, or
/// (`envs`: SH coefficients of maps) relit under each as they stream in.
fn decode(
    header: Header,
    mut body: Body<impl BufRead>,
    envs: Option<&[Vec<[f32; 3]>]>,
) -> std::result::Result<Cache, String> {
    let settings = header
        .settings()
        .ok_or("the header names an unknown lattice")?;
    let transform = Transform {
        scale: DVec3::from_array(header.voxel_scale),
        translation: DVec3::from_array(header.translation),
    };
    let mut density = SparseGrid::new(transform, f32::from_le_bytes(body.fixed()?));
    let leaves = body.section(|r| records(r, header.leaves, LEAF_BYTES))?;
    // Each leaf's origin, active mask and count of active values.
    let masks: Vec<(IVec3, [u64; 8], usize)> = leaves
        .chunks_exact(LEAF_BYTES)
        .map(|b| {
            let origin = ivecs(&b[..12]).next().unwrap_or(IVec3::ZERO);
            let mask = std::array::from_fn(|i| {
                u64::from_le_bytes(std::array::from_fn(|k| b[12 + 8 * i + k]))
            });
            (origin, mask, active_count(&mask))
        })
        .collect();
    drop(leaves);
    let active: usize = masks.iter().map(|(_, _, n)| n).sum();
    // The values go straight into their leaves as they decode: a big cloud's values never sit in
    // memory twice.
    density.reserve_leaves(masks.len());
    let mut fill = LeafFill {
        leaves: masks.into_iter().peekable(),
        pending: Vec::with_capacity(LEAF_VOXELS),
        f16: header.density == Precision::F16,
    };
    fill.take(&[], &mut density)?;
    body.section(|r| {
        let mut take = |chunk: &mut Vec<f32>| fill.take(chunk, &mut density);
        match header.density {
            Precision::F32 => r.each_chunk(active, f32::from_le_bytes, &mut take),
            Precision::F16 => {
                r.each_chunk(active, |b| half::f16::from_le_bytes(b).to_f32(), &mut take)
            }
            Precision::Q8 => Err("the header's density precision is invalid".into()),
        }
    })?;
    let tiles = header.tiles.iter().try_fold(0u64, |a, t| a.checked_add(*t));
    let tiles = body.section(|r| records(r, tiles.unwrap_or(u64::MAX), TILE_BYTES))?;
    let mut records_left = tiles.chunks_exact(TILE_BYTES);
    for (level, &count) in TileLevel::ALL.iter().zip(&header.tiles) {
        for b in records_left.by_ref().take(count as usize) {
            let origin = ivecs(&b[..12]).next().unwrap_or(IVec3::ZERO);
            density.insert_tile(
                *level,
                origin,
                f32::from_le_bytes([b[12], b[13], b[14], b[15]]),
            );
        }
    }
    let voxels = body.section(|r| records(r, header.transfer_voxels, 12))?;
    let layout = TransferLayout::from_voxels(settings.scale, ivecs(&voxels).collect())
        .ok_or("transfer voxels are repeated or out of order")?;
    let coeffs = settings.bands * settings.bands;
    let precision = header.coefficients;
    let n = layout.len();
    let light = match envs {
        None => TransferLight::Coefficients {
            t_ri: body.section(|r| packing::get_coefficients(r, n, coeffs, precision))?,
            f_ms: body.section(|r| packing::get_coefficients(r, n, coeffs, precision))?,
        },
        Some(envs) => {
            let mut relit = StreamRelight::new(envs, coeffs);
            for part in 0..2 {
                body.section(|r| {
                    packing::each_voxel_batch(r, n, coeffs, precision, |batch| {
                        relit.take(part, batch);
                        Ok(())
                    })
                })?;
            }
            TransferLight::Relit(relit.finish())
        }
    };
    // Directions 0: no visibility (a transfer with multiple scattering).
    let shaped = header.visibility_directions > 0;
    let fitted = body.section(|r| r.values(if shaped { n } else { 0 }, f32::from_le_bytes))?;
    let values = body.section(|r| {
        r.values(
            usize::try_from(header.visibility_voxels).unwrap_or(usize::MAX),
            half::f16::from_le_bytes,
        )
    })?;
    if body.left != 0 {
        return Err("padded: bytes follow the last section".into());
    }
    let resolution = Resolution {
        level: header.visibility_level,
        directions: header.visibility_directions,
    };
    let shape = match shaped {
        true => {
            let visibility = Visibility::from_values(&density, resolution, values)
                .ok_or("the visibility's values do not match the density")?;
            Some(Arc::new(TransferShape { visibility, fitted }))
        }
        false if values.is_empty() => None,
        false => return Err("the visibility's values do not match the density".into()),
    };
    let transfer = Transfer {
        layout,
        bands: settings.bands,
        medium: Medium {
            sigma_t: header.sigma_t,
            albedo: header.albedo,
        },
        light,
        lattice: (!settings.single_scatter).then_some(settings.lattice),
        shape,
        basis: header.basis,
    };
    Ok(Cache {
        header,
        density,
        transfer,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transfer::Coefficients;

    /// A tile, and a leaf of two active voxels (0.3 and `peak`) among inactive ones.
    fn tiny_with(precision: Precision, peak: f32) -> (SparseGrid, Transfer, Header) {
        let mut g = SparseGrid::new(Transform::default(), 0.0);
        g.insert_tile(TileLevel::Block, IVec3::new(8, 0, 0), 0.75);
        let mut values = [0.0; LEAF_VOXELS];
        let mut mask = [0u64; 8];
        for (i, v) in [(5, 0.3), (300, peak)] {
            values[i] = v;
            mask[i >> 6] |= 1 << (i & 63);
        }
        values[6] = 9.0; // inactive: not stored, read back as the background
        g.insert_leaf(IVec3::new(0, 16, 0), mask, values);
        let layout = TransferLayout::build(&g, 6);
        let n = layout.len() * 4;
        let shape = TransferShape::build(
            &crate::volume::DensityField::new(g.clone()),
            &layout,
            2.0,
            Resolution::FINE,
        );
        let transfer = Transfer {
            layout,
            bands: 2,
            medium: Medium {
                sigma_t: 2.0,
                albedo: 0.5,
            },
            light: TransferLight::Coefficients {
                t_ri: Coefficients::F32((0..n).map(|i| i as f32 * 0.25).collect()),
                f_ms: Coefficients::F32((0..n).map(|i| -(i as f32) * 0.1).collect()),
            },
            lattice: Some(LatticeKind::All),
            shape: Some(Arc::new(shape)),
            basis: Basis::Quadratic,
        };
        let h = header(&g, &transfer, &tiny_settings(), tiny_origin(), precision);
        (g, transfer, h)
    }

    fn tiny_settings() -> BakeSettings {
        BakeSettings {
            bands: 2,
            scale: 6,
            samples: 64,
            lattice: LatticeKind::All,
            single_scatter: false,
            fit_direct: false,
            seed: 7,
        }
    }

    fn tiny_origin() -> Origin {
        Origin {
            source: Source {
                name: "x.vdb".into(),
                size: 1,
                mtime_ns: 2,
                header_hash: 3,
            },
            grid: "density".into(),
            requested_grid: None,
        }
    }

    fn read_bytes(data: &[u8]) -> std::result::Result<Cache, String> {
        read_from(std::io::Cursor::new(data), data.len() as u64, None)
    }

    fn tiny() -> (SparseGrid, Transfer, Header) {
        tiny_with(Precision::F32, 0.5)
    }

    /// The cache bytes with the header replaced by `h` and the checksum made right again: what a
    /// cache whose counts lie looks like past the checksum.
    fn with_header(bytes: &[u8], h: &Header) -> Vec<u8> {
        let (_, end) = parse_header(bytes, bytes.len() as u64).unwrap();
        let json = serde_json::to_vec(h).unwrap();
        let mut out = bytes[..16].to_vec();
        out.extend((json.len() as u64).to_le_bytes());
        out.extend(json);
        out.extend(&bytes[end..bytes.len() - 8]);
        let sum = xxhash_rust::xxh3::xxh3_64(&out);
        out.extend(sum.to_le_bytes());
        out
    }

    #[test]
    fn reduced_precisions_round_trip_within_their_precision() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.vtc");
        for (precision, peak, density) in [
            (Precision::F16, 0.5, Precision::F16),
            (Precision::Q8, 0.5, Precision::F16),
            // A value past f16's range keeps the density f32.
            (Precision::F16, 1e6, Precision::F32),
        ] {
            let (g, t, h) = tiny_with(precision, peak);
            assert_eq!(h.density, density);
            write(&path, &h, &g, &t).unwrap();
            let back = read(&path).unwrap();
            assert_eq!(back.header, h);
            // An f16 density is held as f16.
            let held = if density == Precision::F16 {
                1024
            } else {
                2048
            };
            let leaves = back.density.leaves();
            assert!(leaves.iter().all(|l| l.values.memory_bytes() == held));
            let close = |a: f32, b: f32, tol: f32| assert!((a - b).abs() <= tol, "{a} vs {b}");
            // Leaf slot i is voxel (i / 64, i / 8 % 8, i % 8) of the leaf at (0, 16, 0).
            let at = |i: i32| IVec3::new(i / 64, 16 + i / 8 % 8, i % 8);
            close(back.density.value(at(5)), 0.3, 2e-4);
            close(back.density.value(at(300)), peak, 0.0);
            assert_eq!(back.density.value(IVec3::new(0, 16, 6)), 0.0);
            assert_eq!(back.density.value(IVec3::new(9, 1, 1)), 0.75);
            let (back_t_ri, t_ri) = (
                back.transfer.coefficients().unwrap().0.to_f32(4),
                t.coefficients().unwrap().0.to_f32(4),
            );
            for (a, b) in back_t_ri.iter().zip(t_ri.iter()) {
                // Within q8's half step of a band scale (packing's tests bound each precision exactly).
                close(*a, *b, b.abs().max(1.0) * 5e-3);
            }
        }
    }

    #[test]
    fn relit_as_read_is_relit_after_reading_bit_for_bit() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.vtc");
        let envs: Vec<Vec<[f32; 3]>> = vec![
            vec![
                [1.0, 0.5, 0.25],
                [0.3, -0.2, 0.1],
                [0.0, 0.1, 0.2],
                [-0.1, 0.0, 0.4],
            ],
            vec![[0.2, 0.2, 0.2]],
        ];
        for precision in [Precision::F32, Precision::F16, Precision::Q8] {
            let (g, t, h) = tiny_with(precision, 0.5);
            write(&path, &h, &g, &t).unwrap();
            let held = read(&path).unwrap().transfer;
            let relit = read_relit(&path, &envs).unwrap().transfer;
            assert_eq!(relit.layout.voxels(), held.layout.voxels());
            assert!(relit.coefficients().is_none());
            for env in &envs {
                let (want, _) = crate::render::relight::relight(&held, env).unwrap();
                let (got, _) = crate::render::relight::relight(&relit, env).unwrap();
                assert_eq!(got, want);
            }
            // Other maps cannot be relit, nor can a relit transfer be written.
            assert!(crate::render::relight::relight(&relit, &[[0.5; 3]]).is_err());
            assert!(write(&dir.path().join("u.vtc"), &h, &g, &relit).is_err());
        }
    }

    #[test]
    fn counts_that_lie_past_the_checksum_are_errors() {
        let (g, t, h) = tiny();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.vtc");
        write(&path, &h, &g, &t).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert!(read_bytes(&with_header(&bytes, &h)).is_ok());
        let lies: [fn(&mut Header); 9] = [
            |h| h.visibility_voxels += 1,
            |h| h.visibility_level = 1,
            |h| h.visibility_directions = 0,
            |h| h.visibility_level = 99,
            |h| h.leaves += 1,
            |h| h.leaves = u64::MAX,
            |h| h.tiles[1] += 1,
            |h| h.transfer_voxels -= 1,
            |h| h.coefficients = Precision::F16,
        ];
        for lie in lies {
            let mut bad = h.clone();
            lie(&mut bad);
            assert!(read_bytes(&with_header(&bytes, &bad)).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn round_trip_is_bit_exact_and_damage_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.vtc");
        let (g, t, h) = tiny();
        write(&path, &h, &g, &t).unwrap();
        let back = read(&path).unwrap();
        assert_eq!(back.header, h);
        assert_eq!(back.transfer.light, t.light);
        assert_eq!(back.transfer.layout.voxels(), t.layout.voxels());
        assert_eq!(back.transfer.basis, Basis::Quadratic);
        assert_eq!(back.density.value(IVec3::new(9, 1, 1)), 0.75);
        let (back_shape, shape) = (back.transfer.shape.unwrap(), t.shape.unwrap());
        assert_eq!(back_shape.fitted, shape.fitted);
        assert_eq!(back_shape.visibility.values(), shape.visibility.values());
        assert!(!shape.visibility.values().is_empty());
        // A transfer with multiple scattering keeps no visibility.
        let unshaped = Transfer { shape: None, ..t };
        let h = header(
            &g,
            &unshaped,
            &tiny_settings(),
            tiny_origin(),
            Precision::F32,
        );
        assert_eq!((h.visibility_directions, h.visibility_voxels), (0, 0));
        write(&path, &h, &g, &unshaped).unwrap();
        assert!(read(&path).unwrap().transfer.shape.is_none());
        let bytes = std::fs::read(&path).unwrap();
        for cut in 0..bytes.len() {
            assert!(read_bytes(&bytes[..cut]).is_err(), "cut at {cut}");
        }
        for at in (0..bytes.len()).step_by(7) {
            let mut b = bytes.clone();
            b[at] ^= 0x10;
            assert!(read_bytes(&b).is_err(), "flip at {at}");
        }
    }
}
