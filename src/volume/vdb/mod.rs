//! The project's own OpenVDB reader (file format 222–224, docs/vdb-format.md): archive header,
//! metadata, grid descriptors, grid bodies — decoding float, half, double, integer and vector trees
//! straight into a [`SparseGrid`]. Everything read from the file is checked against what remains
//! of it before it is used, so a damaged or forged file is a clear error, never a panic or an
//! unbounded allocation.

mod codec;
mod cursor;
mod transform;
mod tree;

use std::path::{Path, PathBuf};

use serde_json::{json, Value};

pub use codec::Scalar;
use codec::{ValueFormat, ACTIVE_MASK, BLOSC, ZIP};
use cursor::Cursor;

use crate::error::{Error, Result};
use crate::volume::{SparseGrid, Transform};

/// A problem found in the bytes of a VDB file; [`VdbFile`] adds the file name.
#[derive(Debug)]
pub struct VdbError(String);

impl VdbError {
    fn new(msg: impl Into<String>) -> Self {
        VdbError(msg.into())
    }
}

/// `20 42 44 56 00 00 00 00`: "VDB " as a little-endian i64.
const MAGIC: [u8; 8] = [0x20, 0x42, 0x44, 0x56, 0, 0, 0, 0];
/// Header bytes up to the file metadata, for format ≥ 222.
const HEADER_LEN: usize = 57;
/// File format versions this reader implements (§13: 222 added the per-grid compression word).
const MIN_VERSION: u32 = 222;
const MAX_VERSION: u32 = 224;
/// Longest grid name, type name or metadata name accepted (§15).
const MAX_NAME: usize = 4096;
/// Smallest possible metadata entry: two empty-string lengths and a value size.
const MIN_META_ENTRY: usize = 12;
/// Smallest possible grid descriptor: three string lengths and three offsets.
const MIN_DESCRIPTOR: usize = 36;
/// Separator OpenVDB puts between a grid's name and its uniqueness index.
const NAME_SEPARATOR: char = '\u{1e}';

/// What a grid's values are.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ValueKind {
    /// A tree this reader decodes (scalars as themselves, vectors as their length).
    Readable { scalar: Scalar, components: usize },
    /// A tree it lists but does not decode (bool/mask leaves hold bits, points need multi-pass).
    Unsupported,
}

/// One grid as the file's descriptor and body header describe it.
#[derive(Debug, Clone)]
pub struct GridInfo {
    /// Display name (the unique name without OpenVDB's `\x1e` index).
    pub name: String,
    /// The value type word of the grid type: `float`, `double`, `vec3s`, `bool`, …
    pub value_type: String,
    /// The full grid type string, e.g. `Tree_float_5_4_3_HalfFloat`.
    pub grid_type: String,
    pub kind: ValueKind,
    /// Values are stored as 16-bit floats.
    pub half: bool,
    /// `fog volume`, `level set`, `staggered` or `unknown`.
    pub class: String,
    /// Name of the grid whose tree this instance shares, if it is an instance.
    pub instance_of: Option<String>,
    pub compression: u32,
    pub transform: Transform,
    /// The transform's map type as written (`UniformScaleMap`, …).
    pub map_type: String,
    /// The writer's own statistics, when it stored them: a cross-check only.
    pub file_voxel_count: Option<i64>,
    unique_name: String,
    /// Byte ranges of the body: where the tree starts, where buffers start, where the grid ends.
    tree_pos: usize,
    block_pos: Option<usize>,
    end_pos: Option<usize>,
}

