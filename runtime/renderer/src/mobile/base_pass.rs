//! PrePass (the optional full depth prepass) and BasePass.
//!
//! BasePass draws opaque and masked meshes with `MobileBasePassVS` / `MobileBasePassPS`, and
//! then the sky where no mesh wrote depth. Forward: the pixel shader lights the pixel
//! (directional light with CSM, local lights, reflections, sky light, vertex fog) into the
//! (multisampled) SceneColor. Deferred: it writes SceneColor and GBufferA/B/C, and the
//! shading model into the stencil for MobileDeferredShading.

use crate::gpu::BufferInit;
use glam::Vec4;

use crate::frame::{replace, untouched, FramePipelines, PassContext, PassDecl, PipelineDesc, VertexInput, Visualize};
use crate::keys;
use crate::pipelines::PipelineError;
use crate::scene::gpu::GpuScene;
use crate::scene::BlendMode;

use super::pipeline::{Draw, MobilePipelines};
use super::shadows::DepthPassUniforms;
use super::{
    MobileOptions, MobileTargets, ShadingPath, SharedResources, DEFERRED_DEPTH_FORMAT, FORWARD_DEPTH_FORMAT,
    GBUFFER_A_FORMAT, GBUFFER_B_FORMAT, GBUFFER_C_FORMAT, LDR_COLOR_FORMAT, SCENE_COLOR_FORMAT, STENCIL_DEFAULT_LIT,
    STENCIL_SHADING_MODEL_MASK,
};

/// The optional full depth prepass.
pub const PREPASS: PassDecl = PassDecl { name: "PrePass", reads: &["Scene", "View"], writes: &["SceneDepth"] };

/// The forward BasePass: lit in the pixel shader (shadow atlas, reflection captures).
pub const FORWARD_PASS: PassDecl = PassDecl {
    name: "BasePass",
    reads: &["Scene", "View", "ShadowAtlas", "ReflectionCaptures"],
    writes: &["SceneColor", "SceneDepth"],
};

/// The deferred BasePass: SceneColor (emissive, sky) and the mobile GBuffer, the shading model in the stencil.
pub const DEFERRED_PASS: PassDecl = PassDecl {
    name: "BasePass",
    reads: &["Scene", "View", "ShadowAtlas", "ReflectionCaptures"],
    writes: &["SceneColor", "GBufferA", "GBufferB", "GBufferC", "SceneDepth"],
};

/// The level of every mobile permutation.
const LEVEL: keys::Level = keys::Level::Es31;

/// The color targets of the base pass: SceneColor, and the GBuffer when deferred.
pub(super) fn base_pass_formats(options: &MobileOptions) -> Vec<wgpu::TextureFormat> {
    match options.path {
        ShadingPath::Forward => vec![if options.hdr { SCENE_COLOR_FORMAT } else { LDR_COLOR_FORMAT }],
        ShadingPath::Deferred => vec![SCENE_COLOR_FORMAT, GBUFFER_A_FORMAT, GBUFFER_B_FORMAT, GBUFFER_C_FORMAT],
    }
}

pub(super) fn depth_format(options: &MobileOptions) -> wgpu::TextureFormat {
    match options.path {
        ShadingPath::Forward => FORWARD_DEPTH_FORMAT,
        ShadingPath::Deferred => DEFERRED_DEPTH_FORMAT,
    }
}

