//! `kiln-view`: renders the bundled scene headless to PNG with the shaders of a Kiln archive.
//!
//! Exit codes: 0 success, 1 render failure (no adapter, pipeline or device error), 2 bad
//! usage or a bad archive.

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;

use clap::{Parser, ValueEnum};
use kiln_renderer::frame::{write_dump, Creation, DumpInfo};
use kiln_renderer::renderer::FrameOutput;
use kiln_renderer::scene::Scene;
use kiln_renderer::{FramePipeline, Renderer, RendererOptions};
use kiln_runtime::pipelines::{manifest_keys, Fallback, Missing, PipelineCache, Precache};
use kiln_runtime::{Backend, Gpu, GpuOptions, ShaderArchive};

#[derive(Clone, Copy, Debug, ValueEnum)]
enum PipelineArg {
    Desktop,
    MobileForward,
    MobileDeferred,
}

/// What `--no-stall` draws while a pipeline is created.
#[derive(Clone, Copy, Debug, ValueEnum)]
enum StallArg {
    /// Skip the draw.
    Skip,
    /// Draw with the nearest ready permutation of the same shader (same bindings).
    Nearest,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum BackendArg {
    Vulkan,
    Gl,
}

/// Render the bundled scene headless with precompiled Kiln shaders.
#[derive(Parser, Debug)]
#[command(name = "kiln-view", version)]
struct Args {
    /// Which frame to render.
    #[arg(long, value_enum, default_value = "desktop")]
    pipeline: PipelineArg,
    /// Graphics API (Mesa's lavapipe or llvmpipe where there is no GPU).
    #[arg(long, value_enum, default_value = "vulkan")]
    backend: BackendArg,
    /// Frame size, WIDTHxHEIGHT.
    #[arg(long, default_value = "640x360", value_parser = parse_size)]
    size: (u32, u32),
    /// Where to write the tonemapped frame.
    #[arg(long, default_value = "frame.png")]
    out: PathBuf,
    /// Write every pass's output as `DIR/<NN>_<Pass>.png` and `DIR/passes.json`.
    #[arg(long, value_name = "DIR")]
    dump_passes: Option<PathBuf>,
    /// Load this archive instead of the one embedded at build time.
    #[arg(long, value_name = "ARCHIVE")]
    shaders: Option<PathBuf>,
    /// Create shader modules from WGSL even where SPIR-V passthrough is available.
    #[arg(long)]
    wgsl: bool,
    /// Pass the SPIR-V of the `--shaders` archive to the driver unchanged (after a structural
    /// check), as for the embedded archive. Only for archives Kiln built that nobody altered:
    /// without it, modules of a file archive come from WGSL, which wgpu validates.
    #[arg(long, requires = "shaders")]
    trust_shaders: bool,
    /// Comparison settings: turn off the effects the other pipelines lack (desktop: TAA,
    /// motion blur, eye adaptation, volumetric fog, reflections, AO, bloom, vignette, sky
    /// gradient; mobile: MSAA, vertex fog, reflections, bloom, translucency).
    #[arg(long)]
    comparison: bool,
    /// Render the frame this many times in a row (the image written is the last).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=1000))]
    frames: u32,
    /// Folder of the driver's pipeline cache (one file per adapter and driver, where the
    /// backend has one). Default: `$KILN_PIPELINE_CACHE`, else `$XDG_CACHE_HOME/kiln/pipelines`,
    /// else `~/.cache/kiln/pipelines`.
    #[arg(long, value_name = "DIR", conflicts_with = "no_pipeline_cache")]
    pipeline_cache: Option<PathBuf>,
    /// Render with the API's validation on (the Khronos validation layer on Vulkan: Debian
    /// package `vulkan-validationlayers`; debug output on GL) and fail (exit 1) with the
    /// messages if it reports any.
    #[arg(long)]
    validation: bool,
    /// Neither read nor write the driver's pipeline cache.
    #[arg(long)]
    no_pipeline_cache: bool,
    /// Instead of rendering: look every permutation of the archive up (by name and by its
    /// dimension values) and create its shader module on the device.
    #[arg(long)]
    verify: bool,
    /// Build the shaders of this permutations.toml in-process, render continuously, and on
    /// every change to a file they read rebuild the permutations it touches, swap them between
    /// frames and rewrite `--out` (one line per reload). Needs the `hot-reload` feature.
    #[arg(long, value_name = "CONFIG", conflicts_with_all = ["shaders", "verify", "dump_passes"])]
    watch: Option<PathBuf>,
    /// Write which pipelines the frames asked for (permutations and whole pipeline keys, how
    /// many frames asked for each and the first that did) to FILE, in the usage format that
    /// `kiln usage merge` and `kiln build --usage` read.
    #[arg(long, value_name = "FILE", conflicts_with_all = ["verify", "watch"])]
    record_usage: Option<PathBuf>,
    /// Do not create the archive's pipeline manifest (`kiln build --usage`) before the first
    /// frame. Without this flag an archive with a manifest has every pipeline of it created
    /// on worker threads first (alongside the frames with `--no-stall`).
    #[arg(long)]
    no_precache: bool,
    /// Never block a frame on a pipeline: one that is not ready is created on a worker
    /// thread and its draws are skipped meanwhile (`--no-stall=nearest`: drawn with the
    /// nearest ready permutation of the same shader with the same bindings).
    #[arg(long, value_enum, value_name = "FALLBACK", num_args = 0..=1, require_equals = true, default_missing_value = "skip")]
    no_stall: Option<StallArg>,
    /// Write the run's pipeline and frame timings as JSON: pipelines_created_before_first_frame,
    /// pipelines_created_during_frames, first_frame_ms, slowest_frame_ms, frames,
    /// fallback_draws, fallback_draws_per_frame, precached.
    #[arg(long, value_name = "FILE", conflicts_with_all = ["verify", "watch"])]
    stats_json: Option<PathBuf>,
    /// With --watch: stop after this many reloads (failed ones included).
    #[arg(long, value_name = "N", requires = "watch", hide = true)]
    watch_reloads: Option<usize>,
}

impl Args {
    fn frame_pipeline(&self) -> FramePipeline {
        match self.pipeline {
            PipelineArg::Desktop => FramePipeline::Desktop,
            PipelineArg::MobileForward => FramePipeline::MobileForward,
            PipelineArg::MobileDeferred => FramePipeline::MobileDeferred,
        }
    }

