//! PostProcessing EyeAdaptation: a 64-bin histogram of SceneColor's log2 luminance
//! (`PostProcessHistogram.usf`, workgroup-local bins merged with atomics), then the exposure
//! that brings the average luminance between the 10th and 90th percentiles to middle grey,
//! adapted smoothly from the previous frame's (`PostProcessEyeAdaptation.usf`). The result
//! stays on the GPU: a storage buffer `{ exposure, average luminance, target exposure }` that
//! the frame copies into the exposure the Bloom and Tonemapper read. A small image of the
//! histogram is drawn for the pass dump.

use crate::frame::{ComputeSlot, PassContext, PassDecl, Slots};
use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use glam::{UVec4, Vec4};

use crate::keys;
use crate::pipelines::PipelineError;

use super::frame_view::{groups, target_2d, uniform_buffer, view};

/// A step of PostProcessing: adapts the previous exposure (history) to the TAA output.
pub const STEP: PassDecl =
    PassDecl { name: "EyeAdaptation", reads: &["TAAHistory", "EyeAdaptation"], writes: &["EyeAdaptation"] };

pub const BINS: usize = 64;
pub const MIN_LOG2_LUMINANCE: f32 = -10.0;
pub const MAX_LOG2_LUMINANCE: f32 = 6.0;
pub const DEBUG_SIZE: [u32; 2] = [256, 64];

#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
struct HistogramParams {
    log_range: Vec4,
    size: UVec4,
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
struct EyeAdaptationParams {
    log_range: Vec4,
    limits: Vec4,
    timing: Vec4,
}

/// `EyeAdaptation` of `PostProcessEyeAdaptation.usf`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct EyeAdaptationResult {
    pub exposure: f32,
    pub average_luminance: f32,
    pub target_exposure: f32,
    pub pad: f32,
}

/// The eye adaptation's settings (Unreal's auto exposure defaults, in relative units).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EyeAdaptationSettings {
    pub low_percent: f32,
    pub high_percent: f32,
    pub min_exposure: f32,
    pub max_exposure: f32,
    /// Adaptation speed towards a brighter scene (per second).
    pub speed_up: f32,
    pub speed_down: f32,
    /// Multiplies the exposure (1: the average maps to 0.18).
    pub compensation: f32,
}

impl Default for EyeAdaptationSettings {
    fn default() -> Self {
        EyeAdaptationSettings {
            low_percent: 0.1,
            high_percent: 0.9,
            min_exposure: 0.25,
            max_exposure: 4.0,
            speed_up: 3.0,
            speed_down: 1.0,
            compensation: 1.0,
        }
    }
}

pub struct EyeAdaptation {
    pub histogram: wgpu::Buffer,
    pub result: wgpu::Buffer,
    pub debug: wgpu::Texture,
    histogram_pipeline: Arc<ComputeSlot>,
    adapt_pipeline: Arc<ComputeSlot>,
    debug_pipeline: Arc<ComputeSlot>,
    histogram_groups: Vec<wgpu::BindGroup>,
    adapt_group: wgpu::BindGroup,
    debug_group: wgpu::BindGroup,
    adapt_params: wgpu::Buffer,
    _histogram_params: wgpu::Buffer,
    size: [u32; 2],
    valid: bool,
    pub settings: EyeAdaptationSettings,
}

