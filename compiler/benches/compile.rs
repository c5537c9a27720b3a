//! Kiln's build against naga alone, in one run.
//!
//! `cargo bench -p kiln --bench compile [-- CONFIG [ROUNDS]]` (CONFIG defaults to the
//! workspace's `permutations.toml`; `KILN_BENCH_JOBS` sets the threads, 2 by default).
//!
//! 1. naga alone: the distinct preprocessed sources of the set (preprocessed by Kiln, not
//!    timed) go through `naga::front::wgsl::parse_str`, the validator and every writer of
//!    their level, on the same number of threads;
//! 2. Kiln cold: `kiln::build::run` with an empty cache (enumerate, preprocess, dedup,
//!    compile, reflect, cache writes, archive);
//! 3. Kiln warm: the same build again, nothing changed;
//! 4. one header edited: on a copy of the set's folder, a token of one header changed
//!    (`KILN_BENCH_EDIT=path/in/the/folder`, `shader_src/Private/Desktop/BRDF.ush` by
//!    default), rebuilt on the warm cache: the time and how many keys were compiled.
//!
//! naga alone is timed twice: on the whole module as a naga user would call it, and keeping
//! only the entry point before validation (the work Kiln asks of naga).
//!
//! Each is run ROUNDS times (3 by default) and the median is printed, with the ratios
//! cold / naga (goal <= 1.15) and warm / cold (goal <= 2%).
//!
//! Then, without a CONFIG argument, the same cold build against naga alone (wall and CPU
//! time) on generated sets of other shapes (`benches/shapes`): few shaders with many
//! permutations, many shaders with few, large sources, and a set whose dimensions mostly
//! change helpers the entry point never calls (where the writers run once per compacted
//! module: its hit rate is printed). `KILN_BENCH_SHAPES=all` adds a 10,240-permutation set.
//! The last lines are one table of every set's ratios.
//!
//! For profilers (callgrind, perf): `KILN_BENCH_ONLY=naga` runs naga alone once on CONFIG's
//! distinct sources and exits (`=compile`: `kiln::compile::compile` on them); `KILN_BENCH_ONLY=kiln` runs one cold build without a cache
//! (`=cold`: with an empty cache);
//! `KILN_BENCH_SHAPES_TO=DIR` writes the generated sets into DIR (`setN/permutations.toml`).

#[path = "support/naga_alone.rs"]
mod naga_alone;
mod shapes;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use kiln::build::{self, CacheDir};
use kiln::permute;
use kiln::preprocess::{self, SourceCache};
use naga_alone::{distinct_sources, naga_alone, pool, Source};
use rayon::prelude::*;

/// `kiln::compile::compile` on one distinct source: Kiln's naga work (parse, compaction to the
/// entry point, validation, reflection, limits, every writer), without the build around it.
fn kiln_compile(s: &Source) -> usize {
    let limits = if s.gles { kiln::compile::Limits::downlevel() } else { kiln::compile::Limits::desktop() };
    let o = kiln::compile::Options { targets: s.targets.clone(), limits };
    kiln::compile::compile(&s.text, &s.entry, s.stage, &o).unwrap().artifacts.len()
}

/// CPU time of this process so far (user + system, all threads).
fn cpu_time() -> Duration {
    // SAFETY: rusage is plain integers and timevals; all zeroes is a valid value.
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: getrusage only writes the struct it is given.
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
    let tv = |t: libc::timeval| Duration::new(t.tv_sec as u64, t.tv_usec as u32 * 1000);
    tv(u.ru_utime) + tv(u.ru_stime)
}

fn median(mut v: Vec<Duration>) -> Duration {
    v.sort();
    v[v.len() / 2]
}

/// One set's ratios for the closing table.
struct Row {
    name: String,
    permutations: usize,
    distinct: usize,
    naga: (Duration, Duration),
    cold: (Duration, Duration),
    no_cache: (Duration, Duration),
    /// Keys whose writers were shared with another key's compacted module.
    shared: usize,
}

