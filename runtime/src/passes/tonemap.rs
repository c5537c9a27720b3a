//! PostProcessing: the Tonemapper, SceneColor (HDR) to the sRGB output with exposure and
//! the ACES filmic curve. Bloom is a step the desktop frame issue adds (`USE_BLOOM`).

use std::sync::Arc;

use crate::frame::{PassContext, Visualize};
use crate::gpu_types::formats;
use crate::pipelines::{Blend, ColorTarget, PipelineError, RenderPipeline, RenderState};

use super::{PassInit, Targets};

pub struct TonemapPass {
    pipeline: Arc<RenderPipeline>,
    groups: Vec<wgpu::BindGroup>,
}

impl TonemapPass {
    pub fn new(init: &PassInit<'_>) -> Result<TonemapPass, PipelineError> {
        let vs = init.permutation("ScreenVS", &[])?;
        let ps = init.permutation("TonemapPS", &[("USE_BLOOM", "0")])?;
        let pipeline = init.cache.render(&vs, Some(&ps), &RenderState::fullscreen(ColorTarget { format: formats::OUTPUT, blend: Blend::Replace }))?;
        let t = &init.shared.targets;
        let layout = &pipeline.layout;
        let groups = vec![
            layout.bind_group(init.device, 0, "Tonemapper view", &init.shared.view_resources())?,
            layout.bind_group(init.device, 1, "Tonemapper input", &[("SceneColorTexture", wgpu::BindingResource::TextureView(&t.scene_color.view))])?,
        ];
        Ok(TonemapPass { pipeline, groups })
    }

    /// Reads SceneColor; writes the output.
    pub fn record(&self, ctx: &mut PassContext<'_>, t: &Targets) {
        ctx.step("Tonemapper", |ctx| {
            {
                ctx.render_pass(&wgpu::RenderPassDescriptor {
                    label: Some("Tonemapper"),
                    color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                        view: &t.output.view,
                        depth_slice: None,
                        resolve_target: None,
                        ops: wgpu::Operations { load: wgpu::LoadOp::Clear(wgpu::Color::BLACK), store: wgpu::StoreOp::Store },
                    })],
                    depth_stencil_attachment: None,
                    timestamp_writes: None,
                    occlusion_query_set: None,
                    multiview_mask: None,
                }, |pass| {
                    pass.set_pipeline(&self.pipeline.pipeline);
                    for (i, g) in self.groups.iter().enumerate() {
                        pass.set_bind_group(i as u32, g, &[]);
                    }
                    pass.draw(0..3, 0..1);
                });
            }
            ctx.output(&t.output.texture, Visualize::Direct);
        });
    }
}
