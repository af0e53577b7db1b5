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
use std::collections::VecDeque;
use std::path::{Path, PathBuf};

fn codec_err(path: &Path, frame: usize, message: String) -> VideoError {
    VideoError::Codec {
        path: path.to_path_buf(),
        codec: "AV1",
        op: "decode",
        frame,
        message,
    }
}

/// A rav1d decoder for one track, fed sample by sample. A panic inside the
/// decoder (a corrupt stream) becomes an error naming the frame, after which
/// the decoder is not used again.
pub(super) struct Av1Decoder {
    path: PathBuf,
    decoder: Decoder,
    width: usize,
    height: usize,
    /// Pictures taken so far (for errors).
    taken: usize,
    /// A panic was caught: the decoder's state is unknown.
    broken: bool,
}

impl Av1Decoder {
    /// A decoder for `track`, sent the configuration OBUs (any picture that
    /// comes out of them is appended to `out`).
    pub(super) fn new(
        path: &Path,
        track: &VideoTrack,
        config: &Av1Config,
        out: &mut VecDeque<Vec<u8>>,
    ) -> Result<Self, VideoError> {
        if config.seq_profile > 2 {
            return Err(VideoError::UnsupportedProfile {
                path: path.to_path_buf(),
                codec: "AV1",
                profile: format!("seq_profile {}", config.seq_profile),
                what_is: "profiles 0 (Main), 1 (High) and 2 (Professional) are",
            });
        }
        let mut settings = Settings::new();
        settings.set_n_threads(1);
        settings.set_max_frame_delay(1);
        let decoder =
            Decoder::with_settings(&settings).map_err(|e| codec_err(path, 0, e.to_string()))?;
        let mut me = Self {
            path: path.to_path_buf(),
            decoder,
            width: usize::from(track.width),
            height: usize::from(track.height),
            taken: 0,
            broken: false,
        };
        if !config.config_obus.is_empty() {
            // The sequence header, ahead of the first temporal unit.
            me.guarded(0, |d| d.send(config.config_obus.clone(), 0, out))?;
        }
        Ok(me)
    }

    /// Decodes sample `i` (a temporal unit); the pictures that come out are
    /// appended to `out` as RGB8.
    pub(super) fn feed(
        &mut self,
        i: usize,
        bytes: Vec<u8>,
        out: &mut VecDeque<Vec<u8>>,
    ) -> Result<(), VideoError> {
        self.guarded(i, |d| {
            d.send(bytes, i, out)?;
            d.take(i, out)
        })
    }

    /// The pictures still held after sample `n - 1`.
    pub(super) fn finish(
        &mut self,
        n: usize,
        out: &mut VecDeque<Vec<u8>>,
    ) -> Result<(), VideoError> {
        self.guarded(n, |d| d.take(n, out))
    }

    /// Runs `step`, turning a panic inside the decoder into an error.
    fn guarded(
        &mut self,
        i: usize,
        step: impl FnOnce(&mut Self) -> Result<(), VideoError>,
    ) -> Result<(), VideoError> {
        if self.broken {
            return Err(codec_err(
                &self.path,
                i,
                "the decoder stopped at an earlier frame".into(),
            ));
        }
        let run = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| step(self)));
        match run {
            Ok(result) => result,
            Err(panic) => {
                self.broken = true;
                let what = panic
                    .downcast_ref::<String>()
                    .cloned()
                    .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                    .unwrap_or_else(|| "the decoder panicked".into());
                Err(codec_err(
                    &self.path,
                    i,
                    format!("corrupt stream (the decoder stopped: {what})"),
                ))
            }
        }
    }

    /// Drains every picture the decoder has ready.
    fn take(&mut self, i: usize, out: &mut VecDeque<Vec<u8>>) -> Result<(), VideoError> {
        loop {
            match self.decoder.get_picture() {
                Ok(pic) => {
                    out.push_back(rgb(&self.path, &pic, self.width, self.height, self.taken)?);
                    self.taken += 1;
                }
                Err(Error::Again) => return Ok(()),
                Err(e) => return Err(codec_err(&self.path, i, e.to_string())),
            }
        }
    }

    /// Sends one chunk, draining pictures whenever the decoder asks.
    fn send(
        &mut self,
        bytes: Vec<u8>,
        i: usize,
        out: &mut VecDeque<Vec<u8>>,
    ) -> Result<(), VideoError> {
        let mut result = self.decoder.send_data(bytes, None, Some(i as i64), None);
        loop {
            match result {
                Ok(()) => return Ok(()),
                Err(Error::Again) => {
                    self.take(i, out)?;
                    result = self.decoder.send_pending_data();
                }
                Err(e) => return Err(codec_err(&self.path, i, e.to_string())),
            }
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
