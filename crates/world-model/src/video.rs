//! Plain-data videos and mask sequences: what callers of the world model pass and
//! get back (no tch types), with conversions to the model's tensor layouts. Single
//! frames are [`RgbFrame`]s (the one frame type of every crate); their tensor
//! conversions are the free functions [`validate_image`] and [`image_to_tensor`].

use crate::error::{Result, WorldModelError};
use crate::mask_coding::labels_tensor;
pub use crate::mask_coding::MaskCoding;
use bridgev2w_io::frame::RgbFrame;
use tch::{Device, Kind, Tensor};

/// An RGB video, `[T, H, W, 3]`, values in [0, 1].
#[derive(Debug, Clone, PartialEq)]
pub struct Video {
    /// Frames.
    pub frames: usize,
    /// Rows.
    pub height: usize,
    /// Columns.
    pub width: usize,
    /// `T * H * W * 3` values in [0, 1].
    pub data: Vec<f32>,
}

/// An embodiment-mask sequence, `[T, H, W]`: 0 = background, else robot
/// (binary masks 1; link-labelled ones the link's label, for
/// [`MaskCoding::Links`]).
#[derive(Debug, Clone, PartialEq)]
pub struct MaskVideo {
    /// Frames.
    pub frames: usize,
    /// Rows.
    pub height: usize,
    /// Columns.
    pub width: usize,
    /// `T * H * W` values, 0 = background, anything else = robot.
    pub data: Vec<u8>,
}

fn check_len(name: &str, got: usize, dims: &[usize]) -> Result<()> {
    let want: usize = dims.iter().product();
    if got != want || want == 0 {
        return Err(WorldModelError::input(
            name,
            format!("{got} values for shape {dims:?} (expected {want}, non-empty)"),
        ));
    }
    Ok(())
}

/// Checks an image's size (`H * W * 3` values, non-empty) and range ([0, 1]).
pub fn validate_image(image: &RgbFrame) -> Result<()> {
    check_len("image", image.rgb.len(), &[image.height, image.width, 3])?;
    if let Some((i, v)) = image
        .rgb
        .iter()
        .enumerate()
        .find(|(_, v)| !(0.0..=1.0).contains(*v))
    {
        return Err(WorldModelError::input(
            "image",
            format!("value {v} at index {i}: expected [0, 1]"),
        ));
    }
    Ok(())
}

/// An image as `[1, 3, H, W]` in [-1, 1] (the VAE's input range).
pub fn image_to_tensor(image: &RgbFrame, device: Device, kind: Kind) -> Result<Tensor> {
    validate_image(image)?;
    let (h, w) = (image.height as i64, image.width as i64);
    Ok(Tensor::from_slice(&image.rgb)
        .reshape([h, w, 3]) // [H, W, 3]
        .permute([2, 0, 1]) // [3, H, W]
        .unsqueeze(0) // [1, 3, H, W]
        .to_device(device)
        .to_kind(kind)
        * 2.0
        - 1.0)
}

impl MaskVideo {
    /// Checks the size.
    pub fn validate(&self) -> Result<()> {
        check_len(
            "masks",
            self.data.len(),
            &[self.frames, self.height, self.width],
        )
    }

    /// The mask conditioning video `[1, 3, T, H, W]` in `coding`'s channels
    /// (the paper's, [`MaskCoding::Binary`]: robot = 1, background = -1).
    pub fn to_tensor(&self, coding: MaskCoding, device: Device, kind: Kind) -> Result<Tensor> {
        self.validate()?;
        let (t, h, w) = (self.frames as i64, self.height as i64, self.width as i64);
        let labels = labels_tensor(&self.data, t, h, w); // [1, 1, T, H, W]
        Ok(coding.code(&labels, 1).to_device(device).to_kind(kind)) // [1, 3, T, H, W]
    }
}

impl Video {
    /// Checks the size.
    pub fn validate(&self) -> Result<()> {
        check_len(
            "video",
            self.data.len(),
            &[self.frames, self.height, self.width, 3],
        )
    }

