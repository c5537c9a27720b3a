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
//! - [`archive`]: the packed file the runtime loads (built without the `compiler` feature,
//!   with [`output`], so the runtime reads archives with the same types and no naga);
//! - [`build_script`]: the `build.rs` API, which the `kiln` command line shares, and
//!   [`bindings`], the typed permutation keys it generates;
//! - [`lsp`]: `kiln lsp`, the Language Server Protocol for editors, on the same stages;
//! - [`output`]: how every output file is written (atomically, never over a device or an input).

pub mod archive;
pub mod output;

#[cfg(feature = "compiler")]
pub mod bindings;
#[cfg(feature = "compiler")]
pub mod build;
#[cfg(feature = "compiler")]
pub mod build_script;
#[cfg(feature = "compiler")]
pub mod cache;
#[cfg(feature = "compiler")]
pub mod cli;
#[cfg(feature = "compiler")]
pub mod compile;
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
