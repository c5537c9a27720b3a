//! Reflections: ScreenSpaceReflections (`ScreenSpaceReflections.usf`) traces each GBuffer
//! pixel's reflected ray against the HZB (rougher surfaces test coarser mips) into an RGBA16F
//! target (reflected colour premultiplied by confidence, confidence); then
//! ReflectionEnvironmentAndSky (`ReflectionEnvironmentShaders.usf`) adds to SceneColor the
//! screen-space reflection where it hit and the reflection capture cubemap (parallax-corrected
//! against its sphere, mip by roughness) or the sky elsewhere, weighted by the environment
//! BRDF. The capture cubemap is filtered once, one mip per roughness, by
//! `ReflectionCaptureFilterCS`.

use crate::frame::{ComputeSlot, PassContext, PassDecl, RenderSlot};
use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use glam::{Vec3, Vec4};

use crate::keys;
use crate::pipelines::{Blend, ColorTarget, PipelineError, RenderState};

use super::frame_view::{color_pass, groups, linear_sampler, target_2d, uniform_buffer, view, EffectPassInit};

/// The Reflections declaration.
pub const PASS: PassDecl = PassDecl {
    name: "Reflections",
    reads: &["View", "SceneDepth", "HZB", "GBufferA", "GBufferB", "GBufferC", "SceneColor"],
    writes: &["ReflectionCapture", "ScreenSpaceReflections", "SceneColor"],
};

pub const SSR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba16Float;
pub const CAPTURE_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba16Float;
pub const CAPTURE_SIZE: u32 = 64;
pub const CAPTURE_MIPS: u32 = 6;
/// Surfaces rougher than this do not trace (the capture alone reflects them).
pub const SSR_MAX_ROUGHNESS: f32 = 0.6;

#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
struct SsrParams {
    trace: Vec4,
    hzb_size: Vec4,
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
struct ReflectionParams {
    capture: Vec4,
    mips: Vec4,
    room: Vec4,
}

/// The GBuffer and scene textures the reflections read.
pub struct ReflectionInputs<'a> {
    pub scene_color: &'a wgpu::TextureView,
    pub scene_depth: &'a wgpu::TextureView,
    pub gbuffer_a: &'a wgpu::TextureView,
    pub gbuffer_b: &'a wgpu::TextureView,
    pub gbuffer_c: &'a wgpu::TextureView,
    pub hzb: &'a wgpu::TextureView,
    pub hzb_size: [u32; 2],
    pub hzb_mips: u32,
}

/// A reflection capture: a sphere of influence and the average colour of the room it sees.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CaptureDesc {
    pub position: Vec3,
    pub radius: f32,
    pub room_color: Vec3,
}

pub struct Reflections {
    pub ssr: wgpu::Texture,
    pub ssr_view: wgpu::TextureView,
    pub capture: wgpu::Texture,
    ssr_pipeline: Arc<RenderSlot>,
    environment: Arc<RenderSlot>,
    filter: Arc<ComputeSlot>,
    ssr_group: wgpu::BindGroup,
    environment_group: wgpu::BindGroup,
    filter_groups: Vec<(wgpu::BindGroup, u32)>,
    _buffers: Vec<wgpu::Buffer>,
    captured: bool,
}

