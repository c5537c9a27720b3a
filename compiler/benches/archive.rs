//! The archive format in numbers, measured in one run.
//!
//! `cargo bench -p kiln --bench archive [-- CONFIG]` (CONFIG defaults to the workspace's
//! `permutations.toml`, the bundled set). For each of
//!
//! 1. the bundled set, built through `kiln::build::run` (its cache under `target/`);
//! 2. a generated set of 1,024 permutations (one fragment shader with 9 bool dimensions,
//!    every dimension adding code, at two levels: real naga artifacts);
//! 3. a generated archive of about 1 GiB (1,024 permutations, 1 MiB of incompressible bytes
//!    each): what opening costs when the body is large and the manifest is not;
//!
//! it prints the sizes (raw artifacts, what format 1 would take, what format 2 takes, the
//! ratio), the time to write the archive, the median open time (memory map, header and
//! manifest checked and parsed), and the median of one lookup by name plus decompression of
//! one artifact, first use (checksum checked) and later uses. Goals (issue 12): at most 1/8 of
//! format 1, open at most 1 ms, lookup + decompression at most 100 µs median.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use kiln::archive::{Archive, ArchiveWriter, DimensionRecord, PermutationRecord, Reflection, ShaderRecord, Target};
use kiln::build::{self, CacheDir};
use kiln::Stage;

fn median(mut v: Vec<Duration>) -> Duration {
    v.sort();
    v[v.len() / 2]
}

fn us(d: Duration) -> f64 {
    d.as_secs_f64() * 1e6
}

fn mb(b: u64) -> f64 {
    b as f64 / 1e6
}

/// Writes the generated 1,024-permutation set: every bool dimension adds code of its own.
fn generate_set(dir: &Path) -> PathBuf {
    let src = dir.join("src");
    std::fs::create_dir_all(&src).unwrap();
    let mut main = String::from(
        "struct Params { tint: vec4<f32>, scale: vec4<f32> }\n@group(0) @binding(0) var<uniform> params: Params;\n",
    );
    for d in 0..9 {
        main.push_str(&format!(
            "#if D{d}\nfn feature{d}(c: vec4<f32>, uv: vec2<f32>) -> vec4<f32> {{\n    let w = sin(uv.x * {d}.5 + uv.y) * 0.5 + 0.5;\n    return mix(c, c * params.tint + vec4<f32>(w, {d}.0 / 10.0, uv), params.scale.x * f32(FACTOR_PCT) / 100.0);\n}}\n#endif\n"
        ));
    }
    main.push_str(
        "@fragment\nfn main_ps(@location(0) uv: vec2<f32>) -> @location(0) vec4<f32> {\n    var c = params.tint;\n",
    );
    for d in 0..9 {
        main.push_str(&format!("#if D{d}\n    c = feature{d}(c, uv);\n#endif\n"));
    }
    main.push_str("    return c;\n}\n");
    std::fs::write(src.join("Main.usf"), main).unwrap();
    let dims: Vec<String> = (0..9).map(|d| format!("D{d} = \"bool\"")).collect();
    let toml = format!(
        "[compiler]\ninclude = [\"src\"]\n\n[levels.sm5]\ndefines = {{ FACTOR_PCT = 100 }}\ntargets = [\"wgsl\", \"spirv\", \"msl\", \"hlsl\"]\n\n[levels.es3_1]\ndefines = {{ FACTOR_PCT = 50 }}\ntargets = [\"glsl\", \"spirv\", \"msl\", \"wgsl\"]\nlimits = \"downlevel\"\n\n[[shader]]\nname = \"GeneratedPS\"\nsource = \"Main.usf\"\nentry = \"main_ps\"\nstage = \"fragment\"\nlevels = [\"sm5\", \"es3_1\"]\ndimensions = {{ {} }}\n",
        dims.join(", ")
    );
    let config = dir.join("generated.toml");
    std::fs::write(&config, toml).unwrap();
    config
}

/// Builds `config` into `out` with the cache `cache`; returns the seconds taken.
fn build_archive(config: &Path, out: &Path, cache: &Path) -> f64 {
    let options = build::Options {
        config: config.to_path_buf(),
        output: Some(out.to_path_buf()),
        cache: CacheDir::Dir(cache.to_path_buf()),
        ..build::Options::default()
    };
    let t = Instant::now();
    match build::run(&options) {
        Ok(_) => {}
        Err(build::Error::Failed(r)) => panic!("build of {} failed:\n{}", config.display(), r.failures.join("\n")),
        Err(e) => panic!("build of {} failed: {e}", config.display()),
    }
    t.elapsed().as_secs_f64()
}

