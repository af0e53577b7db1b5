//! Loading each mesh format from fixtures, and the errors for bad input.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

use bridgev2w_embodiment::mesh::load::{load_mesh, load_mesh_from_bytes, MeshError, MeshFormat};
use bridgev2w_embodiment::mesh::TriMesh;
use std::path::{Path, PathBuf};

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/mesh")
        .join(name)
}

fn load_fixture(name: &str) -> TriMesh {
    let path = fixture(name);
    load_mesh(&path).unwrap_or_else(|e| panic!("{name}: {e}"))
}

fn assert_bounds(mesh: &TriMesh, lo: [f32; 3], hi: [f32; 3]) {
    let (min, max) = mesh.bounds().expect("non-empty mesh");
    for k in 0..3 {
        assert!(
            (min[k] - lo[k]).abs() < 1e-5 && (max[k] - hi[k]).abs() < 1e-5,
            "bounds {min:?}..{max:?}, expected {lo:?}..{hi:?}"
        );
    }
}

const UNIT_LO: [f32; 3] = [-0.5; 3];
const UNIT_HI: [f32; 3] = [0.5; 3];

/// The 8 corners (index bits x, y, z) and 12 triangles of the unit cube.
fn cube() -> TriMesh {
    TriMesh::cuboid([1.0, 1.0, 1.0])
}

/// Binary STL bytes for `mesh`.
fn binary_stl(mesh: &TriMesh) -> Vec<u8> {
    mesh.to_binary_stl()
}

/// A GLB container: 12-byte header, JSON chunk, optional BIN chunk.
fn glb(json: &str, bin: &[u8]) -> Vec<u8> {
    let mut json = json.as_bytes().to_vec();
    while json.len() % 4 != 0 {
        json.push(b' ');
    }
    let mut bin = bin.to_vec();
    while bin.len() % 4 != 0 {
        bin.push(0);
    }
    let total = 12 + 8 + json.len() + if bin.is_empty() { 0 } else { 8 + bin.len() };
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&json);
    if !bin.is_empty() {
        out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
        out.extend_from_slice(b"BIN\0");
        out.extend_from_slice(&bin);
    }
    out
}

/// Cube positions (f32 xyz) followed by u16 indices.
fn cube_buffer() -> Vec<u8> {
    let c = cube();
    let mut bin = Vec::new();
    for v in &c.vertices {
        for x in v.iter() {
            bin.extend_from_slice(&x.to_le_bytes());
        }
    }
    for t in &c.triangles {
        for &i in t {
            bin.extend_from_slice(&(i as u16).to_le_bytes());
        }
    }
    bin
}

/// glTF JSON for the cube buffer (96 bytes positions + 72 bytes indices)
/// with the given `nodes` and buffer entry.
fn cube_gltf_json(nodes: &str, scene_nodes: &str, buffer: &str) -> String {
    format!(
        r#"{{
  "asset": {{"version": "2.0"}},
  "scene": 0,
  "scenes": [{{"nodes": {scene_nodes}}}],
  "nodes": {nodes},
  "meshes": [{{"primitives": [{{"attributes": {{"POSITION": 0}}, "indices": 1}}]}}],
  "buffers": [{buffer}],
  "bufferViews": [
    {{"buffer": 0, "byteOffset": 0, "byteLength": 96}},
    {{"buffer": 0, "byteOffset": 96, "byteLength": 72}}
  ],
  "accessors": [
    {{"bufferView": 0, "componentType": 5126, "count": 8, "type": "VEC3",
      "min": [-0.5, -0.5, -0.5], "max": [0.5, 0.5, 0.5]}},
    {{"bufferView": 1, "componentType": 5123, "count": 36, "type": "SCALAR"}}
  ]
}}"#
    )
}

