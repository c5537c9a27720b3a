//! The `kiln` command line (its subcommands in `cli/`), over the `kiln` library.

use std::process::ExitCode;

#[cfg(target_os = "linux")]
mod alloc;
mod cli;

/// mimalloc, not glibc's allocator: naga's front end and writers allocate and free all the
/// time, and glibc gives freed memory back to the system at once, to fault it in again.
/// Built without transparent huge pages (`no_thp`), which raised the peak resident memory.
/// The largest blocks are mapped on their own ([`alloc`]).
/// Measurements: `docs/design/2026-11-build-memory-measurements.md`.
#[cfg(target_os = "linux")]
#[global_allocator]
static ALLOCATOR: alloc::Allocator = alloc::Allocator;

#[cfg(not(target_os = "linux"))]
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> ExitCode {
    tune_glibc_malloc();
    tune_mimalloc();
    exit_now(cli::main())
}

/// Ends the process with `code` once stdout and stderr are flushed, without the C runtime's
/// exit handlers: mimalloc's (linked statically) hands every free page back to the system,
/// which the kernel does anyway when the process ends. `cli::main` has dropped everything
/// of the build by then: its files are closed, renamed or removed.
fn exit_now(code: ExitCode) -> ExitCode {
    use std::io::Write;
    let _ = std::io::stdout().flush();
    let _ = std::io::stderr().flush();
    match (0..=u8::MAX).find(|&n| ExitCode::from(n) == code) {
        // SAFETY: _exit ends the process at once; nothing is left to run but the exit
        // handlers skipped above.
        Some(n) => unsafe { libc::_exit(n.into()) },
        None => code,
    }
}

/// Hands what this thread's mimalloc heap holds freed back to the system (a build calls it
/// on every worker between stages: the `kiln build` subcommand passes it in
/// `kiln::build::Options::release_freed`).
fn release_freed() {
    extern "C" {
        fn mi_collect(force: bool);
    }
    // SAFETY: mi_collect frees the unused pages of the calling thread's heap of mimalloc,
    // the global allocator above.
    unsafe { mi_collect(true) };
}

/// zstd's C code (dictionary training, compression contexts) still allocates through glibc,
/// which gives an arena's free top back to the system at once, so that its next tables fault
/// in page by page again: a padding stays at each arena's top.
fn tune_glibc_malloc() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets a tuning parameter of glibc's allocator; no thread runs yet.
    unsafe {
        libc::mallopt(libc::M_TOP_PAD, 16 << 20);
    }
}

/// mimalloc (v3) keeps the pages a build frees resident for a second (`purge_delay`): the
/// tables one stage drops stayed resident under the next stage's, and the peak depended on
/// timing. A short delay keeps most of what purging at once gains on the peaks without
/// its page faults. `MIMALLOC_PURGE_DELAY` in the environment still wins. Measurements:
/// `docs/design/2026-11-build-memory-measurements.md`.
fn tune_mimalloc() {
    /// `mi_option_purge_delay` in the `mi_option_t` enum of mimalloc 2 and 3 (`mimalloc.h`).
    const MI_OPTION_PURGE_DELAY: std::ffi::c_int = 15;
    extern "C" {
        fn mi_option_set(option: std::ffi::c_int, value: std::ffi::c_long);
    }
    if std::env::var_os("MIMALLOC_PURGE_DELAY").is_none() {
        // SAFETY: mi_option_set stores an option's value (libmimalloc-sys links mimalloc,
        // the global allocator above); mimalloc reads it at each purge.
        unsafe { mi_option_set(MI_OPTION_PURGE_DELAY, 100) };
    }
}
