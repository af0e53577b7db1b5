//! The planner's view of a world model: action sequences in, predicted
//! observations out, plus the latent encoder used for goal distances.

use crate::error::{check_finite, PlanError, Result};
use crate::goal_latent::{pyramid_latent, GoalLatent};
use crate::{EeAction, Observation};
use bridgev2w_embodiment::actions::{actions_to_joints, Trajectory};
use bridgev2w_embodiment::camera::Camera;
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_embodiment::kinematics::{pose_from_xyz_rpy, xyz_rpy_from_pose, IkOptions};
use bridgev2w_embodiment::masks::render_trajectory_labels;
use bridgev2w_io::frame::RgbFrame;
use bridgev2w_world_model::pipeline::{PredictOptions, WorldModel};
use bridgev2w_world_model::video::MaskVideo;
use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use rayon::prelude::*;

/// An action-conditioned model as planners and policy evaluation use it.
pub trait ActionWorldModel {
    /// Frames per predicted clip (frame 0 is the start frame, so a clip
    /// holds `clip_frames - 1` actions).
    fn clip_frames(&self) -> usize;

    /// `(height, width)` of its images.
    fn resolution(&self) -> (usize, usize);

    /// For each sequence of end-effector actions (one per clip frame after
    /// the first, at most `clip_frames - 1`; shorter ones are padded by
    /// repeating the last action), the predicted observation at the clip's
    /// last frame. All sequences go through the model as one batch.
    fn rollout_batch(
        &self,
        start: &Observation,
        sequences: &[Vec<EeAction>],
    ) -> Result<Vec<Observation>>;

    /// A latent code of an image for goal distances.
    fn encode(&self, image: &RgbFrame) -> Result<Vec<f32>>;
}

impl<T: ActionWorldModel + ?Sized> ActionWorldModel for &T {
    fn clip_frames(&self) -> usize {
        (**self).clip_frames()
    }
    fn resolution(&self) -> (usize, usize) {
        (**self).resolution()
    }
    fn rollout_batch(
        &self,
        start: &Observation,
        sequences: &[Vec<EeAction>],
    ) -> Result<Vec<Observation>> {
        (**self).rollout_batch(start, sequences)
    }
    fn encode(&self, image: &RgbFrame) -> Result<Vec<f32>> {
        (**self).encode(image)
    }
}

/// Pads `actions` to the `clip_frames - 1` action frames of a clip by
/// repeating the last action (the paper pads shorter VLA chunks this way).
pub fn pad_to_clip(actions: &[EeAction], clip_frames: usize) -> Result<Vec<EeAction>> {
    let want = clip_frames.saturating_sub(1);
    let Some(last) = actions.last() else {
        return Err(PlanError::Invalid("an empty action sequence".into()));
    };
    if actions.len() > want {
        return Err(PlanError::ClipTooShort {
            actions: actions.len(),
            frames_per_action: 1,
            clip_frames,
        });
    }
    let mut out = actions.to_vec();
    out.resize(want, *last);
    Ok(out)
}

/// Mean L1 distance `|u - v|_1 / d` between two latents.
pub fn latent_l1(u: &[f32], v: &[f32]) -> Result<f64> {
    if u.len() != v.len() || u.is_empty() {
        return Err(PlanError::Invalid(format!(
            "latents of {} and {} values cannot be compared",
            u.len(),
            v.len()
        )));
    }
    let sum: f64 = u.iter().zip(v).map(|(a, b)| f64::from((a - b).abs())).sum();
    Ok(sum / u.len() as f64)
}

/// Checks that an image has the model's resolution.
pub fn check_image_size(image: &RgbFrame, (h, w): (usize, usize)) -> Result<()> {
    if (image.height, image.width) != (h, w) || image.rgb.len() != h * w * 3 {
        return Err(PlanError::GoalImageSize {
            got_h: image.height,
            got_w: image.width,
            want_h: h,
            want_w: w,
        });
    }
    Ok(())
}

/// `world_from_tcp` of an action.
pub fn world_from_tcp(a: &EeAction) -> Isometry3<f64> {
    pose_from_xyz_rpy([a[0], a[1], a[2], a[3], a[4], a[5]])
}

