//! Kiln against naga_oil 0.23, per permutation, on one core.
//!
//! `cargo bench -p kiln-bench-naga-oil --features naga-oil [-- ROUNDS]` (the bench lives in its
//! own package so that naga_oil is never built by `cargo test`).
//!
//! The shader is `benches/naga_oil/pbr.wgsl`: a forward PBR fragment shader of about 350
//! lines with 8 shader defs, so 256 permutations, each a different module; the output is
//! SPIR-V.
//!
//! - naga_oil: for each permutation, `Composer::make_naga_module` with its shader defs (the
//!   composer made once, non-validating, so that the module is validated once, as Kiln
//!   does), then naga's validator and SPIR-V writer.
//! - Kiln: `kiln::build::run` on the same 256 permutations (`permutations.toml` with one
//!   shader, 8 bool dimensions, one level writing SPIR-V), one worker thread, no cache: the
//!   whole build, configuration, preprocessing, compiling, reflection and the archive
//!   included. Also the library alone: `preprocess_file` and `compile::compile` per
//!   permutation.
//!
//! Each is run ROUNDS times (5 by default); the medians are printed with the ratio
//! naga_oil / Kiln (goal >= 3). `KILN_BENCH_ONLY=oil|build|library` runs one side alone, ROUNDS
//! times, and prints nothing: for a profiler (`perf record`, `valgrind --tool=callgrind`).
//!
//! Where the time goes (callgrind, one round, instructions per permutation; the counts do not
//! move with the machine's load): naga_oil 27.6 M; the Kiln build 10.25 M (10.47 M before the
//! archive's dictionaries were attached rather than copied and trained with fastCover's
//! `accel` 4); the library 8.79 M, of which naga's WGSL front end is 6.61 M (75%), validation,
//! compaction and the SPIR-V writer 2.03 M, the preprocessor 0.36 M. naga alone (parse,
//! validate, write) is 8.05 M, so naga_oil / naga alone is 3.4 in instructions (about 2.8 in
//! CPU time: naga_oil's own work runs at a higher IPC), and the build's 3x needs Kiln below
//! naga alone; what the build adds to the library is the archive (0.71 M: zstd 0.36 M,
//! dictionary training 0.25 M), the token hash of each text (0.35 M) and the structural hash
//! of each compacted module (0.22 M). Ways to parse less that were measured and left out: a
//! text without the blanks naga need not lex parses in 4% fewer instructions, but finding
//! them costs nearly as much (0.2 M); `vec3f` for `vec3<f32>` parses 7% faster but puts the
//! types in naga's arena in another order (other SPIR-V ids); short identifiers save 6% and
//! would rename the outputs.
//!
//! Both sides run in this process on one allocator: glibc's, or with `--features
//! naga-oil,mimalloc` mimalloc, the `kiln` binary's. mimalloc speeds both up alike (on a
//! loaded 2-core machine: naga_oil 2.31 -> 1.97 ms, the Kiln build 1.07 -> 0.94 ms, the
//! library 0.86 -> 0.73 ms per permutation), so the ratios hardly move. Last run with
//! mimalloc (load average 4.9, CPU medians of 7 rounds): naga_oil 2.108 ms, the build 1.009 ms
//! (2.09x), the library 0.801 ms (2.63x); the same machine at load 2.3 before the archive
//! change: 2.137, 1.030 (2.07x) and 0.809 ms (2.64x).

use std::collections::HashMap;
use std::path::Path;
use std::time::{Duration, Instant};

use kiln::build::{self, CacheDir};
use naga_oil::compose::{Composer, NagaModuleDescriptor, ShaderDefValue, ShaderType};

#[cfg(feature = "mimalloc")]
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

const SHADER: &str = include_str!("naga_oil/pbr.wgsl");
const DEFS: [&str; 8] =
    ["VERTEX_COLORS", "NORMAL_MAP", "EMISSIVE", "OCCLUSION", "ALPHA_MASK", "SHADOWS", "FOG", "TONEMAP"];

/// CPU time of this process so far (user + system, all threads).
fn cpu_time() -> Duration {
    // SAFETY: getrusage only writes the struct it is given.
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
    let tv = |t: libc::timeval| Duration::new(t.tv_sec as u64, t.tv_usec as u32 * 1000);
    tv(u.ru_utime) + tv(u.ru_stime)
}

