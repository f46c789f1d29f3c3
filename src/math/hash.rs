//! Stateless hashes to numbers: deterministic jitter from pixel and sample indices, the same on any
//! thread and any thread count.

/// A well-mixed 32-bit integer hash (Wellons' "lowbias32"): deterministic jitter from pixel
/// coordinates, independent of thread scheduling.
#[inline]
fn hash32(mut x: u32) -> u32 {
    x ^= x >> 16;
    x = x.wrapping_mul(0x7feb_352d);
    x ^= x >> 15;
    x = x.wrapping_mul(0x846c_a68b);
    x ^= x >> 16;
    x
}

/// A uniform number in [0, 1) from three integers and a stream id (so the pixel jitter and the
/// step jitter of the same pixel are independent).
#[inline]
pub fn hash_unit(a: u32, b: u32, c: u32, stream: u32) -> f32 {
    let h = hash32(a ^ hash32(b ^ hash32(c ^ hash32(stream))));
    // The top 24 bits fill an f32 mantissa exactly, so the result is < 1.
    (h >> 8) as f32 * (1.0 / (1u32 << 24) as f32)
}