impl GridInfo {
    /// What `vdb_print -l` tells about this grid, as JSON; `tree` is its decoded tree (`None`
    /// when its value type is not a volume).
    pub fn describe(&self, tree: Option<&SparseGrid>) -> Value {
        let g = self;
        let t = &g.transform;
        let mut v = json!({
            "name": g.name,
            "value_type": g.value_type,
            "grid_type": g.grid_type,
            "half": g.half,
            "class": g.class,
            "instance_of": g.instance_of,
            "compression": g.compression_name(),
            "map_type": g.map_type,
            "voxel_size": t.voxel_size().to_array(),
            "scale": t.scale.to_array(),
            "translation": t.translation.to_array(),
        });
        let Some(tree) = tree else {
            v["note"] = json!("not read: this value type is not a volume");
            return v;
        };
        let bbox = tree.active_bbox();
        let stats = tree.value_stats();
        // Vectors are read as their length: a range of lengths is meaningful, a sum is not.
        let scalar = g.is_scalar();
        let extra = json!({
            "active_voxels": tree.active_voxels(),
            "tiles": tree.tile_count(),
            "leaves": tree.leaf_count(),
            "bbox_min": bbox.map(|b| b.0.to_array()),
            "bbox_max": bbox.map(|b| b.1.to_array()),
            "background": tree.background,
            "value_min": stats.map(|s| s.min),
            "value_max": stats.map(|s| s.max),
            "value_sum": stats.filter(|_| scalar).map(|s| s.sum),
            "value_range_of": if scalar { "values" } else { "vector lengths" },
            "memory_bytes": tree.memory_bytes(),
            "file_voxel_count": g.file_voxel_count,
        });
        if let (Value::Object(a), Value::Object(b)) = (&mut v, extra) {
            a.extend(b);
        }
        v
    }

    pub fn is_scalar(&self) -> bool {
        matches!(self.kind, ValueKind::Readable { components: 1, .. })
    }

    /// Compression flags in words, as OpenVDB's `file_compression` metadata spells them.
    pub fn compression_name(&self) -> String {
        let mut parts = Vec::new();
        if self.compression & BLOSC != 0 {
            parts.push("blosc");
        } else if self.compression & ZIP != 0 {
            parts.push("zip");
        }
        if self.compression & ACTIVE_MASK != 0 {
            parts.push("active values");
        }
        if parts.is_empty() {
            "none".into()
        } else {
            parts.join(" + ")
        }
    }
}

/// A VDB file's bytes: mapped from disk, or given in memory (a fuzzer's input).
enum Bytes {
    Mapped(memmap2::Mmap),
    Owned(Vec<u8>),
}

impl std::ops::Deref for Bytes {
    type Target = [u8];
    fn deref(&self) -> &[u8] {
        match self {
            Bytes::Mapped(m) => m,
            Bytes::Owned(v) => v,
        }
    }
}

/// An opened VDB file: its bytes and the list of its grids.
pub struct VdbFile {
    path: PathBuf,
    data: Bytes,
    pub version: u32,
    pub library: (u32, u32),
    pub grids: Vec<GridInfo>,
}

impl VdbFile {
    /// Opens and indexes a VDB file: header, metadata and every grid's descriptor, metadata and
    /// transform. Trees are read on demand by [`VdbFile::read_grid`].
    pub fn open(path: &Path) -> Result<VdbFile> {
        let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
        let meta = file.metadata().map_err(|e| Error::io(path, e))?;
        // A directory opens, and its map fails with "No such device".
        if meta.is_dir() {
            return Err(Error::format(path, "a directory, not a VDB file"));
        }
        let len = meta.len();
        if len < HEADER_LEN as u64 {
            return Err(Error::format(
                path,
                format!("not a VDB file: {len} bytes, shorter than a VDB header"),
            ));
        }
        // SAFETY: the map is read-only and private to this process; a file truncated by another
        // process while mapped is the one case no reader of a shared file can defend against.
        let data = unsafe { memmap2::Mmap::map(&file) }.map_err(|e| Error::io(path, e))?;
        VdbFile::indexed(path, Bytes::Mapped(data))
    }

    /// Indexes a VDB file held in memory as [`VdbFile::open`] does one on disk; `name` stands for
    /// its path in errors. The reader's fuzz target (tools/fuzz) drives it.
    pub fn from_bytes(name: &str, bytes: Vec<u8>) -> Result<VdbFile> {
        if bytes.len() < HEADER_LEN {
            return Err(Error::format(
                name,
                format!(
                    "not a VDB file: {} bytes, shorter than a VDB header",
                    bytes.len()
                ),
            ));
        }
        VdbFile::indexed(Path::new(name), Bytes::Owned(bytes))
    }

    fn indexed(path: &Path, data: Bytes) -> Result<VdbFile> {
        let mut vdb = VdbFile {
            path: path.to_path_buf(),
            data,
            version: 0,
            library: (0, 0),
            grids: Vec::new(),
        };
        vdb.index().map_err(|e| Error::format(path, e.0))?;
        Ok(vdb)
    }

