//! Builds at scale, in one run: `cargo bench -p kiln --bench scale`.
//!
//! On generated `scale`-style sets (compiler/tests/support/scale_set.rs: materials multiply
//! the domain; three shaders, two levels), `kiln build` runs as a child process (so its
//! peak memory is its own: `wait4`'s max RSS) and prints:
//!
//! 0. small sets: a cold build against naga alone on the same distinct sources and targets,
//!    both as whole processes measured the same way (`wait4`: from start to exit, CPU of
//!    all threads), medians of 5 alternating runs, wall and CPU (goal: at most 1.15x wall).
//!    Naga alone is this bench as a child (`-- naga-alone DIR JOBS`, on inputs written by
//!    `-- naga-inputs CONFIG DIR`): it starts, reads the distinct sources (preprocessed by
//!    Kiln beforehand, untimed: naga has no preprocessor), parses, validates and runs every
//!    writer of each source's level on JOBS threads, and writes the outputs into one file.
//!    Kiln's build also preprocesses every permutation, fills its cache and writes the
//!    archive. The first line is the 144-permutation scale set (124 distinct) at
//!    `KILN_SCALE_JOBS`; then the same at `-j 1`, and a set of another shape (25 shaders at
//!    two levels, one dimension: 100 distinct). `KILN_SCALE_SMALL_ONLY=1` stops there;
//!    `KILN_SCALE_KILN=PATH` measures another `kiln` binary (an older build, for a before
//!    and after);
//! 1. for 1k, 10k and 100k permutations: a cold build's wall time, time per distinct
//!    compile, peak memory, archive size, and the size of the cache it filled (its files'
//!    bytes, as `du -sb` counts them) as a ratio of the archive's, then the growth of peak
//!    memory from 10k to 100k (goals: 10k at most 256 MiB; growth at most 1.2x; cache at
//!    most 2x the archive), and the peak memory of the tools on that set and archive
//!    (`kiln inspect` and its `--list` and `--json`, `kiln list`, `kiln explain`; goal at
//!    most 64 MiB each). The 1M point runs only when asked for
//!    (`KILN_SCALE_SIZES=1000,10000,100000,1000000`; not in CI: a cold 1M build takes about
//!    5 minutes of two quiet cores, 1.2 GB of cache and a 595 MB archive); after each cold
//!    build, three warm builds that rewrite the archive, against it: one after the archive
//!    was deleted, one after a material was added to the configuration, one after a
//!    constant was edited in one shader source (these two with the previous archive in
//!    place, whose unchanged compressed blobs they copy; goal at most 3%), each with whether
//!    its archive is byte-identical to a build's without a previous archive;
//! 2. eight shards (`--shard I/8`), each a process with its own local cache and `-j 1`,
//!    sharing a redis remote cache (`redis-server`, started here on a free loopback port),
//!    two at a time, then the assembly (a fresh local cache, the warm remote), against one
//!    process: the assembly's compile count (0), whether the archives are byte-identical,
//!    and the scaling efficiency with the assembly counted, in wall and CPU time;
//! 3. on the same set, for each remote cache backend installed (`redis-server`, nginx with
//!    WebDAV; started here on a free loopback port, as the `remote` bench does): a cold
//!    build that fills an empty remote, then a build with a fresh local cache and that warm
//!    remote (another machine of the team): its hit rate (goal at least 99%) and its time
//!    as a share of the cold build's (goal at most 5%), wall and CPU, and the server's CPU
//!    while serving it (a loaded machine's wall time is about both sides' CPU). A backend that is not
//!    installed is skipped with the reason.
//!
//! Environment: `KILN_SCALE_SIZES=1000,10000` replaces the sizes (`KILN_SCALE_QUICK=1`
//! skips the 100k point); `KILN_SCALE_SHARD_SIZE` (default 10000) the sharded set and
//! `KILN_SCALE_SHARDS` (default 8) its shards;
//! `KILN_SCALE_JOBS` the threads of each build (default 2). `-- generate DIR N` only
//! writes a set of about N permutations into DIR; `-- shards N` runs only the sharded
//! line, on a set of about N permutations.