fn plain_cube_glb() -> Vec<u8> {
    glb(
        &cube_gltf_json(r#"[{"mesh": 0}]"#, "[0]", r#"{"byteLength": 168}"#),
        &cube_buffer(),
    )
}

#[test]
fn format_from_path_is_case_insensitive() {
    let f = |p: &str| MeshFormat::from_path(Path::new(p));
    assert_eq!(f("a/b.stl"), Some(MeshFormat::Stl));
    assert_eq!(f("B.STL"), Some(MeshFormat::Stl));
    assert_eq!(f("x.Obj"), Some(MeshFormat::Obj));
    assert_eq!(f("x.DAE"), Some(MeshFormat::Collada));
    assert_eq!(f("x.gltf"), Some(MeshFormat::Gltf));
    assert_eq!(f("x.GLB"), Some(MeshFormat::Glb));
    assert_eq!(f("x.ply"), None);
    assert_eq!(f("noext"), None);
}

#[test]
fn ascii_stl_cube() {
    let m = load_fixture("cube_ascii.stl");
    assert_eq!(m.triangles.len(), 12);
    assert_eq!(m.vertices.len(), 36); // STL is not indexed
    assert_bounds(&m, UNIT_LO, UNIT_HI);
}

#[test]
fn binary_stl_cube() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cube_binary.STL");
    std::fs::write(&path, binary_stl(&cube())).unwrap();
    let m = load_mesh(&path).unwrap();
    assert_eq!(m.triangles.len(), 12);
    assert_eq!(m.vertices.len(), 36);
    assert_bounds(&m, UNIT_LO, UNIT_HI);
}

#[test]
fn a_binary_stl_whose_triangle_count_lies_is_refused() {
    let good = binary_stl(&cube());
    // The count says 13 triangles, the file holds 12: not silently 12.
    let mut lies = good.clone();
    lies[80..84].copy_from_slice(&13u32.to_le_bytes());
    let err = load_mesh_from_bytes(&lies, MeshFormat::Stl, "lies.stl")
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("lies.stl") && err.contains("13 triangles") && err.contains("734 bytes"),
        "{err}"
    );
    // A truncated file, and one whose header starts with "solid" (as some
    // binary writers do) are still read as binary.
    let err = load_mesh_from_bytes(&good[..good.len() - 10], MeshFormat::Stl, "cut.stl")
        .unwrap_err()
        .to_string();
    assert!(err.contains("should be 684 bytes"), "{err}");
    let mut solid = good;
    solid[..5].copy_from_slice(b"solid");
    let m = load_mesh_from_bytes(&solid, MeshFormat::Stl, "solid.stl").unwrap();
    assert_eq!(m.triangles.len(), 12);
}

#[test]
fn obj_quads_with_missing_mtl_are_triangulated() {
    let m = load_fixture("cube_quads.obj");
    assert_eq!(m.triangles.len(), 12);
    assert_bounds(&m, UNIT_LO, UNIT_HI);
}

#[test]
fn obj_triangles_without_mtl() {
    let m = load_fixture("cube_tris.obj");
    assert_eq!(m.triangles.len(), 12);
    assert_bounds(&m, UNIT_LO, UNIT_HI);
}

#[test]
fn obj_polygon_is_fan_triangulated() {
    let hexagon = "v 1 0 0\nv 0.5 0.8 0\nv -0.5 0.8 0\nv -1 0 0\nv -0.5 -0.8 0\nv 0.5 -0.8 0\n\
                   f 1 2 3 4 5 6\nl 1 4\np 2\n";
    let m = load_mesh_from_bytes(hexagon.as_bytes(), MeshFormat::Obj, "hexagon.obj").unwrap();
    assert_eq!(m.triangles.len(), 4);
    assert_bounds(&m, [-1.0, -0.8, 0.0], [1.0, 0.8, 0.0]);
}

#[test]
fn obj_mtllib_is_never_read_from_bytes() {
    let text = std::fs::read(fixture("cube_quads.obj")).unwrap();
    let m = load_mesh_from_bytes(&text, MeshFormat::Obj, "cube_quads.obj").unwrap();
    assert_eq!(m.triangles.len(), 12);
}

#[test]
fn collada_cube() {
    let m = load_fixture("cube.dae");
    assert_eq!(m.triangles.len(), 12);
    assert_bounds(&m, UNIT_LO, UNIT_HI);
}

#[test]
fn collada_node_transform_and_unit_are_applied() {
    let text = std::fs::read_to_string(fixture("cube.dae")).unwrap();
    let text = text.replace(
        r#"<node id="cube" name="cube" type="NODE">"#,
        r#"<node id="cube" name="cube" type="NODE"><translate>1 2 3</translate>"#,
    );
    let m = load_mesh_from_bytes(text.as_bytes(), MeshFormat::Collada, "moved.dae").unwrap();
    assert_bounds(&m, [0.5, 1.5, 2.5], [1.5, 2.5, 3.5]);
}