    fn missing(&self) -> Missing {
        match self.no_stall {
            None => Missing::Block,
            Some(StallArg::Skip) => Missing::Background { fallback: Fallback::Skip },
            Some(StallArg::Nearest) => Missing::Background { fallback: Fallback::Nearest },
        }
    }

    fn backend(&self) -> Backend {
        match self.backend {
            BackendArg::Vulkan => Backend::Vulkan,
            BackendArg::Gl => Backend::Gl,
        }
    }

    fn gpu(&self) -> Result<Gpu, Failure> {
        let module_source = if self.wgsl { kiln_runtime::ModuleSource::Wgsl } else { kiln_runtime::ModuleSource::Auto };
        if self.validation {
            kiln_runtime::validation::enable(self.backend()).map_err(|e| Failure::Render(e.to_string()))?;
        }
        Gpu::new(&GpuOptions { backend: self.backend(), module_source, timestamps: true, validation: self.validation })
            .map_err(|e| Failure::Render(e.to_string()))
    }
}

#[cfg(not(feature = "hot-reload"))]
mod watch {
    use super::*;

    pub fn run(_: &Args, _: &std::path::Path) -> Result<(), Failure> {
        Err(Failure::Usage(
            "--watch needs kiln-view built with the runtime's `hot-reload` feature: \
             cargo run -p kiln-renderer --features hot-reload --bin kiln-view -- --watch CONFIG"
                .into(),
        ))
    }
}

#[cfg(feature = "hot-reload")]
mod watch {
    //! `--watch CONFIG`: the hot-reload loop.

    use std::path::Path;
    use std::time::{Duration, Instant};

    use kiln_runtime::hot_reload::{Event, HotReload};

    use super::*;

    /// How long to wait for a change between two frames.
    const POLL: Duration = Duration::from_millis(50);

