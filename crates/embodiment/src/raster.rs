//! Triangle rasterizer: binary mask, per-link label map and depth.
//!
//! [`Rasterizer`] draws [`RenderItem`]s (a mesh, its pose and a label) seen
//! through a [`Camera`] into a [`RenderOutput`]: a label map (0 = background),
//! and a depth map (camera-frame z of the nearest surface, metres).
//!
//! Conventions and algorithm:
//! - Pixel centres follow [`Camera::project`] (OpenCV): the centre of pixel
//!   `(x, y)` is at projected coordinates `(x, y)`; a pixel is covered when
//!   its centre is inside a triangle.
//! - Vertices go to the camera frame (`camera_from_world * world_from_mesh`
//!   composed once per item in f64, then applied in f32). Triangles are
//!   clipped against the near plane z = [`NEAR_PLANE_M`] and, only when a
//!   vertex projects absurdly far outside the image, against a guard band
//!   around the image (so fixed-point coordinates stay small).
//! - Projected vertices are snapped to 1/256 pixel and covered pixels are
//!   found with exact integer edge functions over the triangle's bounding box
//!   clamped to the image, with the top-left fill rule: a pixel centre on an
//!   edge shared by two triangles is drawn by exactly one of them. Triangles
//!   are two-sided; zero-area triangles are skipped.
//! - Depth is perspective-correct: 1/z is interpolated linearly in screen
//!   space. The nearest surface wins; at equal depth the lower label wins,
//!   so the output does not depend on the order of items.
//! - Lens distortion: when the camera has non-zero distortion the scene is
//!   rendered into an undistorted pinhole buffer with the same focal lengths
//!   (shrunk if the field of view is very wide) that covers the undistorted
//!   locations of all output pixel centres, and each output pixel copies the
//!   nearest pinhole pixel of its undistorted location (precomputed once in
//!   [`Rasterizer::new`]). The pinhole buffer is allocated per rendered
//!   frame; undistorted frames reuse per-thread scratch buffers.
//! - Implementation: vertices are transformed, clip-tested and projected
//!   four at a time with SIMD (`wide`). Triangles are classified four at a
//!   time in SIMD lanes by bounding-box size, without data-dependent
//!   branches, and sorted into per-thread lists: those whose box lies inside
//!   the image and holds 1, 2 or 2x2 pixel centres are drawn four at a time
//!   in SIMD lanes with exact f32 edge functions; those with boxes of up to
//!   4 x 16 centres row by row, four pixels of a row in SIMD lanes; the rest
//!   (and clipped ones) by the general span rasterizer. Coverage and depth
//!   use the same integer values and floating-point operations on every
//!   path, so the output is bit-identical to drawing each triangle with the
//!   general path (tested).
//! - Label maps alone ([`Rasterizer::render_labels`]) are drawn into one
//!   64-bit key per pixel (depth bits mapped to their order, then the
//!   label), so the depth test is a minimum; same result as separate depth
//!   and label buffers (tested).
//! - The per-frame drawing ([`Rasterizer::draw_items_with`]) is compiled twice,
//!   for the baseline x86-64 instruction set and for AVX2 (x86-64-v3,
//!   chosen at run time with `pulp`): every function it calls is inlined
//!   into it, so the SIMD code uses the wider instruction set. Both give
//!   identical bits: only IEEE-exact operations are used and Rust never
//!   fuses multiplies and adds.
//! - Performance (720x480, one thread, release, minimum over runs on a
//!   shared machine): about 1.3 ms per frame for 8 capsules/spheres of ~2k
//!   triangles each (`benches/raster.rs`, measured before the AVX2 copy)
//!   and about 1.5-1.6 ms of CPU time per label map
//!   ([`Rasterizer::render_labels`], including output allocation) for
//!   pybullet's Franka Panda visual meshes (103k triangles,
//!   `examples/panda_masks.rs`; about 19.5 M instructions per map inside
//!   `render_labels`, callgrind); with two threads `bridgev2w bench masks`
//!   renders about 1100 label maps/s.

use crate::camera::Camera;
use crate::mesh::TriMesh;
use nalgebra::Isometry3;
use rayon::prelude::*;
use std::cell::RefCell;
use wide::{f32x4, f64x4, i32x4, CmpEq, CmpGe, CmpGt, CmpLt, CmpNe};

/// Near clipping plane, camera-frame z in metres.
pub const NEAR_PLANE_M: f32 = 0.01;

/// Sub-pixel bits of the fixed-point vertex coordinates.
const SUBPIXEL_BITS: u32 = 8;
const SUBPIXEL: f32 = (1 << SUBPIXEL_BITS) as f32;
/// Guard band around the image, pixels: vertices projecting further out
/// trigger clipping so fixed-point edge functions cannot overflow.
const GUARD_PX: f32 = 8192.0;
/// Largest pinhole buffer side relative to the output image when rendering
/// with distortion.
const MAX_PINHOLE_SCALE: f64 = 3.0;

/// A mesh placed in the world with a label.
#[derive(Debug, Clone, Copy)]
pub struct RenderItem<'a> {
    /// The mesh in its own frame (metres).
    pub mesh: &'a TriMesh,
    /// Maps mesh-frame points to world-frame points.
    pub world_from_mesh: Isometry3<f64>,
    /// Label written to covered pixels; must be >= 1 (0 is background, items
    /// labelled 0 are not drawn).
    pub label: u16,
    /// Number of leading triangles of `mesh` whose back faces (those facing
    /// away from the camera) may be skipped: 0 for none, `usize::MAX` for
    /// all. Only for triangles forming closed connected components with
    /// outward (counter-clockwise seen from outside) winding, see
    /// [`TriMesh::closed_components_first`]; the result is then unchanged,
    /// since every pixel a back face covers is covered by a nearer front
    /// face of the same component. Ignored for a frame in which any vertex of
    /// the mesh is behind the near plane (the camera could be inside it).
    pub closed_triangles: usize,
}

/// A rendered frame, row-major (`index = y * width + x`).
#[derive(Debug, Clone, PartialEq)]
pub struct RenderOutput {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Label of the nearest surface per pixel, 0 for background.
    pub labels: Vec<u16>,
    /// Camera-frame z (metres) of the nearest surface per pixel,
    /// `f32::INFINITY` for background.
    pub depth_m: Vec<f32>,
}

impl RenderOutput {
    /// An all-background frame of `width` x `height`.
    pub fn new(width: u32, height: u32) -> Self {
        let n = width as usize * height as usize;
        Self {
            width,
            height,
            labels: vec![0; n],
            depth_m: vec![f32::INFINITY; n],
        }
    }

    /// Resets every pixel to background.
    pub fn clear(&mut self) {
        self.labels.fill(0);
        self.depth_m.fill(f32::INFINITY);
    }

    /// Resizes to `width` x `height` (if needed) and clears.
    fn reset(&mut self, width: u32, height: u32) {
        let n = width as usize * height as usize;
        self.width = width;
        self.height = height;
        self.labels.clear();
        self.labels.resize(n, 0);
        self.depth_m.clear();
        self.depth_m.resize(n, f32::INFINITY);
    }

    /// Binary mask: 1 where any item is visible, 0 for background.
    pub fn mask(&self) -> Vec<u8> {
        self.labels.iter().map(|&l| u8::from(l != 0)).collect()
    }

    /// Number of non-background pixels.
    pub fn coverage(&self) -> usize {
        self.labels.iter().filter(|&&l| l != 0).count()
    }
}

/// Pinhole projection parameters of a render target, f32.
#[derive(Debug, Clone, Copy)]
struct Pinhole {
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    width: u32,
    height: u32,
}

/// The distortion remap: output pixel -> pinhole buffer index.
#[derive(Debug, Clone)]
struct Remap {
    /// Pinhole buffer parameters.
    pinhole: Pinhole,
    /// Per output pixel, the pinhole buffer index, or `u32::MAX` when the
    /// pixel's ray is not representable (background).
    source: Vec<u32>,
}

