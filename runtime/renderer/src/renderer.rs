//! The frames. A [`Renderer`] owns the scene on the GPU, the render targets and every pass
//! of one `--pipeline`, all built (and, unless [`Creation::Lazy`], every pipeline created) in
//! [`Renderer::new`], the warm-up. [`Renderer::render`] records the frame function of that
//! pipeline, pass by pass in frame order, asking the cache for each pipeline as it records
//! the draw, and returns the output image with each pass's timings and captures.

use std::sync::Arc;

use crate::frame::{Creation, FrameRecorder, Image, PassResult};
use crate::gpu::Gpu;
use crate::passes::Targets;
use crate::pipelines::{CacheStats, PipelineCache, PipelineError};
use crate::scene::gpu::{GpuScene, SceneLayout};
use crate::scene::Scene;
use crate::shaders::ShaderArchive;

/// Which frame to render (`--pipeline`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum FramePipeline {
    /// Deferred shading at the `sm5` level.
    Desktop,
    /// Forward shading at the `es3_1` level.
    MobileForward,
    /// Deferred shading at the `es3_1` level (`DEFERRED_SHADING_PATH`).
    MobileDeferred,
}

impl FramePipeline {
    pub const ALL: [FramePipeline; 3] =
        [FramePipeline::Desktop, FramePipeline::MobileForward, FramePipeline::MobileDeferred];

    pub fn name(self) -> &'static str {
        match self {
            FramePipeline::Desktop => "desktop",
            FramePipeline::MobileForward => "mobile-forward",
            FramePipeline::MobileDeferred => "mobile-deferred",
        }
    }

    pub fn from_name(name: &str) -> Option<FramePipeline> {
        FramePipeline::ALL.into_iter().find(|p| p.name() == name)
    }

    /// The feature level whose permutations the frame uses.
    pub fn level(self) -> &'static str {
        match self {
            FramePipeline::Desktop => "sm5",
            FramePipeline::MobileForward | FramePipeline::MobileDeferred => "es3_1",
        }
    }
}

#[derive(Clone, Debug)]
pub struct RendererOptions {
    pub pipeline: FramePipeline,
    pub width: u32,
    pub height: u32,
    /// Comparison settings: the effects one pipeline has and another lacks are off, so that
    /// desktop and mobile frames of one scene can be compared like with like. Desktop: the effects
    /// off (no TAA and jitter, motion blur, eye adaptation, volumetric fog, sprites,
    /// reflections or animation: [`crate::desktop::effects::EffectOptions::off`]), no ambient
    /// occlusion, bloom, vignette or sky gradient. Mobile: no MSAA, vertex fog, reflections,
    /// bloom or translucency ([`crate::mobile::MobileOptions::comparable`]). The fire's
    /// particles are still simulated and drawn.
    pub comparison: bool,
}

impl Default for RendererOptions {
    fn default() -> Self {
        RendererOptions { pipeline: FramePipeline::Desktop, width: 640, height: 360, comparison: false }
    }
}

impl RendererOptions {
    /// The desktop frame's options for these renderer options.
    pub fn desktop(&self) -> crate::desktop::DesktopOptions {
        let base = crate::desktop::DesktopOptions {
            width: self.width,
            height: self.height,
            output_format: crate::gpu_types::formats::OUTPUT,
            // the first frame shows the fire burning
            warm_up_particles: true,
            ..Default::default()
        };
        if !self.comparison {
            return base;
        }
        crate::desktop::DesktopOptions {
            ambient_occlusion: false,
            bloom: false,
            vignette: false,
            sky_gradient: false,
            effects: crate::desktop::effects::EffectOptions::off(),
            ..base
        }
    }

