//! The calibration's options: what is searched, fitted, refused and
//! flagged, with their defaults and their validation.

use super::foreground::ForegroundOptions;
use super::marks::Marks;
use super::CalibrateError;
use bridgev2w_embodiment::camera::Camera;

/// Options of [`calibrate`].
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrateOptions {
    /// A rough camera to start from besides the coarse search (any image
    /// size: rescaled to the video's).
    pub guess: Option<Camera>,
    /// The analysis grid's largest width (the video is box-reduced by an
    /// integer factor to fit).
    pub analysis_width: u32,
    /// The middle refinement grid's largest width.
    pub mid_width: u32,
    /// The coarse search grid's largest width.
    pub coarse_width: u32,
    /// `fy / fx` of the start (and of the result unless `fit_aspect`):
    /// 1 for square pixels, 192/180 for DROID's stretched 320x192 videos.
    pub fy_over_fx: f64,
    /// A known focal length: fx at the video's size (pixels; fy = fx x
    /// `fy_over_fx`), kept fixed instead of fitted. A silhouette pins the
    /// focal length down poorly (a near, wide camera against a far,
    /// narrow one), so a known one removes the search's flattest direction.
    pub focal_px: Option<f64>,
    /// Fit `fy / fx` too.
    pub fit_aspect: bool,
    /// Fit the principal point too (else the image centre).
    pub fit_principal_point: bool,
    /// Hold out every n-th block of frames (about 16 blocks per episode).
    pub held_out_every: usize,
    /// Coarse search: azimuth step (degrees), all around.
    pub azimuth_step_deg: f64,
    /// Coarse search: elevations (degrees above the motion's centroid).
    pub elevations_deg: Vec<f64>,
    /// Coarse search: distances from the motion's centroid (metres).
    pub distances_m: Vec<f64>,
    /// Coarse-search candidates screened by a short refinement.
    pub screened: usize,
    /// Nelder-Mead evaluations of each screening.
    pub screen_evaluations: usize,
    /// Screened candidates refined.
    pub starts: usize,
    /// Of those, the best refined on the middle grid.
    pub finalists: usize,
    /// Frames per episode scored in the coarse search.
    pub coarse_frames: usize,
    /// Frames per episode scored in the refinement.
    pub fit_frames: usize,
    /// Frames per episode whose masks give the background model's robot.
    pub mode_frames: usize,
    /// Nelder-Mead evaluations per round.
    pub max_evaluations: usize,
    /// Nelder-Mead evaluations of each re-fit of the valley walk (the
    /// camera moved along an orbit or the dolly-zoom, the rest re-fitted);
    /// 0 skips the walk (a quick look: the walk costs about as much again
    /// as the rest of the search).
    pub walk_evaluations: usize,
    /// Weight of the background-consistency cost (see
    /// `calibrate::background`) added to the silhouette's `1 - IoU` in the
    /// full-grid refinement (not in the earlier stages); 0 fits the
    /// silhouette alone.
    pub background_weight: f64,
    /// Weight of the appearance cost (see `calibrate::appearance`: how well
    /// the rendered robot splits the frames' colours) added in the
    /// full-grid refinement, like the background's; 0 leaves it out.
    pub appearance_weight: f64,
    /// Refuse an episode whose robot surface moves less (metres).
    pub min_motion_m: f64,
    /// Refuse an episode with fewer frames showing robot pixels.
    pub min_robot_frames: usize,
    /// Refuse an episode with a smaller share of frames showing robot pixels.
    pub min_robot_frame_fraction: f64,
    /// A camera is moving when its noise level reaches this...
    pub moving_noise_level: f64,
    /// ...and its unstable fraction reaches this.
    pub moving_unstable_fraction: f64,
    /// Flag a held-out IoU below this.
    pub low_iou: f64,
    /// Flag as ambiguous when the camera moved by `ambiguous_position_m`
    /// (orbit or dolly-zoom, the rest re-fitted) fits less than this worse,
    /// or a refined alternative within this margin differs by more than
    /// `ambiguous_position_m`, `ambiguous_angle_deg` or
    /// `ambiguous_focal_fraction`.
    pub ambiguous_margin: f64,
    /// Nelder-Mead evaluations of each such re-fit.
    pub probe_evaluations: usize,
    /// See `ambiguous_margin` (metres).
    pub ambiguous_position_m: f64,
    /// See `ambiguous_margin` (degrees).
    pub ambiguous_angle_deg: f64,
    /// See `ambiguous_margin` (fraction of the focal length).
    pub ambiguous_focal_fraction: f64,
    /// Foreground detection.
    pub foreground: ForegroundOptions,
    /// Hand marks of the tool point (see [`super::marks`]): checked on
    /// every marked episode; on fitted ones they start and pull the fit.
    pub marks: Option<Marks>,
    /// Fit the marks of fitted episodes (a start and a pull); when false
    /// they are only measured, as a check of the automatic calibration.
    pub fit_marks: bool,
    /// Flag a marked episode whose median reprojection error exceeds this
    /// fraction of the image width.
    pub max_marks_error_fraction: f64,
}

