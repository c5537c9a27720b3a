//! The bundled renderer: the Unreal-style desktop and mobile frames of the bundled scene,
//! built on the thin Kiln runtime (`kiln-runtime`) and nothing but its public API.
//!
//! Takes the bundled archive (compiled by `build.rs` from `../../permutations.toml` and
//! embedded: [`embedded_archive`]) or any archive built by `kiln build`, and a device; gives
//! rendered frames and every pass's output. Every permutation is named through the typed keys
//! of the bundled set ([`keys`]); every pipeline comes from the runtime's one pipeline cache
//! (`kiln_runtime::pipelines::PipelineCache`).
//!
//! The pieces, in the order a frame uses them: [`scene`] (the bundled scene and its GPU
//! upload), [`gpu_types`] (the uniform structs, vertex layouts and target formats shared with
//! the shaders), [`frame`] (pass recording: debug groups, timestamps, captures), [`passes`]
//! (one module per pass), [`desktop`] and [`mobile`] (the frames) and [`renderer`] (one
//! function per `--pipeline`). The binary `kiln-view` renders with it.
//!
//! The runtime's modules are imported at the crate root below, so `crate::pipelines`,
//! `crate::gpu` and `crate::shaders` in this crate name `kiln_runtime`'s public modules.

// The thin runtime's public modules, by the names the frames use.
#[allow(unused_imports)]
use kiln_runtime::{gpu, pipelines, shaders};

pub mod desktop;
pub mod frame;
pub mod gpu_types;
pub mod keys;
pub mod mobile;
pub mod passes;
pub mod renderer;
pub mod scene;

pub use renderer::{FramePipeline, RenderError, Renderer, RendererOptions};

/// The archive `build.rs` compiled from `../../permutations.toml`.
pub static EMBEDDED_ARCHIVE: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/shaders.kpak"));

/// The bundled archive, trusted for SPIR-V passthrough: `build.rs` wrote it into this binary
/// with Kiln's own build.
pub fn embedded_archive() -> Result<kiln_runtime::ShaderArchive, kiln_archive::ArchiveError> {
    // SAFETY: these bytes are the archive `kiln::Build` compiled in this package's build.rs
    // and `include_bytes!` put into the binary; nothing else writes them.
    unsafe { kiln_runtime::ShaderArchive::from_static_trusted(EMBEDDED_ARCHIVE) }
}
