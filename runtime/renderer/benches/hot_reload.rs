//! Hot reload latency, printed in one run: edit-to-new-frame time of the mobile forward frame
//! (640x360) for a header edit that touches one permutation and for one that touches many.
//!
//! The bundled shaders are copied to a temporary folder, where the tonemapper's curve moves
//! into a header of its own (`MobileTonemapCommon.ush`, read by the one `MobileTonemapPS`
//! permutation) and `MobileLighting.ush` (read by every `MobileBasePassPS` permutation) is the
//! shared header. Each edit changes a constant to a value not seen before, so every rebuild
//! compiles; the time runs from the write of the file to the new frame read back, split into
//! Kiln's rebuild (including the watcher's settle time), the swap (`Renderer::reload`) and the
//! frame. This process's CPU time over the same span (user + system, every thread: Kiln's
//! workers and lavapipe's) is printed too: on a shared, loaded machine it says what the reload
//! costs better than the wall clock. `cargo bench -p kiln-renderer --features hot-reload --bench hot_reload` (lavapipe
//! suffices; `KILN_BENCH_BACKEND=gl` runs on llvmpipe's GL).

use std::path::Path;
use std::time::{Duration, Instant};

use kiln_renderer::scene::Scene;
use kiln_renderer::{FramePipeline, Renderer, RendererOptions};
use kiln_runtime::hot_reload::{Event, HotReload};
use kiln_runtime::{Backend, Gpu, GpuOptions};

const EDITS: usize = 5;

fn copy(from: &Path, to: &Path) {
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

fn save(path: &Path, text: &str) {
    let tmp = path.with_extension("tmp~");
    std::fs::write(&tmp, text).unwrap();
    std::fs::rename(&tmp, path).unwrap();
}

/// CPU time of this process so far (user + system, all threads).
fn cpu_time() -> Duration {
    // SAFETY: getrusage writes the struct it is given; a zeroed rusage is a valid value.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: `usage` is a valid, writable rusage for the call to fill.
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut usage) };
    let tv = |t: libc::timeval| Duration::from_secs(t.tv_sec as u64) + Duration::from_micros(t.tv_usec as u64);
    tv(usage.ru_utime) + tv(usage.ru_stime)
}

struct Timing {
    total: Duration,
    cpu: Duration,
    build: Duration,
    swap: Duration,
    frame: Duration,
    rebuilt: usize,
    compiled: usize,
}

/// Saves `text` to `path`, waits for the reload, swaps and renders.
fn edit(hot: &mut HotReload, renderer: &mut Renderer, gpu: &Gpu, scene: &Scene, path: &Path, text: &str) -> Timing {
    let (start, cpu) = (Instant::now(), cpu_time());
    save(path, text);
    let reload = match hot.poll(Duration::from_secs(60)).expect("watch") {
        Some(Event::Reloaded(r)) => r,
        Some(Event::Failed { diagnostics, .. }) => panic!("the edit does not build:\n{diagnostics}"),
        None => panic!("no reload within a minute"),
    };
    let built = Instant::now();
    *renderer = renderer.reload(gpu, reload.archive.clone(), scene, &reload.changed).expect("reload");
    hot.accept(reload.archive);
    let swapped = Instant::now();
    renderer.render(false).expect("frame");
    let end = Instant::now();
    Timing {
        total: end - start,
        cpu: cpu_time() - cpu,
        build: built - start,
        swap: swapped - built,
        frame: end - swapped,
        rebuilt: reload.changed.len(),
        compiled: reload.compiled,
    }
}

fn median(mut v: Vec<Duration>) -> f64 {
    v.sort();
    v[v.len() / 2].as_secs_f64() * 1000.0
}

