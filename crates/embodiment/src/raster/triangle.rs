//! Drawing one triangle into a [`Target`]: the general span rasterizer
//! ([`Target::draw_triangle`]) and the SIMD paths for triangles with small
//! ([`Target::draw_small_x4`]) and medium ([`Target::draw_medium`])
//! bounding boxes, which give the same coverage and depth.

use super::classify::{MEDIUM, MEDIUM_COLUMNS, MEDIUM_ROWS};
use super::lanes::{f64x4_to_f32x4, int_f64};
use super::pixels::Pixels;
use super::vertex::{gather_x4, ScreenVertex};
use super::{SUBPIXEL, SUBPIXEL_BITS};
use wide::{f32x4, f64x4, i32x4, CmpEq, CmpGe, CmpGt, CmpLt, CmpNe};

/// A screen vertex widened for exact edge-function arithmetic.
#[derive(Debug, Clone, Copy)]
struct Vertex64 {
    x: i64,
    y: i64,
    inv_z: f64,
}

/// The pixels drawn into, row-major, `width` x `height`.
pub(super) struct Target<P> {
    pub(super) width: usize,
    pub(super) height: usize,
    pub(super) pixels: P,
}

impl<P: Pixels> Target<P> {
    /// Whether every pixel index of the image fits in an i32 (so that
    /// indices may be computed in i32 SIMD lanes).
    #[inline(always)]
    fn len_fits_i32(&self) -> bool {
        self.width
            .checked_mul(self.height)
            .is_some_and(|n| n <= i32::MAX as usize)
    }

    #[inline(always)]
    fn depth_test_x4(&mut self, idx: usize, z: f32x4, label: u16, covered: i32x4) {
        self.pixels.depth_test_x4(idx, z, label, covered);
    }

