//! `bridgev2w._core`: the native half of the Python package (`python/`).
//! Arrays cross as bytes plus shapes; the Python half (`bridgev2w/__init__.py`)
//! checks dtypes and shapes, names the argument in a `ValueError`, and wraps
//! the results as numpy arrays. Rendering and inverse kinematics run with the
//! GIL released, on the embodiment crate's thread pool.

use bridgev2w_data::raw::convert::ConvertError;
use bridgev2w_data::raw::ctrl_world::SplitRule;
use bridgev2w_data::raw::request::ConvertRequest;
use bridgev2w_data::raw::RawError;
use bridgev2w_data::synth::{
    plan, write_dataset, Perturbation, SynthConfig, SynthError, Task, WriteDatasetError,
};
use bridgev2w_embodiment::actions::{actions_to_joints, check_joint_trajectory, Trajectory};
use bridgev2w_embodiment::camera::CameraTrack;
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_embodiment::kinematics::IkOptions;
use bridgev2w_embodiment::masks::{
    check_render_size, label_of_link, link_labels, render_track, MAX_RENDER_FRAMES,
};
use bridgev2w_embodiment::overlay::label_color;
use bridgev2w_embodiment::raster::RenderOutput;
use bridgev2w_embodiment::robot::LoadOptions;
use bridgev2w_io::frame::{u8_from_unit, RgbFrame};
use pyo3::create_exception;
use pyo3::exceptions::{PyException, PyFileExistsError, PyFileNotFoundError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyByteArray, PyDict};
use rayon::prelude::*;
use std::path::{Path, PathBuf};

mod calibrate;
mod camera;
mod data;
mod policy;
mod world_model;

use camera::{camera_err, Camera};
use world_model::WorldModel;

create_exception!(
    _core,
    Error,
    PyException,
    "An error of bridgev2w (bad robot, camera, actions, ...)."
);

fn err(e: impl std::fmt::Display) -> PyErr {
    Error::new_err(e.to_string())
}

/// Runs `f` (the work of `what`) so that a panic inside it, on this thread
/// or a rayon worker it waits for, is a `bridgev2w.Error` naming `what`
/// instead of pyo3's `PanicException` (a `BaseException` that `except
/// Exception` does not catch). Allocations are bounded before `f` runs
/// ([`bridgev2w_io::memory`]): a failed allocation would abort the
/// interpreter, which no exception can stop.
fn no_panic<T>(what: &str, f: impl FnOnce() -> PyResult<T>) -> PyResult<T> {
    bridgev2w_io::quiet_panic::catch_quiet(f)
        .unwrap_or_else(|panic| Err(Error::new_err(format!("{what}: internal error: {panic}"))))
}

/// A size beyond its maximum or the machine's memory as a `ValueError`.
fn size_err(e: bridgev2w_io::memory::MemoryError) -> PyErr {
    PyValueError::new_err(e.to_string())
}

/// A robot: its kinematic tree, link meshes and end effectors.
#[pyclass(module = "bridgev2w._core", frozen)]
struct Robot {
    inner: Embodiment,
}

#[pymethods]
impl Robot {
    /// A built-in robot (`franka`, `dual-arm`, `agibot-g1`, `franka-robotiq`; `bw.builtin_robots()`).
    #[new]
    fn new(name: &str) -> PyResult<Self> {
        Embodiment::builtin(name)
            .map(|inner| Self { inner })
            .map_err(err)
    }

    /// A robot from a URDF file; `mesh_paths` are searched for
    /// `package://` and relative meshes; `ee_links` (one per arm, action
    /// order) and `gripper_joints` enable end-effector actions.
    #[staticmethod]
    #[pyo3(signature = (path, mesh_paths = Vec::new(), ee_links = Vec::new(), gripper_joints = Vec::new()))]
    fn from_urdf(
        path: PathBuf,
        mesh_paths: Vec<PathBuf>,
        ee_links: Vec<String>,
        gripper_joints: Vec<String>,
    ) -> PyResult<Self> {
        if !path.is_file() {
            return Err(PyFileNotFoundError::new_err(format!(
                "{}: no such URDF file",
                path.display()
            )));
        }
        let options = LoadOptions {
            mesh_search_paths: mesh_paths,
            ..LoadOptions::default()
        };
        let text = path.to_string_lossy().into_owned();
        Embodiment::load(&text, &options, &ee_links, &gripper_joints)
            .map(|inner| Self { inner })
            .map_err(err)
    }

