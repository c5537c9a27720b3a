//! Builds at scale, in one run: `cargo bench -p kiln --bench scale`.
//!
//! On generated `scale`-style sets (compiler/tests/support/scale_set.rs: materials multiply
//! the domain; three shaders, two levels), `kiln build` runs as a child process (so its
//! peak memory is its own: `wait4`'s max RSS) and prints:
//!
//! 0. a small set (144 permutations, about 120 distinct sources): a cold build against
//!    naga alone on the same distinct sources and targets (this bench as a child process:
//!    `-- naga-alone CONFIG JOBS`, timing naga's work only), medians of 5 alternating runs,
//!    wall and CPU (goal: at most 1.15x wall);
//! 1. for 1k, 10k and 100k permutations: a cold build's wall time, time per distinct
//!    compile, peak memory, archive size, and the size of the cache it filled (its files'
//!    bytes, as `du -sb` counts them) as a ratio of the archive's, then the growth of peak
//!    memory from 10k to 100k (goals: 10k at most 256 MiB; growth at most 1.2x; cache at
//!    most 2x the archive). The 1M point runs only when asked for
//!    (`KILN_SCALE_SIZES=1000,10000,100000,1000000`; not in CI: a cold 1M build took about
//!    8 minutes on two busy cores, 1.1 GB of cache and a 606 MB archive); after each cold
//!    build, three warm builds that rewrite the archive, against it: one after the archive
//!    was deleted, one after a material was added to the configuration, one after a
//!    constant was edited in one shader source (these two with the previous archive in
//!    place, whose unchanged compressed blobs they copy; goal at most 3%), each with whether
//!    its archive is byte-identical to a build's without a previous archive;
//! 2. four shards (`--shard I/4`, one after the other, each as if on its own machine)
//!    sharing one cache, then a plain build assembling from it, against one process: the
//!    assembly's compile count (0), whether the archives are byte-identical, and the
//!    scaling efficiency `T(one process) / (4 x (slowest shard + assembly))`;
//! 3. on the same set, for each remote cache backend installed (`redis-server`, nginx with
//!    WebDAV; started here on a free loopback port, as the `remote` bench does): a cold
//!    build that fills an empty remote, then a build with a fresh local cache and that warm
//!    remote (another machine of the team): its hit rate (goal at least 99%) and its time
//!    as a share of the cold build's (goal at most 5%), wall and CPU, and the server's CPU
//!    while serving it (a loaded machine's wall time is about both sides' CPU). A backend that is not
//!    installed is skipped with the reason.
//!
//! Environment: `KILN_SCALE_SIZES=1000,10000` replaces the sizes (`KILN_SCALE_QUICK=1`
//! skips the 100k point); `KILN_SCALE_SHARD_SIZE` (default 10000) the sharded set;
//! `KILN_SCALE_JOBS` the threads of each build (default 2). `-- generate DIR N` only
//! writes a set of about N permutations into DIR.

#[path = "support/naga_alone.rs"]
mod naga_alone;
#[path = "../tests/support/scale_set.rs"]
mod scale_set;
#[path = "support/servers.rs"]
mod servers;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

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
    let start = Instant::now();
    let child = Command::new(env!("CARGO_BIN_EXE_kiln"))
        .args(args)
        .arg("--stats-json")
        .arg(stats)
        .env("CI", "1")
        .env_remove("KILN_SHARD")
        .env_remove("KILN_REMOTE_CACHE")
        .env_remove("KILN_REMOTE_CACHE_MODE")
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("kiln starts");
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
    assert!(libc::WIFEXITED(status) && libc::WEXITSTATUS(status) == 0, "kiln {args:?} failed:\n{err}");
    let stats = serde_json::from_slice(&std::fs::read(stats).expect("stats written")).expect("stats are JSON");
    let time = |t: libc::timeval| Duration::new(t.tv_sec as u64, t.tv_usec as u32 * 1000);
    let cpu = time(usage.ru_utime) + time(usage.ru_stime);
    Run { wall, cpu, max_rss: usage.ru_maxrss as u64 * 1024, stats }
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
    if args.first().map(String::as_str) == Some("naga-alone") {
        naga_alone_child(Path::new(args.get(1).expect("naga-alone CONFIG JOBS")), &args[2]);
        return;
    }
    let jobs = env_usize("KILN_SCALE_JOBS", 2).to_string();
    small_set(&jobs);
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

    // Four shards sharing one cache, then the assembly, against one process.
    let n = env_usize("KILN_SCALE_SHARD_SIZE", 10_000);
    let shards = 4;
    let tmp = tempfile::tempdir().expect("temp dir");
    let dir = tmp.path();
    let (one, one_out, count) = cold(dir, n, &jobs);
    let config = dir.join("set/permutations.toml");
    let cache = dir.join("cache-shared");
    let mut slowest = Duration::ZERO;
    let mut shard_compiled = 0;
    for i in 0..shards {
        let spec = format!("{i}/{shards}");
        let run = kiln(
            &[
                "build",
                "--config",
                config.to_str().unwrap(),
                "--cache-dir",
                cache.to_str().unwrap(),
                "--shard",
                &spec,
                "-j",
                &jobs,
            ],
            &dir.join(format!("shard{i}.json")),
        );
        println!(
            "shard {spec}: {} compiled, {} left to other shards, {:.1} s, peak {:.1} MiB",
            run.count("compiled"),
            run.count("other_shards"),
            run.wall.as_secs_f64(),
            mib(run.max_rss)
        );
        shard_compiled += run.count("compiled");
        slowest = slowest.max(run.wall);
    }
    let out = dir.join("assembled.kpak");
    let assembly = kiln(
        &[
            "build",
            "--config",
            config.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--cache-dir",
            cache.to_str().unwrap(),
            "-j",
            &jobs,
        ],
        &dir.join("assembly.json"),
    );
    let identical = std::fs::read(&one_out).ok() == std::fs::read(&out).ok();
    let sharded = slowest + assembly.wall;
    println!(
        "{count} permutations: one process {:.1} s ({} compiled); {shards} shards {} compiled, slowest {:.1} s; \
         assembly {:.1} s ({} compiled, {} cache hits, peak {:.1} MiB); archives byte-identical: {}",
        one.wall.as_secs_f64(),
        one.count("compiled"),
        shard_compiled,
        slowest.as_secs_f64(),
        assembly.wall.as_secs_f64(),
        assembly.count("compiled"),
        assembly.count("cache_hits"),
        mib(assembly.max_rss),
        if identical { "yes" } else { "NO" }
    );
    println!(
        "scaling efficiency on {shards} machines: {:.0}% (one process / ({shards} x (slowest shard + assembly)))",
        100.0 * one.wall.as_secs_f64() / (shards as f64 * sharded.as_secs_f64())
    );

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

