//! The scene of an episode: split definitions (camera regions, palettes),
//! the table placement, procedural textures, the movable objects, and the
//! per-episode sampling of camera, look and object layout.

use super::{EpisodeMeta, Split, SynthError, Task, World};
use bridgev2w_embodiment::camera::{Camera, Intrinsics};
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_embodiment::mesh::TriMesh;
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector2, Vector3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// A procedural texture.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum Pattern {
    /// One colour.
    Solid,
    /// Two-colour checkerboard with squares of `period` (metres on the table, radians on the background).
    Checker {
        /// Square size.
        period: f64,
    },
    /// Two-colour stripes of `period` at `angle_rad`.
    Stripes {
        /// Stripe period.
        period: f64,
        /// Stripe direction.
        angle_rad: f64,
    },
    /// Smooth value noise of feature size `period`, blending the two colours.
    Noise {
        /// Feature size.
        period: f64,
        /// Noise seed.
        seed: u32,
    },
    /// Dots of the second colour on the first.
    Dots {
        /// Dot spacing.
        period: f64,
    },
}

impl Pattern {
    /// Blend weight of the second colour at `(x, y)`, in `[0, 1]`.
    pub fn weight(&self, x: f64, y: f64) -> f64 {
        match *self {
            Pattern::Solid => 0.0,
            Pattern::Checker { period } => {
                let (i, j) = ((x / period).floor() as i64, (y / period).floor() as i64);
                ((i + j).rem_euclid(2)) as f64
            }
            Pattern::Stripes { period, angle_rad } => {
                let s = x * angle_rad.cos() + y * angle_rad.sin();
                if (s / period).rem_euclid(1.0) < 0.5 {
                    0.0
                } else {
                    1.0
                }
            }
            Pattern::Noise { period, seed } => value_noise(x / period, y / period, seed),
            Pattern::Dots { period } => {
                let fx = (x / period).rem_euclid(1.0) - 0.5;
                let fy = (y / period).rem_euclid(1.0) - 0.5;
                if fx * fx + fy * fy < 0.09 {
                    1.0
                } else {
                    0.0
                }
            }
        }
    }

    /// The pattern family name (palettes list allowed families).
    pub fn family(&self) -> &'static str {
        match self {
            Pattern::Solid => "solid",
            Pattern::Checker { .. } => "checker",
            Pattern::Stripes { .. } => "stripes",
            Pattern::Noise { .. } => "noise",
            Pattern::Dots { .. } => "dots",
        }
    }
}

fn hash2(i: i64, j: i64, seed: u32) -> f64 {
    let mut h = (i as u64).wrapping_mul(bridgev2w_io::seed::GOLDEN_GAMMA)
        ^ (j as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
        ^ u64::from(seed).wrapping_mul(0x1656_67B1_9E37_79F9);
    h ^= h >> 31;
    h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    h ^= h >> 29;
    (h >> 11) as f64 / (1u64 << 53) as f64
}

fn value_noise(x: f64, y: f64, seed: u32) -> f64 {
    let (i, j) = (x.floor(), y.floor());
    let (fx, fy) = (x - i, y - j);
    let (sx, sy) = (fx * fx * (3.0 - 2.0 * fx), fy * fy * (3.0 - 2.0 * fy));
    let (i, j) = (i as i64, j as i64);
    let a = hash2(i, j, seed);
    let b = hash2(i + 1, j, seed);
    let c = hash2(i, j + 1, seed);
    let d = hash2(i + 1, j + 1, seed);
    let top = a + (b - a) * sx;
    let bottom = c + (d - c) * sx;
    top + (bottom - top) * sy
}

/// Camera sampling region: the camera sits at `distance` from the look-at
/// point (the workspace centre), at `azimuth` around the world z axis
/// (0 = in front of the robot, on the +x side, looking back at it) and
/// `elevation` above the table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraRegion {
    /// Allowed azimuth intervals (degrees), union.
    pub azimuth_deg: Vec<[f64; 2]>,
    /// Elevation interval (degrees).
    pub elevation_deg: [f64; 2],
    /// Distance interval (metres).
    pub distance_m: [f64; 2],
    /// Focal length as a fraction of the image width.
    pub focal_over_width: [f64; 2],
    /// Look-at jitter around the workspace centre (metres, per axis).
    pub target_jitter_m: f64,
}

impl CameraRegion {
    /// Whether `azimuth_deg` lies in the region.
    pub fn contains_azimuth(&self, azimuth_deg: f64) -> bool {
        self.azimuth_deg
            .iter()
            .any(|r| (r[0]..=r[1]).contains(&azimuth_deg))
    }
}

