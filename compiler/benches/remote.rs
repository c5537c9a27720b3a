//! A fresh local cache with a warm remote cache, against a cold build, in one run.
//!
//! `cargo bench -p kiln --bench remote [-- CONFIG]`: CONFIG defaults to a generated set of
//! about 1,000 permutations (`KILN_BENCH_PERMUTATIONS` sets the size): the bundled
//! renderer's `permutations.toml` and `shader_src/`, each shader given a `MATERIAL`
//! dimension whose value reaches the shader's text (the way materials multiply Unreal's
//! permutations), so every material is one more real compile. `KILN_BENCH_JOBS` sets the
//! threads (2 by default). `KILN_BENCH_SET=DIR` only writes the generated set to DIR (to
//! profile `kiln build` on it).
//!
//! For each backend whose server is installed (`redis-server`, `nginx`), started here on a
//! free loopback port:
//! 1. cold: an empty local cache and no remote (the baseline);
//! 2. cold + remote writes: an empty local cache and an empty remote (what CI pays to fill
//!    it);
//! 3. fresh local + warm remote: an empty local cache, the remote that (2) filled: the hit
//!    rate (goal >= 99%) and the time as a share of cold (goal <= 5%). With the generated
//!    set, twice: at the same checkout path (CI runners, the pods of one job) and at another
//!    path (a developer's machine). Both find the preprocessing records (paths relative to
//!    the configuration's folder), every entry and the archive in the remote.
//!
//! Each line gives wall time and the process's CPU time (user + system, all threads):
//! these 2 cores are shared, CPU time is the steadier figure. Cold builds are the median of
//! `KILN_BENCH_ROUNDS` (3) runs, the fresh-local builds of twice as many less one.

#[path = "support/servers.rs"]
mod servers;

use std::path::{Path, PathBuf};
use std::time::Instant;

use kiln::build::{self, CacheDir, RemoteCache};

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let dest = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &dest);
        } else {
            std::fs::copy(e.path(), dest).unwrap();
        }
    }
}

fn add_material_line(dir: &Path) {
    for e in std::fs::read_dir(dir).unwrap() {
        let path = e.unwrap().path();
        if path.is_dir() {
            add_material_line(&path);
        } else if path.extension().is_some_and(|e| e == "usf") {
            let mut text = std::fs::read_to_string(&path).unwrap();
            text.push_str("\n#ifdef MATERIAL\nconst kiln_bench_material: u32 = MATERIAL;\n#endif\n");
            std::fs::write(&path, text).unwrap();
        }
    }
}

/// The bundled set with a MATERIAL dimension on every shader, about `target` permutations.
fn generate(root: &Path, dir: &Path, target: usize) -> PathBuf {
    copy_dir(&root.join("shader_src"), &dir.join("shader_src"));
    add_material_line(&dir.join("shader_src"));
    let base = count(&root.join("permutations.toml"));
    let materials = target.div_ceil(base).max(1);
    let mut config: toml::Table =
        std::fs::read_to_string(root.join("permutations.toml")).unwrap().parse().expect("permutations.toml parses");
    for shader in config["shader"].as_array_mut().expect("[[shader]]") {
        let shader = shader.as_table_mut().unwrap();
        let dims = shader.entry("dimensions").or_insert_with(|| toml::Value::Table(toml::Table::new()));
        let values = (0..materials as i64).map(toml::Value::Integer).collect();
        dims.as_table_mut().unwrap().insert("MATERIAL".into(), toml::Value::Array(values));
    }
    let path = dir.join("permutations.toml");
    std::fs::write(&path, toml::to_string(&config).unwrap()).unwrap();
    path
}

/// Kept permutations of a config.
fn count(config: &Path) -> usize {
    let c = kiln::permute::load(config).unwrap_or_else(|e| panic!("{}", e.render()));
    c.permutations_where(|_, _| true).filter(|p| p.is_kept()).count()
}

fn cpu_seconds() -> f64 {
    // SAFETY: rusage is plain integers and timevals; all zeroes is a valid value.
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: `u` is a valid, writable rusage for the call to fill.
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
    let t = |v: libc::timeval| v.tv_sec as f64 + v.tv_usec as f64 * 1e-6;
    t(u.ru_utime) + t(u.ru_stime)
}

