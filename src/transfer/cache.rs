//! The `.vtc` transfer cache: self-contained (medium, bake settings, source, transform, the sparse
//! density, and the transfer as T_ri and F_ms), checksummed, written atomically.
//!
//! Layout, little-endian:
//! ```text
//! magic "VSCTRCACHE\0\0"  12 bytes
//! u32   format version
//! u64   header length H;  H bytes of JSON: everything descriptive, and the section counts
//! density: background f32; per leaf: origin 3×i32, mask 8×u64, 512×f32;
//!          per tile level (8³, 128³, 4096³): per tile origin 3×i32, value f32
//! layout:  per transfer voxel 3×i32, in slot order
//! t_ri, f_ms: voxels × bands² coefficients, f32 or f16 (`coefficients` in the header)
//! u64   xxh3-64 of every byte before it
//! ```
//! The reader derives every section's size from the header's counts with checked arithmetic and
//! requires the total to equal the file's length before it allocates anything, then verifies the
//! checksum, so a truncated or corrupted cache is a clear error.

use std::io::Write;
use std::path::Path;

use glam::{DVec3, IVec3};
use serde::{Deserialize, Serialize};
use xxhash_rust::xxh3::Xxh3;

use super::{lattice::LatticeKind, BakeSettings, Medium, Transfer, TransferLayout};
use crate::error::{Error, Result};
use crate::volume::grid::{SparseGrid, TileLevel, Transform, LEAF_VOXELS};