impl Reflections {
    pub fn new(
        init: &EffectPassInit<'_>,
        size: [u32; 2],
        inputs: &ReflectionInputs<'_>,
        capture: &CaptureDesc,
        scene_color_format: wgpu::TextureFormat,
    ) -> Result<Reflections, PipelineError> {
        let EffectPassInit { device, cache, frame_view } = *init;
        let ssr_pipeline = cache.render(
            &keys::name(keys::screen_space_reflections_vs::Key {}, keys::Level::Sm5)?,
            Some(&keys::name(keys::screen_space_reflections_ps::Key { ssr_quality: 1 }, keys::Level::Sm5)?),
            &RenderState::fullscreen(ColorTarget::new(SSR_FORMAT, Blend::Replace)),
        )?;
        let environment = cache.render(
            &keys::name(keys::reflection_environment_vs::Key {}, keys::Level::Sm5)?,
            Some(&keys::name(keys::reflection_environment_ps::Key {}, keys::Level::Sm5)?),
            &RenderState::fullscreen(ColorTarget::new(scene_color_format, Blend::Additive)),
        )?;
        let filter = cache.compute(&keys::name(keys::reflection_capture_filter_cs::Key {}, keys::Level::Sm5)?)?;
        let ssr = target_2d(
            device,
            "ScreenSpaceReflections",
            size,
            SSR_FORMAT,
            wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING,
        );
        let ssr_view = view(&ssr);
        let capture_texture = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("ReflectionCapture"),
            size: wgpu::Extent3d { width: CAPTURE_SIZE, height: CAPTURE_SIZE, depth_or_array_layers: 6 },
            mip_level_count: CAPTURE_MIPS,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: CAPTURE_FORMAT,
            usage: wgpu::TextureUsages::STORAGE_BINDING
                | wgpu::TextureUsages::TEXTURE_BINDING
                | wgpu::TextureUsages::COPY_SRC,
            view_formats: &[],
        });
        let sampler = linear_sampler(device, "Reflections sampler");
        let ssr_params = uniform_buffer(
            device,
            "SSR params",
            &SsrParams {
                trace: Vec4::new(SSR_MAX_ROUGHNESS, inputs.hzb_mips as f32, 0.3, 12.0),
                hzb_size: Vec4::new(inputs.hzb_size[0] as f32, inputs.hzb_size[1] as f32, 0.0, 0.0),
            },
        );
        let tex = wgpu::BindingResource::TextureView;
        let ssr_group = ssr_pipeline.layout.bind_group(
            device,
            0,
            "ScreenSpaceReflections",
            &[
                ("View", frame_view.as_entire_binding()),
                ("ssr", ssr_params.as_entire_binding()),
                ("scene_color", tex(inputs.scene_color)),
                ("SceneDepthTexture", tex(inputs.scene_depth)),
                ("gbuffer_a", tex(inputs.gbuffer_a)),
                ("gbuffer_b", tex(inputs.gbuffer_b)),
                ("HZBDepthTexture", tex(inputs.hzb)),
                ("linear_sampler", wgpu::BindingResource::Sampler(&sampler)),
            ],
        )?;
        let mut buffers = vec![ssr_params];
        let capture_params = |mip: u32| ReflectionParams {
            capture: capture.position.extend(capture.radius),
            mips: Vec4::new(
                CAPTURE_MIPS as f32,
                mip as f32,
                mip as f32 / (CAPTURE_MIPS - 1) as f32,
                (CAPTURE_SIZE >> mip).max(1) as f32,
            ),
            room: capture.room_color.extend(0.0),
        };
        let mut filter_groups = Vec::new();
        for mip in 0..CAPTURE_MIPS {
            let params = uniform_buffer(device, &format!("ReflectionCapture mip {mip}"), &capture_params(mip));
            let face_view = capture_texture.create_view(&wgpu::TextureViewDescriptor {
                label: Some(&format!("ReflectionCapture mip {mip}")),
                dimension: Some(wgpu::TextureViewDimension::D2Array),
                base_mip_level: mip,
                mip_level_count: Some(1),
                ..Default::default()
            });
            let group = filter.layout.bind_group(
                device,
                0,
                "ReflectionCaptureFilter",
                &[
                    ("View", frame_view.as_entire_binding()),
                    ("reflection", params.as_entire_binding()),
                    ("capture_face", wgpu::BindingResource::TextureView(&face_view)),
                ],
            )?;
            filter_groups.push((group, (CAPTURE_SIZE >> mip).max(1)));
            buffers.push(params);
        }
        let env_params = uniform_buffer(device, "ReflectionEnvironment params", &capture_params(0));
        let cube = capture_texture.create_view(&wgpu::TextureViewDescriptor {
            label: Some("ReflectionCapture cube"),
            dimension: Some(wgpu::TextureViewDimension::Cube),
            ..Default::default()
        });
        let environment_group = environment.layout.bind_group(
            device,
            0,
            "ReflectionEnvironmentAndSky",
            &[
                ("View", frame_view.as_entire_binding()),
                ("reflection", env_params.as_entire_binding()),
                ("SceneDepthTexture", tex(inputs.scene_depth)),
                ("gbuffer_a", tex(inputs.gbuffer_a)),
                ("gbuffer_b", tex(inputs.gbuffer_b)),
                ("gbuffer_c", tex(inputs.gbuffer_c)),
                ("ssr", tex(&ssr_view)),
                ("capture_cube", tex(&cube)),
                ("linear_sampler", wgpu::BindingResource::Sampler(&sampler)),
            ],
        )?;
        buffers.push(env_params);
        Ok(Reflections {
            ssr,
            ssr_view,
            capture: capture_texture,
            ssr_pipeline,
            environment,
            filter,
            ssr_group,
            environment_group,
            filter_groups,
            _buffers: buffers,
            captured: false,
        })
    }

    /// Filters the capture cubemap (once: the capture sees static surroundings).
    pub fn record_capture(&mut self, ctx: &mut PassContext<'_>) {
        if self.captured {
            return;
        }
        let ready = self.filter.ready(ctx.pipelines());
        let mut pass = ctx.open_compute_pass("ReflectionCaptureFilter");
        let Some(p) = ready else { return };
        pass.set_pipeline(&p.pipeline);
        for (group, size) in &self.filter_groups {
            pass.set_bind_group(0, group, &[]);
            pass.dispatch_workgroups(groups(*size, 8), groups(*size, 8), 6);
        }
        self.captured = true;
    }

    /// ScreenSpaceReflections into the SSR target.
    pub fn record_ssr(&self, ctx: &mut PassContext<'_>) {
        let ready = self.ssr_pipeline.ready(ctx.pipelines());
        let mut pass =
            color_pass(ctx, "ScreenSpaceReflections", &self.ssr_view, wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT));
        if let Some(p) = ready {
            pass.set_pipeline(&p.pipeline);
            pass.set_bind_group(0, &self.ssr_group, &[]);
            pass.draw(0..3, 0..1);
        }
    }

    /// ReflectionEnvironmentAndSky, added onto SceneColor.
    pub fn record_environment(&self, ctx: &mut PassContext<'_>, scene_color: &wgpu::TextureView) {
        let ready = self.environment.ready(ctx.pipelines());
        let mut pass = color_pass(ctx, "ReflectionEnvironmentAndSky", scene_color, wgpu::LoadOp::Load);
        if let Some(p) = ready {
            pass.set_pipeline(&p.pipeline);
            pass.set_bind_group(0, &self.environment_group, &[]);
            pass.draw(0..3, 0..1);
        }
    }
}
