//! `kiln build`.

use super::{CliResult, Failure};

/// Arguments of `kiln build`.
#[derive(Debug, clap::Args)]
pub struct Args {}

pub fn exec(_args: Args) -> CliResult {
    Err(Failure::usage("error: `kiln build` is not available yet"))
}