fn main() {
    // As `kiln`'s main does (for zstd's C allocations there; the `kiln` binary's Rust side is
    // on mimalloc, this bench's on glibc for Kiln and naga alone alike).
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets a tuning parameter of glibc's allocator; no thread runs yet.
    unsafe {
        libc::mallopt(libc::M_TOP_PAD, 16 << 20);
    }
    let mut args = std::env::args().skip(1).filter(|a| a != "--bench");
    let given = args.next().map(PathBuf::from);
    let rounds: usize = args.next().and_then(|r| r.parse().ok()).unwrap_or(3).max(1);
    let jobs: usize = std::env::var("KILN_BENCH_JOBS").ok().and_then(|j| j.parse().ok()).unwrap_or(2);
    let bundled = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../permutations.toml"));
    if let Some(dir) = std::env::var_os("KILN_BENCH_SHAPES_TO") {
        // For profilers: the generated sets, one folder each, and nothing timed.
        for (i, shape) in generated_shapes().iter().enumerate() {
            let config = shapes::write(&Path::new(&dir).join(format!("set{i}")), shape);
            println!("{}: {}", shape.name, config.display());
        }
        return;
    }
    if let Ok(only) = std::env::var("KILN_BENCH_ONLY") {
        let config_path = given.unwrap_or(bundled);
        let config = permute::load(&config_path).unwrap_or_else(|e| panic!("{}", e.render()));
        let (distinct, _) = distinct_sources(&config);
        let (_, wall, cpu) = timed(|| match only.as_str() {
            "naga" => {
                let out: usize = pool(jobs).install(|| distinct.par_iter().map(|s| naga_alone(s, false)).sum());
                std::hint::black_box(out);
            }
            "compile" => {
                let out: usize = pool(jobs).install(|| distinct.par_iter().map(kiln_compile).sum());
                std::hint::black_box(out);
            }
            _ => {
                let tmp = tempfile::tempdir().unwrap();
                let options = build::Options {
                    config: config_path.clone(),
                    output: Some(tmp.path().join("shaders.kpak")),
                    jobs: Some(jobs),
                    cache: if only == "cold" { CacheDir::Dir(tmp.path().join("cache")) } else { CacheDir::Disabled },
                    ..build::Options::default()
                };
                build::run(&options).unwrap_or_else(|e| panic!("{e}"));
            }
        });
        println!("{only}: {:.1} ms wall, {:.1} ms CPU", wall.as_secs_f64() * 1e3, cpu.as_secs_f64() * 1e3);
        return;
    }
    let mut rows = vec![full(given.as_deref().unwrap_or(&bundled), rounds, jobs)];
    if given.is_none() {
        let tmp = tempfile::tempdir().unwrap();
        let sets = generated_shapes();
        for (i, shape) in sets.iter().enumerate() {
            let config = shapes::write(&tmp.path().join(format!("set{i}")), shape);
            println!("\n== {} ({} permutations)", shape.name, shape.permutations());
            rows.push(quick(&config, shape.name, rounds, jobs));
        }
    }
    println!(
        "\n{:<34} {:>6} {:>6} {:>8} {:>8} {:>8} {:>8} {:>7}",
        "set", "perms", "keys", "naga ms", "cold ms", "wall x", "CPU x", "shared"
    );
    for r in &rows {
        let ms = |d: Duration| d.as_secs_f64() * 1e3;
        println!(
            "{:<34} {:>6} {:>6} {:>8.1} {:>8.1} {:>8.3} {:>8.3} {:>6.1}%",
            r.name,
            r.permutations,
            r.distinct,
            ms(r.naga.0),
            ms(r.cold.0),
            r.cold.0.as_secs_f64() / r.naga.0.as_secs_f64(),
            r.cold.1.as_secs_f64() / r.naga.1.as_secs_f64(),
            100.0 * r.shared as f64 / r.distinct.max(1) as f64,
        );
        println!(
            "{:<34} {:>6} {:>6} {:>8} {:>8.1} {:>8.3} {:>8.3}   (--no-cache)",
            "",
            "",
            "",
            "",
            ms(r.no_cache.0),
            r.no_cache.0.as_secs_f64() / r.naga.0.as_secs_f64(),
            r.no_cache.1.as_secs_f64() / r.naga.1.as_secs_f64(),
        );
    }
    println!("(cold: an empty cache that the build fills; goal <= 1.15 on every set with >= 100 keys,");
    println!(" <= 1.0 on the bundled set, <= 0.9 on the dedup set; shared: keys whose writers another key ran)");
}