    pub fn run(args: &Args, config: &Path) -> Result<(), Failure> {
        let pipeline = args.frame_pipeline();
        let mut hot = HotReload::start(config, &[pipeline.level()]).map_err(|e| Failure::Usage(e.to_string()))?;
        let gpu = args.gpu()?;
        let scene = Scene::bundled();
        let (width, height) = args.size;
        let options = RendererOptions { pipeline, width, height, comparison: args.comparison };
        let mut renderer = Renderer::new(&gpu, hot.archive(), &scene, options).map_err(render_failure)?;
        write_frame(args, &renderer)?;
        println!(
            "kiln-view: watching {} files of {} ({} on {}); wrote {}",
            hot.watched_files(),
            config.display(),
            pipeline.name(),
            gpu.info.name,
            args.out.display()
        );
        let mut reloads = 0;
        loop {
            if args.watch_reloads.is_some_and(|max| reloads >= max) {
                return Ok(());
            }
            let event = hot.poll(POLL).map_err(|e| Failure::Render(e.to_string()))?;
            let Some(event) = event else {
                // Nothing changed: the next frame.
                renderer.render(false).map_err(render_failure)?;
                continue;
            };
            reloads += 1;
            match event {
                Event::Reloaded(r) => {
                    let before = renderer.cache_stats();
                    match renderer.reload(&gpu, r.archive.clone(), &scene, &r.changed) {
                        Ok(new) => {
                            renderer = new;
                            write_frame(args, &renderer)?;
                            hot.accept(r.archive);
                            let after = renderer.cache_stats();
                            let pipelines = (after.render_pipelines + after.compute_pipelines)
                                - (before.render_pipelines + before.compute_pipelines);
                            println!(
                                "kiln-view: reload after {}: {} permutations rebuilt ({} compiled, build {:.0} ms), {} pipelines created, edit to frame {:.0} ms; wrote {}",
                                file_names(&r.files),
                                r.changed.len(),
                                r.compiled,
                                r.build_time.as_secs_f64() * 1000.0,
                                pipelines,
                                ms_since(r.seen),
                                args.out.display()
                            );
                        }
                        Err(e) => {
                            eprintln!("error: {e}");
                            println!(
                                "kiln-view: reload after {} failed: the rebuilt permutations do not make pipelines; keeping the last good ones",
                                file_names(&r.files)
                            );
                        }
                    }
                }
                Event::Failed { diagnostics, files, .. } => {
                    eprintln!("{}", diagnostics.trim_end());
                    println!(
                        "kiln-view: reload after {} failed: the shaders do not build; keeping the last good pipelines",
                        file_names(&files)
                    );
                }
            }
        }
    }

    fn render_failure(e: kiln_renderer::RenderError) -> Failure {
        Failure::Render(e.to_string())
    }

    /// Renders a frame and rewrites `--out` (atomically).
    fn write_frame(args: &Args, renderer: &Renderer) -> Result<(), Failure> {
        let frame = renderer.render(false).map_err(render_failure)?;
        kiln_archive::write_atomic(&args.out, &frame.image.to_png())
            .map_err(|e| Failure::Render(format!("cannot write {}: {e}", args.out.display())))
    }

    fn ms_since(t: Instant) -> f64 {
        t.elapsed().as_secs_f64() * 1000.0
    }

    fn file_names(files: &[std::path::PathBuf]) -> String {
        let names: Vec<String> =
            files.iter().map(|p| p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default()).collect();
        names.join(", ")
    }
}

/// Where the driver's pipeline cache lives, if anywhere.
fn pipeline_cache_dir(args: &Args) -> Option<PathBuf> {
    if args.no_pipeline_cache {
        return None;
    }
    if let Some(dir) = &args.pipeline_cache {
        return Some(dir.clone());
    }
    let env = |name: &str| std::env::var_os(name).filter(|v| !v.is_empty()).map(PathBuf::from);
    env("KILN_PIPELINE_CACHE")
        .or_else(|| env("XDG_CACHE_HOME").map(|d| d.join("kiln/pipelines")))
        .or_else(|| env("HOME").map(|d| d.join(".cache/kiln/pipelines")))
}

fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(|| format!("`{s}` is not WIDTHxHEIGHT"))?;
    let w: u32 = w.trim().parse().map_err(|_| format!("`{w}` is not a width"))?;
    let h: u32 = h.trim().parse().map_err(|_| format!("`{h}` is not a height"))?;
    if w == 0 || h == 0 || w > 16384 || h > 16384 {
        return Err(format!("{w}x{h} is outside 1x1..16384x16384"));
    }
    Ok((w, h))
}

