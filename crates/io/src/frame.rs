//! The one float RGB frame type of bridgev2w: what the world model takes and
//! returns frame by frame, what the planners compare, and what the metrics
//! score; with the 8-bit conversions every crate shares (PNG, MP4 and
//! dataset frames are 8-bit RGB).

/// An RGB frame, row-major `[height, width, 3]`, values in `[0, 1]`.
#[derive(Debug, Clone, PartialEq)]
pub struct RgbFrame {
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
    /// Interleaved RGB values, `(y * width + x) * 3 + channel`.
    pub rgb: Vec<f32>,
}

/// A frame whose values do not fit its size, or are not numbers.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct FrameError(pub String);

impl RgbFrame {
    /// A frame from `[0, 1]` values; errors when the length is not
    /// `width * height * 3` or a value is not finite.
    pub fn new(width: usize, height: usize, rgb: Vec<f32>) -> Result<Self, FrameError> {
        if rgb.len() != width * height * 3 {
            return Err(FrameError(format!(
                "frame of {width}x{height} needs {} RGB values, got {}",
                width * height * 3,
                rgb.len()
            )));
        }
        if let Some(i) = rgb.iter().position(|v| !v.is_finite()) {
            return Err(FrameError(format!(
                "frame value {i} is {}: expected a finite number in [0, 1]",
                rgb[i]
            )));
        }
        Ok(Self { width, height, rgb })
    }

    /// A frame from 8-bit RGB ([`unit_from_u8`]: `value / 255`); errors
    /// when the length is not `width * height * 3`.
    pub fn from_rgb8(width: usize, height: usize, rgb: &[u8]) -> Result<Self, FrameError> {
        Self::new(
            width,
            height,
            rgb.iter().map(|&v| unit_from_u8(v)).collect(),
        )
    }

    /// The frame as 8-bit RGB ([`u8_from_unit`]: rounded, clamped).
    pub fn to_rgb8(&self) -> Vec<u8> {
        self.rgb.iter().map(|&v| u8_from_unit(v)).collect()
    }
}

/// An 8-bit value on `[0, 1]`: `value / 255`.
#[inline]
pub fn unit_from_u8(v: u8) -> f32 {
    f32::from(v) / 255.0
}

/// A `[0, 1]` value in 8 bits: `v * 255` rounded (half away from zero) and
/// clamped to `0..=255`; NaN gives 0.
#[inline]
pub fn u8_from_unit(v: f32) -> u8 {
    (v * 255.0).round().clamp(0.0, 255.0) as u8
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn checks_size_and_finiteness() {
        assert!(RgbFrame::new(2, 2, vec![0.0; 12]).is_ok());
        let e = RgbFrame::new(2, 2, vec![0.0; 11]).unwrap_err().to_string();
        assert_eq!(e, "frame of 2x2 needs 12 RGB values, got 11");
        let e = RgbFrame::new(1, 1, vec![0.0, f32::NAN, 0.0])
            .unwrap_err()
            .to_string();
        assert_eq!(
            e,
            "frame value 1 is NaN: expected a finite number in [0, 1]"
        );
        assert!(RgbFrame::from_rgb8(1, 1, &[0, 1]).is_err());
    }

    #[test]
    fn eight_bit_round_trip() {
        let f = RgbFrame::from_rgb8(1, 1, &[0, 128, 255]).unwrap();
        assert_eq!(f.rgb, vec![0.0, 128.0 / 255.0, 1.0]);
        assert_eq!(f.to_rgb8(), vec![0, 128, 255]);
        for b in 0..=255u8 {
            assert_eq!(u8_from_unit(unit_from_u8(b)), b);
        }
        // Out of range and not-a-number values.
        assert_eq!(u8_from_unit(-0.3), 0);
        assert_eq!(u8_from_unit(1.7), 255);
        assert_eq!(u8_from_unit(f32::NAN), 0);
        assert_eq!(u8_from_unit(f32::INFINITY), 255);
    }
}
