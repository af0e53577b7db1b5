//! H.264 decoding with openh264: samples sent one at a time in decode order
//! (length-prefixed NAL units rewritten as Annex B, the parameter sets ahead
//! of the first sample and of every sync sample), no flush after each
//! packet, so the decoder reorders B-frames itself and each picture comes
//! out in presentation order; the rest flushed at the end.

use super::VideoError;
use crate::mp4::{H264Config, VideoTrack};
use openh264::decoder::{DecodedYUV, Decoder, DecoderConfig, Flush};
use openh264::formats::YUVSource;
use openh264::OpenH264API;
use std::collections::VecDeque;
use std::path::{Path, PathBuf};

/// H.264 profiles by `profile_idc`; `true` for those openh264 decodes.
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

/// An openh264 decoder for one track, fed sample by sample.
pub(super) struct H264Decoder {
    path: PathBuf,
    decoder: Decoder,
    /// SPS and PPS as Annex B.
    header: Vec<u8>,
    /// NAL length field size.
    ls: usize,
    width: usize,
    height: usize,
    /// The Annex B packet being built (reused).
    packet: Vec<u8>,
}

impl H264Decoder {
    pub(super) fn new(
        path: &Path,
        track: &VideoTrack,
        config: &H264Config,
    ) -> Result<Self, VideoError> {
        let (profile, supported) = h264_profile(config.profile_idc);
        if !supported {
            return Err(VideoError::UnsupportedProfile {
                path: path.to_path_buf(),
                codec: "H.264",
                profile,
                what_is: "8-bit 4:2:0 Baseline, Main and High are",
            });
        }
        let decoder = Decoder::with_api_config(
            OpenH264API::from_source(),
            DecoderConfig::new().flush_after_decode(Flush::NoFlush),
        )
        .map_err(|e| codec_err(path, 0, e.to_string()))?;
        let mut header = Vec::new();
        for ps in config.sps.iter().chain(&config.pps) {
            header.extend_from_slice(&[0, 0, 0, 1]);
            header.extend_from_slice(ps);
        }
        Ok(Self {
            path: path.to_path_buf(),
            decoder,
            header,
            ls: usize::from(config.nal_length_size),
            width: usize::from(track.width),
            height: usize::from(track.height),
            packet: Vec::new(),
        })
    }

    /// Decodes sample `i` (`bytes`, `sync` if a random access point); a
    /// picture that comes out is appended to `out` as RGB8.
    pub(super) fn feed(
        &mut self,
        i: usize,
        bytes: &[u8],
        sync: bool,
        out: &mut VecDeque<Vec<u8>>,
    ) -> Result<(), VideoError> {
        self.packet.clear();
        if i == 0 || sync {
            self.packet.extend_from_slice(&self.header);
        }
        let ls = self.ls;
        let mut pos = 0;
        while pos < bytes.len() {
            let len_bytes = bytes
                .get(pos..pos + ls)
                .ok_or_else(|| codec_err(&self.path, i, "truncated NAL length".into()))?;
            let len = len_bytes
                .iter()
                .fold(0usize, |a, &b| (a << 8) | usize::from(b));
            let nal = bytes
                .get(pos + ls..(pos + ls).saturating_add(len))
                .ok_or_else(|| {
                    codec_err(
                        &self.path,
                        i,
                        format!(
                            "NAL of {len} bytes overruns the {}-byte sample",
                            bytes.len()
                        ),
                    )
                })?;
            self.packet.extend_from_slice(&[0, 0, 0, 1]);
            self.packet.extend_from_slice(nal);
            pos += ls + len;
        }
        let (path, w, h) = (&self.path, self.width, self.height);
        match self.decoder.decode(&self.packet) {
            Ok(Some(yuv)) => out.push_back(rgb(path, &yuv, w, h, i)?),
            Ok(None) => {}
            Err(e) => return Err(codec_err(path, i, e.to_string())),
        }
        Ok(())
    }

    /// Flushes the pictures the decoder still holds (after sample `n - 1`).
    pub(super) fn finish(
        &mut self,
        n: usize,
        out: &mut VecDeque<Vec<u8>>,
    ) -> Result<(), VideoError> {
        let (path, w, h) = (&self.path, self.width, self.height);
        let rest = self
            .decoder
            .flush_remaining()
            .map_err(|e| codec_err(path, n, e.to_string()))?;
        for yuv in &rest {
            out.push_back(rgb(path, yuv, w, h, n)?);
        }
        Ok(())
    }
}

fn codec_err(path: &Path, frame: usize, message: String) -> VideoError {
    VideoError::Codec {
        path: path.to_path_buf(),
        codec: "H.264",
        op: "decode",
        frame,
        message,
    }
}

/// A decoded picture as RGB8, checked against the container's size.
fn rgb(
    path: &Path,
    yuv: &DecodedYUV<'_>,
    w: usize,
    h: usize,
    i: usize,
) -> Result<Vec<u8>, VideoError> {
    let (dw, dh) = yuv.dimensions();
    if (dw, dh) != (w, h) {
        return Err(codec_err(
            path,
            i,
            format!("decoded {dw}x{dh} but the container says {w}x{h}"),
        ));
    }
    let mut rgb = vec![0u8; w * h * 3];
    yuv.write_rgb8(&mut rgb);
    Ok(rgb)
}