impl Default for CalibrateOptions {
    fn default() -> Self {
        Self {
            guess: None,
            analysis_width: 320,
            mid_width: 160,
            coarse_width: 80,
            fy_over_fx: 1.0,
            focal_px: None,
            fit_aspect: false,
            fit_principal_point: false,
            held_out_every: 4,
            azimuth_step_deg: 20.0,
            elevations_deg: vec![-35.0, -20.0, -5.0, 10.0, 25.0, 40.0, 55.0, 70.0],
            distances_m: vec![0.4, 0.55, 0.75, 1.0, 1.4, 2.0, 3.0],
            screened: 60,
            screen_evaluations: 60,
            starts: 10,
            finalists: 3,
            coarse_frames: 8,
            fit_frames: 24,
            mode_frames: 24,
            max_evaluations: 250,
            walk_evaluations: 120,
            background_weight: 10.0,
            appearance_weight: 1.0,
            min_motion_m: 0.05,
            min_robot_frames: 6,
            min_robot_frame_fraction: 0.3,
            moving_noise_level: 7.25,
            moving_unstable_fraction: 0.5,
            low_iou: 0.5,
            ambiguous_margin: 0.01,
            probe_evaluations: 60,
            ambiguous_position_m: 0.05,
            ambiguous_angle_deg: 3.0,
            ambiguous_focal_fraction: 0.05,
            foreground: ForegroundOptions::default(),
            marks: None,
            fit_marks: true,
            max_marks_error_fraction: 0.03,
        }
    }
}

fn option_err(field: &'static str, value: impl ToString, expected: &str) -> CalibrateError {
    CalibrateError::Option {
        field,
        value: value.to_string(),
        expected: expected.to_string(),
    }
}

impl CalibrateOptions {
    /// The options with the analysis grid at most `width` pixels wide and
    /// the middle and coarse grids no wider than it (what a user's
    /// `--analysis-width` sets; the CLI and the Python package share it).
    pub fn with_analysis_width(mut self, width: u32) -> Self {
        self.analysis_width = width;
        self.mid_width = self.mid_width.min(width);
        self.coarse_width = self.coarse_width.min(width);
        self
    }

