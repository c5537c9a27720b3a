//! Recording a frame pass by pass.
//!
//! A frame is a function that calls [`FrameRecorder::pass`] once per pass, in frame order.
//! Each pass's render passes run inside debug groups named after it
//! ([`PassContext::render_pass`]); each pass is timed with timestamp queries
//! where the device has them, and declares the textures it wrote with
//! [`PassContext::output`]; when capturing (`--dump-passes`) each output is copied out right
//! after the pass, before later passes change it, and comes back as an 8-bit image (depth
//! and HDR targets mapped to a visible range). Named steps of a pass
//! ([`PassContext::step`]) are dumped under both names, `PostProcessing_Tonemapper`.

mod decl;
mod image;
mod slot;

pub use decl::{FramePlan, PassDecl};
pub use image::{Image, Visualize};
pub use slot::{
    additive, bind_groups, blended, premultiplied, ready_compute, ready_render, replace, untouched, ComputeSlot,
    Creation, FramePipelines, PipelineDesc, RenderSlot, Slots, VertexInput,
};

use std::path::Path;
use std::sync::{Arc, Mutex};

use crate::pipelines::{Blend, ColorTarget, PipelineCache, PipelineError, RenderState};

use serde::Serialize;

/// One pass (or step) as it ran: name, GPU time and the images it produced.
#[derive(Clone, Debug)]
pub struct PassResult {
    pub name: String,
    /// GPU time in milliseconds, where the device has timestamp queries.
    pub gpu_ms: Option<f64>,
    /// Named images: `name` is `Pass`, `Pass_Step` or `Pass_Output`.
    pub images: Vec<(String, Image)>,
    pub steps: Vec<StepResult>,
}

#[derive(Clone, Debug)]
pub struct StepResult {
    pub name: String,
    pub gpu_ms: Option<f64>,
}

struct PendingCapture {
    pass: usize,
    name: String,
    buffer: wgpu::Buffer,
    width: u32,
    height: u32,
    padded_row: u32,
    format: wgpu::TextureFormat,
    visualize: Visualize,
}

struct PassRecord {
    name: String,
    timestamps: Option<(u32, u32)>,
    steps: Vec<(String, Option<(u32, u32)>)>,
}

/// Copies a depth target into an `rgba8unorm` texture holding each depth's bits, with a
/// draw (`VisualizeDepthPS`), for capturing depth where the device cannot copy depth
/// textures to buffers (GL).
#[derive(Clone, Debug)]
pub struct DepthCopy {
    pipeline: Arc<RenderSlot>,
}

impl DepthCopy {
    pub const FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;

    pub fn new(cache: &PipelineCache, level: &str, creation: Creation) -> Result<DepthCopy, PipelineError> {
        let level = crate::keys::level(level)?;
        let vs = crate::keys::name(crate::keys::screen_vs::Key {}, level)?;
        let ps = crate::keys::name(crate::keys::visualize_depth_ps::Key {}, level)?;
        let state = RenderState::fullscreen(ColorTarget::new(DepthCopy::FORMAT, Blend::Replace));
        let key = crate::pipelines::RenderKey { vertex: vs, fragment: Some(ps), state };
        Ok(DepthCopy { pipeline: Arc::new(RenderSlot::new(cache, key, creation)?) })
    }

    /// Records the copy; returns the texture holding the depth bits (`None` while its
    /// pipeline is not ready).
    fn record(
        &self,
        pipelines: FramePipelines<'_>,
        device: &wgpu::Device,
        encoder: &mut wgpu::CommandEncoder,
        depth: &wgpu::Texture,
    ) -> Option<wgpu::Texture> {
        let pipeline = self.pipeline.ready(pipelines)?;
        let target = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("depth capture"),
            size: depth.size(),
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: DepthCopy::FORMAT,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
            view_formats: &[],
        });
        let aspect =
            if depth.format().has_stencil_aspect() { wgpu::TextureAspect::DepthOnly } else { wgpu::TextureAspect::All };
        let source = depth.create_view(&wgpu::TextureViewDescriptor {
            label: Some("depth capture source"),
            aspect,
            ..Default::default()
        });
        let group = self
            .pipeline
            .layout
            .bind_group(
                device,
                1,
                "depth capture",
                &[("SourceDepthTexture", wgpu::BindingResource::TextureView(&source))],
            )
            .ok()?;
        let view = target.create_view(&wgpu::TextureViewDescriptor::default());
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("depth capture"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: &view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations { load: wgpu::LoadOp::Clear(wgpu::Color::BLACK), store: wgpu::StoreOp::Store },
            })],
            depth_stencil_attachment: None,
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_pipeline(&pipeline.pipeline);
        pass.set_bind_group(1, &group, &[]);
        pass.draw(0..3, 0..1);
        drop(pass);
        Some(target)
    }
}

