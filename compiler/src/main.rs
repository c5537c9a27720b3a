use std::process::ExitCode;

/// mimalloc, not glibc's allocator: naga's front end and writers allocate and free all the
/// time, and glibc gives freed memory back to the system at once, to fault it in again. A
/// cold build of a generated 256-permutation set: 573 -> 522 ms of CPU, 4,200 -> 1,900 page
/// faults; the 256 permutations of benches/naga_oil/pbr.wgsl: 315 -> 287 ms.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> ExitCode {
    kiln::cli::main()
}
