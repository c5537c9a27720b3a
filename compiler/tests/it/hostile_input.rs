//! Bad input, tried as a hostile user would (issue 16): one test per class, each running the
//! `kiln` command line as a subprocess with a timeout. Every run must end (no hang), exit
//! with 0, 1 or 2 (no panic, no abort) and leave inputs and device nodes as they were.
//!
//! Classes: outputs that point at devices, FIFOs, directories, sockets or inputs; `cache
//! clear` beside foreign files; temporary files of killed writers; permutation spaces too
//! large or entirely skipped; names longer than a format width; non-regular `--config`;
//! configuration gaps. Then a bounded fuzz loop over the configuration loader.

use std::io::Read;
use std::os::unix::fs::{FileTypeExt, MetadataExt};
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

/// How long one run may take before it counts as a hang.
const TIMEOUT: Duration = Duration::from_secs(120);

/// Runs `kiln args` in `dir`, killing it after [`TIMEOUT`]; panics on a hang or a crash.
fn kiln(dir: &Path, args: &[&str]) -> Output {
    let mut child = crate::kiln_command()
        .args(args)
        .current_dir(dir)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Drain both pipes on threads so a large output cannot block the child.
    let mut out = child.stdout.take().unwrap();
    let mut err = child.stderr.take().unwrap();
    let out_t = std::thread::spawn(move || {
        let mut v = Vec::new();
        let _ = out.read_to_end(&mut v);
        v
    });
    let err_t = std::thread::spawn(move || {
        let mut v = Vec::new();
        let _ = err.read_to_end(&mut v);
        v
    });
    let start = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if start.elapsed() > TIMEOUT {
            let _ = child.kill();
            let _ = child.wait();
            panic!("kiln {args:?} hung (killed after {TIMEOUT:?})");
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    let o = Output { status, stdout: out_t.join().unwrap(), stderr: err_t.join().unwrap() };
    let code = o.status.code().unwrap_or_else(|| panic!("kiln {args:?} died by a signal: {}", stderr(&o)));
    assert!(matches!(code, 0..=2), "kiln {args:?} exited {code}: {}", stderr(&o));
    assert!(!stderr(&o).contains("panicked"), "kiln {args:?} panicked: {}", stderr(&o));
    o
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

fn code(o: &Output) -> i32 {
    o.status.code().unwrap()
}

/// A folder with a small valid set: `p.toml` (one compute shader, one bool dimension) and
/// `s.usf` including `inc.ush`.
fn fixture() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    write_config(dir.path(), "dimensions = { A = \"bool\" }\n");
    std::fs::write(
        dir.path().join("s.usf"),
        "#include \"inc.ush\"\n@compute @workgroup_size(1) fn main() { let x = A + ONE; }\n",
    )
    .unwrap();
    std::fs::write(dir.path().join("inc.ush"), "#define ONE 1\n").unwrap();
    dir
}

/// `p.toml` with `shader_tail` appended to its one shader.
fn write_config(dir: &Path, shader_tail: &str) {
    std::fs::write(
        dir.join("p.toml"),
        format!(
            "[compiler]\ninclude = [\".\"]\n\n[levels.sm5]\ntargets = [\"wgsl\"]\n\n[[shader]]\nname = \"S\"\nsource = \"s.usf\"\nstage = \"compute\"\n{shader_tail}"
        ),
    )
    .unwrap();
}

fn build(dir: &Path, extra: &[&str]) -> Output {
    let mut args = vec!["build", "--config", "p.toml", "--cache-dir", "cache"];
    args.extend_from_slice(extra);
    kiln(dir, &args)
}

fn mknod_char(path: &Path, major: u32, minor: u32) -> bool {
    let c = std::ffi::CString::new(path.to_str().unwrap()).unwrap();
    // SAFETY: a path we own; makedev and mknod take plain integers.
    unsafe { libc::mknod(c.as_ptr(), libc::S_IFCHR | 0o666, libc::makedev(major, minor)) == 0 }
}

fn mkfifo(path: &Path) {
    let c = std::ffi::CString::new(path.to_str().unwrap()).unwrap();
    // SAFETY: a path we own.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o644) }, 0, "mkfifo {}", path.display());
}

fn is_char_device(path: &Path) -> bool {
    std::fs::symlink_metadata(path).is_ok_and(|m| m.file_type().is_char_device())
}

/// The real /dev/null is still the null device.
fn assert_dev_null_intact() {
    let m = std::fs::symlink_metadata("/dev/null").unwrap();
    assert!(m.file_type().is_char_device(), "/dev/null is no longer a device");
    assert_eq!((libc::major(m.rdev()), libc::minor(m.rdev())), (1, 3));
}

// --- 1. Outputs never destroy what they point at --------------------------------------------

#[test]
fn outputs_on_devices_are_written_through() {
    let fx = fixture();
    let d = fx.path();
    // A copy of /dev/null in the folder (we may be root), and /dev/null itself.
    let mut devices = vec![PathBuf::from("/dev/null")];
    if mknod_char(&d.join("null"), 1, 3) {
        devices.push(d.join("null"));
    }
    for dev in &devices {
        let dev = dev.to_str().unwrap();
        let o = build(d, &["-o", dev, "--stats-json", dev]);
        assert_eq!(code(&o), 0, "{}", stderr(&o));
        let o = kiln(d, &["build", "--config", "p.toml", "--no-cache", "-o", dev]);
        assert_eq!(code(&o), 0, "{}", stderr(&o));
    }
    if devices.len() > 1 {
        assert!(is_char_device(&d.join("null")));
        // --emit-dir's index written through a device in the folder.
        std::fs::create_dir(d.join("emit")).unwrap();
        assert!(mknod_char(&d.join("emit/index.json"), 1, 3));
        let o = build(d, &["-o", "out.kpak", "--emit-dir", "emit"]);
        assert_eq!(code(&o), 0, "{}", stderr(&o));
        assert!(is_char_device(&d.join("emit/index.json")));
    }
    assert_dev_null_intact();
}

#[test]
fn outputs_on_fifos_are_written_through_or_refused_without_reader() {
    let fx = fixture();
    let d = fx.path();
    mkfifo(&d.join("fifo"));
    let o = build(d, &["-o", "fifo"]);
    assert_eq!(code(&o), 2, "{}", stderr(&o));
    assert!(stderr(&o).contains("it is a FIFO with no reader"), "{}", stderr(&o));
    assert!(std::fs::symlink_metadata(d.join("fifo")).unwrap().file_type().is_fifo());

    let path = d.join("fifo");
    let reader = std::thread::spawn(move || {
        let mut bytes = Vec::new();
        std::fs::File::open(path).unwrap().read_to_end(&mut bytes).unwrap();
        bytes
    });
    // The reader opens the FIFO first (open blocks until both ends are there); retry until
    // the build finds it.
    let mut o = build(d, &["-o", "fifo"]);
    for _ in 0..100 {
        if code(&o) == 0 {
            break;
        }
        std::thread::sleep(Duration::from_millis(20));
        o = build(d, &["-o", "fifo"]);
    }
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    let bytes = reader.join().unwrap();
    assert!(bytes.starts_with(b"KILNPAK\0"), "the archive came through the FIFO ({} bytes)", bytes.len());
    assert!(std::fs::symlink_metadata(d.join("fifo")).unwrap().file_type().is_fifo());
}

#[test]
fn directories_and_sockets_are_refused_as_outputs() {
    let fx = fixture();
    let d = fx.path();
    std::fs::create_dir(d.join("dir")).unwrap();
    let _listener = std::os::unix::net::UnixListener::bind(d.join("sock")).unwrap();
    for args in [["-o", "dir"], ["--stats-json", "dir"], ["-o", "sock"], ["--stats-json", "sock"]] {
        let o = build(d, &args);
        assert_eq!(code(&o), 2, "{args:?}: {}", stderr(&o));
        let err = stderr(&o);
        assert!(err.contains("is a directory") || err.contains("is a socket"), "{args:?}: {err}");
    }
    assert!(d.join("dir").is_dir());
    assert!(std::fs::symlink_metadata(d.join("sock")).unwrap().file_type().is_socket());
    let o = build(d, &["--emit-dir", "p.toml"]);
    assert_eq!(code(&o), 2, "{}", stderr(&o));
}

#[test]
fn outputs_naming_an_input_are_refused_and_the_input_kept() {
    let fx = fixture();
    let d = fx.path();
    std::fs::create_dir(d.join("sub")).unwrap();
    std::os::unix::fs::symlink("../inc.ush", d.join("sub/link.ush")).unwrap();
    let before: Vec<Vec<u8>> =
        ["p.toml", "s.usf", "inc.ush"].iter().map(|f| std::fs::read(d.join(f)).unwrap()).collect();
    let cases: [(&[&str], &str); 6] = [
        (&["-o", "p.toml"], "p.toml"),
        (&["-o", "./sub/../p.toml"], "p.toml"),
        (&["-o", "s.usf"], "s.usf"),
        (&["-o", "inc.ush"], "inc.ush"),
        (&["-o", "sub/link.ush"], "inc.ush"),
        (&["-o", "out.kpak", "--stats-json", "p.toml"], "p.toml"),
    ];
    for (args, input) in cases {
        let o = build(d, args);
        assert_eq!(code(&o), 2, "{args:?}: {}", stderr(&o));
        let err = stderr(&o);
        assert!(err.contains("would destroy the input") && err.contains(input), "{args:?}: {err}");
    }
    // Two outputs on one file.
    let o = build(d, &["-o", "out.kpak", "--stats-json", "./out.kpak"]);
    assert_eq!(code(&o), 2, "{}", stderr(&o));
    assert!(stderr(&o).contains("are the same file"), "{}", stderr(&o));
    let after: Vec<Vec<u8>> =
        ["p.toml", "s.usf", "inc.ush"].iter().map(|f| std::fs::read(d.join(f)).unwrap()).collect();
    assert_eq!(before, after);
    assert!(std::fs::symlink_metadata(d.join("sub/link.ush")).unwrap().file_type().is_symlink());
}

#[test]
fn cache_clear_removes_only_kilns_files() {
    let fx = fixture();
    let d = fx.path();
    let o = build(d, &["-o", "out.kpak"]);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    assert!(d.join("cache/CACHEDIR.TAG").is_file());
    let foreign = ["notes.stamp", "photo.kcp", "0123456789abcdef0123456789abcdef.kcp", ".tmp-mine", "a.kpp"];
    for f in foreign {
        std::fs::write(d.join("cache").join(f), format!("user data in {f}")).unwrap();
    }
    let o = kiln(d, &["cache", "clear", "--cache-dir", "cache"]);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    for f in foreign {
        assert_eq!(std::fs::read_to_string(d.join("cache").join(f)).unwrap(), format!("user data in {f}"));
    }
    let left: Vec<String> = std::fs::read_dir(d.join("cache"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| !foreign.contains(&n.as_str()) && n != "CACHEDIR.TAG")
        .collect();
    assert!(left.is_empty(), "Kiln's own files are cleared: {left:?}");
}

#[test]
fn temporary_files_of_killed_writers_are_removed_by_the_next_build() {
    let fx = fixture();
    let d = fx.path();
    let o = build(d, &["-o", "out.kpak"]);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    // What `kill -9` late in a build leaves: a temporary archive beside -o and a temporary
    // pack in the cache, named with the pid of a process that is gone.
    let mut gone = Command::new("true").spawn().unwrap();
    let pid = gone.id();
    gone.wait().unwrap();
    let beside = d.join(format!(".out.kpak.{pid}.123.0.tmp"));
    let in_cache = d.join(format!("cache/.{}.kcp.{pid}.123.0.tmp", "ab".repeat(16)));
    // A live writer's (this test's own pid) and a user's file are left alone.
    let live = d.join(format!(".out.kpak.{}.1.0.tmp", std::process::id()));
    let user = d.join(".out.kpak.tmp");
    for f in [&beside, &in_cache, &live, &user] {
        std::fs::write(f, vec![7u8; 1 << 16]).unwrap();
    }
    std::fs::write(d.join("inc.ush"), "#define ONE 2\n").unwrap();
    let o = build(d, &["-o", "out.kpak"]);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    assert!(!beside.exists() && !in_cache.exists(), "stale temporary files are removed");
    assert!(live.exists() && user.exists());
}

// --- 2. The permutation space is input --------------------------------------------------------

fn bools(n: usize) -> String {
    let dims: Vec<String> = (0..n).map(|i| format!("B{i} = \"bool\"")).collect();
    format!("dimensions = {{ {} }}\n", dims.join(", "))
}

#[test]
fn huge_spaces_are_located_errors_and_skipped_spaces_end_at_once() {
    let fx = fixture();
    let d = fx.path();
    for n in [32, 64] {
        write_config(d, &bools(n));
        for cmd in [&["build", "--config", "p.toml", "--cache-dir", "cache"][..], &["list", "--config", "p.toml"]] {
            let o = kiln(d, cmd);
            assert_eq!(code(&o), 2, "{n} bools, {cmd:?}: {}", stderr(&o));
            let err = stderr(&o);
            assert!(err.contains("over the limit of 16777216") && err.contains("p.toml:11:"), "{err}");
        }
    }
    // `explain` in a space over the limit: one permutation, no dedup group over 2^64 of them.
    let name = format!("S@sm5{{{}}}", (0..64).map(|i| format!("B{i}=0")).collect::<Vec<_>>().join(","));
    let o = kiln(d, &["explain", &name, "--config", "p.toml"]);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    assert!(stdout(&o).contains("dedup group: not computed"), "{}", stdout(&o));
    let o = kiln(d, &["explain", "S@sm5{B0=7}", "--config", "p.toml"]);
    assert_eq!(code(&o), 2, "{}", stderr(&o));
    // Every permutation skipped, by a rule on the first dimension, on none, or on the last.
    for rule in ["B0 || !B0", "1", "B63 == 0 || B63 == 1"] {
        write_config(d, &format!("{}skip = [{{ when = \"{rule}\", why = \"none wanted\" }}]\n", bools(64)));
        let o = build(d, &["-o", "out.kpak"]);
        assert_eq!(code(&o), 0, "{rule}: {}", stderr(&o));
        assert!(stderr(&o).contains("skip every one of the 18446744073709551616 permutations"), "{}", stderr(&o));
        let o = kiln(d, &["list", "--config", "p.toml"]);
        assert_eq!(code(&o), 0, "{rule}: {}", stderr(&o));
        assert!(stdout(&o).contains("18446744073709551616"), "{}", stdout(&o));
        let o = kiln(d, &["list", "--config", "p.toml", "--json"]);
        assert_eq!(code(&o), 0, "{rule}: {}", stderr(&o));
        let v: serde_json::Value = serde_json::from_str(&stdout(&o)).unwrap();
        assert_eq!(v["totals"]["skipped"].as_f64(), Some(18446744073709551616.0));
    }
    // A space over the limit that a rule on its first dimensions brings under it.
    write_config(d, &format!("{}skip = [{{ when = \"B0 || B1 || B2 || B3 || B4 || B5 || B6 || B7 || B8 || B9 || B10 || B11 || B12 || B13 || B14 || B15 || B16 || B17 || B18 || B19 || B20 || B21 || B22 || B23 || B24 || B25 || B26 || B27 || B28 || B29\", why = \"few\" }}]\n", bools(32)));
    let o = kiln(d, &["list", "--config", "p.toml", "--no-analysis"]);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    assert_eq!(stdout(&o).lines().filter(|l| l.starts_with("S@sm5{")).count(), 4);
}

#[test]
fn the_limit_is_set_on_the_command_line_or_in_the_file() {
    let fx = fixture();
    let d = fx.path();
    write_config(d, &bools(12));
    let o = build(d, &["--max-permutations", "1000"]);
    assert_eq!(code(&o), 2, "{}", stderr(&o));
    assert!(stderr(&o).contains("2^12 (4096) permutations at level `sm5`, over the limit of 1000"), "{}", stderr(&o));
    let o = kiln(d, &["list", "--config", "p.toml", "--max-permutations", "1000"]);
    assert_eq!(code(&o), 2, "{}", stderr(&o));
    let text = std::fs::read_to_string(d.join("p.toml")).unwrap();
    std::fs::write(d.join("p.toml"), text.replace("[compiler]\n", "[compiler]\nmax_permutations = 1000\n")).unwrap();
    let o = kiln(d, &["list", "--config", "p.toml", "--no-analysis"]);
    assert_eq!(code(&o), 2, "{}", stderr(&o));
    let o = kiln(d, &["list", "--config", "p.toml", "--no-analysis", "--max-permutations", "5000"]);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    // The limit counts every shader at every level: two levels of 4096 are over 5000.
    let text = std::fs::read_to_string(d.join("p.toml")).unwrap();
    let two = text.replace("[[shader]]", "[levels.es3_1]\ntargets = [\"glsl\"]\n\n[[shader]]");
    std::fs::write(d.join("p.toml"), &two).unwrap();
    let o = kiln(d, &["list", "--config", "p.toml", "--no-analysis", "--max-permutations", "5000"]);
    assert_eq!(code(&o), 2, "{}", stderr(&o));
    assert!(stderr(&o).contains("the permutation set has more than 5000 permutations"), "{}", stderr(&o));
    let o = kiln(d, &["list", "--config", "p.toml", "--no-analysis", "--max-permutations", "5000", "--level", "sm5"]);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    std::fs::write(d.join("p.toml"), text.replace("max_permutations = 1000", "max_permutations = -1")).unwrap();
    let o = kiln(d, &["list", "--config", "p.toml"]);
    assert_eq!(code(&o), 2, "{}", stderr(&o));
    assert!(stderr(&o).contains("p.toml:2:20"), "{}", stderr(&o));
}

#[test]
fn list_streams_a_large_kept_set_in_bounded_memory() {
    let fx = fixture();
    let d = fx.path();
    write_config(d, &bools(17));
    let o = kiln(d, &["list", "--config", "p.toml"]);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    assert_eq!(stdout(&o).lines().filter(|l| l.starts_with("S@sm5{")).count(), 1 << 17);
    assert!(stderr(&o).contains("the analysis (distinct sources, dead dimensions) runs up to"), "{}", stderr(&o));
    // Peak memory of the largest child so far (every child of this test binary is small).
    // SAFETY: rusage is plain integers and timevals; all zeroes is a valid value.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: getrusage fills the struct we pass.
    unsafe { libc::getrusage(libc::RUSAGE_CHILDREN, &mut usage) };
    assert!(usage.ru_maxrss < 200 * 1024, "peak RSS {} KiB", usage.ru_maxrss);
}

// --- 3. No panic, no hang ---------------------------------------------------------------------

#[test]
fn names_longer_than_a_format_width_are_listed_and_explained() {
    let fx = fixture();
    let d = fx.path();
    let long = "D".repeat(66_000);
    write_config(d, &format!("dimensions = {{ {long} = \"bool\" }}\n"));
    std::fs::write(d.join("s.usf"), "@compute @workgroup_size(1) fn main() {}\n").unwrap();
    let o = kiln(d, &["list", "--config", "p.toml"]);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    assert!(stdout(&o).contains(&long));
    let name = format!("S@sm5{{{long}=1}}");
    let o = kiln(d, &["explain", &name, "--config", "p.toml"]);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    // A shader name of that length too.
    let config = std::fs::read_to_string(d.join("p.toml"))
        .unwrap()
        .replace("name = \"S\"", &format!("name = \"{}\"", "S".repeat(66_000)));
    std::fs::write(d.join("p.toml"), config).unwrap();
    let o = kiln(d, &["list", "--config", "p.toml", "--no-analysis"]);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
}

#[test]
fn a_config_that_is_not_a_regular_file_is_an_error_without_blocking() {
    let fx = fixture();
    let d = fx.path();
    mkfifo(&d.join("fifo.toml"));
    std::fs::create_dir(d.join("dir.toml")).unwrap();
    for (config, why) in [("fifo.toml", "it is a FIFO"), ("dir.toml", "it is a directory"), ("/dev/null", "device")] {
        for cmd in ["build", "list"] {
            let o = kiln(d, &[cmd, "--config", config]);
            assert_eq!(code(&o), 2, "{cmd} {config}: {}", stderr(&o));
            assert!(stderr(&o).contains(why), "{cmd} {config}: {}", stderr(&o));
        }
        let o = kiln(d, &["explain", "S@sm5{A=1}", "--config", config]);
        assert_eq!(code(&o), 2, "{}", stderr(&o));
        // The input of `kiln preprocess` too.
        let o = kiln(d, &["preprocess", config]);
        assert_eq!(code(&o), 2, "preprocess {config}: {}", stderr(&o));
        assert!(stderr(&o).contains(why) && stderr(&o).contains("not a regular file"), "{}", stderr(&o));
    }
    assert_dev_null_intact();
}

// --- 4. Configuration gaps ---------------------------------------------------------------------

#[test]
fn configuration_gaps_are_located_errors() {
    let fx = fixture();
    let d = fx.path();
    let cases: [(&str, &str, &str); 4] = [
        ("[levels.sm5]\ntargets = []\n", "level `sm5` has no targets", "p.toml:5:"),
        (
            "dimensions = { defined = \"bool\" }\n",
            "dimension `defined` is a name the preprocessor reserves",
            "p.toml:11:",
        ),
        ("dimensions = { __LINE__ = \"bool\" }\n", "reserves", "p.toml:11:"),
        ("defines = { __VA_ARGS__ = 1 }\n", "reserves", "p.toml:11:"),
    ];
    for (tail, message, at) in cases {
        if tail.starts_with("[levels") {
            let text = format!("[compiler]\ninclude = [\".\"]\n\n{tail}\n[[shader]]\nname = \"S\"\nsource = \"s.usf\"\nstage = \"compute\"\n");
            std::fs::write(d.join("p.toml"), text).unwrap();
        } else {
            write_config(d, tail);
        }
        let o = build(d, &[]);
        assert_eq!(code(&o), 2, "{tail}: {}", stderr(&o));
        let err = stderr(&o);
        assert!(err.contains(message) && err.contains(at), "{tail}: {err}");
    }
    // A skip rule that divides by zero: a configuration error at the rule.
    write_config(d, "dimensions = { A = [0, 2] }\nskip = [{ when = \"4 / A == 2\", why = \"half\" }]\n");
    let o = build(d, &["-o", "out.kpak"]);
    assert_eq!(code(&o), 2, "{}", stderr(&o));
    let err = stderr(&o);
    assert!(err.contains("division by zero") && err.contains("p.toml:12:18") && err.contains("S@sm5{A=0}"), "{err}");
    // Dotted keys 10,000 deep.
    let deep = format!("{} = 1\n", vec!["a"; 10_000].join("."));
    std::fs::write(d.join("p.toml"), format!("[levels.sm5]\n{deep}")).unwrap();
    let o = build(d, &[]);
    assert_eq!(code(&o), 2, "{}", stderr(&o));
    assert!(stderr(&o).contains("p.toml:2:1"), "{}", &stderr(&o)[..stderr(&o).len().min(2000)]);
}

#[test]
fn a_cache_folder_that_cannot_be_made_only_warns() {
    let fx = fixture();
    let d = fx.path();
    std::fs::write(d.join("file"), "not a folder").unwrap();
    let o = kiln(d, &["build", "--config", "p.toml", "--cache-dir", "file/cache", "-o", "out.kpak"]);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    assert!(stderr(&o).contains("building without a cache"), "{}", stderr(&o));
    assert!(d.join("out.kpak").is_file());
}

// --- 5. The configuration loader under random mutations -----------------------------------

struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

/// Pieces that make configuration-shaped garbage.
const PIECES: [&str; 40] = [
    "[",
    "]",
    "{",
    "}",
    "=",
    ",",
    ".",
    "\"",
    "'",
    "\n",
    " ",
    "#",
    "[[shader]]",
    "[levels.x]",
    "[compiler]",
    "dimensions",
    "skip",
    "when",
    "why",
    "derived",
    "defines",
    "targets",
    "limits",
    "levels",
    "bool",
    "range",
    "enum",
    "0",
    "-1",
    "9223372036854775807",
    "1e400",
    "/ 0",
    "% 0",
    "defined",
    "__LINE__",
    "B0",
    "&&",
    "||",
    "max_permutations",
    "\u{0}",
];

const SEED_CONFIG: &str = r#"[compiler]
include = ["."]

[levels.sm5]
defines = { FEATURE_LEVEL = 5 }
targets = ["wgsl", "spirv"]

[levels.es3_1]
targets = ["glsl"]
limits = "downlevel"

[[shader]]
name = "S"
source = "s.usf"
stage = "compute"
dimensions = { A = "bool", B = { range = [0, 3] }, C = { enum = ["X", "Y"] }, D = [1, 2, 4] }
derived = { E = "A * B" }
skip = [{ when = "A && B > 2", why = "unused" }, { when = "D == 4 && C == C_Y", why = "unused" }]
"#;

fn mutate(rng: &mut Rng, text: &str) -> String {
    let mut bytes = text.as_bytes().to_vec();
    for _ in 0..1 + rng.below(4) {
        let at = rng.below(bytes.len() + 1);
        match rng.below(4) {
            0 => {
                let piece = PIECES[rng.below(PIECES.len())];
                bytes.splice(at..at, piece.bytes());
            }
            1 => {
                let end = (at + rng.below(12)).min(bytes.len());
                bytes.drain(at..end);
            }
            2 if !bytes.is_empty() => {
                let i = rng.below(bytes.len());
                bytes[i] = rng.next() as u8;
            }
            _ => {
                // Repeat a slice: long names, deep nesting.
                let end = (at + rng.below(8)).min(bytes.len());
                let slice = bytes[at..end].to_vec();
                for _ in 0..rng.below(200) {
                    bytes.splice(at..at, slice.iter().copied());
                }
            }
        }
    }
    String::from_utf8_lossy(&bytes).into_owned()
}

#[test]
fn config_loader_fuzz_never_panics() {
    let fx = fixture();
    let d = fx.path();
    let path = d.join("p.toml");
    assert!(kiln::permute::load_str(SEED_CONFIG, &path).is_ok());
    // The bundled set too, loaded where it lies (its sources resolve there).
    let bundled_path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../permutations.toml");
    let bundled = std::fs::read_to_string(&bundled_path).unwrap();
    assert!(kiln::permute::load_str(&bundled, &bundled_path).is_ok());
    let mut rng = Rng(0x9E37_79B9_7F4A_7C15);
    let start = Instant::now();
    let mut loaded = 0;
    let mut tried = 0;
    // Bounded by count and by time (a few seconds at most on a slow machine).
    for i in 0..3000 {
        if start.elapsed() > Duration::from_secs(5) {
            break;
        }
        tried += 1;
        let (seed, at) = if i % 4 == 3 { (bundled.as_str(), &bundled_path) } else { (SEED_CONFIG, &path) };
        let text = mutate(&mut rng, seed);
        let r = std::panic::catch_unwind(|| {
            let Ok(config) = kiln::permute::load_str(&text, at) else { return false };
            if config.check_space(|_, _| true, 4096, false).is_ok() {
                for p in config.kept_where(|_, _| true).take(5000) {
                    let _ = config.evaluation_error(&p).map(|e| e.render());
                    let _ = p.name();
                }
                let _ = config.counts();
            }
            true
        });
        match r {
            Ok(ok) => loaded += ok as usize,
            Err(_) => panic!("the loader panicked on mutation {i}:\n{text}"),
        }
        // Every 100th (of the small set) through the command line too: exit 0, 1 or 2 only.
        if i % 100 == 0 {
            std::fs::write(&path, &text).unwrap();
            kiln(d, &["list", "--config", "p.toml", "--no-analysis", "--max-permutations", "4096"]);
        }
    }
    eprintln!("{tried} mutations, {loaded} of them loaded");
    assert!(loaded > 0, "some mutations still load");
}

// --- Issue 28 ------------------------------------------------------------------------------------

/// `kiln args` in `dir` under `ulimit -v` of `kib` KiB (address space), as [`kiln`] checks it.
fn kiln_limited(dir: &Path, kib: u64, args: &[&str]) -> Output {
    let script = format!("ulimit -v {kib} && exec \"$0\" \"$@\"");
    let mut full = vec!["-c", script.as_str(), env!("CARGO_BIN_EXE_kiln")];
    full.extend_from_slice(args);
    let o = crate::without_settings(&mut Command::new("sh"))
        .args(&full)
        .current_dir(dir)
        .stdin(Stdio::null())
        .output()
        .unwrap();
    let code = o.status.code().unwrap_or_else(|| panic!("kiln {args:?} died by a signal: {}", stderr(&o)));
    assert!(matches!(code, 0..=2), "kiln {args:?} exited {code}: {}", stderr(&o));
    assert!(!stderr(&o).contains("panicked") && !stderr(&o).contains("memory allocation"), "{}", stderr(&o));
    o
}

/// Case 4: shard counts far larger than the keys cost nothing (shards past the keys get
/// an empty share); a count or index that cannot be used is exit 2 with a message.
#[test]
fn shard_counts_are_bounded_by_the_keys() {
    let fx = fixture();
    let d = fx.path();
    for shard in ["0/100000000", "1/10000000000", "0/18446744073709551615", "18446744073709551614/18446744073709551615"]
    {
        let start = Instant::now();
        let o = kiln_limited(d, 1 << 20, &["build", "--config", "p.toml", "--cache-dir", "cache", "--shard", shard]);
        assert_eq!(code(&o), 0, "{shard}: {}", stderr(&o));
        assert!(start.elapsed() < Duration::from_secs(60), "{shard}: {:?}", start.elapsed());
    }
    for shard in ["0/18446744073709551616", "5/5", "0/0", "-1/4"] {
        let arg = format!("--shard={shard}");
        let o = kiln_limited(d, 1 << 20, &["build", "--config", "p.toml", "--cache-dir", "cache", &arg]);
        assert_eq!(code(&o), 2, "{shard}: {}", stderr(&o));
        assert!(stderr(&o).contains("invalid shard"), "{shard}: {}", stderr(&o));
    }
    let o = kiln_limited(
        d,
        1 << 20,
        &["build", "--config", "p.toml", "--cache-dir", "cache", "--shards", "99999999999999999999"],
    );
    assert_eq!(code(&o), 2, "{}", stderr(&o));
}

/// Case 6: a FIFO, a link to `/dev/zero` or a folder where the cache keeps its records,
/// stamps or packs is ignored: the build finishes, in bounded memory, with the same archive.
#[test]
fn cache_files_that_are_not_regular_are_ignored() {
    let fx = fixture();
    let d = fx.path();
    assert_eq!(code(&build(d, &[])), 0);
    let archive = std::fs::read(d.join("shaders.kpak")).unwrap();
    let cache_files = |ext: &str| -> Vec<PathBuf> {
        std::fs::read_dir(d.join("cache"))
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.extension().is_some_and(|e| e == ext))
            .collect()
    };
    for ext in ["kpp", "stamp", "kcp"] {
        assert!(!cache_files(ext).is_empty(), "{ext}");
    }
    for (n, replace) in ["fifo", "zero", "dir"].iter().enumerate() {
        for ext in ["kpp", "stamp", "kcp"] {
            for path in cache_files(ext) {
                if path.is_dir() {
                    std::fs::remove_dir(&path).unwrap();
                } else {
                    std::fs::remove_file(&path).unwrap();
                }
                match *replace {
                    "fifo" => mkfifo(&path),
                    "zero" => std::os::unix::fs::symlink("/dev/zero", &path).unwrap(),
                    _ => std::fs::create_dir(&path).unwrap(),
                }
            }
        }
        std::fs::remove_file(d.join("shaders.kpak")).unwrap();
        let o = kiln_limited(d, 2 << 20, &["build", "--config", "p.toml", "--cache-dir", "cache"]);
        assert_eq!(code(&o), 0, "{replace}: {}", stderr(&o));
        assert_eq!(std::fs::read(d.join("shaders.kpak")).unwrap(), archive, "{replace} {n}");
        // Stats and gc pass them by.
        let o = kiln(d, &["cache", "stats", "--cache-dir", "cache"]);
        assert_eq!(code(&o), 0, "{replace}: {}", stderr(&o));
    }
    assert_dev_null_intact();
}

/// Case 11: read-only cache commands on a mistyped folder say so and create nothing.
#[test]
fn cache_commands_never_create_a_folder() {
    let fx = fixture();
    let d = fx.path();
    for action in [&["stats"][..], &["clear"], &["gc", "--max-size", "1M"]] {
        let mut args = vec!["cache"];
        args.extend_from_slice(action);
        args.extend_from_slice(&["--cache-dir", "typo/cache"]);
        let o = kiln(d, &args);
        assert_eq!(code(&o), 0, "{action:?}: {}", stderr(&o));
        assert!(stdout(&o).contains("no cache there"), "{action:?}: {}", stdout(&o));
        assert!(!d.join("typo").exists(), "{action:?} created a folder");
    }
    // The default folder of a config that never built: not made either.
    let o = kiln(d, &["cache", "stats", "--config", "p.toml"]);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    assert!(!d.join(".kiln-cache").exists() && !d.join("target").exists());
    // A file where the folder should be is an error.
    std::fs::write(d.join("file"), b"x").unwrap();
    let o = kiln(d, &["cache", "stats", "--cache-dir", "file"]);
    assert_eq!(code(&o), 2, "{}", stderr(&o));
}

/// Case 10, configurations: a name with control characters is shown escaped in the error.
#[test]
fn names_in_configuration_errors_are_escaped() {
    let fx = fixture();
    let d = fx.path();
    std::fs::write(
        d.join("p.toml"),
        "[levels.sm5]\ntargets = [\"wgsl\"]\n\n[[shader]]\nname = \"S\\u001b[2J\\u0007\"\nsource = \"s.usf\"\nstage = \"compute\"\n",
    )
    .unwrap();
    for cmd in ["build", "list"] {
        let o = kiln(d, &[cmd, "--config", "p.toml"]);
        assert_eq!(code(&o), 2, "{}", stderr(&o));
        assert!(!o.stderr.contains(&0x1b) && !o.stderr.contains(&0x07), "{}", stderr(&o));
        assert!(stderr(&o).contains("S\\u{1b}[2J\\u{7}"), "{}", stderr(&o));
    }
}

/// Case 12: signed overflow in `#if` and in a derived define is a located error, as cpp
/// reports it (`-pedantic-errors`), not a silent wrap.
#[test]
fn arithmetic_that_overflows_is_a_located_error() {
    let fx = fixture();
    let d = fx.path();
    write_config(
        d,
        "dimensions = { A = \"bool\" }\nderived = { X = \"A * 9223372036854775807 + 9223372036854775807\" }\n",
    );
    let o = build(d, &[]);
    assert_eq!(code(&o), 2, "{}", stderr(&o));
    assert!(
        stderr(&o).contains("integer overflow in preprocessor expression") && stderr(&o).contains("p.toml:"),
        "{}",
        stderr(&o)
    );
    write_config(d, "");
    std::fs::write(
        d.join("s.usf"),
        "#if 9223372036854775807 + 1 < 0\n#endif\n@compute @workgroup_size(1) fn main() {}\n",
    )
    .unwrap();
    let o = build(d, &[]);
    assert_eq!(code(&o), 1, "{}", stderr(&o));
    assert!(
        stderr(&o).contains("integer overflow in preprocessor expression") && stderr(&o).contains("s.usf:1:25"),
        "{}",
        stderr(&o)
    );
}

/// Case 9: near-miss search for a 120 KB name over 622 permutations (a long shader name
/// too) ends quickly, for `explain` on the configuration and `inspect` on the archive.
#[test]
fn near_miss_search_of_a_huge_name_is_bounded() {
    let fx = fixture();
    let d = fx.path();
    write_config(d, "dimensions = { A = \"bool\", B = { range = [0, 310] } }\n");
    std::fs::write(d.join("s.usf"), "@compute @workgroup_size(1) fn main() { let b = B; }\n").unwrap();
    std::fs::write(d.join("l.usf"), "@compute @workgroup_size(1) fn main() { }\n").unwrap();
    // A second shader with a long name (the edit distance is over both names).
    let second = format!("\n[[shader]]\nname = \"{}\"\nsource = \"l.usf\"\nstage = \"compute\"\n", "L".repeat(20_000));
    let config = std::fs::read_to_string(d.join("p.toml")).unwrap();
    std::fs::write(d.join("p.toml"), config + &second).unwrap();
    let o = build(d, &["-o", "a.kpak"]);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    // 120 KB: under the kernel's bound of one argument (128 KiB).
    let huge = format!("{}@sm5{{A=1,B=7,{}}}", "X".repeat(100_000), "C=1,".repeat(5_000));
    for args in [vec!["explain", huge.as_str(), "--config", "p.toml"], vec!["inspect", "a.kpak", huge.as_str()]] {
        let start = Instant::now();
        let o = kiln(d, &args);
        assert_eq!(code(&o), 2, "{}", stderr(&o));
        assert!(start.elapsed() < Duration::from_secs(3), "{}: {:?}", args[0], start.elapsed());
        let e = stderr(&o);
        assert!(e.contains("S@sm5{A=1,B=7}"), "{}: {}", args[0], &e[e.len().saturating_sub(3000)..]);
    }
}
