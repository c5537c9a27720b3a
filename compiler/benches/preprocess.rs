//! Preprocessor throughput, Kiln next to GNU cpp on the same generated input, same run.
//!
//! `cargo bench -p kiln --bench preprocess` generates a shader tree (a couple of hundred
//! include files, several MB, dense with macros and `#if` trees) in a temp dir, then runs
//! `cpp -x c -P -undef -nostdinc -std=c11` and `kiln::preprocess` on it and prints MB/s of
//! both and the ratio, twice: by wall time and by CPU time (user + system; for cpp the child
//! process's, from `getrusage`), best of several interleaved runs. On a machine shared with
//! other work the wall times carry the scheduler's noise; the CPU times do not. Kiln's time
//! includes reading the files (a fresh cache each run), as cpp's does.

use std::fmt::Write as _;
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use kiln::preprocess::{self, Options, SourceCache};

const FILES: usize = 200;
const RUNS: usize = 7;

fn generate(dir: &Path) -> usize {
    let mut total = 0;
    let mut main = String::from("// benchmark main file\n#define LEVEL 5\n#define USE_FOG 1\n");
    for f in 0..FILES {
        let mut s = String::new();
        let guard = format!("FILE_{f}_USH");
        let _ = writeln!(s, "#ifndef {guard}\n#define {guard}\n// generated include {f}");
        if f >= 2 {
            let _ = writeln!(s, "#include \"f{}.ush\"\n#include \"f{}.ush\"", f - 1, f - 2);
        }
        for m in 0..12 {
            let _ = writeln!(s, "#define K{f}_{m} ({m} + LEVEL * {f})");
            let _ = writeln!(s, "#define F{f}_{m}(a, b) ((a) * K{f}_{m} + (b) / 2.0)");
        }
        let _ = writeln!(s, "#define CAT{f}(a, b) a ## b\n#define STR{f}(x) #x");
        for block in 0..30 {
            let _ = writeln!(s, "#if LEVEL >= {} && defined(USE_FOG)", block % 7);
            let _ = writeln!(s, "#  if K{f}_{} > 20 || (USE_FOG && {block} % 3 == 0)", block % 12);
            let _ = writeln!(
                s,
                "fn f{f}_{block}(p: vec4<f32>, n: vec3<f32>) -> vec4<f32> {{\n    let a = F{f}_{}(p.x, p.y) + F{f}_{}(n.z, 1.0);",
                block % 12,
                (block + 5) % 12
            );
            let _ = writeln!(
                s,
                "    var CAT{f}(v, {block}): array<vec4<f32>, 4> = array<vec4<f32>, 4>(p, p * 2.0, p * 3.0, p);"
            );
            let _ = writeln!(s, "    // a comment with words in it, as shaders have /* and nested-looking */ text");
            let _ = writeln!(
                s,
                "    let scale = max(dot(n, vec3<f32>(0.3, 0.59, 0.11)), 0.0) * K{f}_{};",
                (block + 3) % 12
            );
            let _ = writeln!(s, "    return vec4<f32>(a, scale, 0.5, 1.0) + CAT{f}(v, {block})[0];\n}}");
            let _ = writeln!(s, "#  elif K{f}_{} < 0\nfn never{f}_{block}() {{}}\n#  else", block % 12);
            let _ = writeln!(s, "const label{f}_{block} = STR{f}(skipped or not);\nfn g{f}_{block}(x: f32) -> f32 {{ return x * 0.5 + 1.0; }}");
            let _ = writeln!(s, "#  endif\n#else\nfn low{f}_{block}() {{}}\n#endif");
            let _ = writeln!(
                s,
                "@group(0) @binding({block}) var<uniform> u{f}_{block}: vec4<f32>; // plain text line with no macros at all"
            );
            let _ = writeln!(s, "struct S{f}_{block} {{ a: vec4<f32>, b: vec3<f32>, c: f32, d: array<u32, 8> }}");
        }
        let _ = writeln!(s, "#endif");
        total += s.len();
        std::fs::write(dir.join(format!("f{f}.ush")), s).expect("write include");
        let _ = writeln!(main, "#include \"f{f}.ush\"");
    }
    main.push_str("@fragment fn main_ps() -> @location(0) vec4<f32> { return vec4<f32>(1.0); }\n");
    total += main.len();
    std::fs::write(dir.join("main.usf"), main).expect("write main");
    total
}

