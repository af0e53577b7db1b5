//! How embodiment masks become the mask branch's three input channels
//! (`model.mask_coding`), a setting the BridgeV2W weights record.
//!
//! The paper's masks are binary: the robot's silhouette, repeated on the
//! three channels of the "mask video" the VAE encodes. The renderer knows
//! more: which link covers each pixel (`labels.npy` of `bridgev2w masks`,
//! `labels/episode_*.npy` of `bridgev2w synth`). `links` puts that in the
//! channels too (beyond the paper, measured in `docs/results.md`), so the
//! branch can tell the upper arm from the gripper.

use crate::error::{Result, WorldModelError};
use tch::{Kind, Tensor};

/// The three mask channels of one pixel, background -1 everywhere.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MaskCoding {
    /// The paper's: robot 1, background -1, on all three channels.
    #[default]
    Binary,
    /// Link-coded (needs link labels, 1.. = the link's label, 0 = background):
    /// channel 0 the silhouette (robot 1), channel 1 a ramp over the label
    /// (`-1 + 2 (l mod 16) / 15`), channel 2 its parity (odd 1, even -1), so
    /// neighbouring links differ sharply; background -1 on every channel.
    Links,
}

crate::named_enum!(MaskCoding, WorldModelError, WorldModelError::input, "mask_coding", {
    Binary => "binary",
    Links => "links",
});

/// Labels above this ramp around (`l mod 16`).
const RAMP_PERIOD: f64 = 16.0;

impl MaskCoding {
    /// The mask channels `[.., 3, ..]` of labels `[.., 1, ..]` (any float
    /// kind; 0 = background, else robot, the link's label for `links`),
    /// concatenated along `channel_dim`.
    pub fn code(self, labels: &Tensor, channel_dim: i64) -> Tensor {
        let robot = labels.gt(0.5).to_kind(labels.kind()); // 1 robot, 0 background
        let silhouette = &robot * 2.0 - 1.0;
        match self {
            Self::Binary => Tensor::cat(&[&silhouette, &silhouette, &silhouette], channel_dim),
            Self::Links => {
                let ramp = labels.remainder(RAMP_PERIOD) * (2.0 / (RAMP_PERIOD - 1.0)) - 1.0;
                let parity = labels.remainder(2.0) * 2.0 - 1.0;
                // robot pixels take the code, background -1
                let on = |c: Tensor| &c * &robot + (&robot - 1.0);
                Tensor::cat(
                    &[silhouette.shallow_clone(), on(ramp), on(parity)],
                    channel_dim,
                )
            }
        }
    }

    /// Whether mask values `data` (0 background, else robot) can feed this
    /// coding: `links` needs link labels, which binary masks (every value 0
    /// or 1, or 0 and 255) are not. `what` names the input in the error.
    pub fn check_values(self, data: &[u8], what: &str) -> Result<()> {
        if self == Self::Links {
            let max = data.iter().copied().max().unwrap_or(0);
            let binary = data.iter().all(|&v| v == 0 || v == max) && (max == 1 || max == 255);
            if binary || max == 0 {
                return Err(WorldModelError::input(
                    what,
                    format!(
                        "binary masks (largest value {max}), but this model reads link-coded masks (mask_coding = \"links\"): pass link labels, e.g. labels.npy of `bridgev2w masks`"
                    ),
                ));
            }
        }
        Ok(())
    }
}

/// Labels `[T, H, W]` as a float tensor `[1, 1, T, H, W]`.
pub(crate) fn labels_tensor(data: &[u8], t: i64, h: i64, w: i64) -> Tensor {
    Tensor::from_slice(data)
        .to_kind(Kind::Float)
        .reshape([1, 1, t, h, w]) // [1, 1, T, H, W]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn values(t: &Tensor) -> Vec<f32> {
        Vec::<f32>::try_from(t.flatten(0, -1)).unwrap_or_default()
    }

    #[test]
    fn binary_repeats_the_silhouette_and_links_code_each_label() {
        let labels = Tensor::from_slice(&[0f32, 1.0, 2.0, 16.0, 17.0]).reshape([1, 5]);
        let b = MaskCoding::Binary.code(&labels, 0);
        assert_eq!(b.size(), [3, 5]);
        for c in 0..3 {
            assert_eq!(values(&b.get(c)), [-1.0, 1.0, 1.0, 1.0, 1.0]);
        }
        let l = MaskCoding::Links.code(&labels, 0);
        assert_eq!(values(&l.get(0)), [-1.0, 1.0, 1.0, 1.0, 1.0]);
        let ramp = values(&l.get(1));
        let want = [
            -1.0,
            -1.0 + 2.0 / 15.0,
            -1.0 + 4.0 / 15.0,
            -1.0,
            -1.0 + 2.0 / 15.0,
        ];
        for (g, w) in ramp.iter().zip(want) {
            assert!((g - w).abs() < 1e-6, "{ramp:?}");
        }
        assert_eq!(values(&l.get(2)), [-1.0, 1.0, -1.0, -1.0, 1.0]);
    }

    #[test]
    fn links_refuse_binary_masks_by_name() {
        let err = MaskCoding::Links
            .check_values(&[0, 1, 1, 0], "--masks m.npy")
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(
            err.contains("--masks m.npy") && err.contains("labels.npy"),
            "{err}"
        );
        assert!(MaskCoding::Links.check_values(&[0, 1, 3, 7], "m").is_ok());
        assert!(MaskCoding::Binary.check_values(&[0, 1], "m").is_ok());
        assert!("links".parse::<MaskCoding>().ok() == Some(MaskCoding::Links));
        assert!("depth".parse::<MaskCoding>().is_err());
    }
}
