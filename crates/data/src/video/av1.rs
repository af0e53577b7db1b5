//! AV1 decoding with rav1d (the pure-Rust port of dav1d, as Rerun publishes
//! it): every sample (a temporal unit) sent in decode order, one thread and
//! no frame delay, so each shown frame comes out in presentation order; the
//! pictures converted to RGB8 by [`super::yuv`]. A panic inside the decoder
//! on a corrupt stream becomes an error naming the frame.

use super::yuv::{to_rgb8, Matrix, Planes};
use super::VideoError;
use crate::mp4::{Av1Config, VideoTrack};
use re_rav1d::dav1d::pixel::{MatrixCoefficients, YUVRange};
use re_rav1d::dav1d::{Decoder, Error, Picture, PixelLayout, PlanarImageComponent, Settings};
use std::path::Path;

fn codec_err(path: &Path, frame: usize, message: String) -> VideoError {
    VideoError::Codec {
        path: path.to_path_buf(),
        codec: "AV1",
        op: "decode",
        frame,
        message,
    }
}

/// The AV1 samples of `track` as RGB8 frames, in presentation order.
pub(super) fn decode(
    path: &Path,
    data: &[u8],
    track: &VideoTrack,
    config: &Av1Config,
) -> Result<Vec<Vec<u8>>, VideoError> {
    if config.seq_profile > 2 {
        return Err(VideoError::UnsupportedProfile {
            path: path.to_path_buf(),
            codec: "AV1",
            profile: format!("seq_profile {}", config.seq_profile),
            what_is: "profiles 0 (Main), 1 (High) and 2 (Professional) are",
        });
    }
    let run = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        decode_samples(path, data, track, config)
    }));
    match run {
        Ok(result) => result,
        Err(panic) => {
            let what = panic
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_else(|| "the decoder panicked".into());
            Err(codec_err(
                path,
                0,
                format!("corrupt stream (the decoder stopped: {what})"),
            ))
        }
    }
}

fn decode_samples(
    path: &Path,
    data: &[u8],
    track: &VideoTrack,
    config: &Av1Config,
) -> Result<Vec<Vec<u8>>, VideoError> {
    let mut settings = Settings::new();
    settings.set_n_threads(1);
    settings.set_max_frame_delay(1);
    let mut decoder =
        Decoder::with_settings(&settings).map_err(|e| codec_err(path, 0, e.to_string()))?;
    let mut frames = Vec::with_capacity(track.samples.len());
    let (w, h) = (usize::from(track.width), usize::from(track.height));
    let take = |decoder: &mut Decoder, frames: &mut Vec<Vec<u8>>, i: usize| loop {
        match decoder.get_picture() {
            Ok(pic) => frames.push(rgb(path, &pic, w, h, frames.len())?),
            Err(Error::Again) => return Ok(()),
            Err(e) => return Err(codec_err(path, i, e.to_string())),
        }
    };
    if !config.config_obus.is_empty() {
        // The sequence header, ahead of the first temporal unit.
        send(
            path,
            &mut decoder,
            config.config_obus.clone(),
            0,
            &mut |d| take(d, &mut frames, 0),
        )?;
    }
    for (i, s) in track.samples.iter().enumerate() {
        let start = s.offset as usize;
        let bytes = data[start..start + s.size as usize].to_vec();
        send(path, &mut decoder, bytes, i, &mut |d| {
            take(d, &mut frames, i)
        })?;
        take(&mut decoder, &mut frames, i)?;
    }
    take(&mut decoder, &mut frames, track.samples.len())?;
    Ok(frames)
}

/// Sends one chunk, draining pictures (`take`) whenever the decoder asks.
fn send(
    path: &Path,
    decoder: &mut Decoder,
    bytes: Vec<u8>,
    i: usize,
    take: &mut dyn FnMut(&mut Decoder) -> Result<(), VideoError>,
) -> Result<(), VideoError> {
    let mut result = decoder.send_data(bytes, None, Some(i as i64), None);
    loop {
        match result {
            Ok(()) => return Ok(()),
            Err(Error::Again) => {
                take(decoder)?;
                result = decoder.send_pending_data();
            }
            Err(e) => return Err(codec_err(path, i, e.to_string())),
        }
    }
}

/// A decoded picture as RGB8, checked against the container's size.
fn rgb(
    path: &Path,
    pic: &Picture,
    w: usize,
    h: usize,
    frame: usize,
) -> Result<Vec<u8>, VideoError> {
    let (pw, ph) = (pic.width() as usize, pic.height() as usize);
    if (pw, ph) != (w, h) {
        return Err(codec_err(
            path,
            frame,
            format!("decoded {pw}x{ph} but the container says {w}x{h}"),
        ));
    }
    let (ss_x, ss_y, mono) = match pic.pixel_layout() {
        PixelLayout::I400 => (0, 0, true),
        PixelLayout::I420 => (1, 1, false),
        PixelLayout::I422 => (1, 0, false),
        PixelLayout::I444 => (0, 0, false),
    };
    let y = pic.plane(PlanarImageComponent::Y);
    let (u, v) = if mono {
        (None, None)
    } else {
        (
            Some(pic.plane(PlanarImageComponent::U)),
            Some(pic.plane(PlanarImageComponent::V)),
        )
    };
    let planes = Planes {
        y: &y,
        u: u.as_deref(),
        v: v.as_deref(),
        y_stride: pic.stride(PlanarImageComponent::Y) as usize,
        c_stride: pic.stride(PlanarImageComponent::U) as usize,
        width: w,
        height: h,
        ss_x,
        ss_y,
        bit_depth: pic.bit_depth() as u32,
    };
    let matrix = match pic.matrix_coefficients() {
        MatrixCoefficients::BT709 => Matrix::Bt709,
        MatrixCoefficients::BT2020NonConstantLuminance
        | MatrixCoefficients::BT2020ConstantLuminance => Matrix::Bt2020,
        _ => Matrix::Bt601,
    };
    let full = pic.color_range() == YUVRange::Full;
    to_rgb8(&planes, matrix, full).ok_or_else(|| {
        codec_err(
            path,
            frame,
            "a decoded plane is smaller than the picture".into(),
        )
    })
}
