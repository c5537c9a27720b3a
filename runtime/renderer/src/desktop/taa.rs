//! PostProcessing TAA (`TemporalAA.usf`): the frame is rasterised with the Halton (2, 3)
//! sub-pixel jitter of [`super::frame_view::taa_jitter`]; this pass reprojects the history
//! (camera motion from depth, object motion from the velocity target), clips it to the
//! current 3x3 neighbourhood's YCoCg box and blends the current frame in with weight
//! [`CURRENT_WEIGHT`]. The output is the next frame's history (ping-pong pair).

use crate::frame::{PassContext, PassDecl, RenderSlot};
use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use glam::Vec4;

use crate::keys;
use crate::pipelines::{Blend, ColorTarget, PipelineError, RenderState};

use super::frame_view::{color_pass, linear_sampler, target_2d, uniform_buffer, view, EffectPassInit};

/// The first step of PostProcessing: resolves SceneColor into the history it reprojects next frame.
pub const STEP: PassDecl = PassDecl {
    name: "TAA",
    reads: &["View", "SceneDepth", "Velocity", "SceneColor", "TAAHistory"],
    writes: &["TAAHistory"],
};

/// Without TAA: SceneColor copied into the history (no step of its own).
pub const BYPASS: PassDecl = PassDecl { name: "TAABypass", reads: &["SceneColor"], writes: &["TAAHistory"] };

pub const HISTORY_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba16Float;
/// Weight of the current frame in the history (Unreal: 0.04 at 8 samples; a larger weight
/// converges in the few frames a test renders).
pub const CURRENT_WEIGHT: f32 = 0.125;

#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
struct TaaParams {
    blend: Vec4,
}

pub struct TemporalAA {
    pub history: [wgpu::Texture; 2],
    history_views: [wgpu::TextureView; 2],
    pipeline: Arc<RenderSlot>,
    params: wgpu::Buffer,
    /// groups[i] reads history 1 - i and writes history i.
    groups: [wgpu::BindGroup; 2],
    current: usize,
    history_valid: bool,
}

impl TemporalAA {
    pub fn new(
        init: &EffectPassInit<'_>,
        size: [u32; 2],
        scene_color: &wgpu::TextureView,
        velocity: &wgpu::TextureView,
        scene_depth: &wgpu::TextureView,
    ) -> Result<TemporalAA, PipelineError> {
        let EffectPassInit { device, cache, frame_view } = *init;
        let pipeline = cache.render(
            &keys::name(keys::temporal_aavs::Key {}, keys::Level::Sm5)?,
            Some(&keys::name(keys::temporal_aaps::Key {}, keys::Level::Sm5)?),
            &RenderState::fullscreen(ColorTarget::new(HISTORY_FORMAT, Blend::Replace)),
        )?;
        let usage = wgpu::TextureUsages::RENDER_ATTACHMENT
            | wgpu::TextureUsages::TEXTURE_BINDING
            | wgpu::TextureUsages::COPY_SRC
            | wgpu::TextureUsages::COPY_DST;
        let history = [
            target_2d(device, "TemporalAAHistory0", size, HISTORY_FORMAT, usage),
            target_2d(device, "TemporalAAHistory1", size, HISTORY_FORMAT, usage),
        ];
        let history_views = [view(&history[0]), view(&history[1])];
        let params = uniform_buffer(device, "TemporalAA params", &TaaParams::default());
        let sampler = linear_sampler(device, "TemporalAA sampler");
        let group = |i: usize| {
            pipeline.layout.bind_group(
                device,
                0,
                "TemporalAA",
                &[
                    ("View", frame_view.as_entire_binding()),
                    ("taa", params.as_entire_binding()),
                    ("scene_color", wgpu::BindingResource::TextureView(scene_color)),
                    ("history", wgpu::BindingResource::TextureView(&history_views[1 - i])),
                    ("velocity", wgpu::BindingResource::TextureView(velocity)),
                    ("SceneDepthTexture", wgpu::BindingResource::TextureView(scene_depth)),
                    ("linear_sampler", wgpu::BindingResource::Sampler(&sampler)),
                ],
            )
        };
        let groups = [group(0)?, group(1)?];
        Ok(TemporalAA { history, history_views, pipeline, params, groups, current: 1, history_valid: false })
    }

    pub fn reset_history(&mut self) {
        self.history_valid = false;
    }

    /// Resolves this frame into the next history; returns the texture written (the
    /// anti-aliased SceneColor).
    pub fn record(&mut self, queue: &wgpu::Queue, ctx: &mut PassContext<'_>) -> &wgpu::TextureView {
        let out = 1 - self.current;
        let params =
            TaaParams { blend: Vec4::new(CURRENT_WEIGHT, if self.history_valid { 1.0 } else { 0.0 }, 0.0, 0.0) };
        queue.write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
        let ready = self.pipeline.ready(ctx.pipelines());
        let mut pass = color_pass(ctx, "TAA", &self.history_views[out], wgpu::LoadOp::Clear(wgpu::Color::BLACK));
        if let Some(p) = ready {
            pass.set_pipeline(&p.pipeline);
            pass.set_bind_group(0, &self.groups[out], &[]);
            pass.draw(0..3, 0..1);
            // a frame that could not resolve leaves the history as it was
            self.history_valid = true;
        }
        drop(pass);
        self.current = out;
        &self.history_views[out]
    }

    /// Without TAA: SceneColor copied into the next history slot as it is (the passes after
    /// read it from there); the history becomes invalid.
    pub fn bypass(&mut self, ctx: &mut PassContext<'_>, scene_color: &wgpu::Texture) {
        let out = 1 - self.current;
        ctx.encoder().copy_texture_to_texture(
            scene_color.as_image_copy(),
            self.history[out].as_image_copy(),
            scene_color.size(),
        );
        self.current = out;
        self.history_valid = false;
    }

    pub fn output(&self) -> &wgpu::Texture {
        &self.history[self.current]
    }

    /// The index of the history written last (0 or 1), as in [`Self::history_views`].
    pub fn current(&self) -> usize {
        self.current
    }

    pub fn history_views(&self) -> [&wgpu::TextureView; 2] {
        [&self.history_views[0], &self.history_views[1]]
    }

    pub fn output_view(&self) -> &wgpu::TextureView {
        &self.history_views[self.current]
    }
}
