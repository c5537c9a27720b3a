//! Compiles the bundled permutation set (`../../permutations.toml`, `../../shader_src/`) into
//! `OUT_DIR/shaders.kpak`, which `src/lib.rs` embeds, and writes its typed permutation keys to
//! `OUT_DIR/kiln_shaders.rs`, which `src/keys.rs` includes.
fn main() {
    kiln::Build::new("../../permutations.toml")
        .out_dir_from_env()
        .rust_bindings("kiln_shaders.rs")
        .run()
        .unwrap_or_else(|e| e.exit_for_cargo());
}
