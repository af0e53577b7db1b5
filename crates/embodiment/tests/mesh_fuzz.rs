//! Fuzzing the mesh loaders: random bytes and mutated fixtures must give
//! `Ok` (a valid mesh) or `Err`, never a panic.
//!
//! Parser panics are caught inside the loader and reported as
//! `MeshError::Parse { message: "parser panicked: ..." }`; set
//! `MESH_FUZZ_STRICT=1` to make those fail too (to find and shrink them).
//! Inputs that once misbehaved live in `tests/data/mesh/regressions/`.

use bridgev2w_embodiment::mesh::load::{load_mesh, load_mesh_from_bytes, MeshError, MeshFormat};
use bridgev2w_embodiment::mesh::TriMesh;
use proptest::prelude::*;
use proptest::sample::Index;
use proptest::test_runner::Config;
use std::path::{Path, PathBuf};

fn data_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/mesh")
}

fn read(name: &str) -> Vec<u8> {
    std::fs::read(data_dir().join(name)).expect("fixture")
}

/// `MESH_FUZZ_STRICT=1` fails on any caught parser panic; any other value
/// fails only on panics whose message contains it.
fn strict(message: &str) -> bool {
    match std::env::var("MESH_FUZZ_STRICT") {
        Ok(filter) => filter == "1" || message.contains(&filter),
        Err(_) => false,
    }
}

/// The loader's contract on one input.
fn check(bytes: &[u8], format: MeshFormat) -> Result<(), TestCaseError> {
    match load_mesh_from_bytes(bytes, format, "fuzz-input") {
        Ok(m) => check_mesh(&m).map_err(TestCaseError::fail),
        Err(MeshError::Parse { message, .. })
            if message.starts_with("parser panicked") && strict(&message) =>
        {
            if let Some(dir) = std::env::var_os("MESH_FUZZ_DUMP") {
                let ext = match format {
                    MeshFormat::Stl => "stl",
                    MeshFormat::Obj => "obj",
                    MeshFormat::Collada => "dae",
                    MeshFormat::Gltf => "gltf",
                    MeshFormat::Glb => "glb",
                };
                let file = Path::new(&dir).join(format!("{}-{}.{ext}", bytes.len(), hash(bytes)));
                std::fs::write(file, bytes).ok();
            }
            Err(TestCaseError::fail(format!("{format}: {message}")))
        }
        Err(MeshError::Io { .. }) => Err(TestCaseError::fail("Io error from bytes")),
        Err(e) => {
            prop_assert!(e.to_string().contains("fuzz-input"), "{}", e);
            Ok(())
        }
    }
}

fn hash(bytes: &[u8]) -> u64 {
    use std::hash::{Hash, Hasher};
    let mut h = std::collections::hash_map::DefaultHasher::new();
    bytes.hash(&mut h);
    h.finish()
}

fn check_mesh(m: &TriMesh) -> Result<(), String> {
    if m.triangles.is_empty() {
        return Err("Ok with no triangles".into());
    }
    let n = m.vertices.len();
    if let Some(t) = m
        .triangles
        .iter()
        .find(|t| t.iter().any(|&i| i as usize >= n))
    {
        return Err(format!("triangle {t:?} out of range of {n} vertices"));
    }
    if m.vertices.iter().any(|v| v.iter().any(|c| !c.is_finite())) {
        return Err("non-finite vertex".into());
    }
    Ok(())
}

fn binary_stl() -> Vec<u8> {
    TriMesh::cuboid([1.0, 1.0, 1.0]).to_binary_stl()
}

/// A GLB of the glTF fixture: its data-URI buffer moved into the BIN chunk.
fn glb() -> Vec<u8> {
    let text = String::from_utf8(read("cube_translated.gltf")).expect("utf8");
    let start = text.find("\"uri\"").expect("uri");
    let end = start + text[start..].find('}').expect("end");
    let json = format!(
        "{}{}",
        text[..start].trim_end().trim_end_matches(','),
        &text[end..]
    );
    // The buffer's bytes, rebuilt exactly as the fixture script wrote them.
    let cube = TriMesh::cuboid([1.0, 1.0, 1.0]);
    let mut bin = Vec::new();
    for v in &cube.vertices {
        for c in v.iter() {
            bin.extend_from_slice(&c.to_le_bytes());
        }
    }
    for t in &cube.triangles {
        for &i in t {
            bin.extend_from_slice(&(i as u16).to_le_bytes());
        }
    }
    let mut json = json.into_bytes();
    while json.len() % 4 != 0 {
        json.push(b' ');
    }
    while bin.len() % 4 != 0 {
        bin.push(0);
    }
    let total = 12 + 8 + json.len() + 8 + bin.len();
    let mut out = Vec::new();
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&json);
    out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(&bin);
    out
}

fn seeds(format: MeshFormat) -> Vec<Vec<u8>> {
    match format {
        MeshFormat::Stl => vec![read("cube_ascii.stl"), binary_stl()],
        MeshFormat::Obj => vec![read("cube_quads.obj"), read("cube_tris.obj")],
        MeshFormat::Collada => vec![read("cube.dae")],
        MeshFormat::Gltf => vec![read("cube_translated.gltf")],
        MeshFormat::Glb => vec![glb()],
    }
}

/// Byte strings likely to upset parsers: big or negative numbers, NaN, tags.
const DICTIONARY: &[&str] = &[
    "99999999",
    "4294967295",
    "-1",
    "-2147483648",
    "nan",
    "inf",
    "1e39",
    "0",
    " ",
    "\n",
    "<",
    "/>",
    "f 1 2 3 4 5\n",
    "f -9 1 2\n",
    "v 1 2 3\n",
    "facet normal 0 0 0\n",
    "<p>0 1 2</p>",
    "<vcount>3</vcount>",
    "\"count\": 4000000000",
    "\"mode\": 5",
    "\"children\": [0]",
    "\"byteStride\": 4",
    "data:,",
];

