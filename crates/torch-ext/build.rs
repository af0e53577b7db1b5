//! Compiles the C++ shims against the headers of the libtorch that torch-sys
//! linked (its `DEP_TCH_LIBTORCH_LIB` lib dir; the headers are in the sibling
//! `include/`), with torch-sys's own flags for libtch:
//!
//! * `csrc/torch_ext.cpp`: autocast;
//! * `csrc/cpu_cache.cpp`: a caching CPU allocator;
//! * `csrc/onednn_linear.cpp`: oneDNN's inference linear layer;
//! * `csrc/cpu_attention.cpp`: bf16 attention on oneDNN's micro-kernel,
//!   optimised and with OpenMP whatever the profile (libtorch's
//!   `parallel_for` is OpenMP in its headers; the wheel's own `libgomp.so.1`,
//!   which libtorch_cpu loads, is linked);
//! * `csrc/shim_error.cpp`: C++ exceptions into the callers' error buffers;
//! * `csrc/c10d.cpp`: c10d's TCPStore and Gloo process group. The PyPI wheel
//!   ships no gloo headers (ProcessGroupGloo.hpp includes them, for pointer
//!   types only): they are looked for in `BRIDGEV2W_GLOO_INCLUDE`, libtorch's
//!   own `include/`, the venv's `include/` (where `scripts/setup-venv.sh`
//!   unpacks Debian's `libgloo-dev`) and `/usr/include`; without them the
//!   shim builds and its Gloo constructor reports what is missing;
//! * `csrc/c10d_nccl.cpp`: the NCCL process group, and `csrc/cuda_memory.cpp`:
//!   the CUDA caching allocator's figures, with the CUDA and NCCL headers of
//!   the wheel's `nvidia-*` packages, when libtorch has CUDA.

use std::path::PathBuf;

include!("../world-model/build_link.rs");