enum Failure {
    Usage(String),
    Render(String),
}

fn main() -> ExitCode {
    let args = match Args::try_parse() {
        Ok(a) => a,
        Err(e) => {
            let code = if e.use_stderr() { 2 } else { 0 };
            let _ = e.print();
            return ExitCode::from(code);
        }
    };
    match run(&args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(Failure::Usage(m)) => {
            eprintln!("error: {m}");
            ExitCode::from(2)
        }
        Err(Failure::Render(m)) => {
            eprintln!("error: {m}");
            ExitCode::from(1)
        }
    }
}

fn run(args: &Args) -> Result<(), Failure> {
    if let Some(config) = &args.watch {
        return watch::run(args, config);
    }
    let archive = open_archive(args)?;
    let gpu = args.gpu()?;
    if args.verify {
        return verify(&gpu, archive);
    }
    let cache = new_cache(args, &gpu, Arc::new(archive));
    cache.set_missing(args.missing());
    let pipelines = |s: kiln_runtime::pipelines::CacheStats| s.render_pipelines + s.compute_pipelines;
    let mut precache = Precaching::start(args, &cache)?;
    if args.missing() == Missing::Block {
        // Blocking frames wait for the manifest first: no frame creates a pipeline.
        precache.finish();
    }
    let renderer = new_renderer(args, &gpu, cache)?;
    let before_first_frame = pipelines(renderer.cache_stats());
    let mut frame_ms = Vec::new();
    let mut fallbacks = Vec::new();
    let mut frame = render_frame(&renderer, false, &mut frame_ms)?;
    fallbacks.push(renderer.pipeline_cache().fallbacks());
    for _ in 1..args.frames {
        frame = render_frame(&renderer, false, &mut frame_ms)?;
        fallbacks.push(renderer.pipeline_cache().fallbacks());
    }
    // The cache counts fallbacks over the run; each frame's are the difference.
    let fallback_draws_per_frame: Vec<u64> =
        fallbacks.iter().scan(0, |before, &total| Some(total - std::mem::replace(before, total))).collect();
    let during_frames = pipelines(renderer.cache_stats()) - before_first_frame;
    let precached = precache.finish();
    if let Some(path) = &args.stats_json {
        let stats = serde_json::json!({
            "pipeline": args.frame_pipeline().name(),
            "frames": frame_ms.len(),
            "pipelines_created_before_first_frame": before_first_frame,
            "pipelines_created_during_frames": during_frames,
            "first_frame_ms": frame_ms.first().copied().unwrap_or(0.0),
            "slowest_frame_ms": frame_ms.iter().copied().fold(0.0, f64::max),
            "fallback_draws": renderer.pipeline_cache().fallbacks(),
            "fallback_draws_per_frame": fallback_draws_per_frame,
            "precached": precached,
        });
        write_file(path, (serde_json::to_string_pretty(&stats).expect("JSON of numbers") + "\n").as_bytes())?;
    }
    if let Some(path) = &args.record_usage {
        write_file(path, renderer.pipeline_cache().usage().to_text().as_bytes())?;
    }
    if let Err(e) = renderer.pipeline_cache().save() {
        eprintln!("warning: cannot write the pipeline cache: {e}");
    }
    check_validation(args, &gpu)?;
    if args.dump_passes.is_some() {
        // Captures copy every pass's output inside the frame; the GPU times come from the
        // frame without them.
        let timed = std::mem::replace(&mut frame, render_frame(&renderer, true, &mut frame_ms)?);
        for (captured, timed) in frame.passes.iter_mut().zip(&timed.passes) {
            captured.gpu_ms = timed.gpu_ms;
            for (step, t) in captured.steps.iter_mut().zip(&timed.steps) {
                step.gpu_ms = t.gpu_ms;
            }
        }
    }
    write_outputs(args, &gpu, &renderer, &frame)
}