/// The `MobileBasePassPS` permutation of a material. `forward_lit`: shade in the pixel
/// shader (forward, and translucency in both paths).
pub(super) fn base_pass_ps(
    options: &MobileOptions,
    material: &crate::scene::Material,
    forward_lit: bool,
    csm: bool,
) -> Result<String, PipelineError> {
    use keys::mobile_base_pass_ps::{Key, MaterialBlendMode};
    let fully_rough = material.fully_rough;
    let material_blend_mode = match material.blend {
        BlendMode::Opaque => MaterialBlendMode::Opaque,
        BlendMode::Masked => MaterialBlendMode::Masked,
        BlendMode::Translucent => MaterialBlendMode::Translucent,
    };
    let key = if forward_lit {
        Key {
            fully_rough,
            max_dynamic_point_lights: i64::from(options.max_dynamic_point_lights),
            use_vertex_fog: options.vertex_fog,
            deferred_shading_path: false,
            directional_light_csm: csm,
            hq_reflections: options.reflections && options.hq_reflections && !fully_rough && options.hdr,
            enable_sky_light: options.sky_light,
            output_gamma_space: !options.hdr,
            material_blend_mode,
        }
    } else {
        Key {
            fully_rough,
            max_dynamic_point_lights: 0,
            use_vertex_fog: false,
            deferred_shading_path: true,
            directional_light_csm: false,
            hq_reflections: false,
            enable_sky_light: false,
            output_gamma_space: false,
            material_blend_mode,
        }
    };
    Ok(keys::name(key, LEVEL)?)
}

pub(super) fn base_pass_vs(vertex_fog: bool) -> Result<String, PipelineError> {
    Ok(keys::name(keys::mobile_base_pass_vs::Key { use_vertex_fog: vertex_fog }, LEVEL)?)
}

/// The full depth prepass: opaque (not masked) meshes, depth only.
pub struct PrePass {
    draw: Draw,
    objects: Vec<usize>,
    _uniforms: wgpu::Buffer,
}

impl PrePass {
    pub fn new(
        pipelines: &MobilePipelines<'_>,
        scene: &GpuScene,
        options: &MobileOptions,
        targets: &MobileTargets,
        shared: &SharedResources,
    ) -> Result<PrePass, PipelineError> {
        let vs = keys::name(keys::mobile_pre_pass_vs::Key {}, LEVEL)?;
        let mut desc = PipelineDesc::new(&vs, None, VertexInput::MeshInstanced);
        desc.cull_mode = Some(wgpu::Face::Back);
        desc.sample_count = targets.samples;
        desc.depth_stencil = Some(wgpu::DepthStencilState {
            format: depth_format(options),
            depth_write_enabled: Some(true),
            depth_compare: Some(wgpu::CompareFunction::GreaterEqual),
            stencil: Default::default(),
            bias: Default::default(),
        });
        let pipeline = pipelines.get(&desc)?;
        let u = DepthPassUniforms { view_proj: shared.view_proj, params: Vec4::ZERO };
        let buffer = pipelines.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("PrePass view"),
            contents: bytemuck::bytes_of(&u),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let draw = Draw::new(pipelines.device, pipeline, &[("Pass", buffer.as_entire_binding())])?;
        let objects = scene
            .objects
            .iter()
            .enumerate()
            .filter(|(_, o)| scene.material(o).blend == BlendMode::Opaque)
            .map(|(i, _)| i)
            .collect();
        Ok(PrePass { draw, objects, _uniforms: buffer })
    }

    pub fn record(&self, ctx: &mut PassContext<'_>, scene: &GpuScene, targets: &MobileTargets) {
        let stencil = targets.scene_depth.texture.format().has_stencil_aspect();
        let pl = ctx.pipelines();
        {
            ctx.render_pass(
                &wgpu::RenderPassDescriptor {
                    label: Some("PrePass"),
                    color_attachments: &[],
                    depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                        view: &targets.scene_depth.view,
                        depth_ops: Some(wgpu::Operations {
                            load: wgpu::LoadOp::Clear(0.0),
                            store: wgpu::StoreOp::Store,
                        }),
                        stencil_ops: stencil
                            .then_some(wgpu::Operations { load: wgpu::LoadOp::Clear(0), store: wgpu::StoreOp::Store }),
                    }),
                    timestamp_writes: None,
                    occlusion_query_set: None,
                    multiview_mask: None,
                },
                |pass| {
                    if self.draw.bind(pl, pass) {
                        for &i in &self.objects {
                            scene.draw(pass, &scene.objects[i]);
                        }
                    }
                },
            );
        }
        if targets.samples == 1 && !stencil {
            ctx.output(&targets.scene_depth.texture, Visualize::Depth);
        }
    }
}