/// Runs `f`, pushing its (wall, CPU) times.
fn timed<T>(times: &mut Vec<(Duration, Duration)>, f: impl FnOnce() -> T) -> T {
    let (t, c) = (Instant::now(), cpu_time());
    let r = f();
    times.push((t.elapsed(), cpu_time() - c));
    r
}

fn median(mut v: Vec<Duration>) -> Duration {
    v.sort();
    v[v.len() / 2]
}

fn spirv(module: &naga::Module) -> usize {
    let info = naga::valid::Validator::new(naga::valid::ValidationFlags::all(), naga::valid::Capabilities::default())
        .validate(module)
        .expect("validates");
    let options = naga::back::spv::Options {
        lang_version: (1, 0),
        flags: naga::back::spv::WriterFlags::LABEL_VARYINGS | naga::back::spv::WriterFlags::FORCE_POINT_SIZE,
        ..Default::default()
    };
    let pipeline =
        naga::back::spv::PipelineOptions { shader_stage: naga::ShaderStage::Fragment, entry_point: "fragment".into() };
    naga::back::spv::write_vec(module, &info, &options, Some(&pipeline)).expect("writes").len() * 4
}

/// Every permutation through naga_oil: the bytes of SPIR-V written.
fn naga_oil_all() -> usize {
    let mut composer = Composer::non_validating();
    let mut bytes = 0;
    for bits in 0..1u32 << DEFS.len() {
        let shader_defs: HashMap<String, ShaderDefValue> = DEFS
            .iter()
            .enumerate()
            .filter(|(i, _)| bits & (1 << i) != 0)
            .map(|(_, d)| (d.to_string(), ShaderDefValue::Bool(true)))
            .collect();
        let module = composer
            .make_naga_module(NagaModuleDescriptor {
                source: SHADER,
                file_path: "pbr.wgsl",
                shader_type: ShaderType::Wgsl,
                shader_defs,
                additional_imports: &[],
            })
            .unwrap_or_else(|e| panic!("naga_oil: {e:?}"));
        bytes += spirv(&module);
    }
    bytes
}

/// The set for Kiln: the shader with `#if NAME` for `#ifdef NAME` (a Kiln dimension is always
/// defined, to 0 or 1), one shader with the 8 defs as bool dimensions, one level writing SPIR-V.
fn kiln_set(dir: &Path) -> std::path::PathBuf {
    std::fs::write(dir.join("pbr.wgsl"), SHADER.replace("#ifdef ", "#if ")).unwrap();
    let dims: Vec<String> = DEFS.iter().map(|d| format!("{d} = \"bool\"")).collect();
    let toml = format!(
        "[compiler]\ninclude = [\".\"]\n\n[levels.desktop]\ntargets = [\"spirv\"]\n\n\
         [[shader]]\nname = \"Pbr\"\nsource = \"pbr.wgsl\"\nentry = \"fragment\"\nstage = \"fragment\"\n\
         levels = [\"desktop\"]\ndimensions = {{ {} }}\n",
        dims.join(", ")
    );
    let path = dir.join("permutations.toml");
    std::fs::write(&path, toml).unwrap();
    path
}

/// Kiln's preprocessor and compiler as a library, every permutation, one thread.
fn kiln_library(config: &kiln::permute::Config) -> usize {
    let sources = kiln::preprocess::SourceCache::new(config.dir.clone());
    let options =
        kiln::compile::Options { targets: vec![kiln::Target::Spirv], limits: kiln::compile::Limits::desktop() };
    let mut bytes = 0;
    for p in config.permutations() {
        let out = kiln::preprocess::preprocess_file(&p.shader.source_path, &p.preprocess_options(config), &sources)
            .expect("preprocesses");
        let c = kiln::compile::compile(&out.text, &p.shader.entry, p.shader.stage, &options).expect("compiles");
        bytes += c.artifacts[0].1.len();
    }
    bytes
}

