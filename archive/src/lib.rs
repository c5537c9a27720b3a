//! The archive: one file holding every permutation of a build.
//!
//! Takes the artifacts and reflection the compile stage produced; gives a file with a header
//! (magic, format version, checksum of header and chunk hashes), chunk hashes (one per chunk
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
//!
//! # Example
//!
//! An archive of one shader with one dimension, written in memory with the writer (the
//! `writer` feature; the compiler writes files with [`StreamingWriter`]), then opened and
//! looked up as a renderer does: by canonical name, or by dimension values in any order.
//!
//! ```
//! use kiln_archive::{
//!     Archive, ArchiveWriter, DimensionRecord, PermutationRecord, Reflection, ShaderRecord, Stage, Target,
//! };
//!
//! let shader = ShaderRecord {
//!     name: "Tonemap".into(),
//!     level: "sm5".into(),
//!     entry: "main".into(),
//!     stage: Stage::Compute,
//!     dimensions: vec![DimensionRecord { name: "HDR".into(), labels: vec![] }],
//! };
//! let reflection = Reflection {
//!     entry: "main".into(),
//!     stage: Stage::Compute,
//!     bindings: vec![],
//!     vertex_inputs: vec![],
//!     color_outputs: vec![],
//!     workgroup_size: Some([8, 8, 1]),
//! };
//!
//! let mut writer = ArchiveWriter::new();
//! let s = writer.add_shader(shader);
//! let r = writer.add_reflection(&reflection);
//! for hdr in 0..2 {
//!     let wgsl = writer.add_blob(format!("// HDR={hdr}\n@compute @workgroup_size(8, 8) fn main() {{}}").as_bytes());
//!     writer.add_permutation(PermutationRecord {
//!         name: format!("Tonemap@sm5{{HDR={hdr}}}"),
//!         shader: s,
//!         values: vec![hdr],
//!         reflection: r,
//!         artifacts: vec![(Target::Wgsl, wgsl)],
//!     });
//! }
//! let bytes = writer.to_bytes()?;
//!
//! // Reading checks the header and the manifest's chunk hashes; each record and blob is
//! // checked the first time it is used.
//! let archive = Archive::from_vec(bytes)?;
//! assert_eq!(archive.permutation_count(), 2);
//! let name = archive.canonical_name("Tonemap", "sm5", &[("HDR", "1")])?;
//! assert_eq!(name, "Tonemap@sm5{HDR=1}");
//! let permutation = archive.get(&name)?.expect("written above");
//! let wgsl = permutation.artifact(Target::Wgsl)?.expect("a WGSL artifact");
//! assert!(wgsl.starts_with(b"// HDR=1"));
//! assert_eq!(permutation.reflection().workgroup_size, Some([8, 8, 1]));
//! // A name that is not there is `None`; `Archive::nearest` lists the closest ones.
//! assert!(archive.get("Tonemap@sm5{HDR=2}")?.is_none());
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

#![warn(missing_docs)]

// The manifest's arenas and layouts are the writer's; the reader reads the bytes in place.
#[cfg_attr(not(feature = "writer"), allow(dead_code))]
mod format;
pub mod input;
pub mod limits;
// Atomic file writes: the compiler writes every output through them, so the module is
// public across the workspace's crates, but it is plumbing, not part of the documented API
// of `kiln-archive` or of `kiln` (which re-exports this crate as `kiln::archive`).
#[doc(hidden)]
pub mod output;
mod reader;
mod reflect;
#[cfg(feature = "writer")]
mod reuse;
pub mod usage;
#[cfg(feature = "writer")]
mod writer;

#[cfg(all(test, feature = "writer"))]
mod tests;