/// Opens `path` repeatedly and looks up + decompresses artifacts; prints one block.
fn measure(label: &str, path: &Path) {
    let a = Archive::open(path).unwrap();
    let (mut raw, mut stored) = (0u64, 0u64);
    for id in 0..a.blob_count() {
        let info = a.blob_info(kiln::archive::BlobId(id as u32)).unwrap();
        raw += info.raw_len;
        stored += info.stored_len;
    }
    let dictionaries: u64 = a.dictionaries().map(|(_, l)| l).sum();
    let file = a.len() as u64;
    // Format 1 held the raw blobs (8-byte aligned) and about the same manifest.
    let format1 = file - stored - dictionaries + raw + 8 * a.blob_count() as u64;
    let perms: Vec<(String, Target)> =
        a.permutations().map(|p| (p.name().to_string(), p.targets().next().unwrap())).collect();
    drop(a);

    let opens: Vec<Duration> = (0..51)
        .map(|_| {
            let t = Instant::now();
            let a = Archive::open(path).unwrap();
            let d = t.elapsed();
            std::hint::black_box(a);
            d
        })
        .collect();
    let a = Archive::open(path).unwrap();
    let order: Vec<usize> = (0..perms.len().min(2000)).map(|i| (i * 7919) % perms.len()).collect();
    let lookup = |i: usize| {
        let (name, t) = &perms[i];
        let t0 = Instant::now();
        let bytes = a.get(name).unwrap().artifact(*t).unwrap().unwrap();
        let d = t0.elapsed();
        std::hint::black_box(bytes);
        d
    };
    let first: Vec<Duration> = order.iter().map(|&i| lookup(i)).collect();
    let again: Vec<Duration> = order.iter().map(|&i| lookup(i)).collect();
    println!("{label}: {} permutations, {} distinct artifacts", perms.len(), a.blob_count());
    println!("  artifacts raw:                  {:10.2} MB", mb(raw));
    println!("  format 1 (raw blobs):           {:10.2} MB", mb(format1));
    println!(
        "  format 2:                       {:10.2} MB  (blobs {:.2} MB + dictionaries {:.3} MB)",
        mb(file),
        mb(stored),
        mb(dictionaries)
    );
    println!("  format 2 / format 1:            {:10.3}  (goal <= 0.125)", file as f64 / format1 as f64);
    println!("  open (mmap, header + manifest): {:10.1} us median  (goal <= 1000)", us(median(opens)));
    println!("  lookup + decompress, first use: {:10.1} us median  (checksum checked)", us(median(first)));
    println!("  lookup + decompress, again:     {:10.1} us median  (goal <= 100)", us(median(again)));
}

/// An archive of `count` permutations, each with one incompressible blob of `blob` bytes.
fn big_archive(path: &Path, count: usize, blob: usize) -> f64 {
    let mut w = ArchiveWriter::new();
    let shader = w.add_shader(ShaderRecord {
        name: "BigPS".into(),
        level: "sm5".into(),
        entry: "main_ps".into(),
        stage: Stage::Fragment,
        dimensions: vec![DimensionRecord { name: "VARIANT".into(), labels: vec![] }],
    });
    let reflection = w.add_reflection(&Reflection {
        entry: "main_ps".into(),
        stage: Stage::Fragment,
        bindings: vec![],
        vertex_inputs: vec![],
        color_outputs: vec![],
        workgroup_size: None,
    });
    let mut bytes = vec![0u8; blob];
    for i in 0..count {
        // blake3's XOF as a fast source of incompressible bytes.
        blake3::Hasher::new().update(&(i as u64).to_le_bytes()).finalize_xof().fill(&mut bytes);
        let id = w.add_blob(&bytes);
        w.add_permutation(PermutationRecord {
            name: format!("BigPS@sm5{{VARIANT={i}}}"),
            shader,
            values: vec![i as i64],
            reflection,
            artifacts: vec![(Target::Spirv, id)],
        });
    }
    let t = Instant::now();
    w.write_unsynced(path).unwrap();
    t.elapsed().as_secs_f64()
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).filter(|a| !a.starts_with("--")).collect();
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let config = args.first().map(PathBuf::from).unwrap_or_else(|| root.join("permutations.toml"));
    let scratch = tempfile::tempdir().unwrap();
    let cache = root.join("target/kiln-bench-cache");

    let out = scratch.path().join("bundled.kpak");
    let secs = build_archive(&config, &out, &cache);
    println!("(build of {} with its cache: {secs:.2} s)", config.display());
    measure(&format!("set {}", config.display()), &out);

    let gen = generate_set(scratch.path());
    let out = scratch.path().join("generated.kpak");
    let secs = build_archive(&gen, &out, &cache);
    println!("(build of the generated set: {secs:.2} s)");
    measure("generated set", &out);
    // Writing alone (dictionary training and compression), from the cache.
    std::fs::remove_file(&out).unwrap();
    let secs = build_archive(&gen, &out, &cache);
    println!("  warm rebuild, archive rewritten: {secs:.2} s");

    let out = scratch.path().join("big.kpak");
    let secs = big_archive(&out, 1024, 1 << 20);
    println!("(generated 1 GiB archive written in {secs:.2} s)");
    measure("1 GiB archive", &out);
}