/// One build with an empty local cache; (wall seconds, CPU seconds, stats).
fn run(config: &Path, remote: RemoteCache, jobs: usize) -> (f64, f64, build::Stats) {
    let tmp = tempfile::tempdir().unwrap();
    let options = build::Options {
        config: config.to_path_buf(),
        output: Some(tmp.path().join("shaders.kpak")),
        cache: CacheDir::Dir(tmp.path().join("cache")),
        remote_cache: remote,
        jobs: Some(jobs),
        ..build::Options::default()
    };
    let (t, cpu) = (Instant::now(), cpu_seconds());
    let report = match build::run(&options) {
        Ok(r) => r,
        Err(build::Error::Failed(r)) => panic!("the build failed:\n{}", r.failures.join("\n")),
        Err(e) => panic!("the build failed: {e}"),
    };
    let (seconds, cpu) = (t.elapsed().as_secs_f64(), cpu_seconds() - cpu);
    for w in report.warnings.iter().filter(|w| w.contains("remote cache")) {
        eprintln!("{w}");
    }
    (seconds, cpu, report.stats)
}

/// `n` runs of `f`: the median wall time, the median CPU time, and the stats of the last
/// run (every run of a bench line does the same work).
fn median(n: usize, f: impl Fn() -> (f64, f64, build::Stats)) -> (f64, f64, build::Stats) {
    let runs: Vec<(f64, f64, build::Stats)> = (0..n).map(|_| f()).collect();
    let middle = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let wall = middle(runs.iter().map(|r| r.0).collect());
    let cpu = middle(runs.iter().map(|r| r.1).collect());
    (wall, cpu, runs.into_iter().last().expect("n >= 1").2)
}

fn main() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap().to_path_buf();
    let jobs: usize = std::env::var("KILN_BENCH_JOBS").ok().and_then(|j| j.parse().ok()).unwrap_or(2);
    let (generated, elsewhere) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let n = std::env::var("KILN_BENCH_PERMUTATIONS").ok().and_then(|n| n.parse().ok()).unwrap_or(1000);
    if let Some(dir) = std::env::var_os("KILN_BENCH_SET").filter(|d| !d.is_empty()) {
        // Only write the generated set (to profile `kiln build` on it), and stop.
        let config = generate(&root, Path::new(&dir), n);
        println!("generated {} ({} permutations)", config.display(), count(&config));
        return;
    }
    let (config, other_path) = match std::env::args().skip(1).find(|a| !a.starts_with('-')) {
        Some(c) => (PathBuf::from(c), None),
        None => (generate(&root, generated.path(), n), Some(generate(&root, elsewhere.path(), n))),
    };
    println!("remote cache bench: {} ({} permutations, {jobs} threads)", config.display(), count(&config));

    let rounds: usize = std::env::var("KILN_BENCH_ROUNDS").ok().and_then(|r| r.parse().ok()).unwrap_or(3).max(1);
    let (cold, cold_cpu, stats) = median(rounds, || run(&config, RemoteCache::Disabled, jobs));
    println!(
        "cold, no remote:                  {cold:6.2} s, CPU {cold_cpu:6.2} s  ({} distinct, {} compiled; median of {rounds})",
        stats.unique_sources, stats.compiled
    );
    let mut any = false;
    for kind in servers::KINDS {
        let server = match servers::start(kind) {
            Ok(s) => s,
            Err(why) => {
                println!("{kind}: {why}; skipped");
                continue;
            }
        };
        any = true;
        let remote = || RemoteCache::Url(server.url.clone());
        let (fill, fill_cpu, s) = run(&config, remote(), jobs);
        println!(
            "{kind:5} cold + remote writes:       {fill:6.2} s, CPU {fill_cpu:6.2} s  ({:.2} x cold CPU; {} writes, {} errors)",
            fill_cpu / cold_cpu,
            s.remote_writes,
            s.remote_errors
        );
        let mut warm_runs = vec![("same path", config.clone())];
        warm_runs.extend(other_path.clone().map(|p| ("other path", p)));
        for (place, config) in warm_runs {
            let (warm, warm_cpu, s) = median(2 * rounds - 1, || run(&config, remote(), jobs));
            let hit_rate = s.remote_hits as f64 / s.unique_sources.max(1) as f64;
            println!(
                "{kind:5} fresh local, {place:10}:    {warm:6.2} s, CPU {warm_cpu:6.2} s  ({:.1}% of cold wall, {:.1}% of cold CPU, goal <= 5%; hit rate {:.1}%, goal >= 99%; {} compiled, {} preprocessed; median of {})",
                100.0 * warm / cold,
                100.0 * warm_cpu / cold_cpu,
                100.0 * hit_rate,
                s.compiled,
                s.preprocessed,
                2 * rounds - 1
            );
        }
    }
    assert!(any, "no server installed: apt-get install redis-server nginx-light");
}
