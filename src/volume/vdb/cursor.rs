//! A bounds-checked little-endian cursor over the file's bytes: every read either succeeds inside
//! the buffer or returns an error saying what was being read, so a truncated file never panics.

use super::VdbError;

#[derive(Clone)]
pub struct Cursor<'a> {
    data: &'a [u8],
    pos: usize,
}

impl<'a> Cursor<'a> {
    pub fn new(data: &'a [u8]) -> Self {
        Cursor { data, pos: 0 }
    }

    /// A cursor over `data[start..end]`, positioned at `start` (offsets stay absolute).
    pub fn window(data: &'a [u8], start: usize, end: usize) -> Result<Self, VdbError> {
        if start > end || end > data.len() {
            return Err(VdbError::new(format!(
                "section {start}..{end} lies outside the file ({} bytes)",
                data.len()
            )));
        }
        Ok(Cursor {
            data: &data[..end],
            pos: start,
        })
    }

    /// Every byte the cursor may read, from the start of the file (offsets are absolute).
    pub fn data(&self) -> &'a [u8] {
        self.data
    }

    pub fn pos(&self) -> usize {
        self.pos
    }

    pub fn remaining(&self) -> usize {
        self.data.len() - self.pos
    }

    pub fn bytes(&mut self, n: usize, what: &str) -> Result<&'a [u8], VdbError> {
        if n > self.remaining() {
            return Err(VdbError::new(format!(
                "truncated: {what} needs {n} bytes at offset {}, only {} left",
                self.pos,
                self.remaining()
            )));
        }
        let s = &self.data[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }

    pub fn skip(&mut self, n: usize, what: &str) -> Result<(), VdbError> {
        self.bytes(n, what).map(|_| ())
    }

    fn array<const N: usize>(&mut self, what: &str) -> Result<[u8; N], VdbError> {
        let mut a = [0u8; N];
        a.copy_from_slice(self.bytes(N, what)?);
        Ok(a)
    }

    pub fn u8(&mut self, what: &str) -> Result<u8, VdbError> {
        Ok(self.array::<1>(what)?[0])
    }

    pub fn bool(&mut self, what: &str) -> Result<bool, VdbError> {
        match self.u8(what)? {
            0 => Ok(false),
            1 => Ok(true),
            b => Err(VdbError::new(format!(
                "{what}: boolean byte is {b}, not 0 or 1"
            ))),
        }
    }

    pub fn u32(&mut self, what: &str) -> Result<u32, VdbError> {
        Ok(u32::from_le_bytes(self.array(what)?))
    }

    pub fn i32(&mut self, what: &str) -> Result<i32, VdbError> {
        Ok(i32::from_le_bytes(self.array(what)?))
    }

    pub fn i64(&mut self, what: &str) -> Result<i64, VdbError> {
        Ok(i64::from_le_bytes(self.array(what)?))
    }

    pub fn f64(&mut self, what: &str) -> Result<f64, VdbError> {
        Ok(f64::from_le_bytes(self.array(what)?))
    }

    pub fn coord(&mut self, what: &str) -> Result<glam::IVec3, VdbError> {
        Ok(glam::IVec3::new(
            self.i32(what)?,
            self.i32(what)?,
            self.i32(what)?,
        ))
    }

    /// A length-prefixed string, its length capped at `max` before anything is allocated.
    pub fn string(&mut self, max: usize, what: &str) -> Result<String, VdbError> {
        let n = self.u32(what)? as usize;
        if n > max {
            return Err(VdbError::new(format!(
                "{what}: length {n} exceeds the limit of {max} bytes"
            )));
        }
        Ok(String::from_utf8_lossy(self.bytes(n, what)?).into_owned())
    }
}
