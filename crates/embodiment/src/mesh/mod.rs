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
        self.triangles.extend(
            other
                .triangles
                .iter()
                .map(|t| [t[0] + base, t[1] + base, t[2] + base]),
        );
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

    /// The mesh with every vertex mapped by `b_from_a` (this mesh is in frame `a`).
    pub fn transformed(&self, b_from_a: &nalgebra::Isometry3<f64>) -> Self {
        let m = b_from_a.to_homogeneous().cast::<f32>();
        let vertices = self
            .vertices
            .iter()
            .map(|v| Point3::from_homogeneous(m * v.to_homogeneous()).unwrap_or(*v))
            .collect();
        Self {
            vertices,
            triangles: self.triangles.clone(),
        }
    }

    /// The same surface with bitwise-identical vertex positions merged and
    /// degenerate triangles (two equal corners) dropped. Mesh files often
    /// repeat a position once per face corner (for normals or texture
    /// coordinates); welding shrinks the per-vertex work of rendering
    /// without changing what is drawn.
    pub fn welded(&self) -> Self {
        let mut index_of: std::collections::HashMap<[u32; 3], u32> =
            std::collections::HashMap::with_capacity(self.vertices.len());
        let mut vertices = Vec::new();
        let remap: Vec<u32> = self
            .vertices
            .iter()
            .map(|v| {
                // +0.0 and -0.0 are the same point.
                let key = [v.x + 0.0, v.y + 0.0, v.z + 0.0].map(f32::to_bits);
                *index_of.entry(key).or_insert_with(|| {
                    vertices.push(*v);
                    (vertices.len() - 1) as u32
                })
            })
            .collect();
        let triangles = self
            .triangles
            .iter()
            .filter_map(|t| {
                let r = t.map(|i| remap.get(i as usize).copied());
                match r {
                    [Some(a), Some(b), Some(c)] if a != b && b != c && a != c => Some([a, b, c]),
                    _ => None,
                }
            })
            .collect();
        Self {
            vertices,
            triangles,
        }
    }

    /// Whether the mesh is closed and consistently oriented: every directed
    /// edge `a -> b` of a triangle appears exactly once, and so does its
    /// reverse `b -> a` (each edge borders exactly two triangles that
    /// traverse it in opposite directions). Such a mesh bounds a volume.
    pub fn is_closed(&self) -> bool {
        if self.triangles.is_empty() {
            return false;
        }
        let mut edges: std::collections::HashMap<(u32, u32), u32> =
            std::collections::HashMap::with_capacity(self.triangles.len() * 3);
        for t in &self.triangles {
            for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
                *edges.entry((a, b)).or_insert(0) += 1;
            }
        }
        edges
            .iter()
            .all(|(&(a, b), &n)| n == 1 && edges.get(&(b, a)) == Some(&1))
    }

    /// The same triangles reordered so that those of closed, consistently
    /// oriented connected components (see [`TriMesh::is_closed`]) come
    /// first, each such component wound outward (flipped when its signed
    /// volume is negative), followed by the remaining (open) components in
    /// their original order. Returns the mesh and the number of leading
    /// triangles in closed components: the renderer may skip back faces of
    /// exactly those. Components are connected through shared vertex
    /// indices, so weld ([`TriMesh::welded`]) first.
    pub fn closed_components_first(&self) -> (Self, usize) {
        let n = self.vertices.len();
        // Union-find over vertices; triangles with an out-of-range index form
        // no component and count as open.
        let mut parent: Vec<u32> = (0..n as u32).collect();
        fn find(parent: &mut [u32], mut x: u32) -> u32 {
            while parent[x as usize] != x {
                let up = parent[parent[x as usize] as usize];
                parent[x as usize] = up;
                x = up;
            }
            x
        }
        let valid = |t: &[u32; 3]| t.iter().all(|&i| (i as usize) < n);
        for t in self.triangles.iter().filter(|t| valid(t)) {
            let a = find(&mut parent, t[0]);
            for &v in &t[1..] {
                let b = find(&mut parent, v);
                parent[b as usize] = a;
            }
        }
        // Triangles grouped by component root, in first-appearance order.
        let mut groups: Vec<Vec<[u32; 3]>> = Vec::new();
        let mut group_of: std::collections::HashMap<u32, usize> = std::collections::HashMap::new();
        let mut invalid = Vec::new();
        for t in &self.triangles {
            if !valid(t) {
                invalid.push(*t);
                continue;
            }
            let root = find(&mut parent, t[0]);
            let g = *group_of.entry(root).or_insert_with(|| {
                groups.push(Vec::new());
                groups.len() - 1
            });
            groups[g].push(*t);
        }
        let mut closed = Vec::with_capacity(self.triangles.len());
        let mut open = Vec::new();
        for triangles in groups {
            let part = TriMesh {
                vertices: Vec::new(),
                triangles,
            };
            if part.is_closed() {
                let outward = self.signed_volume_of(&part.triangles) >= 0.0;
                closed.extend(part.triangles.iter().map(|t| {
                    if outward {
                        *t
                    } else {
                        [t[0], t[2], t[1]]
                    }
                }));
            } else {
                open.extend(part.triangles);
            }
        }
        let n_closed = closed.len();
        closed.extend(open);
        closed.extend(invalid);
        (
            Self {
                vertices: self.vertices.clone(),
                triangles: closed,
            },
            n_closed,
        )
    }

    fn signed_volume_of(&self, triangles: &[[u32; 3]]) -> f64 {
        triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| {
                    self.vertices
                        .get(i as usize)
                        .map_or(nalgebra::Vector3::zeros(), |v| v.coords.cast::<f64>())
                });
                a.dot(&b.cross(&c)) / 6.0
            })
            .sum()
    }

    /// The same triangles (same order) with unreferenced vertices dropped
    /// and the rest renumbered in order of first use.
    pub fn compacted(&self) -> Self {
        let mut remap = vec![u32::MAX; self.vertices.len()];
        let mut vertices = Vec::new();
        let triangles = self
            .triangles
            .iter()
            .map(|t| {
                t.map(|i| match remap.get_mut(i as usize) {
                    Some(r) => {
                        if *r == u32::MAX {
                            *r = vertices.len() as u32;
                            vertices.push(self.vertices[i as usize]);
                        }
                        *r
                    }
                    // Out of range stays out of range.
                    None => u32::MAX,
                })
            })
            .collect();
        Self {
            vertices,
            triangles,
        }
    }

    /// Signed volume (positive when triangles wind counter-clockwise seen
    /// from outside, i.e. normals point out). Meaningful for closed meshes.
    pub fn signed_volume(&self) -> f64 {
        self.signed_volume_of(&self.triangles)
    }

    /// The mesh with every triangle's winding reversed.
    pub fn flipped(mut self) -> Self {
        for t in &mut self.triangles {
            t.swap(1, 2);
        }
        self
    }

    /// The mesh as a binary STL file (80-byte header, zero normals; STL
    /// stores three corners per triangle, so shared vertices are repeated).
    pub fn to_binary_stl(&self) -> Vec<u8> {
        let mut out = vec![0u8; 80];
        let header = b"bridgev2w binary STL";
        out[..header.len()].copy_from_slice(header);
        out.extend_from_slice(&(self.triangles.len() as u32).to_le_bytes());
        for t in &self.triangles {
            out.extend_from_slice(&[0u8; 12]);
            for &i in t {
                let v = self
                    .vertices
                    .get(i as usize)
                    .copied()
                    .unwrap_or_else(Point3::origin);
                for c in v.iter() {
                    out.extend_from_slice(&c.to_le_bytes());
                }
            }
            out.extend_from_slice(&[0u8; 2]);
        }
        out
    }

    /// Axis-aligned bounds `(min, max)`, or `None` for an empty mesh.
    pub fn bounds(&self) -> Option<(Point3<f32>, Point3<f32>)> {
        let first = *self.vertices.first()?;
        Some(
            self.vertices
                .iter()
                .fold((first, first), |(lo, hi), v| (lo.inf(v), hi.sup(v))),
        )
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
            [0, 2, 1],
            [1, 2, 3], // z-
            [4, 5, 6],
            [5, 7, 6], // z+
            [0, 1, 4],
            [1, 5, 4], // y-
            [2, 6, 3],
            [3, 6, 7], // y+
            [0, 4, 2],
            [2, 4, 6], // x-
            [1, 3, 5],
            [3, 7, 5], // x+
        ];
        Self {
            vertices,
            triangles,
        }
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
            // Exact poles, so that welding closes the mesh there.
            let (s, c) = if r == 0 {
                (0.0, 1.0)
            } else if r == rings {
                (0.0, -1.0)
            } else {
                (s, c)
            };
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
        // Pole rings collapse to one vertex (and a zero-length equator band
        // disappears): the result is closed.
        Self {
            vertices,
            triangles,
        }
        .welded()
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
        Self {
            vertices,
            triangles,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn max_radius(m: &TriMesh) -> f32 {
        m.vertices
            .iter()
            .map(|v| v.coords.norm())
            .fold(0.0, f32::max)
    }

    #[test]
    fn sphere_vertices_lie_on_the_sphere() {
        let m = TriMesh::sphere(0.3, 32);
        for v in &m.vertices {
            assert!((v.coords.norm() - 0.3).abs() < 1e-5, "{v:?}");
        }
        let (lo, hi) = m.bounds().expect("non-empty");
        assert!((hi.z - 0.3).abs() < 1e-6 && (lo.z + 0.3).abs() < 1e-6);
        assert!(m
            .triangles
            .iter()
            .flatten()
            .all(|&i| (i as usize) < m.vertices.len()));
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
    fn welding_merges_repeated_positions() {
        // Two triangles of a quad with every corner stored separately.
        let p = |x: f32, y: f32| Point3::new(x, y, 0.0);
        let m = TriMesh {
            vertices: vec![
                p(0.0, 0.0),
                p(1.0, 0.0),
                p(1.0, 1.0),
                p(0.0, 0.0),
                p(1.0, 1.0),
                p(-0.0, 1.0),
                p(0.0, 0.0),
            ],
            triangles: vec![[0, 1, 2], [3, 4, 5], [0, 3, 6]],
        };
        let w = m.welded();
        assert_eq!(w.vertices.len(), 4);
        assert_eq!(w.triangles.len(), 2, "the degenerate triangle is dropped");
        for (a, b) in m.triangles.iter().zip(&w.triangles) {
            for k in 0..3 {
                let (va, vb) = (m.vertices[a[k] as usize], w.vertices[b[k] as usize]);
                assert!((va - vb).norm() == 0.0);
            }
        }
    }

    #[test]
    fn closed_meshes_and_orientation() {
        let cube = TriMesh::cuboid([1.0, 2.0, 3.0]);
        assert!(cube.is_closed());
        assert!(
            (cube.signed_volume() - 6.0).abs() < 1e-9,
            "outward: {}",
            cube.signed_volume()
        );
        assert!((cube.clone().flipped().signed_volume() + 6.0).abs() < 1e-9);
        for m in [
            TriMesh::sphere(0.5, 16),
            TriMesh::cylinder(0.2, 1.0, 16),
            TriMesh::capsule(0.2, 0.5, 16),
        ] {
            assert!(m.is_closed());
            assert!(m.signed_volume() > 0.0);
        }
        let mut open = cube.clone();
        open.triangles.pop();
        assert!(!open.is_closed());
        let mut inconsistent = cube;
        inconsistent.triangles[0].swap(1, 2);
        assert!(!inconsistent.is_closed());
    }

    #[test]
    fn closed_components_come_first_and_outward() {
        // An open cube (one triangle missing), an inward-wound closed cube
        // and an outward closed sphere in one mesh.
        let mut open = TriMesh::cuboid([1.0, 1.0, 1.0]);
        open.triangles.pop();
        let inward = TriMesh::cuboid([0.5, 0.5, 0.5])
            .transformed(&nalgebra::Isometry3::translation(3.0, 0.0, 0.0))
            .flipped();
        let sphere =
            TriMesh::sphere(0.3, 8).transformed(&nalgebra::Isometry3::translation(-3.0, 0.0, 0.0));
        let mut m = TriMesh::default();
        m.append(&open);
        m.append(&inward);
        m.append(&sphere);
        let (sorted, n_closed) = m.closed_components_first();
        assert_eq!(n_closed, inward.triangles.len() + sphere.triangles.len());
        assert_eq!(sorted.triangles.len(), m.triangles.len());
        assert_eq!(sorted.vertices, m.vertices);
        let head = TriMesh {
            vertices: sorted.vertices.clone(),
            triangles: sorted.triangles[..n_closed].to_vec(),
        };
        assert!(head.is_closed());
        let expected = 0.125 + sphere.signed_volume();
        assert!(
            (head.signed_volume() - expected).abs() < 1e-6,
            "{}",
            head.signed_volume()
        );
        // The open cube's triangles follow, unchanged and in order.
        assert_eq!(
            &sorted.triangles[n_closed..],
            &m.triangles[..open.triangles.len()]
        );
        // Same set of triangles up to winding.
        let key = |t: &[u32; 3]| {
            let mut k = *t;
            k.sort_unstable();
            k
        };
        let mut a: Vec<_> = m.triangles.iter().map(key).collect();
        let mut b: Vec<_> = sorted.triangles.iter().map(key).collect();
        a.sort_unstable();
        b.sort_unstable();
        assert_eq!(a, b);
    }

    #[test]
    fn append_reindexes() {
        let mut a = TriMesh::cuboid([1.0; 3]);
        a.append(&TriMesh::cuboid([1.0; 3]));
        assert_eq!(a.vertices.len(), 16);
        assert_eq!(a.triangles[12], [8, 10, 9]);
    }
}