/// Scene appearance and object-layout palette of a split.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScenePalette {
    /// Palette name.
    pub name: String,
    /// Table colours (sRGB 0..255), pairs for two-colour patterns.
    pub table_colors: Vec<[[u8; 3]; 2]>,
    /// Table pattern families.
    pub table_patterns: Vec<String>,
    /// Background colours, pairs.
    pub background_colors: Vec<[[u8; 3]; 2]>,
    /// Background pattern families.
    pub background_patterns: Vec<String>,
    /// Object colours.
    pub object_colors: Vec<[u8; 3]>,
    /// Object layout region relative to the workspace centre: `[x_min, x_max]` (metres).
    pub layout_dx_m: [f64; 2],
    /// `[y_min, y_max]` relative to the workspace centre (metres).
    pub layout_dy_m: [f64; 2],
}

/// The definition of one split (written into the dataset metadata).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SplitSpec {
    /// The split.
    pub split: Split,
    /// Camera region.
    pub camera: CameraRegion,
    /// Scene palette.
    pub scene: ScenePalette,
}

fn training_camera() -> CameraRegion {
    CameraRegion {
        azimuth_deg: vec![[-75.0, 35.0]],
        elevation_deg: [25.0, 50.0],
        distance_m: [1.0, 1.35],
        focal_over_width: [0.85, 1.1],
        target_jitter_m: 0.04,
    }
}

fn training_palette() -> ScenePalette {
    ScenePalette {
        name: "train".into(),
        table_colors: vec![
            [[150, 111, 72], [120, 86, 55]],
            [[180, 180, 176], [140, 140, 138]],
            [[196, 170, 128], [170, 140, 100]],
            [[90, 90, 96], [70, 70, 76]],
        ],
        table_patterns: vec!["solid".into(), "checker".into(), "stripes".into()],
        background_colors: vec![
            [[210, 205, 195], [185, 180, 170]],
            [[150, 170, 190], [120, 140, 160]],
            [[200, 190, 160], [170, 160, 130]],
        ],
        background_patterns: vec!["solid".into(), "stripes".into()],
        object_colors: vec![[200, 40, 40], [40, 160, 60], [40, 80, 200], [230, 200, 40]],
        layout_dx_m: [-0.10, 0.10],
        layout_dy_m: [-0.18, 0.06],
    }
}

fn unseen_palette() -> ScenePalette {
    ScenePalette {
        name: "unseen_scene".into(),
        table_colors: vec![
            [[60, 110, 70], [40, 85, 50]],
            [[70, 80, 150], [50, 60, 120]],
            [[140, 70, 120], [110, 50, 95]],
        ],
        table_patterns: vec!["noise".into(), "dots".into()],
        background_colors: vec![[[90, 50, 40], [60, 35, 30]], [[40, 90, 90], [25, 65, 65]]],
        background_patterns: vec!["noise".into(), "checker".into()],
        object_colors: vec![[240, 120, 20], [150, 60, 200], [20, 200, 200]],
        layout_dx_m: [-0.10, 0.10],
        layout_dy_m: [0.09, 0.20],
    }
}

/// The four split definitions. Train and test share distributions;
/// `unseen_camera` samples azimuths in a region disjoint from training's;
/// `unseen_scene` uses a palette (colours, patterns) and object-layout region
/// disjoint from training's.
pub fn split_specs() -> Vec<SplitSpec> {
    Split::ALL
        .into_iter()
        .map(|split| {
            let mut camera = training_camera();
            let mut scene = training_palette();
            match split {
                Split::UnseenCamera => camera.azimuth_deg = vec![[50.0, 85.0]],
                Split::UnseenScene => scene = unseen_palette(),
                Split::Train | Split::Test => {}
            }
            SplitSpec {
                split,
                camera,
                scene,
            }
        })
        .collect()
}

/// Per-robot placement of the table and workspace, derived from the home
/// end-effector poses.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneFrame {
    /// Height of the table top (world z, metres).
    pub table_z_m: f64,
    /// Table extent in x (metres).
    pub table_x_m: [f64; 2],
    /// Table extent in y (metres).
    pub table_y_m: [f64; 2],
    /// Workspace centre on the table (world frame, metres).
    pub workspace_center_m: [f64; 3],
}

impl SceneFrame {
    /// The scene frame for an embodiment: the workspace centre lies in front
    /// of the home end effector(s); the table top sits below them.
    pub fn for_embodiment(e: &Embodiment) -> SceneFrame {
        let poses = e.robot.link_poses(&e.home);
        let n = e.end_effectors.len().max(1) as f64;
        let mut c = Vector3::zeros();
        for ee in &e.end_effectors {
            c += poses[ee.link].translation.vector;
        }
        c /= n;
        // A single arm stands on the table (base at z = 0); a dual-arm
        // torso (arms hanging at home) faces a table at waist height in
        // front of it.
        let dual = e.end_effectors.len() > 1;
        let table_z_m = if dual { c.z + 0.275 } else { 0.0 };
        let cx = if dual { c.x + 0.38 } else { c.x + 0.15 };
        let x_min = if dual { cx - 0.2 } else { cx - 0.55 };
        SceneFrame {
            table_z_m,
            table_x_m: [x_min, cx + 0.45],
            table_y_m: [c.y - 0.75, c.y + 0.75],
            workspace_center_m: [cx, c.y, table_z_m],
        }
    }
}