/// The generated sets of the closing table (`KILN_BENCH_SHAPES=all` adds the 10k one).
fn generated_shapes() -> Vec<shapes::Shape> {
    let mut sets = vec![
        // 2 shaders, 8 dimensions: 512 permutations of ~7 KB, half the header called.
        shapes::Shape {
            name: "few shaders x many permutations",
            shaders: 2,
            used: 8,
            unused: 0,
            helpers: 12,
            calls: 6,
            mobile: false,
        },
        // 64 shaders at 2 levels, 1 dimension: 256 permutations of ~9 KB, nearly all called.
        shapes::Shape {
            name: "many shaders x few permutations",
            shaders: 64,
            used: 1,
            unused: 0,
            helpers: 16,
            calls: 14,
            mobile: true,
        },
        // 8 shaders, 4 dimensions: 128 permutations of ~45 KB.
        shapes::Shape { name: "large sources", shaders: 8, used: 4, unused: 0, helpers: 80, calls: 40, mobile: false },
        // 4 shaders, 2 used and 4 unused dimensions: 256 keys, 16 compacted modules.
        shapes::Shape {
            name: "unused-helper dimensions (dedup)",
            shaders: 4,
            used: 2,
            unused: 4,
            helpers: 16,
            calls: 8,
            mobile: false,
        },
    ];
    if std::env::var("KILN_BENCH_SHAPES").is_ok_and(|v| v == "all") {
        // 10 shaders, 10 dimensions: 10,240 permutations of ~3 KB.
        sets.push(shapes::Shape {
            name: "10k permutations",
            shaders: 10,
            used: 10,
            unused: 0,
            helpers: 5,
            calls: 2,
            mobile: false,
        });
    }
    sets
}

/// Times `f`: (wall, CPU of the whole process).
fn timed<T>(f: impl FnOnce() -> T) -> (T, Duration, Duration) {
    let (t, c) = (Instant::now(), cpu_time());
    let r = f();
    (r, t.elapsed(), cpu_time() - c)
}

fn median_pair(v: &[(Duration, Duration)]) -> (Duration, Duration) {
    (median(v.iter().map(|p| p.0).collect()), median(v.iter().map(|p| p.1).collect()))
}

/// naga alone, Kiln cold (an empty cache) and Kiln without a cache, wall and CPU, medians.
fn quick(config_path: &Path, name: &str, rounds: usize, jobs: usize) -> Row {
    let config = permute::load(config_path).unwrap_or_else(|e| panic!("{}", e.render()));
    let (distinct, kept) = distinct_sources(&config);
    let kib = distinct.iter().map(|s| s.text.len()).sum::<usize>() as f64 / 1024.0;
    println!(
        "{kept} permutations, {} distinct sources, {kib:.1} KiB of WGSL, {jobs} threads, {rounds} rounds",
        distinct.len()
    );
    let pool = pool(jobs);
    let (mut naga, mut cold, mut no_cache) = (Vec::new(), Vec::new(), Vec::new());
    let mut shared = 0;
    for _ in 0..rounds {
        let (out, w, c) = timed(|| pool.install(|| distinct.par_iter().map(|s| naga_alone(s, false)).sum::<usize>()));
        std::hint::black_box(out);
        naga.push((w, c));
        let tmp = tempfile::tempdir().unwrap();
        let options = build::Options {
            config: config_path.to_path_buf(),
            output: Some(tmp.path().join("shaders.kpak")),
            jobs: Some(jobs),
            cache: CacheDir::Dir(tmp.path().join("cache")),
            ..build::Options::default()
        };
        let (r, w, c) = timed(|| build::run(&options).unwrap_or_else(|e| panic!("{e}")));
        assert_eq!(r.stats.compiled, distinct.len());
        shared = r.stats.shared_modules;
        cold.push((w, c));
        let options = build::Options { cache: CacheDir::Disabled, ..options };
        let (_, w, c) = timed(|| build::run(&options).unwrap_or_else(|e| panic!("{e}")));
        no_cache.push((w, c));
    }
    let row = Row {
        name: name.to_string(),
        permutations: kept,
        distinct: distinct.len(),
        naga: median_pair(&naga),
        cold: median_pair(&cold),
        no_cache: median_pair(&no_cache),
        shared,
    };
    println!(
        "naga alone {:.1} ms (CPU {:.1} ms), kiln cold {:.1} ms (CPU {:.1} ms): {:.3}x wall, {:.3}x CPU; {} of {} keys shared a compacted module",
        row.naga.0.as_secs_f64() * 1e3,
        row.naga.1.as_secs_f64() * 1e3,
        row.cold.0.as_secs_f64() * 1e3,
        row.cold.1.as_secs_f64() * 1e3,
        row.cold.0.as_secs_f64() / row.naga.0.as_secs_f64(),
        row.cold.1.as_secs_f64() / row.naga.1.as_secs_f64(),
        shared,
        row.distinct
    );
    row
}

