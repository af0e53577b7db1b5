//! Mesh files: STL, OBJ, COLLADA (via mesh-loader) and glTF/GLB (via gltf).
//!
//! Every file becomes one [`TriMesh`] in the file's root frame:
//!
//! - **STL** (binary and ASCII): all facets.
//! - **OBJ**: all groups/objects; polygons are fan-triangulated by the parser,
//!   points and lines are dropped. Materials (`mtllib`, `.mtl` files) are
//!   ignored entirely and never read.
//! - **COLLADA** (`.dae`): whatever mesh-loader applies: every `<geometry>` of
//!   `<library_geometries>` is included; node transforms of the visual scene
//!   (accumulated over parents) are applied to the geometry they instance,
//!   and `<unit meter="..">` is applied via the scene's root node. A geometry
//!   instanced several times appears only once (with one of its transforms).
//! - **glTF / GLB**: the default scene (else the first scene) is walked from
//!   its root nodes, applying node transforms (matrix or TRS), so a mesh
//!   instanced by several nodes appears once per node. A file without scenes
//!   contributes every mesh untransformed. Only triangle primitives
//!   (TRIANGLES, TRIANGLE_STRIP, TRIANGLE_FAN, converted to triangle lists)
//!   are read; points and lines are skipped.
//!
//! Results are validated (indices in range, coordinates finite, at least one
//! triangle), and the third-party parsers are run under
//! [`std::panic::catch_unwind`] so malformed input gives a [`MeshError`]
//! rather than a panic. Some declared sizes are checked before parsing so a
//! small hostile file cannot request a huge allocation, and COLLADA inputs
//! that would make mesh-loader loop forever are rejected up front.
//!
//! Caveats: a caught parser panic still runs the process's panic hook (by
//! default a "thread ... panicked at" line on stderr) before it becomes an
//! error, and catching needs `panic = "unwind"` (a `panic = "abort"` build
//! would abort on such files). Known panicking inputs are collected in
//! `tests/data/mesh/regressions/`.

use super::TriMesh;
use bridgev2w_io::quiet_panic::catch_quiet;
use nalgebra::{Matrix4, Point3};
use std::fmt;
use std::path::{Path, PathBuf};

/// Most vertices (and, separately, triangles) a loaded mesh may have.
pub const MAX_ELEMENTS: usize = 1 << 25;

/// Most glTF nodes visited while walking a scene (guards against DAG blow-up).
const MAX_NODE_VISITS: usize = 1 << 16;

/// Deepest glTF node hierarchy followed.
const MAX_NODE_DEPTH: usize = 256;

/// A mesh file format, told by the file extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum MeshFormat {
    /// STL, binary or ASCII (`.stl`).
    Stl,
    /// Wavefront OBJ (`.obj`).
    Obj,
    /// COLLADA (`.dae`).
    Collada,
    /// glTF 2.0 JSON (`.gltf`).
    Gltf,
    /// Binary glTF 2.0 (`.glb`).
    Glb,
}

/// The extensions [`MeshFormat::from_path`] knows, for messages.
pub const SUPPORTED_EXTENSIONS: &str = ".stl, .obj, .dae, .gltf, .glb";

impl MeshFormat {
    /// The format for a path's extension (case-insensitive), if supported.
    pub fn from_path(path: &Path) -> Option<MeshFormat> {
        let ext = path.extension()?.to_str()?;
        Self::from_extension(ext)
    }

    /// The format for an extension without the dot (case-insensitive).
    pub fn from_extension(ext: &str) -> Option<MeshFormat> {
        match ext.to_ascii_lowercase().as_str() {
            "stl" => Some(Self::Stl),
            "obj" => Some(Self::Obj),
            "dae" => Some(Self::Collada),
            "gltf" => Some(Self::Gltf),
            "glb" => Some(Self::Glb),
            _ => None,
        }
    }

    /// A short name of the format.
    pub fn name(self) -> &'static str {
        match self {
            Self::Stl => "STL",
            Self::Obj => "OBJ",
            Self::Collada => "COLLADA",
            Self::Gltf => "glTF",
            Self::Glb => "GLB",
        }
    }
}