    /// Draws four triangles (SIMD lanes of `g`, see [`gather_x4`]) whose
    /// bounding boxes lie inside the image and hold `N` pixel centres each:
    /// 1, 2 (1x2 or 2x1) or 4 (2x2). Same coverage and depth as
    /// [`Target::draw_triangle`]: the same edge functions, here in f32,
    /// which is exact since these boxes are under 3 pixels wide (fixed-point
    /// coordinates relative to the box's first pixel centre are below 2^10,
    /// their products below 2^20), and the same floating-point depth
    /// operations; no data-dependent branches.
    #[inline(always)]
    fn draw_small_x4<const N: usize>(&mut self, g: &[[i32x4; 4]; 3], label: u16) {
        let shift = SUBPIXEL_BITS as i32;
        let zero = i32x4::splat(0);
        let [[x0, y0, iz0, _], [x1, y1, iz1, _], [x2, y2, iz2, _]] = *g;
        // First pixel centre of each box (ceil of the fixed-point minimum).
        let px = zero - ((zero - x0.min(x1).min(x2)) >> shift);
        let py = zero - ((zero - y0.min(y1).min(y2)) >> shift);
        let (ox, oy) = (px << shift, py << shift);
        let rel = |x: i32x4, y: i32x4, iz: i32x4| {
            let iz = bytemuck::cast::<i32x4, f32x4>(iz).to_array();
            (
                (x - ox).round_float(),
                (y - oy).round_float(),
                f64x4::from([
                    f64::from(iz[0]),
                    f64::from(iz[1]),
                    f64::from(iz[2]),
                    f64::from(iz[3]),
                ]),
            )
        };
        let q = [rel(x0, y0, iz0), rel(x1, y1, iz1), rel(x2, y2, iz2)];
        let fzero = f32x4::splat(0.0);
        let area = (q[1].0 - q[0].0) * (q[2].1 - q[0].1) - (q[1].1 - q[0].1) * (q[2].0 - q[0].0);
        // Negative area: swap vertices 1 and 2 (positive orientation).
        let neg = area.cmp_lt(fzero);
        let neg64 =
            f64x4::from_i32x4(bytemuck::cast::<f32x4, i32x4>(neg)).cmp_ne(f64x4::splat(0.0));
        let pick = |a: &(f32x4, f32x4, f64x4), b: &(f32x4, f32x4, f64x4)| {
            (
                neg.blend(a.0, b.0),
                neg.blend(a.1, b.1),
                neg64.blend(a.2, b.2),
            )
        };
        let p = [q[0], pick(&q[2], &q[1]), pick(&q[1], &q[2])];
        let inv_area = f64x4::splat(1.0) / int_f64(area.abs());
        let one = f32x4::splat(SUBPIXEL);
        let mut e = [fzero; 3];
        let mut step_x = [fzero; 3];
        let mut step_y = [fzero; 3];
        let mut iz_origin = f64x4::splat(0.0);
        for (i, (a, b)) in [(1, 2), (2, 0), (0, 1)].into_iter().enumerate() {
            let (a, b) = (&p[a], &p[b]);
            let dx = b.0 - a.0;
            let dy = b.1 - a.1;
            let top_left = dy.cmp_lt(fzero) | (dy.cmp_eq(fzero) & dx.cmp_gt(fzero));
            let unbiased = dx * (fzero - a.1) - dy * (fzero - a.0);
            // Edges that are not top-left exclude their boundary: bias 1.
            e[i] = unbiased - (f32x4::splat(1.0) & !top_left);
            step_x[i] = (fzero - dy) * one;
            step_y[i] = dx * one;
            iz_origin += int_f64(unbiased) * p[i].2;
        }
        let width = self.width;
        // Pixel indices in i32 lanes when every index of the image fits
        // (always, in practice); otherwise per lane in usize.
        let lane_index = self.len_fits_i32();
        let first = px + py * i32x4::splat(width as i32);
        let (px, py) = (px.to_array(), py.to_array());
        if N == 1 {
            let covered =
                (e[0].cmp_ge(fzero) & e[1].cmp_ge(fzero) & e[2].cmp_ge(fzero)).move_mask();
            let z = f32x4::splat(1.0) / f64x4_to_f32x4(iz_origin * inv_area);
            let first = first.to_array();
            let idx: [usize; 4] = std::array::from_fn(|i| {
                if lane_index {
                    first[i] as usize
                } else {
                    py[i] as usize * width + px[i] as usize
                }
            });
            self.pixels.depth_test_lanes(idx, z, label, covered);
            return;
        }
        let mut iz_dx = f64x4::splat(0.0);
        let mut iz_dy = f64x4::splat(0.0);
        for i in 0..3 {
            iz_dx += int_f64(step_x[i]) * p[i].2;
            iz_dy += int_f64(step_y[i]) * p[i].2;
        }
        let iz_origin = iz_origin * inv_area;
        let iz_dx = f64x4_to_f32x4(iz_dx * inv_area);
        let iz_dy = iz_dy * inv_area;
        // Pixel offsets (cx, cy) from the first centre: for two pixels the
        // box's far centre, for four the 2x2 block.
        let (far_x, far_y, far_index) = if N == 2 {
            let sx = (x0.max(x1).max(x2) >> shift) - i32x4::from(px);
            let sy = (y0.max(y1).max(y2) >> shift) - i32x4::from(py);
            let far = first + sx + sy * i32x4::splat(width as i32);
            (sx.round_float(), sy.round_float(), far.to_array())
        } else {
            (f32x4::splat(1.0), f32x4::splat(1.0), [0; 4])
        };
        let first = first.to_array();
        for j in 0..N {
            let (cx, cy) = match (N, j) {
                (2, 0) | (4, 0) => (fzero, fzero),
                (2, _) => (far_x, far_y),
                (_, 1) => (f32x4::splat(1.0), fzero),
                (_, 2) => (fzero, f32x4::splat(1.0)),
                _ => (f32x4::splat(1.0), f32x4::splat(1.0)),
            };
            let ej = |i: usize| e[i] + cx * step_x[i] + cy * step_y[i];
            let covered =
                (ej(0).cmp_ge(fzero) & ej(1).cmp_ge(fzero) & ej(2).cmp_ge(fzero)).move_mask();
            let row = f64x4_to_f32x4(iz_origin + int_f64(cy) * iz_dy);
            let z = f32x4::splat(1.0) / (row + cx * iz_dx);
            let (cx, cy) = (cx.to_array(), cy.to_array());
            let idx: [usize; 4] = std::array::from_fn(|i| match (lane_index, N, j) {
                (true, 2, 0) | (true, 4, 0) => first[i] as usize,
                (true, 2, _) => far_index[i] as usize,
                (true, _, 1) => first[i] as usize + 1,
                (true, _, 2) => first[i] as usize + width,
                (true, _, _) => first[i] as usize + width + 1,
                (false, _, _) => {
                    (py[i] + cy[i] as i32) as usize * width + (px[i] + cx[i] as i32) as usize
                }
            });
            self.pixels.depth_test_lanes(idx, z, label, covered);
        }
    }