    fn index(&mut self) -> std::result::Result<(), VdbError> {
        let data: &[u8] = &self.data;
        let mut cur = Cursor::new(data);
        if cur.bytes(8, "magic")? != MAGIC {
            return Err(VdbError::new("not a VDB file (wrong magic number)"));
        }
        let version = cur.u32("file format version")?;
        if !(MIN_VERSION..=MAX_VERSION).contains(&version) {
            return Err(VdbError::new(format!(
                "VDB file format version {version} is not supported (this reader reads {MIN_VERSION}–{MAX_VERSION}, written by OpenVDB 3.2 and later)"
            )));
        }
        self.version = version;
        self.library = (cur.u32("library version")?, cur.u32("library version")?);
        let has_offsets = cur.bool("has-grid-offsets flag")?;
        cur.skip(36, "UUID")?;
        read_metadata(&mut cur)?;
        let count = cur.i32("grid count")?;
        if count < 0 || count as usize > cur.remaining() / MIN_DESCRIPTOR {
            return Err(VdbError::new(format!(
                "grid count {count} is impossible for the bytes left"
            )));
        }
        let mut grids: Vec<GridInfo> = Vec::new();
        for _ in 0..count {
            let g = read_grid_header(&mut cur, has_offsets, &grids, data.len())?;
            if has_offsets {
                let end = g.end_pos.unwrap_or(data.len());
                cur = Cursor::window(data, end, data.len())?;
            } else if g.instance_of.is_none() {
                // A stream file has no offsets: the next descriptor follows this tree, so the
                // tree must be read through to find it.
                if let ValueKind::Readable { .. } = g.kind {
                    let mut body = Cursor::window(data, g.tree_pos, data.len())?;
                    let bounds = tree::Bounds {
                        block_pos: None,
                        end_pos: None,
                    };
                    tree::read_tree(&mut body, value_format(&g)?, g.transform, &bounds)?;
                    cur = Cursor::window(data, body.pos(), data.len())?;
                } else {
                    return Err(VdbError::new(format!(
                        "grid {:?} of type {} cannot be skipped in a file without grid offsets",
                        g.name, g.grid_type
                    )));
                }
            } else {
                cur = Cursor::window(data, g.tree_pos, data.len())?;
            }
            grids.push(g);
        }
        self.grids = grids;
        Ok(())
    }

    /// The grid `--grid NAME` asks for; by default `density`, else the first scalar grid.
    pub fn choose_grid(&self, name: Option<&str>) -> Result<usize> {
        let list = || {
            self.grids
                .iter()
                .map(|g| format!("{} ({})", g.name, g.value_type))
                .collect::<Vec<_>>()
                .join(", ")
        };
        if self.grids.is_empty() {
            return Err(Error::format(&self.path, "the file holds no grids"));
        }
        let found = match name {
            Some(n) => self.grids.iter().position(|g| g.name == n).ok_or_else(|| {
                Error::format(
                    &self.path,
                    format!("no grid named {n:?}; the file has: {}", list()),
                )
            })?,
            None => self
                .grids
                .iter()
                .position(|g| g.name == "density" && g.is_scalar())
                .or_else(|| self.grids.iter().position(GridInfo::is_scalar))
                .ok_or_else(|| {
                    Error::format(
                        &self.path,
                        format!("no scalar grid to render; the file has: {}", list()),
                    )
                })?,
        };
        if !self.grids[found].is_scalar() {
            let g = &self.grids[found];
            return Err(Error::format(
                &self.path,
                format!(
                    "grid {:?} holds {} values, not a scalar density",
                    g.name, g.value_type
                ),
            ));
        }
        Ok(found)
    }

    /// Reads grid `index`'s tree into a sparse grid (vectors as their length).
    pub fn read_grid(&self, index: usize) -> Result<SparseGrid> {
        let g = &self.grids[index];
        let source = match &g.instance_of {
            Some(parent) => self
                .grids
                .iter()
                .find(|p| &p.unique_name == parent)
                .ok_or_else(|| Error::format(&self.path, "instance parent vanished"))?,
            None => g,
        };
        let result = (|| {
            let fmt = value_format(source)?;
            let end = source.end_pos.unwrap_or(self.data.len());
            let mut cur = Cursor::window(&self.data, source.tree_pos, end)?;
            let bounds = tree::Bounds {
                block_pos: source.block_pos,
                end_pos: source.end_pos,
            };
            tree::read_tree(&mut cur, fmt, g.transform, &bounds)
        })();
        result.map_err(|e| Error::format(&self.path, format!("grid {:?}: {}", g.name, e.0)))
    }
}

