//! `kiln build`, `kiln inspect` and `kiln cache` as a user runs them: exit codes, files
//! written, messages.

use std::path::{Path, PathBuf};
use std::process::Output;

pub(crate) fn kiln(dir: &Path, args: &[&str]) -> Output {
    crate::kiln_command().args(args).current_dir(dir).output().unwrap()
}

pub(crate) fn fixture() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    copy(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/in"), dir.path());
    dir
}

/// Copies the folder `from` into `to`, recursively (the fixtures of this binary's modules).
pub(crate) fn copy(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        if e.file_type().unwrap().is_dir() {
            copy(&e.path(), &to.join(e.file_name()));
        } else {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}

pub(crate) fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

pub(crate) fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

#[test]
fn build_writes_archive_stats_and_emit_dir_then_hits_the_cache() {
    let fx = fixture();
    let d = fx.path();
    let o =
        kiln(d, &["build", "--config", "compute.toml", "--emit-dir", "emit", "--stats-json", "stats.json", "-j", "2"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(d.join("shaders.kpak").is_file());
    assert!(d.join("emit/index.json").is_file());
    let err = stderr(&o);
    assert!(
        err.contains("kiln: 4 permutations (0 skipped), 4 distinct, 4 compiled, 0 cache hits, 0 failed in "),
        "{err}"
    );
    // No cargo workspace around the temporary folder: the cache sits next to the config.
    assert!(d.join(".kiln-cache").is_dir());

    let o = kiln(d, &["build", "--config", "compute.toml", "-o", "again.kpak", "--stats-json", "stats.json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(d.join("stats.json")).unwrap()).unwrap();
    assert_eq!((v["compiled"].as_u64(), v["cache_hits"].as_u64()), (Some(0), Some(4)));
    assert_eq!(std::fs::read(d.join("shaders.kpak")).unwrap(), std::fs::read(d.join("again.kpak")).unwrap());

    let o = kiln(d, &["build", "--config", "compute.toml", "--no-cache", "--stats-json", "stats.json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(d.join("stats.json")).unwrap()).unwrap();
    assert_eq!(v["compiled"].as_u64(), Some(4));
}

#[test]
fn exit_codes() {
    let fx = fixture();
    let d = fx.path();
    // Bad configuration: 2.
    std::fs::write(d.join("bad.toml"), "[levels.sm5]\ntargets = [\"spirv\"]\n[[shader]]\nname = 1\n").unwrap();
    let o = kiln(d, &["build", "--config", "bad.toml"]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    let o = kiln(d, &["build", "--config", "missing.toml"]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    let o = kiln(d, &["build", "--config", "lit.toml", "--target", "dxil"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("unknown target `dxil`"), "{}", stderr(&o));
    // A shader failure: 1, every failure reported, no archive.
    let usf = d.join("histogram.usf");
    let text = std::fs::read_to_string(&usf).unwrap();
    std::fs::write(&usf, text.replace("atomicAdd(&local_bins[bin], 1u);", "atomicAdd(&local_bins[bin], 1.0);"))
        .unwrap();
    let o = kiln(d, &["build", "--config", "compute.toml", "--cache-dir", "c"]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    let err = stderr(&o);
    assert!(err.contains("Histogram@sm5{THREADS=6}") && err.contains("Histogram@es3_1{THREADS=7}"), "{err}");
    assert!(err.contains("histogram.usf:"), "{err}");
    assert!(err.contains("error: 4 of 4 permutations failed; no archive written"), "{err}");
    assert!(!d.join("shaders.kpak").exists());
}

#[test]
fn inspect_shows_the_archive_and_rejects_damage() {
    let fx = fixture();
    let d = fx.path();
    assert!(kiln(d, &["build", "--config", "compute.toml", "--no-cache"]).status.success());
    let o = kiln(d, &["inspect", "shaders.kpak"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(out.contains("permutations: 4"), "{out}");
    assert!(out.contains("Histogram@sm5  compute `main_cs`  2 permutations  dimensions: [THREADS]"), "{out}");
    assert!(out.contains("@group(0) @binding(2) histogram: storage, read_write(256 B)"), "{out}");
    assert!(out.contains("workgroup size (64, 1, 1)"), "{out}");
    let o = kiln(d, &["inspect", "shaders.kpak", "--json"]);
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v["permutations"].as_array().unwrap().len(), 4);
    assert_eq!(v["naga_version"], "30.0.1");

    let bytes = std::fs::read(d.join("shaders.kpak")).unwrap();
    std::fs::write(d.join("cut.kpak"), &bytes[..bytes.len() / 2]).unwrap();
    let o = kiln(d, &["inspect", "cut.kpak"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).starts_with("error: cut.kpak: archive is truncated: the header announces"), "{}", stderr(&o));
    let o = kiln(d, &["inspect", "lit.toml"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("not a kiln archive"), "{}", stderr(&o));
}

#[test]
fn cache_stats_gc_clear() {
    let fx = fixture();
    let d = fx.path();
    let cache: PathBuf = d.join("c");
    let c = cache.to_str().unwrap();
    assert!(kiln(d, &["build", "--config", "compute.toml", "--cache-dir", c]).status.success());
    let o = kiln(d, &["cache", "--cache-dir", c, "stats"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("entries: 4 in 1 packs\n"), "{}", stdout(&o));
    let o = kiln(d, &["cache", "--cache-dir", c, "gc", "--max-size", "1"]);
    assert!(stdout(&o).starts_with("removed 1 packs (4 entries) and 2 preprocessing records ("), "{}", stdout(&o));
    assert!(stdout(&o).ends_with("; kept 0 entries (0 B)\n"), "{}", stdout(&o));
    let o = kiln(d, &["cache", "gc", "--max-size", "10Q", "--cache-dir", c]);
    assert_eq!(o.status.code(), Some(2));
    assert!(kiln(d, &["build", "--config", "compute.toml", "--cache-dir", c]).status.success());
    let o = kiln(d, &["cache", "--cache-dir", c, "clear"]);
    assert_eq!(stdout(&o), format!("removed 4 entries from {c}\n"));
    let o = kiln(d, &["cache", "--cache-dir", c, "stats"]);
    assert!(stdout(&o).contains("entries: 0 in 0 packs\n"), "{}", stdout(&o));
}

#[test]
fn two_processes_at_once_on_one_cache() {
    let fx = fixture();
    let d = fx.path();
    let spawn = |out: &str, stats: &str| {
        crate::kiln_command()
            .args([
                "build",
                "--config",
                "lit.toml",
                "--cache-dir",
                "shared",
                "-o",
                out,
                "--stats-json",
                stats,
                "-j",
                "2",
            ])
            .current_dir(d)
            .spawn()
            .unwrap()
    };
    let (mut a, mut b) = (spawn("a.kpak", "a.json"), spawn("b.kpak", "b.json"));
    assert!(a.wait().unwrap().success());
    assert!(b.wait().unwrap().success());
    assert_eq!(std::fs::read(d.join("a.kpak")).unwrap(), std::fs::read(d.join("b.kpak")).unwrap());
    for stats in ["a.json", "b.json"] {
        let v: serde_json::Value = serde_json::from_slice(&std::fs::read(d.join(stats)).unwrap()).unwrap();
        assert_eq!(v["compiled"].as_u64().unwrap() + v["cache_hits"].as_u64().unwrap(), 24);
    }
    // The cache holds exactly the 24 entries, none damaged: a third build compiles nothing.
    let o =
        kiln(d, &["build", "--config", "lit.toml", "--cache-dir", "shared", "-o", "c.kpak", "--stats-json", "c.json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(!stderr(&o).contains("corrupted"), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(d.join("c.json")).unwrap()).unwrap();
    assert_eq!((v["compiled"].as_u64(), v["cache_hits"].as_u64()), (Some(0), Some(24)));
    let o = kiln(d, &["cache", "--cache-dir", "shared", "stats"]);
    assert!(stdout(&o).contains("entries: 24 in "), "{}", stdout(&o));
}

#[path = "../support/scale_set.rs"]
mod scale_set;

/// `kiln build` in `dir` with these arguments and environment; its stats JSON.
fn build_stats(dir: &Path, args: &[&str], env: &[(&str, &str)], stats: &str) -> serde_json::Value {
    let mut cmd = crate::kiln_command();
    cmd.arg("build").args(args).args(["--stats-json", stats]).current_dir(dir);
    for (k, v) in env {
        cmd.env(k, v);
    }
    let o = cmd.output().unwrap();
    assert!(o.status.success(), "kiln build {args:?} {env:?}: {}", stderr(&o));
    serde_json::from_slice(&std::fs::read(dir.join(stats)).unwrap()).unwrap()
}

fn count(stats: &serde_json::Value, field: &str) -> u64 {
    stats[field].as_u64().unwrap_or_else(|| panic!("no `{field}` in {stats}"))
}

#[test]
fn archive_is_byte_identical_whatever_jobs_cache_state_and_shards() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let (config, permutations) = scale_set::write(&d.join("set"), 6 * scale_set::PER_MATERIAL);
    let config = config.to_str().unwrap();
    let build = |out: &str, cache: &str, extra: &[&str], env: &[(&str, &str)]| {
        let mut args = vec!["--config", config, "-o", out, "--cache-dir", cache];
        args.extend_from_slice(extra);
        build_stats(d, &args, env, &format!("{out}.json"))
    };

    // Cold, one thread: the reference.
    let reference = build("j1.kpak", "c1", &["-j", "1"], &[]);
    assert_eq!(count(&reference, "permutations"), permutations as u64);
    let distinct = count(&reference, "unique_sources");
    assert_eq!(count(&reference, "compiled"), distinct);
    assert!(distinct < permutations as u64, "vertex shaders share keys between materials");
    let bytes = std::fs::read(d.join("j1.kpak")).unwrap();
    let same = |out: &str| {
        let other = std::fs::read(d.join(out)).unwrap();
        assert!(other == bytes, "{out} differs from the one-thread cold build");
    };

    // Cold on four threads.
    build("j4.kpak", "c2", &["-j", "4"], &[]);
    same("j4.kpak");

    // Warm: everything from the cache.
    let warm = build("warm.kpak", "c1", &["-j", "2"], &[]);
    assert_eq!((count(&warm, "compiled"), count(&warm, "cache_hits")), (0, distinct));
    same("warm.kpak");

    // Partly warm: the cache holds one level's keys.
    build("es.kpak", "c3", &["--level", "es3_1"], &[]);
    let partly = build("partly.kpak", "c3", &["-j", "3"], &[]);
    assert!(count(&partly, "compiled") > 0 && count(&partly, "cache_hits") > 0, "{partly}");
    assert_eq!(count(&partly, "compiled") + count(&partly, "cache_hits"), distinct);
    same("partly.kpak");

    // Three shard processes at once on one cache, then the assembly.
    let shards: Vec<_> = (0..3)
        .map(|i| {
            let spec = format!("{i}/3");
            let stats = format!("shard{i}.json");
            let mut cmd = crate::kiln_command();
            cmd.args(["build", "--config", config, "--cache-dir", "c4", "--shard", &spec, "--stats-json", &stats])
                .current_dir(d);
            (cmd.spawn().unwrap(), stats)
        })
        .collect();
    let mut shard_compiled = 0;
    for (mut child, stats) in shards {
        assert!(child.wait().unwrap().success(), "a shard failed");
        let s: serde_json::Value = serde_json::from_slice(&std::fs::read(d.join(&stats)).unwrap()).unwrap();
        assert_eq!(count(&s, "compiled") + count(&s, "other_shards"), distinct, "{s}");
        assert!(count(&s, "compiled") > 0, "every shard has a share: {s}");
        shard_compiled += count(&s, "compiled");
    }
    assert_eq!(shard_compiled, distinct, "each key compiled by one shard");
    assert!(!d.join("shaders.kpak").exists(), "a shard writes no archive unless -o is given");
    let assembly = build("sharded.kpak", "c4", &[], &[]);
    assert_eq!((count(&assembly, "compiled"), count(&assembly, "cache_hits")), (0, distinct));
    same("sharded.kpak");

    // Two shards chosen by the environment: KILN_SHARD, and --shards with a Kubernetes
    // Indexed Job's JOB_COMPLETION_INDEX; the assembly compiles what no shard produced.
    let a = build_stats(d, &["--config", config, "--cache-dir", "c5"], &[("KILN_SHARD", "0/2")], "e0.json");
    let b = build_stats(
        d,
        &["--config", config, "--cache-dir", "c5", "--shards", "2"],
        &[("JOB_COMPLETION_INDEX", "1")],
        "e1.json",
    );
    assert_eq!(count(&a, "compiled") + count(&b, "compiled"), distinct);
    let assembly = build("env.kpak", "c5", &[], &[]);
    assert_eq!(count(&assembly, "compiled"), 0);
    same("env.kpak");

    // A lost shard: the assembly compiles its share, and only that.
    build_stats(d, &["--config", config, "--cache-dir", "c6", "--shard", "0/2"], &[], "l0.json");
    let assembly = build("lost.kpak", "c6", &[], &[]);
    assert_eq!(count(&assembly, "compiled"), count(&b, "compiled"));
    same("lost.kpak");
}

/// A set of 65,536 permutations (256 distinct keys: one of its two dimensions is unused),
/// where `--shard` shares keys by their hash: every key compiled by exactly one shard, and
/// the assembly compiles none and writes the one-process archive.
#[test]
fn large_sets_share_keys_by_hash() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    std::fs::write(
        d.join("p.toml"),
        r#"
[compiler]
include = ["."]

[levels.sm5]
targets = ["wgsl"]

[[shader]]
name = "Tint"
source = "tint.wgsl"
entry = "main_ps"
stage = "fragment"
dimensions = { A = { range = [0, 255] }, B = { range = [0, 255] } }
"#,
    )
    .unwrap();
    std::fs::write(
        d.join("tint.wgsl"),
        "@fragment\nfn main_ps() -> @location(0) vec4<f32> {\n    return vec4<f32>(f32(A) / 255.0, 0.0, 0.0, 1.0);\n}\n",
    )
    .unwrap();
    let reference = build_stats(d, &["--config", "p.toml", "-o", "one.kpak", "--cache-dir", "c1"], &[], "one.json");
    assert_eq!(count(&reference, "permutations"), 65_536);
    let distinct = count(&reference, "unique_sources");
    assert_eq!(distinct, 256);
    let mut compiled = 0;
    for i in 0..3 {
        let spec = format!("{i}/3");
        let s = build_stats(d, &["--config", "p.toml", "--cache-dir", "c2", "--shard", &spec], &[], "s.json");
        assert_eq!(count(&s, "compiled") + count(&s, "other_shards"), distinct, "{s}");
        assert!(count(&s, "compiled") > 40, "each share near a third of the keys: {s}");
        compiled += count(&s, "compiled");
    }
    assert_eq!(compiled, distinct, "each key compiled by one shard");
    let assembly = build_stats(d, &["--config", "p.toml", "-o", "sharded.kpak", "--cache-dir", "c2"], &[], "a.json");
    assert_eq!((count(&assembly, "compiled"), count(&assembly, "cache_hits")), (0, distinct));
    assert!(std::fs::read(d.join("one.kpak")).unwrap() == std::fs::read(d.join("sharded.kpak")).unwrap());
}

#[test]
fn bad_shard_specs_are_usage_errors() {
    let fx = fixture();
    let d = fx.path();
    let run = |args: &[&str], env: &[(&str, &str)]| {
        let mut cmd = crate::kiln_command();
        cmd.args(["build", "--config", "compute.toml"]).args(args).current_dir(d);
        for (k, v) in env {
            cmd.env(k, v);
        }
        cmd.output().unwrap()
    };
    for (args, env, says) in [
        (&["--shard", "4/4"][..], &[][..], "invalid shard `4/4`"),
        (&["--shard", "x"][..], &[][..], "invalid shard `x`"),
        (&["--shard", "1/0"][..], &[][..], "invalid shard `1/0`"),
        (&[][..], &[("KILN_SHARD", "2of3")][..], "KILN_SHARD: invalid shard `2of3`"),
        (&["--shards", "3"][..], &[][..], "needs JOB_COMPLETION_INDEX"),
        (&["--shards", "3"][..], &[("JOB_COMPLETION_INDEX", "3")][..], "JOB_COMPLETION_INDEX 3 with --shards 3"),
        (&["--shards", "3"][..], &[("JOB_COMPLETION_INDEX", "x")][..], "invalid JOB_COMPLETION_INDEX `x`"),
        (&["--shard", "0/2", "--no-cache"][..], &[][..], "--shard needs a cache"),
    ] {
        let o = run(args, env);
        assert_eq!(o.status.code(), Some(2), "{args:?} {env:?}: {}", stderr(&o));
        assert!(stderr(&o).contains(says), "{args:?} {env:?}: {}", stderr(&o));
        assert!(!d.join("shaders.kpak").exists());
    }
}

/// A remote cache that is down: one warning naming it without credentials, and the build
/// succeeds; a bad URL or mode is a usage error (exit 2) that hides credentials too.
#[test]
fn remote_cache_down_is_one_warning_and_credentials_are_never_printed() {
    let fx = fixture();
    let d = fx.path();
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    for url in [format!("redis://:hunter2@127.0.0.1:{port}/1"), format!("http://ci:hunter2@127.0.0.1:{port}/kiln")] {
        let _ = std::fs::remove_dir_all(d.join(".kiln-cache"));
        let o = crate::kiln_command()
            .args(["build", "--config", "compute.toml", "--stats-json", "stats.json", "--remote-cache", &url])
            .current_dir(d)
            .env("KILN_REMOTE_CACHE_TOKEN", "t0ken-xyz")
            .env("KILN_REMOTE_CACHE_TIMEOUT_MS", "500")
            .output()
            .unwrap();
        let (err, out) = (stderr(&o), stdout(&o));
        assert!(o.status.success(), "{err}");
        let warnings: Vec<&str> = err.lines().filter(|l| l.contains("remote cache")).collect();
        assert_eq!(warnings.len(), 1, "{err}");
        let shown = url.replace("ci:hunter2@", "").replace(":hunter2@", "");
        assert!(warnings[0].starts_with("warning: remote cache ") && warnings[0].contains(&shown), "{err}");
        for secret in ["hunter2", "t0ken-xyz"] {
            assert!(!err.contains(secret) && !out.contains(secret), "{err}{out}");
        }
        let stats: serde_json::Value = serde_json::from_slice(&std::fs::read(d.join("stats.json")).unwrap()).unwrap();
        assert_eq!((stats["remote_hits"].as_u64(), stats["compiled"].as_u64()), (Some(0), Some(4)), "{stats}");
        assert!(stats["remote_errors"].as_u64().unwrap() >= 1, "{stats}");
    }
    let o = kiln(d, &["build", "--config", "compute.toml", "--remote-cache", "ftp://u:hunter2@host/x"]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("ftp://host/x") && !stderr(&o).contains("hunter2"), "{}", stderr(&o));
    let o = kiln(
        d,
        &["build", "--config", "compute.toml", "--remote-cache", "redis://h:1", "--remote-cache-mode", "write"],
    );
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("read or read-write"), "{}", stderr(&o));
}
