//! The example's integration tests, one binary: its command line and its dependency tree.

mod cli;
mod dependencies;
