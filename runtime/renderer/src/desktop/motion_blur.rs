//! PostProcessing MotionBlur (`MotionBlur.usf`): gathers the anti-aliased scene colour along
//! each pixel's motion (the velocity target for movable meshes, camera reprojection from depth
//! elsewhere), scaled by the shutter and capped, and writes the result, times the eye
//! adaptation's exposure, back to SceneColor for the Bloom and Tonemapper that follow.

use crate::frame::{PassContext, PassDecl, RenderSlot};
use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use glam::Vec4;

use crate::keys;
use crate::pipelines::{Blend, ColorTarget, PipelineError, RenderState};

use super::frame_view::{color_pass, linear_sampler, uniform_buffer, EffectPassInit};

/// A step of PostProcessing: writes the TAA output back to SceneColor, blurred and exposed.
pub const STEP: PassDecl = PassDecl {
    name: "MotionBlur",
    reads: &["View", "SceneDepth", "Velocity", "TAAHistory", "EyeAdaptation"],
    writes: &["SceneColor"],
};

/// Fraction of the frame the shutter is open (Unreal's default 0.5).
pub const SHUTTER: f32 = 0.5;
/// Longest blur, in uv units.
pub const MAX_LENGTH: f32 = 0.05;
pub const SAMPLES: f32 = 8.0;

#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
struct MotionBlurParams {
    shutter: Vec4,
}

pub struct MotionBlur {
    pipeline: Arc<RenderSlot>,
    /// One bind group per input (the TAA history pair).
    groups: Vec<wgpu::BindGroup>,
    params: wgpu::Buffer,
}

impl MotionBlur {
    /// `inputs`: the textures the blur may read (one bind group each).
    pub fn new(
        init: &EffectPassInit<'_>,
        inputs: &[&wgpu::TextureView],
        velocity: &wgpu::TextureView,
        scene_depth: &wgpu::TextureView,
        eye_adaptation: &wgpu::Buffer,
        output_format: wgpu::TextureFormat,
    ) -> Result<MotionBlur, PipelineError> {
        let EffectPassInit { device, cache, frame_view } = *init;
        let pipeline = cache.render(
            &keys::name(keys::motion_blur_vs::Key {}, keys::Level::Sm5)?,
            Some(&keys::name(keys::motion_blur_ps::Key {}, keys::Level::Sm5)?),
            &RenderState::fullscreen(ColorTarget::new(output_format, Blend::Replace)),
        )?;
        let params = uniform_buffer(
            device,
            "MotionBlur params",
            &MotionBlurParams { shutter: Vec4::new(SHUTTER, MAX_LENGTH, SAMPLES, 0.0) },
        );
        let sampler = linear_sampler(device, "MotionBlur sampler");
        let groups = inputs
            .iter()
            .map(|input| {
                pipeline.layout.bind_group(
                    device,
                    0,
                    "MotionBlur",
                    &[
                        ("View", frame_view.as_entire_binding()),
                        ("blur", params.as_entire_binding()),
                        ("scene_color", wgpu::BindingResource::TextureView(input)),
                        ("velocity", wgpu::BindingResource::TextureView(velocity)),
                        ("SceneDepthTexture", wgpu::BindingResource::TextureView(scene_depth)),
                        ("linear_sampler", wgpu::BindingResource::Sampler(&sampler)),
                        ("eye_adaptation", eye_adaptation.as_entire_binding()),
                    ],
                )
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(MotionBlur { pipeline, groups, params })
    }

    /// Blurs input `input` (an index into the inputs given to `new`) into `output`, with the
    /// shutter open (`blur`) or closed (exposure only).
    pub fn record(
        &self,
        queue: &wgpu::Queue,
        ctx: &mut PassContext<'_>,
        input: usize,
        output: &wgpu::TextureView,
        blur: bool,
    ) {
        let shutter = if blur { SHUTTER } else { 0.0 };
        queue.write_buffer(
            &self.params,
            0,
            bytemuck::bytes_of(&MotionBlurParams { shutter: Vec4::new(shutter, MAX_LENGTH, SAMPLES, 0.0) }),
        );
        let ready = self.pipeline.ready(ctx.pipelines());
        let mut pass = color_pass(ctx, "MotionBlur", output, wgpu::LoadOp::Clear(wgpu::Color::BLACK));
        if let Some(p) = ready {
            pass.set_pipeline(&p.pipeline);
            pass.set_bind_group(0, &self.groups[input], &[]);
            pass.draw(0..3, 0..1);
        }
    }
}