/// Applies a pose increment: the translation is added in the world frame,
/// the rotation increment (roll, pitch, yaw) is applied in the world frame
/// (`world_from_tcp' = R(d) * world_from_tcp`).
pub fn apply_increment(a: &EeAction, inc: &[f64; 6], gripper: f64) -> EeAction {
    let p = world_from_tcp(a);
    let d = UnitQuaternion::from_euler_angles(inc[3], inc[4], inc[5]);
    let t = p.translation.vector + nalgebra::Vector3::new(inc[0], inc[1], inc[2]);
    let next = Isometry3::from_parts(Translation3::from(t), d * p.rotation);
    let v = xyz_rpy_from_pose(&next);
    [v[0], v[1], v[2], v[3], v[4], v[5], gripper]
}

/// An axis-aligned box (world frame) that planned end-effector positions
/// are kept in: the robot's safe workspace (above the table, inside its
/// edges, no higher than a ceiling). Without it, pixel-space objectives
/// have a degenerate optimum that a real planner must exclude: moving the
/// arm out of the camera's view removes its pixels from the difference to
/// the goal image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Workspace {
    /// Lower corner `[x, y, z]` (metres).
    pub min_m: [f64; 3],
    /// Upper corner `[x, y, z]` (metres).
    pub max_m: [f64; 3],
}

impl Workspace {
    /// Checks that the corners are finite and ordered.
    pub fn validate(&self) -> Result<()> {
        let ok = (0..3).all(|i| {
            self.min_m[i].is_finite() && self.max_m[i].is_finite() && self.min_m[i] <= self.max_m[i]
        });
        if ok {
            Ok(())
        } else {
            Err(PlanError::Invalid(format!(
                "workspace min {:?} / max {:?}: expected finite corners with min <= max",
                self.min_m, self.max_m
            )))
        }
    }

    /// The action with its position clamped into the box (orientation and
    /// gripper unchanged).
    pub fn clamp(&self, a: &EeAction) -> EeAction {
        let mut out = *a;
        for (i, v) in out.iter_mut().take(3).enumerate() {
            *v = v.clamp(self.min_m[i], self.max_m[i]);
        }
        out
    }
}

/// Keeps the end effector inside the camera's view: a goal image says
/// nothing about a gripper the camera cannot see, and a distance between
/// images can prefer a gripper out of view to one at the wrong place (the
/// planner's trace showed searches leaving the top of the image). The TCP
/// must project at least `margin_px` pixels inside the image.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewLimit {
    /// The calibrated camera of the observations.
    pub camera: Camera,
    /// Margin inside the image's edges (pixels).
    pub margin_px: f64,
}

impl ViewLimit {
    /// Checks that the margin is finite and leaves some of the image.
    pub fn validate(&self) -> Result<()> {
        let k = &self.camera.intrinsics;
        let half = f64::from(k.width.min(k.height)) / 2.0;
        if self.margin_px.is_finite() && (0.0..half).contains(&self.margin_px) {
            Ok(())
        } else {
            Err(PlanError::input(
                "view margin",
                format!(
                    "{} px: expected at least 0 and less than half the image's smaller side ({half} px)",
                    self.margin_px
                ),
            ))
        }
    }

    /// How far (pixels) the TCP of `a` projects outside the image shrunk
    /// by the margin: 0 inside, infinite behind the camera.
    pub fn outside_px(&self, a: &EeAction) -> f64 {
        let k = &self.camera.intrinsics;
        let Some(p) = self
            .camera
            .project(&nalgebra::Point3::new(a[0], a[1], a[2]))
        else {
            return f64::INFINITY;
        };
        let m = self.margin_px;
        let dx = (m - p.x).max(p.x - (f64::from(k.width) - m)).max(0.0);
        let dy = (m - p.y).max(p.y - (f64::from(k.height) - m)).max(0.0);
        dx.hypot(dy)
    }

