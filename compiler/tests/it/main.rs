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

/// `kiln` as a user with none of the developer's settings runs it: every test here starts
/// the binary through this. `kiln build`'s default cache folder is `$KILN_CACHE_DIR`, else
/// `$CARGO_TARGET_DIR/kiln-cache`: with either exported in the shell that runs
/// `cargo test`, every test's build would share that one folder, across tests and runs, and
/// counts of compiles, cache hits and remote requests would depend on what ran before. The
/// remote cache's, shards' and shared modules' variables would change builds the same way.
/// A test that wants one of them sets it on the command.
pub(crate) fn kiln_command() -> std::process::Command {
    let mut command = std::process::Command::new(env!("CARGO_BIN_EXE_kiln"));
    without_settings(&mut command);
    command
}

/// `command` without the variables [`kiln_command`] leaves out, and with `CI=1` (no
/// progress bar): for a `kiln` started through a shell.
pub(crate) fn without_settings(command: &mut std::process::Command) -> &mut std::process::Command {
    for (name, _) in std::env::vars_os() {
        let text = name.to_string_lossy();
        if text.starts_with("KILN_") || text == "CARGO_TARGET_DIR" || text == "JOB_COMPLETION_INDEX" {
            command.env_remove(&name);
        }
    }
    command.env("CI", "1")
}