    /// The robot's name.
    #[getter]
    fn name(&self) -> String {
        self.inner.robot.name.clone()
    }

    /// The actuated joints, in the order joint arrays use.
    #[getter]
    fn joint_names(&self) -> Vec<String> {
        self.inner
            .robot
            .dof_names()
            .into_iter()
            .map(String::from)
            .collect()
    }

    /// Values per frame of end-effector actions (7 per arm).
    #[getter]
    fn action_dim(&self) -> usize {
        self.inner.action_dim()
    }

    /// End-effector actions (`[T][7 * arms]`) given as poses of `from_links`
    /// (one per arm) re-expressed as poses of `to_links` (rigidly attached:
    /// an arm's flange and its TCP), grippers copied.
    fn convert_action_links(
        &self,
        actions: Vec<Vec<f64>>,
        from_links: Vec<String>,
        to_links: Vec<String>,
    ) -> PyResult<Vec<Vec<f64>>> {
        self.inner
            .convert_action_links(&actions, &from_links, &to_links)
            .map_err(|e| PyValueError::new_err(e.to_string()))
    }

    /// The joints of `joints` (`[T][dof]`) outside their limits, one entry
    /// per joint: `(joint, frames, worst value, its frame, lower, upper)`.
    /// Rendering does not clamp them: a recorded state is drawn as recorded.
    fn limit_violations(
        &self,
        joints: Vec<Vec<f64>>,
    ) -> Vec<(String, usize, f64, usize, f64, f64)> {
        self.inner
            .robot
            .limit_violations(&joints, 1e-6)
            .into_iter()
            .map(|v| {
                (
                    v.joint,
                    v.count,
                    v.worst_value,
                    v.worst_frame,
                    v.limits.0,
                    v.limits.1,
                )
            })
            .collect()
    }

    /// The home configuration (the IK's first warm start).
    #[getter]
    fn home(&self) -> Vec<f64> {
        self.inner.home.clone()
    }

    /// `(label, link name)` of every link with geometry; labels are what
    /// `render(..., labels)` writes.
    fn link_labels(&self) -> Vec<(u16, String)> {
        link_labels(&self.inner.robot)
    }

