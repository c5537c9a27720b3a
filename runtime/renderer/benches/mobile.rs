//! Mobile frame benchmark, printed in one run: frame time of mobile forward, mobile deferred
//! and desktop on the same scene at 640x360, and how each grows with the number of local
//! lights (0 to 16 point lights spread over the room; the forward base pass shades at most
//! `MAX_DYNAMIC_POINT_LIGHTS` = 4 of them, deferred draws one light volume each).
//!
//! Each frame time is the mean over several frames after a warm-up frame: wall time of
//! record + submit + wait, and GPU time summed from the passes' timestamp queries where the
//! device has them. `cargo bench -p kiln-renderer --bench mobile` (lavapipe suffices;
//! `KILN_BENCH_BACKEND=gl` runs on llvmpipe's GL).

use std::sync::Arc;
use std::time::Instant;

use glam::Vec3;
use kiln_renderer::frame::FrameRecorder;
use kiln_renderer::mobile::{MobileContext, MobileFrame, MobileOptions};
use kiln_renderer::scene::gpu::{GpuScene, SceneLayout};
use kiln_renderer::scene::{Mobility, PointLight, Scene};
use kiln_renderer::{FramePipeline, Renderer, RendererOptions};
use kiln_runtime::pipelines::PipelineCache;
use kiln_runtime::{Backend, Gpu, GpuOptions, ShaderArchive};

const WIDTH: u32 = 640;
const HEIGHT: u32 = 360;
const FRAMES: u32 = 5;
const LIGHT_COUNTS: [usize; 6] = [0, 1, 2, 4, 8, 16];

/// The bundled scene with `n` point lights on a ring over the floor instead of its own.
fn scene_with_lights(n: usize) -> Scene {
    let mut scene = Scene::bundled();
    scene.spot_lights.clear();
    scene.point_lights = (0..n)
        .map(|i| {
            let a = i as f32 / n.max(1) as f32 * std::f32::consts::TAU;
            PointLight {
                name: format!("Bench{i}"),
                position: Vec3::new(5.0 * a.cos(), 1.5, 3.5 * a.sin()),
                color: Vec3::new(1.0, 0.8, 0.6),
                intensity: 4.0,
                radius: 5.0,
                mobility: Mobility::Movable,
                casts_shadows: false,
            }
        })
        .collect();
    scene
}

/// Mean wall and GPU milliseconds per frame.
struct Timing {
    wall_ms: f64,
    gpu_ms: Option<f64>,
}

fn mean(frames: &[(f64, Option<f64>)]) -> Timing {
    let n = frames.len() as f64;
    let wall_ms = frames.iter().map(|f| f.0).sum::<f64>() / n;
    let gpu: Option<Vec<f64>> = frames.iter().map(|f| f.1).collect();
    Timing { wall_ms, gpu_ms: gpu.map(|g| g.iter().sum::<f64>() / n) }
}

fn mobile_frame(gpu: &Gpu, archive: &Arc<ShaderArchive>, scene: &Scene, options: MobileOptions) -> Timing {
    let cache = PipelineCache::new(gpu, archive.clone());
    let gpu_scene = GpuScene::upload(&gpu.device, scene, SceneLayout::PerObject);
    let context = MobileContext { gpu, cache: &cache, scene, gpu_scene: &gpu_scene };
    let frame = MobileFrame::new(&context, options, (WIDTH, HEIGHT)).expect("mobile frame");
    let mut frames = Vec::new();
    for i in 0..=FRAMES {
        let start = Instant::now();
        let mut recorder = FrameRecorder::new(&gpu.device, &gpu.queue, &cache, gpu.timestamps, false, None);
        frame.record(&mut recorder, &gpu_scene);
        let passes = recorder.finish().expect("mobile frame pipelines");
        let wall = start.elapsed().as_secs_f64() * 1e3;
        let gpu_ms: Option<f64> = passes.iter().map(|p| p.gpu_ms).sum();
        if i > 0 {
            frames.push((wall, gpu_ms));
        }
    }
    mean(&frames)
}

fn desktop_frame(gpu: &Gpu, archive: &Arc<ShaderArchive>, scene: &Scene) -> Timing {
    let renderer = Renderer::new(
        gpu,
        archive.clone(),
        scene,
        RendererOptions { pipeline: FramePipeline::Desktop, width: WIDTH, height: HEIGHT, comparison: false },
    )
    .expect("desktop frame");
    let mut frames = Vec::new();
    for i in 0..=FRAMES {
        let start = Instant::now();
        let out = renderer.render(false).expect("desktop frame");
        let wall = start.elapsed().as_secs_f64() * 1e3;
        let gpu_ms: Option<f64> = out.passes.iter().map(|p| p.gpu_ms).sum();
        if i > 0 {
            frames.push((wall, gpu_ms));
        }
    }
    mean(&frames)
}

fn fmt(t: &Timing) -> String {
    match t.gpu_ms {
        Some(g) => format!("{:8.2} ms ({:7.2} gpu)", t.wall_ms, g),
        None => format!("{:8.2} ms", t.wall_ms),
    }
}

fn main() {
    let backend = match std::env::var("KILN_BENCH_BACKEND").as_deref() {
        Ok("gl") => Backend::Gl,
        _ => Backend::Vulkan,
    };
    let gpu = Gpu::new(&GpuOptions { backend, ..GpuOptions::default() }).unwrap_or_else(|e| panic!("{e}"));
    let archive = Arc::new(kiln_renderer::embedded_archive().expect("embedded archive"));
    println!(
        "mobile frames at {WIDTH}x{HEIGHT} on {} ({backend}), mean of {FRAMES} frames after one warm-up",
        gpu.info.name
    );
    println!(
        "{:>6} | {:>27} | {:>27} | {:>27} | deferred/forward",
        "lights", "mobile forward", "mobile deferred", "desktop"
    );
    let mut rows = Vec::new();
    for n in LIGHT_COUNTS {
        let scene = scene_with_lights(n);
        let forward = mobile_frame(&gpu, &archive, &scene, MobileOptions::forward());
        let deferred = mobile_frame(&gpu, &archive, &scene, MobileOptions::deferred());
        let desktop = desktop_frame(&gpu, &archive, &scene);
        println!(
            "{n:>6} | {} | {} | {} | {:.2}",
            fmt(&forward),
            fmt(&deferred),
            fmt(&desktop),
            deferred.wall_ms / forward.wall_ms
        );
        rows.push((n, forward, deferred, desktop));
    }
    let base = &rows[0];
    println!("growth of the wall time against 0 local lights (forward shades at most 4):");
    for (n, f, d, k) in &rows[1..] {
        println!(
            "{n:>6} | forward x{:.2} | deferred x{:.2} | desktop x{:.2}",
            f.wall_ms / base.1.wall_ms,
            d.wall_ms / base.2.wall_ms,
            k.wall_ms / base.3.wall_ms
        );
    }
}