    /// The mobile frame's options for these renderer options (the forward path's for
    /// the desktop pipeline).
    pub fn mobile(&self) -> crate::mobile::MobileOptions {
        let path = match self.pipeline {
            FramePipeline::MobileDeferred => crate::mobile::ShadingPath::Deferred,
            FramePipeline::Desktop | FramePipeline::MobileForward => crate::mobile::ShadingPath::Forward,
        };
        if self.comparison {
            crate::mobile::MobileOptions::comparable(path)
        } else {
            match path {
                crate::mobile::ShadingPath::Deferred => crate::mobile::MobileOptions::deferred(),
                crate::mobile::ShadingPath::Forward => crate::mobile::MobileOptions::forward(),
            }
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    #[error(transparent)]
    Desktop(#[from] crate::desktop::DesktopError),
    #[error("frame size {width}x{height} is outside 1..={max} pixels per side on this device")]
    Size { width: u32, height: u32, max: u32 },
    #[error("the frame produced no output image")]
    NoOutput,
    #[error("rendering the frame failed: {0}")]
    Wgpu(String),
    #[error("the device was lost: {0}")]
    DeviceLost(String),
}

/// The passes of each frame, built once (one per renderer: variant sizes do not matter).
#[allow(clippy::large_enum_variant)]
enum Passes {
    /// The desktop deferred frame of `crate::desktop` (its particles: `crate::passes::particles`).
    DesktopDeferred { frame: Box<crate::desktop::DesktopFrame> },
    /// Both mobile frames (`crate::mobile`).
    Mobile(Box<crate::mobile::MobileFrame>),
}

/// One rendered frame.
pub struct FrameOutput {
    /// The tonemapped sRGB output.
    pub image: Image,
    /// Every pass in frame order, with GPU times and (when captured) images.
    pub passes: Vec<PassResult>,
}

pub struct Renderer {
    device: wgpu::Device,
    lost: crate::gpu::DeviceLost,
    queue: wgpu::Queue,
    timestamps: bool,
    options: RendererOptions,
    cache: PipelineCache,
    gpu_scene: GpuScene,
    /// The output target (the mobile frames write their own).
    targets: Targets,
    passes: Passes,
    depth_copy: Option<crate::frame::DepthCopy>,
    creation: Creation,
}

impl Renderer {
    /// Uploads the scene, creates the targets and builds every pass of the frame; this
    /// creates every pipeline the frame uses (the warm-up), so [`Renderer::render`] creates
    /// none.
    pub fn new(
        gpu: &Gpu,
        archive: Arc<ShaderArchive>,
        scene: &Scene,
        options: RendererOptions,
    ) -> Result<Renderer, RenderError> {
        Renderer::with_cache(gpu, PipelineCache::new(gpu, archive), scene, options)
    }

    /// Hot reload: a renderer of the same frame on `archive`, built between frames, that
    /// creates again only the modules and pipelines of the `changed` permutations (see
    /// [`PipelineCache::carry_over`]); every other pipeline is this renderer's. On an error
    /// this renderer is untouched, so the caller keeps the last good pipelines.
    pub fn reload(
        &self,
        gpu: &Gpu,
        archive: Arc<ShaderArchive>,
        scene: &Scene,
        changed: &std::collections::HashSet<String>,
    ) -> Result<Renderer, RenderError> {
        Renderer::with_creation(
            gpu,
            self.cache.carry_over(archive, changed),
            scene,
            self.options.clone(),
            self.creation,
        )
    }

    /// As [`Renderer::new`], with pipelines from `cache` (one made with
    /// [`PipelineCache::with_disk_cache`], say). A device lost before or during the setup,
    /// and a failed pipeline or resource, are errors naming what failed (never a panic).
    pub fn with_cache(
        gpu: &Gpu,
        cache: PipelineCache,
        scene: &Scene,
        options: RendererOptions,
    ) -> Result<Renderer, RenderError> {
        Renderer::with_creation(gpu, cache, scene, options, Creation::Eager)
    }

    /// As [`Renderer::with_cache`], creating the frame's pipelines as `creation` says:
    /// [`Creation::Lazy`] builds the passes without creating any pipeline, each being created
    /// when a frame first asks for it (by a cache that creates pipelines off the frame, a
    /// frame that never waits for one: `kiln-view --no-stall`). A permutation missing from
    /// the archive is an error here either way (the passes read its reflection).
    pub fn with_creation(
        gpu: &Gpu,
        cache: PipelineCache,
        scene: &Scene,
        options: RendererOptions,
        creation: Creation,
    ) -> Result<Renderer, RenderError> {
        if let Some(reason) = gpu.lost.reason() {
            return Err(RenderError::DeviceLost(format!("before the frame was set up: {reason}")));
        }
        let scopes = crate::pipelines::ErrorScopes::push(&gpu.device);
        let result = Renderer::set_up(gpu, cache, scene, options, creation);
        let error = scopes.pop();
        // A loss the driver reported meanwhile reaches the callback on a poll.
        let _ = gpu.device.poll(wgpu::PollType::Poll);
        // The device's reason first: a lost device fails every step after it.
        if let Some(reason) = gpu.lost.reason() {
            return Err(RenderError::DeviceLost(format!("while the frame was set up: {reason}")));
        }
        let renderer = result?;
        match error {
            Some(message) => Err(RenderError::Wgpu(format!("setting up the frame: {message}"))),
            None => Ok(renderer),
        }
    }

    fn set_up(
        gpu: &Gpu,
        cache: PipelineCache,
        scene: &Scene,
        options: RendererOptions,
        creation: Creation,
    ) -> Result<Renderer, RenderError> {
        let max = gpu.device.limits().max_texture_dimension_2d;
        if options.width == 0 || options.height == 0 || options.width > max || options.height > max {
            return Err(RenderError::Size { width: options.width, height: options.height, max });
        }
        let device = &gpu.device;
        let layout = match options.pipeline {
            FramePipeline::Desktop => SceneLayout::Rows,
            FramePipeline::MobileForward | FramePipeline::MobileDeferred => SceneLayout::PerObject,
        };
        let gpu_scene = GpuScene::upload(device, scene, layout);
        let targets = Targets::new(device, options.width, options.height);
        let options_size = (options.width, options.height);
        let passes = {
            match options.pipeline {
                FramePipeline::Desktop => {
                    let frame = crate::desktop::DesktopFrame::with_gpu_scene(
                        device,
                        &gpu.queue,
                        gpu.timestamps,
                        &cache,
                        scene,
                        &gpu_scene,
                        // the same on every backend: the volumes are 2D array textures, which
                        // wgpu's GL backend binds layered (see `desktop::frame_view::volume`)
                        crate::desktop::DesktopOptions { pipelines: creation, ..options.desktop() },
                    )
                    // a pipeline error of either frame is `RenderError::Pipeline` (kiln-view
                    // reports a permutation missing from the archive as a usage error)
                    .map_err(|e| match e {
                        crate::desktop::DesktopError::Pipeline(p) => RenderError::Pipeline(p),
                        e => RenderError::Desktop(e),
                    })?;
                    Passes::DesktopDeferred { frame: Box::new(frame) }
                }
                FramePipeline::MobileForward | FramePipeline::MobileDeferred => {
                    let mobile = crate::mobile::MobileOptions { pipelines: creation, ..options.mobile() };
                    let context = crate::mobile::MobileContext { gpu, cache: &cache, scene, gpu_scene: &gpu_scene };
                    Passes::Mobile(Box::new(crate::mobile::MobileFrame::new(&context, mobile, options_size)?))
                }
            }
        };
        let depth_copy = if gpu.depth_copies {
            None
        } else {
            Some(crate::frame::DepthCopy::new(&cache, options.pipeline.level(), creation)?)
        };
        Ok(Renderer {
            device: device.clone(),
            lost: gpu.lost.clone(),
            queue: gpu.queue.clone(),
            timestamps: gpu.timestamps,
            options,
            cache,
            gpu_scene,
            targets,
            passes,
            depth_copy,
            creation,
        })
    }

    pub fn options(&self) -> &RendererOptions {
        &self.options
    }

    pub fn pipeline_cache(&self) -> &PipelineCache {
        &self.cache
    }

    /// Whether the frame's shader modules are created from SPIR-V (passthrough) rather than
    /// from WGSL: on Vulkan with a trusted archive, for every frame.
    pub fn uses_spirv_passthrough(&self) -> bool {
        self.cache.uses_spirv_passthrough()
    }

    pub fn cache_stats(&self) -> CacheStats {
        self.cache.stats()
    }

    /// The desktop deferred frame, for tests that look at its state across frames.
    pub fn desktop_frame(&self) -> Option<&crate::desktop::DesktopFrame> {
        match &self.passes {
            Passes::DesktopDeferred { frame, .. } => Some(frame),
            _ => None,
        }
    }

    /// The desktop frame's effects, for tests that look at its state across frames.
    pub fn desktop_effects(&self) -> Option<&crate::desktop::effects::Effects> {
        self.desktop_frame().map(|d| d.effects())
    }

    /// Renders one frame. With `capture`, every pass's outputs come back as images.
    pub fn render(&self, capture: bool) -> Result<FrameOutput, RenderError> {
        if let Some(reason) = self.lost.reason() {
            return Err(RenderError::DeviceLost(reason));
        }
        let scopes = crate::pipelines::ErrorScopes::push(&self.device);
        let result = self.record_and_submit(capture);
        if let Some(message) = scopes.pop() {
            return Err(RenderError::Wgpu(message));
        }
        if let Some(reason) = self.lost.reason() {
            return Err(RenderError::DeviceLost(reason));
        }
        result
    }

    fn record_and_submit(&self, capture: bool) -> Result<FrameOutput, RenderError> {
        let mut frame = FrameRecorder::new(
            &self.device,
            &self.queue,
            &self.cache,
            self.timestamps,
            capture,
            self.depth_copy.clone(),
        );
        let (s, t) = (&self.gpu_scene, &self.targets);
        match &self.passes {
            Passes::DesktopDeferred { frame: desktop } => {
                desktop.record_into(&mut frame, (&t.output.texture, &t.output.view));
            }
            Passes::Mobile(mobile) => mobile.record(&mut frame, s),
        }
        // The output is always read back, as a capture of a final pseudo-pass.
        let mut readback = FrameRecorder::new(&self.device, &self.queue, &self.cache, false, true, None);
        let passes = frame.finish()?;
        let output = match &self.passes {
            Passes::Mobile(mobile) => mobile.output(),
            _ => &t.output.texture,
        };
        readback.pass("Output", |ctx| ctx.output(output, crate::frame::Visualize::Direct));
        let mut out = readback.finish()?;
        let image = out.pop().and_then(|mut p| p.images.pop()).map(|(_, i)| i).ok_or(RenderError::NoOutput)?;
        Ok(FrameOutput { image, passes })
    }
}
