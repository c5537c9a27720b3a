//! Depth-only passes: PrePass (the camera's reverse-Z depth of opaque and masked meshes) and
//! ShadowDepths (the directional light's shadow map, depth only, no fragment shader for
//! opaque meshes). Both use `DepthOnlyVS`, with the view uniforms of their viewpoint;
//! masked materials add `DepthOnlyPS` to clip.

use crate::frame::{PassContext, Visualize};
use crate::pipelines::{DepthState, PipelineError, RenderState};
use crate::scene::BlendMode;

use super::{MaterialDraw, PassInit, Target};

/// Which viewpoint a depth pass renders from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DepthView {
    /// The camera: PrePass.
    Camera,
    /// The directional light: ShadowDepths.
    Sun,
}

pub struct DepthPass {
    view: DepthView,
    /// (object index, draw) for every object the pass draws.
    draws: Vec<(usize, MaterialDraw)>,
}

impl DepthPass {
    pub fn new(init: &PassInit<'_>, view: DepthView) -> Result<DepthPass, PipelineError> {
        let vs = init.permutation("DepthOnlyVS", &[])?;
        let masked_ps = init.permutation("DepthOnlyPS", &[])?;
        let mut depth = DepthState::reverse_z(crate::gpu_types::formats::SCENE_DEPTH, true);
        let view_buffer = match view {
            DepthView::Camera => &init.shared.view,
            DepthView::Sun => {
                // Reverse-Z: a negative bias pushes stored depth away from the light (no acne).
                depth.format = crate::gpu_types::formats::SHADOW_DEPTH;
                depth.bias = -2;
                depth.slope_scale_bits = (-2.0f32).to_bits();
                &init.shared.shadow_view
            }
        };
        let view_resources = [("View", view_buffer.as_entire_binding())];
        let mut draws = Vec::new();
        for (i, object) in init.gpu_scene.objects.iter().enumerate() {
            let material = init.gpu_scene.material(object);
            if material.blend == BlendMode::Translucent || (view == DepthView::Sun && !object.casts_shadow) {
                continue;
            }
            let masked = material.blend == BlendMode::Masked;
            // Shadows: both faces, so thin walls and open meshes still occlude.
            let cull = if view == DepthView::Sun || masked { None } else { Some(wgpu::Face::Back) };
            let state = RenderState::mesh().with_depth(depth).with_cull(cull);
            let ps = masked.then_some(masked_ps.as_str());
            let pipeline = init.cache.render(&vs, ps, &state)?;
            let buffer = &init.gpu_scene.materials[object.material].uniforms;
            draws.push((i, MaterialDraw::new(init.device, pipeline, &view_resources, Some(buffer))?));
        }
        Ok(DepthPass { view, draws })
    }

    /// Reads the scene's meshes; writes (clears) `depth`.
    pub fn record(&self, ctx: &mut PassContext<'_>, scene: &crate::scene::gpu::GpuScene, depth: &Target) {
        {
            let label = match self.view {
                DepthView::Camera => "PrePass",
                DepthView::Sun => "ShadowDepths",
            };
            ctx.render_pass(&wgpu::RenderPassDescriptor {
                label: Some(label),
                color_attachments: &[],
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    view: &depth.view,
                    depth_ops: Some(wgpu::Operations { load: wgpu::LoadOp::Clear(0.0), store: wgpu::StoreOp::Store }),
                    stencil_ops: None,
                }),
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            }, |pass| {
                for (i, draw) in &self.draws {
                    draw.bind(pass);
                    scene.draw(pass, &scene.objects[*i]);
                }
            });
        }
        ctx.output(&depth.texture, Visualize::Depth);
    }
}
