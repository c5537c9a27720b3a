//! The Kiln runtime: the thin library a wgpu renderer uses to load a Kiln archive.
//!
//! Takes an archive (any file built by `kiln build`, or one a renderer's `build.rs` compiled
//! with `kiln::Build` and embedded) and a wgpu device (made here for headless use, or the
//! application's own); gives permutations by canonical name, by dimension values or by typed
//! key id, shader modules created lazily (SPIR-V passthrough on Vulkan for trusted archives,
//! WGSL otherwise), bind group and pipeline layouts from the archive's reflection, and one
//! pipeline cache keyed by permutations and every piece of fixed-function state. Guarantees:
//! a corrupt archive, a missing permutation or a layout that does not fit its module is an
//! error naming what is wrong, never a panic or invalid API usage. It holds no scene, no
//! frames and no vertex format of its own: the bundled renderer (`kiln-renderer`, in
//! `runtime/renderer/`) is built on this public API only.
//!
//! The pieces: [`shaders`] (archive access), [`gpu`] (headless device setup), [`pipelines`]
//! (modules, layouts, pipeline cache; `spirv` checks and renumbers SPIR-V for passthrough),
//! and with the `validation` feature `validation` (the API's validation messages as test
//! failures). With the `hot-reload` feature, `hot_reload` rebuilds the permutations an edit
//! touches and names them, so a renderer can swap exactly those between frames
//! ([`pipelines::PipelineCache::carry_over`]).

#![warn(missing_docs)]

pub mod gpu;
#[cfg(feature = "hot-reload")]
pub mod hot_reload;
// Its docs name the private `spirv` module's checks, which passthrough modules pass; they
// resolve in the maintainers' docs (`--document-private-items`). pipelines.rs is being split
// on another branch: the docs of its items come with that split.
#[allow(rustdoc::private_intra_doc_links, missing_docs)]
pub mod pipelines;
pub mod shaders;
// SPIR-V checks and renumbering for passthrough: the runtime's own; public only with the
// `validation` feature, for the tests and benches that feed it hostile modules.
#[cfg(feature = "validation")]
pub mod spirv;
#[cfg(not(feature = "validation"))]
mod spirv;
#[cfg(feature = "validation")]
pub mod validation;

pub use gpu::{Backend, Gpu, GpuError, GpuOptions, ModuleSource};
pub use pipelines::{Fallback, Missing, PipelineCache, Precache, Ready};
pub use shaders::{LookupError, PermutationQuery, ShaderArchive};
