//! BasePass (mobile, es3_1): opaque and masked meshes, depth written here (no full prepass).
//! Forward: lit in the pixel shader by the directional light with its shadow, up to
//! `MAX_DYNAMIC_POINT_LIGHTS` local lights and the sky, fogged per vertex. Deferred
//! (`DEFERRED_SHADING_PATH`): into the mobile GBuffer, lit by MobileDeferredShading.

use crate::frame::{PassContext, Visualize};
use crate::gpu_types::formats;
use crate::pipelines::{Blend, ColorTarget, DepthState, PipelineError, RenderState};
use crate::scene::gpu::GpuScene;
use crate::scene::{BlendMode, Material};

use super::base_pass::GBUFFER_TARGETS;
use super::{sky_clear, MaterialDraw, PassInit, Targets};

/// The mobile base pass's permutation choices.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MobileBasePassOptions {
    pub deferred: bool,
    /// `USE_VERTEX_FOG` (forward only; packs interpolants).
    pub vertex_fog: bool,
    /// `MAX_DYNAMIC_POINT_LIGHTS` (forward only): 0, 1, 2 or 4.
    pub max_dynamic_point_lights: u32,
}

impl MobileBasePassOptions {
    pub fn forward() -> MobileBasePassOptions {
        MobileBasePassOptions { deferred: false, vertex_fog: true, max_dynamic_point_lights: 4 }
    }

    pub fn deferred() -> MobileBasePassOptions {
        MobileBasePassOptions { deferred: true, vertex_fog: false, max_dynamic_point_lights: 0 }
    }

    /// (vertex, pixel) permutation names for a material.
    pub fn permutations(&self, init: &PassInit<'_>, material: &Material) -> Result<(String, String), PipelineError> {
        let fog = u32::from(self.vertex_fog && !self.deferred).to_string();
        let lights = if self.deferred { 0 } else { self.max_dynamic_point_lights }.to_string();
        let vs = init.permutation("MobileBasePassVS", &[("USE_VERTEX_FOG", &fog)])?;
        let ps = init.permutation(
            "MobileBasePassPS",
            &[
                ("FULLY_ROUGH", if material.fully_rough { "1" } else { "0" }),
                ("MAX_DYNAMIC_POINT_LIGHTS", &lights),
                ("USE_VERTEX_FOG", &fog),
                ("DEFERRED_SHADING_PATH", if self.deferred { "1" } else { "0" }),
                ("MATERIAL_BLEND_MODE", material.blend.label()),
            ],
        )?;
        Ok((vs, ps))
    }
}

pub struct MobileBasePass {
    /// SceneColor is cleared to the sky; lights never touch pixels with no depth.
    sky: wgpu::Color,
    options: MobileBasePassOptions,
    draws: Vec<(usize, MaterialDraw)>,
}

impl MobileBasePass {
    pub fn new(init: &PassInit<'_>, options: MobileBasePassOptions) -> Result<MobileBasePass, PipelineError> {
        let view = init.shared.view_resources();
        let forward_target = [ColorTarget { format: formats::SCENE_COLOR, blend: Blend::Replace }];
        let targets: &[ColorTarget] = if options.deferred { &GBUFFER_TARGETS } else { &forward_target };
        let mut draws = Vec::new();
        for (i, object) in init.gpu_scene.objects.iter().enumerate() {
            let material = init.gpu_scene.material(object);
            if material.blend == BlendMode::Translucent {
                continue;
            }
            let (vs, ps) = options.permutations(init, material)?;
            let cull = if material.blend == BlendMode::Masked { None } else { Some(wgpu::Face::Back) };
            let state = RenderState::mesh()
                .with_depth(DepthState::reverse_z(formats::SCENE_DEPTH, true))
                .with_targets(targets)
                .with_cull(cull);
            let pipeline = init.cache.render(&vs, Some(&ps), &state)?;
            let buffer = &init.gpu_scene.materials[object.material].uniforms;
            draws.push((i, MaterialDraw::new(init.device, pipeline, &view, Some(buffer))?));
        }
        Ok(MobileBasePass { options, draws, sky: sky_clear(init.scene) })
    }

    /// Reads the shadow map and local lights (forward); writes SceneDepth and SceneColor,
    /// and GBufferA/B/C when deferred.
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
            let color: Vec<_> = if self.options.deferred {
                vec![clear(&t.scene_color.view, self.sky), clear(&t.gbuffer_a.view, none), clear(&t.gbuffer_b.view, none), clear(&t.gbuffer_c.view, none)]
            } else {
                vec![clear(&t.scene_color.view, self.sky)]
            };
            ctx.render_pass(&wgpu::RenderPassDescriptor {
                label: Some("BasePass"),
                color_attachments: &color,
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    view: &t.scene_depth.view,
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
        ctx.output(&t.scene_color.texture, Visualize::Hdr);
        ctx.output_named("SceneDepth", &t.scene_depth.texture, Visualize::Depth);
        if self.options.deferred {
            ctx.output_named("GBufferA", &t.gbuffer_a.texture, Visualize::Direct);
            ctx.output_named("GBufferB", &t.gbuffer_b.texture, Visualize::Direct);
            ctx.output_named("GBufferC", &t.gbuffer_c.texture, Visualize::Direct);
        }
    }
}