struct ObjectDraw {
    object: usize,
    draw: Draw,
    stencil_ref: u32,
}

/// The base pass of either path.
pub struct BasePass {
    path: ShadingPath,
    hdr: bool,
    objects: Vec<ObjectDraw>,
    sky: Draw,
}

impl BasePass {
    pub fn new(
        pipelines: &MobilePipelines<'_>,
        scene: &GpuScene,
        options: &MobileOptions,
        targets: &MobileTargets,
        shared: &SharedResources,
    ) -> Result<BasePass, PipelineError> {
        let forward = options.path == ShadingPath::Forward;
        let formats = base_pass_formats(options);
        let csm = shared.cascades > 0;
        let vs = base_pass_vs(forward && options.vertex_fog)?;
        let deferred_stencil = wgpu::StencilFaceState {
            compare: wgpu::CompareFunction::Always,
            fail_op: wgpu::StencilOperation::Keep,
            depth_fail_op: wgpu::StencilOperation::Keep,
            pass_op: wgpu::StencilOperation::Replace,
        };
        let depth_stencil = |write: bool, stencil_write: bool| wgpu::DepthStencilState {
            format: depth_format(options),
            depth_write_enabled: Some(write),
            depth_compare: Some(wgpu::CompareFunction::GreaterEqual),
            stencil: if forward || !stencil_write {
                wgpu::StencilState::default()
            } else {
                wgpu::StencilState {
                    front: deferred_stencil,
                    back: deferred_stencil,
                    read_mask: 0xff,
                    write_mask: STENCIL_SHADING_MODEL_MASK,
                }
            },
            bias: Default::default(),
        };
        let view = shared.view_resources(targets);
        let mut objects = Vec::new();
        for (i, object) in scene.objects.iter().enumerate() {
            let material = scene.material(object);
            if material.blend == BlendMode::Translucent {
                continue;
            }
            let ps = base_pass_ps(options, material, forward, csm)?;
            let mut desc = PipelineDesc::new(&vs, Some(&ps), VertexInput::MeshInstanced);
            desc.cull_mode = if material.blend == BlendMode::Masked { None } else { Some(wgpu::Face::Back) };
            desc.depth_stencil = Some(depth_stencil(true, true));
            desc.targets = formats.iter().map(|f| replace(*f)).collect();
            desc.sample_count = targets.samples;
            let pipeline = pipelines.get(&desc)?;
            let mut resources = view.clone();
            resources.push(("Material", scene.materials[object.material].uniforms.as_entire_binding()));
            let draw = Draw::new(pipelines.device, pipeline.clone(), &resources)?;
            objects.push(ObjectDraw {
                object: i,
                draw,
                stencil_ref: if material.unlit { 0 } else { STENCIL_DEFAULT_LIT },
            });
        }
        let sky_vs = keys::name(keys::mobile_sky_vs::Key {}, LEVEL)?;
        let sky_ps = keys::name(keys::mobile_sky_ps::Key { output_gamma_space: !options.hdr }, LEVEL)?;
        let mut desc = PipelineDesc::new(&sky_vs, Some(&sky_ps), VertexInput::None);
        desc.depth_stencil = Some(depth_stencil(false, false));
        desc.targets =
            formats.iter().enumerate().map(|(i, f)| if i == 0 { replace(*f) } else { untouched(*f) }).collect();
        desc.sample_count = targets.samples;
        let sky_pipeline = pipelines.get(&desc)?;
        let sky = Draw::new(pipelines.device, sky_pipeline, &view)?;
        Ok(BasePass { path: options.path, hdr: options.hdr, objects, sky })
    }

