//! `bridgev2w._core.Camera`: a calibrated camera, fixed, moving per frame
//! or mounted on a robot link.

use bridgev2w_embodiment::camera::{isometry_from_rows, CameraPose, CameraTrack};
use pyo3::exceptions::{PyFileNotFoundError, PyValueError};
use pyo3::prelude::*;
use std::path::PathBuf;

/// A calibrated camera: pinhole intrinsics, optional distortion, and its
/// pose: fixed, one per frame, or mounted on a robot link.
#[pyclass(module = "bridgev2w._core", frozen)]
pub(crate) struct Camera {
    pub(crate) inner: CameraTrack,
}

pub(crate) fn camera_err(e: impl std::fmt::Display) -> PyErr {
    PyValueError::new_err(e.to_string())
}

fn rows_to_isometry(m: &[[f64; 4]; 4], name: &str) -> PyResult<nalgebra::Isometry3<f64>> {
    isometry_from_rows(m, name, "matrix").map_err(camera_err)
}

#[pymethods]
impl Camera {
    /// A camera from its JSON text (the format of `bridgev2w masks
    /// --camera`, moving cameras included); `source` names it in errors.
    #[staticmethod]
    #[pyo3(signature = (text, source = "camera JSON"))]
    fn from_json_str(text: &str, source: &str) -> PyResult<Self> {
        CameraTrack::from_json_str(text, source)
            .map(|inner| Self { inner })
            .map_err(camera_err)
    }

    /// A camera from a JSON file.
    #[staticmethod]
    fn from_json(path: PathBuf) -> PyResult<Self> {
        if !path.is_file() {
            return Err(PyFileNotFoundError::new_err(format!(
                "{}: no such camera file",
                path.display()
            )));
        }
        CameraTrack::from_json_file(&path)
            .map(|inner| Self { inner })
            .map_err(camera_err)
    }

    /// The camera as JSON text (a fixed camera).
    fn to_json(&self) -> PyResult<String> {
        self.inner
            .as_fixed()
            .map(|c| c.to_json())
            .ok_or_else(|| PyValueError::new_err("to_json: a moving camera has no single pose"))
    }

    /// This camera with its intrinsics rescaled to `width` x `height`
    /// (each 1..=`MAX_IMAGE_SIDE` pixels; a `ValueError` naming the size
    /// otherwise, before anything of that size is rendered).
    fn rescaled(&self, width: u32, height: u32) -> PyResult<Self> {
        let inner = self.inner.rescaled(width, height);
        inner.intrinsics.validate().map_err(|e| {
            PyValueError::new_err(format!("rescaled(width={width}, height={height}): {e}"))
        })?;
        Ok(Self { inner })
    }

    /// These intrinsics moving through `poses` (`[T][4][4]`, row-major
    /// `world_from_camera` per frame).
    fn with_poses(&self, poses: Vec<[[f64; 4]; 4]>) -> PyResult<Self> {
        let poses = poses
            .iter()
            .enumerate()
            .map(|(t, m)| rows_to_isometry(m, &format!("poses[{t}]")))
            .collect::<PyResult<Vec<_>>>()?;
        Ok(Self {
            inner: self.inner.with_poses(poses),
        })
    }

    /// These intrinsics on a camera mounted on robot link `link`, at
    /// `link_from_camera` (row-major 4x4; default identity).
    #[pyo3(signature = (link, link_from_camera = None))]
    fn mounted(&self, link: String, link_from_camera: Option<[[f64; 4]; 4]>) -> PyResult<Self> {
        let link_from_camera = match link_from_camera {
            Some(m) => rows_to_isometry(&m, "link_from_camera")?,
            None => nalgebra::Isometry3::identity(),
        };
        Ok(Self {
            inner: CameraTrack {
                intrinsics: self.inner.intrinsics,
                pose: CameraPose::Mounted {
                    link,
                    link_from_camera,
                },
            },
        })
    }

    /// `"fixed"`, `"per_frame"` or `"mounted"`.
    #[getter]
    fn kind(&self) -> &'static str {
        match self.inner.pose {
            CameraPose::Fixed(_) => "fixed",
            CameraPose::PerFrame(_) => "per_frame",
            CameraPose::Mounted { .. } => "mounted",
        }
    }

    /// `(width, height)` in pixels.
    #[getter]
    fn size(&self) -> (u32, u32) {
        (self.inner.intrinsics.width, self.inner.intrinsics.height)
    }

    /// `(fx, fy, cx, cy)` in pixels (pixel centres at integer coordinates).
    #[getter]
    fn intrinsics(&self) -> (f64, f64, f64, f64) {
        let i = &self.inner.intrinsics;
        (i.fx, i.fy, i.cx, i.cy)
    }

    /// The pose of a fixed camera, a row-major 4x4 rigid transform (OpenCV
    /// camera axes); a `ValueError` for a moving camera.
    #[getter]
    fn world_from_camera(&self) -> PyResult<[[f64; 4]; 4]> {
        let c = self.inner.as_fixed().ok_or_else(|| {
            PyValueError::new_err("world_from_camera: a moving camera has a pose per frame")
        })?;
        let m = c.world_from_camera.to_homogeneous();
        Ok(std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)])))
    }

    /// The distortion `(k1, k2, p1, p2, k3)`, or None for an ideal pinhole.
    #[getter]
    fn distortion(&self) -> Option<[f64; 5]> {
        self.inner
            .intrinsics
            .distortion
            .as_ref()
            .map(|d| d.coefficients())
    }

    fn __repr__(&self) -> String {
        let i = &self.inner.intrinsics;
        format!(
            "Camera({}x{}, fx={}, fy={}, cx={}, cy={}, {})",
            i.width,
            i.height,
            i.fx,
            i.fy,
            i.cx,
            i.cy,
            self.kind()
        )
    }
}
