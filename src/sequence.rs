//! Frame sequences: the names artists give frames (`cloud.####.vdb`, `cloud.%04d.vdb`,
//! `cloud.$F4.vdb`, globs, plain files), frame ranges (`1001-1240:2`), the output name of each
//! frame, and the deterministic share of a farm task (`--shard K/N`). Pure bookkeeping: nothing
//! here reads a volume.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

/// Frames beyond this many in one range are refused: a typo (`1-100000000`) should not list a
/// hundred million missing files.
const MAX_FRAMES: u64 = 1_000_000;

/// `A-B[:step]` or a single frame `A`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameRange {
    pub first: i64,
    pub last: i64,
    pub step: i64,
}

impl FrameRange {
    /// Parses `1001-1240`, `1001-1240:2` or `1001`.
    pub fn parse(s: &str) -> Result<FrameRange> {
        let bad = || {
            Error::usage(format!(
                "--frames {s:?}: expected FIRST-LAST[:STEP], e.g. 1001-1240 or 1001-1240:2"
            ))
        };
        let (span, step) = match s.split_once(':') {
            Some((span, step)) => (span, step.trim().parse::<i64>().map_err(|_| bad())?),
            None => (s, 1),
        };
        // A leading '-' is a negative frame, so split at a '-' after the first character.
        let cut = span.char_indices().skip(1).find(|&(_, c)| c == '-');
        let (first, last) = match cut {
            Some((i, _)) => (&span[..i], &span[i + 1..]),
            None => (span, span),
        };
        let first: i64 = first.trim().parse().map_err(|_| bad())?;
        let last: i64 = last.trim().parse().map_err(|_| bad())?;
        if step < 1 || last < first {
            return Err(Error::usage(format!(
                "--frames {s:?}: LAST must not be below FIRST, and STEP must be at least 1"
            )));
        }
        let range = FrameRange { first, last, step };
        if range.count() > MAX_FRAMES {
            return Err(Error::usage(format!(
                "--frames {s:?}: more than {MAX_FRAMES} frames"
            )));
        }
        Ok(range)
    }

    fn count(&self) -> u64 {
        ((self.last - self.first) / self.step) as u64 + 1
    }

    pub fn frames(&self) -> impl Iterator<Item = i64> + '_ {
        (self.first..=self.last).step_by(self.step as usize)
    }

    pub fn contains(&self, frame: i64) -> bool {
        frame >= self.first && frame <= self.last && (frame - self.first) % self.step == 0
    }
}

/// A file name with a frame number in it: `prefix`, the number padded to `width`, `suffix`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FramePattern {
    /// The directory and the start of the file name.
    pub prefix: String,
    /// Zero padding of the number (`####` and `%04d` and `$F4`: 4; `%d` and `$F`: 1).
    pub width: usize,
    pub suffix: String,
}

impl FramePattern {
    /// Finds the frame token in `s`: the last `#…#`, `%0Nd`/`%d` or `$FN`/`$F`; `None` when there
    /// is none.
    pub fn parse(s: &str) -> Option<FramePattern> {
        let tokens = [hashes(s), printf(s), houdini(s)];
        let (start, end, width) = tokens.into_iter().flatten().max_by_key(|t| t.0)?;
        Some(FramePattern {
            prefix: s[..start].to_string(),
            width,
            suffix: s[end..].to_string(),
        })
    }

    /// The path of `frame`.
    pub fn path(&self, frame: i64) -> PathBuf {
        PathBuf::from(self.name(frame))
    }

    fn name(&self, frame: i64) -> String {
        let sign = if frame < 0 { "-" } else { "" };
        format!(
            "{}{sign}{:0w$}{}",
            self.prefix,
            frame.unsigned_abs(),
            self.suffix,
            w = self.width
        )
    }

    /// The frame number `name` (a whole path as the pattern spells it) stands for, if it matches:
    /// digits where the token is, at least `width` of them, zero-padded only up to `width`.
    pub fn frame_of(&self, name: &str) -> Option<i64> {
        let digits = name
            .strip_prefix(&self.prefix)?
            .strip_suffix(&self.suffix)?;
        let (neg, body) = match digits.strip_prefix('-') {
            Some(b) => (true, b),
            None => (false, digits),
        };
        if body.len() < self.width.max(1) || !body.bytes().all(|b| b.is_ascii_digit()) {
            return None;
        }
        let n: i64 = body.parse().ok()?;
        let n = if neg { -n } else { n };
        (self.name(n) == name).then_some(n)
    }