#[derive(Debug, Clone)]
enum Mutation {
    BitFlip(Index, u8),
    Overwrite(Index, u8),
    Truncate(Index),
    Insert(Index, Vec<u8>),
    InsertWord(Index, Index),
    Remove(Index, usize),
}

fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        3 => (any::<Index>(), 0u8..8).prop_map(|(i, b)| Mutation::BitFlip(i, b)),
        2 => (any::<Index>(), any::<u8>()).prop_map(|(i, b)| Mutation::Overwrite(i, b)),
        1 => any::<Index>().prop_map(Mutation::Truncate),
        1 => (any::<Index>(), prop::collection::vec(any::<u8>(), 1..8))
            .prop_map(|(i, v)| Mutation::Insert(i, v)),
        2 => (any::<Index>(), any::<Index>()).prop_map(|(i, w)| Mutation::InsertWord(i, w)),
        1 => (any::<Index>(), 1usize..16).prop_map(|(i, n)| Mutation::Remove(i, n)),
    ]
}

fn apply(mut bytes: Vec<u8>, mutations: &[Mutation]) -> Vec<u8> {
    for m in mutations {
        let len = bytes.len();
        match m {
            Mutation::BitFlip(i, b) if len > 0 => bytes[i.index(len)] ^= 1 << b,
            Mutation::Overwrite(i, v) if len > 0 => bytes[i.index(len)] = *v,
            Mutation::Truncate(i) => bytes.truncate(i.index(len + 1)),
            Mutation::Insert(i, v) => {
                let at = i.index(len + 1);
                bytes.splice(at..at, v.iter().copied());
            }
            Mutation::InsertWord(i, w) => {
                let at = i.index(len + 1);
                let word = DICTIONARY[w.index(DICTIONARY.len())].as_bytes();
                bytes.splice(at..at, word.iter().copied());
            }
            Mutation::Remove(i, n) if len > 0 => {
                let at = i.index(len);
                bytes.drain(at..(at + n).min(len));
            }
            _ => {}
        }
    }
    bytes
}

fn config() -> Config {
    // `MESH_FUZZ_CASES` overrides the case count for longer campaigns.
    let cases = std::env::var("MESH_FUZZ_CASES")
        .ok()
        .and_then(|c| c.parse().ok())
        .unwrap_or(256);
    Config {
        cases,
        failure_persistence: None,
        ..Config::default()
    }
}

macro_rules! fuzz_format {
    ($name:ident, $format:expr) => {
        proptest! {
            #![proptest_config(config())]
            #[test]
            fn $name(
                seed in any::<Index>(),
                mutations in prop::collection::vec(mutation(), 1..6),
                random in prop::collection::vec(any::<u8>(), 0..256),
            ) {
                let seeds = seeds($format);
                let bytes = apply(seeds[seed.index(seeds.len())].clone(), &mutations);
                check(&bytes, $format)?;
                check(&random, $format)?;
            }
        }
    };
}

fuzz_format!(fuzz_stl, MeshFormat::Stl);
fuzz_format!(fuzz_obj, MeshFormat::Obj);
fuzz_format!(fuzz_collada, MeshFormat::Collada);
fuzz_format!(fuzz_gltf, MeshFormat::Gltf);
fuzz_format!(fuzz_glb, MeshFormat::Glb);

#[test]
fn seeds_load() {
    for format in [
        MeshFormat::Stl,
        MeshFormat::Obj,
        MeshFormat::Collada,
        MeshFormat::Gltf,
        MeshFormat::Glb,
    ] {
        for seed in seeds(format) {
            let m = load_mesh_from_bytes(&seed, format, "seed").expect("seed loads");
            assert_eq!(m.triangles.len(), 12);
        }
    }
}

/// Every file in `regressions/` (format by extension) must load or fail
/// cleanly, both by path and from bytes.
#[test]
fn regressions_do_not_panic() {
    let dir = data_dir().join("regressions");
    let mut seen = 0;
    for entry in std::fs::read_dir(&dir).expect("regressions dir") {
        let path = entry.expect("entry").path();
        let Some(format) = MeshFormat::from_path(&path) else {
            continue;
        };
        seen += 1;
        let bytes = std::fs::read(&path).expect("read");
        let results = [
            load_mesh(&path),
            load_mesh_from_bytes(&bytes, format, "regression"),
        ];
        for m in results.into_iter().flatten() {
            check_mesh(&m).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        }
    }
    assert!(seen > 0, "no regression files in {}", dir.display());
}

/// Triage helper: `MESH_SCAN_DIR=dir cargo test --test mesh_fuzz scan_dir -- --ignored --nocapture`
/// prints what every mesh file in `dir` gives.
#[test]
#[ignore]
fn scan_dir() {
    let Some(dir) = std::env::var_os("MESH_SCAN_DIR") else {
        return;
    };
    let mut paths: Vec<_> = std::fs::read_dir(dir)
        .expect("dir")
        .map(|e| e.expect("entry").path())
        .collect();
    paths.sort();
    for path in paths {
        let Some(format) = MeshFormat::from_path(&path) else {
            continue;
        };
        let bytes = std::fs::read(&path).expect("read");
        let outcome = match load_mesh_from_bytes(&bytes, format, "scan") {
            Ok(m) => format!("ok: {} triangles", m.triangles.len()),
            Err(e) => format!("err: {e}"),
        };
        println!("SCAN {} {outcome}", path.display());
    }
}