pub use format::{
    write_atomic, write_atomic_unsynced, write_pieces, ArchiveError, BlobId, DimensionRecord, Partial,
    PermutationRecord, PipelineRecord, ShaderRecord, CHUNK_LEN, COMPRESSION_LEVEL, DICTIONARY_SAMPLE, DICTIONARY_SIZE,
    FORMAT_VERSION, HEADER_LEN, MAGIC, MAX_ARTIFACT_LEN, OLDEST_FORMAT_VERSION,
};
pub use reader::{permutation_id, Archive, BlobInfo, Lookup, Near, PermutationRef, Permutations, RELEASE_EVERY};
pub use reflect::{
    Binding, BindingKind, ColorOutput, NumericType, Reflection, SampleKind, ScalarKind, StorageAccess, TextureDim,
    VertexInput,
};
#[cfg(feature = "writer")]
pub use writer::{
    train_dictionary, ArchiveSummary, ArchiveWriter, ArtifactRange, BlobKey, NewPermutation, StreamingWriter,
    WriterHooks,
};

/// The version of Kiln that wrote an archive (recorded in its manifest). The workspace's
/// crates share one version.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");

use serde::{Deserialize, Serialize};

/// An output language of the compile stage.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Target {
    /// WGSL, for wgpu on any backend.
    Wgsl,
    /// SPIR-V, for Vulkan (passed through when trusted).
    Spirv,
    /// Metal Shading Language.
    Msl,
    /// GLSL (ES 3.10 for the downlevel level).
    Glsl,
    /// HLSL (shader model 5.1).
    Hlsl,
}

impl Target {
    /// Every target, in this order.
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

    /// The target named `name` (as `targets` lists it), if any.
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
    /// A vertex shader.
    Vertex,
    /// A fragment shader.
    Fragment,
    /// A compute shader.
    Compute,
}

impl Stage {
    /// Every stage, in this order.
    pub const ALL: [Stage; 3] = [Stage::Vertex, Stage::Fragment, Stage::Compute];

    /// The stage's name as `permutations.toml` and archives write it.
    pub fn name(self) -> &'static str {
        match self {
            Stage::Vertex => "vertex",
            Stage::Fragment => "fragment",
            Stage::Compute => "compute",
        }
    }

    /// The stage named `name`, if any.
    pub fn from_name(name: &str) -> Option<Stage> {
        Stage::ALL.into_iter().find(|s| s.name() == name)
    }
}

impl std::fmt::Display for Stage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Levenshtein distance between `a` and `b`, in characters: how names that name nothing are
/// matched to the nearest ones, by the archive reader and the compiler's configuration alike.
pub fn edit_distance(a: &str, b: &str) -> usize {
    let b: Vec<char> = b.chars().collect();
    let mut prev: Vec<usize> = (0..=b.len()).collect();
    for (i, ca) in a.chars().enumerate() {
        let mut cur = vec![i + 1; b.len() + 1];
        for (j, cb) in b.iter().enumerate() {
            cur[j + 1] = (prev[j] + usize::from(ca != *cb)).min(prev[j + 1] + 1).min(cur[j] + 1);
        }
        prev = cur;
    }
    prev[b.len()]
}

/// `text` for a terminal: each control character (and each bidirectional override, which
/// reorders what follows it) shown as `\u{..}`, so that a name taken from an archive or a
/// configuration cannot move the cursor, clear the screen or retitle the window.
pub fn escape(text: &str) -> std::borrow::Cow<'_, str> {
    let hostile = |c: char| c.is_control() || matches!(c, '\u{202a}'..='\u{202e}' | '\u{2066}'..='\u{2069}');
    if !text.chars().any(hostile) {
        return std::borrow::Cow::Borrowed(text);
    }
    let mut out = String::with_capacity(text.len() + 8);
    for c in text.chars() {
        if hostile(c) {
            out.push_str(&format!("\\u{{{:x}}}", c as u32));
        } else {
            out.push(c);
        }
    }
    std::borrow::Cow::Owned(out)
}

#[cfg(test)]
mod escape_tests {
    #[test]
    fn control_characters_are_shown_escaped() {
        assert_eq!(super::escape("plain name{A=1}"), "plain name{A=1}");
        assert_eq!(super::escape("a\x1b[2Jb\n\u{7}\u{202e}c"), "a\\u{1b}[2Jb\\u{a}\\u{7}\\u{202e}c");
    }
}
