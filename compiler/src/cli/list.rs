//! `kiln list`.

use super::{CliResult, Failure};

/// Arguments of `kiln list`.
#[derive(Debug, clap::Args)]
pub struct Args {}

pub fn exec(_args: Args) -> CliResult {
    Err(Failure::usage("error: `kiln list` is not available yet"))
}