impl fmt::Display for MeshFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Why a mesh file could not be loaded. Every message names the file.
#[derive(Debug, thiserror::Error)]
pub enum MeshError {
    /// The file could not be read.
    #[error("cannot read mesh file {}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The extension is not one of the supported ones.
    #[error(
        "unsupported mesh format {extension:?} for {name} (supported: {SUPPORTED_EXTENSIONS})"
    )]
    UnsupportedFormat {
        /// The file.
        name: String,
        /// Its extension (empty when it has none).
        extension: String,
    },
    /// The parser rejected the file (or panicked on it).
    #[error("cannot parse {format} mesh {name}: {message}")]
    Parse {
        /// The file.
        name: String,
        /// The format it was parsed as.
        format: MeshFormat,
        /// What went wrong.
        message: String,
    },
    /// The file parsed but its geometry is unusable.
    #[error("invalid mesh {name}: {message}")]
    Invalid {
        /// The file.
        name: String,
        /// What is wrong.
        message: String,
    },
    /// The file holds no triangles.
    #[error("mesh {name} has no triangles")]
    Empty {
        /// The file.
        name: String,
    },
}

/// Loads a mesh file, its format told by the extension.
///
/// A `.gltf` file's external buffers are resolved relative to the file.
pub fn load_mesh(path: &Path) -> Result<TriMesh, MeshError> {
    let name = path.display().to_string();
    let format = MeshFormat::from_path(path).ok_or_else(|| MeshError::UnsupportedFormat {
        name: name.clone(),
        extension: path
            .extension()
            .map(|e| e.to_string_lossy().into_owned())
            .unwrap_or_default(),
    })?;
    let bytes = std::fs::read(path).map_err(|source| MeshError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let base = match path.parent() {
        Some(p) if p.as_os_str().is_empty() => Some(Path::new(".")),
        other => other,
    };
    load_impl(&bytes, format, &name, base)
}

/// Loads a mesh from bytes; `name` is used in errors only.
///
/// A `.gltf` document whose buffers are external files cannot be resolved
/// here and gives [`MeshError::Parse`]; embedded `data:` buffers and GLB work.
pub fn load_mesh_from_bytes(
    bytes: &[u8],
    format: MeshFormat,
    name: &str,
) -> Result<TriMesh, MeshError> {
    load_impl(bytes, format, name, None)
}

fn load_impl(
    bytes: &[u8],
    format: MeshFormat,
    name: &str,
    base: Option<&Path>,
) -> Result<TriMesh, MeshError> {
    let parse_err = |message: String| MeshError::Parse {
        name: name.to_string(),
        format,
        message,
    };
    let result = catch_quiet(|| match format {
        MeshFormat::Stl => stl_precheck(bytes)
            .map_err(parse_err)
            .and_then(|()| {
                mesh_loader::stl::from_slice(bytes).map_err(|e| parse_err(e.to_string()))
            })
            .and_then(|scene| merge_scene(name, scene)),
        MeshFormat::Obj => {
            // With no path, mesh-loader never follows `mtllib`.
            mesh_loader::obj::from_slice(bytes, None, |_| -> std::io::Result<Vec<u8>> {
                Err(std::io::Error::other("materials are not read"))
            })
            .map_err(|e| parse_err(e.to_string()))
            .and_then(|scene| merge_scene(name, scene))
        }
        MeshFormat::Collada => {
            let text = collada_text(bytes).map_err(parse_err)?;
            collada_precheck(&text).map_err(parse_err)?;
            mesh_loader::collada::from_str(&text)
                .map_err(|e| parse_err(e.to_string()))
                .and_then(|scene| merge_scene(name, scene))
        }
        MeshFormat::Gltf | MeshFormat::Glb => load_gltf(bytes, name, base).map_err(|e| match e {
            GltfFail::Parse(m) => parse_err(m),
            GltfFail::Mesh(e) => e,
        }),
    });
    let mesh = match result {
        Ok(r) => r?,
        Err(what) => return Err(parse_err(format!("parser panicked: {what}"))),
    };
    validate(name, &mesh)?;
    Ok(mesh)
}

fn invalid(name: &str, message: impl Into<String>) -> MeshError {
    MeshError::Invalid {
        name: name.to_string(),
        message: message.into(),
    }
}

/// Checks indices, finiteness, size and non-emptiness of a finished mesh.
fn validate(name: &str, mesh: &TriMesh) -> Result<(), MeshError> {
    if mesh.vertices.len() > MAX_ELEMENTS || mesh.triangles.len() > MAX_ELEMENTS {
        return Err(invalid(
            name,
            format!(
                "mesh too large: {} vertices, {} triangles (limit {MAX_ELEMENTS})",
                mesh.vertices.len(),
                mesh.triangles.len()
            ),
        ));
    }
    if let Some(i) = mesh
        .vertices
        .iter()
        .position(|v| !(v.x.is_finite() && v.y.is_finite() && v.z.is_finite()))
    {
        return Err(invalid(
            name,
            format!("vertex {i} has a non-finite coordinate"),
        ));
    }
    check_indices(name, "", &mesh.triangles, mesh.vertices.len())?;
    if mesh.triangles.is_empty() {
        return Err(MeshError::Empty {
            name: name.to_string(),
        });
    }
    Ok(())
}

fn check_indices(
    name: &str,
    context: &str,
    triangles: &[[u32; 3]],
    vertex_count: usize,
) -> Result<(), MeshError> {
    for (t, tri) in triangles.iter().enumerate() {
        if let Some(&v) = tri.iter().find(|&&v| v as usize >= vertex_count) {
            return Err(invalid(
                name,
                format!(
                    "{context}triangle {t} references vertex {v} but the {} has {vertex_count} vertices",
                    if context.is_empty() { "mesh" } else { "part" }
                ),
            ));
        }
    }
    Ok(())
}

/// Appends a part, checking its own indices first (so a bad index cannot
/// silently point into another part) and the size limit.
fn append_part(
    name: &str,
    context: &str,
    out: &mut TriMesh,
    vertices: Vec<Point3<f32>>,
    triangles: &[[u32; 3]],
) -> Result<(), MeshError> {
    check_indices(name, context, triangles, vertices.len())?;
    if out.vertices.len() + vertices.len() > MAX_ELEMENTS
        || out.triangles.len() + triangles.len() > MAX_ELEMENTS
    {
        return Err(invalid(
            name,
            format!("mesh too large (limit {MAX_ELEMENTS} vertices or triangles)"),
        ));
    }
    let base = out.vertices.len() as u32;
    out.vertices.extend(vertices);
    out.triangles.extend(
        triangles
            .iter()
            .map(|t| [t[0] + base, t[1] + base, t[2] + base]),
    );
    Ok(())
}

/// Merges mesh-loader meshes (its own merge offsets faces wrongly for
/// de-indexed meshes, so it is not used).
fn merge_scene(name: &str, scene: mesh_loader::Scene) -> Result<TriMesh, MeshError> {
    let mut out = TriMesh::default();
    for (i, m) in scene.meshes.iter().enumerate() {
        let vertices = m
            .vertices
            .iter()
            .map(|v| Point3::new(v[0], v[1], v[2]))
            .collect();
        append_part(
            name,
            &format!("sub-mesh {i}: "),
            &mut out,
            vertices,
            &m.faces,
        )?;
    }
    Ok(out)
}

// ---------------------------------------------------------------------------
// COLLADA guards

/// The document as UTF-8 text (UTF-16 with a BOM is converted).
fn collada_text(bytes: &[u8]) -> Result<String, String> {
    let utf16 = |be: bool| -> Result<String, String> {
        let units: Vec<u16> = bytes[2..]
            .chunks_exact(2)
            .map(|c| {
                if be {
                    u16::from_be_bytes([c[0], c[1]])
                } else {
                    u16::from_le_bytes([c[0], c[1]])
                }
            })
            .collect();
        String::from_utf16(&units).map_err(|e| format!("invalid UTF-16: {e}"))
    };
    match bytes {
        [0xFF, 0xFE, ..] => utf16(false),
        [0xFE, 0xFF, ..] => utf16(true),
        [0xEF, 0xBB, 0xBF, rest @ ..] => {
            String::from_utf8(rest.to_vec()).map_err(|e| format!("invalid UTF-8: {e}"))
        }
        _ => String::from_utf8(bytes.to_vec()).map_err(|e| format!("invalid UTF-8: {e}")),
    }
}

/// Rejects what would make mesh-loader 0.1.13 hang or allocate absurdly:
/// a `Name_array`/`IDREF_array` inside `<library_geometries>` (its string
/// array reader never advances), `count` attributes larger than the file,
/// huge input `offset`s, and `<vcount>` entries larger than the file.
/// A binary STL (80-byte header, u32 triangle count, 50 bytes per
/// triangle) must be exactly as long as its count says: the parser would
/// otherwise read fewer triangles than the file claims, without a word. An
/// ASCII STL (`solid ...` text) is left to the parser.
fn stl_precheck(bytes: &[u8]) -> Result<(), String> {
    // Text never holds a NUL byte; a binary STL's triangle count (< 2^24)
    // always does.
    let ascii = bytes.starts_with(b"solid") && !bytes.contains(&0);
    if ascii {
        return Ok(());
    }
    let Some(count) = bytes.get(80..84) else {
        return Err(format!(
            "{} bytes: a binary STL needs an 84-byte header",
            bytes.len()
        ));
    };
    let count = u32::from_le_bytes([count[0], count[1], count[2], count[3]]);
    let expected = 84 + 50 * u64::from(count);
    if bytes.len() as u64 != expected {
        return Err(format!(
            "binary STL with {count} triangles should be {expected} bytes, but the file has {} (truncated, or a wrong triangle count)",
            bytes.len()
        ));
    }
    Ok(())
}

fn collada_precheck(text: &str) -> Result<(), String> {
    let limit = text.len() as u64;
    // String arrays inside geometries.
    let mut rest = text;
    while let Some(start) = rest.find("<library_geometries") {
        let section = &rest[start..];
        let end = section
            .find("</library_geometries")
            .unwrap_or(section.len());
        let body = &section[..end];
        if body.contains("<Name_array") || body.contains("<IDREF_array") {
            return Err("Name_array/IDREF_array in a geometry source is not supported".to_string());
        }
        rest = &section[end..];
        if end == section.len() {
            break;
        }
    }
    // Attribute values.
    for (attr, max) in [("count", limit), ("offset", 1024), ("stride", 1024)] {
        for value in attribute_values(text, attr) {
            match value.trim().parse::<u64>() {
                Ok(n) if n > max => {
                    return Err(format!("{attr}=\"{n}\" is implausibly large (limit {max})"))
                }
                _ => {}
            }
        }
    }
    // vcount entries.
    let mut rest = text;
    while let Some(start) = rest.find("<vcount>") {
        let body = &rest[start + "<vcount>".len()..];
        let end = body.find('<').unwrap_or(body.len());
        for word in body[..end].split_ascii_whitespace() {
            if let Ok(n) = word.parse::<u64>() {
                if n > limit {
                    return Err(format!("<vcount> entry {n} is implausibly large"));
                }
            }
        }
        rest = &body[end..];
    }
    Ok(())
}

/// Values of ` attr="..."` / ` attr='...'` occurrences (approximate, no XML parse).
fn attribute_values<'t>(text: &'t str, attr: &'t str) -> impl Iterator<Item = &'t str> + 't {
    text.match_indices(attr).filter_map(move |(i, _)| {
        let before = text[..i].chars().next_back()?;
        if !before.is_ascii_whitespace() {
            return None;
        }
        let after = text[i + attr.len()..].trim_start();
        let after = after.strip_prefix('=')?.trim_start();
        let quote = after.chars().next()?;
        if quote != '"' && quote != '\'' {
            return None;
        }
        let value = &after[1..];
        value.find(quote).map(|end| &value[..end])
    })
}

