//! Sorting triangles by the path that draws them: classes computed four at
//! a time in SIMD lanes without data-dependent branches, then collected
//! into per-class lists.

use super::lanes::LANE_MASKS;
use super::vertex::{gather_x4, ScreenVertex};
use super::SUBPIXEL_BITS;
use wide::{f64x4, i32x4, CmpEq, CmpGt, CmpLt};

/// Triangle classes of the fast path, see [`classify_x4`].
pub(super) const CLASSES: usize = 7;
/// Not drawn: no pixel centre in the image's part of the bounding box, zero
/// area, culled back face, or all vertices outside one clip plane.
pub(super) const CLASS_SKIP: u8 = 0;
/// Bounding box inside the image holding exactly one pixel centre.
pub(super) const CLASS_ONE: u8 = 1;
/// Bounding box inside the image holding two pixel centres (1x2 or 2x1).
pub(super) const CLASS_TWO: u8 = 2;
/// Bounding box inside the image holding 2x2 pixel centres.
pub(super) const CLASS_QUAD: u8 = 3;
/// Any other unclipped triangle: `Target::draw_triangle` (in `triangle.rs`).
pub(super) const CLASS_LARGE: u8 = 4;
/// Some vertex outside a clip plane: clipped, then
/// `Target::draw_triangle` (in `triangle.rs`).
pub(super) const CLASS_CLIP: u8 = 5;
/// Not small, bounding box inside the image holding at most
/// [`MEDIUM_COLUMNS`] x [`MEDIUM_ROWS`] pixel centres:
/// `Target::draw_medium` (in `triangle.rs`).
pub(super) const CLASS_MEDIUM: u8 = 6;
/// Largest box of [`CLASS_MEDIUM`], pixel centres.
pub(super) const MEDIUM_COLUMNS: usize = 4;
pub(super) const MEDIUM_ROWS: usize = 16;
/// `draw_list` selector of `Target::draw_medium` (in `triangle.rs`).
pub(super) const MEDIUM: usize = 3;

