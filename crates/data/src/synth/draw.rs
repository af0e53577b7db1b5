//! Rendering a scene's RGB frames: table, background, objects and robot
//! links through [`crate::render`].

use super::{EpisodeMeta, ObjectPose, SceneState, World};
use crate::render::{camera_depth_m, draw_mesh, pixel_ray_world, Canvas, Light};
use bridgev2w_embodiment::camera::Camera;
use bridgev2w_embodiment::mesh::TriMesh;
use nalgebra::Vector3;

fn srgb_to_linear(c: [u8; 3]) -> [f32; 3] {
    c.map(|v| (f32::from(v) / 255.0).powf(2.2))
}

fn linear_to_srgb(c: [f32; 3]) -> [f32; 3] {
    c.map(|v| v.clamp(0.0, 1.0).powf(1.0 / 2.2))
}

fn mix(a: [f32; 3], b: [f32; 3], w: f32) -> [f32; 3] {
    [
        a[0] + (b[0] - a[0]) * w,
        a[1] + (b[1] - a[1]) * w,
        a[2] + (b[2] - a[2]) * w,
    ]
}

/// The table top as the built-in renderer colours it (its pattern and
/// colours, unshaded), `width x height` pixels (sRGB8, row-major) over the
/// table's extent: row 0 at the table's largest y, column 0 at its smallest
/// x (an image laid on the table seen from above, x right, y up).
/// The backdrop seen along the world-frame ray `dir` (linear RGB): the
/// look's background pattern over azimuth and elevation, darker towards
/// the floor.
fn backdrop_linear(look: &super::SceneLook, back: [[f32; 3]; 2], dir: &Vector3<f64>) -> [f32; 3] {
    let az = dir.y.atan2(dir.x);
    let el = dir.z.clamp(-1.0, 1.0).asin();
    let wgt = look.background_pattern.weight(az, el) as f32;
    let shade = 0.75 + 0.25 * (el as f32 + 0.5).clamp(0.0, 1.0);
    mix(back[0], back[1], wgt).map(|v| v * shade)
}

/// [`World::backdrop`].
fn backdrop_image(meta: &EpisodeMeta, camera: &Camera) -> Vec<u8> {
    let look = &meta.look;
    let back = look.background_colors.map(srgb_to_linear);
    let (w, h) = (
        camera.intrinsics.width as usize,
        camera.intrinsics.height as usize,
    );
    let mut out = Vec::with_capacity(w * h * 3);
    for y in 0..h {
        for x in 0..w {
            let (_, dir) = pixel_ray_world(camera, x as f64, y as f64);
            let c = linear_to_srgb(backdrop_linear(look, back, &dir));
            out.extend(c.map(|v| (v * 255.0).round() as u8));
        }
    }
    out
}

pub(super) fn table_texture(
    world: &World,
    meta: &EpisodeMeta,
    width: usize,
    height: usize,
) -> Vec<u8> {
    let (fr, look) = (&world.frame, &meta.look);
    let table = look.table_colors.map(srgb_to_linear);
    let mut out = Vec::with_capacity(width * height * 3);
    for row in 0..height {
        let y = fr.table_y_m[1]
            - (row as f64 + 0.5) / height as f64 * (fr.table_y_m[1] - fr.table_y_m[0]);
        for col in 0..width {
            let x = fr.table_x_m[0]
                + (col as f64 + 0.5) / width as f64 * (fr.table_x_m[1] - fr.table_x_m[0]);
            let c = linear_to_srgb(mix(
                table[0],
                table[1],
                look.table_pattern.weight(x, y) as f32,
            ));
            out.extend(c.map(|v| (v * 255.0).round() as u8));
        }
    }
    out
}

/// Link colours (sRGB), by link index.
const LINK_COLORS: [[u8; 3]; 6] = [
    [235, 235, 232],
    [60, 62, 68],
    [200, 200, 205],
    [245, 245, 245],
    [110, 112, 120],
    [225, 225, 220],
];