/// As a child process: naga alone on CONFIG's distinct sources (preprocessed first, untimed)
/// on JOBS threads; prints `naga WALL_MS CPU_MS`.
fn naga_alone_child(config: &Path, jobs: &str) {
    use rayon::prelude::*;
    let config = kiln::permute::load(config).unwrap_or_else(|e| panic!("{}", e.render()));
    let (distinct, _) = naga_alone::distinct_sources(&config);
    let pool = naga_alone::pool(jobs.parse().expect("JOBS"));
    let (start, cpu) = (Instant::now(), cpu_time());
    let bytes: usize = pool.install(|| distinct.par_iter().map(|s| naga_alone::naga_alone(s, false)).sum());
    std::hint::black_box(bytes);
    let (wall, cpu) = (start.elapsed(), cpu_time() - cpu);
    println!("naga {} {}", wall.as_secs_f64() * 1e3, cpu.as_secs_f64() * 1e3);
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

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// A small set (about 120 distinct sources): a cold `kiln build` as a whole process against
/// naga alone on the same distinct sources and targets (a child process too, timing only
/// naga's work, not its preprocessing), 5 runs each, alternating; medians of wall and CPU.
fn small_set(jobs: &str) {
    let tmp = tempfile::tempdir().expect("temp dir");
    let (config, count) = scale_set::write(&tmp.path().join("set"), 144);
    let (mut kiln_wall, mut kiln_cpu, mut naga_wall, mut naga_cpu) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let mut distinct = 0;
    for i in 0..5 {
        let out = tmp.path().join("small.kpak");
        let cache = tmp.path().join(format!("cache{i}"));
        let args = ["build", "--config", config.to_str().unwrap(), "-o", out.to_str().unwrap()];
        let run = kiln(
            &[&args[..], &["--cache-dir", cache.to_str().unwrap(), "-j", jobs]].concat(),
            &tmp.path().join("s.json"),
        );
        distinct = run.count("unique_sources");
        kiln_wall.push(run.wall.as_secs_f64() * 1e3);
        kiln_cpu.push(run.cpu.as_secs_f64() * 1e3);
        let child = Command::new(std::env::current_exe().expect("this bench"))
            .args(["naga-alone", config.to_str().unwrap(), jobs])
            .output()
            .expect("naga alone runs");
        let text = String::from_utf8_lossy(&child.stdout);
        let line = text.lines().find_map(|l| l.strip_prefix("naga ")).expect("naga alone prints its times");
        let mut times = line.split(' ').map(|t| t.parse::<f64>().expect("a time"));
        naga_wall.push(times.next().expect("wall"));
        naga_cpu.push(times.next().expect("CPU"));
    }
    let (kw, kc, nw, nc) = (median(kiln_wall), median(kiln_cpu), median(naga_wall), median(naga_cpu));
    println!(
        "small set ({count} permutations, {distinct} distinct), -j {jobs}, medians of 5 alternating runs: kiln cold \
         build {kw:.0} ms wall ({kc:.0} ms CPU), naga alone {nw:.0} ms ({nc:.0} ms CPU): {:.2}x wall (goal <= 1.15x), \
         {:.2}x CPU",
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
