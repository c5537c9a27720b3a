//! Shader modules, bind group layouts and pipelines from the archive.
//!
//! Takes permutation names and fixed-function state; gives modules, layouts and pipelines
//! from the runtime's one cache ([`PipelineCache`]), keyed by [`RenderKey`] (permutations,
//! vertex layout, primitive and cull, depth and stencil with the bias as bits, color targets
//! with blend and write masks, sample count) or [`ComputeKey`]. Guarantees: every field of a
//! permutation's reflection is checked against the device's limits before it is used
//! ([`check_limits`]); bind group layouts come from the reflection, merged across stages
//! (visibility is the set of stages that use a binding); modules are created lazily, from
//! SPIR-V passthrough where the device allows it and the archive is trusted (walked and
//! checked against the reflection, binding numbers rewritten to the layout's Vulkan ones:
//! [`crate::spirv`]), from WGSL otherwise; every wgpu error is a [`PipelineError`] naming
//! what failed. Bind groups are built by resource name: a pass hands over
//! `("View", buffer)`-style pairs and the reflection says where each goes.
//!
//! One concern per file: [`state`] (fixed-function state and pipeline keys), [`modules`]
//! (shader modules and wgpu error scopes), [`layouts`] (bind group and pipeline layouts from
//! reflection), [`limits`] (reflection against the device's limits), [`cache`] (the pipeline
//! cache), [`disk_cache`] (wgpu's driver pipeline cache on disk), [`usage`] (what the
//! frames asked for, as `kiln_archive::usage` files), [`state_text`] (a usage file's
//! render state text read back into a [`RenderState`]), [`precache`] (an archive's pipeline
//! manifest created on worker threads) and [`missing`] (what a frame gets when a pipeline is
//! not ready: [`Missing`]), over [`inflight`] (the in-flight set that makes every key's
//! creation happen once, and the background job queue).

mod cache;
mod disk_cache;
mod inflight;
mod layouts;
mod limits;
mod missing;
mod modules;
mod precache;
mod state;
mod state_text;
#[cfg(test)]
mod tests;
mod usage;

use kiln_archive::Stage;

pub use crate::gpu::error_chain;
use crate::shaders::LookupError;
use crate::spirv::SpirvError;

pub use cache::{CacheStats, ComputePipeline, PipelineCache, RenderPipeline};
pub use kiln_archive::usage::{Usage, UsageError, UsageKey, UseCount};
pub use layouts::{merge_bindings, storage_format, MergedBinding, PipelineLayoutInfo};
pub use limits::check_limits;
pub use missing::{Fallback, Missing, Ready};
pub use modules::{create_spirv_module, create_wgsl_module, short_label, ErrorScopes};
pub use precache::{manifest_keys, Precache, PrecacheError, Progress};
pub use state::{
    Blend, ColorTarget, ComputeKey, DepthState, PipelineKey, RenderKey, RenderState, VertexBuffer, VertexLayout,
};
pub use state_text::StateTextError;
pub use usage::state_text;

/// Why a module, layout, pipeline or bind group could not be made: each names the
/// permutation or pipeline and what is wrong.
#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    /// The permutation is not in the archive, or its name is malformed.
    #[error(transparent)]
    Lookup(#[from] LookupError),
    /// A permutation used for a stage it was not compiled for.
    #[error("permutation `{name}` is a {found} shader, used as a {wanted} shader")]
    WrongStage {
        /// The permutation.
        name: String,
        /// Its stage in the archive.
        found: Stage,
        /// The stage it was used as.
        wanted: Stage,
    },
    /// The permutation has no artifact the runtime can make a module from.
    #[error("permutation `{name}` has neither a WGSL nor a SPIR-V artifact (it has: {targets})")]
    NoArtifact {
        /// The permutation.
        name: String,
        /// The targets it has.
        targets: String,
    },
    /// The artifact cannot be read (damaged in the archive, or not UTF-8 WGSL).
    #[error("permutation `{name}`: {message}")]
    BadArtifact {
        /// The permutation.
        name: String,
        /// What is wrong.
        message: String,
    },
    /// The SPIR-V for passthrough failed its checks.
    #[error("permutation `{name}`: {source}")]
    Spirv {
        /// The permutation.
        name: String,
        /// The check that failed.
        source: SpirvError,
    },
    /// The permutation's reflection asks for more than the device allows.
    #[error("permutation `{name}`: {what}")]
    Limit {
        /// The permutation.
        name: String,
        /// The limit and by how much it is exceeded.
        what: String,
    },
    /// wgpu refused to create an object.
    #[error("{what}: wgpu rejected it: {message}")]
    Wgpu {
        /// The object.
        what: String,
        /// wgpu's message.
        message: String,
    },
    /// Two stages of a pipeline declare one binding with different kinds.
    #[error("pipeline `{label}`: binding @group({group}) @binding({binding}) is `{kind_a}` in one stage and `{kind_b}` in another")]
    StageConflict {
        /// The pipeline.
        label: String,
        /// The binding's group.
        group: u32,
        /// The binding.
        binding: u32,
        /// Its kind in one stage.
        kind_a: String,
        /// Its kind in the other.
        kind_b: String,
    },
    /// A vertex input that no attribute of the vertex layout provides.
    #[error("pipeline `{label}`: vertex input @location({location}) is not provided by its vertex layout (locations {provided:?})")]
    VertexInput {
        /// The pipeline.
        label: String,
        /// The input's location.
        location: u32,
        /// The locations the layout provides.
        provided: Vec<u32>,
    },
    /// A storage texture of a format the runtime cannot name to wgpu.
    #[error("pipeline `{label}`: storage texture format `{format}` is not known to the runtime")]
    StorageFormat {
        /// The pipeline.
        label: String,
        /// The format as the reflection names it.
        format: String,
    },
    /// A bind group was asked for without a resource its reflection lists.
    #[error("bind group {group} of `{label}`: no resource given for binding {binding} `{name}`")]
    MissingResource {
        /// The pipeline.
        label: String,
        /// The group.
        group: u32,
        /// The binding.
        binding: u32,
        /// Its name in the shader.
        name: String,
    },
}