impl World {
    /// The backdrop as `camera` sees it behind everything (interleaved
    /// sRGB8, the camera's size): what the renderer draws where a pixel's
    /// ray meets neither the table nor an object nor the robot. The MuJoCo
    /// engine draws it behind its scene.
    pub fn backdrop(&self, meta: &EpisodeMeta, camera: &Camera) -> Vec<u8> {
        backdrop_image(meta, camera)
    }

    /// Renders the scene in `state` (interleaved RGB8).
    pub fn render_state(&self, meta: &EpisodeMeta, camera: &Camera, state: &SceneState) -> Vec<u8> {
        self.render_poses(meta, camera, &state.joints, &state.object_poses)
    }

    /// Renders the scene with the robot at `joints` (URDF actuated order)
    /// and the objects at `object_poses` (interleaved RGB8): e.g. a frame of
    /// an episode another engine simulated, drawn as this world draws.
    pub fn render_poses(
        &self,
        meta: &EpisodeMeta,
        camera: &Camera,
        joints: &[f64],
        object_poses: &[ObjectPose],
    ) -> Vec<u8> {
        let meshes: Vec<TriMesh> = meta.objects.iter().map(|o| o.shape.mesh()).collect();
        self.render_rgb(meta, camera, &meshes, joints, object_poses)
    }

    pub(super) fn render_rgb(
        &self,
        meta: &EpisodeMeta,
        camera: &Camera,
        meshes: &[TriMesh],
        q: &[f64],
        object_poses: &[ObjectPose],
    ) -> Vec<u8> {
        let (w, h) = (
            camera.intrinsics.width as usize,
            camera.intrinsics.height as usize,
        );
        let mut canvas = Canvas::new(w, h);
        let look = &meta.look;
        let light = Light {
            to_light_world: Vector3::from(look.to_light_world).normalize(),
            ambient: 0.35,
        };
        let table = look.table_colors.map(srgb_to_linear);
        let back = look.background_colors.map(srgb_to_linear);
        let fr = &self.frame;
        let table_shade = light.shade(&Vector3::z()) as f32;
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                let (eye, dir) = pixel_ray_world(camera, x as f64, y as f64);
                let mut hit = false;
                if dir.z < -1e-9 {
                    let t = (fr.table_z_m - eye.z) / dir.z;
                    let p = eye + dir * t;
                    if t > 0.0
                        && (fr.table_x_m[0]..=fr.table_x_m[1]).contains(&p.x)
                        && (fr.table_y_m[0]..=fr.table_y_m[1]).contains(&p.y)
                    {
                        let wgt = look.table_pattern.weight(p.x, p.y) as f32;
                        let c = mix(table[0], table[1], wgt);
                        canvas.rgb[i] = c.map(|v| v * table_shade);
                        canvas.inv_depth[i] = (1.0 / camera_depth_m(camera, &p)) as f32;
                        hit = true;
                    }
                }
                if !hit {
                    canvas.rgb[i] = backdrop_linear(look, back, &dir);
                }
            }
        }
        for (o, (mesh, pose)) in meta.objects.iter().zip(meshes.iter().zip(object_poses)) {
            let world_from_obj = pose.world_from_object_center(o.shape.height_m());
            draw_mesh(
                &mut canvas,
                camera,
                mesh,
                &world_from_obj,
                srgb_to_linear(o.color),
                &light,
            );
        }
        let robot = &self.embodiment.robot;
        let link_poses = robot.link_poses(q);
        for (li, (link, pose)) in robot.links.iter().zip(&link_poses).enumerate() {
            if let Some(mesh) = &link.mesh {
                let color = srgb_to_linear(LINK_COLORS[li % LINK_COLORS.len()]);
                draw_mesh(&mut canvas, camera, mesh, pose, color, &light);
            }
        }
        for px in &mut canvas.rgb {
            *px = linear_to_srgb(*px);
        }
        canvas.to_rgb8()
    }
}
