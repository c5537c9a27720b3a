//! The archive format in numbers, measured in one run.
//!
//! `cargo bench -p kiln --bench archive [-- CONFIG]` (CONFIG defaults to the workspace's
//! `permutations.toml`, the bundled set; `KILN_ARCHIVE_SETS=bundled,generated,big,many,files`
//! runs only some of the parts below; `KILN_ARCHIVE_FILES=a.kpak,...` adds archives built
//! elsewhere to `files`). For each of
//!
//! 1. the bundled set, built through `kiln::build::run` (its cache under `target/`);
//! 2. a generated set of 1,024 permutations (one fragment shader with 9 bool dimensions,
//!    every dimension adding code, at two levels: real naga artifacts);
//! 3. a generated archive of about 1 GiB (1,024 permutations, 1 MiB of incompressible bytes
//!    each): what opening costs when the body is large and the manifest is not;
//! 4. generated archives of 10,000 and 100,000 permutations with engine-like names (16
//!    shader/level pairs of 11 dimensions, two small artifacts each): what opening costs when
//!    the manifest is large;
//!
//! it prints the sizes (raw artifacts, what format 1 would take, what this format takes, the
//! ratio), the time to write the archive, the median open time (memory map, header and chunk
//! hashes checked, tables parsed), the first lookup after an open (the chunks its binary
//! search reads checked), the median of one lookup by name plus decompression of one
//! artifact, first use (chunks, record and blob checked) and later uses, and a walk of every
//! record (which checks every chunk of the manifest's records, values, artifacts and names). Goals (issue 12): at most 1/8 of
//! format 1, open at most 1 ms, lookup + decompression at most 100 µs median. For the two
//! real sets it also compares the two schemes issue 12 names (per-target dictionaries and
//! compressed groups of similar artifacts): sizes and what one lookup costs.

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
        a.permutations().unwrap().map(|p| (p.name().to_string(), p.targets().next().unwrap())).collect();
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
    // The first lookup after open: every chunk its binary search reads is checked (the
    // worst case of a lookup), median of fresh opens.
    let order: Vec<usize> = (0..perms.len().min(2000)).map(|i| (i * 7919) % perms.len()).collect();
    let lookup_in = |a: &Archive, i: usize| {
        let (name, t) = &perms[i];
        let t0 = Instant::now();
        let bytes = a.get(name).unwrap().unwrap().artifact(*t).unwrap().unwrap();
        let d = t0.elapsed();
        std::hint::black_box(bytes);
        d
    };
    let cold: Vec<Duration> = order
        .iter()
        .take(21)
        .map(|&i| {
            let a = Archive::open(path).unwrap();
            lookup_in(&a, i)
        })
        .collect();
    // The same without the artifact: the binary search alone, its chunks and record checked
    // (no dictionary loaded, no blob decompressed).
    let cold_get: Vec<Duration> = order
        .iter()
        .cycle()
        .skip(21)
        .take(21)
        .map(|&i| {
            let a = Archive::open(path).unwrap();
            let t0 = Instant::now();
            std::hint::black_box(a.get(&perms[i].0).unwrap().unwrap());
            t0.elapsed()
        })
        .collect();
    // A walk of every record checks them all, and every chunk they lie in.
    let walks: Vec<Duration> = (0..5)
        .map(|_| {
            let a = Archive::open(path).unwrap();
            let t = Instant::now();
            std::hint::black_box(a.permutations().unwrap().count());
            t.elapsed()
        })
        .collect();
    let a = Archive::open(path).unwrap();
    let lookup = |i: usize| lookup_in(&a, i);
    let first: Vec<Duration> = order.iter().map(|&i| lookup(i)).collect();
    let again: Vec<Duration> = order.iter().map(|&i| lookup(i)).collect();
    println!("{label}: {} permutations, {} distinct artifacts", perms.len(), a.blob_count());
    println!("  artifacts raw:                  {:10.2} MB", mb(raw));
    println!("  format 1 (raw blobs):           {:10.2} MB", mb(format1));
    println!(
        "  format {}:                       {:10.2} MB  (blobs {:.2} MB + dictionaries {:.3} MB)",
        kiln::archive::FORMAT_VERSION,
        mb(file),
        mb(stored),
        mb(dictionaries)
    );
    println!(
        "  format {} / format 1:            {:10.3}  (goal <= 0.125)",
        kiln::archive::FORMAT_VERSION,
        file as f64 / format1 as f64
    );
    println!("  open (mmap, header, chunk hashes): {:7.1} us median  (goal <= 1000)", us(median(opens)));
    println!("  first lookup after open:        {:10.1} us median  (the chunks it reads checked)", us(median(cold)));
    println!("  first lookup after open, no artifact: {:4.1} us median  (its chunks checked)", us(median(cold_get)));
    println!("  lookup + decompress, first use: {:10.1} us median  (chunks, record, blob checked)", us(median(first)));
    println!("  lookup + decompress, again:     {:10.1} us median  (goal <= 100)", us(median(again)));
    println!("  walk of every record:           {:10.1} us median  (every chunk checked)", us(median(walks)));
}

