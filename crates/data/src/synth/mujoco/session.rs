//! A MuJoCo scene kept open in its worker process (`mujoco_world.py
//! --serve`): reset at a plan's start, then stepped a chunk of joint targets
//! at a time, each frame's reached joints, object poses and touches
//! returned, its RGB and robot pixels when asked. `synth --engine mujoco`
//! runs each episode through one; a planner executing in MuJoCo keeps one
//! per trial.

use super::engine_error;
use crate::synth::{Contact, ObjectPose, SynthError};
use base64::Engine as _;
use serde::Deserialize;
use std::io::{BufRead, BufReader, Write};
use std::path::Path;
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};

/// Which frames of a step are rendered.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Render {
    /// None (state only).
    None,
    /// The last frame.
    Last,
    /// Every frame.
    All,
}

impl Render {
    fn name(self) -> &'static str {
        match self {
            Self::None => "none",
            Self::Last => "last",
            Self::All => "all",
        }
    }
}

/// One simulated frame.
#[derive(Debug, Clone)]
pub struct SimFrame {
    /// The joints the arm reached (the robot's actuated order).
    pub joints: Vec<f64>,
    /// Per object: its pose (bottom centre and yaw).
    pub objects: Vec<ObjectPose>,
    /// Per object: whether a robot geom touched it during the frame.
    pub touched: Vec<bool>,
    /// Rendered RGB8, `height * width * 3`, when asked.
    pub rgb: Option<Vec<u8>>,
    /// MuJoCo's segmentation of the robot (0/1), `height * width`, when
    /// rendered.
    pub robot: Option<Vec<u8>>,
}

/// How high above the table (metres) an object the robot touches counts as
/// carried (held).
const CARRIED_ABOVE_TABLE_M: f64 = 0.005;

impl SimFrame {
    /// Per object: carried (touched by the robot, above the table top at
    /// `table_z_m`), pushed (touched) or none.
    pub fn contacts(&self, table_z_m: f64) -> Vec<Contact> {
        self.objects
            .iter()
            .zip(&self.touched)
            .map(|(p, &touched)| match touched {
                false => Contact::None,
                true if p.position_m[2] > table_z_m + CARRIED_ABOVE_TABLE_M => Contact::Carried,
                true => Contact::Pushed,
            })
            .collect()
    }
}

/// What a reset or a step returned.
#[derive(Debug, Clone)]
pub struct SimReply {
    /// The frames simulated (up to the unstable one, excluded).
    pub frames: Vec<SimFrame>,
    /// Why the physics went unstable, if it did.
    pub unstable: Option<String>,
    /// MuJoCo's version.
    pub mujoco: String,
    /// Physics steps per frame.
    pub substeps: usize,
}

#[derive(Deserialize)]
struct WireFrame {
    joints: Vec<f64>,
    objects: Vec<[f64; 4]>,
    touched: Vec<u8>,
    rgb: Option<String>,
    robot: Option<String>,
}

/// A frame, or (a rollout's) why its physics went unstable.
#[derive(Deserialize)]
#[serde(untagged)]
enum WireEntry {
    Unstable { unstable: String },
    Frame(WireFrame),
}

#[derive(Deserialize)]
struct WireReply {
    frames: Vec<WireEntry>,
    stable: bool,
    reason: String,
    mujoco: String,
    substeps: usize,
}

/// A worker process holding one scene.
#[derive(Debug)]
pub struct MujocoSession {
    child: Child,
    stdin: ChildStdin,
    stdout: BufReader<ChildStdout>,
    stderr_path: std::path::PathBuf,
    /// `(height, width)` of the rendered frames.
    size: (usize, usize),
}

