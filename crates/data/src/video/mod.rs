//! Video in MP4: encoding RGB frames as H.264 with openh264 (bundled
//! source), and decoding what cameras and encoders write: H.264 (openh264:
//! Baseline, Main and High profiles, CABAC, B-frames) and AV1 ([`av1`], the
//! pure-Rust port of dav1d: 8/10/12 bit, 4:2:0, 4:2:2, 4:4:4, monochrome),
//! frames returned in presentation order with their presentation times.

mod av1;
mod yuv;

use crate::mp4::{
    demux, mux_h264, read_file, H264Config, H264Stream, Mp4Error, TrackCodec, VideoTrack,
};
use openh264::decoder::{Decoder, DecoderConfig, Flush};
use openh264::encoder::{
    BitRate, Encoder, EncoderConfig, FrameRate, FrameType, QpRange, RateControlMode,
};
use openh264::formats::{RgbSliceU8, YUVBuffer, YUVSource};
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

/// Reads and decodes every frame of an MP4 file (H.264 or AV1).
pub fn decode_mp4(path: &Path) -> Result<DecodedVideo, VideoError> {
    let data = read_file(path)?;
    let track = demux(path, &data)?;
    decode_track(path, &data, &track)
}

/// Decodes the samples of `track` (from `data`, the file's bytes): the
/// frames in presentation order, with their presentation times.
pub fn decode_track(
    path: &Path,
    data: &[u8],
    track: &VideoTrack,
) -> Result<DecodedVideo, VideoError> {
    let (w, h) = (usize::from(track.width), usize::from(track.height));
    let frames = match &track.codec {
        TrackCodec::H264(config) => decode_h264(path, data, track, config)?,
        TrackCodec::Av1(config) => av1::decode(path, data, track, config)?,
    };
    let n = track.samples.len();
    if frames.len() != n {
        return Err(VideoError::Codec {
            path: path.to_path_buf(),
            codec: codec_name(&track.codec),
            op: "decode",
            frame: frames.len(),
            message: format!("decoded {} frames from {n} samples", frames.len()),
        });
    }
    // Decoders return frames in presentation order.
    let mut pts: Vec<i64> = track.samples.iter().map(|s| s.pts).collect();
    pts.sort_unstable();
    let timestamps_s = pts
        .iter()
        .map(|&p| p as f64 / f64::from(track.timescale.max(1)))
        .collect();
    Ok(DecodedVideo {
        width: w,
        height: h,
        frames,
        timestamps_s,
    })
}

fn codec_name(codec: &TrackCodec) -> &'static str {
    match codec {
        TrackCodec::H264(_) => "H.264",
        TrackCodec::Av1(_) => "AV1",
    }
}

/// H.264 profiles by `profile_idc`; `Some(true)` for those openh264 decodes.
fn h264_profile(profile_idc: u8) -> (String, bool) {
    let (name, ok) = match profile_idc {
        66 => ("Baseline", true),
        77 => ("Main", true),
        100 => ("High", true),
        88 => ("Extended", false),
        110 => ("High 10", false),
        122 => ("High 4:2:2", false),
        244 => ("High 4:4:4 Predictive", false),
        44 => ("CAVLC 4:4:4 Intra", false),
        _ => ("profile", false),
    };
    (format!("{name} (profile_idc {profile_idc})"), ok)
}

/// The H.264 samples of `track` decoded with openh264, in presentation
/// order (the decoder reorders B-frames; no flush after each packet, the
/// rest flushed at the end).
fn decode_h264(
    path: &Path,
    data: &[u8],
    track: &VideoTrack,
    config: &H264Config,
) -> Result<Vec<Vec<u8>>, VideoError> {
    let codec_err = |frame: usize, message: String| VideoError::Codec {
        path: path.to_path_buf(),
        codec: "H.264",
        op: "decode",
        frame,
        message,
    };
    let (profile, supported) = h264_profile(config.profile_idc);
    if !supported {
        return Err(VideoError::UnsupportedProfile {
            path: path.to_path_buf(),
            codec: "H.264",
            profile,
            what_is: "8-bit 4:2:0 Baseline, Main and High are",
        });
    }
    let mut decoder = Decoder::with_api_config(
        OpenH264API::from_source(),
        DecoderConfig::new().flush_after_decode(Flush::NoFlush),
    )
    .map_err(|e| codec_err(0, e.to_string()))?;
    let (w, h) = (usize::from(track.width), usize::from(track.height));
    let mut frames = Vec::with_capacity(track.samples.len());
    let mut header = Vec::new();
    for ps in config.sps.iter().chain(&config.pps) {
        header.extend_from_slice(&[0, 0, 0, 1]);
        header.extend_from_slice(ps);
    }
    let ls = usize::from(config.nal_length_size);
    let push = |frames: &mut Vec<Vec<u8>>,
                yuv: &openh264::decoder::DecodedYUV<'_>,
                i: usize|
     -> Result<(), VideoError> {
        let (dw, dh) = yuv.dimensions();
        if (dw, dh) != (w, h) {
            return Err(codec_err(
                i,
                format!("decoded {dw}x{dh} but the container says {w}x{h}"),
            ));
        }
        let mut rgb = vec![0u8; w * h * 3];
        yuv.write_rgb8(&mut rgb);
        frames.push(rgb);
        Ok(())
    };
    for (i, s) in track.samples.iter().enumerate() {
        let start = s.offset as usize;
        let bytes = &data[start..start + s.size as usize];
        let mut packet = if i == 0 || s.sync {
            header.clone()
        } else {
            Vec::new()
        };
        let mut pos = 0;
        while pos < bytes.len() {
            let len_bytes = bytes
                .get(pos..pos + ls)
                .ok_or_else(|| codec_err(i, "truncated NAL length".into()))?;
            let len = len_bytes
                .iter()
                .fold(0usize, |a, &b| (a << 8) | usize::from(b));
            let nal = bytes.get(pos + ls..pos + ls + len).ok_or_else(|| {
                codec_err(
                    i,
                    format!(
                        "NAL of {len} bytes overruns the {}-byte sample",
                        bytes.len()
                    ),
                )
            })?;
            packet.extend_from_slice(&[0, 0, 0, 1]);
            packet.extend_from_slice(nal);
            pos += ls + len;
        }
        match decoder.decode(&packet) {
            Ok(Some(yuv)) => push(&mut frames, &yuv, i)?,
            Ok(None) => {}
            Err(e) => return Err(codec_err(i, e.to_string())),
        }
    }
    let n = track.samples.len();
    let rest = decoder
        .flush_remaining()
        .map_err(|e| codec_err(n, e.to_string()))?;
    for yuv in &rest {
        push(&mut frames, yuv, n)?;
    }
    Ok(frames)
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