    /// `to` if its TCP is in view (or no farther out than `from`'s);
    /// otherwise the point on the way from `from` to `to` (position only)
    /// where the TCP reaches the view's edge (bisection). Along a straight
    /// move the distance outside the view is convex, so the points no
    /// farther out than `from` are an interval that starts at `from`.
    pub fn constrain(&self, from: &EeAction, to: &EeAction) -> EeAction {
        let limit = self.outside_px(from).max(0.0);
        if self.outside_px(to) <= limit {
            return *to;
        }
        let at = |t: f64| {
            let mut a = *to;
            for i in 0..3 {
                a[i] = from[i] + t * (to[i] - from[i]);
            }
            a
        };
        let (mut lo, mut hi) = (0.0, 1.0);
        for _ in 0..30 {
            let mid = 0.5 * (lo + hi);
            if self.outside_px(&at(mid)) <= limit {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        at(lo)
    }
}

/// Expands waypoints into clip frames: `frames_per_action` frames per
/// waypoint, interpolating the pose (linear translation, slerp rotation)
/// from the previous waypoint (the first from `start`), the gripper at the
/// waypoint's command.
pub fn expand_waypoints(
    start: &EeAction,
    waypoints: &[EeAction],
    frames_per_action: usize,
) -> Vec<EeAction> {
    let mut out = Vec::with_capacity(waypoints.len() * frames_per_action);
    let mut prev = world_from_tcp(start);
    for w in waypoints {
        let next = world_from_tcp(w);
        for f in 1..=frames_per_action {
            let s = f as f64 / frames_per_action as f64;
            let t = prev.translation.vector.lerp(&next.translation.vector, s);
            let r = prev.rotation.slerp(&next.rotation, s);
            let v = xyz_rpy_from_pose(&Isometry3::from_parts(Translation3::from(t), r));
            out.push([v[0], v[1], v[2], v[3], v[4], v[5], w[6]]);
        }
        prev = next;
    }
    out
}

/// Full action rows for the embodiment: the acting arm's action at its 7
/// columns, the other arms holding `hold` (7 values per arm, full width).
pub fn full_rows(actions: &[EeAction], arm: usize, hold: &[f64]) -> Vec<Vec<f64>> {
    actions
        .iter()
        .map(|a| {
            let mut row = hold.to_vec();
            row[7 * arm..7 * arm + 7].copy_from_slice(a);
            row
        })
        .collect()
}

/// Any [`WorldModel`] as an [`ActionWorldModel`]: actions -> IK (warm-started
/// from the start joints) -> embodiment masks from the model's camera ->
/// one `predict_batch` call for all sequences.
pub struct MaskConditioned<'m, M: ?Sized> {
    /// The world model.
    pub model: &'m M,
    /// The robot.
    pub embodiment: Embodiment,
    /// The acting arm.
    pub arm: usize,
    /// The camera of the model's images (intrinsics at the model's resolution).
    pub camera: Camera,
    /// Full-width action row the other arms hold.
    pub hold: Vec<f64>,
    /// Sampling options.
    pub predict: PredictOptions,
    /// IK settings.
    pub ik: IkOptions,
    /// The latent of goal distances ([`ActionWorldModel::encode`]).
    pub goal_latent: GoalLatent,
}

impl<M: ?Sized> std::fmt::Debug for MaskConditioned<'_, M> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MaskConditioned")
            .field("arm", &self.arm)
            .field("predict", &self.predict)
            .field("goal_latent", &self.goal_latent)
            .finish_non_exhaustive()
    }
}

impl<'m, M: WorldModel + ?Sized> MaskConditioned<'m, M> {
    /// Wraps `model`; the camera must be at the model's resolution.
    pub fn new(
        model: &'m M,
        embodiment: Embodiment,
        arm: usize,
        camera: Camera,
        hold: Vec<f64>,
        predict: PredictOptions,
    ) -> Result<Self> {
        let (h, w) = model.resolution();
        let (ch, cw) = (
            camera.intrinsics.height as usize,
            camera.intrinsics.width as usize,
        );
        if (ch, cw) != (h, w) {
            return Err(PlanError::Invalid(format!(
                "camera is {ch}x{cw} (HxW) but the model works at {h}x{w}"
            )));
        }
        if arm >= embodiment.end_effectors.len() || hold.len() != 7 * embodiment.end_effectors.len()
        {
            return Err(PlanError::Invalid(format!(
                "arm {arm} / hold row of {} values do not fit {} end effector(s)",
                hold.len(),
                embodiment.end_effectors.len()
            )));
        }
        Ok(Self {
            model,
            embodiment,
            arm,
            camera,
            hold,
            predict,
            ik: IkOptions {
                restarts: 2,
                ..IkOptions::default()
            },
            goal_latent: GoalLatent::Model,
        })
    }
}

