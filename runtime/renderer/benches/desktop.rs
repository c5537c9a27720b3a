//! Desktop frame benchmark: each pass's GPU time at 640x360 on the bundled scene, and how
//! the frame time grows from 8 to 512 local lights, per-light volumes against the tiled
//! path (which `Auto` picks above 80 unshadowed lights). Prints ratios measured in one run.
//!
//! `cargo bench -p kiln-renderer --bench desktop` (env `KILN_BENCH_FRAMES`, default 5).

use std::sync::Arc;
use std::time::Instant;

use glam::Vec3;
use kiln_renderer::desktop::{DesktopFrame, DesktopOptions, LightingPath};
use kiln_renderer::frame::PassResult;
use kiln_renderer::scene::{Mobility, PointLight, Scene};
use kiln_runtime::pipelines::PipelineCache;
use kiln_runtime::{Gpu, GpuOptions};

const W: u32 = 640;
const H: u32 = 360;

/// The bundled scene with local lights added until it has `total` of them.
fn scene_with_lights(total: usize) -> Scene {
    let mut scene = Scene::bundled();
    let mut seed = 7u32;
    let mut rand = || {
        seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
        (seed >> 8) as f32 / (1u32 << 24) as f32
    };
    let existing = scene.point_lights.len() + scene.spot_lights.len();
    for i in existing..total {
        scene.point_lights.push(PointLight {
            name: format!("Extra{i}"),
            position: Vec3::new(-7.5 + 15.0 * rand(), 0.2 + 2.5 * rand(), -5.5 + 11.0 * rand()),
            color: Vec3::new(0.3 + rand(), 0.3 + rand(), 0.3 + rand()),
            intensity: 1.0,
            radius: 1.0 + 1.5 * rand(),
            mobility: Mobility::Movable,
            casts_shadows: false,
        });
    }
    scene
}

struct Timing {
    wall_ms: f64,
    passes: Vec<(String, Option<f64>)>,
}

fn measure(gpu: &Gpu, cache: &PipelineCache, scene: &Scene, path: LightingPath, frames: usize) -> Timing {
    let options = DesktopOptions { width: W, height: H, lighting_path: path, ..Default::default() };
    let frame = DesktopFrame::new(&gpu.device, &gpu.queue, gpu.timestamps, cache, scene, options)
        .unwrap_or_else(|e| panic!("{e}"));
    let _ = frame.render(cache, false); // warm-up: first use of every pipeline
    let mut sums: Vec<(String, Option<f64>)> = Vec::new();
    let start = Instant::now();
    for _ in 0..frames {
        let (_, passes) = frame.render(cache, false).unwrap_or_else(|e| panic!("{e}"));
        accumulate(&mut sums, &passes);
    }
    let wall_ms = start.elapsed().as_secs_f64() * 1000.0 / frames as f64;
    Timing { wall_ms, passes: sums.into_iter().map(|(n, t)| (n, t.map(|t| t / frames as f64))).collect() }
}

fn accumulate(sums: &mut Vec<(String, Option<f64>)>, passes: &[PassResult]) {
    for p in passes {
        match sums.iter_mut().find(|(n, _)| *n == p.name) {
            Some((_, t)) => *t = t.zip(p.gpu_ms).map(|(a, b)| a + b),
            None => sums.push((p.name.clone(), p.gpu_ms)),
        }
    }
}

fn main() {
    let frames: usize = std::env::var("KILN_BENCH_FRAMES").ok().and_then(|v| v.parse().ok()).unwrap_or(5);
    let gpu = Gpu::new(&GpuOptions::default()).unwrap_or_else(|e| panic!("{e}"));
    let archive = Arc::new(kiln_renderer::embedded_archive().unwrap_or_else(|e| panic!("{e}")));
    let cache = PipelineCache::new(&gpu, archive);
    println!("desktop frame, {W}x{H}, {} ({}), {frames} frames each", gpu.info.name, gpu.backend);

    let base = measure(&gpu, &cache, &Scene::bundled(), LightingPath::Auto, frames);
    println!("\npass times, bundled scene:");
    let gpu_total: f64 = base.passes.iter().filter_map(|(_, t)| *t).sum();
    for (name, t) in &base.passes {
        match t {
            Some(t) => println!("  {name:<22} {t:>9.3} ms  {:>5.1}%", 100.0 * t / gpu_total.max(1e-9)),
            None => println!("  {name:<22}       n/a (no timestamp queries)"),
        }
    }
    println!("  {:<22} {:>9.3} ms (wall, submit to readback)", "frame", base.wall_ms);

    println!("\nframe time against local lights (ratio to 8 lights):");
    println!("  {:>6}  {:>22}  {:>22}  {:>12}", "lights", "per-light volumes", "auto (tiled above 80)", "Lighting GPU");
    let mut first: Option<(f64, f64)> = None;
    for n in [8usize, 32, 128, 512] {
        let scene = scene_with_lights(n);
        let per_light = measure(&gpu, &cache, &scene, LightingPath::PerLight, frames);
        let auto = measure(&gpu, &cache, &scene, LightingPath::Auto, frames);
        let (p0, a0) = *first.get_or_insert((per_light.wall_ms, auto.wall_ms));
        let lighting = auto.passes.iter().find(|(n, _)| n == "Lighting").and_then(|(_, t)| *t);
        println!(
            "  {n:>6}  {:>10.2} ms ({:>5.2}x)  {:>10.2} ms ({:>5.2}x)  {:>12}",
            per_light.wall_ms,
            per_light.wall_ms / p0,
            auto.wall_ms,
            auto.wall_ms / a0,
            lighting.map_or("n/a".to_string(), |t| format!("{t:.2} ms")),
        );
    }
}
