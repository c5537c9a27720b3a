//! Runtime benchmarks, printed as figures and ratios measured in one run. Every name comes
//! from the archive itself (none is spelled here), so the bench follows the permutation set:
//! - archive open (embedded bytes and memory-mapped file) plus 1,000 lookups, by name and by
//!   dimension values, against a linear scan of the manifest for the same names;
//! - shader module creation, SPIR-V passthrough against WGSL, per module (grouped by shader);
//! - pipeline creation for a whole frame (every render and compute pipeline it uses, from
//!   its keys) with a cold and a warm on-disk driver pipeline cache;
//! - first-frame time of each pipeline (renderer creation and the first frame) against a
//!   later frame.
//!
//! `cargo bench -p kiln-renderer --bench runtime` (lavapipe suffices).

use std::hint::black_box;
use std::sync::Arc;
use std::time::{Duration, Instant};

use kiln_archive::Target;
use kiln_renderer::scene::Scene;
use kiln_renderer::{FramePipeline, Renderer, RendererOptions};
use kiln_runtime::pipelines::{create_spirv_module, create_wgsl_module, merge_bindings, PipelineCache};
use kiln_runtime::spirv::{SpirvModule, VulkanBindings};
use kiln_runtime::{Backend, Gpu, GpuOptions, ModuleSource, ShaderArchive};

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
    let bytes = kiln_renderer::EMBEDDED_ARCHIVE;
    let dir = std::env::temp_dir().join(format!("kiln-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("shaders.kpak");
    std::fs::write(&path, bytes).unwrap();
    let archive = kiln_renderer::embedded_archive().unwrap();
    let names: Vec<String> = archive.permutations().unwrap().map(|p| p.name().to_string()).collect();
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
            black_box(archive.permutations().unwrap().find(|p| p.name() == *n).unwrap());
        }
    });
    // The same permutations named by shader, level and dimension values (enum values by
    // their index, which the builder accepts like the label).
    let picked: Vec<_> = wanted.iter().map(|n| archive.get(n).unwrap()).collect();
    let builder = time(200, || {
        for p in &picked {
            let shader = p.shader();
            let mut q = archive.shader(&shader.name).level(&shader.level);
            for (d, v) in shader.dimensions.iter().zip(p.values()) {
                q = q.with(&d.name, v);
            }
            black_box(q.find().unwrap());
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
    let mut w = kiln_archive::ArchiveWriter::new();
    let dims = ["QUALITY", "LIGHT_COUNT", "USE_FOG", "VARIANT"];
    let shader = w.add_shader(kiln_archive::ShaderRecord {
        name: "SyntheticPS".into(),
        level: "sm5".into(),
        entry: "main_ps".into(),
        stage: kiln_archive::Stage::Fragment,
        dimensions: dims
            .iter()
            .map(|d| kiln_archive::DimensionRecord { name: d.to_string(), labels: vec![] })
            .collect(),
    });
    let reflection = w.add_reflection(&kiln_archive::Reflection {
        entry: "main_ps".into(),
        stage: kiln_archive::Stage::Fragment,
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
        w.add_permutation(kiln_archive::PermutationRecord {
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
            black_box(big.permutations().unwrap().find(|p| p.name() == *n).unwrap());
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

fn vulkan(source: ModuleSource) -> Gpu {
    Gpu::new(&GpuOptions { backend: Backend::Vulkan, module_source: source, timestamps: true, validation: false })
        .unwrap_or_else(|e| panic!("the runtime benchmark needs a Vulkan adapter: {e}"))
}

fn module_bench() {
    let gpu = vulkan(ModuleSource::Auto);
    assert!(gpu.spirv_passthrough, "{} does not offer PASSTHROUGH_SHADERS", gpu.info.name);
    let archive = kiln_renderer::embedded_archive().unwrap();
    // Each permutation's module as a pipeline of that one stage makes it: SPIR-V walked,
    // checked and renumbered for its layout, or WGSL parsed and validated by wgpu's naga.
    struct Module {
        shader: String,
        name: String,
        words: Vec<u32>,
        wgsl: Vec<u8>,
        reflection: kiln_archive::Reflection,
    }
    let modules: Vec<Module> = archive
        .permutations()
        .unwrap()
        .filter_map(|p| {
            let (spirv, wgsl) = (p.artifact(Target::Spirv).unwrap()?, p.artifact(Target::Wgsl).unwrap()?);
            let parsed = SpirvModule::parse(&spirv).unwrap();
            let groups = merge_bindings(p.name(), &[p.reflection()]).unwrap();
            let numbering = VulkanBindings::new(groups.iter().map(|g| g.iter().map(|b| b.binding).collect()).collect());
            let words = parsed.remap_bindings(|g, b| numbering.get(g, b)).unwrap_or(parsed.words);
            Some(Module {
                shader: p.shader().name.clone(),
                name: p.name().to_string(),
                words,
                wgsl: wgsl.to_vec(),
                reflection: p.reflection().clone(),
            })
        })
        .collect();
    let rounds = 3;
    let mut per_shader: std::collections::BTreeMap<&str, (usize, Duration, Duration)> = Default::default();
    for m in &modules {
        // One unmeasured creation each: the first use of a code path is not the cost per module.
        black_box(create_spirv_module(&gpu.device, &m.name, m.words.clone(), &m.reflection).unwrap());
        black_box(create_wgsl_module(&gpu.device, &m.name, &m.wgsl).unwrap());
        let spirv = time(rounds, || {
            black_box(create_spirv_module(&gpu.device, &m.name, m.words.clone(), &m.reflection).unwrap());
        });
        let wgsl = time(rounds, || {
            black_box(create_wgsl_module(&gpu.device, &m.name, &m.wgsl).unwrap());
        });
        let e = per_shader.entry(&m.shader).or_default();
        e.0 += 1;
        e.1 += spirv;
        e.2 += wgsl;
    }
    let (total_spirv, total_wgsl) =
        per_shader.values().fold((Duration::ZERO, Duration::ZERO), |(a, b), (_, s, w)| (a + *s, b + *w));
    println!(
        "shader modules on {} ({} permutations, mean of {rounds} creations each), per module:",
        gpu.info.name,
        modules.len()
    );
    println!("  {:36} {:>5} {:>12} {:>12} {:>8}", "shader", "perms", "SPIR-V us", "WGSL us", "ratio");
    for (shader, (n, spirv, wgsl)) in &per_shader {
        let (s, w) = (us(*spirv) / *n as f64, us(*wgsl) / *n as f64);
        println!("  {shader:36} {n:>5} {s:>12.1} {w:>12.1} {:>7.1}x", w / s);
    }
    let n = modules.len() as f64;
    println!(
        "  all modules: SPIR-V passthrough {:.1} us, WGSL {:.1} us per module, ratio WGSL / SPIR-V {:.1}x",
        us(total_spirv) / n,
        us(total_wgsl) / n,
        total_wgsl.as_secs_f64() / total_spirv.as_secs_f64()
    );
}

/// Pipeline creation for a whole frame, from the keys the frame uses, with the driver's
/// pipeline cache on disk cold (no file) and warm (the file the cold run saved).
fn pipeline_cache_bench() {
    let gpu = vulkan(ModuleSource::Auto);
    let archive = Arc::new(kiln_renderer::embedded_archive().unwrap());
    let scene = Scene::bundled();
    let dir = std::env::temp_dir().join(format!("kiln-bench-pc-{}", std::process::id()));
    let options = |pipeline| RendererOptions { pipeline, width: 640, height: 360, comparison: false };
    println!(
        "pipeline creation for a whole frame on {} (every module and pipeline, from the frame's keys):",
        gpu.info.name
    );
    for pipeline in FramePipeline::ALL {
        let keys = Renderer::new(&gpu, archive.clone(), &scene, options(pipeline)).unwrap().pipeline_cache().keys();
        let rounds = 3;
        let mut cold = Duration::ZERO;
        let mut warm = Duration::ZERO;
        let mut size = 0;
        // A cold run fills the file first; then each round measures warm (the file there) and
        // cold (no file) in turn, so neither always runs on a device the other warmed.
        let _ = std::fs::remove_dir_all(&dir);
        let (cache, _) = PipelineCache::with_disk_cache(&gpu, archive.clone(), &dir);
        cache.warm_up(&keys).unwrap();
        cache.save().unwrap();
        for _ in 0..rounds {
            let (cache, warning) = PipelineCache::with_disk_cache(&gpu, archive.clone(), &dir);
            assert_eq!(warning, None);
            let start = Instant::now();
            cache.warm_up(&keys).unwrap();
            warm += start.elapsed();
            let _ = std::fs::remove_dir_all(&dir);
            let (cache, _) = PipelineCache::with_disk_cache(&gpu, archive.clone(), &dir);
            let start = Instant::now();
            cache.warm_up(&keys).unwrap();
            cold += start.elapsed();
            let path = cache.save().unwrap();
            size = path.map(|p| std::fs::metadata(p).unwrap().len()).unwrap_or(0);
        }
        let (cold, warm) = (us(cold / rounds) / 1e3, us(warm / rounds) / 1e3);
        println!(
            "  {:16} {:3} pipelines: cold cache {cold:8.1} ms, warm cache {warm:8.1} ms, ratio cold / warm {:.2}x (cache file {size} bytes)",
            pipeline.name(),
            keys.len(),
            cold / warm
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// First-frame time (creating the renderer: scene upload, every pipeline; then one frame)
/// against a later frame, for each pipeline.
fn first_frame_bench() {
    let archive = Arc::new(kiln_renderer::embedded_archive().unwrap());
    let scene = Scene::bundled();
    println!("first frame at 640x360 (renderer creation + frame 1, a fresh device each) against frame 6:");
    for pipeline in FramePipeline::ALL {
        let gpu = vulkan(ModuleSource::Auto);
        let start = Instant::now();
        let r = Renderer::new(
            &gpu,
            archive.clone(),
            &scene,
            RendererOptions { pipeline, width: 640, height: 360, comparison: false },
        )
        .unwrap();
        let created = start.elapsed();
        r.render(false).unwrap();
        let first = start.elapsed();
        for _ in 0..4 {
            r.render(false).unwrap();
        }
        let later = time(1, || {
            r.render(false).unwrap();
        });
        println!(
            "  {:16} creation {:8.1} ms, first frame {:8.1} ms (total), frame 6 {:8.1} ms, ratio first / later {:.1}x",
            pipeline.name(),
            us(created) / 1e3,
            us(first) / 1e3,
            us(later) / 1e3,
            first.as_secs_f64() / later.as_secs_f64()
        );
    }
}

fn frame_bench() {
    let gpu = vulkan(ModuleSource::Auto);
    let archive = Arc::new(kiln_renderer::embedded_archive().unwrap());
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
    pipeline_cache_bench();
    first_frame_bench();
    frame_bench();
}
