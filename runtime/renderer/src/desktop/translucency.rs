//! Translucency: the glass statues, forward shaded into the separate translucency target
//! (premultiplied color, alpha = transmittance), depth tested against the scene; then
//! composited over SceneColor (the particle sprites follow, `Effects::particle_sprites`). The glass is lit
//! by one of two TranslucencyLightingModes (the `TRANSLUCENCY_LIGHTING_MODE` dimension, chosen
//! per frame by [`EffectOptions::translucency_lighting`](super::effects::EffectOptions)):
//! per pixel (sky light, the directional light with its cascaded shadow, the local lights of
//! the light grid cell each pixel falls in), or with the diffuse light of the volumes' lights
//! read from the two cascades of the translucency lighting volumes.

use std::sync::Arc;

use crate::frame::{blended, PassContext, PassDecl, PipelineDesc, RenderSlot, VertexInput, Visualize};
use crate::keys;
use crate::scene::BlendMode;

use super::effects::{TranslucencyLightingMode, TranslucencyVolumeInputs};
use super::frame_view::volume_view;
use super::light_grid::LightGrid;
use super::pipelines::{blend, BindGroups, DesktopLayout};
use super::resources::{begin, color_attachment, formats, SceneBuffers, Targets, Texture};
use super::shadow_depths::ShadowDepths;
use super::{DesktopError, PassSetup};
use crate::gpu_types::uniform_buffer;

/// The Translucency declaration.
pub const PASS: PassDecl = PassDecl {
    name: "Translucency",
    reads: &["Scene", "View", "SceneDepth", "LightGrid", "ShadowDepths", "TranslucencyVolume", "SceneColor"],
    writes: &["SeparateTranslucency", "SceneColor"],
};

pub struct Translucency {
    /// The lit translucent surfaces: [forward shaded, lit by the volumes].
    surfaces: Option<[(Arc<RenderSlot>, BindGroups); 2]>,
    compose: Arc<RenderSlot>,
    compose_groups: BindGroups,
    /// The surfaces' `DirectionalShadow` buffers (the cascades follow the camera).
    directional_shadow: Vec<wgpu::Buffer>,
}

impl Translucency {
    pub fn new(
        b: &PassSetup<'_>,
        grid: &LightGrid,
        shadows: &ShadowDepths,
        dummy_shadow: &Texture,
        volume: &TranslucencyVolumeInputs,
    ) -> Result<Translucency, DesktopError> {
        let p = b.pipelines;
        let t = b.targets;
        let mut directional_shadow = Vec::new();
        let surfaces = if b.buffers.draws.iter().any(|d| d.blend == BlendMode::Translucent) {
            let (ambient, directional) =
                (volume.ambient.each_ref().map(volume_view), volume.directional.each_ref().map(volume_view));
            let volume_sampler = b.device.create_sampler(&wgpu::SamplerDescriptor {
                label: Some("TranslucencyLightingVolumeSampler"),
                mag_filter: wgpu::FilterMode::Linear,
                min_filter: wgpu::FilterMode::Linear,
                ..Default::default()
            });
            let csm = shadows.csm_texture().unwrap_or(dummy_shadow);
            let mut resources = b.scene_resources();
            resources.extend([
                ("LocalLights", b.lights_buffer.as_entire_binding()),
                ("NumCulledLightsGrid", grid.num_culled_lights.as_entire_binding()),
                ("CulledLightDataGrid", grid.culled_light_data.as_entire_binding()),
                ("ShadowDepthTexture", wgpu::BindingResource::TextureView(&csm.view)),
                ("ShadowDepthSampler", wgpu::BindingResource::Sampler(&b.samplers.shadow)),
                ("TranslucencyLightingVolume", volume.params.as_entire_binding()),
                ("TranslucencyLightingVolumeAmbientInner", wgpu::BindingResource::TextureView(&ambient[0])),
                ("TranslucencyLightingVolumeDirectionalInner", wgpu::BindingResource::TextureView(&directional[0])),
                ("TranslucencyLightingVolumeAmbientOuter", wgpu::BindingResource::TextureView(&ambient[1])),
                ("TranslucencyLightingVolumeDirectionalOuter", wgpu::BindingResource::TextureView(&directional[1])),
                ("TranslucencyLightingVolumeSampler", wgpu::BindingResource::Sampler(&volume_sampler)),
            ]);
            let (forward, a) =
                Self::surface_pipeline(b, TranslucencyLightingMode::SurfaceForwardShading, shadows, &resources)?;
            let (volume, b) =
                Self::surface_pipeline(b, TranslucencyLightingMode::SurfaceLightingVolume, shadows, &resources)?;
            drop(resources);
            directional_shadow = vec![a, b];
            Some([forward, volume])
        } else {
            None
        };
        let compose = p.render(&PipelineDesc::fullscreen(
            &keys::name(keys::post_process_vs::Key {}, p.key_level()?)?,
            &keys::name(keys::compose_separate_translucency_ps::Key {}, p.key_level()?)?,
            blended(formats::SCENE_COLOR, Some(blend::TRANSMITTANCE)),
        ))?;
        let compose_groups = compose.layout.bind_groups(
            b.device,
            &[("SeparateTranslucencyTexture", wgpu::BindingResource::TextureView(&t.translucency.view))],
        )?;
        Ok(Translucency { surfaces, compose, compose_groups, directional_shadow })
    }