/// Classes of four triangles (vertex indices `tris`, screen vertices
/// `screen`), computed in SIMD lanes without branches. `cull`: lanes whose
/// back faces are skipped (all bits set) or kept (zero), back
/// faces (positive signed area, screen y pointing down); `last_x`, `last_y`:
/// largest pixel coordinates of the image. A triangle with an out-of-range
/// index is skipped.
///
/// The signed area is computed in f64, which is exact for unclipped
/// triangles: their fixed-point coordinates lie in the guard band, below
/// 2^23 in magnitude, so coordinate differences (i32) are below 2^24 and
/// the products below 2^48 (lanes of clipped triangles are ignored).
#[inline(always)]
pub(super) fn classify_x4(
    tris: [[u32; 3]; 4],
    screen: &[ScreenVertex],
    cull: i32x4,
    last_x: i32,
    last_y: i32,
) -> [u8; 4] {
    let [[x0, y0, _, o0], [x1, y1, _, o1], [x2, y2, _, o2]] = gather_x4(tris, screen);
    let zero = i32x4::splat(0);
    let any_out = o0 | o1 | o2;
    let all_out = o0 & o1 & o2;
    // Bounding box, in f32 (exact: coordinates of unclipped triangles are
    // integers below 2^23 in magnitude; min/max are single instructions).
    let (fx0, fx1, fx2) = (x0.round_float(), x1.round_float(), x2.round_float());
    let (fy0, fy1, fy2) = (y0.round_float(), y1.round_float(), y2.round_float());
    let min_x = fx0.fast_min(fx1).fast_min(fx2).fast_trunc_int();
    let max_x = fx0.fast_max(fx1).fast_max(fx2).fast_trunc_int();
    let min_y = fy0.fast_min(fy1).fast_min(fy2).fast_trunc_int();
    let max_y = fy0.fast_max(fy1).fast_max(fy2).fast_trunc_int();
    // Pixel centres of the unclamped bounding box.
    let shift = SUBPIXEL_BITS as i32;
    let cx0 = zero - ((zero - min_x) >> shift);
    let cx1 = max_x >> shift;
    let cy0 = zero - ((zero - min_y) >> shift);
    let cy1 = max_y >> shift;
    let (lx, ly) = (i32x4::splat(last_x), i32x4::splat(last_y));
    // No centre in the box clamped to the image: max(c0, 0) > min(c1, last)
    // on either axis.
    let no_image = i32x4::splat(-i32::from(last_x < 0 || last_y < 0));
    let empty = cx0.cmp_gt(cx1)
        | cx0.cmp_gt(lx)
        | cx1.cmp_lt(zero)
        | cy0.cmp_gt(cy1)
        | cy0.cmp_gt(ly)
        | cy1.cmp_lt(zero)
        | no_image;
    let unclipped = any_out.cmp_eq(zero);
    // Often (meshes finer than the pixels, in coherent triangle order)
    // all four are skipped: no need for areas and classes.
    let skipped = (unclipped & empty) | !all_out.cmp_eq(zero);
    if skipped.move_mask() == 0b1111 {
        return [CLASS_SKIP; 4];
    }
    let f = f64x4::from_i32x4;
    let area = f(x1 - x0) * f(y2 - y0) - f(y1 - y0) * f(x2 - x0);
    let area_zero = LANE_MASKS[area.cmp_eq(f64x4::splat(0.0)).move_mask() as usize & 15];
    let back = LANE_MASKS[area.cmp_gt(f64x4::splat(0.0)).move_mask() as usize & 15];
    let culled = cull & back;
    let keep = unclipped & !(empty | area_zero | culled);
    let clip = !unclipped & all_out.cmp_eq(zero);
    let outside = cx0.cmp_lt(zero) | cx1.cmp_gt(lx) | cy0.cmp_lt(zero) | cy1.cmp_gt(ly);
    let (nx, ny) = (cx1 - cx0, cy1 - cy0);
    // With `keep`, nx and ny are >= 0; 1 + nx + ny is then the small class.
    let not_one = i32x4::splat(!1);
    let small = !outside & (nx & not_one).cmp_eq(zero) & (ny & not_one).cmp_eq(zero);
    let medium = !outside
        & (nx & i32x4::splat(!(MEDIUM_COLUMNS as i32 - 1))).cmp_eq(zero)
        & (ny & i32x4::splat(!(MEDIUM_ROWS as i32 - 1))).cmp_eq(zero);
    let drawn = small.blend(
        i32x4::splat(1) + nx + ny,
        medium.blend(
            i32x4::splat(i32::from(CLASS_MEDIUM)),
            i32x4::splat(i32::from(CLASS_LARGE)),
        ),
    );
    let class = keep.blend(drawn, clip & i32x4::splat(i32::from(CLASS_CLIP)));
    let c = class.to_array();
    [c[0] as u8, c[1] as u8, c[2] as u8, c[3] as u8]
}

/// Appends to `list` the indices of the entries of `classes` equal to
/// `class` (`classes.len()` a multiple of 64), in increasing order.
#[inline(always)]
pub(super) fn collect_class(classes: &[u8], class: u8, list: &mut Vec<u32>) {
    use wide::u8x16;
    list.clear();
    let key = u8x16::splat(class);
    let mask = |block: &[u8]| {
        let mut bytes = [0u8; 16];
        bytes.copy_from_slice(block);
        u64::from(u8x16::from(bytes).cmp_eq(key).move_mask() as u16)
    };
    // Blocks of 64: fewer loop exits to mispredict than with 16.
    for (chunk, block) in classes.chunks_exact(64).enumerate() {
        let mut bits = mask(&block[..16])
            | mask(&block[16..32]) << 16
            | mask(&block[32..48]) << 32
            | mask(&block[48..]) << 48;
        let base = (chunk * 64) as u32;
        while bits != 0 {
            list.push(base + bits.trailing_zeros());
            bits &= bits - 1;
        }
    }
}
