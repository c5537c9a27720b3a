//! Compiles the bundled permutation set (`../permutations.toml`, `../shader_src/`) into
//! `OUT_DIR/shaders.kpak`, which `src/lib.rs` embeds.
fn main() {
    kiln::Build::new("../permutations.toml").out_dir_from_env().run().unwrap_or_else(|e| e.exit_for_cargo());
}