    /// The visual mesh of every link with geometry, in the order of
    /// `link_labels`: `(link name, label, colour, vertices, triangles)`, the
    /// colour RGB8 as the overlays of `bridgev2w masks` draw the label, vertices
    /// `V * 3` little-endian f32 (metres, in the link frame), triangles
    /// `M * 3` little-endian u32 (vertex indices).
    #[allow(clippy::type_complexity)]
    fn link_meshes<'py>(
        &self,
        py: Python<'py>,
    ) -> Vec<(
        String,
        u16,
        [u8; 3],
        Bound<'py, PyByteArray>,
        Bound<'py, PyByteArray>,
    )> {
        self.inner
            .robot
            .links
            .iter()
            .enumerate()
            .filter_map(|(i, l)| l.mesh.as_ref().map(|m| (i, l, m)))
            .map(|(i, l, m)| {
                let vertices: Vec<u8> = m
                    .vertices
                    .iter()
                    .flat_map(|p| [p.x, p.y, p.z])
                    .flat_map(f32::to_le_bytes)
                    .collect();
                let triangles: Vec<u8> = m
                    .triangles
                    .iter()
                    .flatten()
                    .flat_map(|v| v.to_le_bytes())
                    .collect();
                let label = label_of_link(i);
                (
                    l.name.clone(),
                    label,
                    label_color(label).map(|c| (c * 255.0).round().clamp(0.0, 255.0) as u8),
                    PyByteArray::new(py, &vertices),
                    PyByteArray::new(py, &triangles),
                )
            })
            .collect()
    }

    /// Forward kinematics of a joint sequence (`[T][dof]`, checked as
    /// `render` checks it): `world_from_link` of every link with geometry
    /// (the order of `link_meshes`) at every frame, `T * L * 16` little-endian
    /// f64 (row-major 4x4 matrices). Frames run in parallel on the Rust
    /// thread pool with the GIL released.
    fn link_poses<'py>(
        &self,
        py: Python<'py>,
        joints: Vec<Vec<f64>>,
    ) -> PyResult<Bound<'py, PyByteArray>> {
        let r = &self.inner.robot;
        let joints = vec![joints];
        check_joints(r, &joints)?;
        let with_mesh: Vec<usize> = r
            .links
            .iter()
            .enumerate()
            .filter(|(_, l)| l.mesh.is_some())
            .map(|(i, _)| i)
            .collect();
        // Every link's pose per frame, then the returned bytes (128 each).
        let frames = joints[0].len();
        bridgev2w_io::memory::at_most("joints", frames as u64, MAX_RENDER_FRAMES as u64, "frames")
            .map_err(size_err)?;
        bridgev2w_io::memory::check_fits(
            &format!("the link poses of {frames} frames"),
            bridgev2w_io::memory::bytes(&[
                frames as u64,
                r.links.len() as u64 + with_mesh.len() as u64,
                128,
            ]),
            "pass fewer frames at a time",
        )
        .map_err(size_err)?;
        let bytes: Vec<u8> = py.detach(|| {
            no_panic("link_poses", || {
                let poses = r.trajectory_link_poses(&joints[0]);
                Ok(poses
                    .iter()
                    .flat_map(|frame| with_mesh.iter().map(move |&i| frame[i].to_homogeneous()))
                    // nalgebra stores column-major: transpose to write rows.
                    .flat_map(|m| m.transpose().as_slice().to_vec())
                    .flat_map(f64::to_le_bytes)
                    .collect())
            })
        })?;
        Ok(PyByteArray::new(py, &bytes))
    }

    /// Joint positions for a batch of end-effector action sequences
    /// (`[B][T][7 * arms]`), each warm-started from the home configuration
    /// and frame to frame, and a residual per frame and arm: `(frame, arm,
    /// position_error_m, rotation_error_rad, reached)`. The sequences are
    /// solved in parallel on the Rust thread pool, with the GIL released.
    /// Unreached targets are an error unless `allow_residual`.
    #[pyo3(signature = (actions, allow_residual = false))]
    #[allow(clippy::type_complexity)]
    fn solve_ik(
        &self,
        py: Python<'_>,
        actions: Vec<Vec<Vec<f64>>>,
        allow_residual: bool,
    ) -> PyResult<Vec<(Vec<Vec<f64>>, Vec<(usize, String, f64, f64, bool)>)>> {
        let batched = actions.len() > 1;
        let name = |b: usize| {
            if batched {
                format!("actions[{b}]")
            } else {
                "actions".to_string()
            }
        };
        let trajs = actions
            .into_iter()
            .enumerate()
            .map(|(b, a)| Trajectory::new(&name(b), a))
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        let e = &self.inner;
        let frames: usize = trajs.iter().map(Trajectory::len).sum();
        bridgev2w_io::memory::at_most("actions", frames as u64, MAX_RENDER_FRAMES as u64, "frames")
            .map_err(size_err)?;
        let solved = py.detach(|| {
            no_panic("solve_ik", || {
                Ok(trajs
                    .par_iter()
                    .map(|traj| {
                        actions_to_joints(
                            &e.robot,
                            &e.end_effectors,
                            traj,
                            &e.home,
                            &IkOptions::default(),
                            allow_residual,
                        )
                    })
                    .collect::<Vec<_>>())
            })
        })?;
        solved
            .into_iter()
            .enumerate()
            .map(|(b, r)| {
                let (q, residuals) = r.map_err(|e| {
                    if batched {
                        err(format!("{}: {e}", name(b)))
                    } else {
                        err(e)
                    }
                })?;
                let res = residuals
                    .into_iter()
                    .map(|r| {
                        (
                            r.frame,
                            r.arm,
                            r.position_error_m,
                            r.rotation_error_rad,
                            r.reached,
                        )
                    })
                    .collect();
                Ok((q, res))
            })
            .collect()
    }

    fn __repr__(&self) -> String {
        format!(
            "Robot({:?}, joints={}, action_dim={})",
            self.inner.robot.name,
            self.inner.robot.dof_names().len(),
            self.inner.action_dim()
        )
    }
}

