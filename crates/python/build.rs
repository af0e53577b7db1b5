//! The module links libtorch (the world model): an rpath to the lib dir of
//! the libtorch it was built against (the project venv's torch), as every
//! libtorch crate of the workspace sets for its own binaries.

include!("../world-model/build_link.rs");

fn main() {
    let lib = std::env::var("DEP_TCH_LIBTORCH_LIB")
        .expect("torch-sys did not report its libtorch lib dir (DEP_TCH_LIBTORCH_LIB)");
    emit_libtorch_link_args(&lib);
}