#[path = "support/naga_alone.rs"]
mod naga_alone;
#[path = "../tests/support/scale_set.rs"]
mod scale_set;
#[path = "support/servers.rs"]
mod servers;
#[path = "shapes/mod.rs"]
mod shapes;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use kiln::archive::Target;

/// One `kiln build` child: wall time, CPU time (user + system), peak RSS (bytes), its stats.
struct Run {
    wall: Duration,
    cpu: Duration,
    max_rss: u64,
    stats: serde_json::Value,
}

impl Run {
    fn count(&self, field: &str) -> u64 {
        self.stats[field].as_u64().unwrap_or(0)
    }
}

fn kiln(args: &[&str], stats: &Path) -> Run {
    let mut cmd = kiln_command();
    cmd.args(args).arg("--stats-json").arg(stats);
    let (wall, cpu, max_rss) = measured(&mut cmd, &format!("kiln {args:?}"));
    let stats = serde_json::from_slice(&std::fs::read(stats).expect("stats written")).expect("stats are JSON");
    Run { wall, cpu, max_rss, stats }
}

/// `kiln` (`KILN_SCALE_KILN`, else this tree's), with no remote cache or shard from the
/// environment.
fn kiln_command() -> Command {
    let bin = std::env::var_os("KILN_SCALE_KILN").unwrap_or_else(|| env!("CARGO_BIN_EXE_kiln").into());
    let mut cmd = Command::new(bin);
    cmd.env("CI", "1").env_remove("KILN_SHARD").env_remove("KILN_REMOTE_CACHE").env_remove("KILN_REMOTE_CACHE_MODE");
    cmd
}

/// Runs `cmd` as a whole process, from its start to its end: wall time, CPU time (user +
/// system, its threads included) and peak RSS (bytes), as `wait4` gives them. Panics with
/// its stderr when it fails.
fn measured(cmd: &mut Command, what: &str) -> (Duration, Duration, u64) {
    let start = Instant::now();
    let child = cmd.stdout(std::process::Stdio::null()).stderr(std::process::Stdio::piped()).spawn().expect("starts");
    let pid = child.id() as libc::pid_t;
    let mut status = 0;
    // SAFETY: rusage is plain integers and timevals; all zeroes is a valid value.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    // wait4 reaps the child and gives its own resource usage (ru_maxrss in KiB on Linux).
    // SAFETY: `status` and `usage` are valid and writable; `pid` is our own child.
    let r = unsafe { libc::wait4(pid, &mut status, 0, &mut usage) };
    let wall = start.elapsed();
    assert_eq!(r, pid, "wait4: {}", std::io::Error::last_os_error());
    let mut child = child;
    let mut err = String::new();
    if let Some(mut e) = child.stderr.take() {
        use std::io::Read;
        let _ = e.read_to_string(&mut err);
    }
    assert!(libc::WIFEXITED(status) && libc::WEXITSTATUS(status) == 0, "{what} failed:\n{err}");
    let time = |t: libc::timeval| Duration::new(t.tv_sec as u64, t.tv_usec as u32 * 1000);
    (wall, time(usage.ru_utime) + time(usage.ru_stime), usage.ru_maxrss as u64 * 1024)
}