/// CPU time (user + system) of this process (Kiln preprocesses on a worker thread; child
/// processes are not counted).
fn process_cpu() -> Duration {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: clock_gettime writes the timespec we pass and nothing else.
    unsafe { libc::clock_gettime(libc::CLOCK_PROCESS_CPUTIME_ID, &mut ts) };
    Duration::new(ts.tv_sec as u64, ts.tv_nsec as u32)
}

/// CPU time (user + system) of all waited-for child processes.
fn children_cpu() -> Duration {
    // SAFETY: getrusage fills the struct we pass; a zeroed rusage is a valid value.
    let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: `ru` is a valid, writable rusage for the call to fill.
    unsafe { libc::getrusage(libc::RUSAGE_CHILDREN, &mut ru) };
    let us = |t: libc::timeval| Duration::new(t.tv_sec as u64, (t.tv_usec * 1000) as u32);
    us(ru.ru_utime) + us(ru.ru_stime)
}

/// Best wall and best CPU time of the runs.
#[derive(Default)]
struct Best {
    wall: Option<Duration>,
    cpu: Option<Duration>,
}

impl Best {
    fn add(&mut self, wall: Duration, cpu: Duration) {
        self.wall = Some(self.wall.map_or(wall, |w| w.min(wall)));
        self.cpu = Some(self.cpu.map_or(cpu, |c| c.min(cpu)));
    }
    fn rates(&self, mb: f64) -> (f64, f64, f64, f64) {
        let (w, c) = (self.wall.unwrap_or_default().as_secs_f64(), self.cpu.unwrap_or_default().as_secs_f64());
        (w * 1e3, mb / w, c * 1e3, mb / c)
    }
}

fn main() {
    let dir = tempfile::tempdir().expect("temp dir");
    let bytes = generate(dir.path());
    // `KILN_BENCH_KEEP=DIR` also copies the generated tree there (to profile by hand).
    if let Ok(keep) = std::env::var("KILN_BENCH_KEEP") {
        let keep = Path::new(&keep);
        std::fs::create_dir_all(keep).expect("create KILN_BENCH_KEEP");
        generate(keep);
    }
    let main = dir.path().join("main.usf");
    let mb = bytes as f64 / 1e6;
    println!("input: {FILES} include files + main, {mb:.2} MB");

    let opts = Options::default();
    let cpp_ok = Command::new("cpp").arg("--version").output().is_ok_and(|o| o.status.success());
    if !cpp_ok {
        println!("cpp: not installed (apt-get install cpp): Kiln alone");
    }
    let (mut kiln, mut cpp) = (Best::default(), Best::default());
    let mut kiln_out = String::new();
    let mut cpp_out = Vec::new();
    // Interleaved, so both see the same machine load.
    for _ in 0..RUNS {
        let cache = SourceCache::new(dir.path().to_path_buf());
        let (t, c) = (Instant::now(), process_cpu());
        let out = preprocess::preprocess_file(&main, &opts, &cache).expect("kiln preprocesses the benchmark");
        kiln.add(t.elapsed(), process_cpu() - c);
        kiln_out = out.text;
        if cpp_ok {
            let (t, c) = (Instant::now(), children_cpu());
            let out = Command::new("cpp")
                .args(["-x", "c", "-P", "-undef", "-nostdinc", "-std=c11", "main.usf"])
                .current_dir(dir.path())
                .output()
                .expect("cpp runs");
            cpp.add(t.elapsed(), children_cpu() - c);
            assert!(out.status.success(), "cpp failed: {}", String::from_utf8_lossy(&out.stderr));
            cpp_out = out.stdout;
        }
    }
    let (kw, kwr, kc, kcr) = kiln.rates(mb);
    println!(
        "kiln: wall {kw:8.2} ms {kwr:7.1} MB/s   cpu {kc:8.2} ms {kcr:7.1} MB/s   (output {:.2} MB)",
        kiln_out.len() as f64 / 1e6
    );
    if !cpp_ok {
        return;
    }
    let (cw, cwr, cc, ccr) = cpp.rates(mb);
    println!("cpp:  wall {cw:8.2} ms {cwr:7.1} MB/s   cpu {cc:8.2} ms {ccr:7.1} MB/s");
    let cpp_text = String::from_utf8_lossy(&cpp_out);
    let same = preprocess::tokens(&kiln_out) == preprocess::tokens(&cpp_text);
    println!("token streams identical: {same}");
    println!("ratio kiln/cpp throughput: wall {:.2}x, cpu {:.2}x", kwr / cwr, kcr / ccr);
    assert!(same, "the benchmark input must preprocess to the same tokens as cpp");
}