// ---------------------------------------------------------------------------
// glTF

enum GltfFail {
    Parse(String),
    Mesh(MeshError),
}

impl From<MeshError> for GltfFail {
    fn from(e: MeshError) -> Self {
        GltfFail::Mesh(e)
    }
}

fn load_gltf(bytes: &[u8], name: &str, base: Option<&Path>) -> Result<TriMesh, GltfFail> {
    let gltf::Gltf { document, blob } =
        gltf::Gltf::from_slice(bytes).map_err(|e| GltfFail::Parse(e.to_string()))?;
    if base.is_none() {
        for buffer in document.buffers() {
            if let gltf::buffer::Source::Uri(uri) = buffer.source() {
                if !uri.starts_with("data:") {
                    return Err(GltfFail::Parse(format!(
                        "buffer {} refers to external file {uri:?}, which cannot be resolved when \
                         loading from bytes (load the file by path instead)",
                        buffer.index()
                    )));
                }
            }
        }
    }
    let buffers = gltf::import_buffers(&document, base, blob)
        .map_err(|e| GltfFail::Parse(format!("cannot load buffers: {e}")))?;
    // Every accessor element but sparse zero-fill takes at least one byte.
    let budget = buffers.iter().map(|b| b.len()).sum::<usize>().max(64);

    let mut out = TriMesh::default();
    let scene = document
        .default_scene()
        .or_else(|| document.scenes().next());
    match scene {
        Some(scene) => {
            let mut visits = 0usize;
            let mut stack: Vec<(gltf::Node, Matrix4<f32>, usize)> =
                scene.nodes().map(|n| (n, Matrix4::identity(), 0)).collect();
            while let Some((node, parent, depth)) = stack.pop() {
                visits += 1;
                if visits > MAX_NODE_VISITS {
                    return Err(invalid(
                        name,
                        format!("scene visits more than {MAX_NODE_VISITS} nodes"),
                    )
                    .into());
                }
                if depth > MAX_NODE_DEPTH {
                    return Err(invalid(
                        name,
                        format!(
                            "node hierarchy deeper than {MAX_NODE_DEPTH} (cycle?) at node {}",
                            node.index()
                        ),
                    )
                    .into());
                }
                let local = node.transform().matrix();
                let world = parent * Matrix4::from_fn(|r, c| local[c][r]);
                if let Some(mesh) = node.mesh() {
                    add_gltf_mesh(name, &mut out, &mesh, &world, &buffers, budget)?;
                }
                for child in node.children() {
                    stack.push((child, world, depth + 1));
                }
            }
        }
        None => {
            for mesh in document.meshes() {
                add_gltf_mesh(
                    name,
                    &mut out,
                    &mesh,
                    &Matrix4::identity(),
                    &buffers,
                    budget,
                )?;
            }
        }
    }
    Ok(out)
}