/// Checks a batch of joint sequences (`[B][T][dof]`) as `bridgev2w masks
/// --joints` does: `dof` finite values per frame (limits are reported by
/// `Robot.limit_violations`, not enforced); a
/// `ValueError` naming `joints` (`joints[b]` in a batch), the frame and joint.
fn check_joints(r: &bridgev2w_embodiment::robot::Robot, joints: &[Vec<Vec<f64>>]) -> PyResult<()> {
    let dof = r.dof_names().len();
    let batched = joints.len() > 1;
    for (b, seq) in joints.iter().enumerate() {
        let name = if batched {
            format!("joints[{b}]")
        } else {
            "joints".to_string()
        };
        if let Some((i, q)) = seq.iter().enumerate().find(|(_, q)| q.len() != dof) {
            return Err(PyValueError::new_err(format!(
                "{name}: frame {i} has {} values but robot {:?} has {dof} actuated joints ({}); for end-effector poses use actions=",
                q.len(),
                r.name,
                r.dof_names().join(", ")
            )));
        }
        // As `bridgev2w masks --joints`: finite values.
        let traj = Trajectory::new(&name, seq.clone())
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        check_joint_trajectory(r, &traj).map_err(|e| PyValueError::new_err(e.to_string()))?;
    }
    Ok(())
}

/// Renders a batch of joint sequences (`[B][T][dof]`) of `robot`, sequence
/// `b` through `cameras[b]` (all of one size): the per-link label maps
/// (`B * T * H * W` little-endian u16) and, with `depth`, camera-frame depths
/// (`B * T * H * W` little-endian f32, inf for background). Every frame of
/// every sequence is rendered in parallel on the Rust thread pool (rayon),
/// with the GIL released.
#[pyfunction]
#[pyo3(signature = (robot, cameras, joints, depth = false))]
fn render<'py>(
    py: Python<'py>,
    robot: &Robot,
    cameras: Vec<PyRef<'py, Camera>>,
    joints: Vec<Vec<Vec<f64>>>,
    depth: bool,
) -> PyResult<(Bound<'py, PyByteArray>, Option<Bound<'py, PyByteArray>>)> {
    if cameras.len() != joints.len() {
        return Err(PyValueError::new_err(format!(
            "camera: expected one camera or one per sequence ({}), got {}",
            joints.len(),
            cameras.len()
        )));
    }
    let cams: Vec<CameraTrack> = cameras.iter().map(|c| c.inner.clone()).collect();
    if let Some(c) = cams.iter().find(|c| {
        (c.intrinsics.width, c.intrinsics.height)
            != (cams[0].intrinsics.width, cams[0].intrinsics.height)
    }) {
        return Err(PyValueError::new_err(format!(
            "camera: expected cameras of one size, got {}x{} and {}x{}",
            cams[0].intrinsics.width,
            cams[0].intrinsics.height,
            c.intrinsics.width,
            c.intrinsics.height
        )));
    }
    let r = &robot.inner.robot;
    check_joints(r, &joints)?;
    for (b, (cam, seq)) in cams.iter().zip(&joints).enumerate() {
        cam.check(r, seq.len(), &format!("camera[{b}]"))
            .map_err(camera_err)?;
    }
    // Every frame of every sequence is held at once: bounded, and checked
    // against the machine's memory, before any is rendered.
    let total: usize = joints.iter().map(Vec::len).sum();
    let (w, h) = cams
        .first()
        .map_or((0, 0), |c| (c.intrinsics.width, c.intrinsics.height));
    check_render_size("joints", total, w, h, depth).map_err(size_err)?;
    let frames: Vec<Vec<RenderOutput>> = py.detach(|| {
        no_panic("render", || {
            Ok(joints
                .par_iter()
                .zip(&cams)
                .map(|(seq, cam)| render_track(r, cam, seq, &|| {}))
                .collect())
        })
    })?;
    let n: usize = frames.iter().flatten().map(|f| f.labels.len()).sum();
    let mut labels = Vec::with_capacity(2 * n);
    let mut depths = Vec::with_capacity(if depth { 4 * n } else { 0 });
    for f in frames.iter().flatten() {
        for l in &f.labels {
            labels.extend_from_slice(&l.to_le_bytes());
        }
        if depth {
            for d in &f.depth_m {
                depths.extend_from_slice(&d.to_le_bytes());
            }
        }
    }
    Ok((
        PyByteArray::new(py, &labels),
        depth.then(|| PyByteArray::new(py, &depths)),
    ))
}

fn frame(name: &str, bytes: &[u8], (height, width): (usize, usize)) -> PyResult<RgbFrame> {
    RgbFrame::from_rgb8(width, height, bytes)
        .map_err(|e| PyValueError::new_err(format!("{name}: {e}")))
}

