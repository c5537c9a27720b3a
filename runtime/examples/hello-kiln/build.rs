//! Compiles the example's permutation set (`permutations.toml`, `shaders/`) into
//! `OUT_DIR/shaders.kpak`, which `src/lib.rs` embeds. Editing a shader reruns it (`kiln::Build`
//! prints `cargo:rerun-if-changed` for every file a permutation read).
fn main() {
    kiln::Build::new("permutations.toml").out_dir_from_env().run().unwrap_or_else(|e| e.exit_for_cargo());
}
