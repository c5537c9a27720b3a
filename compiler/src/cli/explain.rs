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
    let config = load_config(&args.config)?;
    let cache = SourceCache::new(config.dir.clone());
    let report = permute::explain(&config, &cache, &args.name).map_err(|e| Failure::usage(e.render()))?;
    print_stdout(&report.text)?;
    match report.error {
        Some(diagnostic) => Err(Failure::shader(crate::preprocess::render(
            std::slice::from_ref(&diagnostic),
            &cache,
            std::io::stderr().is_terminal(),
        ))),
        None => Ok(()),
    }
}
