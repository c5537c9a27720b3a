//! `kiln lsp`.

use super::{CliResult, Failure};

/// Arguments of `kiln lsp`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Accepted for editors that pass it (`--stdio` is the only transport).
    #[arg(long)]
    pub stdio: bool,
}

pub fn exec(_args: Args) -> CliResult {
    // LSP: `exit` without `shutdown` ends with status 1.
    kiln::lsp::run_stdio().map_err(|e| Failure::shader(format!("error: kiln lsp: {e}")))
}