    /// Every existing file that matches, by frame: the files in the pattern's directory.
    fn scan(&self) -> Result<BTreeMap<i64, PathBuf>> {
        let whole = PathBuf::from(format!("{}0{}", self.prefix, self.suffix));
        let dir = whole
            .parent()
            .filter(|d| !d.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
        let mut found = BTreeMap::new();
        let entries = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
        for entry in entries.flatten() {
            let path = match whole.parent().filter(|d| !d.as_os_str().is_empty()) {
                Some(_) => dir.join(entry.file_name()),
                None => PathBuf::from(entry.file_name()),
            };
            if let Some(n) = self.frame_of(&path.to_string_lossy()) {
                found.insert(n, path);
            }
        }
        Ok(found)
    }
}

/// The last run of two or more `#` (one `#` alone is too common in names to be a token).
fn hashes(s: &str) -> Option<(usize, usize, usize)> {
    let end = s.rfind('#')? + 1;
    let start = s[..end].trim_end_matches('#').len();
    (end - start >= 2 || s.matches('#').count() == 1).then_some((start, end, end - start))
}

/// The last `%d` or `%0Nd`.
fn printf(s: &str) -> Option<(usize, usize, usize)> {
    let start = s.rfind('%')?;
    let rest = &s[start + 1..];
    let d = rest.find('d')?;
    let spec = &rest[..d];
    let width = match spec {
        "" => 1,
        w if w.starts_with('0') && w.len() > 1 && w.bytes().all(|b| b.is_ascii_digit()) => {
            w.parse().ok()?
        }
        _ => return None,
    };
    Some((start, start + 2 + d, width))
}

/// The last `$F` or `$FN` (Houdini).
fn houdini(s: &str) -> Option<(usize, usize, usize)> {
    let start = s.rfind("$F")?;
    let rest = &s[start + 2..];
    let digits = rest.len() - rest.trim_start_matches(|c: char| c.is_ascii_digit()).len();
    let width = match digits {
        0 => 1,
        _ => rest[..digits].parse().ok()?,
    };
    Some((start, start + 2 + digits, width))
}

/// One frame of a sequence: its number (when its name has one) and its file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Frame {
    pub number: Option<i64>,
    pub path: PathBuf,
}

/// The frames of a command line: what exists, in order, and the frames a range asked for that
/// have no file.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Frames {
    pub frames: Vec<Frame>,
    pub missing: Vec<PathBuf>,
}

/// Resolves the inputs of a batch or a sequence render: frame patterns (with `range`, the frames
/// it names; without, every file that matches), globs and plain files, in the order given, each
/// file once. An input that matches nothing is an error.
pub fn resolve(inputs: &[String], range: Option<FrameRange>) -> Result<Frames> {
    let mut out = Frames::default();
    for input in inputs {
        if let Some(pattern) = FramePattern::parse(input) {
            let found = pattern.scan();
            match range {
                Some(r) => {
                    let found = found.unwrap_or_default();
                    for n in r.frames() {
                        let path = pattern.path(n);
                        match found.contains_key(&n) || path.exists() {
                            true => out.frames.push(Frame {
                                number: Some(n),
                                path,
                            }),
                            false => out.missing.push(path),
                        }
                    }
                }
                None => {
                    let found = found?;
                    out.frames.extend(found.into_iter().map(|(n, path)| Frame {
                        number: Some(n),
                        path,
                    }));
                }
            }
            if out.frames.is_empty() && out.missing.is_empty() {
                return Err(Error::usage(format!("{input}: no file matches")));
            }
        } else if input.contains(['*', '?', '[']) {
            let paths = glob::glob(input)
                .map_err(|e| Error::usage(format!("{input}: not a valid glob ({e})")))?;
            let mut matched: Vec<PathBuf> = paths.flatten().collect();
            matched.sort_by_key(|p| natural_key(p));
            let matched: Vec<Frame> = matched
                .into_iter()
                .map(|path| Frame {
                    number: trailing_number(&path),
                    path,
                })
                .filter(|f| range.is_none_or(|r| f.number.is_some_and(|n| r.contains(n))))
                .collect();
            if matched.is_empty() {
                return Err(Error::usage(format!("{input}: no file matches")));
            }
            out.frames.extend(matched);
        } else {
            let path = PathBuf::from(input);
            out.frames.push(Frame {
                number: trailing_number(&path),
                path,
            });
        }
    }
    let mut seen = std::collections::HashSet::new();
    out.frames.retain(|f| seen.insert(f.path.clone()));
    Ok(out)
}

