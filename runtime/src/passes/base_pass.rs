//! BasePass (desktop): opaque and masked meshes into the GBuffer (SceneColor with emissive
//! and sky light, GBufferA normals, GBufferB metallic/specular/roughness/shading model,
//! GBufferC base color and AO), depth-tested against the PrePass. And Translucency: the
//! translucent meshes forward lit over SceneColor, on desktop with `BasePassPS`, on mobile
//! with the forward `MobileBasePassPS`, then the particle sprites added.

use crate::frame::{PassContext, Visualize};
use crate::gpu_types::formats;
use crate::pipelines::{Blend, ColorTarget, DepthState, PipelineError, RenderState};
use crate::scene::gpu::GpuScene;
use crate::scene::BlendMode;

use super::mobile_base_pass::MobileBasePassOptions;
use super::particles::{ParticleSprites, ParticleSystem};
use super::{sky_clear, MaterialDraw, PassInit, Targets};

pub const GBUFFER_TARGETS: [ColorTarget; 4] = [
    ColorTarget { format: formats::SCENE_COLOR, blend: Blend::Replace },
    ColorTarget { format: formats::GBUFFER_A, blend: Blend::Replace },
    ColorTarget { format: formats::GBUFFER_B, blend: Blend::Replace },
    ColorTarget { format: formats::GBUFFER_C, blend: Blend::Replace },
];

pub struct BasePass {
    /// SceneColor is cleared to the sky; lights never touch pixels with no depth.
    sky: wgpu::Color,
    draws: Vec<(usize, MaterialDraw)>,
}

impl BasePass {
    pub fn new(init: &PassInit<'_>) -> Result<BasePass, PipelineError> {
        let vs = init.permutation("BasePassVS", &[])?;
        let view = init.shared.view_resources();
        let mut draws = Vec::new();
        for (i, object) in init.gpu_scene.objects.iter().enumerate() {
            let material = init.gpu_scene.material(object);
            if material.blend == BlendMode::Translucent {
                continue;
            }
            let ps = init.permutation("BasePassPS", &[("MATERIAL_BLEND_MODE", material.blend.label())])?;
            let cull = if material.blend == BlendMode::Masked { None } else { Some(wgpu::Face::Back) };
            let state = RenderState::mesh()
                .with_depth(DepthState::reverse_z(formats::SCENE_DEPTH, false))
                .with_targets(&GBUFFER_TARGETS)
                .with_cull(cull);
            let pipeline = init.cache.render(&vs, Some(&ps), &state)?;
            let buffer = &init.gpu_scene.materials[object.material].uniforms;
            draws.push((i, MaterialDraw::new(init.device, pipeline, &view, Some(buffer))?));
        }
        Ok(BasePass { draws, sky: sky_clear(init.scene) })
    }

    /// Reads SceneDepth (test only); writes SceneColor and GBufferA/B/C (cleared).
    pub fn record(&self, ctx: &mut PassContext<'_>, scene: &GpuScene, t: &Targets) {
        {
            fn clear(v: &wgpu::TextureView, color: wgpu::Color) -> Option<wgpu::RenderPassColorAttachment<'_>> {
                Some(wgpu::RenderPassColorAttachment {
                    view: v,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations { load: wgpu::LoadOp::Clear(color), store: wgpu::StoreOp::Store },
                })
            }
            let none = wgpu::Color::TRANSPARENT;
            ctx.render_pass(&wgpu::RenderPassDescriptor {
                label: Some("BasePass"),
                color_attachments: &[clear(&t.scene_color.view, self.sky), clear(&t.gbuffer_a.view, none), clear(&t.gbuffer_b.view, none), clear(&t.gbuffer_c.view, none)],
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    view: &t.scene_depth.view,
                    depth_ops: Some(wgpu::Operations { load: wgpu::LoadOp::Load, store: wgpu::StoreOp::Store }),
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
        ctx.output(&t.scene_color.texture, Visualize::Hdr);
        ctx.output_named("GBufferA", &t.gbuffer_a.texture, Visualize::Direct);
        ctx.output_named("GBufferB", &t.gbuffer_b.texture, Visualize::Direct);
        ctx.output_named("GBufferC", &t.gbuffer_c.texture, Visualize::Direct);
    }
}

/// Which shaders light the translucent meshes.
#[derive(Clone, Copy, Debug)]
pub enum TranslucencyShading {
    /// `BasePassVS` + `BasePassPS{MATERIAL_BLEND_MODE=TRANSLUCENT}` (sm5).
    Desktop,
    /// The forward mobile base pass (es3_1) with these options.
    Mobile(MobileBasePassOptions),
}

pub struct TranslucencyPass {
    draws: Vec<(usize, MaterialDraw)>,
    /// Particle sprites, added after the translucent meshes.
    sprites: Vec<ParticleSprites>,
}

impl TranslucencyPass {
    /// `particles`: systems whose sprites this pass draws (the desktop frame's).
    pub fn new(init: &PassInit<'_>, shading: TranslucencyShading, particles: &[ParticleSystem]) -> Result<TranslucencyPass, PipelineError> {
        let view = init.shared.view_resources();
        let mut draws = Vec::new();
        for (i, object) in init.gpu_scene.objects.iter().enumerate() {
            let material = init.gpu_scene.material(object);
            if material.blend != BlendMode::Translucent {
                continue;
            }
            let (vs, ps) = match shading {
                TranslucencyShading::Desktop => {
                    (init.permutation("BasePassVS", &[])?, init.permutation("BasePassPS", &[("MATERIAL_BLEND_MODE", "TRANSLUCENT")])?)
                }
                TranslucencyShading::Mobile(options) => {
                    let forward = MobileBasePassOptions { deferred: false, ..options };
                    forward.permutations(init, material)?
                }
            };
            let state = RenderState::mesh()
                .with_depth(DepthState::reverse_z(formats::SCENE_DEPTH, false))
                .with_targets(&[ColorTarget { format: formats::SCENE_COLOR, blend: Blend::PremultipliedAlpha }])
                .with_cull(None);
            let pipeline = init.cache.render(&vs, Some(&ps), &state)?;
            let buffer = &init.gpu_scene.materials[object.material].uniforms;
            draws.push((i, MaterialDraw::new(init.device, pipeline, &view, Some(buffer))?));
        }
        let sprites = particles.iter().map(|p| ParticleSprites::new(init, p, true)).collect::<Result<_, _>>()?;
        Ok(TranslucencyPass { draws, sprites })
    }

    /// Reads SceneDepth (test only) and the shadow map; blends over SceneColor.
    pub fn record(&self, ctx: &mut PassContext<'_>, scene: &GpuScene, t: &Targets) {
        {
            ctx.render_pass(&wgpu::RenderPassDescriptor {
                label: Some("Translucency"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: &t.scene_color.view,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations { load: wgpu::LoadOp::Load, store: wgpu::StoreOp::Store },
                })],
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    view: &t.scene_depth.view,
                    depth_ops: Some(wgpu::Operations { load: wgpu::LoadOp::Load, store: wgpu::StoreOp::Store }),
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
                for s in &self.sprites {
                    s.draw(pass);
                }
            });
        }
        ctx.output(&t.scene_color.texture, Visualize::Hdr);
    }
}
