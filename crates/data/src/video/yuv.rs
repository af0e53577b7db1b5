//! Planar YUV (any chroma subsampling, 8 to 16 bits) to interleaved RGB8,
//! with the colour matrix and range the stream signals (BT.601 when it
//! signals none, as FFmpeg's swscale assumes). Chroma is sampled at the
//! co-sited position (nearest), not interpolated.

/// The Y'CbCr matrix: luma weights `(Kr, Kb)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Matrix {
    /// BT.601 (SD; also the default when none is signalled).
    Bt601,
    /// BT.709 (HD).
    Bt709,
    /// BT.2020 non-constant luminance.
    Bt2020,
}

impl Matrix {
    fn kr_kb(self) -> (f32, f32) {
        match self {
            Self::Bt601 => (0.299, 0.114),
            Self::Bt709 => (0.2126, 0.0722),
            Self::Bt2020 => (0.2627, 0.0593),
        }
    }
}

/// One picture's planes: `y` always; `u`/`v` absent for monochrome.
/// Strides are in bytes; samples of more than 8 bits are little-endian u16.
#[derive(Debug, Clone, Copy)]
pub(super) struct Planes<'a> {
    pub y: &'a [u8],
    pub u: Option<&'a [u8]>,
    pub v: Option<&'a [u8]>,
    pub y_stride: usize,
    pub c_stride: usize,
    pub width: usize,
    pub height: usize,
    /// Chroma subsampling shifts (1, 1 for 4:2:0; 1, 0 for 4:2:2).
    pub ss_x: u32,
    pub ss_y: u32,
    pub bit_depth: u32,
}

impl Planes<'_> {
    /// The sample at `(row, col)` of `plane`, scaled to the 8-bit range.
    fn at(&self, plane: &[u8], stride: usize, row: usize, col: usize) -> Option<f32> {
        if self.bit_depth <= 8 {
            plane.get(row * stride + col).map(|&v| f32::from(v))
        } else {
            let i = row * stride + 2 * col;
            let v = u16::from_le_bytes([*plane.get(i)?, *plane.get(i + 1)?]);
            Some(f32::from(v) / (1u32 << (self.bit_depth - 8)) as f32)
        }
    }
}

/// `planes` as `height * width * 3` RGB bytes; `None` when a plane is
/// shorter than its geometry says.
pub(super) fn to_rgb8(planes: &Planes<'_>, matrix: Matrix, full_range: bool) -> Option<Vec<u8>> {
    let (kr, kb) = matrix.kr_kb();
    let kg = 1.0 - kr - kb;
    let (y_off, y_scale, c_scale) = if full_range {
        (0.0, 1.0, 1.0)
    } else {
        (16.0, 255.0 / 219.0, 255.0 / 224.0)
    };
    let (w, h) = (planes.width, planes.height);
    let mut out = vec![0u8; w * h * 3];
    let clamp = |v: f32| v.round().clamp(0.0, 255.0) as u8;
    for row in 0..h {
        let crow = row >> planes.ss_y;
        for col in 0..w {
            let luma = (planes.at(planes.y, planes.y_stride, row, col)? - y_off) * y_scale;
            let (cb, cr) = match (planes.u, planes.v) {
                (Some(u), Some(v)) => {
                    let ccol = col >> planes.ss_x;
                    (
                        (planes.at(u, planes.c_stride, crow, ccol)? - 128.0) * c_scale,
                        (planes.at(v, planes.c_stride, crow, ccol)? - 128.0) * c_scale,
                    )
                }
                _ => (0.0, 0.0),
            };
            let r = luma + 2.0 * (1.0 - kr) * cr;
            let b = luma + 2.0 * (1.0 - kb) * cb;
            let g = luma - (2.0 * kb * (1.0 - kb) / kg) * cb - (2.0 * kr * (1.0 - kr) / kg) * cr;
            let o = 3 * (row * w + col);
            out[o] = clamp(r);
            out[o + 1] = clamp(g);
            out[o + 2] = clamp(b);
        }
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn known_colours_in_bt601_limited_and_full_range() {
        // One 2x2 picture of a single colour, 4:2:0.
        let one = |y: u8, u: u8, v: u8, full: bool| {
            let (yp, up, vp) = ([y; 4], [u], [v]);
            let p = Planes {
                y: &yp,
                u: Some(&up),
                v: Some(&vp),
                y_stride: 2,
                c_stride: 1,
                width: 2,
                height: 2,
                ss_x: 1,
                ss_y: 1,
                bit_depth: 8,
            };
            to_rgb8(&p, Matrix::Bt601, full).unwrap()[..3].to_vec()
        };
        // Limited range: black, white, and BT.601 red (Y 81, Cb 90, Cr 240).
        assert_eq!(one(16, 128, 128, false), vec![0, 0, 0]);
        assert_eq!(one(235, 128, 128, false), vec![255, 255, 255]);
        let red = one(81, 90, 240, false);
        assert!(red[0] >= 253 && red[1] <= 2 && red[2] <= 2, "{red:?}");
        // Full range: grey stays grey.
        assert_eq!(one(100, 128, 128, true), vec![100, 100, 100]);
    }

    #[test]
    fn ten_bit_samples_are_scaled_and_short_planes_refused() {
        let y = 940u16.to_le_bytes(); // white at 10 bits, limited range
        let c = 512u16.to_le_bytes();
        let p = Planes {
            y: &y,
            u: Some(&c),
            v: Some(&c),
            y_stride: 2,
            c_stride: 2,
            width: 1,
            height: 1,
            ss_x: 0,
            ss_y: 0,
            bit_depth: 10,
        };
        assert_eq!(
            to_rgb8(&p, Matrix::Bt709, false).unwrap(),
            vec![255, 255, 255]
        );
        let short = Planes { width: 2, ..p };
        assert!(to_rgb8(&short, Matrix::Bt709, false).is_none());
    }
}