    /// Checks every option; the error names the command-line flag.
    pub fn validate(&self) -> Result<(), CalibrateError> {
        let widths = [
            ("--analysis-width", self.analysis_width),
            ("--mid-width", self.mid_width),
            ("--coarse-width", self.coarse_width),
        ];
        for (field, w) in widths {
            if !(16..=4096).contains(&w) {
                return Err(option_err(field, w, "16..=4096 pixels"));
            }
        }
        if !(self.coarse_width <= self.mid_width && self.mid_width <= self.analysis_width) {
            return Err(option_err(
                "--coarse-width",
                format!(
                    "{} (mid {}, analysis {})",
                    self.coarse_width, self.mid_width, self.analysis_width
                ),
                "coarse <= mid <= analysis width",
            ));
        }
        if let Some(f) = self.focal_px {
            if !(f.is_finite() && f > 0.0 && f <= 1e6) {
                return Err(option_err(
                    "--focal-px",
                    f,
                    "a focal length in pixels, above 0",
                ));
            }
        }
        if !(self.fy_over_fx.is_finite() && (0.5..=2.0).contains(&self.fy_over_fx)) {
            return Err(option_err(
                "--fy-over-fx",
                self.fy_over_fx,
                "a pixel aspect of 0.5..=2",
            ));
        }
        if !(2..=100).contains(&self.held_out_every) {
            return Err(option_err(
                "--held-out-every",
                self.held_out_every,
                "2..=100",
            ));
        }
        if !(self.azimuth_step_deg.is_finite() && (1.0..=180.0).contains(&self.azimuth_step_deg)) {
            return Err(option_err(
                "--azimuth-step-deg",
                self.azimuth_step_deg,
                "1..=180 degrees",
            ));
        }
        if self.elevations_deg.is_empty()
            || self
                .elevations_deg
                .iter()
                .any(|e| !(e.is_finite() && (-85.0..=85.0).contains(e)))
        {
            return Err(option_err(
                "--elevations-deg",
                format!("{:?}", self.elevations_deg),
                "one or more elevations of -85..=85 degrees",
            ));
        }
        if self.distances_m.is_empty()
            || self
                .distances_m
                .iter()
                .any(|d| !(d.is_finite() && (0.1..=20.0).contains(d)))
        {
            return Err(option_err(
                "--distances-m",
                format!("{:?}", self.distances_m),
                "one or more distances of 0.1..=20 m",
            ));
        }
        let counts = [
            ("--screened", self.screened, 1, 1000),
            ("--screen-evaluations", self.screen_evaluations, 10, 100_000),
            ("--starts", self.starts, 1, 64),
            ("--finalists", self.finalists, 1, 64),
            ("--coarse-frames", self.coarse_frames, 2, 1000),
            ("--fit-frames", self.fit_frames, 2, 1000),
            ("--mode-frames", self.mode_frames, 3, 1000),
            ("--max-evaluations", self.max_evaluations, 10, 100_000),
            ("--min-robot-frames", self.min_robot_frames, 1, 100_000),
            ("--probe-evaluations", self.probe_evaluations, 1, 100_000),
            ("--walk-evaluations", self.walk_evaluations, 0, 100_000),
            ("--static-window", self.foreground.static_window, 1, 100),
        ];
        for (field, v, lo, hi) in counts {
            if !(lo..=hi).contains(&v) {
                return Err(option_err(field, v, &format!("{lo}..={hi}")));
            }
        }
        let fractions = [
            ("--min-robot-frame-fraction", self.min_robot_frame_fraction),
            ("--moving-unstable-fraction", self.moving_unstable_fraction),
            ("--low-iou", self.low_iou),
            ("--max-marks-error-fraction", self.max_marks_error_fraction),
            ("--ambiguous-focal-fraction", self.ambiguous_focal_fraction),
            (
                "--min-robot-pixels-fraction",
                self.foreground.min_robot_pixels_fraction,
            ),
        ];
        for (field, v) in fractions {
            if !(v.is_finite() && (0.0..=1.0).contains(&v)) {
                return Err(option_err(field, v, "a fraction of 0..=1"));
            }
        }
        let positive = [
            ("--min-motion-m", self.min_motion_m),
            ("--background-weight", self.background_weight),
            ("--appearance-weight", self.appearance_weight),
            ("--moving-noise-level", self.moving_noise_level),
            ("--ambiguous-margin", self.ambiguous_margin),
            ("--ambiguous-position-m", self.ambiguous_position_m),
            ("--ambiguous-angle-deg", self.ambiguous_angle_deg),
            ("--min-threshold", self.foreground.min_threshold),
            ("--noise-factor", self.foreground.noise_factor),
        ];
        for (field, v) in positive {
            if !(v.is_finite() && v >= 0.0) {
                return Err(option_err(field, v, "a finite value >= 0"));
            }
        }
        if let Some(g) = &self.guess {
            g.intrinsics.validate()?;
        }
        Ok(())
    }
}
