//! The Kiln runtime: loads a Kiln archive and renders the bundled scene with wgpu.
//!
//! Takes an archive (embedded at build time from `../permutations.toml`, or any file built
//! by `kiln build`) and a headless device (Vulkan or GL, Mesa's lavapipe and llvmpipe where
//! there is no GPU); gives rendered frames and every pass's output. Guarantees: a corrupt
//! archive or a missing permutation is an error naming what is wrong, never a panic;
//! shader modules are created lazily, from SPIR-V passthrough on Vulkan where the device
//! allows it and from WGSL otherwise; bind group layouts come from the archive's
//! reflection; pipelines are cached per (permutations, fixed-function state).
//!
//! The pieces, in the order a frame uses them: [`shaders`] (archive access), [`gpu`]
//! (device setup), [`pipelines`] (modules, layouts, pipeline cache), [`scene`] (the bundled
//! scene and its GPU upload), [`frame`] (pass recording: debug groups, timestamps,
//! captures), [`passes`] (one module per pass) and [`renderer`] (the frames, one function
//! per `--pipeline`). With the `hot-reload` feature, [`hot_reload`] rebuilds the
//! permutations an edit touches and [`Renderer::reload`] swaps them between frames.

pub mod desktop;
pub mod frame;
pub mod gpu;
pub mod gpu_types;
#[cfg(feature = "hot-reload")]
pub mod hot_reload;
pub mod keys;
pub mod mobile;
pub mod passes;
pub mod pipelines;
pub mod renderer;
pub mod scene;
pub mod shaders;
pub mod spirv;
pub mod validation;

pub use gpu::{Backend, Gpu, GpuError, GpuOptions, ModuleSource};
pub use renderer::{FramePipeline, RenderError, Renderer, RendererOptions};
pub use shaders::{LookupError, PermutationQuery, ShaderArchive};

/// The archive `runtime/build.rs` compiled from `../permutations.toml`.
pub static EMBEDDED_ARCHIVE: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/shaders.kpak"));
