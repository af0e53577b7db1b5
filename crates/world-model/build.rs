include!("build_link.rs");

fn main() {
    // Set by torch-sys (links = "tch"): the libtorch lib dir it linked against.
    let lib = std::env::var("DEP_TCH_LIBTORCH_LIB")
        .expect("torch-sys did not report its libtorch lib dir (DEP_TCH_LIBTORCH_LIB)");
    println!("cargo:libtorch_lib={lib}");
    emit_libtorch_link_args(&lib);
}