impl MujocoSession {
    /// Starts `python script --serve`, its errors into `stderr_path`.
    pub(super) fn start(
        python: &Path,
        script: &Path,
        stderr_path: &Path,
    ) -> Result<Self, SynthError> {
        let stderr = std::fs::File::create(stderr_path)
            .map_err(|e| engine_error(format!("{}: {e}", stderr_path.display())))?;
        let mut child = Command::new(python)
            .arg(script)
            .arg("--serve")
            .env(
                "MUJOCO_GL",
                std::env::var("MUJOCO_GL").unwrap_or_else(|_| "egl".into()),
            )
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::from(stderr))
            .spawn()
            .map_err(|e| engine_error(format!("{}: cannot run it: {e}", python.display())))?;
        let (Some(stdin), Some(stdout)) = (child.stdin.take(), child.stdout.take()) else {
            return Err(engine_error("the MuJoCo worker's pipes did not open"));
        };
        Ok(Self {
            child,
            stdin,
            stdout: BufReader::new(stdout),
            stderr_path: stderr_path.to_path_buf(),
            size: (0, 0),
        })
    }

    /// Builds the scene `episode` describes (the worker's episode JSON; its
    /// `joints` hold at least the start row) and returns its start frame,
    /// rendered at `(height, width)`.
    pub fn reset(
        &mut self,
        episode: &serde_json::Value,
        size: (usize, usize),
    ) -> Result<SimReply, SynthError> {
        self.size = size;
        self.call(&serde_json::json!({"cmd": "reset", "episode": episode}))
    }

    /// Steps one frame towards each row of `joints` (the robot's actuated
    /// order), rendering the frames `render` says.
    pub fn step(&mut self, joints: &[Vec<f64>], render: Render) -> Result<SimReply, SynthError> {
        self.call(&serde_json::json!({"cmd": "step", "joints": joints, "render": render.name()}))
    }

    /// Keeps the current state under `slot` (for [`MujocoSession::rollouts`]
    /// and [`MujocoSession::restore`]); returns the current frame, unrendered.
    pub fn save(&mut self, slot: &str) -> Result<SimReply, SynthError> {
        self.call(&serde_json::json!({"cmd": "save", "slot": slot}))
    }

    /// Goes back to the state saved under `slot`.
    pub fn restore(&mut self, slot: &str) -> Result<SimReply, SynthError> {
        self.call(&serde_json::json!({"cmd": "restore", "slot": slot}))
    }

    /// From the state saved under `slot`, each candidate's joint rows
    /// stepped, its last frame returned (rendered when `render`), or why its
    /// physics went unstable; the scene is left at the saved state. What a
    /// perfect model of the MuJoCo world predicts for a batch of candidates.
    pub fn rollouts(
        &mut self,
        slot: &str,
        candidates: &[Vec<Vec<f64>>],
        render: bool,
    ) -> Result<Vec<Result<SimFrame, String>>, SynthError> {
        let wire = self.call_raw(&serde_json::json!({
            "cmd": "rollouts", "slot": slot, "candidates": candidates,
            "render": if render { "last" } else { "none" },
        }))?;
        if wire.frames.len() != candidates.len() {
            return Err(engine_error(format!(
                "the MuJoCo worker answered {} rollouts of {}",
                wire.frames.len(),
                candidates.len()
            )));
        }
        wire.frames
            .iter()
            .map(|entry| match entry {
                WireEntry::Unstable { unstable } => Ok(Err(unstable.clone())),
                WireEntry::Frame(f) => self.frame(f).map(Ok),
            })
            .collect()
    }

    fn call(&mut self, message: &serde_json::Value) -> Result<SimReply, SynthError> {
        let wire = self.call_raw(message)?;
        let frames = wire
            .frames
            .iter()
            .map(|entry| match entry {
                WireEntry::Frame(f) => self.frame(f),
                WireEntry::Unstable { unstable } => Err(engine_error(format!(
                    "the MuJoCo worker answered a rollout's instability ({unstable}) to another command"
                ))),
            })
            .collect::<Result<_, SynthError>>()?;
        Ok(SimReply {
            frames,
            unstable: (!wire.stable).then_some(wire.reason),
            mujoco: wire.mujoco,
            substeps: wire.substeps,
        })
    }

    fn call_raw(&mut self, message: &serde_json::Value) -> Result<WireReply, SynthError> {
        let mut line = message.to_string();
        line.push('\n');
        let sent = self
            .stdin
            .write_all(line.as_bytes())
            .and_then(|()| self.stdin.flush());
        let mut answer = String::new();
        let read = sent.and_then(|()| self.stdout.read_line(&mut answer));
        if !matches!(read, Ok(n) if n > 0) {
            return Err(self.died());
        }
        serde_json::from_str(&answer).map_err(|e| {
            engine_error(format!(
                "the MuJoCo worker answered something else than its protocol ({e})"
            ))
        })
    }

    fn frame(&self, f: &WireFrame) -> Result<SimFrame, SynthError> {
        let (h, w) = self.size;
        let decode =
            |what: &str, b64: &Option<String>, len: usize| -> Result<Option<Vec<u8>>, SynthError> {
                let Some(text) = b64 else { return Ok(None) };
                let bytes = base64::engine::general_purpose::STANDARD
                    .decode(text)
                    .map_err(|e| engine_error(format!("the MuJoCo worker's {what}: {e}")))?;
                if bytes.len() != len {
                    return Err(engine_error(format!(
                        "the MuJoCo worker's {what}: {} bytes, expected {len} ({h}x{w})",
                        bytes.len()
                    )));
                }
                Ok(Some(bytes))
            };
        Ok(SimFrame {
            joints: f.joints.clone(),
            objects: f
                .objects
                .iter()
                .map(|p| ObjectPose {
                    position_m: [p[0], p[1], p[2]],
                    yaw_rad: p[3],
                })
                .collect(),
            touched: f.touched.iter().map(|&t| t != 0).collect(),
            rgb: decode("frame", &f.rgb, h * w * 3)?,
            robot: decode("segmentation", &f.robot, h * w)?,
        })
    }

    /// The worker's error: what it wrote to stderr, with its exit status.
    fn died(&mut self) -> SynthError {
        let status = self
            .child
            .wait()
            .map(|s| s.to_string())
            .unwrap_or_else(|e| e.to_string());
        let stderr = std::fs::read_to_string(&self.stderr_path).unwrap_or_default();
        engine_error(format!(
            "MuJoCo's worker stopped ({status}): {}",
            stderr.trim()
        ))
    }
}

impl Drop for MujocoSession {
    fn drop(&mut self) {
        let _ = self.stdin.write_all(b"{\"cmd\": \"close\"}\n");
        let _ = self.stdin.flush();
        // Up to 2 s to exit by itself (MuJoCo's OpenGL context torn down),
        // then killed.
        for _ in 0..100 {
            if matches!(self.child.try_wait(), Ok(Some(_))) {
                return;
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