/// The tools on the cold build's set (its config `dir/set/permutations.toml`) and archive
/// `out`: each one's wall time and peak memory (goal: at most 64 MiB each).
fn tools(dir: &Path, out: &Path) {
    let config = dir.join("set/permutations.toml");
    let (config, out) = (config.to_str().unwrap(), out.to_str().unwrap());
    let name = "ShadowDepthPS@sm5{MATERIAL=0,MASKED=1}";
    let runs: [(&str, Vec<&str>); 7] = [
        ("inspect", vec!["inspect", out]),
        ("inspect --list", vec!["inspect", "--list", out]),
        ("inspect --json", vec!["inspect", "--json", out]),
        ("list", vec!["list", "--config", config]),
        ("list --no-analysis", vec!["list", "--no-analysis", "--config", config]),
        ("explain", vec!["explain", "--config", config, name]),
        ("inspect NAME", vec!["inspect", out, name, "--reflection"]),
    ];
    let line: Vec<String> = runs
        .iter()
        .map(|(what, args)| {
            let (wall, _, peak) = measured(kiln_command().args(args), &format!("kiln {args:?}"));
            format!("{what} {:.1} MiB ({:.1} s)", mib(peak), wall.as_secs_f64())
        })
        .collect();
    println!("{:>12} tools, peak (goal <= 64 MiB): {}", "", line.join(", "));
}

fn mib(bytes: u64) -> f64 {
    bytes as f64 / (1024.0 * 1024.0)
}

fn sizes() -> Vec<usize> {
    if let Ok(s) = std::env::var("KILN_SCALE_SIZES") {
        return s.split(',').filter_map(|n| n.trim().parse().ok()).collect();
    }
    if std::env::var_os("KILN_SCALE_QUICK").is_some() {
        return vec![1_000, 10_000];
    }
    vec![1_000, 10_000, 100_000]
}

fn env_usize(name: &str, default: usize) -> usize {
    std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default)
}

/// The bytes of the files directly in `dir` (a cache folder is flat).
fn dir_bytes(dir: &Path) -> u64 {
    std::fs::read_dir(dir)
        .map(|entries| entries.filter_map(Result::ok).filter_map(|e| e.metadata().ok()).map(|m| m.len()).sum())
        .unwrap_or(0)
}

