//! Screen vertices: mesh vertices transformed to the camera frame,
//! clip-tested and projected to fixed-point pixels, and gathered into SIMD
//! lanes per triangle.

use super::clip::Planes;
use super::{Pinhole, SUBPIXEL};
use wide::i32x4;

/// A vertex ready for rasterization: fixed-point screen position (1/256
/// pixel; bounded by the guard band, so i32 suffices), 1/z, and its clip
/// outcode (bit i set when outside clip plane i of [`Planes`]; position and
/// 1/z are only meaningful when the outcode is 0), stored as the SIMD lanes
/// `[x, y, bits of 1/z, outcode]` so that four vertices load and transpose
/// into per-field lanes cheaply.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct ScreenVertex(pub(super) wide::i32x4);

impl ScreenVertex {
    #[inline(always)]
    pub(super) fn new(x: i32, y: i32, inv_z: f32, outcode: u8) -> Self {
        Self(wide::i32x4::from([
            x,
            y,
            inv_z.to_bits() as i32,
            i32::from(outcode),
        ]))
    }

    #[inline(always)]
    pub(super) fn x(&self) -> i32 {
        self.0.as_array_ref()[0]
    }

    #[inline(always)]
    pub(super) fn y(&self) -> i32 {
        self.0.as_array_ref()[1]
    }

    #[inline(always)]
    pub(super) fn inv_z(&self) -> f32 {
        f32::from_bits(self.0.as_array_ref()[2] as u32)
    }

    #[inline(always)]
    pub(super) fn outcode(&self) -> u8 {
        self.0.as_array_ref()[3] as u8
    }
}

/// Stands in for the vertex of an out-of-range index (and for the padding
/// of the last group of four triangles): outside every clip plane, so the
/// triangle is skipped.
const INVALID_VERTEX: ScreenVertex = ScreenVertex(wide::i32x4::new([0, 0, 0, 0x1F]));

/// The vertices of four triangles (vertex indices `tris`) as SIMD lanes:
/// per triangle vertex k, `[x, y, bits of 1/z, outcode]` of the four
/// triangles. An out-of-range index gives [`INVALID_VERTEX`].
#[inline(always)]
pub(super) fn gather_x4(tris: [[u32; 3]; 4], screen: &[ScreenVertex]) -> [[i32x4; 4]; 3] {
    let vertex = |i: u32| screen.get(i as usize).copied().unwrap_or(INVALID_VERTEX).0;
    // (Explicit arrays: `array::map` is not always inlined.)
    let gather = |k: usize| {
        i32x4::transpose([
            vertex(tris[0][k]),
            vertex(tris[1][k]),
            vertex(tris[2][k]),
            vertex(tris[3][k]),
        ])
    };
    [gather(0), gather(1), gather(2)]
}

/// Maps a mesh-frame point to the camera frame with the 3x4 matrix `r`.
#[inline(always)]
pub(super) fn transform(r: &[[f32; 4]; 3], x: f32, y: f32, z: f32) -> [f32; 3] {
    [
        r[0][0] * x + r[0][1] * y + r[0][2] * z + r[0][3],
        r[1][0] * x + r[1][1] * y + r[1][2] * z + r[1][3],
        r[2][0] * x + r[2][1] * y + r[2][2] * z + r[2][3],
    ]
}