/// The two schemes issue 12 names, measured on this archive's artifacts: per-target
/// dictionaries (each artifact its own frame) and compressed groups of similar artifacts
/// (one shader and target, cut at a size). Sizes exclude the manifest; "one lookup" is the
/// median time to decompress what a lookup needs (its frame, or its whole group).
fn compare_schemes(path: &Path) {
    use std::collections::{BTreeMap, HashSet};
    let a = Archive::open(path).unwrap();
    let mut perms: Vec<_> = a.permutations().unwrap().collect();
    perms.sort_by(|x, y| x.name().cmp(y.name()));
    let mut seen = HashSet::new();
    let mut blobs: Vec<(Target, u32, Vec<u8>)> = Vec::new();
    for p in &perms {
        for t in p.targets() {
            let id = p.blob_id(t).unwrap();
            if seen.insert(id) {
                blobs.push((t, p.shader_index(), a.blob(id).unwrap().into_owned()));
            }
        }
    }
    let raw: usize = blobs.iter().map(|b| b.2.len()).sum();
    println!("  schemes ({} distinct artifacts, {:.2} MB raw; sizes without manifest):", blobs.len(), mb(raw as u64));
    let plain: usize = blobs.iter().map(|b| zstd::bulk::compress(&b.2, 3).unwrap().len()).sum();
    println!(
        "    zstd -3 per artifact, no dictionary:   {:7.3} MB {:5.1}x",
        mb(plain as u64),
        raw as f64 / plain as f64
    );
    for dsize in [64usize << 10, 128 << 10] {
        let (mut total, mut times) = (0usize, Vec::new());
        for t in Target::ALL {
            let samples: Vec<&[u8]> = blobs.iter().filter(|b| b.0 == t).map(|b| &b.2[..]).collect();
            if samples.len() < 8 {
                continue;
            }
            let dict =
                zstd::dict::from_samples(&samples, dsize.min(samples.iter().map(|s| s.len()).sum::<usize>() / 16))
                    .unwrap();
            total += dict.len();
            let mut comp = zstd::bulk::Compressor::with_dictionary(3, &dict).unwrap();
            let mut dec = zstd::bulk::Decompressor::with_dictionary(&dict).unwrap();
            for s in &samples {
                let c = comp.compress(s).unwrap();
                total += c.len();
                let t0 = Instant::now();
                std::hint::black_box(dec.decompress(&c, s.len()).unwrap());
                times.push(t0.elapsed());
            }
        }
        println!(
            "    per-target dictionary {:3} KiB, -3:    {:7.3} MB {:5.1}x  one lookup {:7.1} us",
            dsize >> 10,
            mb(total as u64),
            raw as f64 / total as f64,
            us(median(times))
        );
    }
    for cap in [64usize << 10, 256 << 10, 1 << 20] {
        let mut groups: BTreeMap<(u32, Target), Vec<Vec<&[u8]>>> = BTreeMap::new();
        for b in &blobs {
            let g = groups.entry((b.1, b.0)).or_default();
            let full = g.last().is_none_or(|last| last.iter().map(|x| x.len()).sum::<usize>() + b.2.len() > cap);
            if full {
                g.push(Vec::new());
            }
            g.last_mut().unwrap().push(&b.2);
        }
        let (mut total, mut times) = (0usize, Vec::new());
        for chunk in groups.values().flatten() {
            let cat = chunk.concat();
            let c = zstd::bulk::compress(&cat, 3).unwrap();
            total += c.len();
            let t0 = Instant::now();
            std::hint::black_box(zstd::bulk::decompress(&c, cat.len()).unwrap());
            let d = t0.elapsed();
            times.extend(std::iter::repeat_n(d, chunk.len()));
        }
        println!(
            "    groups of <= {:4} KiB, -3:            {:7.3} MB {:5.1}x  one lookup {:7.1} us",
            cap >> 10,
            mb(total as u64),
            raw as f64 / total as f64,
            us(median(times))
        );
    }
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

/// An archive of `count` permutations shaped like a generated engine set: 16 (shader, level)
/// pairs of 11 dimensions (ten bools and an enum), so names are as long as real ones, with a
/// WGSL and a SPIR-V artifact of a few hundred bytes each (pairs of permutations share the
/// SPIR-V one). What opening costs when the manifest, not the body, is large.
fn many_archive(path: &Path, count: usize) -> f64 {
    let mut w = ArchiveWriter::new();
    let modes = ["OPAQUE", "MASKED", "TRANSLUCENT", "ADDITIVE"];
    let mut shaders = Vec::new();
    for s in 0..8 {
        for level in ["sm5", "es3_1"] {
            let mut dimensions: Vec<DimensionRecord> =
                (0..10).map(|d| DimensionRecord { name: format!("USE_FEATURE_{d}"), labels: vec![] }).collect();
            dimensions.push(DimensionRecord { name: "BLEND_MODE".into(), labels: modes.map(String::from).to_vec() });
            dimensions.push(DimensionRecord { name: "LAYER".into(), labels: vec![] });
            let name = format!("GeneratedMaterial{s}PS");
            let handle = w.add_shader(ShaderRecord {
                name: name.clone(),
                level: level.into(),
                entry: "main_ps".into(),
                stage: Stage::Fragment,
                dimensions,
            });
            let reflection = w.add_reflection(&Reflection {
                entry: "main_ps".into(),
                stage: Stage::Fragment,
                bindings: vec![],
                vertex_inputs: vec![],
                color_outputs: vec![],
                workgroup_size: Some([s, 1, 1]),
            });
            shaders.push((name, level, handle, reflection));
        }
    }
    for i in 0..count {
        let (name, level, shader, reflection) = &shaders[i % shaders.len()];
        let k = i / shaders.len();
        let values: Vec<i64> =
            (0..10).map(|d| ((k >> d) & 1) as i64).chain([(k >> 10) as i64 % 4, (k >> 12) as i64]).collect();
        let dims: Vec<String> = (0..10).map(|d| format!("USE_FEATURE_{d}={}", values[d])).collect();
        let wgsl = format!("// {name} {level} {k}\n{}", "fn f() -> f32 { return 1.0; }\n".repeat(8 + k % 5));
        let spirv: Vec<u8> =
            (0..64u32).flat_map(|x| (x.wrapping_mul(2654435761) ^ (i as u32 / 2)).to_le_bytes()).collect();
        let artifacts = vec![(Target::Wgsl, w.add_blob(wgsl.as_bytes())), (Target::Spirv, w.add_blob(&spirv))];
        w.add_permutation(PermutationRecord {
            name: format!(
                "{name}@{level}{{{},BLEND_MODE={},LAYER={}}}",
                dims.join(","),
                modes[values[10] as usize],
                values[11]
            ),
            shader: *shader,
            values,
            reflection: *reflection,
            artifacts,
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

    // KILN_ARCHIVE_SETS=bundled,generated,big,many,files picks the parts to run (all by default).
    let sets = std::env::var("KILN_ARCHIVE_SETS").unwrap_or_default();
    let wanted = |set: &str| sets.is_empty() || sets.split(',').any(|s| s.trim() == set);

    if wanted("bundled") {
        let out = scratch.path().join("bundled.kpak");
        let secs = build_archive(&config, &out, &cache);
        println!("(build of {} with its cache: {secs:.2} s)", config.display());
        measure(&format!("set {}", config.display()), &out);
        compare_schemes(&out);
    }

    if wanted("generated") {
        let gen = generate_set(scratch.path());
        let out = scratch.path().join("generated.kpak");
        let secs = build_archive(&gen, &out, &cache);
        println!("(build of the generated set: {secs:.2} s)");
        measure("generated set", &out);
        compare_schemes(&out);
        // Writing alone (dictionary training and compression), from the cache.
        std::fs::remove_file(&out).unwrap();
        let secs = build_archive(&gen, &out, &cache);
        println!("  warm rebuild, archive rewritten: {secs:.2} s");
    }

    if wanted("big") {
        let out = scratch.path().join("big.kpak");
        let secs = big_archive(&out, 1024, 1 << 20);
        println!("(generated 1 GiB archive written in {secs:.2} s)");
        measure("1 GiB archive", &out);
        std::fs::remove_file(&out).unwrap();
    }

    // KILN_ARCHIVE_FILES=a.kpak,b.kpak: archives built elsewhere (a generated 100k set's, say),
    // measured the same way (`KILN_ARCHIVE_SETS=files` for those alone).
    if wanted("files") {
        for file in std::env::var("KILN_ARCHIVE_FILES").unwrap_or_default().split(',').filter(|f| !f.is_empty()) {
            measure(file, Path::new(file));
        }
    }

    for count in [10_000, 100_000].into_iter().filter(|_| wanted("many")) {
        let out = scratch.path().join(format!("many{count}.kpak"));
        let secs = many_archive(&out, count);
        println!("(generated archive of {count} permutations written in {secs:.2} s)");
        measure(&format!("generated archive, {count} permutations"), &out);
        // What opening checks: the chunk hashes (32 bytes per chunk of manifest and table).
        let bytes = std::fs::read(&out).unwrap();
        let manifest_len = u64::from_le_bytes(bytes[32..40].try_into().unwrap()) as usize;
        let blobs = u64::from_le_bytes(bytes[40..48].try_into().unwrap()) as usize;
        let chunk = u32::from_le_bytes(bytes[48..52].try_into().unwrap()) as usize;
        let hashes = (manifest_len.div_ceil(chunk) + (blobs * 64).div_ceil(chunk)) * 32;
        let manifest_start = bytes.len() - blobs * 64 - manifest_len.next_multiple_of(8);
        let checked = &bytes[manifest_start - hashes..manifest_start];
        let sums: Vec<Duration> = (0..21)
            .map(|_| {
                let t = Instant::now();
                std::hint::black_box(blake3::hash(checked));
                t.elapsed()
            })
            .collect();
        println!(
            "  of which blake3 of the chunk hashes: {:.1} us median ({:.1} KB; {:.2} MB of manifest and table, {} KiB chunks)",
            us(median(sums)),
            checked.len() as f64 / 1e3,
            mb((manifest_len + blobs * 64) as u64),
            chunk >> 10
        );
    }
}
