//! The per-frame drawing of all items ([`Rasterizer::draw_items`]):
//! vertices to the screen, triangles classified and drawn per class,
//! clipped ones through [`clip_polygon`].

use super::classify::{
    classify_x4, collect_class, CLASSES, CLASS_CLIP, CLASS_LARGE, CLASS_MEDIUM, CLASS_ONE,
    CLASS_QUAD, CLASS_SKIP, CLASS_TWO, MEDIUM,
};
use super::clip::{clip_polygon, Planes, MAX_POLY};
use super::lanes::LANE_INDEX;
#[cfg(test)]
use super::pixels::LabelDepth;
use super::pixels::Pixels;
use super::triangle::Target;
use super::vertex::{project, transform, transform_vertices, ScreenVertex};
#[cfg(test)]
use super::RenderOutput;
use super::{Pinhole, Rasterizer, RenderItem, SUBPIXEL_BITS};
use std::cell::RefCell;
use wide::{i32x4, CmpLt};

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
}

/// An inclusive rectangle of pixels (empty when `x0 > x1` or `y0 > y1`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct PixelRect {
    pub(super) x0: i64,
    pub(super) x1: i64,
    pub(super) y0: i64,
    pub(super) y1: i64,
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
    pub(super) fn rows(&self) -> std::ops::Range<usize> {
        if self.is_empty() {
            0..0
        } else {
            self.y0.max(0) as usize..self.y1.max(0) as usize + 1
        }
    }
}

impl Rasterizer {
    /// Draws all items into `labels` and `depth_m`, row-major buffers of
    /// the size of `k` (background-initialized by the caller). Returns a
    /// rectangle of pixels outside which nothing was drawn.
    pub(super) fn draw_items<P: Pixels>(
        &self,
        items: &[RenderItem],
        k: &Pinhole,
        pixels: P,
    ) -> PixelRect {
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
    pub(super) fn draw_items_reference(
        &self,
        items: &[RenderItem],
        k: &Pinhole,
        out: &mut RenderOutput,
    ) {
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