fn value_format(g: &GridInfo) -> std::result::Result<ValueFormat, VdbError> {
    match g.kind {
        ValueKind::Readable { scalar, components } => Ok(ValueFormat {
            scalar,
            components,
            half: g.half,
            flags: g.compression,
        }),
        ValueKind::Unsupported => Err(VdbError::new(format!(
            "grids of type {} cannot be read as a volume",
            g.grid_type
        ))),
    }
}

/// The value kind of a grid type string with the `_HalfFloat` suffix already stripped.
fn value_kind(grid_type: &str) -> (String, ValueKind) {
    let Some(value) = grid_type
        .strip_prefix("Tree_")
        .and_then(|t| t.strip_suffix("_5_4_3"))
    else {
        return (grid_type.to_string(), ValueKind::Unsupported);
    };
    let readable = |scalar, components| ValueKind::Readable { scalar, components };
    let kind = match value {
        "float" => readable(Scalar::F32, 1),
        "double" => readable(Scalar::F64, 1),
        "int32" => readable(Scalar::I32, 1),
        "int64" => readable(Scalar::I64, 1),
        "vec3s" => readable(Scalar::F32, 3),
        "vec3d" => readable(Scalar::F64, 3),
        "vec3i" => readable(Scalar::I32, 3),
        _ => ValueKind::Unsupported,
    };
    (value.to_string(), kind)
}

/// What the reader keeps from a grid's metadata map.
#[derive(Default)]
struct GridMeta {
    class: Option<String>,
    half: bool,
    file_voxel_count: Option<i64>,
}

/// Reads a metadata map (§4), validating sizes; returns the entries vscatter uses.
fn read_metadata(cur: &mut Cursor) -> std::result::Result<GridMeta, VdbError> {
    let count = cur.u32("metadata count")? as usize;
    if count > cur.remaining() / MIN_META_ENTRY {
        return Err(VdbError::new(format!(
            "metadata count {count} is impossible for the bytes left"
        )));
    }
    let mut meta = GridMeta::default();
    let mut names = hashbrown::HashSet::new();
    for _ in 0..count {
        let name = cur.string(MAX_NAME, "metadata name")?;
        if name.is_empty() || !names.insert(name.clone()) {
            return Err(VdbError::new(format!(
                "metadata name {name:?} is empty or repeated"
            )));
        }
        let type_name = cur.string(MAX_NAME, "metadata type")?;
        let size = cur.u32("metadata value size")? as usize;
        let fixed = match type_name.as_str() {
            "bool" => Some(1),
            "int32" | "float" => Some(4),
            "int64" | "double" | "vec2i" | "vec2s" => Some(8),
            "vec3i" | "vec3s" => Some(12),
            "vec2d" | "vec4i" | "vec4s" => Some(16),
            "vec3d" => Some(24),
            "vec4d" => Some(32),
            "mat4s" => Some(64),
            "mat4d" => Some(128),
            _ => None,
        };
        if fixed.is_some_and(|f| f != size) {
            return Err(VdbError::new(format!(
                "metadata {name:?} of type {type_name} has size {size}"
            )));
        }
        let payload = cur.bytes(size, "metadata value")?;
        match (name.as_str(), type_name.as_str()) {
            ("class", "string") => meta.class = Some(String::from_utf8_lossy(payload).into_owned()),
            ("is_saved_as_half_float", "bool") => {
                meta.half = match payload[0] {
                    0 => false,
                    1 => true,
                    b => return Err(VdbError::new(format!("half-float flag byte is {b}"))),
                }
            }
            ("file_voxel_count", "int64") => {
                let mut a = [0u8; 8];
                a.copy_from_slice(payload);
                meta.file_voxel_count = Some(i64::from_le_bytes(a));
            }
            _ => {}
        }
    }
    Ok(meta)
}

