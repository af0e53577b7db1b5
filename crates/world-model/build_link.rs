// Shared by the build scripts of every crate that links libtorch (included with
// `include!`): sets an rpath to libtorch's lib dir, so binaries run without
// LD_LIBRARY_PATH, and keeps libtorch_cuda.so as a dependency even though no symbol
// of it is referenced directly (the linker's --as-needed would drop it, and with it
// CUDA support). RUNPATH is searched after LD_LIBRARY_PATH, so on another machine
// `LD_LIBRARY_PATH=<its torch>/lib` selects that machine's libtorch.
fn emit_libtorch_link_args(libtorch_lib: &str) {
    println!("cargo:rustc-link-arg=-Wl,-rpath,{libtorch_lib}");
    if std::path::Path::new(libtorch_lib)
        .join("libtorch_cuda.so")
        .exists()
    {
        println!("cargo:rustc-link-arg=-Wl,--no-as-needed,-ltorch_cuda,--as-needed");
    }
}
