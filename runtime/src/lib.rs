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
//!
//! # Looking permutations up (no GPU needed)
//!
//! A renderer opens its archive once ([`ShaderArchive::open`] for a file, `from_static`
//! for one its `build.rs` embedded) and names permutations by dimension values; a name
//! that is not there is an error listing the nearest ones. Here the archive is written in
//! memory first, as `kiln build` would write it:
//!
//! ```
//! use kiln_runtime::{LookupError, ShaderArchive};
//! # use kiln_archive::{ArchiveWriter, DimensionRecord, PermutationRecord, Reflection, ShaderRecord, Stage, Target};
//! # let mut writer = ArchiveWriter::new();
//! # let s = writer.add_shader(ShaderRecord {
//! #     name: "Blur".into(),
//! #     level: "sm5".into(),
//! #     entry: "main".into(),
//! #     stage: Stage::Compute,
//! #     dimensions: vec![
//! #         DimensionRecord { name: "RADIUS".into(), labels: vec![] },
//! #         DimensionRecord { name: "QUALITY".into(), labels: vec!["LOW".into(), "HIGH".into()] },
//! #     ],
//! # });
//! # let r = writer.add_reflection(&Reflection {
//! #     entry: "main".into(),
//! #     stage: Stage::Compute,
//! #     bindings: vec![],
//! #     vertex_inputs: vec![],
//! #     color_outputs: vec![],
//! #     workgroup_size: Some([64, 1, 1]),
//! # });
//! # for radius in [2, 4] {
//! #     for (quality, label) in ["LOW", "HIGH"].iter().enumerate() {
//! #         let wgsl = writer.add_blob(format!("// {radius} {label}\n@compute @workgroup_size(64) fn main() {{}}").as_bytes());
//! #         writer.add_permutation(PermutationRecord {
//! #             name: format!("Blur@sm5{{RADIUS={radius},QUALITY={label}}}"),
//! #             shader: s,
//! #             values: vec![radius, quality as i64],
//! #             reflection: r,
//! #             artifacts: vec![(Target::Wgsl, wgsl)],
//! #         });
//! #     }
//! # }
//! # let bytes = writer.to_bytes()?;
//! // `bytes`: an archive of `Blur` with RADIUS in {2, 4} and QUALITY in {LOW, HIGH}.
//! let archive = ShaderArchive::from_vec(bytes)?;
//!
//! // By dimension values, in any order (an enum by label or index); the level may be left
//! // out when the shader has one.
//! let blur = archive.shader("Blur").with("QUALITY", "HIGH").with("RADIUS", 4).find()?;
//! assert_eq!(blur.name(), "Blur@sm5{RADIUS=4,QUALITY=HIGH}");
//! assert_eq!(blur.reflection().workgroup_size, Some([64, 1, 1]));
//!
//! // By canonical name; a missing one names the nearest.
//! assert!(archive.get("Blur@sm5{RADIUS=2,QUALITY=LOW}").is_ok());
//! match archive.get("Blur@sm5{RADIUS=3,QUALITY=LOW}") {
//!     Err(LookupError::Missing { nearest, .. }) => assert!(!nearest.is_empty()),
//!     other => panic!("expected a missing permutation, got {:?}", other.map(|p| p.name())),
//! }
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```
//!
//! # Drawing with it
//!
//! The whole setup, as the `hello-kiln` example (`runtime/examples/hello-kiln`) does it on
//! a headless device; a renderer with a device of its own builds a [`Gpu`] from it instead.
//!
//! ```no_run
//! use std::sync::Arc;
//!
//! use kiln_runtime::pipelines::{Blend, ColorTarget, PipelineCache, RenderState};
//! use kiln_runtime::{Gpu, GpuOptions, ShaderArchive};
//!
//! let archive = Arc::new(ShaderArchive::open("shaders.kpak".as_ref())?);
//! let gpu = Gpu::new(&GpuOptions::default())?;
//! let cache = PipelineCache::new(&gpu, archive);
//! // Modules (SPIR-V passthrough or WGSL), bind group layouts from the reflection of both
//! // stages and the pipeline are created on first use, then found by key.
//! let state = RenderState::fullscreen(ColorTarget::new(wgpu::TextureFormat::Rgba8Unorm, Blend::Replace));
//! let pipeline = cache.render("HelloVS@portable{SHAPE=QUAD}", Some("HelloPS@portable{PALETTE=WARM,TINT=0}"), &state)?;
//! // Bind groups by the resources' names in the shader; none for this pair.
//! let resources: Vec<(&str, wgpu::BindingResource)> = Vec::new();
//! for group in 0..pipeline.layout.groups.len() as u32 {
//!     let _bind_group = pipeline.layout.bind_group(&gpu.device, group, "hello", &resources)?;
//! }
//! // `pipeline.pipeline` is a `wgpu::RenderPipeline`: set it in a render pass and draw.
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

#![warn(missing_docs)]

pub mod gpu;
#[cfg(feature = "hot-reload")]
pub mod hot_reload;
// Its docs name the private `spirv` module's checks, which passthrough modules pass; they
// resolve in the maintainers' docs (`--document-private-items`).
#[allow(rustdoc::private_intra_doc_links)]
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