/// Draws meshes through one camera. Cheap to share across threads.
#[derive(Debug, Clone)]
pub struct Rasterizer {
    camera_from_world: Isometry3<f64>,
    width: u32,
    height: u32,
    /// Target of triangle drawing: the camera itself without distortion.
    pinhole: Pinhole,
    remap: Option<Remap>,
}

/// A vertex ready for rasterization: fixed-point screen position (1/256
/// pixel; bounded by the guard band, so i32 suffices), 1/z, and its clip
/// outcode (bit i set when outside clip plane i of [`Planes`]; position and
/// 1/z are only meaningful when the outcode is 0), stored as the SIMD lanes
/// `[x, y, bits of 1/z, outcode]` so that four vertices load and transpose
/// into per-field lanes cheaply.
#[derive(Debug, Clone, Copy, Default)]
struct ScreenVertex(wide::i32x4);

impl ScreenVertex {
    #[inline(always)]
    fn new(x: i32, y: i32, inv_z: f32, outcode: u8) -> Self {
        Self(wide::i32x4::from([
            x,
            y,
            inv_z.to_bits() as i32,
            i32::from(outcode),
        ]))
    }

    #[inline(always)]
    fn x(&self) -> i32 {
        self.0.as_array_ref()[0]
    }

    #[inline(always)]
    fn y(&self) -> i32 {
        self.0.as_array_ref()[1]
    }

    #[inline(always)]
    fn inv_z(&self) -> f32 {
        f32::from_bits(self.0.as_array_ref()[2] as u32)
    }

    #[inline(always)]
    fn outcode(&self) -> u8 {
        self.0.as_array_ref()[3] as u8
    }
}

/// Clip planes in the camera frame: `a·p + d >= 0` is inside. Plane 0 is the
/// near plane, 1..=4 the guard band (left, right, top, bottom).
#[derive(Debug, Clone, Copy)]
struct Planes {
    planes: [[f32; 4]; 5],
}

impl Planes {
    fn new(k: &Pinhole) -> Self {
        let (gl, gr) = (-GUARD_PX, k.width as f32 + GUARD_PX);
        let (gt, gb) = (-GUARD_PX, k.height as f32 + GUARD_PX);
        Self {
            planes: [
                [0.0, 0.0, 1.0, -NEAR_PLANE_M],
                // u >= gl  <=>  fx x + (cx - gl) z >= 0 (for z > 0)
                [k.fx, 0.0, k.cx - gl, 0.0],
                // u <= gr  <=>  -fx x + (gr - cx) z >= 0
                [-k.fx, 0.0, gr - k.cx, 0.0],
                [0.0, k.fy, k.cy - gt, 0.0],
                [0.0, -k.fy, gb - k.cy, 0.0],
            ],
        }
    }

    #[inline]
    fn distance(plane: &[f32; 4], p: &[f32; 3]) -> f32 {
        plane[0] * p[0] + plane[1] * p[1] + plane[2] * p[2] + plane[3]
    }

    /// Clip outcode of `p`: bit i set when outside plane i (NaN counts as
    /// outside). Uses the planes' structure (each ignores one or two
    /// coordinates), which gives the same distances as [`Planes::distance`]
    /// for finite points.
    #[inline]
    #[cfg(test)]
    fn outcode(&self, p: &[f32; 3]) -> u8 {
        let [x, y, z] = *p;
        let [near, left, right, top, bottom] = &self.planes;
        let d = [
            z + near[3],
            left[0] * x + left[2] * z,
            right[0] * x + right[2] * z,
            top[1] * y + top[2] * z,
            bottom[1] * y + bottom[2] * z,
        ];
        let mut code = 0u8;
        for (i, d) in d.iter().enumerate() {
            code |= u8::from(d.is_nan() | (*d < 0.0)) << i;
        }
        code
    }
}

/// Largest clipped polygon: a triangle clipped by 5 planes.
const MAX_POLY: usize = 8;

/// Clips the triangle `tri` against the planes flagged in `mask`; returns the
/// polygon vertex count (0 when fully clipped).
///
/// Intersections are computed from the (inside, outside) endpoint pair only,
/// so an edge shared by two triangles is clipped at bit-identical points.
fn clip_polygon(
    tri: [[f32; 3]; 3],
    planes: &Planes,
    mask: u8,
    out: &mut [[f32; 3]; MAX_POLY],
) -> usize {
    let mut a = [[0.0f32; 3]; MAX_POLY];
    a[..3].copy_from_slice(&tri);
    let mut n = 3;
    for (i, plane) in planes.planes.iter().enumerate() {
        if mask & (1 << i) == 0 {
            continue;
        }
        let mut b = [[0.0f32; 3]; MAX_POLY];
        let mut m = 0;
        for j in 0..n {
            let cur = a[j];
            let next = a[(j + 1) % n];
            let dc = Planes::distance(plane, &cur);
            let dn = Planes::distance(plane, &next);
            let cur_in = dc >= 0.0;
            let next_in = dn >= 0.0;
            if cur_in && m < MAX_POLY {
                b[m] = cur;
                m += 1;
            }
            if cur_in != next_in && m < MAX_POLY {
                let (pi, di, po, d_o) = if cur_in {
                    (cur, dc, next, dn)
                } else {
                    (next, dn, cur, dc)
                };
                let t = di / (di - d_o);
                b[m] = [
                    pi[0] + t * (po[0] - pi[0]),
                    pi[1] + t * (po[1] - pi[1]),
                    pi[2] + t * (po[2] - pi[2]),
                ];
                m += 1;
            }
        }
        a = b;
        n = m;
        if n < 3 {
            return 0;
        }
    }
    *out = a;
    n
}

/// A screen vertex widened for exact edge-function arithmetic.
#[derive(Debug, Clone, Copy)]
struct Vertex64 {
    x: i64,
    y: i64,
    inv_z: f64,
}