/// A movable object's shape.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum Shape {
    /// A box with full side lengths (metres).
    Box {
        /// `[x, y, z]` sizes.
        size_m: [f64; 3],
    },
    /// An upright cylinder.
    Cylinder {
        /// Radius.
        radius_m: f64,
        /// Height.
        height_m: f64,
    },
}

impl Shape {
    /// Height (metres).
    pub fn height_m(&self) -> f64 {
        match *self {
            Shape::Box { size_m } => size_m[2],
            Shape::Cylinder { height_m, .. } => height_m,
        }
    }

    /// Radius of the circular footprint used by the contact rules (metres).
    pub fn footprint_radius_m(&self) -> f64 {
        match *self {
            Shape::Box { size_m } => 0.5 * size_m[0].max(size_m[1]),
            Shape::Cylinder { radius_m, .. } => radius_m,
        }
    }

    /// The shape's triangle mesh, centred on its origin.
    pub fn mesh(&self) -> TriMesh {
        match *self {
            Shape::Box { size_m } => {
                TriMesh::cuboid([size_m[0] as f32, size_m[1] as f32, size_m[2] as f32])
            }
            Shape::Cylinder { radius_m, height_m } => {
                TriMesh::cylinder(radius_m as f32, height_m as f32, 20)
            }
        }
    }
}

/// A movable object's pose: bottom centre on the table and yaw.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ObjectPose {
    /// Bottom-centre position (world frame, metres).
    pub position_m: [f64; 3],
    /// Rotation about world z (radians).
    pub yaw_rad: f64,
}

impl ObjectPose {
    pub(super) fn world_from_object_center(&self, height_m: f64) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(
                self.position_m[0],
                self.position_m[1],
                self.position_m[2] + 0.5 * height_m,
            ),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), self.yaw_rad),
        )
    }
}

/// A movable object of an episode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneObject {
    /// Shape.
    pub shape: Shape,
    /// sRGB colour.
    pub color: [u8; 3],
    /// Initial pose.
    pub initial: ObjectPose,
}

/// The appearance chosen for one episode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneLook {
    /// Table colour pair.
    pub table_colors: [[u8; 3]; 2],
    /// Table pattern.
    pub table_pattern: Pattern,
    /// Background colour pair.
    pub background_colors: [[u8; 3]; 2],
    /// Background pattern.
    pub background_pattern: Pattern,
    /// Unit direction towards the light (world frame).
    pub to_light_world: [f64; 3],
}

fn jitter_color(rng: &mut ChaCha8Rng, c: [u8; 3]) -> [u8; 3] {
    c.map(|v| (f64::from(v) + rng.gen_range(-8.0..=8.0)).clamp(0.0, 255.0) as u8)
}

fn pick_pattern(rng: &mut ChaCha8Rng, families: &[String], scale: f64) -> Pattern {
    let f = families
        .get(rng.gen_range(0..families.len().max(1)))
        .map(String::as_str)
        .unwrap_or("solid");
    match f {
        "checker" => Pattern::Checker {
            period: scale * rng.gen_range(0.6..1.4),
        },
        "stripes" => Pattern::Stripes {
            period: scale * rng.gen_range(0.6..1.4),
            angle_rad: rng.gen_range(0.0..PI),
        },
        "noise" => Pattern::Noise {
            period: scale * rng.gen_range(0.5..1.5),
            seed: rng.gen(),
        },
        "dots" => Pattern::Dots {
            period: scale * rng.gen_range(0.6..1.4),
        },
        _ => Pattern::Solid,
    }
}

