//! Per-pixel storage of the nearest surface and its depth test: separate
//! depth and label buffers ([`LabelDepth`]) or one packed key per pixel
//! ([`Keys`]).

use wide::{f32x4, i32x4, CmpEq, CmpLt};

/// Per-pixel storage of the nearest surface: a depth test per fragment.
pub(super) trait Pixels {
    /// Depth test of one candidate fragment, without branches: pixel `idx`
    /// takes depth `z` and `label` when `covered` and nearer (or as near
    /// with a lower label). Out-of-range pixels are ignored.
    fn depth_test(&mut self, idx: usize, z: f32, label: u16, covered: bool);

    /// [`Pixels::depth_test`] of the four pixels from `idx` on, in SIMD
    /// lanes (`covered`: lane masks). Uncovered pixels keep their values,
    /// so the four may extend past the end of an image row (not past the
    /// buffer: the last pixels of the buffer are tested one by one).
    fn depth_test_x4(&mut self, idx: usize, z: f32x4, label: u16, covered: i32x4);

    /// [`Pixels::depth_test`] of the pixels `idx` (lane `i`: pixel
    /// `idx[i]`, depth lane `i` of `z`, covered when bit `i` of `covered`
    /// is set), one after another.
    #[inline(always)]
    fn depth_test_lanes(&mut self, idx: [usize; 4], z: f32x4, label: u16, covered: i32) {
        let z = z.to_array();
        for i in 0..4 {
            self.depth_test(idx[i], z[i], label, (covered >> i) & 1 != 0);
        }
    }

    /// [`Pixels::depth_test`] of the pixels `start..=end` (covered when
    /// `z_at`, called once per pixel in order, gives a depth); false (and
    /// nothing drawn) when the span is out of range.
    fn depth_test_span(
        &mut self,
        start: usize,
        end: usize,
        label: u16,
        z_at: impl FnMut() -> Option<f32>,
    ) -> bool;
}

/// Separate depth and label buffers, row-major.
pub(super) struct LabelDepth<'a> {
    pub(super) labels: &'a mut [u16],
    pub(super) depth_m: &'a mut [f32],
}

impl Pixels for LabelDepth<'_> {
    #[inline(always)]
    fn depth_test(&mut self, idx: usize, z: f32, label: u16, covered: bool) {
        if let (Some(d), Some(l)) = (self.depth_m.get_mut(idx), self.labels.get_mut(idx)) {
            let win = covered & ((z < *d) | ((z == *d) & (label < *l)));
            *d = if win { z } else { *d };
            *l = if win { label } else { *l };
        }
    }

    #[inline(always)]
    fn depth_test_x4(&mut self, idx: usize, z: f32x4, label: u16, covered: i32x4) {
        let (Some(d), Some(l)) = (
            self.depth_m.get_mut(idx..idx + 4),
            self.labels.get_mut(idx..idx + 4),
        ) else {
            let (z, covered) = (z.to_array(), covered.move_mask());
            for (c, &z) in z.iter().enumerate() {
                self.depth_test(idx + c, z, label, (covered >> c) & 1 != 0);
            }
            return;
        };
        let old_d = f32x4::from([d[0], d[1], d[2], d[3]]);
        let old_l = i32x4::from([l[0], l[1], l[2], l[3]].map(i32::from));
        let label_v = i32x4::splat(i32::from(label));
        let nearer = bytemuck::cast::<f32x4, i32x4>(z.cmp_lt(old_d));
        let equal = bytemuck::cast::<f32x4, i32x4>(z.cmp_eq(old_d));
        let win = covered & (nearer | (equal & label_v.cmp_lt(old_l)));
        let new_d = bytemuck::cast::<i32x4, f32x4>(win)
            .blend(z, old_d)
            .to_array();
        let new_l = win.blend(label_v, old_l).to_array();
        d.copy_from_slice(&new_d);
        for (l, n) in l.iter_mut().zip(new_l) {
            *l = n as u16;
        }
    }

    #[inline(always)]
    fn depth_test_span(
        &mut self,
        start: usize,
        end: usize,
        label: u16,
        mut z_at: impl FnMut() -> Option<f32>,
    ) -> bool {
        let (Some(depths), Some(labels)) = (
            self.depth_m.get_mut(start..=end),
            self.labels.get_mut(start..=end),
        ) else {
            return false;
        };
        for (d, l) in depths.iter_mut().zip(labels.iter_mut()) {
            if let Some(z) = z_at() {
                if z < *d || (z == *d && label < *l) {
                    *d = z;
                    *l = label;
                }
            }
        }
        true
    }
}

