//! The `kiln` package's integration tests, one binary: the command line as a child process,
//! hostile input, typed keys, limits, `kiln lsp` (with Neovim), shared modules and `--watch`.

mod budget;
mod cli_build;
mod cli_inspect;
mod hostile_input;
mod keys;
mod limits;
mod lsp;
mod shared_modules;
mod watch;