impl World {
    pub(super) fn sample(
        &self,
        split: Split,
        index: usize,
        task: Task,
        seed: u64,
        rng: &mut ChaCha8Rng,
    ) -> Result<(EpisodeMeta, Camera, Vec<Vec<f64>>), SynthError> {
        let spec = self.spec(split);
        let c = Vector3::from(self.frame.workspace_center_m);
        // Camera.
        let region = &spec.camera.azimuth_deg[rng.gen_range(0..spec.camera.azimuth_deg.len())];
        let az = rng.gen_range(region[0]..=region[1]);
        let el = rng.gen_range(spec.camera.elevation_deg[0]..=spec.camera.elevation_deg[1]);
        let dist = rng.gen_range(spec.camera.distance_m[0]..=spec.camera.distance_m[1]);
        let f = rng.gen_range(spec.camera.focal_over_width[0]..=spec.camera.focal_over_width[1]);
        let j = spec.camera.target_jitter_m;
        let target = Point3::new(
            c.x + rng.gen_range(-j..=j),
            c.y + rng.gen_range(-j..=j),
            c.z + 0.2 + rng.gen_range(-j..=j),
        );
        let (azr, elr) = (az.to_radians(), el.to_radians());
        let eye =
            target + dist * Vector3::new(elr.cos() * azr.cos(), elr.cos() * azr.sin(), elr.sin());
        let intrinsics = Intrinsics::centered(
            f * f64::from(self.config.width),
            self.config.width,
            self.config.height,
        );
        let camera = Camera::look_at(intrinsics, eye, target, Vector3::z())?;

        // Look.
        let pal = &spec.scene;
        let tc = pal.table_colors[rng.gen_range(0..pal.table_colors.len())];
        let bc = pal.background_colors[rng.gen_range(0..pal.background_colors.len())];
        let look = SceneLook {
            table_colors: [jitter_color(rng, tc[0]), jitter_color(rng, tc[1])],
            table_pattern: pick_pattern(rng, &pal.table_patterns, 0.08),
            background_colors: [jitter_color(rng, bc[0]), jitter_color(rng, bc[1])],
            background_pattern: pick_pattern(rng, &pal.background_patterns, 0.25),
            to_light_world: {
                let a: f64 = rng.gen_range(0.0..2.0 * PI);
                let e: f64 = rng.gen_range(0.9..1.3);
                [e.cos() * a.cos(), e.cos() * a.sin(), e.sin()]
            },
        };

        // Objects: 1..=3, non-overlapping, in the layout region.
        let n_obj = rng.gen_range(1..=3usize);
        let mut objects: Vec<SceneObject> = Vec::new();
        let mut tries = 0;
        while objects.len() < n_obj && tries < 200 {
            tries += 1;
            let shape = if rng.gen_bool(0.5) {
                Shape::Box {
                    size_m: [
                        rng.gen_range(0.035..0.05),
                        rng.gen_range(0.035..0.05),
                        rng.gen_range(0.04..0.07),
                    ],
                }
            } else {
                Shape::Cylinder {
                    radius_m: rng.gen_range(0.018..0.028),
                    height_m: rng.gen_range(0.045..0.08),
                }
            };
            let x = c.x + rng.gen_range(pal.layout_dx_m[0]..=pal.layout_dx_m[1]);
            let y = c.y + rng.gen_range(pal.layout_dy_m[0]..=pal.layout_dy_m[1]);
            let r = shape.footprint_radius_m();
            let clear = objects.iter().all(|o| {
                let d = Vector2::new(o.initial.position_m[0] - x, o.initial.position_m[1] - y);
                d.norm() > r + o.shape.footprint_radius_m() + 0.06
            });
            if !clear {
                continue;
            }
            let base = pal.object_colors[rng.gen_range(0..pal.object_colors.len())];
            objects.push(SceneObject {
                shape,
                color: jitter_color(rng, base),
                initial: ObjectPose {
                    position_m: [x, y, self.frame.table_z_m],
                    yaw_rad: rng.gen_range(-PI..PI),
                },
            });
        }

        // Reach target: a random point above the table.
        let reach = Vector3::new(
            c.x + rng.gen_range(-0.1..=0.1),
            c.y + rng.gen_range(-0.2..=0.2),
            self.frame.table_z_m + rng.gen_range(0.1..=0.18),
        );
        // Acting arm: the one whose home TCP is nearest the task's focus.
        let focus = match (task, objects.first()) {
            (Task::Reach, _) | (_, None) => reach.xy(),
            (_, Some(o)) => Vector2::new(o.initial.position_m[0], o.initial.position_m[1]),
        };
        let arm = (0..self.home_tcp.len())
            .min_by(|&a, &b| {
                let da = (self.home_tcp[a].translation.vector.xy() - focus).norm();
                let db = (self.home_tcp[b].translation.vector.xy() - focus).norm();
                da.total_cmp(&db)
            })
            .unwrap_or(0);

        let actions = self.script(task, arm, &objects, reach, rng);
        let meta = EpisodeMeta {
            split,
            index_in_split: index,
            task,
            seed,
            arm,
            camera_azimuth_deg: az,
            camera_elevation_deg: el,
            camera_distance_m: dist,
            look,
            objects,
            max_ik_residual_m: 0.0,
            perturbation: None,
            mujoco: None,
        };
        Ok((meta, camera, actions))
    }
}