/// The last run of digits in a file's name (`cloud.1001.vdb` → 1001), the frame number of a file
/// named without a pattern.
fn trailing_number(path: &Path) -> Option<i64> {
    let name = path.file_name()?.to_string_lossy();
    let end = name.rfind(|c: char| c.is_ascii_digit())? + 1;
    let start = name[..end]
        .trim_end_matches(|c: char| c.is_ascii_digit())
        .len();
    name[start..end].parse().ok()
}

/// Sorts `cloud.2.vdb` before `cloud.10.vdb`.
fn natural_key(path: &Path) -> (String, Option<i64>, String) {
    let s = path.to_string_lossy().into_owned();
    (
        path.parent()
            .map_or_else(String::new, |p| p.to_string_lossy().into_owned()),
        trailing_number(path),
        s,
    )
}

/// `--shard K/N`: task K (1-based) of N takes every N-th frame from the K-th on, so N tasks
/// given the same frames split them exactly, with no coordination.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Shard {
    pub index: usize,
    pub count: usize,
}

impl Shard {
    pub fn parse(s: &str) -> Result<Shard> {
        let bad = || Error::usage(format!("--shard {s:?}: expected K/N with 1 ≤ K ≤ N"));
        let (k, n) = s.split_once('/').ok_or_else(bad)?;
        let index: usize = k.trim().parse().map_err(|_| bad())?;
        let count: usize = n.trim().parse().map_err(|_| bad())?;
        if index < 1 || index > count {
            return Err(bad());
        }
        Ok(Shard { index, count })
    }

    /// This shard's share of `items`.
    pub fn select<T>(&self, items: Vec<T>) -> Vec<T> {
        items
            .into_iter()
            .enumerate()
            .filter(|(i, _)| i % self.count == self.index - 1)
            .map(|(_, t)| t)
            .collect()
    }
}

/// The output of each input in `dir`: the input's file name with its extension replaced by `ext`
/// (`cloud.1001.vdb` → `DIR/cloud.1001.vtc`). Two inputs that would write one output are refused.
pub fn outputs_in(dir: &Path, frames: &[Frame], ext: &str) -> Result<Vec<PathBuf>> {
    let mut taken: BTreeMap<PathBuf, &Path> = BTreeMap::new();
    let mut out = Vec::with_capacity(frames.len());
    for f in frames {
        let name = f
            .path
            .file_name()
            .ok_or_else(|| Error::usage(format!("{}: not a file name", f.path.display())))?;
        let target = dir.join(Path::new(name).with_extension(ext));
        if let Some(other) = taken.insert(target.clone(), &f.path) {
            return Err(Error::usage(format!(
                "{} and {} would both write {}",
                other.display(),
                f.path.display(),
                target.display()
            )));
        }
        out.push(target);
    }
    Ok(out)
}

/// The name a map gives its images: `studio.exr` → `studio`, `sky` → `sky`.
pub fn map_name(env: &str) -> String {
    Path::new(env)
        .file_stem()
        .map_or_else(|| env.to_string(), |s| s.to_string_lossy().into_owned())
}

/// The image of each frame (with its index in the whole sequence) under each map: `output`'s frame
/// pattern filled with the frame's number (its position from 1 when it has none). Under several
/// maps, the map's name goes before the number (`img.####.exr` → `img.studio.####.exr`; without a
/// pattern, before the extension). Two maps of one name are refused.
pub fn image_names(
    output: &Path,
    frames: &[(usize, Frame)],
    maps: &[String],
) -> Result<Vec<Vec<PathBuf>>> {
    let names: Vec<String> = maps.iter().map(|m| map_name(m)).collect();
    if let Some(dup) = (1..names.len()).find(|&i| names[..i].contains(&names[i])) {
        return Err(Error::usage(format!(
            "--env: two maps named {:?} would write the same images",
            names[dup]
        )));
    }
    let pattern = FramePattern::parse(&output.to_string_lossy());
    let name = |index: usize, frame: &Frame, map: Option<&str>| -> PathBuf {
        let number = frame.number.unwrap_or(index as i64 + 1);
        match (&pattern, map) {
            (Some(p), None) => p.path(number),
            (Some(p), Some(m)) => FramePattern {
                prefix: format!("{}{m}.", p.prefix),
                ..p.clone()
            }
            .path(number),
            (None, None) => output.to_path_buf(),
            (None, Some(m)) => {
                let ext = output.extension().unwrap_or_default().to_string_lossy();
                output.with_extension(format!("{m}.{ext}"))
            }
        }
    };
    Ok(frames
        .iter()
        .map(|(i, f)| match names.len() {
            1 => vec![name(*i, f, None)],
            _ => names.iter().map(|m| name(*i, f, Some(m))).collect(),
        })
        .collect())
}

#[cfg(test)]
mod tests;
