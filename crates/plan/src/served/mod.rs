//! Policies served over openpi's websocket protocol (the way π0 and π0.5
//! are served: `openpi`'s `serve_policy.py`, clients through
//! `openpi-client`'s `WebsocketClientPolicy`):
//!
//! 1. the client connects (`ws://HOST:PORT`); the server sends its metadata,
//!    one msgpack-numpy message;
//! 2. per query the client sends the observation (a map of arrays and the
//!    prompt) and receives a map holding the action chunk (`"actions"`,
//!    `[steps, dim]`); a text message instead is the server's error.
//!
//! [`ServedPolicy`] is such a client as a [`Policy`]: the observation is
//! built from the rollout's frame, joints and pose by a
//! [`ServedPolicyConfig`], the chunk read back as end-effector actions.
//! Every failure (unreachable, closed, slow, a chunk of the wrong shape,
//! dtype or values) is an error naming the policy, the step and the field.

pub mod config;
pub mod msgpack_numpy;

use crate::error::{PlanError, Result};
use crate::policy::Policy;
use crate::{EeAction, Observation};
use bridgev2w_data::raw::convert::resize_rgb;
use bridgev2w_embodiment::kinematics::xyz_rpy_from_pose;
use bridgev2w_embodiment::robot::Robot;
use bridgev2w_io::frame::u8_from_unit;
pub use config::{ActionLayout, ImageLayout, ServedPolicyConfig};
use msgpack_numpy::{as_array, insert, kind, lookup, NdArray, Packed};
use rmpv::Value;
use std::net::{TcpStream, ToSocketAddrs};
use std::sync::Arc;
use std::time::Duration;
use tungstenite::{Message, WebSocket};

/// A policy behind an openpi websocket server.
pub struct ServedPolicy {
    name: String,
    url: String,
    config: ServedPolicyConfig,
    socket: WebSocket<TcpStream>,
    metadata: Value,
    step: usize,
    kinematics: Option<TcpKinematics>,
}

impl std::fmt::Debug for ServedPolicy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ServedPolicy")
            .field("name", &self.name)
            .field("url", &self.url)
            .field("step", &self.step)
            .finish()
    }
}

impl ServedPolicy {
    /// Connects to `url` (`ws://HOST:PORT[/PATH]`) and reads the server's
    /// metadata, each within the config's timeout.
    pub fn connect(name: &str, url: &str, config: ServedPolicyConfig) -> Result<Self> {
        let fail = |message: String| PlanError::Policy {
            policy: name.to_string(),
            step: None,
            message,
        };
        config.check().map_err(&fail)?;
        let rest = match url.strip_prefix("ws://") {
            Some(r) => r,
            None if url.starts_with("wss://") => {
                return Err(fail(format!(
                "{url}: wss:// (TLS) is not built in; use a ws:// URL (e.g. through an SSH tunnel)"
            )))
            }
            None => return Err(fail(format!("{url}: expected a ws://HOST:PORT URL"))),
        };
        let host_port = rest.split('/').next().unwrap_or_default();
        let timeout = Duration::from_secs_f64(config.timeout_s);
        let addrs: Vec<_> = host_port
            .to_socket_addrs()
            .map_err(|e| {
                fail(format!(
                    "{url}: {host_port:?} is not a reachable HOST:PORT ({e})"
                ))
            })?
            .collect();
        let mut last = None;
        let mut stream = None;
        for a in &addrs {
            match TcpStream::connect_timeout(a, timeout) {
                Ok(s) => {
                    stream = Some(s);
                    break;
                }
                Err(e) => last = Some(e),
            }
        }
        let stream = stream.ok_or_else(|| {
            fail(format!(
                "{url}: cannot connect ({}); is the policy server running?",
                last.map_or("no address".to_string(), |e| e.to_string())
            ))
        })?;
        stream
            .set_read_timeout(Some(timeout))
            .and_then(|()| stream.set_write_timeout(Some(timeout)))
            .map_err(|e| fail(format!("{url}: {e}")))?;
        let (mut socket, _) = tungstenite::client::client(url, stream)
            .map_err(|e| fail(format!("{url}: websocket handshake failed: {e}")))?;
        let metadata = read_message(&mut socket, config.timeout_s)
            .map_err(|m| fail(format!("{url}: reading the server's metadata: {m}")))?;
        Ok(Self {
            name: name.to_string(),
            url: url.to_string(),
            config,
            socket,
            metadata,
            step: 0,
            kinematics: None,
        })
    }

