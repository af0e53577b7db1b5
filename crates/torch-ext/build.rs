//! Compiles `csrc/torch_ext.cpp` against the headers of the libtorch that
//! torch-sys linked (its `DEP_TCH_LIBTORCH_LIB` lib dir; the headers are in
//! the sibling `include/`), with torch-sys's own flags for libtch.

use std::path::PathBuf;

include!("../world-model/build_link.rs");

fn main() {
    let lib = std::env::var("DEP_TCH_LIBTORCH_LIB")
        .expect("torch-sys did not report its libtorch lib dir (DEP_TCH_LIBTORCH_LIB)");
    let root = PathBuf::from(&lib)
        .parent()
        .map(PathBuf::from)
        .expect("libtorch lib dir has no parent");
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
    println!("cargo:rerun-if-changed=csrc/torch_ext.cpp");
    cc::Build::new()
        .cpp(true)
        .pic(true)
        .warnings(false)
        .include(&include)
        .include(&api_include)
        .flag("-std=c++17")
        .flag(format!("-D_GLIBCXX_USE_CXX11_ABI={abi}"))
        .flag("-DGLOG_USE_GLOG_EXPORT")
        .file("csrc/torch_ext.cpp")
        .compile("bridgev2w_torch_ext");
    // The shim calls into libtorch_cpu / libc10 (after it on the link line).
    println!("cargo:rustc-link-search=native={lib}");
    println!("cargo:rustc-link-lib=dylib=torch_cpu");
    println!("cargo:rustc-link-lib=dylib=c10");
    println!("cargo:libtorch_lib={lib}");
    // This crate's own test binaries: rpath (and libtorch_cuda kept linked).
    emit_libtorch_link_args(&lib);
}
