//! Runtime benchmarks, printed as ratios measured in one run:
//! - archive open (embedded bytes and memory-mapped file) plus 1,000 lookups, against a
//!   linear scan of the manifest for the same names;
//! - shader module creation from SPIR-V passthrough against WGSL on the same permutations,
//!   and the warm-up (every module and pipeline of a frame) both ways;
//! - frame time of each pipeline at 640x360.
//!
//! `cargo bench -p kiln-runtime --bench runtime` (lavapipe suffices).

use std::hint::black_box;
use std::sync::Arc;
use std::time::{Duration, Instant};

use kiln::archive::Target;
use kiln_runtime::pipelines::create_module;
use kiln_runtime::scene::Scene;
use kiln_runtime::{Backend, FramePipeline, Gpu, GpuOptions, ModuleSource, Renderer, RendererOptions, ShaderArchive};

/// Runs `f` `n` times and returns the mean duration.
fn time(n: u32, mut f: impl FnMut()) -> Duration {
    let start = Instant::now();
    for _ in 0..n {
        f();
    }
    start.elapsed() / n
}

fn us(d: Duration) -> f64 {
    d.as_secs_f64() * 1e6
}

fn archive_bench() {
    let bytes = kiln_runtime::EMBEDDED_ARCHIVE;
    let dir = std::env::temp_dir().join(format!("kiln-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("shaders.kpak");
    std::fs::write(&path, bytes).unwrap();
    let archive = ShaderArchive::embedded().unwrap();
    let names: Vec<String> = archive.permutations().map(|p| p.name().to_string()).collect();
    let wanted: Vec<&str> = (0..1000).map(|i| names[(i * 7919) % names.len()].as_str()).collect();

    let open_static = time(200, || {
        black_box(ShaderArchive::from_static(bytes).unwrap());
    });
    let open_mmap = time(200, || {
        black_box(ShaderArchive::open(&path).unwrap());
    });
    let lookups = time(200, || {
        for n in &wanted {
            black_box(archive.get(n).unwrap());
        }
    });
    let scans = time(20, || {
        for n in &wanted {
            black_box(archive.permutations().find(|p| p.name() == *n).unwrap());
        }
    });
    let builder = time(200, || {
        for i in 0..1000 {
            let p = archive
                .shader("MobileBasePassPS")
                .level("es3_1")
                .with("FULLY_ROUGH", i % 2)
                .with("MAX_DYNAMIC_POINT_LIGHTS", [0, 1, 2, 4][i % 4])
                .with("USE_VERTEX_FOG", (i / 2) % 2)
                .with("DEFERRED_SHADING_PATH", 0)
                .with("MATERIAL_BLEND_MODE", "OPAQUE")
                .find()
                .unwrap();
            black_box(p);
        }
    });
    println!("archive: {} bytes, {} permutations, {} blobs", bytes.len(), names.len(), archive.archive().blob_count());
    println!("  open (embedded, verify checksum + parse manifest): {:8.1} us", us(open_static));
    println!("  open (mmap file):                                  {:8.1} us", us(open_mmap));
    println!(
        "  1,000 lookups by name (hash map):                  {:8.1} us  ({:.0} ns each)",
        us(lookups),
        us(lookups)
    );
    println!("  1,000 lookups by builder (canonical name + hash):  {:8.1} us", us(builder));
    println!("  1,000 lookups by linear scan (baseline):           {:8.1} us", us(scans));
    println!("  open + 1,000 lookups:                              {:8.1} us", us(open_static + lookups));
    println!(
        "  ratio linear scan / hash lookup:                   {:8.1}x",
        scans.as_secs_f64() / lookups.as_secs_f64()
    );
    let _ = std::fs::remove_dir_all(&dir);

    // Lookups stay flat as archives grow: a synthetic archive of 16,384 permutations
    // (one 4-dimension shader, every permutation its own small blob).
    let mut w = kiln::archive::ArchiveWriter::new();
    let dims = ["QUALITY", "LIGHT_COUNT", "USE_FOG", "VARIANT"];
    let shader = w.add_shader(kiln::archive::ShaderRecord {
        name: "SyntheticPS".into(),
        level: "sm5".into(),
        entry: "main_ps".into(),
        stage: kiln::Stage::Fragment,
        dimensions: dims
            .iter()
            .map(|d| kiln::archive::DimensionRecord { name: d.to_string(), labels: vec![] })
            .collect(),
    });
    let reflection = w.add_reflection(&kiln::archive::Reflection {
        entry: "main_ps".into(),
        stage: kiln::Stage::Fragment,
        bindings: vec![],
        vertex_inputs: vec![],
        color_outputs: vec![],
        workgroup_size: None,
    });
    let mut big_names = Vec::new();
    for i in 0..16384i64 {
        let values = [i / 2048, (i / 256) % 8, (i / 128) % 2, i % 128];
        let name = format!(
            "SyntheticPS@sm5{{{}}}",
            dims.iter().zip(values).map(|(d, v)| format!("{d}={v}")).collect::<Vec<_>>().join(",")
        );
        let blob = w.add_blob(name.as_bytes());
        w.add_permutation(kiln::archive::PermutationRecord {
            name: name.clone(),
            shader,
            values: values.to_vec(),
            reflection,
            artifacts: vec![(Target::Wgsl, blob)],
        });
        big_names.push(name);
    }
    let big_bytes = w.to_bytes().unwrap();
    let big_open = time(5, || {
        black_box(ShaderArchive::from_vec(big_bytes.clone()).unwrap());
    });
    let big = ShaderArchive::from_vec(big_bytes.clone()).unwrap();
    let big_wanted: Vec<&str> = (0..1000).map(|i| big_names[(i * 7919) % big_names.len()].as_str()).collect();
    let big_lookups = time(200, || {
        for n in &big_wanted {
            black_box(big.get(n).unwrap());
        }
    });
    let big_scans = time(2, || {
        for n in &big_wanted {
            black_box(big.permutations().find(|p| p.name() == *n).unwrap());
        }
    });
    println!("synthetic archive: {} bytes, {} permutations", big_bytes.len(), big_names.len());
    println!("  open:                                              {:8.1} us", us(big_open));
    println!(
        "  1,000 lookups by name (hash map):                  {:8.1} us  ({:.0} ns each)",
        us(big_lookups),
        us(big_lookups)
    );
    println!("  1,000 lookups by linear scan (baseline):           {:8.1} us", us(big_scans));
    println!(
        "  ratio linear scan / hash lookup:                   {:8.1}x",
        big_scans.as_secs_f64() / big_lookups.as_secs_f64()
    );
    println!(
        "  hash lookup, 16,384 vs {} permutations:            {:8.2}x",
        names.len(),
        big_lookups.as_secs_f64() / lookups.as_secs_f64()
    );
}

fn module_bench() {
    let gpu = match Gpu::new(&GpuOptions {
        backend: Backend::Vulkan,
        module_source: ModuleSource::Auto,
        timestamps: false,
    }) {
        Ok(g) => g,
        Err(e) => panic!("the module benchmark needs a Vulkan adapter: {e}"),
    };
    assert!(gpu.spirv_passthrough, "{} does not offer PASSTHROUGH_SHADERS", gpu.info.name);
    let archive = ShaderArchive::embedded().unwrap();
    let perms: Vec<_> = archive
        .permutations()
        .filter(|p| p.blob_id(Target::Spirv).is_some() && p.blob_id(Target::Wgsl).is_some())
        .collect();
    let create_all = |passthrough: bool| {
        for p in &perms {
            let (spirv, wgsl) = (p.artifact(Target::Spirv).unwrap(), p.artifact(Target::Wgsl).unwrap());
            let m = create_module(
                &gpu.device,
                passthrough,
                p.name(),
                spirv.as_deref(),
                wgsl.as_deref(),
                p.reflection(),
                "",
            )
            .unwrap();
            black_box(m);
        }
    };
    create_all(true);
    create_all(false);
    let rounds = 5;
    let spirv = time(rounds, || create_all(true));
    let wgsl = time(rounds, || create_all(false));
    println!("shader modules on {} ({} permutations, mean of {rounds} rounds):", gpu.info.name, perms.len());
    println!("  SPIR-V passthrough: {:8.2} ms  ({:.1} us per module)", us(spirv) / 1e3, us(spirv) / perms.len() as f64);
    println!("  WGSL:               {:8.2} ms  ({:.1} us per module)", us(wgsl) / 1e3, us(wgsl) / perms.len() as f64);
    println!("  ratio WGSL / SPIR-V passthrough: {:.1}x", wgsl.as_secs_f64() / spirv.as_secs_f64());
    drop(gpu);

    // Warm-up of whole frames: every module and pipeline a frame uses, both ways.
    let archive = Arc::new(archive);
    let scene = Scene::bundled();
    println!("warm-up (Renderer::new: scene upload, every module and pipeline of the frame):");
    for pipeline in FramePipeline::ALL {
        let mut ms = [0.0; 2];
        for (i, source) in [ModuleSource::Auto, ModuleSource::Wgsl].into_iter().enumerate() {
            let gpu =
                Gpu::new(&GpuOptions { backend: Backend::Vulkan, module_source: source, timestamps: false }).unwrap();
            // One unmeasured round: the driver's first-use costs are not the warm-up's.
            black_box(
                Renderer::new(
                    &gpu,
                    archive.clone(),
                    &scene,
                    RendererOptions { pipeline, width: 640, height: 360, comparison: false },
                )
                .unwrap(),
            );
            let t = time(3, || {
                black_box(
                    Renderer::new(
                        &gpu,
                        archive.clone(),
                        &scene,
                        RendererOptions { pipeline, width: 640, height: 360, comparison: false },
                    )
                    .unwrap(),
                );
            });
            ms[i] = us(t) / 1e3;
        }
        println!(
            "  {:16} SPIR-V {:8.1} ms, WGSL {:8.1} ms, ratio {:.2}x",
            pipeline.name(),
            ms[0],
            ms[1],
            ms[1] / ms[0]
        );
    }
}

fn frame_bench() {
    let gpu = Gpu::new(&GpuOptions::default()).unwrap();
    let archive = Arc::new(ShaderArchive::embedded().unwrap());
    let scene = Scene::bundled();
    println!(
        "frame time at 640x360 on {} (mean of 5 frames, CPU wall clock incl. readback; GPU sum of passes):",
        gpu.info.name
    );
    let mut base = None;
    for pipeline in FramePipeline::ALL {
        let r = Renderer::new(
            &gpu,
            archive.clone(),
            &scene,
            RendererOptions { pipeline, width: 640, height: 360, comparison: false },
        )
        .unwrap();
        r.render(false).unwrap();
        let mut gpu_ms = 0.0;
        let wall = time(5, || {
            let f = r.render(false).unwrap();
            gpu_ms += f.passes.iter().filter_map(|p| p.gpu_ms).sum::<f64>();
        });
        let wall_ms = us(wall) / 1e3;
        let base_ms = *base.get_or_insert(wall_ms);
        println!(
            "  {:16} {:8.1} ms wall, {:8.1} ms GPU, {:.2}x desktop",
            pipeline.name(),
            wall_ms,
            gpu_ms / 5.0,
            wall_ms / base_ms
        );
    }
}

fn main() {
    archive_bench();
    module_bench();
    frame_bench();
}