/// The `--shaders` archive (trusted with `--trust-shaders`), else the embedded one.
fn open_archive(args: &Args) -> Result<ShaderArchive, Failure> {
    let Some(path) = &args.shaders else {
        return kiln_renderer::embedded_archive().map_err(|e| Failure::Usage(format!("embedded archive: {e}")));
    };
    let archive = ShaderArchive::open(path).map_err(|e| Failure::Usage(e.to_string()))?;
    if args.trust_shaders {
        // SAFETY: the user states the archive is Kiln's own, unaltered (`--trust-shaders`).
        Ok(unsafe { archive.assume_trusted() })
    } else {
        Ok(archive)
    }
}

/// The pipeline cache, with the driver's cache on disk unless told otherwise.
fn new_cache(args: &Args, gpu: &Gpu, archive: Arc<ShaderArchive>) -> PipelineCache {
    match pipeline_cache_dir(args) {
        Some(dir) => {
            let (cache, warning) = PipelineCache::with_disk_cache(gpu, archive, &dir);
            if let Some(w) = warning {
                eprintln!("warning: {w}");
            }
            cache
        }
        None => PipelineCache::new(gpu, archive),
    }
}

/// The archive's pipeline manifest being created on worker threads (`--no-precache`: not).
struct Precaching {
    running: Option<Precache>,
    /// Pipelines it created or found, once finished.
    done: usize,
}

impl Precaching {
    fn start(args: &Args, cache: &PipelineCache) -> Result<Precaching, Failure> {
        let manifest = cache.archive().pipeline_manifest().filter(|_| !args.no_precache);
        let running = match manifest {
            Some(records) => {
                let keys = manifest_keys(records)
                    .map_err(|e| Failure::Usage(format!("the archive's pipeline manifest: {e}")))?;
                Some(cache.precache(keys))
            }
            None => None,
        };
        Ok(Precaching { running, done: 0 })
    }

    /// Waits for it (warning of each pipeline it could not create); returns how many it
    /// created or found.
    fn finish(&mut self) -> usize {
        if let Some(p) = self.running.take() {
            let total = p.progress().total;
            let failed = p.wait();
            for e in &failed {
                eprintln!("warning: precaching: {e}");
            }
            self.done = total - failed.len();
        }
        self.done
    }
}

fn new_renderer(args: &Args, gpu: &Gpu, cache: PipelineCache) -> Result<Renderer, Failure> {
    let (width, height) = args.size;
    let options = RendererOptions { pipeline: args.frame_pipeline(), width, height, comparison: args.comparison };
    // A frame that never waits for a pipeline (`--no-stall`) needs a renderer that does not
    // create them all first.
    let creation = if args.missing() == Missing::Block { Creation::Eager } else { Creation::Lazy };
    Renderer::with_creation(gpu, cache, &Scene::bundled(), options, creation).map_err(|e| match e {
        // A permutation the frame needs is missing from the archive: the archive is wrong.
        kiln_renderer::RenderError::Pipeline(kiln_runtime::pipelines::PipelineError::Lookup(l)) => {
            Failure::Usage(format!("{l}"))
        }
        e => Failure::Render(e.to_string()),
    })
}

/// One frame, its wall time added to `frame_ms`; then the cache's next frame.
fn render_frame(renderer: &Renderer, capture: bool, frame_ms: &mut Vec<f64>) -> Result<FrameOutput, Failure> {
    let start = std::time::Instant::now();
    let frame = renderer.render(capture).map_err(|e| Failure::Render(e.to_string()));
    frame_ms.push(start.elapsed().as_secs_f64() * 1000.0);
    renderer.pipeline_cache().next_frame();
    frame
}

fn write_file(path: &std::path::Path, bytes: &[u8]) -> Result<(), Failure> {
    kiln_archive::write_atomic(path, bytes)
        .map_err(|e| Failure::Render(format!("cannot write {}: {e}", path.display())))
}

