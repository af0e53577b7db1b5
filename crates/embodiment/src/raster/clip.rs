//! Clipping against the near plane and the guard band around the image.

use super::{Pinhole, NEAR_PLANE_M};

/// Guard band around the image, pixels: vertices projecting further out
/// trigger clipping so fixed-point edge functions cannot overflow.
const GUARD_PX: f32 = 8192.0;

/// Clip planes in the camera frame: `a·p + d >= 0` is inside. Plane 0 is the
/// near plane, 1..=4 the guard band (left, right, top, bottom).
#[derive(Debug, Clone, Copy)]
pub(super) struct Planes {
    pub(super) planes: [[f32; 4]; 5],
}

impl Planes {
    pub(super) fn new(k: &Pinhole) -> Self {
        let (gl, gr) = (-GUARD_PX, k.width as f32 + GUARD_PX);
        let (gt, gb) = (-GUARD_PX, k.height as f32 + GUARD_PX);
        Self {
            planes: [
                [0.0, 0.0, 1.0, -NEAR_PLANE_M],
                // u >= gl  <=>  fx x + (cx - gl) z >= 0 (for z > 0)
                [k.fx, 0.0, k.cx - gl, 0.0],
                // u <= gr  <=>  -fx x + (gr - cx) z >= 0
                [-k.fx, 0.0, gr - k.cx, 0.0],
                [0.0, k.fy, k.cy - gt, 0.0],
                [0.0, -k.fy, gb - k.cy, 0.0],
            ],
        }
    }

    #[inline]
    fn distance(plane: &[f32; 4], p: &[f32; 3]) -> f32 {
        plane[0] * p[0] + plane[1] * p[1] + plane[2] * p[2] + plane[3]
    }

    /// Clip outcode of `p`: bit i set when outside plane i (NaN counts as
    /// outside). Uses the planes' structure (each ignores one or two
    /// coordinates), which gives the same distances as [`Planes::distance`]
    /// for finite points.
    #[inline]
    #[cfg(test)]
    pub(super) fn outcode(&self, p: &[f32; 3]) -> u8 {
        let [x, y, z] = *p;
        let [near, left, right, top, bottom] = &self.planes;
        let d = [
            z + near[3],
            left[0] * x + left[2] * z,
            right[0] * x + right[2] * z,
            top[1] * y + top[2] * z,
            bottom[1] * y + bottom[2] * z,
        ];
        let mut code = 0u8;
        for (i, d) in d.iter().enumerate() {
            code |= u8::from(d.is_nan() | (*d < 0.0)) << i;
        }
        code
    }
}

/// Largest clipped polygon: a triangle clipped by 5 planes.
pub(super) const MAX_POLY: usize = 8;

/// Clips the triangle `tri` against the planes flagged in `mask`; returns the
/// polygon vertex count (0 when fully clipped).
///
/// Intersections are computed from the (inside, outside) endpoint pair only,
/// so an edge shared by two triangles is clipped at bit-identical points.
pub(super) fn clip_polygon(
    tri: [[f32; 3]; 3],
    planes: &Planes,
    mask: u8,
    out: &mut [[f32; 3]; MAX_POLY],
) -> usize {
    let mut a = [[0.0f32; 3]; MAX_POLY];
    a[..3].copy_from_slice(&tri);
    let mut n = 3;
    for (i, plane) in planes.planes.iter().enumerate() {
        if mask & (1 << i) == 0 {
            continue;
        }
        let mut b = [[0.0f32; 3]; MAX_POLY];
        let mut m = 0;
        for j in 0..n {
            let cur = a[j];
            let next = a[(j + 1) % n];
            let dc = Planes::distance(plane, &cur);
            let dn = Planes::distance(plane, &next);
            let cur_in = dc >= 0.0;
            let next_in = dn >= 0.0;
            if cur_in && m < MAX_POLY {
                b[m] = cur;
                m += 1;
            }
            if cur_in != next_in && m < MAX_POLY {
                let (pi, di, po, d_o) = if cur_in {
                    (cur, dc, next, dn)
                } else {
                    (next, dn, cur, dc)
                };
                let t = di / (di - d_o);
                b[m] = [
                    pi[0] + t * (po[0] - pi[0]),
                    pi[1] + t * (po[1] - pi[1]),
                    pi[2] + t * (po[2] - pi[2]),
                ];
                m += 1;
            }
        }
        a = b;
        n = m;
        if n < 3 {
            return 0;
        }
    }
    *out = a;
    n
}