    /// Draws a triangle whose bounding box lies inside the image and holds
    /// at most [`MEDIUM_COLUMNS`] x [`MEDIUM_ROWS`] pixel centres. Same
    /// coverage and depth as [`Target::draw_triangle`] (same integer edge
    /// functions, here in i32, which suffices for these boxes: fixed-point
    /// coordinates relative to the first pixel centre are below 2^13, edge
    /// values below 2^26; and the same floating-point depth operations), a
    /// row of up to four pixels at a time in SIMD lanes.
    #[inline(always)]
    fn draw_medium(&mut self, v: [&ScreenVertex; 3], label: u16) {
        let one = 1i32 << SUBPIXEL_BITS;
        let min_x = v[0].x().min(v[1].x()).min(v[2].x());
        let max_x = v[0].x().max(v[1].x()).max(v[2].x());
        let min_y = v[0].y().min(v[1].y()).min(v[2].y());
        let max_y = v[0].y().max(v[1].y()).max(v[2].y());
        let x0 = -((-min_x) >> SUBPIXEL_BITS);
        let y0 = -((-min_y) >> SUBPIXEL_BITS);
        let columns = ((max_x >> SUBPIXEL_BITS) - x0 + 1).clamp(0, MEDIUM_COLUMNS as i32);
        let rows = ((max_y >> SUBPIXEL_BITS) - y0 + 1).clamp(0, MEDIUM_ROWS as i32);
        // Coordinates relative to the pixel centre (x0, y0).
        let (ox, oy) = (x0 * one, y0 * one);
        let rel = |s: &ScreenVertex| (s.x() - ox, s.y() - oy, f64::from(s.inv_z()));
        let (p0, q1, q2) = (rel(v[0]), rel(v[1]), rel(v[2]));
        let area = (q1.0 - p0.0) * (q2.1 - p0.1) - (q1.1 - p0.1) * (q2.0 - p0.0);
        if area == 0 {
            return;
        }
        let (p1, p2) = if area < 0 { (q2, q1) } else { (q1, q2) };
        let edges = [(p1, p2), (p2, p0), (p0, p1)];
        let iz = [p0.2, p1.2, p2.2];
        let lanes = i32x4::from([0, 1, 2, 3]);
        let mut e = [i32x4::splat(0); 3];
        let mut step_y = [0i32; 3];
        let mut iz_origin = 0.0f64;
        let mut iz_dx = 0.0f64;
        let mut iz_dy = 0.0f64;
        for (i, (a, b)) in edges.iter().enumerate() {
            let dx = b.0 - a.0;
            let dy = b.1 - a.1;
            let top_left = (dy < 0) | ((dy == 0) & (dx > 0));
            let unbiased = dx * (-a.1) - dy * (-a.0);
            let step_x = -dy * one;
            step_y[i] = dx * one;
            // Lanes: the pixels x0 .. x0 + 3 of the first row.
            let first = unbiased - i32::from(!top_left);
            e[i] = i32x4::from([
                first,
                first + step_x,
                first + 2 * step_x,
                first + 3 * step_x,
            ]);
            iz_origin += f64::from(unbiased) * iz[i];
            iz_dx += f64::from(step_x) * iz[i];
            iz_dy += f64::from(step_y[i]) * iz[i];
        }
        let inv_area = 1.0 / f64::from(area.abs());
        iz_origin *= inv_area;
        let iz_dx = (iz_dx * inv_area) as f32;
        iz_dy *= inv_area;
        // dxf * iz_dx per lane, dxf the column offset (as in draw_triangle).
        let column_iz = lanes.round_float() * f32x4::splat(iz_dx);
        let in_box = lanes.cmp_lt(i32x4::splat(columns));
        let width = self.width;
        for row in 0..rows {
            let iz_row = (iz_origin + f64::from(row) * iz_dy) as f32;
            let z = f32x4::splat(1.0) / (f32x4::splat(iz_row) + column_iz);
            let covered = (e[0] | e[1] | e[2]).cmp_gt(i32x4::splat(-1)) & in_box;
            let base = (y0 + row) as usize * width + x0 as usize;
            self.depth_test_x4(base, z, label, covered);
            for i in 0..3 {
                e[i] += i32x4::splat(step_y[i]);
            }
        }
    }