/// A cold build of a set of about `n` permutations in `dir`.
fn cold(dir: &Path, n: usize, jobs: &str) -> (Run, PathBuf, usize) {
    let (config, count) = scale_set::write(&dir.join("set"), n);
    let out = dir.join("one.kpak");
    let run = kiln(
        &[
            "build",
            "--config",
            config.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--cache-dir",
            dir.join("cache-one").to_str().unwrap(),
            "-j",
            jobs,
        ],
        &dir.join("one.json"),
    );
    (run, out, count)
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).filter(|a| a != "--bench").collect();
    if args.first().map(String::as_str) == Some("generate") {
        let dir = PathBuf::from(args.get(1).expect("generate DIR N"));
        let n: usize = args.get(2).and_then(|n| n.parse().ok()).expect("generate DIR N");
        let (config, count) = scale_set::write(&dir, n);
        println!("{} ({count} permutations)", config.display());
        return;
    }
    if args.first().map(String::as_str) == Some("naga-inputs") {
        let n = naga_inputs(Path::new(args.get(1).expect("naga-inputs CONFIG DIR")), Path::new(&args[2]));
        println!("{n} sources");
        return;
    }
    if args.first().map(String::as_str) == Some("naga-alone") {
        naga_alone_child(Path::new(args.get(1).expect("naga-alone DIR JOBS")), &args[2]);
        return;
    }
    let jobs = env_usize("KILN_SCALE_JOBS", 2).to_string();
    if args.first().map(String::as_str) == Some("shards") {
        let n: usize = args.get(1).and_then(|n| n.parse().ok()).expect("shards N");
        let tmp = tempfile::tempdir().expect("temp dir");
        let (one, one_out, _) = cold(tmp.path(), n, &jobs);
        sharded(tmp.path(), &tmp.path().join("set/permutations.toml"), &one, &one_out, &jobs);
        return;
    }
    small_sets(&jobs);
    if std::env::var_os("KILN_SCALE_SMALL_ONLY").is_some() {
        return;
    }
    println!("kiln build, cold, -j {jobs}, as a child process (peak memory: wait4 max RSS)");
    println!(
        "{:>12} {:>9} {:>9} {:>10} {:>16} {:>12} {:>12} {:>12} {:>14}",
        "permutations",
        "distinct",
        "compiled",
        "wall s",
        "ms/distinct",
        "peak MiB",
        "archive MiB",
        "cache MiB",
        "cache/archive"
    );
    let mut peaks = Vec::new();
    for n in sizes() {
        let tmp = tempfile::tempdir().expect("temp dir");
        let (run, out, count) = cold(tmp.path(), n, &jobs);
        let compiled = run.count("compiled");
        assert_eq!(run.count("permutations") as usize, count, "kept permutations");
        let archive = std::fs::metadata(&out).map(|m| m.len()).unwrap_or(0);
        let cache = dir_bytes(&tmp.path().join("cache-one"));
        println!(
            "{:>12} {:>9} {:>9} {:>10.1} {:>16.2} {:>12.1} {:>12.1} {:>12.1} {:>13.2}x",
            count,
            run.count("unique_sources"),
            compiled,
            run.wall.as_secs_f64(),
            run.wall.as_secs_f64() * 1000.0 / compiled.max(1) as f64,
            mib(run.max_rss),
            mib(archive),
            mib(cache),
            cache as f64 / archive.max(1) as f64
        );
        peaks.push((count, run.max_rss));
        tools(tmp.path(), &out);
        warm_rewrite(tmp.path(), &run, &out, &jobs);
    }
    let at = |lo: usize, hi: usize| peaks.iter().find(|(c, _)| (lo..hi).contains(c)).map(|p| p.1);
    println!("(cache/archive: goal <= 2x)");
    if let Some(p10k) = at(9_000, 11_000) {
        println!("peak at 10k: {:.1} MiB (goal <= 256 MiB)", mib(p10k));
        if let Some(p100k) = at(90_000, 110_000) {
            println!("peak growth 10k -> 100k: {:.2}x (goal <= 1.2x)", p100k as f64 / p10k as f64);
        }
    }

    // One process against the same set in shards, then the remote cache lines.
    let n = env_usize("KILN_SCALE_SHARD_SIZE", 10_000);
    let tmp = tempfile::tempdir().expect("temp dir");
    let dir = tmp.path();
    let (one, one_out, _) = cold(dir, n, &jobs);
    let config = dir.join("set/permutations.toml");
    sharded(dir, &config, &one, &one_out, &jobs);

    // A fresh local cache with a warm remote, against the cold build above.
    for kind in servers::KINDS {
        let server = match servers::start(kind) {
            Ok(s) => s,
            Err(why) => {
                println!("{kind}: {why}; the remote cache line is skipped");
                continue;
            }
        };
        let build = |cache: &str, stats: &str| {
            kiln(
                &[
                    "build",
                    "--config",
                    config.to_str().unwrap(),
                    "-o",
                    dir.join(format!("{cache}.kpak")).to_str().unwrap(),
                    "--cache-dir",
                    dir.join(cache).to_str().unwrap(),
                    "--remote-cache",
                    &server.url,
                    "-j",
                    &jobs,
                ],
                &dir.join(stats),
            )
        };
        let fill = build(&format!("cache-{kind}-fill"), &format!("{kind}-fill.json"));
        let served = server.cpu();
        let warm = build(&format!("cache-{kind}-fresh"), &format!("{kind}-fresh.json"));
        let served = server.cpu().saturating_sub(served);
        let identical =
            std::fs::read(&one_out).ok() == std::fs::read(dir.join(format!("cache-{kind}-fresh.kpak"))).ok();
        println!(
            "{kind:5} remote: cold + writes {:.1} s ({} writes); fresh local + warm remote {:.2} s: hit rate {:.1}% \
             (goal >= 99%), {:.1}% of cold wall, {:.1}% of cold CPU (goal <= 5%), the server's CPU {:.2} s, {} \
             compiled, peak {:.1} MiB; archive byte-identical: {}",
            fill.wall.as_secs_f64(),
            fill.count("remote_writes"),
            warm.wall.as_secs_f64(),
            100.0 * warm.count("remote_hits") as f64 / warm.count("unique_sources").max(1) as f64,
            100.0 * warm.wall.as_secs_f64() / one.wall.as_secs_f64(),
            100.0 * warm.cpu.as_secs_f64() / one.cpu.as_secs_f64(),
            served.as_secs_f64(),
            warm.count("compiled"),
            mib(warm.max_rss),
            if identical { "yes" } else { "NO" }
        );
    }
}

