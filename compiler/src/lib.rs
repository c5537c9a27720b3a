//! Kiln bakes shader permutations.
//!
//! A shader is written once in a `.usf`-like dialect (WGSL plus a C preprocessor) and
//! `permutations.toml` declares which macros vary per feature level. The stages, in the order
//! data flows:
//!
//! - [`preprocess`]: the dialect's C preprocessor with an exact source map;
//! - [`permute`]: the configuration schema, enumeration, skip rules and derived defines;
//! - [`compile`]: naga parse, validation per level, one writer per target, reflection;
//! - [`cache`]: the content-addressed artifact store;
//! - [`archive`]: the packed file the runtime loads (the `kiln-archive` crate, which the
//!   runtime reads archives with, without this crate or naga);
//! - [`build_script`]: the `build.rs` API, which the `kiln` command line shares, and
//!   [`keys`], the typed permutation keys it generates;
//! - [`lsp`]: `kiln lsp`, the Language Server Protocol for editors, on the same stages;
//! - every output file is written as `kiln_archive::output` writes it (atomically, never over a
//!   device or an input).
//!
//! Most users call [`Build`] from `build.rs`, or the `kiln` command line. The stages can be
//! called one by one; for example, the preprocessor alone, on a source held in memory, with
//! a define set as a permutation would set it:
//!
//! ```
//! use kiln::preprocess::{self, Options, SourceCache};
//!
//! let sources = SourceCache::new(std::env::temp_dir());
//! let shader = sources.add_virtual(
//!     "tint.usf",
//!     "#if WARM\nconst TINT = vec3<f32>(1.0, 0.6, 0.2);\n#else\nconst TINT = vec3<f32>(0.2, 0.6, 1.0);\n#endif\n",
//! );
//! let mut options = Options::default();
//! options.defines.push(("WARM".into(), "1".into()));
//! let out = preprocess::preprocess_file_id(shader, &options, &sources).unwrap();
//! assert!(out.text.contains("1.0, 0.6, 0.2"));
//! assert!(!out.text.contains("0.2, 0.6, 1.0"));
//! ```

#![warn(missing_docs)]

/// The archive format, reader and writer, and the vocabulary shared with the runtime: the
/// `kiln-archive` crate.
pub use kiln_archive as archive;
use kiln_archive::output;

#[cfg(feature = "compiler")]
pub mod build;
#[cfg(feature = "compiler")]
pub mod build_script;
// cache/ is being reworked for hostile input on another branch; its clippy findings (a
// `Result<Option<(Pack, Vec<..>)>>`, the remote's unboxed `Store::Http`), its public docs'
// links to private items (`bundle`, `STREAMS`) and its undocumented items go with that work
// rather than into a conflicting edit here.
#[cfg(feature = "compiler")]
#[allow(clippy::type_complexity, clippy::large_enum_variant, rustdoc::private_intra_doc_links, missing_docs)]
pub mod cache;
#[cfg(feature = "compiler")]
pub mod compile;
#[cfg(feature = "compiler")]
pub mod diff;
#[cfg(feature = "compiler")]
pub mod explain;
#[cfg(feature = "compiler")]
pub mod keys;
#[cfg(feature = "compiler")]
pub mod lsp;
#[cfg(feature = "compiler")]
pub mod permute;
#[cfg(feature = "compiler")]
pub mod preprocess;
#[cfg(feature = "compiler")]
pub mod watch;

pub use archive::{Stage, Target};
#[cfg(feature = "compiler")]
pub use build_script::Build;

/// Kiln's version, part of every cache key.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");