impl<M: ?Sized> MaskConditioned<'_, M> {
    /// The masks `[T, H, W]` of an action sequence from `start_joints` (frame
    /// 0 at the start joints), and the joints of the last frame.
    pub fn masks(
        &self,
        start_joints: &[f64],
        actions: &[EeAction],
    ) -> Result<(MaskVideo, Vec<f64>)> {
        let traj = Trajectory::new("planned actions", full_rows(actions, self.arm, &self.hold))?;
        let (joints, _) = actions_to_joints(
            &self.embodiment.robot,
            &self.embodiment.end_effectors,
            &traj,
            start_joints,
            &self.ik,
            true,
        )?;
        let mut all = Vec::with_capacity(joints.len() + 1);
        all.push(start_joints.to_vec());
        all.extend(joints);
        let labels = render_trajectory_labels(&self.embodiment.robot, &self.camera, &all, &|| {});
        let (h, w) = (
            self.camera.intrinsics.height as usize,
            self.camera.intrinsics.width as usize,
        );
        // Link labels (at most 255): the binary coding reads them as the
        // silhouette, `links` as they are.
        let data: Vec<u8> = labels.iter().flatten().map(|&l| l.min(255) as u8).collect();
        let last = all.pop().unwrap_or_default();
        Ok((
            MaskVideo {
                frames: labels.len(),
                height: h,
                width: w,
                data,
            },
            last,
        ))
    }
}

