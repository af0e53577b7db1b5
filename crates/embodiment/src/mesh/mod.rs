//! Triangle meshes: the geometry the rasterizer draws.
//!
//! [`TriMesh`] is the one mesh type of the crate. Primitives (box, cylinder,
//! sphere, capsule) are tessellated here; mesh files (STL, OBJ, COLLADA,
//! glTF/GLB) are read by [`load`].

pub mod load;

use nalgebra::Point3;
use std::f32::consts::PI;

/// An indexed triangle mesh in its own frame, metres, scale already applied.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TriMesh {
    /// Vertex positions.
    pub vertices: Vec<Point3<f32>>,
    /// Triangles as indices into `vertices` (any winding; the rasterizer is two-sided).
    pub triangles: Vec<[u32; 3]>,
}

impl TriMesh {
    /// Appends `other`, re-indexing its triangles.
    pub fn append(&mut self, other: &TriMesh) {
        let base = self.vertices.len() as u32;
        self.vertices.extend_from_slice(&other.vertices);
        self.triangles
            .extend(other.triangles.iter().map(|t| [t[0] + base, t[1] + base, t[2] + base]));
    }

    /// Multiplies every vertex coordinate by `scale` (per axis).
    pub fn scaled(mut self, scale: [f32; 3]) -> Self {
        for v in &mut self.vertices {
            v.x *= scale[0];
            v.y *= scale[1];
            v.z *= scale[2];
        }
        self
    }

    /// Axis-aligned bounds `(min, max)`, or `None` for an empty mesh.
    pub fn bounds(&self) -> Option<(Point3<f32>, Point3<f32>)> {
        let first = *self.vertices.first()?;
        Some(self.vertices.iter().fold((first, first), |(lo, hi), v| {
            (lo.inf(v), hi.sup(v))
        }))
    }

    /// An axis-aligned box centred on the origin with full side lengths `size`.
    pub fn cuboid(size: [f32; 3]) -> Self {
        let [hx, hy, hz] = [size[0] / 2.0, size[1] / 2.0, size[2] / 2.0];
        let vertices = (0..8)
            .map(|i| {
                Point3::new(
                    if i & 1 == 0 { -hx } else { hx },
                    if i & 2 == 0 { -hy } else { hy },
                    if i & 4 == 0 { -hz } else { hz },
                )
            })
            .collect();
        // Two triangles per face; corner index bits are (x, y, z).
        let triangles = vec![
            [0, 2, 1], [1, 2, 3], // z-
            [4, 5, 6], [5, 7, 6], // z+
            [0, 1, 4], [1, 5, 4], // y-
            [2, 6, 3], [3, 6, 7], // y+
            [0, 4, 2], [2, 4, 6], // x-
            [1, 3, 5], [3, 7, 5], // x+
        ];
        Self { vertices, triangles }
    }

    /// A UV sphere of `radius` with `segments` around the z axis and
    /// `segments / 2` rings from pole to pole.
    pub fn sphere(radius: f32, segments: u32) -> Self {
        Self::capsule(radius, 0.0, segments)
    }

    /// A capsule along z: a cylinder of `length` between two hemispheres of
    /// `radius` (total height `length + 2 radius`), as URDF's `<capsule>`.
    pub fn capsule(radius: f32, length: f32, segments: u32) -> Self {
        let segments = segments.max(4);
        let rings = (segments / 2).max(2);
        let half = length / 2.0;
        let mut vertices = Vec::new();
        let mut triangles = Vec::new();
        // Ring r goes from the north pole (r = 0) to the south pole (r = rings);
        // the equator is duplicated when length > 0 to form the cylinder part.
        let mut ring_rows: Vec<(f32, f32)> = Vec::new(); // (z, ring radius)
        for r in 0..=rings {
            let polar = PI * r as f32 / rings as f32;
            let (s, c) = polar.sin_cos();
            let z_offset = if 2 * r < rings {
                half
            } else if 2 * r > rings {
                -half
            } else {
                // The equator: top copy, then a bottom copy below it.
                ring_rows.push((half + radius * c, radius * s));
                -half
            };
            ring_rows.push((z_offset + radius * c, radius * s));
        }
        for &(z, rr) in &ring_rows {
            for k in 0..segments {
                let az = 2.0 * PI * k as f32 / segments as f32;
                vertices.push(Point3::new(rr * az.cos(), rr * az.sin(), z));
            }
        }
        for row in 0..ring_rows.len() as u32 - 1 {
            for k in 0..segments {
                let a = row * segments + k;
                let b = row * segments + (k + 1) % segments;
                let c = a + segments;
                let d = b + segments;
                triangles.push([a, c, b]);
                triangles.push([b, c, d]);
            }
        }
        Self { vertices, triangles }
    }