/// The detailed report of one set (the bundled one by default).
fn full(config_path: &Path, rounds: usize, jobs: usize) -> Row {
    let config = permute::load(config_path).unwrap_or_else(|e| panic!("{}", e.render()));
    let pool = pool(jobs);
    let (distinct, kept) = distinct_sources(&config);
    let wgsl_bytes: usize = distinct.iter().map(|s| s.text.len()).sum();
    println!(
        "set: {} ({kept} permutations, {} distinct sources, {:.1} KiB of WGSL), {jobs} threads, {rounds} rounds",
        config_path.display(),
        distinct.len(),
        wgsl_bytes as f64 / 1024.0
    );

    let mut pre_times = Vec::new();
    let mut naga_times = Vec::new();
    let mut kc_times = Vec::new();
    let mut naga_entry_times = Vec::new();
    let mut cold_times = Vec::new();
    let mut warm_times = Vec::new();
    let mut nocache_times = Vec::new();
    let mut last = None;
    let (mut naga_cpu, mut cold_cpu, mut nocache_cpu) = (Vec::new(), Vec::new(), Vec::new());
    let kept_perms: Vec<permute::Permutation<'_>> = config.permutations().filter(|p| p.is_kept()).collect();
    for _ in 0..rounds {
        // Kiln's preprocessor alone on every kept permutation (what dedup needs).
        let t = Instant::now();
        let fresh = SourceCache::new(config.dir.clone());
        let n: usize = pool.install(|| {
            kept_perms
                .par_iter()
                .map(|p| {
                    let out =
                        preprocess::preprocess_file(&p.shader.source_path, &p.preprocess_options(&config), &fresh)
                            .expect("preprocesses");
                    std::hint::black_box(out.token_hash());
                    out.text.len()
                })
                .sum()
        });
        std::hint::black_box(n);
        pre_times.push(t.elapsed());

        let t = Instant::now();
        let c0 = cpu_time();
        let out: usize = pool.install(|| distinct.par_iter().map(|s| naga_alone(s, false)).sum());
        naga_cpu.push(cpu_time() - c0);
        naga_times.push(t.elapsed());
        std::hint::black_box(out);
        let t = Instant::now();
        let out: usize = pool.install(|| distinct.par_iter().map(kiln_compile).sum());
        kc_times.push(t.elapsed());
        std::hint::black_box(out);
        let t = Instant::now();
        let out: usize = pool.install(|| distinct.par_iter().map(|s| naga_alone(s, true)).sum());
        naga_entry_times.push(t.elapsed());
        std::hint::black_box(out);

        let tmp = tempfile::tempdir().unwrap();
        let options = build::Options {
            config: config_path.to_path_buf(),
            output: Some(tmp.path().join("shaders.kpak")),
            jobs: Some(jobs),
            cache: CacheDir::Dir(tmp.path().join("cache")),
            ..build::Options::default()
        };
        let t = Instant::now();
        let c0 = cpu_time();
        let cold = build::run(&options).unwrap_or_else(|e| panic!("{e}"));
        cold_cpu.push(cpu_time() - c0);
        cold_times.push(t.elapsed());
        assert_eq!(cold.stats.compiled, distinct.len());
        let t = Instant::now();
        let warm = build::run(&options).unwrap_or_else(|e| panic!("{e}"));
        warm_times.push(t.elapsed());
        let (t, c0) = (Instant::now(), cpu_time());
        build::run(&build::Options { cache: CacheDir::Disabled, ..options.clone() }).unwrap_or_else(|e| panic!("{e}"));
        nocache_cpu.push(cpu_time() - c0);
        nocache_times.push(t.elapsed());
        assert_eq!(warm.stats.compiled, 0);
        last = Some((cold, warm));
    }
    let (cold, warm) = last.unwrap();
    let row = Row {
        name: "bundled (permutations.toml)".to_string(),
        permutations: kept,
        distinct: distinct.len(),
        naga: (median(naga_times.clone()), median(naga_cpu.clone())),
        cold: (median(cold_times.clone()), median(cold_cpu.clone())),
        no_cache: (median(nocache_times.clone()), median(nocache_cpu)),
        shared: cold.stats.shared_modules,
    };
    let (n, ne, c, w) = (median(naga_times), median(naga_entry_times), median(cold_times), median(warm_times));
    println!("naga alone (parse + validate + every writer): {:>9.1} ms", n.as_secs_f64() * 1e3);
    let p = median(pre_times);
    println!("kiln::compile::compile on the same sources:  {:>9.1} ms", median(kc_times).as_secs_f64() * 1e3);
    println!("  the same keeping only the entry point:      {:>9.1} ms", ne.as_secs_f64() * 1e3);
    println!(
        "kiln cold build:                              {:>9.1} ms  (preprocess {:.1} ms, compile {:.1} ms)",
        c.as_secs_f64() * 1e3,
        cold.stats.seconds.preprocess * 1e3,
        cold.stats.seconds.compile * 1e3
    );
    println!(
        "kiln's preprocessor alone, every permutation:  {:>9.1} ms  ({:.0}% of naga alone)",
        p.as_secs_f64() * 1e3,
        100.0 * p.as_secs_f64() / n.as_secs_f64()
    );
    println!("kiln build without a cache:                   {:>9.1} ms", median(nocache_times).as_secs_f64() * 1e3);
    println!(
        "kiln warm build:                              {:>9.1} ms  ({} of {} permutations preprocessed)",
        w.as_secs_f64() * 1e3,
        warm.stats.preprocessed,
        warm.stats.permutations
    );
    println!("cold / naga alone: {:.3}  (goal <= 1.15)", c.as_secs_f64() / n.as_secs_f64());
    println!("cold / naga alone, entry point only: {:.3}", c.as_secs_f64() / ne.as_secs_f64());
    println!(
        "CPU time per round (median): naga alone {:.1} ms, kiln cold {:.1} ms, ratio {:.3} (less sensitive to other load)",
        row.naga.1.as_secs_f64() * 1e3,
        row.cold.1.as_secs_f64() * 1e3,
        row.cold.1.as_secs_f64() / row.naga.1.as_secs_f64()
    );
    println!("warm / cold:       {:.2}%  (goal <= 2%)", 100.0 * w.as_secs_f64() / c.as_secs_f64());
    one_header_edit(config_path, jobs);
    row
}