impl<M: WorldModel + ?Sized> ActionWorldModel for MaskConditioned<'_, M> {
    fn clip_frames(&self) -> usize {
        self.model.clip_frames()
    }

    fn resolution(&self) -> (usize, usize) {
        self.model.resolution()
    }

    fn rollout_batch(
        &self,
        start: &Observation,
        sequences: &[Vec<EeAction>],
    ) -> Result<Vec<Observation>> {
        check_image_size(&start.image, self.resolution())?;
        let clip = self.clip_frames();
        // Mask rendering in parallel; the model itself need not be Sync.
        let renderer = MaskConditioned::<()> {
            model: &(),
            embodiment: self.embodiment.clone(),
            arm: self.arm,
            camera: self.camera.clone(),
            hold: self.hold.clone(),
            predict: self.predict.clone(),
            ik: self.ik.clone(),
            goal_latent: self.goal_latent,
        };
        let prepared: Vec<(Vec<EeAction>, MaskVideo, Vec<f64>)> = sequences
            .par_iter()
            .map(|seq| {
                check_finite("action sequence", seq)?;
                let padded = pad_to_clip(seq, clip)?;
                let (masks, last) = renderer.masks(&start.joints, &padded)?;
                Ok((padded, masks, last))
            })
            .collect::<Result<_>>()?;
        let frames = vec![start.image.clone(); prepared.len()];
        let masks: Vec<MaskVideo> = prepared.iter().map(|p| p.1.clone()).collect();
        let videos = self.model.predict_batch(&frames, &masks, &self.predict)?;
        videos
            .into_iter()
            .zip(prepared)
            .map(|(v, (padded, _, joints))| {
                let image = v
                    .frame(v.frames.saturating_sub(1))
                    .ok_or_else(|| PlanError::Invalid("the model predicted no frames".into()))?;
                Ok(Observation {
                    image,
                    joints,
                    ee: padded.last().copied().unwrap_or(start.ee),
                    scene: None,
                })
            })
            .collect()
    }

    fn encode(&self, image: &RgbFrame) -> Result<Vec<f32>> {
        match self.goal_latent {
            GoalLatent::Model => Ok(self.model.encode_image(image)?),
            GoalLatent::Pyramid => {
                check_image_size(image, self.resolution())?;
                Ok(pyramid_latent(image))
            }
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn padding_repeats_the_last_action_to_the_clip() {
        let a = [[1.0; 7], [2.0; 7]];
        let p = pad_to_clip(&a, 5).unwrap();
        assert_eq!(p, vec![[1.0; 7], [2.0; 7], [2.0; 7], [2.0; 7]]);
        assert_eq!(pad_to_clip(&a, 3).unwrap(), a.to_vec());
        assert!(matches!(
            pad_to_clip(&a, 2),
            Err(PlanError::ClipTooShort { .. })
        ));
        assert!(pad_to_clip(&[], 5).is_err());
    }

    #[test]
    fn workspace_clamps_positions_only_and_rejects_bad_boxes() {
        let w = Workspace {
            min_m: [0.0, -0.5, 0.02],
            max_m: [0.8, 0.5, 0.5],
        };
        w.validate().unwrap();
        let a = [1.2, -0.7, 0.3, 0.1, 0.2, 0.3, 1.0];
        assert_eq!(w.clamp(&a), [0.8, -0.5, 0.3, 0.1, 0.2, 0.3, 1.0]);
        let inside = [0.4, 0.0, 0.1, 3.0, 0.0, 0.0, 0.0];
        assert_eq!(w.clamp(&inside), inside);
        let flipped = Workspace {
            min_m: [0.0, 0.6, 0.0],
            ..w
        };
        assert!(flipped.validate().is_err());
        let nan = Workspace {
            max_m: [f64::NAN, 0.5, 0.5],
            ..w
        };
        assert!(nan.validate().is_err());
    }

    /// A camera 1 m above the origin looking down, 100x80 pixels.
    fn down_camera() -> Camera {
        let k = bridgev2w_embodiment::camera::Intrinsics::centered(100.0, 100, 80);
        Camera::look_at(
            k,
            nalgebra::Point3::new(0.0, 0.0, 1.0),
            nalgebra::Point3::origin(),
            nalgebra::Vector3::new(0.0, 1.0, 0.0),
        )
        .unwrap()
    }

    #[test]
    fn the_view_limit_stops_a_move_at_the_edge_of_the_view() {
        let v = ViewLimit {
            camera: down_camera(),
            margin_px: 10.0,
        };
        v.validate().unwrap();
        // At z = 0 (1 m away, f = 100 px, centre 49.5 px) 1 px is 1 cm:
        // x = 0.405 m projects onto the margin's edge at 90 px.
        let from = [0.0, 0.0, 0.0, 0.1, 0.2, 0.3, 1.0];
        let inside = [0.3, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        assert_eq!(v.outside_px(&inside), 0.0);
        assert_eq!(v.constrain(&from, &inside), inside);
        let out = [0.6, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        assert!(
            (v.outside_px(&out) - 19.5).abs() < 1e-6,
            "{}",
            v.outside_px(&out)
        );
        let c = v.constrain(&from, &out);
        assert!((c[0] - 0.405).abs() < 1e-6, "{c:?}");
        assert_eq!(c[3..], out[3..], "orientation and gripper are the target's");
        assert!(v.outside_px(&c) < 1e-6);
        // Behind the camera: infinitely far out, never reached.
        assert!(v
            .outside_px(&[0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 0.0])
            .is_infinite());
        // Starting outside, a move that goes no farther out is kept, one
        // that goes farther out stops where it started to.
        let far = [0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let back = [0.45, 0.1, 0.0, 0.0, 0.0, 0.0, 0.0];
        assert_eq!(v.constrain(&far, &back), back);
        let c = v.constrain(&far, &[0.7, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
        assert!((c[0] - 0.5).abs() < 1e-6, "{c:?}");
        for bad in [-1.0, 40.0, f64::NAN] {
            let e = ViewLimit {
                margin_px: bad,
                ..v.clone()
            }
            .validate()
            .unwrap_err()
            .to_string();
            assert!(e.contains("view margin") && e.contains("40 px"), "{e}");
        }
    }

    #[test]
    fn increments_and_interpolation() {
        let a = [0.5, 0.0, 0.3, std::f64::consts::PI, 0.0, 0.0, 0.0];
        let b = apply_increment(&a, &[0.1, -0.2, 0.0, 0.0, 0.0, 0.5], 1.0);
        assert!((b[0] - 0.6).abs() < 1e-12 && (b[1] + 0.2).abs() < 1e-12);
        let (_, rot) =
            bridgev2w_embodiment::kinematics::pose_error(&world_from_tcp(&a), &world_from_tcp(&b));
        assert!((rot - 0.5).abs() < 1e-9, "{rot}");
        assert_eq!(b[6], 1.0);
        let f = expand_waypoints(&a, &[b], 2);
        assert_eq!(f.len(), 2);
        assert!((f[0][0] - 0.55).abs() < 1e-12);
        assert_eq!(f[1][..3], b[..3]);
    }

    #[test]
    fn latent_distance_is_mean_l1() {
        assert_eq!(latent_l1(&[0.0, 1.0], &[1.0, 1.0]).unwrap(), 0.5);
        assert!(latent_l1(&[0.0], &[1.0, 1.0]).is_err());
    }
}
