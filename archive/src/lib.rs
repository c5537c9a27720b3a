//! The archive: one file holding every permutation of a build.
//!
//! Takes the artifacts and reflection the compile stage produced; gives a file with a header
//! (magic, format version, checksum of header and chunk hashes), chunk hashes (one per 16 KiB
//! of manifest and blob table), a manifest (permutations, their targets, reflection),
//! per-target zstd dictionaries and deduplicated, compressed blobs, each with its own
//! checksum. Guarantees: the writer streams (blob bytes spool to disk as
//! they come, from any thread) and is deterministic (the bytes depend on the set of
//! permutations and blobs, not on the order they came in) and atomic (temp file, then
//! rename); the reader never panics on bad bytes, checks the header and the manifest's
//! chunk hashes at open (O(1) in the number of permutations, the manifest read in place,
//! nothing parsed per permutation), checks each chunk of the manifest and blob table, each
//! record and each blob the first time it is used, and finds a permutation by name or id
//! with a binary search of the manifest's sorted records.
//!
//! This crate is the vocabulary the compiler (`kiln`) and the runtime (`kiln-runtime`)
//! share: stages, targets, reflection and limits, the archive's format and reader, and
//! atomic file writes ([`output`]). The writer sits behind the `writer` feature, so the
//! runtime reads archives through these very types without linking zstd's dictionary
//! builder, and nothing here calls back into a build: the writer's memory hooks are passed
//! in ([`WriterHooks`]).

// The manifest's arenas and layouts are the writer's; the reader reads the bytes in place.
#[cfg_attr(not(feature = "writer"), allow(dead_code))]
mod format;
pub mod limits;
pub mod output;
mod reader;
mod reflect;
#[cfg(feature = "writer")]
mod writer;

#[cfg(all(test, feature = "writer"))]
mod tests;

pub use format::{
    write_atomic, write_atomic_unsynced, write_pieces, ArchiveError, BlobId, DimensionRecord, PermutationRecord,
    ShaderRecord, CHUNK_LEN, COMPRESSION_LEVEL, DICTIONARY_SAMPLE, DICTIONARY_SIZE, FORMAT_VERSION, HEADER_LEN, MAGIC,
    MAX_ARTIFACT_LEN,
};
pub use reader::{permutation_id, Archive, BlobInfo, Lookup, Near, PermutationRef, Permutations, RELEASE_EVERY};
pub use reflect::{
    Binding, BindingKind, ColorOutput, NumericType, Reflection, SampleKind, ScalarKind, StorageAccess, TextureDim,
    VertexInput,
};
#[cfg(feature = "writer")]
pub use writer::{
    train_dictionary, ArchiveSummary, ArchiveWriter, BlobKey, NewPermutation, StreamingWriter, WriterHooks,
};

/// The version of Kiln that wrote an archive (recorded in its manifest). The workspace's
/// crates share one version.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");

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