/// Shards as separate machines would run them, against `one` (the cold build of `config`
/// in one process, its archive `one_out`): `KILN_SCALE_SHARDS` shards (default 8), each a
/// process with its own empty local cache and `-j 1`, sharing one redis remote cache
/// (started here), two at a time; then the assembly, a plain build with a fresh local cache
/// and the warm remote. Prints the assembly's compile count, whether its archive is
/// byte-identical to the one process's, and the scaling efficiency with the assembly
/// counted: this machine's time for one process over its time for all the shards plus the
/// assembly (wall, and CPU: the same work split `shards` ways costs the same when 1.0).
fn sharded(dir: &Path, config: &Path, one: &Run, one_out: &Path, jobs: &str) {
    let shards = env_usize("KILN_SCALE_SHARDS", 8);
    let server = match servers::start("redis") {
        Ok(s) => s,
        Err(why) => {
            println!("shards: {why}; the sharded line is skipped");
            return;
        }
    };
    let shard = |i: usize| {
        let spec = format!("{i}/{shards}");
        let cache = dir.join(format!("cache-shard{i}"));
        let args = ["build", "--config", config.to_str().unwrap(), "--shard", &spec, "-j", "1"];
        let remote = ["--cache-dir", cache.to_str().unwrap(), "--remote-cache", &server.url];
        kiln(&[&args[..], &remote[..]].concat(), &dir.join(format!("shard{i}.json")))
    };
    let start = Instant::now();
    let mut runs: Vec<(usize, Run)> = Vec::new();
    // Two at a time: a pair's processes start together and the next pair waits for both.
    for pair in (0..shards).collect::<Vec<_>>().chunks(2) {
        let done: Vec<(usize, Run)> = std::thread::scope(|s| {
            let handles: Vec<_> = pair.iter().map(|&i| (i, s.spawn(move || shard(i)))).collect();
            handles.into_iter().map(|(i, h)| (i, h.join().expect("a shard's thread"))).collect()
        });
        runs.extend(done);
    }
    let shards_wall = start.elapsed();
    for (i, run) in &runs {
        println!(
            "shard {i}/{shards}: {} compiled, {} left to other shards, {:.1} s wall, {:.1} s CPU, peak {:.1} MiB",
            run.count("compiled"),
            run.count("other_shards"),
            run.wall.as_secs_f64(),
            run.cpu.as_secs_f64(),
            mib(run.max_rss)
        );
    }
    let out = dir.join("assembled.kpak");
    let cache = dir.join("cache-assembly");
    let args = ["build", "--config", config.to_str().unwrap(), "-o", out.to_str().unwrap(), "-j", jobs];
    let remote = ["--cache-dir", cache.to_str().unwrap(), "--remote-cache", &server.url];
    let assembly = kiln(&[&args[..], &remote[..]].concat(), &dir.join("assembly.json"));
    let identical = std::fs::read(one_out).ok() == std::fs::read(&out).ok();
    let shard_cpu: Duration = runs.iter().map(|(_, r)| r.cpu).sum();
    let compiled: u64 = runs.iter().map(|(_, r)| r.count("compiled")).sum();
    println!(
        "{} permutations: one process {:.1} s wall, {:.1} s CPU ({} compiled); {shards} shards (2 at a time, -j 1, \
         redis) {compiled} compiled in {:.1} s wall, {:.1} s CPU; assembly {:.1} s wall, {:.1} s CPU ({} compiled, {} \
         remote hits, peak {:.1} MiB); archives byte-identical: {}",
        one.count("permutations"),
        one.wall.as_secs_f64(),
        one.cpu.as_secs_f64(),
        one.count("compiled"),
        shards_wall.as_secs_f64(),
        shard_cpu.as_secs_f64(),
        assembly.wall.as_secs_f64(),
        assembly.cpu.as_secs_f64(),
        assembly.count("compiled"),
        assembly.count("remote_hits"),
        mib(assembly.max_rss),
        if identical { "yes" } else { "NO" }
    );
    println!(
        "scaling efficiency of {shards} shards with the assembly counted (goal >= 0.8): {:.2} wall (one process / \
         (shards + assembly) on this machine), {:.2} CPU",
        one.wall.as_secs_f64() / (shards_wall + assembly.wall).as_secs_f64(),
        one.cpu.as_secs_f64() / (shard_cpu + assembly.cpu).as_secs_f64()
    );
}

