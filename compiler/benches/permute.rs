//! Permutation throughput: enumerate (skip rules and derived defines evaluated) and
//! preprocess a large generated permutation set, and print permutations per second.
//!
//! `cargo bench -p kiln --bench permute` (set `KILN_BENCH_DIMS` to change the number of bool
//! dimensions of the preprocessed shader; default 10, so 1024 permutations per level).
//! Every number is measured in this one run; the ratios compare runs of the same work.

use std::path::Path;
use std::time::Instant;

use kiln::permute::{self, Permutation};
use kiln::preprocess::{self, SourceCache};

/// Writes a permutation set: one shader with `dims` bool dimensions (each used by the source
/// through `#if` and a macro), two levels, a skip rule and a derived define, and `headers`
/// included headers with `#pragma once`.
fn generate(dir: &Path, dims: usize, headers: usize) {
    let src = dir.join("src");
    std::fs::create_dir_all(&src).unwrap();
    let mut main = String::new();
    for h in 0..headers {
        main.push_str(&format!("#include \"Header{h}.ush\"\n"));
        let mut header = format!("#pragma once\n// header {h}\n#define SCALE{h}(x) ((x) * {h}.5)\n");
        for f in 0..20 {
            header.push_str(&format!(
                "fn h{h}_f{f}(v: vec4<f32>) -> vec4<f32> {{\n#if FEATURE_LEVEL >= 5\n    return v * SCALE{h}({f}.0);\n#else\n    return v + vec4<f32>({f}.0);\n#endif\n}}\n"
            ));
        }
        std::fs::write(src.join(format!("Header{h}.ush")), header).unwrap();
    }
    main.push_str("@fragment\nfn main() -> @location(0) vec4<f32> {\n    var c = vec4<f32>(0.0);\n");
    for d in 0..dims {
        main.push_str(&format!(
            "#if D{d}\n    c = h{}_f{}(c) + vec4<f32>(f32(D{d} + PACKED));\n#endif\n",
            d % headers.max(1),
            d % 20
        ));
    }
    main.push_str("    return c;\n}\n");
    std::fs::write(src.join("Main.usf"), main).unwrap();

    let dim_list: Vec<String> = (0..dims).map(|d| format!("D{d} = \"bool\"")).collect();
    let toml = format!(
        r#"[compiler]
include = ["src"]

[levels.sm5]
defines = {{ FEATURE_LEVEL = 5 }}

[levels.es3_1]
defines = {{ FEATURE_LEVEL = 3, ES3_1_PROFILE = 1 }}

[[shader]]
name = "Big"
source = "Main.usf"
stage = "fragment"
dimensions = {{ {} }}
derived = {{ PACKED = "D0 && ES3_1_PROFILE" }}
skip = [{{ when = "D0 && D1 && FEATURE_LEVEL < 5", why = "bench" }}]

[[shader]]
name = "Huge"
source = "Main.usf"
stage = "fragment"
levels = ["sm5"]
dimensions = {{ {} }}
skip = [{{ when = "E0 && E19", why = "bench" }}]
"#,
        dim_list.join(", "),
        (0..20).map(|d| format!("E{d} = \"bool\"")).collect::<Vec<_>>().join(", ")
    );
    std::fs::write(dir.join("permutations.toml"), toml).unwrap();
}

fn main() {
    let dims: usize = std::env::var("KILN_BENCH_DIMS").ok().and_then(|v| v.parse().ok()).unwrap_or(10);
    let dir = tempfile::tempdir().unwrap();
    generate(dir.path(), dims, 8);
    let config = match permute::load(&dir.path().join("permutations.toml")) {
        Ok(c) => c,
        Err(e) => panic!("{}", e.render()),
    };

    // 1. Enumeration alone: the 20-dimension shader (a million permutations), streamed.
    let t = Instant::now();
    let (mut kept, mut total) = (0usize, 0usize);
    for p in config.permutations_where(|s, _| s.name == "Huge") {
        total += 1;
        kept += usize::from(p.is_kept());
    }
    let enum_secs = t.elapsed().as_secs_f64();
    let enum_rate = total as f64 / enum_secs;
    println!("enumerate: {total} permutations ({kept} kept) in {enum_secs:.3} s = {enum_rate:.0} permutations/s");

    // 2. Enumerate and preprocess every kept permutation of `Big`, in parallel, one shared cache.
    let only_big = |s: &permute::Shader, _: &permute::Level| s.name == "Big";
    let t = Instant::now();
    let cache = SourceCache::new(dir.path().to_path_buf());
    let analysis = permute::analyze(&config, &cache, only_big);
    let par_secs = t.elapsed().as_secs_f64();
    let preprocessed: usize = analysis.levels.iter().map(|l| l.permutations.len()).sum();
    let distinct: usize = analysis.levels.iter().map(|l| l.distinct).sum();
    assert!(analysis.failed.is_empty(), "{}", analysis.failed[0].error);
    let par_rate = preprocessed as f64 / par_secs;
    println!(
        "preprocess (parallel, {} threads, shared cache): {preprocessed} permutations ({distinct} distinct) in {par_secs:.3} s = {par_rate:.0} permutations/s",
        rayon::current_num_threads()
    );

    // 3. The same work on one thread, shared cache.
    let kept_big: Vec<Permutation<'_>> = config.permutations_where(only_big).filter(Permutation::is_kept).collect();
    let t = Instant::now();
    let cache = SourceCache::new(dir.path().to_path_buf());
    for p in &kept_big {
        let out = preprocess::preprocess_file(&p.shader.source_path, &p.preprocess_options(&config), &cache).unwrap();
        std::hint::black_box(out.token_hash());
    }
    let seq_secs = t.elapsed().as_secs_f64();
    let seq_rate = kept_big.len() as f64 / seq_secs;
    println!(
        "preprocess (1 thread, shared cache): {} permutations in {seq_secs:.3} s = {seq_rate:.0} permutations/s",
        kept_big.len()
    );

    // 4. One thread, a fresh cache per permutation (every file read again each time).
    let sample = &kept_big[..kept_big.len().min(256)];
    let t = Instant::now();
    for p in sample {
        let cache = SourceCache::new(dir.path().to_path_buf());
        let out = preprocess::preprocess_file(&p.shader.source_path, &p.preprocess_options(&config), &cache).unwrap();
        std::hint::black_box(out.token_hash());
    }
    let fresh_rate = sample.len() as f64 / t.elapsed().as_secs_f64();
    println!("preprocess (1 thread, fresh cache each): {} permutations = {fresh_rate:.0} permutations/s", sample.len());

    println!("ratio parallel / one thread: {:.2}x", par_rate / seq_rate);
    println!("ratio shared cache / fresh cache: {:.2}x", seq_rate / fresh_rate);
    println!("ratio enumerate / preprocess (parallel): {:.0}x", enum_rate / par_rate);
}
