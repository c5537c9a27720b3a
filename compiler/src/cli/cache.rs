//! `kiln cache`.

use super::{CliResult, Failure};

/// Arguments of `kiln cache`.
#[derive(Debug, clap::Args)]
pub struct Args {}

pub fn exec(_args: Args) -> CliResult {
    Err(Failure::usage("error: `kiln cache` is not available yet"))
}