/// Queries of one frame: two per pass or step.
const MAX_QUERIES: u32 = 256;

/// Records a frame's passes into one command encoder, asking `cache` for each pipeline as
/// it records the draw.
pub struct FrameRecorder<'c> {
    recording: Recording,
    cache: &'c PipelineCache,
    /// The first pipeline that could not be created while recording.
    failed: Mutex<Option<PipelineError>>,
}

/// What [`FrameRecorder`] records, apart from where pipelines come from.
struct Recording {
    device: wgpu::Device,
    queue: wgpu::Queue,
    encoder: wgpu::CommandEncoder,
    capture: bool,
    queries: Option<wgpu::QuerySet>,
    next_query: u32,
    passes: Vec<PassRecord>,
    captures: Vec<PendingCapture>,
    current_step: Option<String>,
    depth_copy: Option<DepthCopy>,
    /// Submit and wait before each capture (GL, see [`FrameRecorder::new`]).
    sync_captures: bool,
}

impl<'c> FrameRecorder<'c> {
    /// `cache`: where the passes' pipelines come from. `timestamps`: the device has
    /// `TIMESTAMP_QUERY_INSIDE_ENCODERS`. `capture`: copy every pass output for dumping.
    /// `depth_copy`: how to capture depth where the device cannot copy depth textures to
    /// buffers.
    pub fn new(
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        cache: &'c PipelineCache,
        timestamps: bool,
        capture: bool,
        depth_copy: Option<DepthCopy>,
    ) -> FrameRecorder<'c> {
        FrameRecorder {
            recording: Recording::new(device, queue, timestamps, capture, depth_copy),
            cache,
            failed: Mutex::new(None),
        }
    }

    /// Records one pass: timestamps around it, its render passes in debug groups named after
    /// it, and its outputs.
    pub fn pass<R>(&mut self, name: &str, record: impl FnOnce(&mut PassContext<'_>) -> R) -> R {
        let r = &mut self.recording;
        let start = r.timestamp();
        let index = r.passes.len();
        r.passes.push(PassRecord { name: name.to_string(), timestamps: None, steps: Vec::new() });
        let pipelines = FramePipelines::new(self.cache, &self.failed);
        let result = record(&mut PassContext { recorder: &mut self.recording, pass: index, pipelines });
        let r = &mut self.recording;
        let end = r.timestamp();
        r.passes[index].timestamps = start.zip(end);
        result
    }

    /// Submits the frame, waits for it, and reads back timings and captures. A pipeline
    /// that could not be created while recording is an error (its draws were skipped).
    pub fn finish(self) -> Result<Vec<PassResult>, PipelineError> {
        let results = self.recording.finish();
        match self.failed.into_inner().unwrap_or_else(|e| e.into_inner()) {
            Some(e) => Err(e),
            None => Ok(results),
        }
    }
}