fn main() {
    let lib = std::env::var("DEP_TCH_LIBTORCH_LIB")
        .expect("torch-sys did not report its libtorch lib dir (DEP_TCH_LIBTORCH_LIB)");
    let root = PathBuf::from(&lib)
        .parent()
        .map(PathBuf::from)
        .expect("libtorch lib dir has no parent");
    // `.venv/libtorch` is a link to the wheel's `torch/`; the gloo and
    // nvidia headers are found from where it really is.
    let real_root = std::fs::canonicalize(&root).unwrap_or_else(|_| root.clone());
    let include = root.join("include");
    let api_include = include.join("torch/csrc/api/include");
    if !include.join("ATen/autocast_mode.h").is_file() {
        panic!(
            "{}: no ATen/autocast_mode.h (the libtorch headers are needed to build the autocast shim)",
            include.display()
        );
    }
    // torch-sys asks Python for the ABI of a pip wheel; torch >= 2.7 wheels
    // (and this project's 2.11) use the new C++11 ABI. Overridable like torch-sys's.
    let abi = std::env::var("LIBTORCH_CXX11_ABI").unwrap_or_else(|_| "1".into());
    println!("cargo:rerun-if-env-changed=LIBTORCH_CXX11_ABI");
    for f in [
        "csrc/torch_ext.cpp",
        "csrc/cpu_cache.cpp",
        "csrc/onednn_linear.cpp",
        "csrc/cpu_attention.cpp",
        "csrc/c10d.cpp",
        "csrc/c10d_nccl.cpp",
        "csrc/c10d_shim.h",
        "csrc/shim_error.cpp",
        "csrc/shim_error.h",
    ] {
        println!("cargo:rerun-if-changed={f}");
    }
    println!("cargo:rerun-if-env-changed=BRIDGEV2W_GLOO_INCLUDE");
    let base = || {
        let mut b = cc::Build::new();
        b.cpp(true)
            .pic(true)
            .warnings(false)
            .include(&include)
            .include(&api_include)
            .flag("-std=c++17")
            .flag(format!("-D_GLIBCXX_USE_CXX11_ABI={abi}"))
            .flag("-DGLOG_USE_GLOG_EXPORT");
        b
    };
    let mut build = base();
    build
        .file("csrc/torch_ext.cpp")
        .file("csrc/cpu_cache.cpp")
        .file("csrc/onednn_linear.cpp")
        .file("csrc/shim_error.cpp")
        .file("csrc/c10d.cpp");
    match gloo_include(&real_root) {
        Some(dir) => {
            build.include(dir).define("BV2W_HAVE_GLOO", None);
        }
        None => println!(
            "cargo:warning=no gloo headers (gloo/context.h) found: data-parallel training on the CPU \
             will be unavailable; run scripts/setup-venv.sh or set BRIDGEV2W_GLOO_INCLUDE"
        ),
    }
    if let Some(venv_include) = real_root.ancestors().nth(4).map(|v| v.join("include")) {
        if venv_include.is_dir() {
            // setup-venv.sh unpacking the gloo headers there rebuilds the shim.
            println!("cargo:rerun-if-changed={}", venv_include.display());
        }
    }
    // Before the main library on the link line: it calls shim_error.cpp's
    // reporting.
    let mut attention = base();
    attention
        .file("csrc/cpu_attention.cpp")
        .opt_level(3)
        .flag("-fopenmp");
    attention.compile("bridgev2w_torch_ext_attention");
    build.compile("bridgev2w_torch_ext");
    // NCCL in its own library: its headers pull in CUDA's (the CUDA
    // allocator's figures need the same headers).
    let mut nccl = base();
    nccl.file("csrc/c10d_nccl.cpp").file("csrc/cuda_memory.cpp");
    let cuda = PathBuf::from(&lib).join("libtorch_cuda.so").is_file();
    let nvidia = real_root.parent().map(|p| p.join("nvidia"));
    let headers = nvidia.as_ref().and_then(|n| {
        let cuda_inc = n.join("cu13/include");
        let nccl_inc = n.join("nccl/include");
        let needed = [
            cuda_inc.join("cuda_runtime_api.h"),
            cuda_inc.join("crt/host_config.h"),
            cuda_inc.join("nv/target"),
            nccl_inc.join("nccl.h"),
        ];
        needed
            .iter()
            .all(|p| p.exists())
            .then_some((cuda_inc, nccl_inc))
    });
    let with_nccl = match (cuda, headers) {
        (true, Some((cuda_inc, nccl_inc))) => {
            nccl.include(cuda_inc)
                .include(nccl_inc)
                .define("BV2W_HAVE_NCCL", None);
            true
        }
        (true, None) => {
            println!(
                "cargo:warning=libtorch has CUDA but the CUDA/NCCL headers (PyPI nvidia-cuda-runtime, \
                 nvidia-cuda-crt, nvidia-cuda-cccl, nvidia-nccl) are missing: no NCCL backend"
            );
            false
        }
        (false, _) => false,
    };
    nccl.compile("bridgev2w_torch_ext_nccl");
    // The shims call into libtorch_cpu / libc10 (after them on the link line).
    println!("cargo:rustc-link-search=native={lib}");
    if with_nccl {
        println!("cargo:rustc-link-lib=dylib=torch_cuda");
        println!("cargo:rustc-link-lib=dylib=c10_cuda");
    }
    println!("cargo:rustc-link-lib=dylib=torch_cpu");
    println!("cargo:rustc-link-lib=dylib=c10");
    // The attention shim's OpenMP calls: the runtime libtorch_cpu itself
    // needs (its lib dir holds only `libgomp.so.1`, no `libgomp.so`).
    println!("cargo:rustc-link-lib=dylib:+verbatim=libgomp.so.1");
    println!("cargo:libtorch_lib={lib}");
    // This crate's own test binaries: rpath (and libtorch_cuda kept linked).
    emit_libtorch_link_args(&lib);
}

/// The first folder holding `gloo/context.h`: `BRIDGEV2W_GLOO_INCLUDE`,
/// libtorch's `include/`, the venv's `include/` (libtorch's root is
/// `<venv>/lib/pythonX.Y/site-packages/torch`), `/usr/include`.
fn gloo_include(libtorch_root: &std::path::Path) -> Option<PathBuf> {
    let mut candidates: Vec<PathBuf> = Vec::new();
    if let Ok(dir) = std::env::var("BRIDGEV2W_GLOO_INCLUDE") {
        candidates.push(dir.into());
    }
    candidates.push(libtorch_root.join("include"));
    if let Some(venv) = libtorch_root.ancestors().nth(4) {
        candidates.push(venv.join("include"));
    }
    candidates.push("/usr/include".into());
    candidates
        .into_iter()
        .find(|d| d.join("gloo/context.h").is_file())
}