/// As a child process, the baseline: naga alone as a tool calling it directly would run,
/// on the sources [`naga_inputs`] wrote into DIR (`jobs.txt`, `N.wgsl`), on JOBS threads:
/// reads each source, parses, validates and runs every writer of its level, and writes the
/// outputs, one after another, into one file (`DIR/out.bin`; the cheapest way to write
/// them: a file per output costs this machine's file system more than naga's work). The
/// parent measures this whole process, as it does `kiln build`.
fn naga_alone_child(dir: &Path, jobs: &str) {
    use rayon::prelude::*;
    let list = std::fs::read_to_string(dir.join("jobs.txt")).expect("jobs.txt");
    let pool = naga_alone::pool(jobs.parse().expect("JOBS"));
    let outputs: Vec<Vec<(Target, Vec<u8>)>> = pool.install(|| {
        list.par_lines()
            .map(|line| {
                let f: Vec<&str> = line.split('\t').collect();
                let (n, stage, entry, gles) = (f[0], f[1], f[2], f[3] == "1");
                let stage = kiln::archive::Stage::ALL.into_iter().find(|s| s.name() == stage).expect("a stage");
                let targets =
                    f[4].split(',').map(|t| Target::ALL.into_iter().find(|a| a.name() == t).expect("a target"));
                let text = std::fs::read_to_string(dir.join(format!("{n}.wgsl"))).expect("a source");
                let source =
                    naga_alone::Source { text, entry: entry.to_string(), stage, targets: targets.collect(), gles };
                naga_alone::naga_outputs(&source, false)
            })
            .collect()
    });
    let mut out = std::io::BufWriter::new(std::fs::File::create(dir.join("out.bin")).expect("out.bin"));
    for (_, bytes) in outputs.iter().flatten() {
        std::io::Write::write_all(&mut out, bytes).expect("out.bin written");
    }
    std::io::Write::flush(&mut out).expect("out.bin written");
}

