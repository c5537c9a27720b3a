//! `kiln explain`.

use std::io::IsTerminal;
use std::path::PathBuf;

use super::list::load_config;
use super::{print_stdout, CliResult, Failure};
use crate::permute;
use crate::preprocess::SourceCache;

/// Arguments of `kiln explain`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// A canonical name, `Shader@level{DIM=value,...}` (enum values by name or index, dimensions in any order).
    #[arg(value_name = "PERMUTATION_NAME")]
    pub name: String,
    /// The permutation set.
    #[arg(long, value_name = "FILE", default_value = "permutations.toml")]
    pub config: PathBuf,
}

pub fn exec(args: Args) -> CliResult {
    let (text, failure) = run(&args, std::io::stderr().is_terminal())?;
    print_stdout(&text)?;
    failure.map_or(Ok(()), Err)
}

/// The text `kiln explain` prints, and how it fails after printing it. A name that does not
/// exist is exit code 2 (with the nearest names); a permutation that fails to preprocess is
/// explained, then fails with exit code 1 and the rendered error.
pub(super) fn run(args: &Args, color: bool) -> Result<(String, Option<Failure>), Failure> {
    let config = load_config(&args.config, color)?;
    let cache = SourceCache::new(config.dir.clone());
    let report = permute::explain(&config, &cache, &args.name).map_err(|e| Failure::usage(e.render()))?;
    let failure = report
        .error
        .map(|d| Failure::shader(crate::preprocess::render(std::slice::from_ref(&d), &cache, color)));
    Ok((report.text, failure))
}
