//! A small software RGB rasterizer for the synthetic scene.
//!
//! Triangles are projected through an undistorted pinhole camera (pixel
//! centres at integer coordinates, as the embodiment crate's mask
//! rasterizer), depth-tested per pixel on interpolated inverse camera depth
//! and flat shaded (ambient + Lambert from one directional light, two-sided
//! normals facing the camera). The table top and the background are drawn
//! per pixel by casting the pixel's ray.

use bridgev2w_embodiment::camera::Camera;
use bridgev2w_embodiment::mesh::TriMesh;
use nalgebra::{Isometry3, Point3, Vector3};

/// Closest camera depth drawn (metres); triangles with a corner closer are skipped.
const NEAR_M: f64 = 0.01;

/// A float RGB image with an inverse-depth buffer.
#[derive(Debug, Clone)]
pub struct Canvas {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Row-major linear RGB in `[0, 1]`.
    pub rgb: Vec<[f32; 3]>,
    /// `1 / depth_m` of the nearest surface drawn (0 = nothing, at infinity).
    pub inv_depth: Vec<f32>,
}

impl Canvas {
    /// A black canvas at infinite depth.
    pub fn new(width: usize, height: usize) -> Self {
        Self {
            width,
            height,
            rgb: vec![[0.0; 3]; width * height],
            inv_depth: vec![0.0; width * height],
        }
    }

    /// The image as interleaved 8-bit RGB.
    pub fn to_rgb8(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.rgb.len() * 3);
        for px in &self.rgb {
            for c in px {
                out.push((c.clamp(0.0, 1.0) * 255.0 + 0.5) as u8);
            }
        }
        out
    }
}

/// Lighting of the scene.
#[derive(Debug, Clone, Copy)]
pub struct Light {
    /// Unit direction towards the light, world frame.
    pub to_light_world: Vector3<f64>,
    /// Ambient fraction in `[0, 1]`.
    pub ambient: f64,
}

impl Light {
    /// Shading factor for a surface with unit normal `n_world`.
    pub fn shade(&self, n_world: &Vector3<f64>) -> f64 {
        self.ambient + (1.0 - self.ambient) * n_world.dot(&self.to_light_world).max(0.0)
    }
}

/// Draws `mesh` placed at `world_from_mesh` in flat colour `color` with
/// Lambert shading and a per-pixel depth test.
pub fn draw_mesh(
    canvas: &mut Canvas,
    camera: &Camera,
    mesh: &TriMesh,
    world_from_mesh: &Isometry3<f64>,
    color: [f32; 3],
    light: &Light,
) {
    let camera_from_world = camera.world_from_camera.inverse();
    let camera_from_mesh = camera_from_world * world_from_mesh;
    let eye_world = camera.world_from_camera.translation.vector;
    let k = &camera.intrinsics;
    let world: Vec<Point3<f64>> = mesh
        .vertices
        .iter()
        .map(|v| world_from_mesh * Point3::new(f64::from(v.x), f64::from(v.y), f64::from(v.z)))
        .collect();
    let cam: Vec<Point3<f64>> = mesh
        .vertices
        .iter()
        .map(|v| camera_from_mesh * Point3::new(f64::from(v.x), f64::from(v.y), f64::from(v.z)))
        .collect();
    for tri in &mesh.triangles {
        let [a, b, c] = tri.map(|i| i as usize);
        let (pa, pb, pc) = (cam[a], cam[b], cam[c]);
        if pa.z < NEAR_M || pb.z < NEAR_M || pc.z < NEAR_M {
            continue;
        }
        let mut n = (world[b] - world[a]).cross(&(world[c] - world[a]));
        let norm = n.norm();
        if norm.is_nan() || norm <= 1e-18 {
            continue;
        }
        n /= norm;
        if n.dot(&(eye_world - world[a].coords)) < 0.0 {
            n = -n;
        }
        let s = light.shade(&n) as f32;
        let shaded = [color[0] * s, color[1] * s, color[2] * s];
        let project =
            |p: &Point3<f64>| (k.fx * p.x / p.z + k.cx, k.fy * p.y / p.z + k.cy, 1.0 / p.z);
        fill_triangle(canvas, project(&pa), project(&pb), project(&pc), shaded);
    }
}

/// Fills a screen-space triangle (`(u, v, 1/z)` corners) where it is nearer
/// than what is drawn. A pixel is covered when its centre is inside.
fn fill_triangle(
    canvas: &mut Canvas,
    a: (f64, f64, f64),
    b: (f64, f64, f64),
    c: (f64, f64, f64),
    color: [f32; 3],
) {
    let area = (b.0 - a.0) * (c.1 - a.1) - (b.1 - a.1) * (c.0 - a.0);
    if area.abs() < 1e-12 {
        return;
    }
    let (w, h) = (canvas.width as f64, canvas.height as f64);
    let x0 = a.0.min(b.0).min(c.0).ceil().max(0.0);
    let x1 = a.0.max(b.0).max(c.0).floor().min(w - 1.0);
    let y0 = a.1.min(b.1).min(c.1).ceil().max(0.0);
    let y1 = a.1.max(b.1).max(c.1).floor().min(h - 1.0);
    if x0 > x1 || y0 > y1 {
        return;
    }
    let inv_area = 1.0 / area;
    let edge = |p: (f64, f64, f64), q: (f64, f64, f64), x: f64, y: f64| {
        (q.0 - p.0) * (y - p.1) - (q.1 - p.1) * (x - p.0)
    };
    for y in (y0 as usize)..=(y1 as usize) {
        let yf = y as f64;
        for x in (x0 as usize)..=(x1 as usize) {
            let xf = x as f64;
            let wa = edge(b, c, xf, yf) * inv_area;
            let wb = edge(c, a, xf, yf) * inv_area;
            let wc = edge(a, b, xf, yf) * inv_area;
            if wa < 0.0 || wb < 0.0 || wc < 0.0 {
                continue;
            }
            let iz = (wa * a.2 + wb * b.2 + wc * c.2) as f32;
            let i = y * canvas.width + x;
            if iz > canvas.inv_depth[i] {
                canvas.inv_depth[i] = iz;
                canvas.rgb[i] = color;
            }
        }
    }
}

/// The pixel's ray: camera centre and unit direction (world frame).
pub fn pixel_ray_world(camera: &Camera, u: f64, v: f64) -> (Point3<f64>, Vector3<f64>) {
    let eye = Point3::from(camera.world_from_camera.translation.vector);
    (eye, camera.pixel_ray(u, v))
}

/// Camera-frame depth (metres) of the world point `p_world`.
pub fn camera_depth_m(camera: &Camera, p_world: &Point3<f64>) -> f64 {
    camera.world_from_camera.inverse_transform_point(p_world).z
}
