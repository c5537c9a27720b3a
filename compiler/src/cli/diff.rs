//! `kiln diff`.

use std::path::PathBuf;

use super::{print_stdout, CliResult, Failure};
use kiln::diff::{Diff, Summary};

/// Arguments of `kiln diff`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The old set: an archive, or a permutations.toml (a `.toml` file).
    pub old: PathBuf,
    /// The new set: an archive, or a permutations.toml.
    pub new: PathBuf,
    /// Print a Markdown table, for a pull request comment.
    #[arg(long, conflicts_with = "json")]
    pub markdown: bool,
    /// Print JSON: {"added", "removed", "permutations", "distinct", "bytes", "archive_bytes",
    /// "shaders": {NAME: {...}}}.
    #[arg(long)]
    pub json: bool,
    /// Do not preprocess a configuration's permutations: no distinct sources for it.
    #[arg(long)]
    pub no_analysis: bool,
}

pub fn exec(args: Args) -> CliResult {
    let load = |p: &PathBuf| Summary::load(p, !args.no_analysis).map_err(|e| Failure::usage(format!("error: {e}")));
    let (old, new) = (load(&args.old)?, load(&args.new)?);
    let diff = Diff::new(&old, &new);
    let text = if args.json {
        let mut s = serde_json::to_string_pretty(&diff.to_json()).expect("JSON of numbers and strings");
        s.push('\n');
        s
    } else if args.markdown {
        diff.to_markdown()
    } else {
        diff.to_text()
    };
    print_stdout(&text)
}