    /// From a decoded tensor `[3, T, H, W]` in [-1, 1] (clamped).
    pub fn from_tensor(t: &Tensor) -> Result<Self> {
        let size = t.size();
        if size.len() != 4 || size[0] != 3 {
            return Err(WorldModelError::input(
                "video tensor",
                format!("shape {size:?}: expected [3, T, H, W]"),
            ));
        }
        let hwc = ((t.to_kind(Kind::Float).to_device(Device::Cpu) + 1.0) / 2.0)
            .clamp(0.0, 1.0)
            .permute([1, 2, 3, 0]) // [T, H, W, 3]
            .contiguous()
            .flatten(0, -1);
        Ok(Self {
            frames: size[1] as usize,
            height: size[2] as usize,
            width: size[3] as usize,
            data: Vec::<f32>::try_from(&hwc)?,
        })
    }

    /// `[1, 3, T, H, W]` in [-1, 1].
    pub fn to_tensor(&self, device: Device, kind: Kind) -> Result<Tensor> {
        self.validate()?;
        let (t, h, w) = (self.frames as i64, self.height as i64, self.width as i64);
        Ok(Tensor::from_slice(&self.data)
            .reshape([t, h, w, 3]) // [T, H, W, 3]
            .permute([3, 0, 1, 2]) // [3, T, H, W]
            .unsqueeze(0) // [1, 3, T, H, W]
            .to_device(device)
            .to_kind(kind)
            * 2.0
            - 1.0)
    }

    /// Frame `i` as an image.
    pub fn frame(&self, i: usize) -> Option<RgbFrame> {
        let n = self.height * self.width * 3;
        (i < self.frames).then(|| RgbFrame {
            width: self.width,
            height: self.height,
            rgb: self.data[i * n..(i + 1) * n].to_vec(),
        })
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn video_tensor_round_trip_and_layouts() {
        let v = Video {
            frames: 2,
            height: 3,
            width: 4,
            data: (0..72).map(|i| i as f32 / 71.0).collect(),
        };
        let t = v.to_tensor(Device::Cpu, Kind::Float).unwrap();
        assert_eq!(t.size(), [1, 3, 2, 3, 4]);
        // pixel (t=1, y=2, x=3), channel 1 is data[((1*3+2)*4+3)*3+1]
        let idx = ((3 + 2) * 4 + 3) * 3 + 1;
        let want = v.data[idx] * 2.0 - 1.0;
        assert!((t.double_value(&[0, 1, 1, 2, 3]) as f32 - want).abs() < 1e-6);
        let back = Video::from_tensor(&t.squeeze_dim(0)).unwrap();
        for (a, b) in back.data.iter().zip(&v.data) {
            assert!((a - b).abs() < 1e-6);
        }
        assert_eq!(back.frame(1).unwrap().rgb, v.data[36..72].to_vec());
    }

    #[test]
    fn image_tensor_layout() {
        let img = RgbFrame {
            width: 3,
            height: 2,
            rgb: (0..18).map(|i| i as f32 / 17.0).collect(),
        };
        let t = image_to_tensor(&img, Device::Cpu, Kind::Float).unwrap();
        assert_eq!(t.size(), [1, 3, 2, 3]);
        // pixel (y=1, x=2), channel 2 is rgb[(1 * 3 + 2) * 3 + 2]
        let want = img.rgb[17] * 2.0 - 1.0;
        assert!((t.double_value(&[0, 2, 1, 2]) as f32 - want).abs() < 1e-6);
    }

    #[test]
    fn masks_become_plus_minus_one_on_three_channels() {
        let m = MaskVideo {
            frames: 1,
            height: 1,
            width: 2,
            data: vec![0, 1],
        };
        let t = m
            .to_tensor(MaskCoding::Binary, Device::Cpu, Kind::Float)
            .unwrap();
        assert_eq!(t.size(), [1, 3, 1, 1, 2]);
        assert_eq!(
            Vec::<f32>::try_from(t.flatten(0, -1)).unwrap(),
            vec![-1.0, 1.0, -1.0, 1.0, -1.0, 1.0]
        );
    }

    #[test]
    fn bad_sizes_and_ranges_are_errors() {
        let img = RgbFrame {
            width: 2,
            height: 2,
            rgb: vec![0.5; 11],
        };
        assert!(validate_image(&img).unwrap_err().to_string().contains("12"));
        let img = RgbFrame {
            width: 1,
            height: 1,
            rgb: vec![0.5, 1.5, 0.0],
        };
        assert!(validate_image(&img)
            .unwrap_err()
            .to_string()
            .contains("1.5"));
        assert!(image_to_tensor(&img, Device::Cpu, Kind::Float).is_err());
        let m = MaskVideo {
            frames: 0,
            height: 2,
            width: 2,
            data: vec![],
        };
        assert!(m.validate().is_err());
    }
}