/// The depth and label of a fragment packed into one integer whose order
/// is that of the depth test: smaller wins (nearer, or as near with a
/// lower label). The high 32 bits are the bits of `z` mapped so that they
/// order as the values (negative values' bits flipped, the sign bit of the
/// others set), the low 16 bits the label. Orders as [`LabelDepth`]'s
/// comparisons for all depths except NaN and zeros (of either sign), which
/// never occur: depths are `1 / iz` with `iz` finite and not NaN
/// (interpolated from finite 1/z of unclipped vertices).
#[inline(always)]
pub(super) fn depth_key(z: f32, label: u16) -> u64 {
    let bits = z.to_bits();
    let ordered = bits ^ ((((bits as i32) >> 31) as u32) | 0x8000_0000);
    (u64::from(ordered) << 32) | u64::from(label)
}

/// The high halves of [`depth_key`] (depth bits mapped to their order) of
/// four depths, in SIMD lanes.
#[inline(always)]
fn ordered_bits_x4(z: f32x4) -> i32x4 {
    let bits = bytemuck::cast::<f32x4, i32x4>(z);
    let sign: i32x4 = bits >> 31_i32;
    bits ^ (sign | i32x4::splat(i32::MIN))
}

/// [`depth_key`] of the background (depth infinity, label 0).
pub(super) const BACKGROUND_KEY: u64 = (((0x7f80_0000u32) | 0x8000_0000) as u64) << 32;

/// Depth and label packed per pixel ([`depth_key`]), row-major: the depth
/// test is a minimum.
pub(super) struct Keys<'a> {
    pub(super) keys: &'a mut [u64],
}

impl Pixels for Keys<'_> {
    #[inline(always)]
    fn depth_test(&mut self, idx: usize, z: f32, label: u16, covered: bool) {
        if let Some(k) = self.keys.get_mut(idx) {
            let key = if covered {
                depth_key(z, label)
            } else {
                u64::MAX
            };
            *k = (*k).min(key);
        }
    }

    #[inline(always)]
    fn depth_test_x4(&mut self, idx: usize, z: f32x4, label: u16, covered: i32x4) {
        if let Some(k) = self.keys.get_mut(idx..idx + 4) {
            let ordered = ordered_bits_x4(z).to_array();
            let covered = covered.to_array();
            for ((k, &o), &c) in k.iter_mut().zip(ordered.iter()).zip(covered.iter()) {
                let key = if c != 0 {
                    (u64::from(o as u32) << 32) | u64::from(label)
                } else {
                    u64::MAX
                };
                *k = (*k).min(key);
            }
        } else {
            let (z, covered) = (z.to_array(), covered.move_mask());
            for (c, &z) in z.iter().enumerate() {
                self.depth_test(idx + c, z, label, (covered >> c) & 1 != 0);
            }
        }
    }

    #[inline(always)]
    fn depth_test_lanes(&mut self, idx: [usize; 4], z: f32x4, label: u16, covered: i32) {
        let ordered = ordered_bits_x4(z).to_array();
        for i in 0..4 {
            let key = if (covered >> i) & 1 != 0 {
                (u64::from(ordered[i] as u32) << 32) | u64::from(label)
            } else {
                u64::MAX
            };
            if let Some(k) = self.keys.get_mut(idx[i]) {
                *k = (*k).min(key);
            }
        }
    }

    #[inline(always)]
    fn depth_test_span(
        &mut self,
        start: usize,
        end: usize,
        label: u16,
        mut z_at: impl FnMut() -> Option<f32>,
    ) -> bool {
        let Some(keys) = self.keys.get_mut(start..=end) else {
            return false;
        };
        for k in keys {
            if let Some(z) = z_at() {
                *k = (*k).min(depth_key(z, label));
            }
        }
        true
    }
}