    /// The metadata the server sent on connect.
    pub fn metadata(&self) -> &Value {
        &self.metadata
    }

    /// The observation as the server's map.
    pub fn observation(&self, obs: &Observation) -> Packed {
        let o = &self.config.observation;
        let style = self.config.keys;
        let mut map = Vec::new();
        let [h, w] = o.image_size;
        let rgb: Vec<u8> = obs.image.rgb.iter().map(|&v| u8_from_unit(v)).collect();
        let resized = resize_rgb(&rgb, (obs.image.width, obs.image.height), (w, h));
        let image = |data: Vec<u8>| match o.image_layout {
            ImageLayout::Hwc => NdArray::from_u8(vec![h, w, 3], data),
            ImageLayout::Chw => {
                let chw = (0..3)
                    .flat_map(|c| data.iter().skip(c).step_by(3).copied().collect::<Vec<_>>())
                    .collect();
                NdArray::from_u8(vec![3, h, w], chw)
            }
        };
        insert(&mut map, &o.image, Packed::Array(image(resized)), style);
        for key in &o.blank_images {
            insert(
                &mut map,
                key,
                Packed::Array(image(vec![0; h * w * 3])),
                style,
            );
        }
        if !o.joints.is_empty() {
            let n = o.arm_joints.min(obs.joints.len());
            let joints = NdArray::from_f64(vec![n], &obs.joints[..n]);
            insert(&mut map, &o.joints, Packed::Array(joints), style);
        }
        if !o.gripper.is_empty() {
            let g = NdArray::from_f64(vec![1], &obs.ee[6..7]);
            insert(&mut map, &o.gripper, Packed::Array(g), style);
        }
        if !o.ee_pose.is_empty() {
            let pose = NdArray::from_f64(vec![6], &obs.ee[..6]);
            insert(&mut map, &o.ee_pose, Packed::Array(pose), style);
        }
        if !o.prompt_key.is_empty() {
            insert(
                &mut map,
                &o.prompt_key,
                Packed::Str(o.prompt.clone()),
                style,
            );
        }
        Packed::Map(map)
    }

    /// Sets the forward kinematics that `joint_position` and
    /// `joint_velocity` chunks go through.
    pub fn set_kinematics(&mut self, kinematics: Option<TcpKinematics>) {
        self.kinematics = kinematics;
    }

    /// The chunk in a response, as end-effector actions from the
    /// observation `obs` (its pose for deltas, its joints for joint actions).
    pub fn chunk(
        &self,
        response: &Value,
        obs: &Observation,
    ) -> std::result::Result<Vec<EeAction>, String> {
        let a = &self.config.action;
        if response.as_map().is_none() {
            return Err(format!("the answer is {}, expected a map", kind(response)));
        }
        let v = lookup(response, &a.key, self.config.keys).ok_or_else(|| {
            format!(
                "the answer has no {:?} (keys: {})",
                a.key,
                keys_of(response)
            )
        })?;
        let arr = as_array(v).map_err(|e| format!("{:?}: {e}", a.key))?;
        let values = arr.to_f64().map_err(|e| format!("{:?}: {e}", a.key))?;
        let arm = self.config.observation.arm_joints.min(obs.joints.len());
        let (width, what) = match a.layout {
            ActionLayout::EeAbsolute | ActionLayout::EeDelta => (
                7,
                "[x, y, z, roll, pitch, yaw, gripper] per step".to_string(),
            ),
            ActionLayout::JointPosition | ActionLayout::JointVelocity => (
                arm + 1,
                format!("{arm} arm joints and the gripper per step"),
            ),
        };
        let rows = match arr.shape[..] {
            [n, w] if w == width => n,
            [w] if w == width => 1,
            _ => {
                return Err(format!(
                    "{:?}: shape {:?}, expected [steps, {width}] ({what})",
                    a.key, arr.shape
                ))
            }
        };
        if let Some(i) = values.iter().position(|x| !x.is_finite()) {
            return Err(format!(
                "{:?}: row {}, column {} is {}, expected finite numbers",
                a.key,
                i / width,
                i % width,
                values[i]
            ));
        }
        if rows == 0 {
            return Err(format!("{:?}: an empty chunk", a.key));
        }
        let take = if a.execute == 0 {
            rows
        } else {
            a.execute.min(rows)
        };
        let rows = values.chunks_exact(width).take(take);
        match a.layout {
            ActionLayout::EeAbsolute | ActionLayout::EeDelta => Ok(rows
                .map(|r| {
                    let mut act: EeAction = [0.0; 7];
                    act.copy_from_slice(r);
                    if a.layout == ActionLayout::EeDelta {
                        for (x, c) in act.iter_mut().zip(&obs.ee).take(6) {
                            *x += c;
                        }
                    }
                    act
                })
                .collect()),
            ActionLayout::JointPosition | ActionLayout::JointVelocity => {
                let k = self.kinematics.as_ref().ok_or(
                    "joint actions need the robot's forward kinematics (ServedPolicy::set_kinematics)",
                )?;
                let mut q = obs.joints.clone();
                let dt = 1.0 / a.control_hz;
                Ok(rows
                    .map(|r| {
                        for (qi, ri) in q.iter_mut().zip(&r[..arm]) {
                            if a.layout == ActionLayout::JointPosition {
                                *qi = *ri;
                            } else {
                                *qi += ri * dt;
                            }
                        }
                        let p = k.pose(&q);
                        [p[0], p[1], p[2], p[3], p[4], p[5], r[arm]]
                    })
                    .collect())
            }
        }
    }
}