    /// Draws the listed triangles: with [`Target::draw_small_x4`] for `N` =
    /// 1, 2, 4, four at a time (the last group padded by repeating a
    /// triangle, which draws nothing new), with [`Target::draw_medium`] for
    /// `N` = [`MEDIUM`] and with [`Target::draw_triangle`] for `N` = 0.
    #[inline(always)]
    pub(super) fn draw_list<const N: usize>(
        &mut self,
        list: &[u32],
        triangles: &[[u32; 3]],
        screen: &[ScreenVertex],
        label: u16,
    ) {
        let tri = |t: u32| triangles.get(t as usize).copied().unwrap_or([u32::MAX; 3]);
        if N == MEDIUM {
            for &t in list {
                let [i0, i1, i2] = tri(t);
                let v = |i: u32| screen.get(i as usize);
                if let (Some(a), Some(b), Some(c)) = (v(i0), v(i1), v(i2)) {
                    self.draw_medium([a, b, c], label);
                }
            }
            return;
        }
        if N == 0 {
            for &t in list {
                let [i0, i1, i2] = tri(t);
                let v = |i: u32| screen.get(i as usize);
                if let (Some(a), Some(b), Some(c)) = (v(i0), v(i1), v(i2)) {
                    self.draw_triangle([a, b, c], label);
                }
            }
            return;
        }
        for chunk in list.chunks(4) {
            let t = |i: usize| tri(chunk.get(i).copied().unwrap_or(chunk[0]));
            let g = gather_x4([t(0), t(1), t(2), t(3)], screen);
            self.draw_small_x4::<N>(&g, label);
        }
    }

