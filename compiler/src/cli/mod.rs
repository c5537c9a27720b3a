//! The `kiln` command line: one file per subcommand, each clap derive args plus an `exec`
//! that calls the same library functions the build-script API uses.

use std::io::Write;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

mod build;
mod cache;
mod diff;
mod explain;
mod inspect;
mod list;
mod lsp;
mod preprocess;
mod usage;

/// Kiln: a shader permutation compiler for WGSL with a C preprocessor.
#[derive(Debug, Parser)]
#[command(name = "kiln", version, about, long_about = None)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Compile a permutation set into an archive (and optionally loose files).
    Build(build::Args),
    /// Preprocess one file and print the result on stdout.
    Preprocess(preprocess::Args),
    /// List the permutations of a configuration.
    List(list::Args),
    /// Explain one permutation: its defines, skip rules, files, hash and dedup group.
    Explain(explain::Args),
    /// Show the contents of an archive.
    Inspect(inspect::Args),
    /// Manage the artifact cache.
    Cache(cache::Args),
    /// Serve the Language Server Protocol on stdin and stdout (for editors).
    Lsp(lsp::Args),
    /// Compare two permutation sets (archives or configurations): permutations added and
    /// removed, distinct sources and archive bytes, per shader.
    Diff(diff::Args),
    /// Usage files recorded by a renderer: merge them, or print coverage per shader.
    Usage(usage::Args),
}

/// How a subcommand failed: the exit code of DESIGN.md and what to print on stderr
/// (already rendered: diagnostics come with their source snippets).
#[derive(Debug)]
pub struct Failure {
    /// 1: a shader failed; 2: bad usage or bad configuration; 3: a budget is exceeded.
    pub code: u8,
    pub message: String,
}

impl Failure {
    /// A shader failed to preprocess or compile (exit code 1).
    pub fn shader(message: impl Into<String>) -> Self {
        Failure { code: 1, message: message.into() }
    }
    /// Bad usage or bad configuration (exit code 2).
    pub fn usage(message: impl Into<String>) -> Self {
        Failure { code: 2, message: message.into() }
    }
    /// A `[budget]` or shader budget is exceeded (exit code 3).
    pub fn budget(message: impl Into<String>) -> Self {
        Failure { code: 3, message: message.into() }
    }
}

pub type CliResult = Result<(), Failure>;

/// A name from an archive, a configuration or the command line, for the terminal.
pub(crate) use kiln::archive::escape;

/// Entry point of the `kiln` binary.
pub fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => {
            let code = if e.use_stderr() { 2 } else { 0 };
            let _ = e.print();
            return ExitCode::from(code);
        }
    };
    let result = match cli.command {
        Command::Build(args) => build::exec(args),
        Command::Preprocess(args) => preprocess::exec(args),
        Command::List(args) => list::exec(args),
        Command::Explain(args) => explain::exec(args),
        Command::Inspect(args) => inspect::exec(args),
        Command::Cache(args) => cache::exec(args),
        Command::Lsp(args) => lsp::exec(args),
        Command::Diff(args) => diff::exec(args),
        Command::Usage(args) => usage::exec(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(failure) => {
            let mut stderr = std::io::stderr().lock();
            let msg = failure.message.trim_end();
            if !msg.is_empty() {
                let _ = writeln!(stderr, "{msg}");
            }
            ExitCode::from(failure.code)
        }
    }
}

/// Write to stdout, treating a closed pipe (`kiln list | head`) as success.
pub fn print_stdout(text: &str) -> CliResult {
    let mut out = std::io::stdout().lock();
    match out.write_all(text.as_bytes()).and_then(|_| out.flush()) {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
        Err(e) => Err(Failure::usage(format!("error: cannot write to stdout: {e}"))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;

    #[test]
    fn cli_definition_is_consistent() {
        Cli::command().debug_assert();
    }
}