/// Copies the set's folder, builds it, changes one token of one header, builds again.
fn one_header_edit(config_path: &std::path::Path, jobs: usize) {
    let edit = std::env::var("KILN_BENCH_EDIT").unwrap_or_else(|_| "shader_src/Private/Desktop/BRDF.ush".into());
    let config_path = std::path::absolute(config_path).unwrap();
    let Some(dir) = config_path.parent() else { return };
    let copy = tempfile::tempdir().unwrap();
    for entry in walkdir::WalkDir::new(dir).into_iter().filter_map(Result::ok) {
        let rel = entry.path().strip_prefix(dir).unwrap();
        let top = rel.components().next().map(|c| c.as_os_str().to_string_lossy().into_owned()).unwrap_or_default();
        if top == "target" || top.starts_with('.') {
            continue;
        }
        let to = copy.path().join(rel);
        if entry.file_type().is_dir() {
            std::fs::create_dir_all(&to).unwrap();
        } else if entry.file_type().is_file() {
            std::fs::copy(entry.path(), &to).unwrap();
        }
    }
    let header = copy.path().join(&edit);
    let Ok(text) = std::fs::read_to_string(&header) else {
        println!("one-header edit: {} not found, skipped", header.display());
        return;
    };
    let options = build::Options {
        config: copy.path().join(config_path.file_name().unwrap()),
        output: Some(copy.path().join("shaders.kpak")),
        jobs: Some(jobs),
        cache: CacheDir::Dir(copy.path().join("cache")),
        ..build::Options::default()
    };
    let cold = build::run(&options).unwrap_or_else(|e| panic!("{e}"));
    // A new function changes the token stream of every permutation that includes the header.
    std::fs::write(&header, format!("{text}\nfn kiln_bench_edit() -> f32 {{ return 1.0; }}\n")).unwrap();
    let t = Instant::now();
    let edited = build::run(&options).unwrap_or_else(|e| panic!("{e}"));
    let e = t.elapsed();
    println!(
        "one-header edit ({edit}): {:.1} ms, {} of {} keys compiled, {} of {} permutations preprocessed",
        e.as_secs_f64() * 1e3,
        edited.stats.compiled,
        cold.stats.unique_sources,
        edited.stats.preprocessed,
        edited.stats.permutations
    );
}
