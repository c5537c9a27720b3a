//! ExponentialHeightFog: fog whose density falls off with height, integrated along each
//! camera ray and blended over SceneColor (SceneColor * transmittance + inscattering), with
//! the directional light's inscattering lobe.

use std::sync::Arc;

use crate::frame::{blended, PassContext, PassDecl, PipelineDesc, RenderSlot, Visualize};
use crate::keys;

use super::pipelines::{blend, BindGroups, DesktopLayout};
use super::resources::{begin, color_attachment, formats, Targets};
use super::{DesktopError, PassSetup};

/// The ExponentialHeightFog declaration.
pub const PASS: PassDecl =
    PassDecl { name: "ExponentialHeightFog", reads: &["View", "SceneDepth", "SceneColor"], writes: &["SceneColor"] };

pub struct HeightFog {
    pipeline: Arc<RenderSlot>,
    groups: BindGroups,
}

impl HeightFog {
    pub fn new(b: &PassSetup<'_>) -> Result<HeightFog, DesktopError> {
        let p = b.pipelines;
        let pipeline = p.render(&PipelineDesc::fullscreen(
            &keys::name(keys::post_process_vs::Key {}, p.key_level()?)?,
            &keys::name(
                keys::exponential_height_fog_ps::Key {
                    support_fog_directional_light_inscattering: b.scene.sun.enabled,
                },
                p.key_level()?,
            )?,
            blended(formats::SCENE_COLOR, Some(blend::TRANSMITTANCE)),
        ))?;
        let groups = pipeline.layout.bind_groups(
            b.device,
            &[
                ("View", b.view_buffer.as_entire_binding()),
                ("SceneDepthTexture", wgpu::BindingResource::TextureView(&b.targets.scene_depth.depth_view)),
            ],
        )?;
        Ok(HeightFog { pipeline, groups })
    }

    pub fn record(&self, ctx: &mut PassContext<'_>, t: &Targets) {
        {
            let ready = self.pipeline.ready(ctx.pipelines());
            let mut pass = begin(ctx, "ExponentialHeightFog", &[color_attachment(&t.scene_color.view, None)], None);
            if let Some(p) = ready {
                pass.set_pipeline(&p.pipeline);
                self.groups.set_render(&mut pass);
                pass.draw(0..3, 0..1);
            }
        }
        ctx.output(&t.scene_color.texture, Visualize::Hdr);
    }
}
