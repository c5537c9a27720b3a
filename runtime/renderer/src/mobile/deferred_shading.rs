//! MobileDeferredShading: the lighting of the mobile deferred path.
//!
//! Steps: `SceneDepthAux` copies the scene depth into a depth texture the lights can read
//! while the scene depth-stencil stays attached; then one render pass on SceneColor:
//! `DirectionalLight` (one full-screen draw: the directional light with its CSM, reflections
//! and the sky light, where the stencil says default lit), and `LocalLights`: per light a
//! stencil draw of the volume's front faces marks the pixels in front of the volume (depth
//! fails, the sandbox bit is set), then the light draws the volume's back faces where the
//! stencil is default lit and unmarked, and clears the mark (RenderLocalLight_StencilMask /
//! RenderLocalLight of the seed). Point lights draw spheres, spot lights cones.

use crate::gpu::BufferInit;

use crate::frame::{additive, untouched, PassContext, PassDecl, PipelineDesc, VertexInput, Visualize};
use crate::keys;
use crate::pipelines::PipelineError;

use super::light_volumes::{unit_cone, unit_sphere, volume_to_world, VolumeMesh};
use super::pipeline::{Draw, MobilePipelines};
use super::uniforms::{DeferredLightUniforms, LocalLight};
use super::{
    MobileOptions, MobileTargets, SharedResources, DEFERRED_DEPTH_FORMAT, SCENE_COLOR_FORMAT, SCENE_DEPTH_AUX_FORMAT,
    STENCIL_DEFAULT_LIT, STENCIL_SANDBOX, STENCIL_SHADING_MODEL_MASK,
};

/// Lights SceneColor from the GBuffer and the depth (through SceneDepthAux).
pub const PASS: PassDecl = PassDecl {
    name: "MobileDeferredShading",
    reads: &[
        "View",
        "ShadowAtlas",
        "ReflectionCaptures",
        "GBufferA",
        "GBufferB",
        "GBufferC",
        "SceneDepth",
        "SceneColor",
    ],
    writes: &["SceneDepthAux", "SceneColor"],
};

/// The level of every mobile permutation.
const LEVEL: keys::Level = keys::Level::Es31;

fn stencil_face(
    compare: wgpu::CompareFunction,
    fail: wgpu::StencilOperation,
    depth_fail: wgpu::StencilOperation,
    pass: wgpu::StencilOperation,
) -> wgpu::StencilFaceState {
    wgpu::StencilFaceState { compare, fail_op: fail, depth_fail_op: depth_fail, pass_op: pass }
}

struct LightDraw {
    is_spot: bool,
    stencil: Draw,
    light: Draw,
}

pub struct MobileDeferredShading {
    depth_aux: Draw,
    directional: Draw,
    lights: Vec<LightDraw>,
    sphere: VolumeMesh,
    cone: VolumeMesh,
    _buffers: Vec<wgpu::Buffer>,
    _depth_view: wgpu::TextureView,
}

/// SceneDepthAux: the scene depth into a depth texture (frag_depth = depth).
fn depth_aux_desc(fullscreen: &str) -> Result<PipelineDesc, PipelineError> {
    let ps = keys::name(keys::mobile_scene_depth_aux_ps::Key {}, LEVEL)?;
    let mut desc = PipelineDesc::new(fullscreen, Some(&ps), VertexInput::None);
    desc.depth_stencil = Some(wgpu::DepthStencilState {
        format: SCENE_DEPTH_AUX_FORMAT,
        depth_write_enabled: Some(true),
        depth_compare: Some(wgpu::CompareFunction::Always),
        stencil: Default::default(),
        bias: Default::default(),
    });
    Ok(desc)
}

/// The directional light: full screen, default lit pixels only, adds to SceneColor.
fn directional_desc(fullscreen: &str, options: &MobileOptions, csm: bool) -> Result<PipelineDesc, PipelineError> {
    let direct_ps = keys::name(
        keys::mobile_direct_light_ps::Key {
            directional_light_csm: csm,
            hq_reflections: options.reflections && options.hq_reflections,
            enable_sky_light: options.sky_light,
        },
        LEVEL,
    )?;
    let only_default_lit = stencil_face(
        wgpu::CompareFunction::Equal,
        wgpu::StencilOperation::Keep,
        wgpu::StencilOperation::Keep,
        wgpu::StencilOperation::Keep,
    );
    let mut desc = PipelineDesc::new(fullscreen, Some(&direct_ps), VertexInput::None);
    desc.targets = vec![additive(SCENE_COLOR_FORMAT)];
    desc.depth_stencil = Some(wgpu::DepthStencilState {
        format: DEFERRED_DEPTH_FORMAT,
        depth_write_enabled: Some(false),
        depth_compare: Some(wgpu::CompareFunction::Always),
        stencil: wgpu::StencilState {
            front: only_default_lit,
            back: only_default_lit,
            read_mask: STENCIL_SHADING_MODEL_MASK,
            write_mask: 0,
        },
        bias: Default::default(),
    });
    Ok(desc)
}

