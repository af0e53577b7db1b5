//! SIMD lane helpers.

use wide::{f32x4, f64x4, i32x4};

/// Lane masks (-1 where set) of the 4-bit masks 0..16.
/// Lane numbers 0..4.
pub(super) const LANE_INDEX: i32x4 = i32x4::new([0, 1, 2, 3]);

pub(super) const LANE_MASKS: [wide::i32x4; 16] = {
    let mut m = [wide::i32x4::new([0; 4]); 16];
    let mut bits = 0;
    while bits < 16 {
        let mut lanes = [0i32; 4];
        let mut i = 0;
        while i < 4 {
            lanes[i] = -(((bits >> i) & 1) as i32);
            i += 1;
        }
        m[bits] = wide::i32x4::new(lanes);
        bits += 1;
    }
    m
};

/// Rounds f64 lanes to f32 (as `as f32`: to nearest).
#[inline(always)]
pub(super) fn f64x4_to_f32x4(v: f64x4) -> f32x4 {
    let v = v.to_array();
    f32x4::from([v[0] as f32, v[1] as f32, v[2] as f32, v[3] as f32])
}

/// Converts integer-valued lanes below 2^31 in magnitude to f64 (exact).
#[inline(always)]
pub(super) fn int_f64(v: f32x4) -> f64x4 {
    f64x4::from_i32x4(v.round_int())
}