/// PSNR (dB) of two RGB8 frames of `height` x `width` (values in [0, 1]).
#[pyfunction]
fn psnr(pred: &[u8], gt: &[u8], height: usize, width: usize) -> PyResult<f64> {
    let (p, g) = (
        frame("pred", pred, (height, width))?,
        frame("gt", gt, (height, width))?,
    );
    bridgev2w_eval::video::psnr(&p, &g).map_err(|e| PyValueError::new_err(e.to_string()))
}

/// SSIM of two RGB8 frames (Gaussian window, as scikit-image's
/// `structural_similarity(..., gaussian_weights=True, sigma=1.5,
/// use_sample_covariance=False, channel_axis=-1, data_range=1)`).
#[pyfunction]
fn ssim(pred: &[u8], gt: &[u8], height: usize, width: usize) -> PyResult<f64> {
    let (p, g) = (
        frame("pred", pred, (height, width))?,
        frame("gt", gt, (height, width))?,
    );
    bridgev2w_eval::video::ssim(&p, &g).map_err(|e| PyValueError::new_err(e.to_string()))
}

/// IoU of two masks (non-zero = inside), 1 when both are empty.
#[pyfunction]
fn mask_iou(pred: &[u8], gt: &[u8]) -> PyResult<f64> {
    bridgev2w_eval::video::mask_iou(pred, gt).map_err(|e| PyValueError::new_err(e.to_string()))
}

/// The rows of a joint or action file as `bridgev2w masks --joints` and
/// `--actions` read it (JSON array of arrays, CSV with an optional header
/// row, or a 1-D/2-D `.npy`): `[T][n]`, every row of one length, finite.
#[pyfunction]
fn read_trajectory(path: PathBuf) -> PyResult<Vec<Vec<f64>>> {
    if !path.is_file() {
        return Err(PyFileNotFoundError::new_err(format!(
            "{}: no such joint or action file",
            path.display()
        )));
    }
    Trajectory::read(&path)
        .map(|t| t.rows)
        .map_err(|e| PyValueError::new_err(e.to_string()))
}

/// The names of the built-in robots.
#[pyfunction]
fn builtin_robots() -> String {
    bridgev2w_embodiment::embodiment::builtin_names()
}

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    // The binary's start-up settings (bf16 layers widened to f32 on a CPU
    // without bf16 arithmetic; inference layers and bf16 attention on
    // oneDNN), with BRIDGEV2W_CPU_BF16, BRIDGEV2W_CPU_LINEAR and
    // BRIDGEV2W_CPU_ATTENTION read the same way.
    bridgev2w_world_model::cpu_bf16::init_from_env().map_err(|e| Error::new_err(e.to_string()))?;
    bridgev2w_world_model::cpu_linear::init_from_env()
        .map_err(|e| Error::new_err(e.to_string()))?;
    bridgev2w_world_model::cpu_attention::init_from_env()
        .map_err(|e| Error::new_err(e.to_string()))?;
    m.add("Error", m.py().get_type::<Error>())?;
    // The stated maxima the Python half checks before it builds its bytes.
    m.add(
        "MAX_PREDICT_BATCH",
        bridgev2w_world_model::bridge::MAX_PREDICT_BATCH,
    )?;
    m.add("MAX_RENDER_FRAMES", MAX_RENDER_FRAMES)?;
    m.add_class::<Robot>()?;
    m.add_class::<Camera>()?;
    m.add_class::<WorldModel>()?;
    m.add_function(wrap_pyfunction!(render, m)?)?;
    m.add_function(wrap_pyfunction!(psnr, m)?)?;
    m.add_function(wrap_pyfunction!(ssim, m)?)?;
    m.add_function(wrap_pyfunction!(mask_iou, m)?)?;
    m.add_function(wrap_pyfunction!(builtin_robots, m)?)?;
    m.add_function(wrap_pyfunction!(read_trajectory, m)?)?;
    m.add_function(wrap_pyfunction!(data::synth_generate, m)?)?;
    m.add_function(wrap_pyfunction!(data::convert, m)?)?;
    m.add_function(wrap_pyfunction!(data::read_episode, m)?)?;
    m.add_function(wrap_pyfunction!(calibrate::calibrate, m)?)?;
    m.add_function(wrap_pyfunction!(policy::evaluate_policies, m)?)?;
    Ok(())
}
