//! Lighting (desktop): StandardDeferredLighting, one full-screen draw per light reading the
//! GBuffer and adding into SceneColor. The directional light projects its shadow map
//! (`USE_SHADOWS`); point and spot lights use the inverse squared falloff. (Light volumes,
//! the screen-space shadow mask and the tiled path are for the desktop frame issue.)

use wgpu::util::DeviceExt;

use crate::frame::{PassContext, Visualize};
use crate::gpu_types::{formats, LightData};
use crate::pipelines::{Blend, ColorTarget, PipelineError, RenderPipeline, RenderState};
use crate::scene::gpu::{directional_light_data, point_light_data, spot_light_data};

use super::{PassInit, Targets};

struct LightDraw {
    name: String,
    pipeline: std::sync::Arc<RenderPipeline>,
    groups: Vec<wgpu::BindGroup>,
}

pub struct LightingPass {
    lights: Vec<LightDraw>,
    _buffers: Vec<wgpu::Buffer>,
}

impl LightingPass {
    pub fn new(init: &PassInit<'_>) -> Result<LightingPass, PipelineError> {
        let vs = init.permutation("ScreenVS", &[])?;
        let state = RenderState::fullscreen(ColorTarget { format: formats::SCENE_COLOR, blend: Blend::Additive });
        let t = &init.shared.targets;
        let gbuffer = [
            ("SceneDepthTexture", wgpu::BindingResource::TextureView(&t.scene_depth.view)),
            ("GBufferATexture", wgpu::BindingResource::TextureView(&t.gbuffer_a.view)),
            ("GBufferBTexture", wgpu::BindingResource::TextureView(&t.gbuffer_b.view)),
            ("GBufferCTexture", wgpu::BindingResource::TextureView(&t.gbuffer_c.view)),
        ];
        let scene = init.scene;
        let mut wanted: Vec<(String, &str, bool, LightData)> = Vec::new();
        if scene.sun.enabled {
            wanted.push(("DirectionalLight".into(), "DIRECTIONAL", scene.sun.casts_shadows, directional_light_data(scene)));
        }
        for l in &scene.point_lights {
            wanted.push((l.name.clone(), "POINT", false, point_light_data(l)));
        }
        for l in &scene.spot_lights {
            wanted.push((l.name.clone(), "SPOT", false, spot_light_data(l)));
        }
        let mut lights = Vec::new();
        let mut buffers = Vec::new();
        for (name, ty, shadows, data) in wanted {
            let falloff = if ty == "DIRECTIONAL" { "0" } else { "1" };
            let ps = init.permutation(
                "DeferredLightPS",
                &[("LIGHT_TYPE", ty), ("USE_SHADOWS", if shadows { "1" } else { "0" }), ("INVERSE_SQUARED_FALLOFF", falloff)],
            )?;
            let pipeline = init.cache.render(&vs, Some(&ps), &state)?;
            let buffer = init.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(&format!("{name} light uniforms")),
                contents: bytemuck::bytes_of(&data),
                usage: wgpu::BufferUsages::UNIFORM,
            });
            let layout = &pipeline.layout;
            let groups = vec![
                layout.bind_group(init.device, 0, &format!("{name} view"), &init.shared.view_resources())?,
                layout.bind_group(init.device, 1, &format!("{name} gbuffer"), &gbuffer)?,
                layout.bind_group(init.device, 2, &format!("{name} light"), &[("DeferredLight", buffer.as_entire_binding())])?,
            ];
            buffers.push(buffer);
            lights.push(LightDraw { name, pipeline, groups });
        }
        Ok(LightingPass { lights, _buffers: buffers })
    }

    /// Reads SceneDepth, GBufferA/B/C and the shadow map; adds into SceneColor.
    pub fn record(&self, ctx: &mut PassContext<'_>, t: &Targets) {
        ctx.step("StandardDeferredLighting", |ctx| {
            {
                ctx.render_pass(&wgpu::RenderPassDescriptor {
                    label: Some("StandardDeferredLighting"),
                    color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                        view: &t.scene_color.view,
                        depth_slice: None,
                        resolve_target: None,
                        ops: wgpu::Operations { load: wgpu::LoadOp::Load, store: wgpu::StoreOp::Store },
                    })],
                    depth_stencil_attachment: None,
                    timestamp_writes: None,
                    occlusion_query_set: None,
                    multiview_mask: None,
                }, |pass| {
                    for light in &self.lights {
                        pass.insert_debug_marker(&light.name);
                        pass.set_pipeline(&light.pipeline.pipeline);
                        for (i, g) in light.groups.iter().enumerate() {
                            pass.set_bind_group(i as u32, g, &[]);
                        }
                        pass.draw(0..3, 0..1);
                    }
                });
            }
            ctx.output(&t.scene_color.texture, Visualize::Hdr);
        });
    }
}
