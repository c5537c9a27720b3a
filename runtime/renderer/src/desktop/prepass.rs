//! PrePass: opaque and masked meshes into the reverse-Z scene depth (near = 1, far = 0,
//! cleared to 0, depth test Greater). Opaque meshes have no pixel shader; masked ones clip
//! with `DepthPassPS`. Instanced pairs are one draw call each.

use std::sync::Arc;

use crate::frame::{PassContext, PassDecl, Visualize};
use crate::keys;
use crate::scene::BlendMode;

use super::pipelines::{BindGroups, Render, RenderDesc, Vertices};
use super::resources::{begin, SceneBuffers, Targets};
use super::{DesktopError, PassSetup};

/// The PrePass declaration.
pub const PASS: PassDecl = PassDecl { name: "PrePass", reads: &["Scene", "View"], writes: &["SceneDepth"] };

pub struct PrePass {
    opaque: Arc<Render>,
    masked: Arc<Render>,
    opaque_groups: BindGroups,
    masked_groups: BindGroups,
}

impl PrePass {
    pub fn new(b: &PassSetup<'_>) -> Result<PrePass, DesktopError> {
        let p = b.pipelines;
        let desc = RenderDesc {
            vertices: Vertices::Mesh,
            cull: Some(wgpu::Face::Back),
            depth_stencil: Some(wgpu::DepthStencilState {
                format: b.targets.scene_depth.format,
                depth_write_enabled: Some(true),
                depth_compare: Some(wgpu::CompareFunction::Greater),
                stencil: wgpu::StencilState::default(),
                bias: wgpu::DepthBiasState::default(),
            }),
            targets: Vec::new(),
        };
        let opaque =
            p.render(&keys::name(keys::depth_pass_vs::Key { material_masked: false }, p.key_level()?)?, None, &desc)?;
        let masked_desc = RenderDesc { cull: None, ..desc };
        let masked = p.render(
            &keys::name(keys::depth_pass_vs::Key { material_masked: true }, p.key_level()?)?,
            Some(&keys::name(keys::depth_pass_ps::Key {}, p.key_level()?)?),
            &masked_desc,
        )?;
        let resources = b.scene_resources();
        Ok(PrePass {
            opaque_groups: opaque.layout.bind_groups(b.device, &resources)?,
            masked_groups: masked.layout.bind_groups(b.device, &resources)?,
            opaque,
            masked,
        })
    }

    pub fn record(&self, ctx: &mut PassContext<'_>, scene: &SceneBuffers, targets: &Targets) {
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
                pass.set_pipeline(&pipeline.pipeline);
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
