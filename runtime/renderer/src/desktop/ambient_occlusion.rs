//! AmbientOcclusion: screen-space AO from depth and normals, as Unreal's
//! `AmbientOcclusionSetup` (half resolution normal + depth), `AmbientOcclusionPS` at half
//! resolution (`SetupAsInput=1 Upsample=0`), again at full resolution combining the
//! upsampled half resolution result (`SetupAsInput=0 Upsample=1`), then
//! `ApplyAOToBasePassSceneColor`, which multiplies SceneColor (indirect light so far).

use std::sync::Arc;

use glam::Vec4;

use crate::frame::{blended, PassContext, PassDecl, PipelineDesc, RenderSlot, Visualize};
use crate::keys;

use super::pipelines::{blend, BindGroups, DesktopLayout};
use super::resources::{begin, color_attachment, formats, Targets};
use super::view::AmbientOcclusionUniforms;
use super::{DesktopError, PassSetup};
use crate::gpu_types::uniform_buffer;

/// The AmbientOcclusion declaration.
pub const PASS: PassDecl = PassDecl {
    name: "AmbientOcclusion",
    reads: &["View", "SceneDepth", "GBufferA", "SceneColor"],
    writes: &["AmbientOcclusion", "SceneColor"],
};

struct Step {
    name: &'static str,
    pipeline: Arc<RenderSlot>,
    groups: BindGroups,
}

pub struct AmbientOcclusion {
    setup: Step,
    half: Step,
    full: Step,
    apply: Step,
}

/// World radius of the AO kernel (meters), intensity, angle bias, fade-out depth.
pub const AO_PARAMS: [f32; 4] = [1.0, 3.0, 0.1, 60.0];

impl AmbientOcclusion {
    pub fn new(b: &PassSetup<'_>) -> Result<AmbientOcclusion, DesktopError> {
        let p = b.pipelines;
        let t = b.targets;
        let vs = keys::name(keys::post_process_vs::Key {}, p.key_level()?)?;
        let frame = b.options.frame_index;
        let jitter = Vec4::new((frame % 4) as f32, ((frame / 4) % 4) as f32, 0.0, 0.0);
        let params = |w: u32, h: u32| AmbientOcclusionUniforms {
            params: Vec4::from(AO_PARAMS),
            output_size: Vec4::new(w as f32, h as f32, 1.0 / w as f32, 1.0 / h as f32),
            jitter,
        };
        let (hw, hh) = (t.ao_half.texture.width(), t.ao_half.texture.height());
        let half_uniforms = uniform_buffer(b.device, "AmbientOcclusion half", &params(hw, hh));
        let full_uniforms = uniform_buffer(b.device, "AmbientOcclusion full", &params(t.width, t.height));
        let quality = i64::from(b.options.ao_quality.min(2));
        let step = |name: &'static str,
                    ps: String,
                    blend: Option<wgpu::BlendState>,
                    format,
                    resources: &[(&str, wgpu::BindingResource<'_>)]|
         -> Result<Step, DesktopError> {
            let pipeline = p.render(&PipelineDesc::fullscreen(&vs, &ps, blended(format, blend)))?;
            let groups = pipeline.layout.bind_groups(b.device, resources)?;
            Ok(Step { name, pipeline, groups })
        };
        let ao_ps = |setup: bool, upsample: bool| {
            let key = keys::ambient_occlusion_ps::Key {
                use_ao_setup_as_input: setup,
                use_upsample: upsample,
                shader_quality: quality,
            };
            Ok::<_, DesktopError>(keys::name(key, p.key_level()?)?)
        };
        let mut ao = AmbientOcclusion {
            setup: step(
                "Setup",
                keys::name(keys::ambient_occlusion_setup_ps::Key {}, p.key_level()?)?,
                None,
                formats::AO_SETUP,
                &ao_resources(b, &half_uniforms),
            )?,
            half: step("HalfResolution", ao_ps(true, false)?, None, formats::AO, &ao_resources(b, &half_uniforms))?,
            full: step("FullResolution", ao_ps(false, true)?, None, formats::AO, &ao_resources(b, &full_uniforms))?,
            apply: step(
                "ApplyToSceneColor",
                keys::name(keys::ambient_occlusion_apply_ps::Key {}, p.key_level()?)?,
                Some(blend::MULTIPLY),
                formats::SCENE_COLOR,
                &ao_resources(b, &full_uniforms),
            )?,
        };
        ao.half.groups.keep.push(half_uniforms);
        ao.full.groups.keep.push(full_uniforms);
        Ok(ao)
    }

    pub fn record(&self, ctx: &mut PassContext<'_>, t: &Targets) {
        let draw = |ctx: &mut PassContext<'_>, step: &Step, target: &wgpu::TextureView, clear: bool| {
            let ready = step.pipeline.ready(ctx.pipelines());
            let mut pass =
                begin(ctx, step.name, &[color_attachment(target, clear.then_some(wgpu::Color::WHITE))], None);
            if let Some(p) = ready {
                pass.set_pipeline(&p.pipeline);
                step.groups.set_render(&mut pass);
                pass.draw(0..3, 0..1);
            }
        };
        ctx.step(self.setup.name, |ctx| {
            draw(ctx, &self.setup, &t.ao_setup.view, true);
            ctx.output(&t.ao_setup.texture, Visualize::Direct);
        });
        ctx.step(self.half.name, |ctx| {
            draw(ctx, &self.half, &t.ao_half.view, true);
            ctx.output(&t.ao_half.texture, Visualize::Direct);
        });
        ctx.step(self.full.name, |ctx| {
            draw(ctx, &self.full, &t.ao_full.view, true);
            ctx.output(&t.ao_full.texture, Visualize::Direct);
        });
        ctx.step(self.apply.name, |ctx| {
            draw(ctx, &self.apply, &t.scene_color.view, false);
            ctx.output(&t.scene_color.texture, Visualize::Hdr);
        });
    }
}

fn ao_resources<'r>(b: &'r PassSetup<'_>, ao: &'r wgpu::Buffer) -> Vec<(&'static str, wgpu::BindingResource<'r>)> {
    let t = b.targets;
    vec![
        ("View", b.view_buffer.as_entire_binding()),
        ("SceneDepthTexture", wgpu::BindingResource::TextureView(&t.scene_depth.depth_view)),
        ("GBufferATexture", wgpu::BindingResource::TextureView(&t.gbuffer_a.view)),
        ("SetupTexture", wgpu::BindingResource::TextureView(&t.ao_setup.view)),
        ("LowResAOTexture", wgpu::BindingResource::TextureView(&t.ao_half.view)),
        ("LinearSampler", wgpu::BindingResource::Sampler(&b.samplers.linear)),
        ("RandomNormalTexture", wgpu::BindingResource::TextureView(&b.samplers.random_normals.view)),
        ("AmbientOcclusion", ao.as_entire_binding()),
        ("AmbientOcclusionTexture", wgpu::BindingResource::TextureView(&t.ao_full.view)),
    ]
}