impl Recording {
    fn new(
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        timestamps: bool,
        capture: bool,
        depth_copy: Option<DepthCopy>,
    ) -> Recording {
        let encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("frame") });
        let queries = timestamps.then(|| {
            device.create_query_set(&wgpu::QuerySetDescriptor {
                label: Some("pass timestamps"),
                ty: wgpu::QueryType::Timestamp,
                count: MAX_QUERIES,
            })
        });
        Recording {
            device: device.clone(),
            queue: queue.clone(),
            encoder,
            capture,
            queries,
            next_query: 0,
            passes: Vec::new(),
            captures: Vec::new(),
            current_step: None,
            depth_copy,
            // Mesa 22.3's llvmpipe behind GL can read a texture for a copy while its rasterizer
            // threads still run the draws that write it, once the framebuffer has changed: a
            // capture then comes back with the target as it was before the pass (measured: the
            // ExponentialHeightFog capture in 3 of 5 runs, the ReflectionEnvironmentAndSky one
            // too; never with LP_NUM_THREADS=0). Waiting for the device before each copy
            // finishes those draws; the frame itself is not affected (later passes see them).
            sync_captures: capture && device.adapter_info().backend == wgpu::Backend::Gl,
        }
    }

    fn timestamp(&mut self) -> Option<u32> {
        let set = self.queries.as_ref()?;
        if self.next_query >= MAX_QUERIES {
            return None;
        }
        let i = self.next_query;
        self.encoder.write_timestamp(set, i);
        self.next_query += 1;
        Some(i)
    }

    fn finish(mut self) -> Vec<PassResult> {
        let resolve = self.queries.as_ref().filter(|_| self.next_query > 0).map(|set| {
            let size = u64::from(self.next_query) * 8;
            let resolve = self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("timestamp resolve"),
                size,
                usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            });
            let readback = self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("timestamp readback"),
                size,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            self.encoder.resolve_query_set(set, 0..self.next_query, &resolve, 0);
            self.encoder.copy_buffer_to_buffer(&resolve, 0, &readback, 0, size);
            readback
        });
        self.queue.submit([self.encoder.finish()]);
        let period = f64::from(self.queue.get_timestamp_period());
        for c in &self.captures {
            c.buffer.slice(..).map_async(wgpu::MapMode::Read, |_| {});
        }
        if let Some(r) = &resolve {
            r.slice(..).map_async(wgpu::MapMode::Read, |_| {});
        }
        let _ = self.device.poll(wgpu::PollType::wait_indefinitely());
        let stamps: Vec<u64> = match &resolve {
            Some(r) => match r.slice(..).get_mapped_range() {
                Ok(view) => bytemuck::pod_collect_to_vec(&view),
                Err(_) => Vec::new(),
            },
            None => Vec::new(),
        };
        let ms = |pair: Option<(u32, u32)>| {
            let (a, b) = pair?;
            let (a, b) = (*stamps.get(a as usize)?, *stamps.get(b as usize)?);
            Some(b.saturating_sub(a) as f64 * period / 1.0e6)
        };
        let mut results: Vec<PassResult> = self
            .passes
            .iter()
            .map(|p| PassResult {
                name: p.name.clone(),
                gpu_ms: ms(p.timestamps),
                images: Vec::new(),
                steps: p.steps.iter().map(|(n, t)| StepResult { name: n.clone(), gpu_ms: ms(*t) }).collect(),
            })
            .collect();
        for c in self.captures {
            let image = match c.buffer.slice(..).get_mapped_range() {
                Ok(view) => image::decode(&view, c.width, c.height, c.padded_row, c.format, c.visualize),
                Err(_) => None,
            };
            if let Some(image) = image {
                results[c.pass].images.push((c.name, image));
            }
        }
        results
    }
}

/// What a pass records into.
pub struct PassContext<'a> {
    recorder: &'a mut Recording,
    pass: usize,
    pipelines: FramePipelines<'a>,
}

