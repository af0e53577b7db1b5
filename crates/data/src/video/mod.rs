//! Video in MP4: encoding RGB frames as H.264 with openh264 (bundled
//! source), and decoding what cameras and encoders write: H.264 (openh264:
//! Baseline, Main and High profiles, CABAC, B-frames) and AV1 ([`av1`], the
//! pure-Rust port of dav1d: 8/10/12 bit, 4:2:0, 4:2:2, 4:4:4, monochrome),
//! frames returned in presentation order with their presentation times,
//! one at a time ([`VideoStream`], memory bounded by the codec's reorder
//! depth) or all at once ([`decode_mp4`]).

mod av1;
mod h264;
mod stream;
mod yuv;

pub use stream::{VideoFrame, VideoInfo, VideoStream};

use crate::mp4::{mux_h264, H264Stream, Mp4Error, TrackCodec, VideoTrack};
use openh264::encoder::{
    BitRate, Encoder, EncoderConfig, FrameRate, FrameType, QpRange, RateControlMode,
};
use openh264::formats::{RgbSliceU8, YUVBuffer};
use openh264::OpenH264API;
use std::path::{Path, PathBuf};

/// Video errors, naming the file.
#[derive(Debug, thiserror::Error)]
pub enum VideoError {
    /// Container problem.
    #[error(transparent)]
    Mp4(#[from] Mp4Error),
    /// The codec failed (a corrupt or truncated stream).
    #[error("{path}: {codec} {op} failed at frame {frame}: {message}")]
    Codec {
        /// File.
        path: PathBuf,
        /// "H.264" or "AV1".
        codec: &'static str,
        /// "encode" or "decode".
        op: &'static str,
        /// Frame index.
        frame: usize,
        /// Codec message.
        message: String,
    },
    /// A profile or format of a supported codec that cannot be decoded.
    #[error("{path}: {codec} {profile} is not supported ({what_is}); re-encode the video, e.g. ffmpeg -c:v libx264 -pix_fmt yuv420p")]
    UnsupportedProfile {
        /// File.
        path: PathBuf,
        /// "H.264" or "AV1".
        codec: &'static str,
        /// The profile or format found.
        profile: String,
        /// What is supported.
        what_is: &'static str,
    },
    /// Bad frame buffer or geometry.
    #[error("{path}: {message}")]
    Frame {
        /// File.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
}

/// Timescale units per frame in the MP4s written here.
const TICKS_PER_FRAME: u32 = 1000;

/// Encodes RGB frames into an H.264 MP4 held in memory, then written with
/// [`Mp4VideoWriter::finish`]. Frames marked as keyframes are coded as IDR
/// (episode starts), so every episode can be decoded on its own.
pub struct Mp4VideoWriter {
    path: PathBuf,
    encoder: Encoder,
    width: usize,
    height: usize,
    fps: u32,
    sps: Option<Vec<u8>>,
    pps: Option<Vec<u8>>,
    samples: Vec<Vec<u8>>,
    sync: Vec<bool>,
}

impl std::fmt::Debug for Mp4VideoWriter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Mp4VideoWriter")
            .field("path", &self.path)
            .field("width", &self.width)
            .field("height", &self.height)
            .field("frames", &self.samples.len())
            .finish()
    }
}

/// Splits an Annex-B byte stream into NAL units (without start codes).
pub fn annexb_nals(stream: &[u8]) -> Vec<&[u8]> {
    let mut starts = Vec::new();
    let mut i = 0;
    while i + 3 <= stream.len() {
        if stream[i] == 0 && stream[i + 1] == 0 && stream[i + 2] == 1 {
            starts.push(i + 3);
            i += 3;
        } else {
            i += 1;
        }
    }
    let mut out = Vec::new();
    for (k, &s) in starts.iter().enumerate() {
        let mut e = starts.get(k + 1).map_or(stream.len(), |&n| n - 3);
        while e > s && stream[e - 1] == 0 && k + 1 < starts.len() {
            e -= 1;
        }
        out.push(&stream[s..e]);
    }
    out
}

impl Mp4VideoWriter {
    /// A writer for `width` x `height` RGB frames (both even) at `fps`;
    /// `path` names the file in errors and is where [`Self::finish`] writes.
    pub fn new(path: &Path, width: usize, height: usize, fps: u32) -> Result<Self, VideoError> {
        if width == 0
            || height == 0
            || width % 2 != 0
            || height % 2 != 0
            || width > 4096
            || height > 4096
        {
            return Err(VideoError::Frame {
                path: path.to_path_buf(),
                message: format!("video size {width}x{height} must be even and within 2..4096"),
            });
        }
        let bits = (width * height) as f64 * f64::from(fps) * 2.0;
        let config = EncoderConfig::new()
            .max_frame_rate(FrameRate::from_hz(fps as f32))
            .bitrate(BitRate::from_bps(bits.min(f64::from(u32::MAX)) as u32))
            .rate_control_mode(RateControlMode::Off)
            .qp(QpRange::new(8, 24))
            .skip_frames(false)
            .num_threads(1);
        let encoder =
            Encoder::with_api_config(OpenH264API::from_source(), config).map_err(|e| {
                VideoError::Codec {
                    path: path.to_path_buf(),
                    codec: "H.264",
                    op: "encode",
                    frame: 0,
                    message: e.to_string(),
                }
            })?;
        Ok(Self {
            path: path.to_path_buf(),
            encoder,
            width,
            height,
            fps,
            sps: None,
            pps: None,
            samples: Vec::new(),
            sync: Vec::new(),
        })
    }

