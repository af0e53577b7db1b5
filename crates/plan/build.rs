include!("../world-model/build_link.rs");

fn main() {
    // Exported by bridgev2w-world-model (links = "bridgev2w_torch").
    let lib = std::env::var("DEP_BRIDGEV2W_TORCH_LIBTORCH_LIB")
        .expect("bridgev2w-world-model did not report libtorch's lib dir");
    emit_libtorch_link_args(&lib);
}