#[test]
fn gltf_embedded_buffer_with_node_translation_and_scale() {
    let m = load_fixture("cube_translated.gltf");
    assert_eq!(m.vertices.len(), 8);
    assert_eq!(m.triangles.len(), 12);
    // scale 2 then translate (1, 2, 3)
    assert_bounds(&m, [0.0, 1.0, 2.0], [2.0, 3.0, 4.0]);
    // The same from bytes (data-URI buffers need no file system).
    let bytes = std::fs::read(fixture("cube_translated.gltf")).unwrap();
    let b = load_mesh_from_bytes(&bytes, MeshFormat::Gltf, "cube_translated.gltf").unwrap();
    assert_eq!(b, m);
}

#[test]
fn gltf_external_buffer_resolves_relative_to_file() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("meshes")).unwrap();
    std::fs::write(dir.path().join("meshes/cube.bin"), cube_buffer()).unwrap();
    let json = cube_gltf_json(
        r#"[{"mesh": 0}]"#,
        "[0]",
        r#"{"byteLength": 168, "uri": "cube.bin"}"#,
    );
    let path = dir.path().join("meshes/cube.gltf");
    std::fs::write(&path, &json).unwrap();
    let m = load_mesh(&path).unwrap();
    assert_bounds(&m, UNIT_LO, UNIT_HI);

    let err = load_mesh_from_bytes(json.as_bytes(), MeshFormat::Gltf, "cube.gltf").unwrap_err();
    assert!(matches!(err, MeshError::Parse { .. }), "{err:?}");
    let msg = err.to_string();
    assert!(
        msg.contains("cube.gltf") && msg.contains("cube.bin"),
        "{msg}"
    );
}

#[test]
fn glb_node_hierarchy_strips_fans_and_skipped_points() {
    // Node 0 translates by (10, 0, 0) and has child node 1 whose matrix
    // rotates 90 degrees about z and scales by 2 (column-major), holding the
    // mesh. Primitives: indexed triangles (cube), an unindexed strip of 4
    // vertices (2 triangles), a fan of 5 (3 triangles), and points (skipped).
    let bin = cube_buffer();
    let json = r#"{
  "asset": {"version": "2.0"},
  "scene": 0,
  "scenes": [{"nodes": [0]}],
  "nodes": [
    {"translation": [10, 0, 0], "children": [1]},
    {"matrix": [0,2,0,0, -2,0,0,0, 0,0,2,0, 0,0,0,1], "mesh": 0}
  ],
  "meshes": [{"primitives": [
    {"attributes": {"POSITION": 0}, "indices": 1},
    {"attributes": {"POSITION": 2}, "mode": 5},
    {"attributes": {"POSITION": 3}, "mode": 6},
    {"attributes": {"POSITION": 0}, "mode": 0}
  ]}],
  "buffers": [{"byteLength": 168}],
  "bufferViews": [
    {"buffer": 0, "byteOffset": 0, "byteLength": 96},
    {"buffer": 0, "byteOffset": 96, "byteLength": 72}
  ],
  "accessors": [
    {"bufferView": 0, "componentType": 5126, "count": 8, "type": "VEC3",
     "min": [-0.5, -0.5, -0.5], "max": [0.5, 0.5, 0.5]},
    {"bufferView": 1, "componentType": 5123, "count": 36, "type": "SCALAR"},
    {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
     "min": [-0.5, -0.5, -0.5], "max": [0.5, 0.5, -0.5]},
    {"bufferView": 0, "componentType": 5126, "count": 5, "type": "VEC3",
     "min": [-0.5, -0.5, -0.5], "max": [0.5, 0.5, 0.5]}
  ]
}"#;
    let bytes = glb(json, &bin);
    let m = load_mesh_from_bytes(&bytes, MeshFormat::Glb, "tree.glb").unwrap();
    assert_eq!(m.triangles.len(), 12 + 2 + 3);
    assert_eq!(m.vertices.len(), 8 + 4 + 5);
    // Cube of side 2 rotated about z (still axis-aligned) moved to x = 10.
    assert_bounds(&m, [9.0, -1.0, -1.0], [11.0, 1.0, 1.0]);
    // (x, y) -> (-2y, 2x) + (10, 0): the first corner (-0.5, -0.5, -0.5).
    let v0 = m.vertices[0];
    assert!(
        (v0.x - 11.0).abs() < 1e-5 && (v0.y + 1.0).abs() < 1e-5,
        "{v0:?}"
    );
}