fn report(what: &str, t: &[Timing]) -> f64 {
    let total = median(t.iter().map(|t| t.total).collect());
    println!(
        "  {what:<34} {:>4} permutations rebuilt ({} compiled): edit to frame {total:>7.1} ms (build {:.1}, swap {:.1}, frame {:.1}), CPU {:.1} ms; median of {}",
        t[0].rebuilt,
        t[0].compiled,
        median(t.iter().map(|t| t.build).collect()),
        median(t.iter().map(|t| t.swap).collect()),
        median(t.iter().map(|t| t.frame).collect()),
        median(t.iter().map(|t| t.cpu).collect()),
        t.len()
    );
    total
}

fn main() {
    let backend = match std::env::var("KILN_BENCH_BACKEND").as_deref() {
        Ok("gl") => Backend::Gl,
        _ => Backend::Vulkan,
    };
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    copy(&root.join("shader_src"), &d.join("shader_src"));
    std::fs::copy(root.join("permutations.toml"), d.join("permutations.toml")).unwrap();
    std::env::set_var("KILN_CACHE_DIR", d.join("cache"));

    // The tonemapper's curve in a header of its own: one permutation reads it.
    let mobile = d.join("shader_src/Private/Mobile");
    let tonemap = std::fs::read_to_string(mobile.join("MobileTonemap.usf")).unwrap();
    let (start, end) = (tonemap.find("fn aces_film").unwrap(), tonemap.find("fn linear_to_srgb").unwrap());
    let curve = |a: f64| tonemap[start..end].replace("let a = 2.51;", &format!("let a = {a:.6};"));
    std::fs::write(mobile.join("MobileTonemapCommon.ush"), curve(2.51)).unwrap();
    let usf = format!("{}#include \"MobileTonemapCommon.ush\"\n{}", &tonemap[..start], &tonemap[end..]);
    std::fs::write(mobile.join("MobileTonemap.usf"), usf).unwrap();
    let lighting = std::fs::read_to_string(mobile.join("MobileLighting.ush")).unwrap();
    const SKY: &str = "return max(irradiance, vec3<f32>(0.0));";
    assert!(lighting.contains(SKY));

    let gpu = Gpu::new(&GpuOptions { backend, ..GpuOptions::default() }).unwrap_or_else(|e| panic!("{e}"));
    let scene = Scene::bundled();
    let pipeline = FramePipeline::MobileForward;
    let cold = Instant::now();
    let mut hot = HotReload::start(&d.join("permutations.toml"), &[pipeline.level()]).unwrap_or_else(|e| panic!("{e}"));
    let cold = cold.elapsed();
    let options = RendererOptions { pipeline, width: 640, height: 360, comparison: false };
    let mut renderer = Renderer::new(&gpu, hot.archive(), &scene, options).expect("renderer");
    renderer.render(false).expect("frame");
    let (steady, steady_cpu) = (Instant::now(), cpu_time());
    for _ in 0..3 {
        renderer.render(false).expect("frame");
    }
    let (steady, steady_cpu) = (steady.elapsed() / 3, (cpu_time() - steady_cpu) / 3);
    println!(
        "hot reload of the mobile forward frame at 640x360 on {} ({backend}); first build of es3_1 {:.1} s, a frame {:.1} ms (CPU {:.1} ms)",
        gpu.info.name,
        cold.as_secs_f64(),
        steady.as_secs_f64() * 1000.0,
        steady_cpu.as_secs_f64() * 1000.0
    );

    let mut one = Vec::new();
    let mut many = Vec::new();
    for i in 0..EDITS {
        let a = 2.51 + 0.01 * (i + 1) as f64;
        one.push(edit(&mut hot, &mut renderer, &gpu, &scene, &mobile.join("MobileTonemapCommon.ush"), &curve(a)));
        let sky = SKY.replace("(0.0));", &format!("(0.0)) * {:.2};", 1.0 + 0.05 * (i + 1) as f64));
        many.push(edit(
            &mut hot,
            &mut renderer,
            &gpu,
            &scene,
            &mobile.join("MobileLighting.ush"),
            &lighting.replace(SKY, &sky),
        ));
    }
    let a = report("MobileTonemapCommon.ush (one)", &one);
    let b = report("MobileLighting.ush (many)", &many);
    println!("  many / one: {:.1}x", b / a);
}