    /// A closed cylinder along z centred on the origin, as URDF's `<cylinder>`.
    pub fn cylinder(radius: f32, length: f32, segments: u32) -> Self {
        let segments = segments.max(3);
        let half = length / 2.0;
        let mut vertices = vec![Point3::new(0.0, 0.0, half), Point3::new(0.0, 0.0, -half)];
        let mut triangles = Vec::new();
        for k in 0..segments {
            let az = 2.0 * PI * k as f32 / segments as f32;
            let (s, c) = az.sin_cos();
            vertices.push(Point3::new(radius * c, radius * s, half));
            vertices.push(Point3::new(radius * c, radius * s, -half));
        }
        for k in 0..segments {
            let top_a = 2 + 2 * k;
            let bot_a = top_a + 1;
            let top_b = 2 + 2 * ((k + 1) % segments);
            let bot_b = top_b + 1;
            triangles.push([0, top_a, top_b]);
            triangles.push([1, bot_b, bot_a]);
            triangles.push([top_a, bot_a, top_b]);
            triangles.push([top_b, bot_a, bot_b]);
        }
        Self { vertices, triangles }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn max_radius(m: &TriMesh) -> f32 {
        m.vertices.iter().map(|v| v.coords.norm()).fold(0.0, f32::max)
    }

    #[test]
    fn sphere_vertices_lie_on_the_sphere() {
        let m = TriMesh::sphere(0.3, 32);
        for v in &m.vertices {
            assert!((v.coords.norm() - 0.3).abs() < 1e-5, "{v:?}");
        }
        let (lo, hi) = m.bounds().expect("non-empty");
        assert!((hi.z - 0.3).abs() < 1e-6 && (lo.z + 0.3).abs() < 1e-6);
        assert!(m.triangles.iter().flatten().all(|&i| (i as usize) < m.vertices.len()));
    }

    #[test]
    fn capsule_height_is_length_plus_two_radii() {
        let m = TriMesh::capsule(0.05, 0.2, 16);
        let (lo, hi) = m.bounds().expect("non-empty");
        assert!((hi.z - lo.z - 0.3).abs() < 1e-6, "{lo:?} {hi:?}");
        assert!(max_radius(&m) <= 0.15 + 1e-6);
    }

    #[test]
    fn cylinder_and_box_bounds() {
        let c = TriMesh::cylinder(0.1, 0.4, 24);
        let (lo, hi) = c.bounds().expect("non-empty");
        assert!((hi.z - 0.2).abs() < 1e-6 && (lo.z + 0.2).abs() < 1e-6);
        assert!((hi.x - 0.1).abs() < 1e-6);
        let b = TriMesh::cuboid([0.2, 0.4, 0.6]);
        let (lo, hi) = b.bounds().expect("non-empty");
        assert_eq!((lo.x, hi.y, hi.z), (-0.1, 0.2, 0.3));
        assert_eq!(b.triangles.len(), 12);
    }

    #[test]
    fn append_reindexes() {
        let mut a = TriMesh::cuboid([1.0; 3]);
        a.append(&TriMesh::cuboid([1.0; 3]));
        assert_eq!(a.vertices.len(), 16);
        assert_eq!(a.triangles[12], [8, 10, 9]);
    }
}