const MAGIC: &[u8; 12] = b"VSCTRCACHE\0\0";
/// Bumped whenever the layout or the meaning of the data changes; older caches are refused with a
/// message to re-bake. 2: T_ri holds values fitted for trilinear interpolation (`transfer::fit`),
/// not point values, and F_ms what the fit took from them. 3: the source is identified by size,
/// modification time in nanoseconds and a hash of its first bytes; the grid asked for and the
/// framing box are recorded.
pub const VERSION: u32 = 3;
/// Longest JSON header accepted: far above any real one, small enough to allocate safely.
const MAX_HEADER: u64 = 1 << 20;
const LEAF_BYTES: u64 = 12 + 64 + 4 * LEAF_VOXELS as u64;
const TILE_BYTES: u64 = 16;

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
        use std::io::Read;
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
    /// `f32` or `f16`.
    pub coefficients: String,
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
        "{}: vscatter transfer cache, format {}, {}\n  source      {} (grid {:?}, {} bytes)\n  medium      sigma_t {} per world unit, albedo {}\n  bake        {} bands, 1/{} resolution, {} samples, lattice {}{}, seed {}\n  transform   scale {:?}, translation {:?}\n  density     {} leaves, tiles {:?} (8³, 128³, 4096³)\n  transfer    {} voxels, {} coefficients\n",
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
        if h.single_scatter { " (single scattering only)" } else { "" },
        h.seed,
        h.voxel_scale,
        h.translation,
        h.leaves,
        h.tiles,
        h.transfer_voxels,
        h.coefficients,
    )
    }

    fn coefficient_bytes(&self) -> Option<u64> {
        match self.coefficients.as_str() {
            "f32" => Some(4),
            "f16" => Some(2),
            _ => None,
        }
    }

    /// Bytes of everything after the header and before the checksum.
    fn body_len(&self) -> Option<u64> {
        let coeffs = (self.bands as u64).checked_mul(self.bands as u64)?;
        let tiles: u64 = self.tiles.iter().try_fold(0u64, |a, t| a.checked_add(*t))?;
        let transfer = self
            .transfer_voxels
            .checked_mul(coeffs)?
            .checked_mul(self.coefficient_bytes()?)?
            .checked_mul(2)?;
        4u64.checked_add(self.leaves.checked_mul(LEAF_BYTES)?)?
            .checked_add(tiles.checked_mul(TILE_BYTES)?)?
            .checked_add(self.transfer_voxels.checked_mul(12)?)?
            .checked_add(transfer)
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

fn put_ivec(w: &mut impl Write, v: IVec3) -> std::io::Result<()> {
    v.to_array()
        .iter()
        .try_for_each(|c| w.write_all(&c.to_le_bytes()))
}

fn put_coefficients(w: &mut impl Write, values: &[f32], half: bool) -> std::io::Result<()> {
    for chunk in values.chunks(4096) {
        let bytes: Vec<u8> = if half {
            chunk
                .iter()
                .flat_map(|v| half::f16::from_f32(*v).to_le_bytes())
                .collect()
        } else {
            chunk.iter().flat_map(|v| v.to_le_bytes()).collect()
        };
        w.write_all(&bytes)?;
    }
    Ok(())
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
    half: bool,
) -> Header {
    let t = density.transform;
    Header {
        sigma_t: transfer.medium.sigma_t,
        albedo: transfer.medium.albedo,
        bands: settings.bands,
        scale: settings.scale,
        samples: settings.samples,
        lattice: settings.lattice.directions(),
        single_scatter: settings.single_scatter,
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
        coefficients: if half { "f16" } else { "f32" }.into(),
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
    let half = header.coefficients == "f16";
    crate::io::atomic::write_atomic(path, |file| {
        let mut w = Hashing {
            inner: file,
            hash: Xxh3::new(),
        };
        w.write_all(MAGIC)?;
        w.write_all(&VERSION.to_le_bytes())?;
        w.write_all(&(json.len() as u64).to_le_bytes())?;
        w.write_all(&json)?;
        w.write_all(&density.background.to_le_bytes())?;
        for leaf in density.leaves() {
            put_ivec(&mut w, leaf.origin)?;
            leaf.mask
                .iter()
                .try_for_each(|m| w.write_all(&m.to_le_bytes()))?;
            let bytes: Vec<u8> = leaf.values.iter().flat_map(|v| v.to_le_bytes()).collect();
            w.write_all(&bytes)?;
        }
        for level in TileLevel::ALL {
            // Sorted so that two bakes of one input give identical files whatever the map order.
            let mut tiles: Vec<(IVec3, f32)> = density.tiles(level).collect();
            tiles.sort_by_key(|(o, _)| o.to_array());
            for (origin, value) in tiles {
                put_ivec(&mut w, origin)?;
                w.write_all(&value.to_le_bytes())?;
            }
        }
        for v in transfer.layout.voxels() {
            put_ivec(&mut w, *v)?;
        }
        put_coefficients(&mut w, &transfer.t_ri, half)?;
        put_coefficients(&mut w, &transfer.f_ms, half)?;
        let sum = w.hash.digest();
        w.inner.write_all(&sum.to_le_bytes())
    })
}

/// A bounds-checked reader over the cache body (sizes were validated up front, so a short read
/// here means the header lied about a count — still an error, never a panic).
struct Body<'a> {
    bytes: &'a [u8],
}

impl<'a> Body<'a> {
    fn take(&mut self, n: usize) -> std::result::Result<&'a [u8], String> {
        if n > self.bytes.len() {
            return Err("cache sections are shorter than the header says".into());
        }
        let (a, b) = self.bytes.split_at(n);
        self.bytes = b;
        Ok(a)
    }

    fn u32s<const N: usize>(&mut self) -> std::result::Result<[u32; N], String> {
        let b = self.take(4 * N)?;
        Ok(std::array::from_fn(|i| {
            u32::from_le_bytes([b[4 * i], b[4 * i + 1], b[4 * i + 2], b[4 * i + 3]])
        }))
    }

    fn ivec(&mut self) -> std::result::Result<IVec3, String> {
        let [x, y, z] = self.u32s::<3>()?;
        Ok(IVec3::new(x as i32, y as i32, z as i32))
    }

    fn f32(&mut self) -> std::result::Result<f32, String> {
        Ok(f32::from_bits(self.u32s::<1>()?[0]))
    }

    fn coefficients(&mut self, n: usize, half: bool) -> std::result::Result<Vec<f32>, String> {
        if half {
            let b = self.take(2 * n)?;
            Ok(b.chunks_exact(2)
                .map(|c| half::f16::from_le_bytes([c[0], c[1]]).to_f32())
                .collect())
        } else {
            let b = self.take(4 * n)?;
            Ok(b.chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect())
        }
    }
}

/// Whether `path` starts with the cache magic (a short or unreadable file is not a cache here; the
/// VDB reader then reports what is wrong with it).
pub fn is_cache(path: &Path) -> Result<bool> {
    use std::io::Read;
    let mut magic = [0u8; MAGIC.len()];
    let mut file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    Ok(file.read_exact(&mut magic).is_ok() && &magic == MAGIC)
}

/// The format version of the cache at `path`; `None` when it does not start with the cache magic.
pub fn format_version(path: &Path) -> Result<Option<u32>> {
    use std::io::Read;
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
    let body = header
        .body_len()
        .ok_or("the header's counts or coefficient type are invalid")?;
    let want = (end as u64)
        .checked_add(body)
        .and_then(|n| n.checked_add(8));
    if want != Some(file_len) {
        return Err(format!(
            "truncated or padded: the header describes {} bytes, the file has {file_len}",
            want.map_or("too many".into(), |n| n.to_string()),
        ));
    }
    if !(1..=crate::light::sh::MAX_BANDS).contains(&header.bands) || header.scale < 1 {
        return Err("the header's bake settings are invalid".into());
    }
    Ok((header, end))
}

/// Reads only the header of the cache at `path`, checked against the file's length (not the
/// checksum): enough to tell whether the cache is current without reading its data. `None` for
/// a cache of an older format (stale: what a bake computes changed); an error for anything else
/// that is not a cache of this format.
pub fn read_header(path: &Path) -> Result<Option<Header>> {
    use std::io::Read;
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
    let data = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    read_bytes(&data).map_err(|m| damaged(path, m))
}