/// Reads one grid descriptor and its body header (compression, metadata, transform).
fn read_grid_header(
    cur: &mut Cursor,
    has_offsets: bool,
    earlier: &[GridInfo],
    file_len: usize,
) -> std::result::Result<GridInfo, VdbError> {
    let unique_name = cur.string(MAX_NAME, "grid name")?;
    let raw_type = cur.string(MAX_NAME, "grid type")?;
    let parent = cur.string(MAX_NAME, "instance parent name")?;
    let offsets = [
        cur.i64("grid offset")?,
        cur.i64("block offset")?,
        cur.i64("end offset")?,
    ];
    let name = unique_name
        .split(NAME_SEPARATOR)
        .next()
        .unwrap_or_default()
        .to_string();
    if earlier.iter().any(|g| g.unique_name == unique_name) {
        return Err(VdbError::new(format!(
            "grid name {unique_name:?} appears twice"
        )));
    }
    let (suffix_half, base_type) = match raw_type.strip_suffix("_HalfFloat") {
        Some(t) => (true, t),
        None => (false, raw_type.as_str()),
    };
    let (value_type, kind) = value_kind(base_type);
    let instance_of = (!parent.is_empty()).then_some(parent);
    if let Some(p) = &instance_of {
        let ok = earlier
            .iter()
            .any(|g| &g.unique_name == p && g.instance_of.is_none() && g.grid_type == raw_type);
        if !ok {
            return Err(VdbError::new(format!(
                "grid {name:?} is an instance of {p:?}, which is not an earlier grid of the same type"
            )));
        }
    }
    let (block_pos, end_pos) = match has_offsets {
        true => grid_window(
            cur,
            &name,
            offsets,
            instance_of.is_some(),
            earlier,
            file_len,
        )?,
        false => (None, None),
    };
    let compression = cur.u32("compression flags")?;
    if compression & !(ZIP | ACTIVE_MASK | BLOSC) != 0 {
        return Err(VdbError::new(format!(
            "grid {name:?}: compression flags {compression:#x} have unknown bits"
        )));
    }
    let meta = read_metadata(cur)?;
    if meta.half != suffix_half {
        return Err(VdbError::new(format!(
            "grid {name:?}: type {raw_type} disagrees with its half-float metadata"
        )));
    }
    let (transform, map_type) = transform::read_transform(cur)?;
    Ok(GridInfo {
        name,
        value_type,
        grid_type: raw_type,
        kind,
        half: suffix_half,
        class: meta.class.unwrap_or_else(|| "unknown".into()),
        instance_of,
        compression,
        transform,
        map_type,
        file_voxel_count: meta.file_voxel_count,
        unique_name,
        tree_pos: cur.pos(),
        block_pos,
        end_pos,
    })
}

/// Checks a grid's offsets (grid, block, end) against the descriptor's end, the file and the grid
/// before it, and narrows `cur` to the grid's bytes; returns where its buffers start (not for an
/// instance, which has none) and where it ends.
fn grid_window(
    cur: &mut Cursor,
    name: &str,
    offsets: [i64; 3],
    instance: bool,
    earlier: &[GridInfo],
    file_len: usize,
) -> std::result::Result<(Option<usize>, Option<usize>), VdbError> {
    let desc_end = cur.pos() as i64;
    let [g, b, e] = offsets;
    let block_ok = if instance { b == 0 } else { g <= b && b <= e };
    if !(desc_end <= g && block_ok && g <= e && e <= file_len as i64) {
        return Err(VdbError::new(format!(
            "grid {name:?}: offsets {g}/{b}/{e} do not fit in the file ({file_len} bytes)"
        )));
    }
    if earlier
        .last()
        .and_then(|l| l.end_pos)
        .is_some_and(|prev| e as usize <= prev)
    {
        return Err(VdbError::new(format!(
            "grid {name:?}: offsets go backwards"
        )));
    }
    *cur = Cursor::window(cur_data(cur), g as usize, e as usize)?;
    Ok(((!instance).then_some(b as usize), Some(e as usize)))
}

/// The whole file behind a cursor (cursors keep absolute offsets).
fn cur_data<'a>(cur: &Cursor<'a>) -> &'a [u8] {
    cur.data()
}

#[cfg(test)]
mod tests;