    /// Rasterizes one triangle (any winding) with the top-left fill rule.
    #[inline(always)]
    pub(super) fn draw_triangle(&mut self, v: [&ScreenVertex; 3], label: u16) {
        let wide = |s: &ScreenVertex| Vertex64 {
            x: i64::from(s.x()),
            y: i64::from(s.y()),
            inv_z: f64::from(s.inv_z()),
        };
        let [v0, mut v1, mut v2] = v.map(wide);
        // Bounding box of pixel centres (integer coordinates) inside the
        // image: ceil / floor of the fixed-point extent (arithmetic shifts).
        let one = 1i64 << SUBPIXEL_BITS;
        let min_x = v0.x.min(v1.x).min(v2.x);
        let max_x = v0.x.max(v1.x).max(v2.x);
        let min_y = v0.y.min(v1.y).min(v2.y);
        let max_y = v0.y.max(v1.y).max(v2.y);
        let x0 = (-((-min_x) >> SUBPIXEL_BITS)).max(0);
        let x1 = (max_x >> SUBPIXEL_BITS).min(self.width as i64 - 1);
        let y0 = (-((-min_y) >> SUBPIXEL_BITS)).max(0);
        let y1 = (max_y >> SUBPIXEL_BITS).min(self.height as i64 - 1);
        if x0 > x1 || y0 > y1 {
            return;
        }
        let mut area = (v1.x - v0.x) * (v2.y - v0.y) - (v1.y - v0.y) * (v2.x - v0.x);
        if area == 0 {
            return;
        }
        if area < 0 {
            std::mem::swap(&mut v1, &mut v2);
            area = -area;
        }
        // Edge i is opposite vertex i: e_i(p) = (b - a) x (p - a) for edge a->b.
        // With positive area, inside means e_i >= 0 on all edges. Top-left
        // rule (y down): an edge is top if dy == 0 && dx > 0, left if dy < 0;
        // other edges exclude their boundary via a bias of 1.
        let edges = [(v1, v2), (v2, v0), (v0, v1)];
        let mut e_row = [0i64; 3];
        let mut step_x = [0i64; 3];
        let mut step_y = [0i64; 3];
        let px = x0 * one;
        let py = y0 * one;
        for (i, (a, b)) in edges.iter().enumerate() {
            let dx = b.x - a.x;
            let dy = b.y - a.y;
            let top_left = dy < 0 || (dy == 0 && dx > 0);
            let bias = if top_left { 0 } else { 1 };
            e_row[i] = dx * (py - a.y) - dy * (px - a.x) - bias;
            step_x[i] = -dy * one;
            step_y[i] = dx * one;
        }
        let inv_area = 1.0 / area as f64;
        let iz = [v0.inv_z, v1.inv_z, v2.inv_z];
        if x0 == x1 && y0 == y1 {
            // One candidate pixel (most triangles of dense meshes): test it
            // directly; same depth formula as the general path at (x0, y0).
            if (e_row[0] | e_row[1] | e_row[2]) < 0 {
                return;
            }
            let mut iz_origin = 0.0f64;
            for i in 0..3 {
                let (a, b) = edges[i];
                let e = (b.x - a.x) * (py - a.y) - (b.y - a.y) * (px - a.x);
                iz_origin += e as f64 * iz[i];
            }
            let z = 1.0 / ((iz_origin * inv_area) as f32);
            let idx = y0 as usize * self.width + x0 as usize;
            self.pixels.depth_test(idx, z, label, true);
            return;
        }
        // 1/z as a plane over pixel coordinates: sum_i (e_i / area) inv_z_i.
        let mut iz_dx = 0.0f64;
        let mut iz_dy = 0.0f64;
        let mut iz_origin = 0.0f64;
        for i in 0..3 {
            // Unbiased edge value at (x0, y0).
            let (a, b) = edges[i];
            let e = (b.x - a.x) * (py - a.y) - (b.y - a.y) * (px - a.x);
            iz_origin += e as f64 * iz[i];
            iz_dx += step_x[i] as f64 * iz[i];
            iz_dy += step_y[i] as f64 * iz[i];
        }
        iz_origin *= inv_area;
        let iz_dx = (iz_dx * inv_area) as f32;
        iz_dy *= inv_area;

        let width = self.width;
        // Boxes of several columns are traversed by exact per-row spans; a
        // single column is tested pixel by pixel.
        let wide = x1 > x0;
        for (row, y) in (y0..=y1).enumerate() {
            let iz_row = (iz_origin + row as f64 * iz_dy) as f32;
            let base = y as usize * width;
            // Covered pixels of this row: x0 + [lo, hi] (offsets from x0).
            let (lo, hi) = if wide {
                row_span(&e_row, &step_x, x1 - x0)
            } else {
                (0, x1 - x0)
            };
            if lo <= hi {
                let start = base + (x0 + lo) as usize;
                let end = base + (x0 + hi) as usize;
                let mut e = [
                    e_row[0] + lo * step_x[0],
                    e_row[1] + lo * step_x[1],
                    e_row[2] + lo * step_x[2],
                ];
                let mut dxf = lo as f32;
                let z_at = || {
                    // In a span every pixel is inside; the test is then a
                    // predictable always-true branch.
                    let z = if (e[0] | e[1] | e[2]) >= 0 {
                        Some(1.0 / (iz_row + dxf * iz_dx))
                    } else {
                        None
                    };
                    e[0] += step_x[0];
                    e[1] += step_x[1];
                    e[2] += step_x[2];
                    dxf += 1.0;
                    z
                };
                if !self.pixels.depth_test_span(start, end, label, z_at) {
                    return;
                }
            }
            e_row[0] += step_y[0];
            e_row[1] += step_y[1];
            e_row[2] += step_y[2];
        }
    }
}

/// The offsets `[lo, hi]` within `[0, max_offset]` where all three biased
/// edge functions `e[i] + k * step[i]` are >= 0 (exact integer arithmetic,
/// so the result equals testing each pixel). Empty when `lo > hi`.
#[inline]
fn row_span(e: &[i64; 3], step: &[i64; 3], max_offset: i64) -> (i64, i64) {
    let (mut lo, mut hi) = (0i64, max_offset);
    for i in 0..3 {
        let (e, s) = (e[i], step[i]);
        if s > 0 {
            if e < 0 {
                // k >= ceil(-e / s)
                lo = lo.max((-e + s - 1) / s);
            }
        } else if s < 0 {
            if e < 0 {
                return (1, 0);
            }
            // k <= floor(e / -s)
            hi = hi.min(e / -s);
        } else if e < 0 {
            return (1, 0);
        }
    }
    (lo, hi)
}