impl<'a> PassContext<'a> {
    /// Where the pass's pipelines come from while it records ([`RenderSlot::ready`]); a copy
    /// that does not borrow the context, for use inside its render and compute passes.
    pub fn pipelines(&self) -> FramePipelines<'a> {
        self.pipelines
    }

    pub fn encoder(&mut self) -> &mut wgpu::CommandEncoder {
        &mut self.recorder.encoder
    }

    pub fn device(&self) -> &wgpu::Device {
        &self.recorder.device
    }

    /// Whether outputs are captured (`--dump-passes`): passes whose output is not an image
    /// (a buffer) draw a picture of it only then.
    pub fn capturing(&self) -> bool {
        self.recorder.capture
    }

    /// The debug group name of the current pass or step (`PostProcessing/Tonemapper`).
    pub fn debug_name(&self) -> String {
        let r = &*self.recorder;
        match &r.current_step {
            Some(step) => format!("{}/{step}", r.passes[self.pass].name),
            None => r.passes[self.pass].name.clone(),
        }
    }

    /// Begins a render pass inside a debug group named after the pass (and step).
    ///
    /// Debug groups are pushed inside render passes, not on the command encoder: wgpu splits
    /// an encoder into several Vulkan command buffers, and an encoder-level group spanning a
    /// render pass is unbalanced per command buffer (gfx-rs/wgpu#3733), which crashes
    /// lavapipe.
    pub fn render_pass<R>(
        &mut self,
        desc: &wgpu::RenderPassDescriptor<'_>,
        record: impl FnOnce(&mut wgpu::RenderPass<'_>) -> R,
    ) -> R {
        let mut pass = self.open_render_pass(desc);
        record(&mut pass)
    }

    /// Begins a compute pass inside a debug group named after the pass (and step).
    pub fn compute_pass<R>(&mut self, label: &str, record: impl FnOnce(&mut wgpu::ComputePass<'_>) -> R) -> R {
        let mut pass = self.open_compute_pass(label);
        record(&mut pass)
    }

    /// [`PassContext::render_pass`] as a value: the render pass, its debug group popped when
    /// it is dropped. For code that hands a pass on rather than recording in a closure.
    pub fn open_render_pass(&mut self, desc: &wgpu::RenderPassDescriptor<'_>) -> GroupedRenderPass<'_> {
        let name = self.debug_name();
        let mut pass = self.recorder.encoder.begin_render_pass(desc);
        pass.push_debug_group(&name);
        GroupedRenderPass(pass)
    }

    /// [`PassContext::compute_pass`] as a value (see [`PassContext::open_render_pass`]).
    pub fn open_compute_pass(&mut self, label: &str) -> GroupedComputePass<'_> {
        let name = self.debug_name();
        let mut pass = self
            .recorder
            .encoder
            .begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some(label), timestamp_writes: None });
        pass.push_debug_group(&name);
        GroupedComputePass(pass)
    }

    /// A named step of this pass, timed on its own; its render passes' debug groups are
    /// named `Pass/Step`.
    pub fn step<R>(&mut self, name: &str, record: impl FnOnce(&mut PassContext<'_>) -> R) -> R {
        let start = self.recorder.timestamp();
        let outer = self.recorder.current_step.replace(name.to_string());
        let result = record(&mut PassContext { recorder: self.recorder, pass: self.pass, pipelines: self.pipelines });
        self.recorder.current_step = outer;
        let end = self.recorder.timestamp();
        self.recorder.passes[self.pass].steps.push((name.to_string(), start.zip(end)));
        result
    }

    /// Declares the pass's (or the current step's) main output.
    pub fn output(&mut self, texture: &wgpu::Texture, visualize: Visualize) {
        self.capture(None, texture, visualize);
    }

    /// Declares a further output, dumped as `Pass_<name>` (`BasePass_GBufferA`).
    pub fn output_named(&mut self, name: &str, texture: &wgpu::Texture, visualize: Visualize) {
        self.capture(Some(name), texture, visualize);
    }

    fn capture(&mut self, name: Option<&str>, texture: &wgpu::Texture, visualize: Visualize) {
        if !self.recorder.capture {
            return;
        }
        let r = &mut *self.recorder;
        if r.sync_captures {
            let done = std::mem::replace(
                &mut r.encoder,
                r.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("frame") }),
            );
            r.queue.submit([done.finish()]);
            let _ = r.device.poll(wgpu::PollType::wait_indefinitely());
        }
        let mut full = r.passes[self.pass].name.clone();
        for part in [r.current_step.as_deref(), name].into_iter().flatten() {
            full.push('_');
            full.push_str(part);
        }
        let copied;
        let texture = match (&r.depth_copy, texture.format().is_depth_stencil_format()) {
            (Some(copy), true) => match copy.record(self.pipelines, &r.device, &mut r.encoder, texture) {
                Some(t) => {
                    copied = t;
                    &copied
                }
                None => return,
            },
            _ => texture,
        };
        let format = texture.format();
        let Some(bytes_per_texel) = format
            .block_copy_size(Some(wgpu::TextureAspect::All))
            .or_else(|| format.block_copy_size(Some(wgpu::TextureAspect::DepthOnly)))
        else {
            return;
        };
        let (width, height) = (texture.width(), texture.height());
        let padded_row =
            (width * bytes_per_texel).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
        let buffer = r.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(&format!("capture {full}")),
            size: u64::from(padded_row) * u64::from(height),
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let aspect =
            if format.is_depth_stencil_format() { wgpu::TextureAspect::DepthOnly } else { wgpu::TextureAspect::All };
        r.encoder.copy_texture_to_buffer(
            wgpu::TexelCopyTextureInfo { texture, mip_level: 0, origin: wgpu::Origin3d::ZERO, aspect },
            wgpu::TexelCopyBufferInfo {
                buffer: &buffer,
                layout: wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(padded_row),
                    rows_per_image: Some(height),
                },
            },
            wgpu::Extent3d { width, height, depth_or_array_layers: 1 },
        );
        r.captures.push(PendingCapture {
            pass: self.pass,
            name: full,
            buffer,
            width,
            height,
            padded_row,
            format,
            visualize,
        });
    }
}

/// A render pass inside its pass's debug group, popped when dropped.
pub struct GroupedRenderPass<'e>(wgpu::RenderPass<'e>);