/// A local light's stencil mask: front faces, depth fail marks.
fn stencil_desc(volume_vs: &str) -> Result<PipelineDesc, PipelineError> {
    let mark = stencil_face(
        wgpu::CompareFunction::Always,
        wgpu::StencilOperation::Keep,
        wgpu::StencilOperation::Replace,
        wgpu::StencilOperation::Keep,
    );
    let ps = keys::name(keys::mobile_light_stencil_ps::Key {}, LEVEL)?;
    let mut desc = PipelineDesc::new(volume_vs, Some(&ps), VertexInput::Position);
    desc.cull_mode = Some(wgpu::Face::Back);
    desc.targets = vec![untouched(SCENE_COLOR_FORMAT)];
    desc.depth_stencil = Some(wgpu::DepthStencilState {
        format: DEFERRED_DEPTH_FORMAT,
        depth_write_enabled: Some(false),
        depth_compare: Some(wgpu::CompareFunction::GreaterEqual),
        stencil: wgpu::StencilState { front: mark, back: mark, read_mask: 0xff, write_mask: STENCIL_SANDBOX },
        bias: Default::default(),
    });
    Ok(desc)
}

/// A local light: back faces behind the surface, unmarked default lit pixels; clears the
/// mark.
fn light_desc(volume_vs: &str, spot: bool) -> Result<PipelineDesc, PipelineError> {
    let lit = stencil_face(
        wgpu::CompareFunction::Equal,
        wgpu::StencilOperation::Zero,
        wgpu::StencilOperation::Zero,
        wgpu::StencilOperation::Zero,
    );
    let ps = keys::name(keys::mobile_radial_light_ps::Key { is_spot_light: spot }, LEVEL)?;
    let mut desc = PipelineDesc::new(volume_vs, Some(&ps), VertexInput::Position);
    desc.cull_mode = Some(wgpu::Face::Front);
    desc.targets = vec![additive(SCENE_COLOR_FORMAT)];
    desc.depth_stencil = Some(wgpu::DepthStencilState {
        format: DEFERRED_DEPTH_FORMAT,
        depth_write_enabled: Some(false),
        depth_compare: Some(wgpu::CompareFunction::LessEqual),
        stencil: wgpu::StencilState {
            front: lit,
            back: lit,
            read_mask: STENCIL_SHADING_MODEL_MASK | STENCIL_SANDBOX,
            write_mask: STENCIL_SANDBOX,
        },
        bias: Default::default(),
    });
    Ok(desc)
}

/// What the lights read: the view's resources, the GBuffer and SceneDepthAux.
fn light_resources<'t>(
    shared: &'t SharedResources,
    targets: &'t MobileTargets,
) -> Vec<(&'static str, wgpu::BindingResource<'t>)> {
    fn gbuffer(t: &Option<super::Target>) -> wgpu::BindingResource<'_> {
        wgpu::BindingResource::TextureView(&t.as_ref().expect("deferred targets have a GBuffer").view)
    }
    let aux = targets.scene_depth_aux.as_ref().expect("deferred targets have SceneDepthAux");
    let mut resources = shared.view_resources(targets);
    resources.push(("GBufferATexture", gbuffer(&targets.gbuffer_a)));
    resources.push(("GBufferBTexture", gbuffer(&targets.gbuffer_b)));
    resources.push(("GBufferCTexture", gbuffer(&targets.gbuffer_c)));
    resources.push(("SceneDepthTexture", wgpu::BindingResource::TextureView(&aux.view)));
    resources
}