/// Reads a cache's header and verifies the checksum over the whole file, without decoding the
/// data (for `info`: a damaged cache is reported as damaged, not described).
pub fn verify(path: &Path) -> Result<Header> {
    let data = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let check = || {
        let (header, _) = parse_header(&data, data.len() as u64)?;
        verify_checksum(&data)?;
        Ok(header)
    };
    check().map_err(|m| damaged(path, m))
}

/// The xxh3 of everything before the last 8 bytes against those bytes (the caller has checked
/// the length against the header).
fn verify_checksum(data: &[u8]) -> std::result::Result<(), String> {
    let split = data.len() - 8;
    let mut sum = [0u8; 8];
    sum.copy_from_slice(&data[split..]);
    if xxhash_rust::xxh3::xxh3_64(&data[..split]) != u64::from_le_bytes(sum) {
        return Err("checksum mismatch: the cache is corrupted".into());
    }
    Ok(())
}

fn read_bytes(data: &[u8]) -> std::result::Result<Cache, String> {
    let (header, start) = parse_header(data, data.len() as u64)?;
    verify_checksum(data)?;
    let split = data.len() - 8;
    let settings = header
        .settings()
        .ok_or("the header names an unknown lattice")?;
    let transform = Transform {
        scale: DVec3::from_array(header.voxel_scale),
        translation: DVec3::from_array(header.translation),
    };
    let mut body = Body {
        bytes: &data[start..split],
    };
    let mut density = SparseGrid::new(transform, body.f32()?);
    for _ in 0..header.leaves {
        let origin = body.ivec()?;
        let words = body.u32s::<16>()?;
        let mask = std::array::from_fn(|i| words[2 * i] as u64 | (words[2 * i + 1] as u64) << 32);
        let values = body.coefficients(LEAF_VOXELS, false)?;
        let mut array = [0f32; LEAF_VOXELS];
        array.copy_from_slice(&values);
        density.insert_leaf(origin, mask, array);
    }
    for (level, &count) in TileLevel::ALL.iter().zip(&header.tiles) {
        for _ in 0..count {
            let origin = body.ivec()?;
            density.insert_tile(*level, origin, body.f32()?);
        }
    }
    let mut voxels = Vec::new();
    for _ in 0..header.transfer_voxels {
        voxels.push(body.ivec()?);
    }
    let layout = TransferLayout::from_voxels(settings.scale, voxels)
        .ok_or("transfer voxels are repeated or out of order")?;
    let half = header.coefficients == "f16";
    let n = layout.len() * settings.bands * settings.bands;
    let t_ri = body.coefficients(n, half)?;
    let f_ms = body.coefficients(n, half)?;
    let transfer = Transfer {
        layout,
        bands: settings.bands,
        medium: Medium {
            sigma_t: header.sigma_t,
            albedo: header.albedo,
        },
        t_ri,
        f_ms,
        lattice: (!settings.single_scatter).then_some(settings.lattice),
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

    fn tiny() -> (SparseGrid, Transfer, Header) {
        let mut g = SparseGrid::new(Transform::default(), 0.0);
        g.insert_tile(TileLevel::Block, IVec3::new(8, 0, 0), 0.75);
        let layout = TransferLayout::build(&g, 6);
        let n = layout.len() * 4;
        let transfer = Transfer {
            layout,
            bands: 2,
            medium: Medium {
                sigma_t: 2.0,
                albedo: 0.5,
            },
            t_ri: (0..n).map(|i| i as f32 * 0.25).collect(),
            f_ms: (0..n).map(|i| -(i as f32)).collect(),
            lattice: Some(LatticeKind::All),
        };
        let settings = BakeSettings {
            bands: 2,
            scale: 6,
            samples: 64,
            lattice: LatticeKind::All,
            single_scatter: false,
            seed: 7,
        };
        let origin = Origin {
            source: Source {
                name: "x.vdb".into(),
                size: 1,
                mtime_ns: 2,
                header_hash: 3,
            },
            grid: "density".into(),
            requested_grid: None,
        };
        let h = header(&g, &transfer, &settings, origin, false);
        (g, transfer, h)
    }

    #[test]
    fn round_trip_is_bit_exact_and_damage_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.vtc");
        let (g, t, h) = tiny();
        write(&path, &h, &g, &t).unwrap();
        let back = read(&path).unwrap();
        assert_eq!(back.header, h);
        assert_eq!(back.transfer.t_ri, t.t_ri);
        assert_eq!(back.transfer.f_ms, t.f_ms);
        assert_eq!(back.transfer.layout.voxels(), t.layout.voxels());
        assert_eq!(back.density.value(IVec3::new(9, 1, 1)), 0.75);
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