/// Transforms mesh vertices by `r`, computes their outcodes and projects
/// them into `screen` (resized to match), four at a time with SIMD. Returns
/// the OR of all outcodes. Same IEEE operations in the same order as
/// [`transform`], [`Planes::outcode`] and [`project`] (so bit-identical
/// results); position and 1/z of a vertex with a non-zero outcode are
/// unspecified (never read), which lets rounding use a plain truncating
/// conversion (exact here: guard-band coordinates are far below 2^31). Also
/// returns `[min x, max x, min y, max y]` of the fixed-point positions of
/// the vertices with outcode 0 (`i32::MAX`/`i32::MIN` when there are none).
#[inline(always)]
pub(super) fn transform_vertices(
    vertices: &[nalgebra::Point3<f32>],
    r: &[[f32; 4]; 3],
    k: &Pinhole,
    planes: &Planes,
    screen: &mut Vec<ScreenVertex>,
) -> (u8, [i32; 4]) {
    use wide::{f32x4, i32x4, CmpEq, CmpGe};
    const LANES: usize = 4;
    screen.clear();
    let m: [[f32x4; 4]; 3] = r.map(|row| row.map(f32x4::splat));
    let [near, left, right, top, bottom] = planes.planes.map(|p| p.map(f32x4::splat));
    let zero = f32x4::splat(0.0);
    let half = f32x4::splat(0.5);
    let (fx, fy) = (f32x4::splat(k.fx), f32x4::splat(k.fy));
    let (cx, cy) = (f32x4::splat(k.cx), f32x4::splat(k.cy));
    let subpixel = f32x4::splat(SUBPIXEL);
    // Four vertices: their screen vertices and outcode lanes.
    let four = |vs: &[nalgebra::Point3<f32>; LANES]| {
        let x = f32x4::from([vs[0].x, vs[1].x, vs[2].x, vs[3].x]);
        let y = f32x4::from([vs[0].y, vs[1].y, vs[2].y, vs[3].y]);
        let z = f32x4::from([vs[0].z, vs[1].z, vs[2].z, vs[3].z]);
        let p: [f32x4; 3] =
            std::array::from_fn(|i| m[i][0] * x + m[i][1] * y + m[i][2] * z + m[i][3]);
        let [px, py, pz] = p;
        // Outcode lanes: bit j set when outside plane j (d < 0 or NaN,
        // i.e. !(d >= 0)).
        let distances = [
            pz + near[3],
            left[0] * px + left[2] * pz,
            right[0] * px + right[2] * pz,
            top[1] * py + top[2] * pz,
            bottom[1] * py + bottom[2] * pz,
        ];
        let mut code = i32x4::splat(0);
        for (plane, d) in distances.iter().enumerate() {
            let outside = !bytemuck::cast::<_, i32x4>(d.cmp_ge(zero));
            code |= outside & i32x4::splat(1 << plane);
        }
        let inv_z = f32x4::splat(1.0) / pz;
        let round = |v: f32x4| (v + half.copysign(v)).fast_trunc_int();
        let sx = round((fx * px * inv_z + cx) * subpixel);
        let sy = round((fy * py * inv_z + cy) * subpixel);
        let lanes = i32x4::transpose([sx, sy, bytemuck::cast::<_, i32x4>(inv_z), code]);
        (lanes.map(ScreenVertex), code, sx, sy)
    };
    let mut any = i32x4::splat(0);
    // Bounds of the vertices inside every clip plane.
    let (mut min_x, mut max_x) = (i32x4::splat(i32::MAX), i32x4::splat(i32::MIN));
    let (mut min_y, mut max_y) = (min_x, max_x);
    let mut bound = |code: i32x4, sx: i32x4, sy: i32x4| {
        let inside = code.cmp_eq(i32x4::splat(0));
        min_x = min_x.min(inside.blend(sx, i32x4::splat(i32::MAX)));
        max_x = max_x.max(inside.blend(sx, i32x4::splat(i32::MIN)));
        min_y = min_y.min(inside.blend(sy, i32x4::splat(i32::MAX)));
        max_y = max_y.max(inside.blend(sy, i32x4::splat(i32::MIN)));
    };
    let mut chunks = vertices.chunks_exact(LANES);
    for vs in &mut chunks {
        let Ok(vs) = <&[_; LANES]>::try_from(vs) else {
            continue;
        };
        let (out, code, sx, sy) = four(vs);
        screen.extend_from_slice(&out);
        any |= code;
        bound(code, sx, sy);
    }
    let rest = chunks.remainder();
    if !rest.is_empty() {
        // Padding lanes (copies of a mesh vertex) change neither the
        // outcodes' union nor the screen vertices kept.
        let mut vs = [rest[0]; LANES];
        vs[..rest.len()].copy_from_slice(rest);
        let (out, code, sx, sy) = four(&vs);
        screen.extend_from_slice(&out[..rest.len()]);
        any |= code;
        bound(code, sx, sy);
    }
    let any = any.to_array();
    let any = any[0] | any[1] | any[2] | any[3];
    let min = |v: i32x4| v.to_array().into_iter().fold(i32::MAX, i32::min);
    let max = |v: i32x4| v.to_array().into_iter().fold(i32::MIN, i32::max);
    (any as u8, [min(min_x), max(max_x), min(min_y), max(max_y)])
}

/// Projects a camera-frame point with z >= near to fixed-point pixels.
#[inline]
pub(super) fn project(k: &Pinhole, p: &[f32; 3]) -> ScreenVertex {
    let inv_z = 1.0 / p[2];
    let u = k.fx * p[0] * inv_z + k.cx;
    let v = k.fy * p[1] * inv_z + k.cy;
    ScreenVertex::new(
        round_to_i32(u * SUBPIXEL),
        round_to_i32(v * SUBPIXEL),
        inv_z,
        0,
    )
}

/// Rounds half away from zero (saturating; NaN -> 0) without a libm call.
#[inline]
fn round_to_i32(x: f32) -> i32 {
    // Same as adding 0.5 when x >= 0 (including -0.0) and subtracting it
    // otherwise, without a branch.
    (x + 0.5f32.copysign(x)) as i32
}
