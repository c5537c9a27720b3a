//! Nothing but a home for `compiler/benches/naga_oil.rs`, the per-permutation comparison of
//! Kiln with naga_oil 0.23, kept out of the workspace's default builds (see Cargo.toml).