impl MobileDeferredShading {
    pub fn new(
        pipelines: &MobilePipelines<'_>,
        options: &MobileOptions,
        targets: &MobileTargets,
        shared: &SharedResources,
        lights: &[LocalLight],
    ) -> Result<MobileDeferredShading, PipelineError> {
        let device = pipelines.device;
        let fullscreen = keys::name(keys::mobile_fullscreen_vs::Key {}, LEVEL)?;
        let depth_view = targets.scene_depth.depth_view();
        let depth_aux = Draw::new(
            device,
            pipelines.get(&depth_aux_desc(&fullscreen)?)?,
            &[("SceneDepthTexture", wgpu::BindingResource::TextureView(&depth_view))],
        )?;
        let resources = light_resources(shared, targets);
        let directional_desc = directional_desc(&fullscreen, options, shared.cascades > 0)?;
        let directional = Draw::new(device, pipelines.get(&directional_desc)?, &resources)?;
        let volume_vs = keys::name(keys::mobile_deferred_light_vs::Key {}, LEVEL)?;
        let stencil_pipeline = pipelines.get(&stencil_desc(&volume_vs)?)?;
        let point_pipeline = pipelines.get(&light_desc(&volume_vs, false)?)?;
        let spot_pipeline = pipelines.get(&light_desc(&volume_vs, true)?)?;
        let mut buffers = Vec::new();
        let mut draws = Vec::new();
        for l in lights {
            let u = DeferredLightUniforms { volume_to_world: volume_to_world(l), light: l.data };
            let buffer = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(&format!("DeferredLight {}", l.name)),
                contents: bytemuck::bytes_of(&u),
                usage: wgpu::BufferUsages::UNIFORM,
            });
            let mut r = resources.clone();
            r.push(("Light", buffer.as_entire_binding()));
            let light = if l.is_spot { spot_pipeline.clone() } else { point_pipeline.clone() };
            draws.push(LightDraw {
                is_spot: l.is_spot,
                stencil: Draw::new(device, stencil_pipeline.clone(), &r)?,
                light: Draw::new(device, light, &r)?,
            });
            buffers.push(buffer);
        }
        Ok(MobileDeferredShading {
            depth_aux,
            directional,
            lights: draws,
            sphere: VolumeMesh::new(device, "LightSphere", unit_sphere()),
            cone: VolumeMesh::new(device, "LightCone", unit_cone()),
            _buffers: buffers,
            _depth_view: depth_view,
        })
    }

    /// Reads the GBuffer and the scene depth; adds light to SceneColor.
    pub fn record(&self, ctx: &mut PassContext<'_>, targets: &MobileTargets) {
        let aux = targets.scene_depth_aux.as_ref().expect("deferred targets have SceneDepthAux");
        let pl = ctx.pipelines();
        ctx.step("SceneDepthAux", |ctx| {
            {
                ctx.render_pass(
                    &wgpu::RenderPassDescriptor {
                        label: Some("SceneDepthAux"),
                        color_attachments: &[],
                        depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                            view: &aux.view,
                            depth_ops: Some(wgpu::Operations {
                                load: wgpu::LoadOp::Clear(0.0),
                                store: wgpu::StoreOp::Store,
                            }),
                            stencil_ops: None,
                        }),
                        timestamp_writes: None,
                        occlusion_query_set: None,
                        multiview_mask: None,
                    },
                    |pass| {
                        if self.depth_aux.bind(pl, pass) {
                            pass.draw(0..3, 0..1);
                        }
                    },
                );
            }
            ctx.output(&aux.texture, Visualize::Depth);
        });
        {
            ctx.render_pass(
                &wgpu::RenderPassDescriptor {
                    label: Some("MobileDeferredShading"),
                    color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                        view: &targets.scene_color.view,
                        depth_slice: None,
                        resolve_target: None,
                        ops: wgpu::Operations { load: wgpu::LoadOp::Load, store: wgpu::StoreOp::Store },
                    })],
                    depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                        view: &targets.scene_depth.view,
                        // Depth is only tested; the stencil dies with the pass.
                        depth_ops: None,
                        stencil_ops: Some(wgpu::Operations { load: wgpu::LoadOp::Load, store: wgpu::StoreOp::Discard }),
                    }),
                    timestamp_writes: None,
                    occlusion_query_set: None,
                    multiview_mask: None,
                },
                |pass| {
                    pass.push_debug_group("DirectionalLight");
                    if self.directional.bind(pl, pass) {
                        pass.set_stencil_reference(STENCIL_DEFAULT_LIT);
                        pass.draw(0..3, 0..1);
                    }
                    pass.pop_debug_group();
                    pass.push_debug_group("LocalLights");
                    for l in &self.lights {
                        let volume = if l.is_spot { &self.cone } else { &self.sphere };
                        // the light is drawn only where its volume's stencil marked
                        if !l.stencil.bind(pl, pass) {
                            continue;
                        }
                        pass.set_stencil_reference(STENCIL_SANDBOX);
                        volume.draw(pass);
                        if l.light.bind(pl, pass) {
                            pass.set_stencil_reference(STENCIL_DEFAULT_LIT);
                            volume.draw(pass);
                        }
                    }
                    pass.pop_debug_group();
                },
            );
        }
        ctx.output(&targets.scene_color.texture, Visualize::Hdr);
    }
}