    /// Writes SceneColor (and GBufferA/B/C, depth, stencil when deferred). `prepass`: depth
    /// is already there. `keep_for_translucency`: the multisampled color and the depth are
    /// stored for the Translucency pass; otherwise the MSAA color resolves here and nothing
    /// multisampled is stored.
    pub fn record(
        &self,
        ctx: &mut PassContext<'_>,
        scene: &GpuScene,
        targets: &MobileTargets,
        prepass: bool,
        keep_for_translucency: bool,
    ) {
        let deferred = self.path == ShadingPath::Deferred;
        let colors = Self::color_attachments(targets, deferred, keep_for_translucency);
        let depth_load = if prepass { wgpu::LoadOp::Load } else { wgpu::LoadOp::Clear(0.0) };
        let depth_store = if deferred || keep_for_translucency { wgpu::StoreOp::Store } else { wgpu::StoreOp::Discard };
        let pl = ctx.pipelines();
        {
            ctx.render_pass(
                &wgpu::RenderPassDescriptor {
                    label: Some("BasePass"),
                    color_attachments: &colors,
                    depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                        view: &targets.scene_depth.view,
                        depth_ops: Some(wgpu::Operations { load: depth_load, store: depth_store }),
                        stencil_ops: deferred.then_some(wgpu::Operations {
                            load: if prepass { wgpu::LoadOp::Load } else { wgpu::LoadOp::Clear(0) },
                            store: wgpu::StoreOp::Store,
                        }),
                    }),
                    timestamp_writes: None,
                    occlusion_query_set: None,
                    multiview_mask: None,
                },
                |pass| self.draw(pl, pass, scene, deferred),
            );
        }
        let vis = if self.hdr { Visualize::Hdr } else { Visualize::Direct };
        ctx.output(&targets.scene_color.texture, vis);
        // Forward depth survives the pass only when Translucency needs it, and only a
        // single-sampled one can be read back.
        if !deferred && targets.samples == 1 && depth_store == wgpu::StoreOp::Store {
            ctx.output_named("SceneDepth", &targets.scene_depth.texture, Visualize::Depth);
        }
        if deferred {
            for g in [&targets.gbuffer_a, &targets.gbuffer_b, &targets.gbuffer_c].into_iter().flatten() {
                ctx.output_named(g.name, &g.texture, Visualize::Direct);
            }
        }
    }

    /// SceneColor (resolved here unless Translucency needs the samples) and, deferred, the
    /// GBuffer.
    fn color_attachments(
        targets: &MobileTargets,
        deferred: bool,
        keep_for_translucency: bool,
    ) -> Vec<Option<wgpu::RenderPassColorAttachment<'_>>> {
        let clear = wgpu::Color::BLACK;
        let color_store = if targets.scene_color_msaa.is_some() && !keep_for_translucency {
            wgpu::StoreOp::Discard
        } else {
            wgpu::StoreOp::Store
        };
        let mut colors = vec![Some(wgpu::RenderPassColorAttachment {
            view: &targets.color_attachment().view,
            depth_slice: None,
            resolve_target: targets.scene_color_msaa.as_ref().map(|_| &targets.scene_color.view),
            ops: wgpu::Operations { load: wgpu::LoadOp::Clear(clear), store: color_store },
        })];
        if deferred {
            // No subpasses in wgpu: the GBuffer must be stored for the lighting pass to read.
            for g in [&targets.gbuffer_a, &targets.gbuffer_b, &targets.gbuffer_c].into_iter().flatten() {
                colors.push(Some(wgpu::RenderPassColorAttachment {
                    view: &g.view,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT),
                        store: wgpu::StoreOp::Store,
                    },
                }));
            }
        }
        colors
    }

    /// The objects (each with its shading model's stencil when deferred), then the sky.
    fn draw(&self, pl: FramePipelines<'_>, pass: &mut wgpu::RenderPass<'_>, scene: &GpuScene, deferred: bool) {
        for o in &self.objects {
            if !o.draw.bind(pl, pass) {
                continue;
            }
            if deferred {
                pass.set_stencil_reference(o.stencil_ref);
            }
            scene.draw(pass, &scene.objects[o.object]);
        }
        if self.sky.bind(pl, pass) {
            pass.draw(0..3, 0..1);
        }
    }
}
