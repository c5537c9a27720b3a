//! The `build.rs` API (under construction).

/// A build of a permutation set, configured like `cc::Build`.
pub struct Build {}
