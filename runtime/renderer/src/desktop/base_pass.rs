//! BasePass: the GBuffer. The sky first (over the pixels the prepass left at the far plane),
//! then opaque and masked meshes with the depth test against the prepass (GreaterEqual, no
//! depth write); lit materials set the stencil bit the lighting passes test.
//!   SceneColor  emissive + indirect (sky) light
//!   GBufferA    world normal, RGB10A2
//!   GBufferB    metallic, specular, roughness, shading model
//!   GBufferC    base color, ambient occlusion

use std::sync::Arc;

use crate::frame::{replace, PassContext, PassDecl, PipelineDesc, RenderSlot, VertexInput, Visualize};
use crate::keys;
use crate::scene::BlendMode;

use super::pipelines::{BindGroups, DesktopLayout};
use super::resources::{begin, color_attachment, formats, SceneBuffers, Targets, STENCIL_LIT};
use super::{DesktopError, PassSetup};

/// Tests against the prepass depth and marks lit pixels in its stencil.
pub const PASS: PassDecl = PassDecl {
    name: "BasePass",
    reads: &["Scene", "View", "SceneDepth"],
    writes: &["SceneColor", "GBufferA", "GBufferB", "GBufferC", "SceneDepth"],
};

struct Variant {
    blend: BlendMode,
    unlit: bool,
    pipeline: Arc<RenderSlot>,
    groups: BindGroups,
}

pub struct BasePass {
    sky: Arc<RenderSlot>,
    sky_groups: BindGroups,
    variants: Vec<Variant>,
}

fn gbuffer_targets() -> Vec<wgpu::ColorTargetState> {
    [formats::SCENE_COLOR, formats::GBUFFER_A, formats::GBUFFER_B, formats::GBUFFER_C].map(replace).to_vec()
}

impl BasePass {
    pub fn new(b: &PassSetup<'_>) -> Result<BasePass, DesktopError> {
        let p = b.pipelines;
        let depth = |mark: bool, compare: wgpu::CompareFunction| {
            let op = if mark { wgpu::StencilOperation::Replace } else { wgpu::StencilOperation::Keep };
            let face = wgpu::StencilFaceState {
                compare: wgpu::CompareFunction::Always,
                fail_op: wgpu::StencilOperation::Keep,
                depth_fail_op: wgpu::StencilOperation::Keep,
                pass_op: op,
            };
            Some(wgpu::DepthStencilState {
                format: b.targets.scene_depth.format,
                depth_write_enabled: Some(false),
                depth_compare: Some(compare),
                stencil: wgpu::StencilState {
                    front: face,
                    back: face,
                    read_mask: STENCIL_LIT,
                    write_mask: if mark { STENCIL_LIT } else { 0 },
                },
                bias: wgpu::DepthBiasState::default(),
            })
        };
        let resources = b.scene_resources();
        let sky = p.render(&PipelineDesc {
            cull_mode: None,
            depth_stencil: depth(false, wgpu::CompareFunction::GreaterEqual),
            targets: gbuffer_targets(),
            ..PipelineDesc::new(
                &keys::name(keys::post_process_vs::Key {}, p.key_level()?)?,
                Some(&keys::name(keys::sky_pass_ps::Key {}, p.key_level()?)?),
                VertexInput::None,
            )
        })?;
        let sky_groups = sky.layout.bind_groups(b.device, &resources)?;
        let vs = keys::name(keys::deferred_base_pass_vs::Key {}, p.key_level()?)?;
        let mut variants = Vec::new();
        for blend in [BlendMode::Opaque, BlendMode::Masked] {
            for unlit in [false, true] {
                if !b.buffers.draws.iter().any(|d| d.blend == blend && d.unlit == unlit) {
                    continue;
                }
                use keys::deferred_base_pass_ps::{
                    Key, MaterialBlendMode, MaterialShadingmodel, TranslucencyLightingMode,
                };
                let key = Key {
                    material_blend_mode: match blend {
                        BlendMode::Opaque => MaterialBlendMode::Opaque,
                        BlendMode::Masked => MaterialBlendMode::Masked,
                        BlendMode::Translucent => MaterialBlendMode::Translucent,
                    },
                    material_shadingmodel: if unlit {
                        MaterialShadingmodel::Unlit
                    } else {
                        MaterialShadingmodel::DefaultLit
                    },
                    translucency_lighting_mode: TranslucencyLightingMode::SurfaceForwardShading,
                };
                let ps = keys::name(key, p.key_level()?)?;
                let pipeline = p.render(&PipelineDesc {
                    cull_mode: if blend == BlendMode::Masked { None } else { Some(wgpu::Face::Back) },
                    depth_stencil: depth(!unlit, wgpu::CompareFunction::GreaterEqual),
                    targets: gbuffer_targets(),
                    ..PipelineDesc::new(&vs, Some(&ps), VertexInput::Mesh)
                })?;
                let groups = pipeline.layout.bind_groups(b.device, &resources)?;
                variants.push(Variant { blend, unlit, pipeline, groups });
            }
        }
        Ok(BasePass { sky, sky_groups, variants })
    }

    pub fn record(&self, ctx: &mut PassContext<'_>, scene: &SceneBuffers, t: &Targets) {
        let pl = ctx.pipelines();
        {
            let clear = Some(wgpu::Color::TRANSPARENT);
            let mut pass = begin(
                ctx,
                "BasePass",
                &[
                    color_attachment(&t.scene_color.view, Some(wgpu::Color::BLACK)),
                    color_attachment(&t.gbuffer_a.view, clear),
                    color_attachment(&t.gbuffer_b.view, clear),
                    color_attachment(&t.gbuffer_c.view, clear),
                ],
                Some(wgpu::RenderPassDepthStencilAttachment {
                    view: &t.scene_depth.attachment,
                    depth_ops: Some(wgpu::Operations { load: wgpu::LoadOp::Load, store: wgpu::StoreOp::Store }),
                    stencil_ops: Some(wgpu::Operations { load: wgpu::LoadOp::Load, store: wgpu::StoreOp::Store }),
                }),
            );
            pass.set_stencil_reference(STENCIL_LIT);
            // The skydome first, as Unreal does; the prepass keeps it from overdrawing.
            if let Some(p) = self.sky.ready(pl) {
                pass.set_pipeline(&p.pipeline);
                self.sky_groups.set_render(&mut pass);
                pass.draw(0..3, 0..1);
            }
            for v in &self.variants {
                let Some(p) = v.pipeline.ready(pl) else { continue };
                pass.set_pipeline(&p.pipeline);
                v.groups.set_render(&mut pass);
                for draw in scene.draws.iter().filter(|d| d.blend == v.blend && d.unlit == v.unlit) {
                    scene.draw(&mut pass, draw);
                }
            }
        }
        ctx.output(&t.scene_color.texture, Visualize::Hdr);
        ctx.output_named("GBufferA", &t.gbuffer_a.texture, Visualize::Direct);
        ctx.output_named("GBufferB", &t.gbuffer_b.texture, Visualize::Direct);
        ctx.output_named("GBufferC", &t.gbuffer_c.texture, Visualize::Direct);
    }
}
