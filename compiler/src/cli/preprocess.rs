//! `kiln preprocess`.

use super::{CliResult, Failure};

/// Arguments of `kiln preprocess`.
#[derive(Debug, clap::Args)]
pub struct Args {}

pub fn exec(_args: Args) -> CliResult {
    Err(Failure::usage("error: `kiln preprocess` is not available yet"))
}