#[test]
fn same_cube_in_every_format_has_the_same_bounds() {
    let dir = tempfile::tempdir().unwrap();
    let stl = dir.path().join("cube.stl");
    std::fs::write(&stl, binary_stl(&cube())).unwrap();
    let glb_path = dir.path().join("cube.glb");
    std::fs::write(&glb_path, plain_cube_glb()).unwrap();
    let gltf_path = dir.path().join("cube.gltf");
    let untransformed = std::fs::read_to_string(fixture("cube_translated.gltf"))
        .unwrap()
        .replace(r#""translation": ["#, r#""extras_t": ["#)
        .replace(r#""scale": ["#, r#""extras_s": ["#);
    std::fs::write(&gltf_path, untransformed).unwrap();
    let paths = [
        fixture("cube_ascii.stl"),
        stl,
        fixture("cube_quads.obj"),
        fixture("cube_tris.obj"),
        fixture("cube.dae"),
        gltf_path,
        glb_path,
    ];
    for path in &paths {
        let m = load_mesh(path).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(m.triangles.len(), 12, "{}", path.display());
        assert_bounds(&m, UNIT_LO, UNIT_HI);
    }
}

// ---------------------------------------------------------------------------
// Errors

#[test]
fn missing_file_is_io_error_naming_the_path() {
    let err = load_mesh(Path::new("/no/such/dir/robot_link.stl")).unwrap_err();
    assert!(matches!(err, MeshError::Io { .. }), "{err:?}");
    assert!(
        err.to_string().contains("/no/such/dir/robot_link.stl"),
        "{err}"
    );
}

#[test]
fn unknown_extension_is_unsupported() {
    let err = load_mesh(Path::new("/tmp/whatever/link.ply")).unwrap_err();
    match &err {
        MeshError::UnsupportedFormat { extension, .. } => assert_eq!(extension, "ply"),
        other => panic!("{other:?}"),
    }
    let msg = err.to_string();
    assert!(msg.contains("link.ply"), "{msg}");
    for ext in [".stl", ".obj", ".dae", ".gltf", ".glb"] {
        assert!(msg.contains(ext), "{msg}");
    }
}

#[test]
fn garbage_is_an_error_for_every_format() {
    let garbage: Vec<u8> = (0..500u32)
        .map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8)
        .collect();
    for format in [
        MeshFormat::Stl,
        MeshFormat::Obj,
        MeshFormat::Collada,
        MeshFormat::Gltf,
        MeshFormat::Glb,
    ] {
        for bytes in [
            &garbage[..],
            b"",
            b"hello world\n",
            b"solid x\nfacet nonsense",
        ] {
            let err = load_mesh_from_bytes(bytes, format, "garbage.bin").unwrap_err();
            assert!(
                matches!(
                    err,
                    MeshError::Parse { .. } | MeshError::Invalid { .. } | MeshError::Empty { .. }
                ),
                "{format}: {err:?}"
            );
            assert!(err.to_string().contains("garbage.bin"), "{err}");
        }
    }
}

#[test]
fn obj_face_with_missing_vertex_is_an_error() {
    let text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n";
    let err = load_mesh_from_bytes(text.as_bytes(), MeshFormat::Obj, "bad.obj").unwrap_err();
    assert!(
        matches!(err, MeshError::Parse { .. } | MeshError::Invalid { .. }),
        "{err:?}"
    );
    assert!(err.to_string().contains("bad.obj"), "{err}");
}

#[test]
fn gltf_index_out_of_range_is_invalid() {
    let mut bin = cube_buffer();
    // Last index (u16) -> 99.
    let n = bin.len();
    bin[n - 2..].copy_from_slice(&99u16.to_le_bytes());
    let json = cube_gltf_json(r#"[{"mesh": 0}]"#, "[0]", r#"{"byteLength": 168}"#);
    let err = load_mesh_from_bytes(&glb(&json, &bin), MeshFormat::Glb, "oob.glb").unwrap_err();
    match &err {
        MeshError::Invalid { message, .. } => {
            assert!(
                message.contains("triangle 11 references vertex 99"),
                "{message}"
            )
        }
        other => panic!("{other:?}"),
    }
    assert!(err.to_string().contains("oob.glb"));
}

#[test]
fn nan_vertex_is_invalid() {
    let mut c = cube();
    c.vertices[3].y = f32::NAN;
    let err = load_mesh_from_bytes(&binary_stl(&c), MeshFormat::Stl, "nan.stl").unwrap_err();
    match &err {
        MeshError::Invalid { message, .. } => assert!(message.contains("non-finite"), "{message}"),
        other => panic!("{other:?}"),
    }
    assert!(err.to_string().contains("nan.stl"));

    let mut bin = cube_buffer();
    bin[4..8].copy_from_slice(&f32::INFINITY.to_le_bytes());
    let json = cube_gltf_json(r#"[{"mesh": 0}]"#, "[0]", r#"{"byteLength": 168}"#);
    let err = load_mesh_from_bytes(&glb(&json, &bin), MeshFormat::Glb, "inf.glb").unwrap_err();
    match &err {
        MeshError::Invalid { message, .. } => {
            assert!(message.contains("vertex 0 has a non-finite"), "{message}")
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn no_triangles_is_empty() {
    let text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nl 1 2\n";
    let err = load_mesh_from_bytes(text.as_bytes(), MeshFormat::Obj, "lines.obj").unwrap_err();
    assert!(matches!(err, MeshError::Empty { .. }), "{err:?}");
    assert!(err.to_string().contains("lines.obj"));

    // glTF whose only primitive is POINTS.
    let json = cube_gltf_json(r#"[{"mesh": 0}]"#, "[0]", r#"{"byteLength": 168}"#)
        .replace(r#""indices": 1}"#, r#""mode": 0}"#);
    let err = load_mesh_from_bytes(&glb(&json, &cube_buffer()), MeshFormat::Glb, "points.glb")
        .unwrap_err();
    assert!(matches!(err, MeshError::Empty { .. }), "{err:?}");
}

#[test]
fn gltf_node_cycle_is_an_error_not_a_hang() {
    let json = cube_gltf_json(
        r#"[{"mesh": 0, "children": [1]}, {"children": [0]}]"#,
        "[0]",
        r#"{"byteLength": 168}"#,
    );
    let r = load_mesh_from_bytes(&glb(&json, &cube_buffer()), MeshFormat::Glb, "cycle.glb");
    assert!(r.is_err(), "{r:?}");
}

#[test]
fn collada_huge_declared_count_is_rejected() {
    let text = std::fs::read_to_string(fixture("cube.dae"))
        .unwrap()
        .replace(r#"count="24""#, r#"count="4000000000""#);
    let err = load_mesh_from_bytes(text.as_bytes(), MeshFormat::Collada, "huge.dae").unwrap_err();
    assert!(matches!(err, MeshError::Parse { .. }), "{err:?}");
}

#[test]
fn gltf_huge_sparse_accessor_is_rejected_before_allocating() {
    // A sparse POSITION accessor without a bufferView claims 4e9 vertices
    // (zero-filled): reading it would need ~48 GB.
    let json = cube_gltf_json(r#"[{"mesh": 0}]"#, "[0]", r#"{"byteLength": 168}"#).replace(
        r#"{"bufferView": 0, "componentType": 5126, "count": 8, "type": "VEC3","#,
        r#"{"componentType": 5126, "count": 4000000000, "type": "VEC3",
      "sparse": {"count": 1, "indices": {"bufferView": 1, "componentType": 5123},
                 "values": {"bufferView": 0}},"#,
    );
    assert!(json.contains("4000000000"));
    let err = load_mesh_from_bytes(&glb(&json, &cube_buffer()), MeshFormat::Glb, "sparse.glb")
        .unwrap_err();
    match &err {
        MeshError::Invalid { message, .. } => {
            assert!(message.contains("count 4000000000 exceeds"), "{message}")
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn gltf_exponential_node_dag_is_rejected() {
    // Node i has node i+1 as a child twice: 2^24 paths to the last node.
    let nodes: Vec<String> = (0..24)
        .map(|i| format!(r#"{{"children": [{0}, {0}]}}"#, i + 1))
        .chain([r#"{"mesh": 0}"#.to_string()])
        .collect();
    let json = cube_gltf_json(
        &format!("[{}]", nodes.join(",")),
        "[0]",
        r#"{"byteLength": 168}"#,
    );
    let r = load_mesh_from_bytes(&glb(&json, &cube_buffer()), MeshFormat::Glb, "dag.glb");
    match r {
        Err(MeshError::Invalid { message, .. }) => {
            assert!(message.contains("more than 65536 nodes"), "{message}")
        }
        other => panic!("{:?}", other.map(|m| m.triangles.len())),
    }
}

#[test]
fn collada_utf16_with_bom_loads() {
    let text = std::fs::read_to_string(fixture("cube.dae")).unwrap();
    let mut bytes = vec![0xFF, 0xFE];
    for unit in text.encode_utf16() {
        bytes.extend_from_slice(&unit.to_le_bytes());
    }
    let m = load_mesh_from_bytes(&bytes, MeshFormat::Collada, "utf16.dae").unwrap();
    assert_eq!(m.triangles.len(), 12);
}