fn main() {
    let rounds: usize =
        std::env::args().skip(1).find(|a| a != "--bench").and_then(|r| r.parse().ok()).unwrap_or(5).max(1);
    let n = 1usize << DEFS.len();
    let dir = tempfile::tempdir().unwrap();
    let config_path = kiln_set(dir.path());
    let config = kiln::permute::load(&config_path).unwrap_or_else(|e| panic!("{}", e.render()));
    // The preprocessor runs in place on a big stack, as on the build's workers.
    let big_stack = |f: fn(&kiln::permute::Config) -> usize, c: &kiln::permute::Config| -> usize {
        std::thread::scope(|s| {
            std::thread::Builder::new()
                .stack_size(kiln::preprocess::STACK_BYTES)
                .spawn_scoped(s, || {
                    kiln::preprocess::big_stack_thread();
                    f(c)
                })
                .unwrap()
                .join()
                .unwrap()
        })
    };
    println!(
        "{} lines, {} shader defs, {n} permutations, SPIR-V, one thread, {rounds} rounds, {} for both",
        SHADER.lines().count(),
        DEFS.len(),
        if cfg!(feature = "mimalloc") { "mimalloc" } else { "glibc's allocator" }
    );

    // The whole build of the set into `out`: one worker thread, no cache.
    let kiln_build = |out: &Path| {
        let options = build::Options {
            config: config_path.clone(),
            output: Some(out.join("shaders.kpak")),
            jobs: Some(1),
            cache: CacheDir::Disabled,
            ..build::Options::default()
        };
        build::run(&options).unwrap_or_else(|e| panic!("{e}"))
    };
    let (mut oil, mut build_times, mut library) = (Vec::new(), Vec::new(), Vec::new());
    let (mut oil_bytes, mut kiln_bytes) = (0, 0);
    // `KILN_BENCH_ONLY=oil|build|library` runs one side alone (for a profiler); no ratio then.
    let only = std::env::var("KILN_BENCH_ONLY").ok();
    let runs = |side: &str| only.as_deref().is_none_or(|o| o == side);
    if only.is_some() {
        for _ in 0..rounds {
            if runs("oil") {
                std::hint::black_box(naga_oil_all());
            }
            if runs("build") {
                let out = tempfile::tempdir().unwrap();
                kiln_build(out.path());
            }
            if runs("library") {
                std::hint::black_box(big_stack(kiln_library, &config));
            }
        }
        return;
    }
    for _ in 0..rounds {
        oil_bytes = std::hint::black_box(timed(&mut oil, naga_oil_all));

        let out = tempfile::tempdir().unwrap();
        let report = timed(&mut build_times, || kiln_build(out.path()));
        assert_eq!((report.stats.permutations, report.stats.compiled), (n, n));

        kiln_bytes = std::hint::black_box(timed(&mut library, || big_stack(kiln_library, &config)));
    }
    let per = |d: Duration| d.as_secs_f64() * 1e3 / n as f64;
    let pair =
        |v: &[(Duration, Duration)]| (median(v.iter().map(|p| p.0).collect()), median(v.iter().map(|p| p.1).collect()));
    let (o, b, l) = (pair(&oil), pair(&build_times), pair(&library));
    println!("per permutation, medians: wall ms, CPU ms (CPU is what to read on a loaded machine)");
    println!(
        "naga_oil (compose, validate, SPIR-V):      {:>7.3} {:>7.3}  ({} KiB)",
        per(o.0),
        per(o.1),
        oil_bytes / 1024
    );
    println!("kiln build -j 1 --no-cache (whole build):  {:>7.3} {:>7.3}", per(b.0), per(b.1));
    println!(
        "kiln preprocess + compile (library):       {:>7.3} {:>7.3}  ({} KiB)",
        per(l.0),
        per(l.1),
        kiln_bytes / 1024
    );
    let ratio = |a: Duration, b: Duration| a.as_secs_f64() / b.as_secs_f64();
    println!("naga_oil / kiln build:   {:.2}x wall, {:.2}x CPU  (goal >= 3)", ratio(o.0, b.0), ratio(o.1, b.1));
    println!("naga_oil / kiln library: {:.2}x wall, {:.2}x CPU", ratio(o.0, l.0), ratio(o.1, l.1));
}
