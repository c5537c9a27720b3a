//! `kiln inspect`.

use super::{CliResult, Failure};

/// Arguments of `kiln inspect`.
#[derive(Debug, clap::Args)]
pub struct Args {}

pub fn exec(_args: Args) -> CliResult {
    Err(Failure::usage("error: `kiln inspect` is not available yet"))
}