/// `--validation`: the messages the API reported, as a failure.
fn check_validation(args: &Args, gpu: &Gpu) -> Result<(), Failure> {
    if !args.validation {
        return Ok(());
    }
    gpu.wait();
    let messages = kiln_runtime::validation::take();
    if messages.is_empty() {
        return Ok(());
    }
    Err(Failure::Render(format!(
        "{} validation message(s) over {} frame(s):\n{}",
        messages.len(),
        args.frames,
        messages.join("\n")
    )))
}

/// Writes the image, the `--dump-passes` folder, and the summary line.
fn write_outputs(args: &Args, gpu: &Gpu, renderer: &Renderer, frame: &FrameOutput) -> Result<(), Failure> {
    let (pipeline, backend, (width, height)) = (args.frame_pipeline(), args.backend(), args.size);
    write_file(&args.out, &frame.image.to_png())?;
    if let Some(dir) = &args.dump_passes {
        let permutations = renderer.pipeline_cache().permutations_used();
        let info = DumpInfo {
            pipeline: pipeline.name(),
            backend: backend.name(),
            adapter: &gpu.info.name,
            width,
            height,
            timestamps: gpu.timestamps,
            spirv_passthrough: renderer.uses_spirv_passthrough(),
            permutations: &permutations,
        };
        write_dump(dir, &info, &frame.passes)
            .map_err(|e| Failure::Render(format!("cannot write {}: {e}", dir.display())))?;
    }
    let stats = renderer.cache_stats();
    eprintln!(
        "kiln-view: {} on {} ({}), {}x{}, {} pipelines, modules from {}; wrote {}",
        pipeline.name(),
        gpu.info.name,
        backend,
        width,
        height,
        stats.render_pipelines + stats.compute_pipelines,
        if renderer.uses_spirv_passthrough() { "SPIR-V passthrough" } else { "WGSL" },
        args.out.display()
    );
    Ok(())
}

/// `--verify`: every permutation found by name and by builder, and its module created.
fn verify(gpu: &Gpu, archive: ShaderArchive) -> Result<(), Failure> {
    let archive = Arc::new(archive);
    let cache = kiln_runtime::pipelines::PipelineCache::new(gpu, archive.clone());
    let mut failures = Vec::new();
    let mut count = 0;
    for p in archive.permutations().map_err(|e| Failure::Render(e.to_string()))? {
        count += 1;
        let shader = p.shader();
        let mut q = archive.shader(&shader.name).level(&shader.level);
        for (d, v) in shader.dimensions.iter().zip(p.values()) {
            q = q.with(&d.name, v);
        }
        let found = match (archive.get(p.name()), q.find()) {
            (Ok(a), Ok(b)) if a.name() == p.name() && b.name() == p.name() => Ok(()),
            (Err(e), _) | (_, Err(e)) => Err(e.to_string()),
            _ => Err("lookup returned another permutation".to_string()),
        };
        let made = found.and_then(|()| cache.module(p.name(), shader.stage).map(|_| ()).map_err(|e| e.to_string()));
        if let Err(e) = made {
            failures.push(format!("{}: {e}", p.name()));
        }
    }
    let source = if cache.uses_spirv_passthrough() { "SPIR-V passthrough" } else { "WGSL" };
    println!(
        "{count} permutations looked up by name and by dimension values; {} distinct modules created from {source} on {}",
        cache.stats().modules,
        gpu.info.name
    );
    if failures.is_empty() {
        Ok(())
    } else {
        Err(Failure::Render(format!("{} of {count} permutations failed:\n{}", failures.len(), failures.join("\n"))))
    }
}

#[cfg(test)]
mod tests {
    use clap::CommandFactory;

    use super::*;

    #[test]
    fn args_are_consistent() {
        Args::command().debug_assert();
    }

    #[test]
    fn sizes() {
        assert_eq!(parse_size("640x360"), Ok((640, 360)));
        assert_eq!(parse_size("8X2"), Ok((8, 2)));
        assert_eq!(parse_size("0x10"), Err("0x10 is outside 1x1..16384x16384".to_string()));
        assert_eq!(parse_size("x10"), Err("`` is not a width".to_string()));
    }
}
