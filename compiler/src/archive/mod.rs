//! The archive: one file holding every permutation of a build.
//!
//! Takes the artifacts and reflection the compile stage produced; gives a file with a header
//! (magic, format version, checksum), a manifest (permutations, their targets, reflection)
//! and deduplicated blobs. Guarantees: the writer is atomic (temp file, then rename); the
//! reader never panics on bad bytes, checks the checksum before trusting anything, does not
//! parse blobs until asked, and finds a permutation by name with one hash-map lookup.
//!
//! This module builds without the `compiler` feature: the runtime reads archives through
//! these very types, with no naga in its dependency tree.

mod format;
mod reflect;

#[cfg(feature = "compiler")]
pub(crate) use format::write_all_vectored;
pub use format::{
    permutation_id, write_atomic, write_atomic_unsynced, Archive, ArchiveError, ArchiveWriter, BlobId, DimensionRecord,
    Lookup, Near, PermutationRecord, PermutationRef, ShaderRecord, FORMAT_VERSION, MAGIC,
};
pub use reflect::{
    Binding, BindingKind, ColorOutput, NumericType, Reflection, SampleKind, ScalarKind, StorageAccess, TextureDim,
    VertexInput,
};

use serde::{Deserialize, Serialize};

/// An output language of the compile stage.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Target {
    Wgsl,
    Spirv,
    Msl,
    Glsl,
    Hlsl,
}

impl Target {
    pub const ALL: [Target; 5] = [Target::Wgsl, Target::Spirv, Target::Msl, Target::Glsl, Target::Hlsl];

    /// The name used in `permutations.toml` and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Target::Wgsl => "wgsl",
            Target::Spirv => "spirv",
            Target::Msl => "msl",
            Target::Glsl => "glsl",
            Target::Hlsl => "hlsl",
        }
    }

    pub fn from_name(name: &str) -> Option<Target> {
        Target::ALL.into_iter().find(|t| t.name() == name)
    }

    /// The file extension of an emitted artifact (`--emit-dir`). GLSL files are named by
    /// stage, as glslangValidator expects.
    pub fn extension(self, stage: Stage) -> &'static str {
        match self {
            Target::Wgsl => "wgsl",
            Target::Spirv => "spv",
            Target::Msl => "metal",
            Target::Hlsl => "hlsl",
            Target::Glsl => match stage {
                Stage::Vertex => "vert",
                Stage::Fragment => "frag",
                Stage::Compute => "comp",
            },
        }
    }

    /// Whether the artifact is text (everything but SPIR-V).
    pub fn is_text(self) -> bool {
        self != Target::Spirv
    }
}

impl std::fmt::Display for Target {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A shader stage.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Stage {
    Vertex,
    Fragment,
    Compute,
}

impl Stage {
    pub const ALL: [Stage; 3] = [Stage::Vertex, Stage::Fragment, Stage::Compute];

    pub fn name(self) -> &'static str {
        match self {
            Stage::Vertex => "vertex",
            Stage::Fragment => "fragment",
            Stage::Compute => "compute",
        }
    }

    pub fn from_name(name: &str) -> Option<Stage> {
        Stage::ALL.into_iter().find(|s| s.name() == name)
    }
}

impl std::fmt::Display for Stage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}
