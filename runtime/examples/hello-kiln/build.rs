//! Compiles the example's permutation set (`permutations.toml`, `shaders/`) into
//! `OUT_DIR/shaders.kpak`, which `src/lib.rs` embeds, and writes its typed permutation keys to
//! `OUT_DIR/kiln_shaders.rs`, which `src/lib.rs` includes. Editing a shader or the toml reruns
//! it (`kiln::Build` prints `cargo:rerun-if-changed` for every file a permutation read).
fn main() {
    kiln::Build::new("permutations.toml")
        .out_dir_from_env()
        .rust_bindings("kiln_shaders.rs")
        .run()
        .unwrap_or_else(|e| e.exit_for_cargo());
}