/// Per-pixel storage of the nearest surface: a depth test per fragment.
trait Pixels {
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
struct LabelDepth<'a> {
    labels: &'a mut [u16],
    depth_m: &'a mut [f32],
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
fn depth_key(z: f32, label: u16) -> u64 {
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
const BACKGROUND_KEY: u64 = (((0x7f80_0000u32) | 0x8000_0000) as u64) << 32;

/// Depth and label packed per pixel ([`depth_key`]), row-major: the depth
/// test is a minimum.
struct Keys<'a> {
    keys: &'a mut [u64],
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

/// The pixels drawn into, row-major, `width` x `height`.
struct Target<P> {
    width: usize,
    height: usize,
    pixels: P,
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
    fn draw_list<const N: usize>(
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
    fn draw_triangle(&mut self, v: [&ScreenVertex; 3], label: u16) {
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

/// Triangle classes of the fast path, see [`classify_x4`].
const CLASSES: usize = 7;
/// Not drawn: no pixel centre in the image's part of the bounding box, zero
/// area, culled back face, or all vertices outside one clip plane.
const CLASS_SKIP: u8 = 0;
/// Bounding box inside the image holding exactly one pixel centre.
const CLASS_ONE: u8 = 1;
/// Bounding box inside the image holding two pixel centres (1x2 or 2x1).
const CLASS_TWO: u8 = 2;
/// Bounding box inside the image holding 2x2 pixel centres.
const CLASS_QUAD: u8 = 3;
/// Any other unclipped triangle: [`Target::draw_triangle`].
const CLASS_LARGE: u8 = 4;
/// Some vertex outside a clip plane: clipped, then
/// [`Target::draw_triangle`].
const CLASS_CLIP: u8 = 5;
/// Not small, bounding box inside the image holding at most
/// [`MEDIUM_COLUMNS`] x [`MEDIUM_ROWS`] pixel centres:
/// [`Target::draw_medium`].
const CLASS_MEDIUM: u8 = 6;
/// Largest box of [`CLASS_MEDIUM`], pixel centres.
const MEDIUM_COLUMNS: usize = 4;
const MEDIUM_ROWS: usize = 16;
/// `draw_list` selector of [`Target::draw_medium`].
const MEDIUM: usize = 3;

/// Per-thread scratch buffers of [`Rasterizer::draw_items`], reused across
/// items and frames (their contents never outlive one item).
#[derive(Debug, Default)]
struct Scratch {
    /// Screen vertices.
    screen: Vec<ScreenVertex>,
    /// Class of every triangle, padded to a multiple of 64 with
    /// [`CLASS_SKIP`].
    classes: Vec<u8>,
    /// Triangle indices per class.
    lists: [Vec<u32>; CLASSES],
}

thread_local! {
    static SCRATCH: RefCell<Scratch> = RefCell::new(Scratch::default());
    /// Frame buffers of [`Rasterizer::render_labels_into`].
    static LABEL_FRAME: RefCell<LabelFrame> = const { RefCell::new(LabelFrame::new()) };
}

/// An inclusive rectangle of pixels (empty when `x0 > x1` or `y0 > y1`).
#[derive(Debug, Clone, Copy, PartialEq)]
struct PixelRect {
    x0: i64,
    x1: i64,
    y0: i64,
    y1: i64,
}

impl PixelRect {
    const EMPTY: Self = Self {
        x0: 0,
        x1: -1,
        y0: 0,
        y1: -1,
    };

    /// The whole image whose last pixel is `(last_x, last_y)`.
    fn full(last_x: i32, last_y: i32) -> Self {
        Self {
            x0: 0,
            x1: i64::from(last_x),
            y0: 0,
            y1: i64::from(last_y),
        }
    }

    fn is_empty(&self) -> bool {
        self.x0 > self.x1 || self.y0 > self.y1
    }

    /// The smallest rectangle holding both.
    fn union(&self, other: &Self) -> Self {
        match (self.is_empty(), other.is_empty()) {
            (true, _) => *other,
            (_, true) => *self,
            _ => Self {
                x0: self.x0.min(other.x0),
                x1: self.x1.max(other.x1),
                y0: self.y0.min(other.y0),
                y1: self.y1.max(other.y1),
            },
        }
    }

    /// Its rows (none when empty).
    fn rows(&self) -> std::ops::Range<usize> {
        if self.is_empty() {
            0..0
        } else {
            self.y0.max(0) as usize..self.y1.max(0) as usize + 1
        }
    }
}

/// The per-thread frame of [`Rasterizer::render_labels_into`]: drawn into,
/// then its covered pixels are copied to the caller's label map, so that
/// map is only ever written (never read) and only where something is drawn:
/// for a freshly zeroed allocation, pages of background are never touched,
/// and none is first read (mapping the shared zero page) and then written
/// (a copy-on-write fault with a TLB flush on every core the process runs
/// on). Depth and label are packed per pixel ([`Keys`]). Between frames
/// every pixel is background ([`BACKGROUND_KEY`]), restored block by block
/// where something was drawn, so there is no full clear per frame.
#[derive(Debug)]
struct LabelFrame {
    keys: Vec<u64>,
    /// Set while drawing: a frame left dirty (by a panic) is cleared in full.
    dirty: bool,
}

impl LabelFrame {
    const fn new() -> Self {
        Self {
            keys: Vec::new(),
            dirty: false,
        }
    }
}

/// Stands in for the vertex of an out-of-range index (and for the padding
/// of the last group of four triangles): outside every clip plane, so the
/// triangle is skipped.
const INVALID_VERTEX: ScreenVertex = ScreenVertex(wide::i32x4::new([0, 0, 0, 0x1F]));

/// Lane masks (-1 where set) of the 4-bit masks 0..16.
/// Lane numbers 0..4.
const LANE_INDEX: i32x4 = i32x4::new([0, 1, 2, 3]);

const LANE_MASKS: [wide::i32x4; 16] = {
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
fn f64x4_to_f32x4(v: f64x4) -> f32x4 {
    let v = v.to_array();
    f32x4::from([v[0] as f32, v[1] as f32, v[2] as f32, v[3] as f32])
}

/// Converts integer-valued lanes below 2^31 in magnitude to f64 (exact).
#[inline(always)]
fn int_f64(v: f32x4) -> f64x4 {
    f64x4::from_i32x4(v.round_int())
}

/// The vertices of four triangles (vertex indices `tris`) as SIMD lanes:
/// per triangle vertex k, `[x, y, bits of 1/z, outcode]` of the four
/// triangles. An out-of-range index gives [`INVALID_VERTEX`].
#[inline(always)]
fn gather_x4(tris: [[u32; 3]; 4], screen: &[ScreenVertex]) -> [[i32x4; 4]; 3] {
    let vertex = |i: u32| screen.get(i as usize).copied().unwrap_or(INVALID_VERTEX).0;
    // (Explicit arrays: `array::map` is not always inlined.)
    let gather = |k: usize| {
        i32x4::transpose([
            vertex(tris[0][k]),
            vertex(tris[1][k]),
            vertex(tris[2][k]),
            vertex(tris[3][k]),
        ])
    };
    [gather(0), gather(1), gather(2)]
}

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
fn classify_x4(
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
fn collect_class(classes: &[u8], class: u8, list: &mut Vec<u32>) {
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

impl Rasterizer {
    /// A rasterizer for `camera` (its intrinsics are assumed validated, as
    /// [`Camera`]'s constructors do). Precomputes the distortion remap.
    pub fn new(camera: &Camera) -> Self {
        let k = &camera.intrinsics;
        let camera_pinhole = Pinhole {
            fx: k.fx as f32,
            fy: k.fy as f32,
            cx: k.cx as f32,
            cy: k.cy as f32,
            width: k.width,
            height: k.height,
        };
        let remap = k.active_distortion().map(|d| {
            // Undistorted normalized coordinates of every output pixel centre.
            let n = k.width as usize * k.height as usize;
            let mut undistorted = Vec::with_capacity(n);
            let (mut lo_x, mut hi_x) = (f64::INFINITY, f64::NEG_INFINITY);
            let (mut lo_y, mut hi_y) = (f64::INFINITY, f64::NEG_INFINITY);
            for v in 0..k.height {
                for u in 0..k.width {
                    let xd = (f64::from(u) - k.cx) / k.fx;
                    let yd = (f64::from(v) - k.cy) / k.fy;
                    let (x, y) = d.undistort(xd, yd);
                    // Keep only rays that the lens model maps back correctly.
                    let (rx, ry) = d.distort(x, y);
                    let ok = x.is_finite()
                        && y.is_finite()
                        && (rx - xd).abs() < 1e-6
                        && (ry - yd).abs() < 1e-6;
                    if ok {
                        lo_x = lo_x.min(x);
                        hi_x = hi_x.max(x);
                        lo_y = lo_y.min(y);
                        hi_y = hi_y.max(y);
                        undistorted.push(Some((x, y)));
                    } else {
                        undistorted.push(None);
                    }
                }
            }
            if !(lo_x <= hi_x && lo_y <= hi_y) {
                (lo_x, hi_x, lo_y, hi_y) = (0.0, 0.0, 0.0, 0.0);
            }
            // Same focal lengths as the camera unless that makes the buffer
            // larger than MAX_PINHOLE_SCALE times the output.
            let span_x = k.fx * (hi_x - lo_x);
            let span_y = k.fy * (hi_y - lo_y);
            let scale = 1.0f64
                .min(MAX_PINHOLE_SCALE * f64::from(k.width) / span_x.max(1e-9))
                .min(MAX_PINHOLE_SCALE * f64::from(k.height) / span_y.max(1e-9));
            let (fx, fy) = (k.fx * scale, k.fy * scale);
            // One pixel of margin on each side.
            let cx = 1.0 - fx * lo_x;
            let cy = 1.0 - fy * lo_y;
            let width = (fx * (hi_x - lo_x)).ceil() as u32 + 3;
            let height = (fy * (hi_y - lo_y)).ceil() as u32 + 3;
            let source = undistorted
                .iter()
                .map(|p| match p {
                    Some((x, y)) => {
                        let su = (fx * x + cx).round();
                        let sv = (fy * y + cy).round();
                        let index = sv * f64::from(width) + su;
                        let inside = su >= 0.0
                            && sv >= 0.0
                            && su < f64::from(width)
                            && sv < f64::from(height);
                        if inside && index < f64::from(u32::MAX) {
                            index as u32
                        } else {
                            u32::MAX
                        }
                    }
                    None => u32::MAX,
                })
                .collect();
            Remap {
                pinhole: Pinhole {
                    fx: fx as f32,
                    fy: fy as f32,
                    cx: cx as f32,
                    cy: cy as f32,
                    width,
                    height,
                },
                source,
            }
        });
        Self {
            camera_from_world: camera.world_from_camera.inverse(),
            width: k.width,
            height: k.height,
            pinhole: camera_pinhole,
            remap,
        }
    }

    /// Renders `items` into a new frame of the camera's size.
    pub fn render(&self, items: &[RenderItem]) -> RenderOutput {
        let mut out = RenderOutput::new(self.width, self.height);
        self.render_into(items, &mut out);
        out
    }

    /// Renders `items` into `out`, reusing its buffers (resized to the
    /// camera's size if needed; previous contents are cleared).
    pub fn render_into(&self, items: &[RenderItem], out: &mut RenderOutput) {
        out.reset(self.width, self.height);
        match &self.remap {
            None => {
                let pixels = LabelDepth {
                    labels: &mut out.labels,
                    depth_m: &mut out.depth_m,
                };
                self.draw_items(items, &self.pinhole, pixels);
            }
            Some(remap) => {
                let mut buffer = RenderOutput::new(remap.pinhole.width, remap.pinhole.height);
                let pixels = LabelDepth {
                    labels: &mut buffer.labels,
                    depth_m: &mut buffer.depth_m,
                };
                self.draw_items(items, &remap.pinhole, pixels);
                for ((&src, label), depth) in remap
                    .source
                    .iter()
                    .zip(out.labels.iter_mut())
                    .zip(out.depth_m.iter_mut())
                {
                    let src = src as usize;
                    if let (Some(&l), Some(&d)) = (buffer.labels.get(src), buffer.depth_m.get(src))
                    {
                        *label = l;
                        *depth = d;
                    }
                }
            }
        }
    }

    /// Renders `items` and returns only the label map (row-major, camera
    /// size; [`RenderOutput::labels`] of [`Rasterizer::render`]). Faster
    /// than a full render: the depth map is a reused per-thread buffer and
    /// the label map is written only where something is drawn.
    pub fn render_labels(&self, items: &[RenderItem]) -> Vec<u16> {
        // Zeroed allocation: untouched (background) pages are never written.
        let mut labels = vec![0u16; self.width as usize * self.height as usize];
        self.render_labels_into(items, &mut labels);
        labels
    }

    /// Draws the label map of `items` into `labels` (row-major, camera
    /// size): pixels that an item covers get the label of the nearest
    /// surface, the others keep their value. With `labels` all background
    /// (0) on entry this is [`Rasterizer::render_labels`]; only covered
    /// pixels are written, so the untouched pages of a freshly zeroed
    /// allocation are never written (see
    /// [`crate::masks::render_trajectory_label_array`]).
    ///
    /// # Panics
    /// If `labels.len()` is not the camera's pixel count.
    pub fn render_labels_into(&self, items: &[RenderItem], labels: &mut [u16]) {
        let n = self.width as usize * self.height as usize;
        assert_eq!(labels.len(), n, "label map size");
        if self.remap.is_some() {
            let full = self.render(items);
            for (l, &f) in labels.iter_mut().zip(&full.labels) {
                if f != 0 {
                    *l = f;
                }
            }
            return;
        }
        LABEL_FRAME.with(|frame| match frame.try_borrow_mut() {
            Ok(mut frame) => self.draw_labels(items, &mut frame, labels),
            Err(_) => self.draw_labels(items, &mut LabelFrame::new(), labels),
        });
    }

    /// [`Rasterizer::render_labels_into`] without distortion, drawing into
    /// the per-thread `frame` and then copying its covered pixels.
    fn draw_labels(&self, items: &[RenderItem], frame: &mut LabelFrame, labels: &mut [u16]) {
        let n = labels.len();
        if frame.dirty || frame.keys.len() != n {
            frame.keys.clear();
            frame.keys.resize(n, BACKGROUND_KEY);
        }
        frame.dirty = true;
        let pixels = Keys {
            keys: &mut frame.keys,
        };
        let drawn = self.draw_items(items, &self.pinhole, pixels);
        // Covered pixels are those with a label (items labelled 0 are not
        // drawn; the label is the key's low 16 bits), all inside `drawn`:
        // copy them and reset their blocks of each row to background.
        const BLOCK: usize = 16;
        let width = self.width as usize;
        for y in drawn.rows() {
            let row = y * width;
            let span = row + drawn.x0 as usize..row + drawn.x1 as usize + 1;
            let (Some(src), Some(dst)) = (frame.keys.get_mut(span.clone()), labels.get_mut(span))
            else {
                continue;
            };
            for (src, dst) in src.chunks_mut(BLOCK).zip(dst.chunks_mut(BLOCK)) {
                if src.iter().fold(0, |acc, &k| acc | k as u16) == 0 {
                    continue;
                }
                for (s, d) in src.iter().zip(dst.iter_mut()) {
                    let label = *s as u16;
                    if label != 0 {
                        *d = label;
                    }
                }
                src.fill(BACKGROUND_KEY);
            }
        }
        debug_assert!(
            frame.keys.iter().all(|&k| k == BACKGROUND_KEY),
            "drawn outside {drawn:?}"
        );
        frame.dirty = false;
    }

    /// Renders one frame per entry of `frames`, in parallel with rayon. The
    /// result does not depend on the number of threads.
    pub fn render_frames(&self, frames: &[Vec<RenderItem>]) -> Vec<RenderOutput> {
        frames.par_iter().map(|items| self.render(items)).collect()
    }

    /// Draws all items into `labels` and `depth_m`, row-major buffers of
    /// the size of `k` (background-initialized by the caller). Returns a
    /// rectangle of pixels outside which nothing was drawn.
    fn draw_items<P: Pixels>(&self, items: &[RenderItem], k: &Pinhole, pixels: P) -> PixelRect {
        let mut target = Target {
            width: k.width as usize,
            height: k.height as usize,
            pixels,
        };
        SCRATCH.with(|scratch| match scratch.try_borrow_mut() {
            Ok(mut scratch) => self.draw_items_with(items, k, &mut target, &mut scratch),
            Err(_) => self.draw_items_with(items, k, &mut target, &mut Scratch::default()),
        })
    }

    /// [`Rasterizer::draw_items`] with explicit scratch buffers.
    ///
    /// Triangles are classified four at a time ([`classify_x4`]) and drawn
    /// per class: small ones with [`Target::draw_small_x4`], medium ones
    /// with [`Target::draw_medium`], the others (and clipped ones) with
    /// [`Target::draw_triangle`]. The result is the same as drawing every
    /// triangle with [`Target::draw_triangle`], since both compute identical
    /// coverage and depth and the depth test does not depend on the order.
    fn draw_items_with<P: Pixels>(
        &self,
        items: &[RenderItem],
        k: &Pinhole,
        target: &mut Target<P>,
        scratch: &mut Scratch,
    ) -> PixelRect {
        /// [`Rasterizer::draw_items_inline`] as a `pulp` kernel.
        struct Kernel<'a, 'b, P> {
            rasterizer: &'a Rasterizer,
            items: &'a [RenderItem<'b>],
            k: &'a Pinhole,
            target: &'a mut Target<P>,
            scratch: &'a mut Scratch,
        }
        impl<P: Pixels> pulp::WithSimd for Kernel<'_, '_, P> {
            type Output = PixelRect;
            #[inline(always)]
            fn with_simd<S: pulp::Simd>(self, _simd: S) -> PixelRect {
                let Self {
                    rasterizer,
                    items,
                    k,
                    target,
                    scratch,
                } = self;
                rasterizer.draw_items_inline(items, k, target, scratch)
            }
        }
        pulp::Arch::new().dispatch(Kernel {
            rasterizer: self,
            items,
            k,
            target,
            scratch,
        })
    }

    /// The body of [`Rasterizer::draw_items_with`], inlined into its
    /// instruction-set-specific copies (as is everything it calls).
    #[inline(always)]
    fn draw_items_inline<P: Pixels>(
        &self,
        items: &[RenderItem],
        k: &Pinhole,
        target: &mut Target<P>,
        scratch: &mut Scratch,
    ) -> PixelRect {
        let planes = Planes::new(k);
        let last_x = k.width as i32 - 1;
        let last_y = k.height as i32 - 1;
        let Scratch {
            screen,
            classes,
            lists,
        } = scratch;
        let mut drawn = PixelRect::EMPTY;
        for item in items {
            if item.label == 0 {
                continue;
            }
            let camera_from_mesh = self.camera_from_world * item.world_from_mesh;
            let m = camera_from_mesh.to_homogeneous();
            if !m.iter().all(|v| v.is_finite()) {
                continue;
            }
            let r: [[f32; 4]; 3] =
                std::array::from_fn(|i| std::array::from_fn(|j| m[(i, j)] as f32));
            let (outcodes_any, [min_x, max_x, min_y, max_y]) =
                transform_vertices(&item.mesh.vertices, &r, k, &planes, screen);
            // Pixels drawn lie in the vertices' bounding box unless some
            // triangle is clipped (then anywhere).
            let item_rect = if outcodes_any == 0 {
                let shift = SUBPIXEL_BITS;
                PixelRect {
                    x0: (-((-i64::from(min_x)) >> shift)).max(0),
                    x1: (i64::from(max_x) >> shift).min(i64::from(last_x)),
                    y0: (-((-i64::from(min_y)) >> shift)).max(0),
                    y1: (i64::from(max_y) >> shift).min(i64::from(last_y)),
                }
            } else {
                PixelRect::full(last_x, last_y)
            };
            drawn = drawn.union(&item_rect);
            // Back faces are hidden only when the camera is outside the
            // mesh, which holds when no vertex is behind the near plane.
            let n_cull = if outcodes_any & 1 == 0 {
                item.closed_triangles
            } else {
                0
            };
            let triangles = &item.mesh.triangles[..];
            classes.clear();
            classes.resize(triangles.len().div_ceil(64) * 64, CLASS_SKIP);
            let n = i32::try_from(n_cull).unwrap_or(i32::MAX);
            let classify = |chunk: usize, tris: [[u32; 3]; 4]| {
                // Lane i culls when triangle 4 * chunk + i < n_cull.
                let first = i32::try_from(chunk * 4).unwrap_or(i32::MAX);
                let cull = (i32x4::splat(first) + LANE_INDEX).cmp_lt(i32x4::splat(n));
                classify_x4(tris, screen, cull, last_x, last_y)
            };
            let mut groups = triangles.chunks_exact(4);
            for (chunk, (tris, out)) in (&mut groups).zip(classes.chunks_exact_mut(4)).enumerate() {
                if let (Ok(tris), Ok(out)) = (
                    <[[u32; 3]; 4]>::try_from(tris),
                    <&mut [u8; 4]>::try_from(out),
                ) {
                    *out = classify(chunk, tris);
                }
            }
            let rest = groups.remainder();
            if !rest.is_empty() {
                // Padding lanes: out-of-range indices, skipped.
                let tri = |i: usize| rest.get(i).copied().unwrap_or([u32::MAX; 3]);
                let chunk = triangles.len() / 4;
                let c = classify(chunk, [tri(0), tri(1), tri(2), tri(3)]);
                if let Some(out) = classes.get_mut(chunk * 4..chunk * 4 + 4) {
                    out.copy_from_slice(&c);
                }
            }
            for (class, list) in lists.iter_mut().enumerate().skip(1) {
                if class == usize::from(CLASS_CLIP) && outcodes_any == 0 {
                    // Every vertex inside every clip plane: nothing clipped.
                    list.clear();
                    continue;
                }
                collect_class(classes, class as u8, list);
            }
            let label = item.label;
            let list = |class: u8| &lists[usize::from(class)][..];
            target.draw_list::<1>(list(CLASS_ONE), triangles, screen, label);
            target.draw_list::<2>(list(CLASS_TWO), triangles, screen, label);
            target.draw_list::<4>(list(CLASS_QUAD), triangles, screen, label);
            target.draw_list::<MEDIUM>(list(CLASS_MEDIUM), triangles, screen, label);
            target.draw_list::<0>(list(CLASS_LARGE), triangles, screen, label);
            for &t in list(CLASS_CLIP) {
                let Some(&[i0, i1, i2]) = triangles.get(t as usize) else {
                    continue;
                };
                let [i0, i1, i2] = [i0, i1, i2].map(|i| i as usize);
                let (Some(a), Some(b), Some(c)) = (screen.get(i0), screen.get(i1), screen.get(i2))
                else {
                    continue;
                };
                let any_out = a.outcode() | b.outcode() | c.outcode();
                let vertices = &item.mesh.vertices;
                let (Some(pa), Some(pb), Some(pc)) =
                    (vertices.get(i0), vertices.get(i1), vertices.get(i2))
                else {
                    continue;
                };
                let cam = [pa, pb, pc].map(|v| transform(&r, v.x, v.y, v.z));
                let mut poly = [[0.0f32; 3]; MAX_POLY];
                let n = clip_polygon(cam, &planes, any_out, &mut poly);
                if n < 3 {
                    continue;
                }
                let p0 = project(k, &poly[0]);
                for j in 1..n - 1 {
                    target.draw_triangle(
                        [&p0, &project(k, &poly[j]), &project(k, &poly[j + 1])],
                        label,
                    );
                }
            }
        }
        drawn
    }

    /// The straightforward version of [`Rasterizer::draw_items`]: every
    /// triangle through [`Target::draw_triangle`]. Reference for tests.
    #[cfg(test)]
    fn draw_items_reference(&self, items: &[RenderItem], k: &Pinhole, out: &mut RenderOutput) {
        let planes = Planes::new(k);
        let mut target = Target {
            width: k.width as usize,
            height: k.height as usize,
            pixels: LabelDepth {
                labels: &mut out.labels,
                depth_m: &mut out.depth_m,
            },
        };
        for item in items {
            if item.label == 0 {
                continue;
            }
            let camera_from_mesh = self.camera_from_world * item.world_from_mesh;
            let m = camera_from_mesh.to_homogeneous();
            if !m.iter().all(|v| v.is_finite()) {
                continue;
            }
            let r: [[f32; 4]; 3] =
                std::array::from_fn(|i| std::array::from_fn(|j| m[(i, j)] as f32));
            let cam: Vec<[f32; 3]> = item
                .mesh
                .vertices
                .iter()
                .map(|v| {
                    [
                        r[0][0] * v.x + r[0][1] * v.y + r[0][2] * v.z + r[0][3],
                        r[1][0] * v.x + r[1][1] * v.y + r[1][2] * v.z + r[1][3],
                        r[2][0] * v.x + r[2][1] * v.y + r[2][2] * v.z + r[2][3],
                    ]
                })
                .collect();
            let outcodes: Vec<u8> = cam.iter().map(|p| planes.outcode(p)).collect();
            let cull = outcodes.iter().all(|o| o & 1 == 0);
            for (ti, tri) in item.mesh.triangles.iter().enumerate() {
                let cull = cull && ti < item.closed_triangles;
                let [i0, i1, i2] = tri.map(|i| i as usize);
                let codes = [outcodes[i0], outcodes[i1], outcodes[i2]];
                let any_out = codes[0] | codes[1] | codes[2];
                if codes[0] & codes[1] & codes[2] != 0 {
                    continue;
                }
                let mut poly = [[0.0f32; 3]; MAX_POLY];
                let n = if any_out == 0 {
                    poly[..3].copy_from_slice(&[cam[i0], cam[i1], cam[i2]]);
                    3
                } else {
                    clip_polygon([cam[i0], cam[i1], cam[i2]], &planes, any_out, &mut poly)
                };
                if n < 3 {
                    continue;
                }
                let p0 = project(k, &poly[0]);
                for j in 1..n - 1 {
                    let (p1, p2) = (project(k, &poly[j]), project(k, &poly[j + 1]));
                    if cull && any_out == 0 {
                        let area = (i64::from(p1.x()) - i64::from(p0.x()))
                            * (i64::from(p2.y()) - i64::from(p0.y()))
                            - (i64::from(p1.y()) - i64::from(p0.y()))
                                * (i64::from(p2.x()) - i64::from(p0.x()));
                        if area > 0 {
                            continue;
                        }
                    }
                    target.draw_triangle([&p0, &p1, &p2], item.label);
                }
            }
        }
    }
}

/// Maps a mesh-frame point to the camera frame with the 3x4 matrix `r`.
#[inline(always)]
fn transform(r: &[[f32; 4]; 3], x: f32, y: f32, z: f32) -> [f32; 3] {
    [
        r[0][0] * x + r[0][1] * y + r[0][2] * z + r[0][3],
        r[1][0] * x + r[1][1] * y + r[1][2] * z + r[1][3],
        r[2][0] * x + r[2][1] * y + r[2][2] * z + r[2][3],
    ]
}

/// Transforms mesh vertices by `r`, computes their outcodes and projects
/// them into `screen` (resized to match), four at a time with SIMD. Returns
/// the OR of all outcodes. Same IEEE operations in the same order as
/// [`transform`], [`Planes::outcode`] and [`project`] (so bit-identical
/// results); position and 1/z of a vertex with a non-zero outcode are
/// unspecified (never read), which lets rounding use a plain truncating
/// conversion (exact here: guard-band coordinates are far below 2^31). Also
/// returns `[min x, max x, min y, max y]` of the fixed-point positions of
/// the vertices with outcode 0 (`i32::MAX`/`i32::MIN` when there are none).
#[inline(always)]
fn transform_vertices(
    vertices: &[nalgebra::Point3<f32>],
    r: &[[f32; 4]; 3],
    k: &Pinhole,
    planes: &Planes,
    screen: &mut Vec<ScreenVertex>,
) -> (u8, [i32; 4]) {
    use wide::{f32x4, i32x4, CmpEq, CmpGe};
    const LANES: usize = 4;
    screen.clear();
    let m: [[f32x4; 4]; 3] = r.map(|row| row.map(f32x4::splat));
    let [near, left, right, top, bottom] = planes.planes.map(|p| p.map(f32x4::splat));
    let zero = f32x4::splat(0.0);
    let half = f32x4::splat(0.5);
    let (fx, fy) = (f32x4::splat(k.fx), f32x4::splat(k.fy));
    let (cx, cy) = (f32x4::splat(k.cx), f32x4::splat(k.cy));
    let subpixel = f32x4::splat(SUBPIXEL);
    // Four vertices: their screen vertices and outcode lanes.
    let four = |vs: &[nalgebra::Point3<f32>; LANES]| {
        let x = f32x4::from([vs[0].x, vs[1].x, vs[2].x, vs[3].x]);
        let y = f32x4::from([vs[0].y, vs[1].y, vs[2].y, vs[3].y]);
        let z = f32x4::from([vs[0].z, vs[1].z, vs[2].z, vs[3].z]);
        let p: [f32x4; 3] =
            std::array::from_fn(|i| m[i][0] * x + m[i][1] * y + m[i][2] * z + m[i][3]);
        let [px, py, pz] = p;
        // Outcode lanes: bit j set when outside plane j (d < 0 or NaN,
        // i.e. !(d >= 0)).
        let distances = [
            pz + near[3],
            left[0] * px + left[2] * pz,
            right[0] * px + right[2] * pz,
            top[1] * py + top[2] * pz,
            bottom[1] * py + bottom[2] * pz,
        ];
        let mut code = i32x4::splat(0);
        for (plane, d) in distances.iter().enumerate() {
            let outside = !bytemuck::cast::<_, i32x4>(d.cmp_ge(zero));
            code |= outside & i32x4::splat(1 << plane);
        }
        let inv_z = f32x4::splat(1.0) / pz;
        let round = |v: f32x4| (v + half.copysign(v)).fast_trunc_int();
        let sx = round((fx * px * inv_z + cx) * subpixel);
        let sy = round((fy * py * inv_z + cy) * subpixel);
        let lanes = i32x4::transpose([sx, sy, bytemuck::cast::<_, i32x4>(inv_z), code]);
        (lanes.map(ScreenVertex), code, sx, sy)
    };
    let mut any = i32x4::splat(0);
    // Bounds of the vertices inside every clip plane.
    let (mut min_x, mut max_x) = (i32x4::splat(i32::MAX), i32x4::splat(i32::MIN));
    let (mut min_y, mut max_y) = (min_x, max_x);
    let mut bound = |code: i32x4, sx: i32x4, sy: i32x4| {
        let inside = code.cmp_eq(i32x4::splat(0));
        min_x = min_x.min(inside.blend(sx, i32x4::splat(i32::MAX)));
        max_x = max_x.max(inside.blend(sx, i32x4::splat(i32::MIN)));
        min_y = min_y.min(inside.blend(sy, i32x4::splat(i32::MAX)));
        max_y = max_y.max(inside.blend(sy, i32x4::splat(i32::MIN)));
    };
    let mut chunks = vertices.chunks_exact(LANES);
    for vs in &mut chunks {
        let Ok(vs) = <&[_; LANES]>::try_from(vs) else {
            continue;
        };
        let (out, code, sx, sy) = four(vs);
        screen.extend_from_slice(&out);
        any |= code;
        bound(code, sx, sy);
    }
    let rest = chunks.remainder();
    if !rest.is_empty() {
        // Padding lanes (copies of a mesh vertex) change neither the
        // outcodes' union nor the screen vertices kept.
        let mut vs = [rest[0]; LANES];
        vs[..rest.len()].copy_from_slice(rest);
        let (out, code, sx, sy) = four(&vs);
        screen.extend_from_slice(&out[..rest.len()]);
        any |= code;
        bound(code, sx, sy);
    }
    let any = any.to_array();
    let any = any[0] | any[1] | any[2] | any[3];
    let min = |v: i32x4| v.to_array().into_iter().fold(i32::MAX, i32::min);
    let max = |v: i32x4| v.to_array().into_iter().fold(i32::MIN, i32::max);
    (any as u8, [min(min_x), max(max_x), min(min_y), max(max_y)])
}

/// Projects a camera-frame point with z >= near to fixed-point pixels.
#[inline]
fn project(k: &Pinhole, p: &[f32; 3]) -> ScreenVertex {
    let inv_z = 1.0 / p[2];
    let u = k.fx * p[0] * inv_z + k.cx;
    let v = k.fy * p[1] * inv_z + k.cy;
    ScreenVertex::new(
        round_to_i32(u * SUBPIXEL),
        round_to_i32(v * SUBPIXEL),
        inv_z,
        0,
    )
}

/// Rounds half away from zero (saturating; NaN -> 0) without a libm call.
#[inline]
fn round_to_i32(x: f32) -> i32 {
    // Same as adding 0.5 when x >= 0 (including -0.0) and subtracting it
    // otherwise, without a branch.
    (x + 0.5f32.copysign(x)) as i32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rasterizer_is_send_sync() {
        fn assert_send_sync<T: Send + Sync>() {}
        assert_send_sync::<Rasterizer>();
    }

    use nalgebra::{Point3, Translation3, UnitQuaternion};

    /// Deterministic xorshift generator in [0, 1).
    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> f32 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            (self.0 >> 40) as f32 / (1u64 << 24) as f32
        }
    }

    /// A dense random mesh around `centre`: clusters of tiny triangles (many
    /// sub-pixel) sharing vertices, plus a few large ones.
    fn dense_mesh(rng: &mut Rng, centre: [f32; 3], spread: f32, size: f32, n: usize) -> TriMesh {
        let mut vertices = Vec::new();
        let mut triangles = Vec::new();
        for _ in 0..n {
            let c = [
                centre[0] + spread * (rng.next() - 0.5),
                centre[1] + spread * (rng.next() - 0.5),
                centre[2] + spread * (rng.next() - 0.5),
            ];
            let s = if rng.next() < 0.05 { size * 30.0 } else { size };
            let base = vertices.len() as u32;
            for _ in 0..4 {
                vertices.push(Point3::new(
                    c[0] + s * (rng.next() - 0.5),
                    c[1] + s * (rng.next() - 0.5),
                    c[2] + s * (rng.next() - 0.5),
                ));
            }
            triangles.push([base, base + 1, base + 2]);
            triangles.push([base + 2, base + 1, base + 3]);
            triangles.push([base, base + 3, base + 1]);
        }
        TriMesh {
            vertices,
            triangles,
        }
    }

    /// Triangles of 0 to 7 pixels anywhere in (and around) a small image,
    /// so that every class occurs, also touching the image borders and the
    /// last pixels of the buffer: same output as the reference.
    #[test]
    fn size_classes_match_reference_at_borders() {
        use crate::camera::Intrinsics;
        let (w, h) = (37u32, 23u32);
        let intrinsics = Intrinsics {
            fx: 100.0,
            fy: 100.0,
            cx: 18.0,
            cy: 11.0,
            width: w,
            height: h,
            distortion: None,
        };
        let camera = Camera::look_at(
            intrinsics,
            nalgebra::Point3::new(0.0, 0.0, 0.0),
            nalgebra::Point3::new(0.0, 0.0, 1.0),
            nalgebra::Vector3::y(),
        )
        .expect("camera");
        let rasterizer = Rasterizer::new(&camera);
        let mut rng = Rng(0x2545_f491_4f6c_dd1d);
        let mut drawn = 0;
        for case in 0..60 {
            let mut vertices = Vec::new();
            let mut triangles = Vec::new();
            let max_size = [1.5, 3.0, 7.0][case % 3];
            for t in 0..400u32 {
                // Pixel-space centre, biased towards the bottom-right corner
                // in a third of the cases; 1 px = 0.01 m at z = 1.
                let corner = case % 3 == 1 && t % 2 == 0;
                let (u, v) = if corner {
                    (w as f32 - 4.0 * rng.next(), h as f32 - 4.0 * rng.next())
                } else {
                    (
                        (w as f32 + 4.0) * rng.next() - 2.0,
                        (h as f32 + 4.0) * rng.next() - 2.0,
                    )
                };
                let z = 1.0 + rng.next();
                for _ in 0..3 {
                    let du = max_size * (rng.next() - 0.5);
                    let dv = max_size * (rng.next() - 0.5);
                    // Snap some vertices to pixel centres and edges.
                    let snap = |p: f32| {
                        if rng.0 % 4 == 0 {
                            (p * 2.0).round() / 2.0
                        } else {
                            p
                        }
                    };
                    let (pu, pv) = (snap(u + du), snap(v + dv));
                    vertices.push(nalgebra::Point3::new(
                        (pu - 18.0) * 0.01 * z,
                        (pv - 11.0) * 0.01 * z,
                        z,
                    ));
                }
                triangles.push([3 * t, 3 * t + 1, 3 * t + 2]);
            }
            let mesh = TriMesh {
                vertices,
                triangles,
            };
            let items = [RenderItem {
                mesh: &mesh,
                world_from_mesh: Isometry3::identity(),
                label: 1 + (case % 3) as u16,
                closed_triangles: if case % 2 == 1 { usize::MAX } else { 0 },
            }];
            let fast = rasterizer.render(&items);
            let mut reference = RenderOutput::new(w, h);
            rasterizer.draw_items_reference(&items, &rasterizer.pinhole, &mut reference);
            assert_eq!(fast.labels, reference.labels, "case {case}");
            for (a, b) in fast.depth_m.iter().zip(&reference.depth_m) {
                assert_eq!(a.to_bits(), b.to_bits(), "case {case}");
            }
            assert_eq!(rasterizer.render_labels(&items), reference.labels);
            drawn += fast.coverage();
        }
        assert!(drawn > 5000, "{drawn}");
    }

    /// Packed keys order as the depth test (nearer wins, then the lower
    /// label) for depths of any sign and infinities, and the packed pixel
    /// buffer's depth tests (single, four in a row, four anywhere, spans)
    /// give the labels of separate depth and label buffers.
    #[test]
    fn packed_keys_match_separate_buffers() {
        let mut rng = Rng(0x1234_5678_9abc_def1);
        let depths = [
            f32::NEG_INFINITY,
            -3.5,
            -1e-30,
            1e-30,
            0.01,
            0.5,
            0.5000001,
            1.0,
            7.25,
            1e30,
            f32::INFINITY,
        ];
        for &a in &depths {
            for &b in &depths {
                for (la, lb) in [(1u16, 2u16), (2, 1), (3, 3)] {
                    let float_wins = a < b || (a == b && la < lb);
                    assert_eq!(depth_key(a, la) < depth_key(b, lb), float_wins, "{a} {b}");
                }
            }
        }
        assert_eq!(depth_key(f32::INFINITY, 0), BACKGROUND_KEY);
        let n = 64;
        let mut labels = vec![0u16; n];
        let mut depth_m = vec![f32::INFINITY; n];
        let mut keys = vec![BACKGROUND_KEY; n];
        let z_of = |rng: &mut Rng| {
            // Few distinct depths, so that ties occur.
            let z = 0.5 + (rng.next() * 8.0).floor() * 0.25;
            if rng.next() < 0.05 {
                -z
            } else {
                z
            }
        };
        for step in 0..4000 {
            let label = 1 + (rng.next() * 5.0) as u16;
            let mut separate = LabelDepth {
                labels: &mut labels,
                depth_m: &mut depth_m,
            };
            let mut packed = Keys { keys: &mut keys };
            // Indices reach past the end: ignored by both.
            let idx = (rng.next() * (n + 6) as f32) as usize;
            let z = f32x4::from([
                z_of(&mut rng),
                z_of(&mut rng),
                z_of(&mut rng),
                z_of(&mut rng),
            ]);
            let bits = (rng.next() * 16.0) as i32;
            match step % 4 {
                0 => {
                    let covered = bits & 1 != 0;
                    let z = z.to_array()[0];
                    separate.depth_test(idx, z, label, covered);
                    packed.depth_test(idx, z, label, covered);
                }
                1 => {
                    let covered = LANE_MASKS[bits as usize];
                    separate.depth_test_x4(idx, z, label, covered);
                    packed.depth_test_x4(idx, z, label, covered);
                }
                2 => {
                    let idx: [usize; 4] =
                        std::array::from_fn(|_| (rng.next() * (n + 2) as f32) as usize);
                    separate.depth_test_lanes(idx, z, label, bits);
                    packed.depth_test_lanes(idx, z, label, bits);
                }
                _ => {
                    let end = idx + (rng.next() * 5.0) as usize;
                    let zs = z.to_array();
                    let z_at = |i: &mut usize| {
                        *i += 1;
                        ((bits >> (*i % 4)) & 1 != 0).then_some(zs[*i % 4])
                    };
                    let (mut i, mut j) = (0, 0);
                    let a = separate.depth_test_span(idx, end, label, || z_at(&mut i));
                    let b = packed.depth_test_span(idx, end, label, || z_at(&mut j));
                    assert_eq!(a, b);
                }
            }
            for i in 0..n {
                assert_eq!(keys[i], depth_key(depth_m[i], labels[i]), "step {step}");
            }
        }
        assert!(labels.iter().filter(|&&l| l != 0).count() > n / 2);
    }

    #[test]
    fn fast_path_matches_reference() {
        use crate::camera::Intrinsics;
        let intrinsics = Intrinsics {
            fx: 300.0,
            fy: 310.0,
            cx: 79.5,
            cy: 59.5,
            width: 160,
            height: 120,
            distortion: None,
        };
        let camera = Camera::look_at(
            intrinsics,
            nalgebra::Point3::new(0.0, 0.0, 0.0),
            nalgebra::Point3::new(0.0, 0.0, 1.0),
            nalgebra::Vector3::y(),
        )
        .expect("camera");
        let rasterizer = Rasterizer::new(&camera);
        let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
        for case in 0..40 {
            let meshes: Vec<TriMesh> = (0..3)
                .map(|i| {
                    let z = 0.3 + rng.next() * 1.5;
                    let spread = 0.2 + rng.next() * 0.6;
                    // Some meshes reach behind the near plane and outside
                    // the image.
                    let spread = if case % 5 == 0 && i == 0 { 2.0 } else { spread };
                    let size = 0.0005 + rng.next() * 0.004;
                    dense_mesh(&mut rng, [0.0, 0.0, z], spread, size, 3000)
                })
                .collect();
            let items: Vec<RenderItem> = meshes
                .iter()
                .enumerate()
                .map(|(i, mesh)| RenderItem {
                    mesh,
                    world_from_mesh: Isometry3::from_parts(
                        Translation3::new(0.0, 0.0, 0.0),
                        UnitQuaternion::from_euler_angles(0.01 * case as f64, 0.0, 0.0),
                    ),
                    label: 1 + (i as u16 % 2),
                    closed_triangles: if case % 2 == 1 { usize::MAX } else { 0 },
                })
                .collect();
            let fast = rasterizer.render(&items);
            let mut reference = RenderOutput::new(160, 120);
            rasterizer.draw_items_reference(&items, &rasterizer.pinhole, &mut reference);
            assert!(
                fast.coverage() > 200,
                "case {case}: coverage {}",
                fast.coverage()
            );
            assert_eq!(fast.labels, reference.labels, "case {case}");
            for (a, b) in fast.depth_m.iter().zip(&reference.depth_m) {
                assert_eq!(a.to_bits(), b.to_bits(), "case {case}");
            }
        }
    }

    /// Label maps rendered one after another on one thread (reusing its
    /// frame buffers, which are reset only where something was drawn) equal
    /// fresh full renders: meshes crossing the near plane and the image
    /// border, in a corner, none at all, and drawn over a non-zero map.
    #[test]
    fn label_frames_reused_across_frames_match_full_renders() {
        use crate::camera::Intrinsics;
        let camera = Camera::look_at(
            Intrinsics::centered(120.0, 96, 64),
            nalgebra::Point3::new(0.0, 0.0, 0.0),
            nalgebra::Point3::new(0.0, 0.0, 1.0),
            nalgebra::Vector3::y(),
        )
        .expect("camera");
        let rasterizer = Rasterizer::new(&camera);
        let sphere = TriMesh::sphere(0.3, 24);
        let cube = TriMesh::cuboid([0.2, 0.2, 0.2]);
        let at = |mesh, x: f64, y: f64, z: f64, label| RenderItem {
            mesh,
            world_from_mesh: Isometry3::translation(x, y, z),
            label,
            closed_triangles: 0,
        };
        let scenes: Vec<Vec<RenderItem>> = vec![
            vec![at(&sphere, 0.0, 0.0, 1.5, 1), at(&cube, 0.1, 0.0, 1.2, 2)],
            // Crosses the near plane: clipped.
            vec![at(&sphere, 0.1, 0.05, 0.1, 3)],
            vec![at(&cube, 0.55, 0.35, 1.3, 1)],
            vec![],
            // Partly outside the image.
            vec![at(&sphere, -0.7, 0.0, 1.0, 2), at(&cube, 0.0, 0.4, 1.0, 5)],
            vec![at(&cube, -0.3, -0.2, 2.0, 4)],
        ];
        for round in 0..2 {
            for (i, items) in scenes.iter().enumerate() {
                let expected = rasterizer.render(items).labels;
                assert_eq!(rasterizer.render_labels(items), expected, "scene {i}");
                let mut over = vec![9u16; expected.len()];
                rasterizer.render_labels_into(items, &mut over);
                for (o, &e) in over.iter().zip(&expected) {
                    assert_eq!(*o, if e != 0 { e } else { 9 }, "scene {i} round {round}");
                }
            }
        }
        assert!(rasterizer.render(&scenes[1]).coverage() > 1000);
    }

    #[test]
    fn culling_closed_components_changes_nothing() {
        use crate::camera::Intrinsics;
        // An open box (one face missing: its inside shows), an inward-wound
        // closed box and a sphere, as one mesh with closed components first.
        let mut open = TriMesh::cuboid([0.3, 0.3, 0.3]);
        open.triangles.truncate(open.triangles.len() - 2);
        let inward = TriMesh::cuboid([0.2, 0.25, 0.15])
            .transformed(&Isometry3::translation(0.4, 0.0, 0.0))
            .flipped();
        let sphere = TriMesh::sphere(0.15, 24).transformed(&Isometry3::translation(-0.4, 0.1, 0.0));
        let mut mesh = TriMesh::default();
        mesh.append(&open);
        mesh.append(&inward);
        mesh.append(&sphere);
        let (mesh, n_closed) = mesh.closed_components_first();
        assert_eq!(n_closed, inward.triangles.len() + sphere.triangles.len());
        let mut rng = Rng(0x2545_f491_4f6c_dd1d);
        for case in 0..24 {
            let angle = f64::from(rng.next()) * std::f64::consts::TAU;
            let height = -0.8 + 1.6 * f64::from(rng.next());
            let eye = nalgebra::Point3::new(1.6 * angle.cos(), 1.6 * angle.sin(), height);
            let camera = Camera::look_at(
                Intrinsics::centered(150.0, 160, 120),
                eye,
                nalgebra::Point3::origin(),
                nalgebra::Vector3::z(),
            )
            .expect("camera");
            let rasterizer = Rasterizer::new(&camera);
            let item = |closed_triangles| RenderItem {
                mesh: &mesh,
                world_from_mesh: Isometry3::identity(),
                label: 3,
                closed_triangles,
            };
            let culled = rasterizer.render(&[item(n_closed)]);
            let full = rasterizer.render(&[item(0)]);
            assert!(full.coverage() > 1000, "case {case}: {}", full.coverage());
            assert_eq!(culled.labels, full.labels, "case {case}");
            for (a, b) in culled.depth_m.iter().zip(&full.depth_m) {
                assert!(
                    a == b || (a - b).abs() <= 1e-5 * b.abs(),
                    "case {case}: {a} vs {b}"
                );
            }
        }
    }
}
