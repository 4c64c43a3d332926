//! What both bf16 units and the packing share: bf16 values as the hardware rounds them,
//! and the geometry of the 1 KiB blocks they are packed in (`pack.rs` draws the layout).

/// Rows (of `A`) or columns (of `B`) per block, and inner pairs per block.
pub(crate) const BLOCK: usize = 16;
/// Inner values per block.
pub(crate) const K_BLOCK: usize = 32;
/// `u32` pairs per block.
pub(crate) const BLOCK_LEN: usize = BLOCK * BLOCK;

/// f32 → bf16 as the hardware converts (`VCVTNE2PS2BF16`): round to nearest even,
/// subnormals to signed zero, NaN quieted, past the largest bf16 to infinity.
pub(crate) fn bf16_bits(x: f32) -> u16 {
    let b = x.to_bits();
    if b & 0x7f80_0000 == 0 {
        return ((b >> 16) & 0x8000) as u16;
    }
    if x.is_nan() {
        return ((b >> 16) | 0x0040) as u16;
    }
    ((b + 0x7fff + ((b >> 16) & 1)) >> 16) as u16
}

/// The f32 value of bf16 bits.
#[cfg(test)]
pub(crate) fn bf16_value(h: u16) -> f32 {
    f32::from_bits((h as u32) << 16)
}