/// The end-effector pose of a joint vector: a robot and the link whose
/// pose actions give (e.g. the TCP), for joint-space chunks.
#[derive(Debug, Clone)]
pub struct TcpKinematics {
    /// The robot.
    pub robot: Arc<Robot>,
    /// The link (index into the robot's links).
    pub link: usize,
}

impl TcpKinematics {
    /// `[x, y, z, roll, pitch, yaw]` of the link at joints `q` (the robot's
    /// actuated order), in the robot's base frame.
    pub fn pose(&self, q: &[f64]) -> [f64; 6] {
        xyz_rpy_from_pose(&self.robot.link_pose(self.link, q))
    }
}

/// The keys of a map, for errors.
fn keys_of(v: &Value) -> String {
    let keys: Vec<String> = v
        .as_map()
        .map(|m| {
            m.iter()
                .map(|(k, _)| match k {
                    Value::String(s) => s.as_str().unwrap_or("?").to_string(),
                    Value::Binary(b) => String::from_utf8_lossy(b).into_owned(),
                    other => other.to_string(),
                })
                .collect()
        })
        .unwrap_or_default();
    if keys.is_empty() {
        "none".into()
    } else {
        keys.join(", ")
    }
}

/// The next binary message, decoded; a text message is the server's error.
fn read_message(
    socket: &mut WebSocket<TcpStream>,
    timeout_s: f64,
) -> std::result::Result<Value, String> {
    loop {
        let msg = socket.read().map_err(|e| match e {
            tungstenite::Error::Io(io)
                if matches!(
                    io.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) =>
            {
                format!("no answer within {timeout_s} s (timeout_s)")
            }
            tungstenite::Error::ConnectionClosed | tungstenite::Error::AlreadyClosed => {
                "the server closed the connection".to_string()
            }
            e => format!("the connection failed: {e}"),
        })?;
        match msg {
            Message::Binary(bytes) => {
                return rmpv::decode::read_value(&mut &bytes[..])
                    .map_err(|e| format!("an answer that is not msgpack: {e}"));
            }
            Message::Text(text) => {
                return Err(format!("the server reported an error:\n{}", text.as_str()))
            }
            Message::Close(frame) => {
                return Err(format!(
                    "the server closed the connection{}",
                    frame
                        .map(|f| format!(" ({}: {})", f.code, f.reason))
                        .unwrap_or_default()
                ))
            }
            // Pings are answered by tungstenite on the next read or write.
            Message::Ping(_) | Message::Pong(_) | Message::Frame(_) => {}
        }
    }
}

impl Policy for ServedPolicy {
    fn name(&self) -> String {
        self.name.clone()
    }

    fn reset(&mut self, _trial: usize) {
        // openpi's client keeps its connection across episodes (its reset does nothing).
        self.step = 0;
    }

    fn act(&mut self, obs: &Observation) -> Result<Vec<EeAction>> {
        let step = self.step;
        self.step += 1;
        let fail = |message: String| PlanError::Policy {
            policy: self.name.clone(),
            step: Some(step),
            message,
        };
        let bytes = self.observation(obs).to_bytes();
        self.socket
            .send(Message::Binary(bytes.into()))
            .map_err(|e| fail(format!("sending the observation: {e}")))?;
        let response = read_message(&mut self.socket, self.config.timeout_s).map_err(&fail)?;
        self.chunk(&response, obs).map_err(fail)
    }
}

impl Drop for ServedPolicy {
    fn drop(&mut self) {
        let _ = self.socket.close(None);
        let _ = self.socket.flush();
    }
}
