//! `kiln explain`.

use super::{CliResult, Failure};

/// Arguments of `kiln explain`.
#[derive(Debug, clap::Args)]
pub struct Args {}

pub fn exec(_args: Args) -> CliResult {
    Err(Failure::usage("error: `kiln explain` is not available yet"))
}
