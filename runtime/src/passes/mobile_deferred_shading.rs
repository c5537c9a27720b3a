//! MobileDeferredShading (es3_1): the directional light as one full-screen draw over the
//! mobile GBuffer (octahedral normals), default lit pixels only, added into SceneColor.
//! Depth is read as an unfilterable float texture, as GLES allows.

use std::sync::Arc;

use crate::frame::{PassContext, Visualize};
use crate::gpu_types::formats;
use crate::pipelines::{Blend, ColorTarget, PipelineError, RenderPipeline, RenderState};

use super::{PassInit, Targets};

pub struct MobileDeferredShadingPass {
    pipeline: Arc<RenderPipeline>,
    groups: Vec<wgpu::BindGroup>,
}

impl MobileDeferredShadingPass {
    pub fn new(init: &PassInit<'_>) -> Result<MobileDeferredShadingPass, PipelineError> {
        let vs = init.permutation("ScreenVS", &[])?;
        let ps = init.permutation("MobileDeferredShadingPS", &[])?;
        let state = RenderState::fullscreen(ColorTarget { format: formats::SCENE_COLOR, blend: Blend::Additive });
        let pipeline = init.cache.render(&vs, Some(&ps), &state)?;
        let t = &init.shared.targets;
        let gbuffer = [
            ("SceneDepthTexture", wgpu::BindingResource::TextureView(&t.scene_depth.view)),
            ("GBufferATexture", wgpu::BindingResource::TextureView(&t.gbuffer_a.view)),
            ("GBufferBTexture", wgpu::BindingResource::TextureView(&t.gbuffer_b.view)),
            ("GBufferCTexture", wgpu::BindingResource::TextureView(&t.gbuffer_c.view)),
        ];
        let layout = &pipeline.layout;
        let groups = vec![
            layout.bind_group(init.device, 0, "MobileDeferredShading view", &init.shared.view_resources())?,
            layout.bind_group(init.device, 1, "MobileDeferredShading gbuffer", &gbuffer)?,
        ];
        Ok(MobileDeferredShadingPass { pipeline, groups })
    }

    /// Reads SceneDepth, GBufferA/B/C and the shadow map; adds into SceneColor.
    pub fn record(&self, ctx: &mut PassContext<'_>, t: &Targets) {
        {
            ctx.render_pass(&wgpu::RenderPassDescriptor {
                label: Some("MobileDeferredShading"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: &t.scene_color.view,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations { load: wgpu::LoadOp::Load, store: wgpu::StoreOp::Store },
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
        ctx.output(&t.scene_color.texture, Visualize::Hdr);
    }
}