/// Writes naga alone's inputs for the set of `config` into `dir`: its distinct sources as
/// Kiln's dedup sees them, preprocessed by Kiln (naga has no preprocessor; not timed), one
/// `N.wgsl` each, and `jobs.txt` (a line each: N, stage, entry point, downlevel, targets).
/// Gives the number of sources.
fn naga_inputs(config: &Path, dir: &Path) -> usize {
    let config = kiln::permute::load(config).unwrap_or_else(|e| panic!("{}", e.render()));
    let (distinct, _) = naga_alone::distinct_sources(&config);
    std::fs::create_dir_all(dir).expect("a folder for naga's inputs");
    let mut jobs = String::new();
    for (n, s) in distinct.iter().enumerate() {
        std::fs::write(dir.join(format!("{n}.wgsl")), &s.text).expect("a source written");
        let targets: Vec<&str> = s.targets.iter().map(|t| t.name()).collect();
        let gles = if s.gles { 1 } else { 0 };
        jobs.push_str(&format!("{n}\t{}\t{}\t{gles}\t{}\n", s.stage.name(), s.entry, targets.join(",")));
    }
    std::fs::write(dir.join("jobs.txt"), jobs).expect("jobs.txt written");
    distinct.len()
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// The small sets: the scale set of 144 permutations (124 distinct sources) and a set of
/// another shape (25 shaders at two levels, one dimension each: 100 distinct sources).
fn small_sets(jobs: &str) {
    let tmp = tempfile::tempdir().expect("temp dir");
    let (scale, count) = scale_set::write(&tmp.path().join("scale"), 144);
    let shape = shapes::Shape {
        name: "many shaders x few permutations",
        shaders: 25,
        used: 1,
        unused: 0,
        helpers: 16,
        calls: 14,
        mobile: true,
    };
    let other = shapes::write(&tmp.path().join("shape"), &shape);
    let mut runs = vec![(format!("small set ({count} permutations"), scale.clone(), jobs.to_string())];
    if jobs != "1" {
        runs.push((format!("small set ({count} permutations"), scale, "1".to_string()));
    }
    runs.push((format!("{} ({} permutations", shape.name, shape.permutations()), other, jobs.to_string()));
    for (i, (name, config, j)) in runs.into_iter().enumerate() {
        small_set(&tmp.path().join(format!("run{i}")), &name, &config, &j);
    }
}

/// A cold `kiln build` of `config` against naga alone ([`naga_alone_child`]) on the same
/// distinct sources and targets, both as whole processes on `jobs` threads (start, reading
/// the sources, compiling, writing the outputs, exit), 5 runs each, alternating; prints the
/// medians of wall and CPU time.
fn small_set(dir: &Path, name: &str, config: &Path, jobs: &str) {
    let inputs = dir.join("naga");
    let sources = naga_inputs(config, &inputs);
    let (mut kiln_wall, mut kiln_cpu, mut naga_wall, mut naga_cpu) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let mut distinct = 0;
    for i in 0..5 {
        let out = dir.join("small.kpak");
        let cache = dir.join(format!("cache{i}"));
        let args = ["build", "--config", config.to_str().unwrap(), "-o", out.to_str().unwrap()];
        let run =
            kiln(&[&args[..], &["--cache-dir", cache.to_str().unwrap(), "-j", jobs]].concat(), &dir.join("s.json"));
        distinct = run.count("unique_sources");
        kiln_wall.push(run.wall.as_secs_f64() * 1e3);
        kiln_cpu.push(run.cpu.as_secs_f64() * 1e3);
        let mut naga = Command::new(std::env::current_exe().expect("this bench"));
        naga.args(["naga-alone", inputs.to_str().unwrap(), jobs]);
        let (wall, cpu, _) = measured(&mut naga, "naga alone");
        naga_wall.push(wall.as_secs_f64() * 1e3);
        naga_cpu.push(cpu.as_secs_f64() * 1e3);
    }
    assert_eq!(distinct as usize, sources, "naga alone compiles the distinct sources Kiln does");
    let (kw, kc, nw, nc) = (median(kiln_wall), median(kiln_cpu), median(naga_wall), median(naga_cpu));
    println!(
        "{name}, {distinct} distinct), -j {jobs}, whole processes, medians of 5 alternating runs: kiln cold build \
         {kw:.0} ms wall ({kc:.0} ms CPU), naga alone {nw:.0} ms ({nc:.0} ms CPU): {:.2}x wall (goal <= 1.15x), {:.2}x CPU",
        kw / nw,
        kc / nc
    );
}

/// After the cold build of the set in `dir` (`cold`, its archive `out`), against it: a warm
/// build after the archive was deleted; then one material added to the configuration, and
/// then a constant edited in one shader source (the masked shadow pass's clip threshold:
/// the keys of a subset of the permutations change), each followed by a warm build that
/// rewrites `out` (its previous archive there, whose unchanged blobs it copies) and the
/// same set built into another file, with nothing to copy, to compare bytes.
fn warm_rewrite(dir: &Path, cold: &Run, out: &Path, jobs: &str) {
    let config = dir.join("set/permutations.toml");
    let cache = dir.join("cache-one");
    let build = |to: &Path, stats: &str| {
        let args = ["build", "--config", config.to_str().unwrap(), "-o", to.to_str().unwrap()];
        kiln(&[&args[..], &["--cache-dir", cache.to_str().unwrap(), "-j", jobs]].concat(), &dir.join(stats))
    };
    // The archive gone: a warm cache, nothing to copy blobs from.
    let cold_bytes = std::fs::read(out).ok();
    let _ = std::fs::remove_file(out);
    let gone = build(out, "gone.json");
    println!(
        "{:>12} warm rewrite (archive deleted): {:.1} s, {:.1}% of cold wall, {:.1}% of cold CPU, peak {:.1} MiB; \
         byte-identical to the cold build's: {}",
        "",
        gone.wall.as_secs_f64(),
        100.0 * gone.wall.as_secs_f64() / cold.wall.as_secs_f64(),
        100.0 * gone.cpu.as_secs_f64() / cold.cpu.as_secs_f64(),
        mib(gone.max_rss),
        if std::fs::read(out).ok() == cold_bytes { "yes" } else { "NO" }
    );
    let text = std::fs::read_to_string(&config).expect("the set's config");
    let Some(last) = text.split("range = [0, ").nth(1).and_then(|r| r.split(']').next()) else { return };
    let more = (last.parse::<u64>().expect("a material count") + 1).to_string();
    std::fs::write(&config, text.replace(&format!("range = [0, {last}]"), &format!("range = [0, {more}]"))).unwrap();
    rewrite(&build, dir, cold, out, "one material added");
    let shader = dir.join("set/ShadowDepthPS.usf");
    let source = std::fs::read_to_string(&shader).expect("the set's shadow shader");
    let edited = source.replace("m.opacity < 0.5", "m.opacity < 0.4");
    assert_ne!(source, edited, "the shadow shader's clip threshold");
    std::fs::write(&shader, edited).unwrap();
    rewrite(&build, dir, cold, out, "one shader constant edited");
}

/// A warm build that rewrites `out` (its previous archive there) after `change`, then the
/// same set built into another file without a previous archive (with the same cache), and
/// the comparison of their bytes.
fn rewrite(build: &dyn Fn(&Path, &str) -> Run, dir: &Path, cold: &Run, out: &Path, change: &str) {
    let warm = build(out, "rewrite.json");
    let fresh = dir.join("fresh.kpak");
    build(&fresh, "fresh.json");
    let identical = std::fs::read(out).ok() == std::fs::read(&fresh).ok();
    let _ = std::fs::remove_file(&fresh);
    println!(
        "{:>12} warm rewrite ({change}, {} compiled, {} preprocessed, {} of {} blobs copied): {:.1} s, {:.1}% of cold \
         wall, {:.1}% of cold CPU (goal <= 3%), peak {:.1} MiB; byte-identical to a build without the previous \
         archive: {}",
        "",
        warm.count("compiled"),
        warm.count("preprocessed"),
        warm.count("archive_reused_blobs"),
        warm.count("artifacts"),
        warm.wall.as_secs_f64(),
        100.0 * warm.wall.as_secs_f64() / cold.wall.as_secs_f64(),
        100.0 * warm.cpu.as_secs_f64() / cold.cpu.as_secs_f64(),
        mib(warm.max_rss),
        if identical { "yes" } else { "NO" }
    );
}
