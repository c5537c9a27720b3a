//! `kiln lsp`: the Language Server Protocol (3.17) over stdio for `.usf`/`.ush` files.
//!
//! Takes the editor's open buffers and the `permutations.toml` found upward from each file
//! (or named by `initializationOptions.config`); gives diagnostics, inactive regions, hover,
//! definitions, completion and document symbols for the *active permutation* of each shader
//! that reads a file, and, in the background, the errors of the rest of those shaders'
//! domains with how many kept permutations each breaks.
//!
//! Guarantees: every stage is the build's own (the preprocessor with its source map, the
//! permutation enumeration, naga validation with the level's limits), fed the unsaved text of
//! every open buffer; every `didOpen`/`didChange` is answered by a `publishDiagnostics`
//! carrying that document's version; background checking is cancelled by the next edit and
//! never runs on the thread that answers; bad input (a broken toml, a missing include, a
//! file outside every root, a huge file, an unknown request, malformed JSON) becomes a
//! diagnostic or an error response, never an exit or a panic; the end of stdin ends the
//! server cleanly.
//!
//! Protocol plumbing uses `lsp-server` and `lsp-types` (as rust-analyzer does):
//! `server` is the loop, `workspace` the documents, configurations and active
//! permutations, `check` the diagnostics, `features` hover, definition, completion,
//! symbols and semantic tokens.

mod check;
mod features;
mod server;
mod text;
mod workspace;

pub use server::run_stdio;
