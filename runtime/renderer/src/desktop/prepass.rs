//! PrePass: opaque and masked meshes into the reverse-Z scene depth (near = 1, far = 0,
//! cleared to 0, depth test Greater). Opaque meshes have no pixel shader; masked ones clip
//! with `DepthPassPS`. Instanced pairs are one draw call each.

use std::sync::Arc;

use crate::frame::{PassContext, PassDecl, PipelineDesc, RenderSlot, VertexInput, Visualize};
use crate::keys;
use crate::scene::BlendMode;

use super::pipelines::{BindGroups, DesktopLayout};
use super::resources::{begin, SceneBuffers, Targets};
use super::{DesktopError, PassSetup};

/// The PrePass declaration.
pub const PASS: PassDecl = PassDecl { name: "PrePass", reads: &["Scene", "View"], writes: &["SceneDepth"] };

pub struct PrePass {
    opaque: Arc<RenderSlot>,
    masked: Arc<RenderSlot>,
    opaque_groups: BindGroups,
    masked_groups: BindGroups,
}

impl PrePass {
    pub fn new(b: &PassSetup<'_>) -> Result<PrePass, DesktopError> {
        let p = b.pipelines;
        let opaque_vs = keys::name(keys::depth_pass_vs::Key { material_masked: false }, p.key_level()?)?;
        let desc = PipelineDesc {
            cull_mode: Some(wgpu::Face::Back),
            depth_stencil: Some(wgpu::DepthStencilState {
                format: b.targets.scene_depth.format,
                depth_write_enabled: Some(true),
                depth_compare: Some(wgpu::CompareFunction::Greater),
                stencil: wgpu::StencilState::default(),
                bias: wgpu::DepthBiasState::default(),
            }),
            ..PipelineDesc::new(&opaque_vs, None, VertexInput::Mesh)
        };
        let opaque = p.render(&desc)?;
        let masked = p.render(&PipelineDesc {
            vertex: keys::name(keys::depth_pass_vs::Key { material_masked: true }, p.key_level()?)?,
            fragment: Some(keys::name(keys::depth_pass_ps::Key {}, p.key_level()?)?),
            cull_mode: None,
            ..desc
        })?;
        let resources = b.scene_resources();
        Ok(PrePass {
            opaque_groups: opaque.layout.bind_groups(b.device, &resources)?,
            masked_groups: masked.layout.bind_groups(b.device, &resources)?,
            opaque,
            masked,
        })
    }

    pub fn record(&self, ctx: &mut PassContext<'_>, scene: &SceneBuffers, targets: &Targets) {
        let pl = ctx.pipelines();
        {
            let mut pass = begin(
                ctx,
                "PrePass",
                &[],
                Some(wgpu::RenderPassDepthStencilAttachment {
                    view: &targets.scene_depth.attachment,
                    depth_ops: Some(wgpu::Operations { load: wgpu::LoadOp::Clear(0.0), store: wgpu::StoreOp::Store }),
                    stencil_ops: Some(wgpu::Operations { load: wgpu::LoadOp::Clear(0), store: wgpu::StoreOp::Store }),
                }),
            );
            for (blend, pipeline, groups) in [
                (BlendMode::Opaque, &self.opaque, &self.opaque_groups),
                (BlendMode::Masked, &self.masked, &self.masked_groups),
            ] {
                let Some(p) = pipeline.ready(pl) else { continue };
                pass.set_pipeline(&p.pipeline);
                groups.set_render(&mut pass);
                for draw in scene.draws.iter().filter(|d| d.blend == blend) {
                    pass.insert_debug_marker(&draw.name);
                    scene.draw(&mut pass, draw);
                }
            }
        }
        ctx.output(&targets.scene_depth.texture, Visualize::Depth);
    }
}