    /// Frames encoded so far.
    pub fn frames(&self) -> usize {
        self.samples.len()
    }

    /// Encodes one interleaved RGB8 frame; `keyframe` forces an IDR frame.
    pub fn push(&mut self, rgb: &[u8], keyframe: bool) -> Result<(), VideoError> {
        let frame = self.samples.len();
        if rgb.len() != self.width * self.height * 3 {
            return Err(VideoError::Frame {
                path: self.path.clone(),
                message: format!(
                    "frame {frame} has {} bytes, expected {} ({}x{}x3)",
                    rgb.len(),
                    self.width * self.height * 3,
                    self.width,
                    self.height
                ),
            });
        }
        let yuv = YUVBuffer::from_rgb8_source(RgbSliceU8::new(rgb, (self.width, self.height)));
        if keyframe {
            self.encoder.force_intra_frame();
        }
        let path = self.path.clone();
        let bs = self.encoder.encode(&yuv).map_err(|e| VideoError::Codec {
            path: path.clone(),
            codec: "H.264",
            op: "encode",
            frame,
            message: e.to_string(),
        })?;
        let is_idr = matches!(bs.frame_type(), FrameType::IDR);
        let stream = bs.to_vec();
        let mut sample = Vec::with_capacity(stream.len());
        for nal in annexb_nals(&stream) {
            match nal.first().map(|b| b & 0x1F) {
                Some(7) => {
                    self.sps.get_or_insert_with(|| nal.to_vec());
                }
                Some(8) => {
                    self.pps.get_or_insert_with(|| nal.to_vec());
                }
                Some(_) => {
                    sample.extend_from_slice(&(nal.len() as u32).to_be_bytes());
                    sample.extend_from_slice(nal);
                }
                None => {}
            }
        }
        if sample.is_empty() {
            return Err(VideoError::Codec {
                path,
                codec: "H.264",
                op: "encode",
                frame,
                message: "the encoder produced no picture (skipped frame)".into(),
            });
        }
        self.samples.push(sample);
        self.sync.push(is_idr);
        Ok(())
    }

    /// The MP4 file's bytes.
    pub fn to_bytes(&self) -> Result<Vec<u8>, VideoError> {
        let (Some(sps), Some(pps)) = (&self.sps, &self.pps) else {
            return Err(VideoError::Frame {
                path: self.path.clone(),
                message: "no frames were encoded".into(),
            });
        };
        Ok(mux_h264(&H264Stream {
            width: self.width as u16,
            height: self.height as u16,
            timescale: self.fps * TICKS_PER_FRAME,
            sample_duration: TICKS_PER_FRAME,
            sps,
            pps,
            samples: &self.samples,
            sync: &self.sync,
        }))
    }
}

/// Writes a `frames`-frame H.264 MP4 test pattern (a horizontal gradient
/// that brightens by 10 levels per frame) of `width` x `height` at `fps`, for
/// tests and fixtures that need a real video file.
pub fn write_test_pattern(
    path: &Path,
    (width, height): (usize, usize),
    frames: usize,
    fps: u32,
) -> Result<(), VideoError> {
    let mut writer = Mp4VideoWriter::new(path, width, height, fps)?;
    for f in 0..frames {
        let rgb: Vec<u8> = (0..width * height * 3)
            .map(|i| ((i / 3 % width) * 4 + f * 10) as u8)
            .collect();
        writer.push(&rgb, f == 0)?;
    }
    let bytes = writer.to_bytes()?;
    bridgev2w_io::npy::write_atomic(path, &bytes).map_err(|e| VideoError::Frame {
        path: path.to_path_buf(),
        message: format!("cannot write: {e}"),
    })
}

/// A decoded video: interleaved RGB8 frames and their timestamps.
#[derive(Debug, Clone)]
pub struct DecodedVideo {
    /// Width (pixels).
    pub width: usize,
    /// Height (pixels).
    pub height: usize,
    /// Frames, `height * width * 3` bytes each.
    pub frames: Vec<Vec<u8>>,
    /// Presentation times (seconds).
    pub timestamps_s: Vec<f64>,
}

/// Reads and decodes every frame of an MP4 file (H.264 or AV1) into memory
/// (`frames * height * width * 3` bytes: for long or large videos use
/// [`VideoStream`], which holds a few frames at a time).
pub fn decode_mp4(path: &Path) -> Result<DecodedVideo, VideoError> {
    VideoStream::open(path)?.read_all()
}

/// Decodes the samples of `track` (from `data`, the file's bytes): the
/// frames in presentation order, with their presentation times.
pub fn decode_track(
    path: &Path,
    data: &[u8],
    track: &VideoTrack,
) -> Result<DecodedVideo, VideoError> {
    VideoStream::new(path, std::io::Cursor::new(data), track.clone())?.read_all()
}

fn codec_name(codec: &TrackCodec) -> &'static str {
    match codec {
        TrackCodec::H264(_) => "H.264",
        TrackCodec::Av1(_) => "AV1",
    }
}

/// Peak signal-to-noise ratio (dB) between two 8-bit buffers.
pub fn psnr_db(a: &[u8], b: &[u8]) -> f64 {
    let n = a.len().min(b.len()).max(1);
    let mse: f64 = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| {
            let d = f64::from(x) - f64::from(y);
            d * d
        })
        .sum::<f64>()
        / n as f64;
    if mse == 0.0 {
        f64::INFINITY
    } else {
        10.0 * (255.0f64 * 255.0 / mse).log10()
    }
}