    /// This frame's cascades of the directional light (they follow the camera).
    pub fn update(&self, queue: &wgpu::Queue, cascaded: Option<&super::view::ShadowProjectionUniforms>) {
        if let Some(u) = cascaded {
            for buffer in &self.directional_shadow {
                queue.write_buffer(buffer, 0, bytemuck::bytes_of(u));
            }
        }
    }

    /// The lit translucent surfaces' pipeline in `mode`, with its bind groups.
    fn surface_pipeline(
        b: &PassSetup<'_>,
        mode: TranslucencyLightingMode,
        shadows: &ShadowDepths,
        resources: &[(&str, wgpu::BindingResource<'_>)],
    ) -> Result<((Arc<RenderSlot>, BindGroups), wgpu::Buffer), DesktopError> {
        let (p, t) = (b.pipelines, b.targets);
        let pipeline = p.render(&PipelineDesc {
            cull_mode: Some(wgpu::Face::Back),
            depth_stencil: Some(wgpu::DepthStencilState {
                format: t.scene_depth.format,
                depth_write_enabled: Some(false),
                depth_compare: Some(wgpu::CompareFunction::GreaterEqual),
                stencil: wgpu::StencilState::default(),
                bias: wgpu::DepthBiasState::default(),
            }),
            targets: vec![blended(formats::TRANSLUCENCY, Some(blend::TRANSLUCENT))],
            ..PipelineDesc::new(
                &keys::name(keys::deferred_base_pass_vs::Key {}, p.key_level()?)?,
                Some(&keys::name(
                    keys::deferred_base_pass_ps::Key {
                        material_blend_mode: keys::deferred_base_pass_ps::MaterialBlendMode::Translucent,
                        material_shadingmodel: keys::deferred_base_pass_ps::MaterialShadingmodel::DefaultLit,
                        translucency_lighting_mode: match mode {
                            TranslucencyLightingMode::SurfaceForwardShading => {
                                keys::deferred_base_pass_ps::TranslucencyLightingMode::SurfaceForwardShading
                            }
                            TranslucencyLightingMode::SurfaceLightingVolume => {
                                keys::deferred_base_pass_ps::TranslucencyLightingMode::SurfaceLightingVolume
                            }
                        },
                    },
                    p.key_level()?,
                )?),
                VertexInput::Mesh,
            )
        })?;
        let directional = uniform_buffer(b.device, "DirectionalShadow", &shadows.setup.cascaded.unwrap_or_default());
        let mut resources = resources.to_vec();
        resources.push(("DirectionalShadow", directional.as_entire_binding()));
        let groups = pipeline.layout.bind_groups(b.device, &resources)?;
        drop(resources);
        Ok(((pipeline, groups.keeping(directional.clone())), directional))
    }

    /// `mode`: how the glass is lit this frame.
    pub fn record(&self, ctx: &mut PassContext<'_>, scene: &SceneBuffers, t: &Targets, mode: TranslucencyLightingMode) {
        ctx.step("SeparateTranslucency", |ctx| {
            {
                let pl = ctx.pipelines();
                let mut pass = begin(
                    ctx,
                    "SeparateTranslucency",
                    &[color_attachment(&t.translucency.view, Some(wgpu::Color { r: 0.0, g: 0.0, b: 0.0, a: 1.0 }))],
                    Some(wgpu::RenderPassDepthStencilAttachment {
                        view: &t.scene_depth.attachment,
                        depth_ops: None,
                        stencil_ops: None,
                    }),
                );
                if let Some(surfaces) = &self.surfaces {
                    let (pipeline, groups) =
                        &surfaces[usize::from(mode == TranslucencyLightingMode::SurfaceLightingVolume)];
                    if let Some(p) = pipeline.ready(pl) {
                        pass.set_pipeline(&p.pipeline);
                        groups.set_render(&mut pass);
                        for draw in scene.draws.iter().filter(|d| d.blend == BlendMode::Translucent) {
                            scene.draw(&mut pass, draw);
                        }
                    }
                }
            }
            ctx.output(&t.translucency.texture, Visualize::Hdr);
        });
        ctx.step("ComposeSeparateTranslucency", |ctx| {
            {
                let ready = self.compose.ready(ctx.pipelines());
                let mut pass =
                    begin(ctx, "ComposeSeparateTranslucency", &[color_attachment(&t.scene_color.view, None)], None);
                if let Some(p) = ready {
                    pass.set_pipeline(&p.pipeline);
                    self.compose_groups.set_render(&mut pass);
                    pass.draw(0..3, 0..1);
                }
            }
            ctx.output(&t.scene_color.texture, Visualize::Hdr);
        });
    }
}