impl EyeAdaptation {
    /// `inputs`: the textures the histogram may measure (one bind group each).
    pub fn new(
        device: &wgpu::Device,
        cache: Slots<'_>,
        inputs: &[&wgpu::TextureView],
        size: [u32; 2],
    ) -> Result<EyeAdaptation, PipelineError> {
        let histogram_pipeline =
            cache.compute(&keys::name(keys::post_process_histogram_cs::Key {}, keys::Level::Sm5)?)?;
        let adapt_pipeline =
            cache.compute(&keys::name(keys::post_process_eye_adaptation_cs::Key {}, keys::Level::Sm5)?)?;
        let debug_pipeline =
            cache.compute(&keys::name(keys::post_process_histogram_debug_cs::Key {}, keys::Level::Sm5)?)?;
        let histogram = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("PostProcessHistogram"),
            size: (BINS * 4) as u64,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        // the eye starts adapted to exposure 1 and moves from there at the adaptation speed,
        // frame after frame (one frame changes the exposure by a few percent)
        let result = crate::gpu::BufferInit::create_buffer_init(
            device,
            &wgpu::util::BufferInitDescriptor {
                label: Some("EyeAdaptation"),
                contents: bytemuck::bytes_of(&EyeAdaptationResult {
                    exposure: 1.0,
                    average_luminance: 0.18,
                    target_exposure: 1.0,
                    pad: 0.0,
                }),
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST,
            },
        );
        let debug = target_2d(
            device,
            "PostProcessHistogram image",
            DEBUG_SIZE,
            wgpu::TextureFormat::Rgba8Unorm,
            wgpu::TextureUsages::STORAGE_BINDING | wgpu::TextureUsages::TEXTURE_BINDING,
        );
        let histogram_params = uniform_buffer(
            device,
            "PostProcessHistogram params",
            &HistogramParams {
                log_range: Vec4::new(MIN_LOG2_LUMINANCE, MAX_LOG2_LUMINANCE, 0.0, 0.0),
                size: UVec4::new(size[0], size[1], 0, 0),
            },
        );
        let adapt_params = uniform_buffer(device, "EyeAdaptation params", &EyeAdaptationParams::default());
        let histogram_groups = inputs
            .iter()
            .map(|input| {
                histogram_pipeline.layout.bind_group(
                    device,
                    0,
                    "PostProcessHistogram",
                    &[
                        ("params", histogram_params.as_entire_binding()),
                        ("histogram", histogram.as_entire_binding()),
                        ("scene_color", wgpu::BindingResource::TextureView(input)),
                    ],
                )
            })
            .collect::<Result<Vec<_>, _>>()?;
        let adapt_group = adapt_pipeline.layout.bind_group(
            device,
            0,
            "PostProcessEyeAdaptation",
            &[
                ("params", adapt_params.as_entire_binding()),
                ("histogram", histogram.as_entire_binding()),
                ("eye", result.as_entire_binding()),
            ],
        )?;
        let debug_view = view(&debug);
        let debug_group = debug_pipeline.layout.bind_group(
            device,
            0,
            "PostProcessHistogram image",
            &[
                ("histogram", histogram.as_entire_binding()),
                ("debug_image", wgpu::BindingResource::TextureView(&debug_view)),
            ],
        )?;
        Ok(EyeAdaptation {
            histogram,
            result,
            debug,
            histogram_pipeline,
            adapt_pipeline,
            debug_pipeline,
            histogram_groups,
            adapt_group,
            debug_group,
            adapt_params,
            _histogram_params: histogram_params,
            size,
            valid: true,
            settings: EyeAdaptationSettings::default(),
        })
    }

    /// Histogram of input `input`, its image, then the adapted exposure (`delta_time` seconds
    /// after the last).
    pub fn record(&mut self, queue: &wgpu::Queue, ctx: &mut PassContext<'_>, input: usize, delta_time: f32) {
        let s = &self.settings;
        let params = EyeAdaptationParams {
            log_range: Vec4::new(MIN_LOG2_LUMINANCE, MAX_LOG2_LUMINANCE, s.low_percent, s.high_percent),
            limits: Vec4::new(s.min_exposure, s.max_exposure, s.speed_up, s.speed_down),
            timing: Vec4::new(delta_time, s.compensation, if self.valid { 1.0 } else { 0.0 }, 0.0),
        };
        queue.write_buffer(&self.adapt_params, 0, bytemuck::bytes_of(&params));
        ctx.encoder().clear_buffer(&self.histogram, 0, None);
        let pl = ctx.pipelines();
        let mut pass = ctx.open_compute_pass("PostProcessHistogram");
        // the exposure adapts from a histogram of this frame only: without one, it waits
        let Some(histogram) = self.histogram_pipeline.ready(pl) else { return };
        pass.set_pipeline(&histogram.pipeline);
        pass.set_bind_group(0, &self.histogram_groups[input], &[]);
        pass.dispatch_workgroups(groups(self.size[0], 16), groups(self.size[1], 16), 1);
        if let Some(debug) = self.debug_pipeline.ready(pl) {
            pass.set_pipeline(&debug.pipeline);
            pass.set_bind_group(0, &self.debug_group, &[]);
            pass.dispatch_workgroups(groups(DEBUG_SIZE[0], 8), groups(DEBUG_SIZE[1], 8), 1);
        }
        if let Some(adapt) = self.adapt_pipeline.ready(pl) {
            pass.set_pipeline(&adapt.pipeline);
            pass.set_bind_group(0, &self.adapt_group, &[]);
            pass.dispatch_workgroups(1, 1, 1);
            self.valid = true;
        }
    }

    /// Sets the exposure to `exposure` without measuring (eye adaptation off); adaptation
    /// resumes from it.
    pub fn set_fixed(&mut self, queue: &wgpu::Queue, exposure: f32) {
        queue.write_buffer(
            &self.result,
            0,
            bytemuck::bytes_of(&EyeAdaptationResult {
                exposure,
                average_luminance: 0.0,
                target_exposure: exposure,
                pad: 0.0,
            }),
        );
    }

    /// Copies the adapted exposure (one f32) into `buffer` at `offset` (a uniform the
    /// tonemapper reads), on the GPU: no read-back, no stall.
    pub fn copy_exposure_to(&self, encoder: &mut wgpu::CommandEncoder, buffer: &wgpu::Buffer, offset: u64) {
        encoder.copy_buffer_to_buffer(&self.result, 0, buffer, offset, 4);
    }
}