fn add_gltf_mesh(
    name: &str,
    out: &mut TriMesh,
    mesh: &gltf::Mesh,
    transform: &Matrix4<f32>,
    buffers: &[gltf::buffer::Data],
    budget: usize,
) -> Result<(), GltfFail> {
    use gltf::mesh::Mode;
    for prim in mesh.primitives() {
        let mode = prim.mode();
        if !matches!(
            mode,
            Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan
        ) {
            continue;
        }
        let context = format!("mesh {} primitive {}: ", mesh.index(), prim.index());
        let too_big = |what: &str, count: usize| {
            invalid(
                name,
                format!("{context}{what} accessor count {count} exceeds the buffer data"),
            )
        };
        let pos_acc = prim
            .get(&gltf::Semantic::Positions)
            .ok_or_else(|| invalid(name, format!("{context}no POSITION attribute")))?;
        if pos_acc.count() > budget {
            return Err(too_big("POSITION", pos_acc.count()).into());
        }
        let reader = prim.reader(|b| buffers.get(b.index()).map(|d| &d.0[..]));
        let positions: Vec<Point3<f32>> = reader
            .read_positions()
            .ok_or_else(|| invalid(name, format!("{context}cannot read POSITION data")))?
            .map(|p| transform.transform_point(&Point3::new(p[0], p[1], p[2])))
            .collect();
        let indices: Vec<u32> = match prim.indices() {
            Some(acc) => {
                if acc.count() > budget {
                    return Err(too_big("index", acc.count()).into());
                }
                reader
                    .read_indices()
                    .ok_or_else(|| invalid(name, format!("{context}cannot read index data")))?
                    .into_u32()
                    .collect()
            }
            None => (0..positions.len() as u32).collect(),
        };
        let triangles: Vec<[u32; 3]> = match mode {
            Mode::Triangles => indices
                .chunks_exact(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect(),
            Mode::TriangleStrip => indices
                .windows(3)
                .enumerate()
                .map(|(i, w)| {
                    if i % 2 == 0 {
                        [w[0], w[1], w[2]]
                    } else {
                        [w[1], w[0], w[2]]
                    }
                })
                .collect(),
            _ => match indices.split_first() {
                Some((&first, rest)) => rest.windows(2).map(|w| [first, w[0], w[1]]).collect(),
                None => Vec::new(),
            },
        };
        append_part(name, &context, out, positions, &triangles)?;
    }
    Ok(())
}
