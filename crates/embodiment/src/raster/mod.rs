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
//! - Performance: measured by `benches/raster.rs`, `examples/panda_masks.rs`
//!   and `bridgev2w bench masks`; the figures are in `docs/benchmarks.md`.

// One job per file:
// - `vertex`: screen vertices (transform, clip outcodes, projection, gathers);
// - `clip`: clip planes and polygon clipping;
// - `pixels`: per-pixel depth test into separate or packed buffers;
// - `triangle`: drawing one triangle (small, medium and general paths);
// - `classify`: sorting triangles into those paths, four at a time;
// - `lanes`: SIMD lane helpers;
// - `draw`: the per-frame drawing of all items;
// - `labels`: label maps alone, through a reused per-thread frame;
// - `distort`: the lens-distortion remap.
mod classify;
mod clip;
mod distort;
mod draw;
mod labels;
mod lanes;
mod pixels;
#[cfg(test)]
mod tests;
mod triangle;
mod vertex;

use crate::camera::Camera;
use crate::mesh::TriMesh;
use distort::Remap;
use labels::{LabelFrame, LABEL_FRAME};
use nalgebra::Isometry3;
use pixels::LabelDepth;
use rayon::prelude::*;

/// Near clipping plane, camera-frame z in metres.
pub const NEAR_PLANE_M: f32 = 0.01;

/// Sub-pixel bits of the fixed-point vertex coordinates.
const SUBPIXEL_BITS: u32 = 8;
const SUBPIXEL: f32 = (1 << SUBPIXEL_BITS) as f32;

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

/// Draws meshes through one camera. Cheap to share across threads.
#[derive(Debug, Clone)]
pub struct Rasterizer {
    camera_from_world: Isometry3<f64>,
    width: u32,
    height: u32,
    /// Target of triangle drawing: the camera itself without distortion.
    pinhole: Pinhole,
    remap: Option<std::sync::Arc<Remap>>,
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
        let remap = k
            .active_distortion()
            .map(|d| std::sync::Arc::new(Remap::new(k, d)));
        Self {
            camera_from_world: camera.world_from_camera.inverse(),
            width: k.width,
            height: k.height,
            pinhole: camera_pinhole,
            remap,
        }
    }

    /// The same camera (intrinsics and distortion remap, shared) at another
    /// pose: a moving camera's frame without recomputing the remap.
    pub fn posed(&self, world_from_camera: &Isometry3<f64>) -> Self {
        Self {
            camera_from_world: world_from_camera.inverse(),
            ..self.clone()
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
                remap.copy_to(&buffer, out);
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

    /// Renders one frame per entry of `frames`, in parallel with rayon. The
    /// result does not depend on the number of threads.
    pub fn render_frames(&self, frames: &[Vec<RenderItem>]) -> Vec<RenderOutput> {
        frames.par_iter().map(|items| self.render(items)).collect()
    }
}