impl Drop for GroupedRenderPass<'_> {
    fn drop(&mut self) {
        self.0.pop_debug_group();
    }
}

impl<'e> std::ops::Deref for GroupedRenderPass<'e> {
    type Target = wgpu::RenderPass<'e>;
    fn deref(&self) -> &wgpu::RenderPass<'e> {
        &self.0
    }
}

impl<'e> std::ops::DerefMut for GroupedRenderPass<'e> {
    fn deref_mut(&mut self) -> &mut wgpu::RenderPass<'e> {
        &mut self.0
    }
}

/// A compute pass inside its pass's debug group, popped when dropped.
pub struct GroupedComputePass<'e>(wgpu::ComputePass<'e>);

impl Drop for GroupedComputePass<'_> {
    fn drop(&mut self) {
        self.0.pop_debug_group();
    }
}

impl<'e> std::ops::Deref for GroupedComputePass<'e> {
    type Target = wgpu::ComputePass<'e>;
    fn deref(&self) -> &wgpu::ComputePass<'e> {
        &self.0
    }
}

impl<'e> std::ops::DerefMut for GroupedComputePass<'e> {
    fn deref_mut(&mut self) -> &mut wgpu::ComputePass<'e> {
        &mut self.0
    }
}

#[derive(Serialize)]
struct PassesJson<'a> {
    pipeline: &'a str,
    backend: &'a str,
    adapter: &'a str,
    width: u32,
    height: u32,
    timestamps: bool,
    /// Modules from SPIR-V passthrough (else WGSL).
    spirv_passthrough: bool,
    passes: Vec<PassJson>,
    /// Every permutation the frame's pipelines run.
    permutations: &'a [String],
}

#[derive(Serialize)]
struct PassJson {
    index: usize,
    name: String,
    images: Vec<String>,
    gpu_ms: Option<f64>,
    steps: Vec<StepJson>,
}

#[derive(Serialize)]
struct StepJson {
    name: String,
    gpu_ms: Option<f64>,
}

/// Facts about the run written at the top of `passes.json`.
pub struct DumpInfo<'a> {
    pub pipeline: &'a str,
    pub backend: &'a str,
    pub adapter: &'a str,
    pub width: u32,
    pub height: u32,
    pub timestamps: bool,
    pub spirv_passthrough: bool,
    pub permutations: &'a [String],
}

/// Writes `DIR/<NN>_<Name>.png` for every captured image and `DIR/passes.json` (frame
/// order, names, image files, GPU times or null). Every file is written atomically.
pub fn write_dump(dir: &Path, info: &DumpInfo<'_>, passes: &[PassResult]) -> std::io::Result<()> {
    std::fs::create_dir_all(dir)?;
    let mut json = PassesJson {
        pipeline: info.pipeline,
        backend: info.backend,
        adapter: info.adapter,
        width: info.width,
        height: info.height,
        timestamps: info.timestamps,
        spirv_passthrough: info.spirv_passthrough,
        passes: Vec::new(),
        permutations: info.permutations,
    };
    for (i, p) in passes.iter().enumerate() {
        let mut files = Vec::new();
        for (name, image) in &p.images {
            let file = format!("{i:02}_{name}.png");
            kiln_archive::write_atomic(&dir.join(&file), &image.to_png())?;
            files.push(file);
        }
        json.passes.push(PassJson {
            index: i,
            name: p.name.clone(),
            images: files,
            gpu_ms: p.gpu_ms,
            steps: p.steps.iter().map(|s| StepJson { name: s.name.clone(), gpu_ms: s.gpu_ms }).collect(),
        });
    }
    let text = serde_json::to_string_pretty(&json).map_err(std::io::Error::other)?;
    kiln_archive::write_atomic(&dir.join("passes.json"), text.as_bytes())
}

/// A 2D render or storage target with one mip (COPY_SRC added, so passes can dump it).
pub fn target_2d(
    device: &wgpu::Device,
    label: &str,
    size: [u32; 2],
    format: wgpu::TextureFormat,
    usage: wgpu::TextureUsages,
) -> wgpu::Texture {
    device.create_texture(&wgpu::TextureDescriptor {
        label: Some(label),
        size: wgpu::Extent3d { width: size[0].max(1), height: size[1].max(1), depth_or_array_layers: 1 },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format,
        usage: usage | wgpu::TextureUsages::COPY_SRC,
        view_formats: &[],
    })
}
