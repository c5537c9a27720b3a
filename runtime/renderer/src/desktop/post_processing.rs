//! PostProcessing: Bloom (threshold at half resolution, a chain of filtered downsamples, then
//! tent upsamples added back up the chain) and the Tonemapper (exposure, bloom, filmic curve,
//! vignette) into the sRGB output.

use std::sync::Arc;

use glam::Vec4;

use crate::frame::{blended, PassContext, PassDecl, PipelineDesc, RenderSlot, Visualize};
use crate::keys;

use super::pipelines::{blend, BindGroups, DesktopLayout};
use super::resources::{begin, color_attachment, formats, Targets};
use super::view::{BloomUniforms, TonemapUniforms};
use super::{DesktopError, PassSetup};
use crate::gpu_types::uniform_buffer;

/// Bloom and the Tonemapper (after the temporal steps).
pub const PASS: PassDecl = PassDecl { name: "PostProcessing", reads: &["SceneColor"], writes: &["Bloom", "Output"] };

struct Draw {
    pipeline: Arc<RenderSlot>,
    groups: BindGroups,
    /// Index into the bloom chain it writes (None: the output).
    target: Option<usize>,
    clear: bool,
}

pub struct PostProcessing {
    bloom: Vec<Draw>,
    tonemap_uses_bloom: bool,
    tonemap: Draw,
}

/// Bloom threshold, soft knee, and intensity in the tonemapper.
pub const BLOOM: [f32; 3] = [1.5, 0.5, 0.2];

impl PostProcessing {
    pub fn new(b: &PassSetup<'_>, output_format: wgpu::TextureFormat) -> Result<PostProcessing, DesktopError> {
        let bloom = Self::bloom(b)?;
        let tonemap = Self::tonemap(b, output_format)?;
        Ok(PostProcessing { bloom, tonemap_uses_bloom: b.options.bloom, tonemap })
    }

    /// Bloom: the setup from SceneColor, down the levels, then back up adding each.
    fn bloom(b: &PassSetup<'_>) -> Result<Vec<Draw>, DesktopError> {
        let p = b.pipelines;
        let t = b.targets;
        let vs = keys::name(keys::post_process_vs::Key {}, p.key_level()?)?;
        let setup_ps = keys::name(keys::bloom_setup_ps::Key {}, p.key_level()?)?;
        let down_ps = keys::name(keys::bloom_downsample_ps::Key {}, p.key_level()?)?;
        let up_ps = keys::name(keys::bloom_upsample_ps::Key {}, p.key_level()?)?;
        let texel = |tex: &wgpu::Texture| Vec4::new(1.0 / tex.width() as f32, 1.0 / tex.height() as f32, 0.0, 0.0);
        let mut bloom = Vec::new();
        let mut add = |ps: &str,
                       source: &wgpu::TextureView,
                       source_tex: &wgpu::Texture,
                       target: usize,
                       blend: Option<wgpu::BlendState>,
                       intensity: f32|
         -> Result<(), DesktopError> {
            let pipeline = p.render(&PipelineDesc::fullscreen(&vs, ps, blended(formats::BLOOM, blend)))?;
            let u = uniform_buffer(
                b.device,
                "Bloom",
                &BloomUniforms {
                    params: Vec4::new(BLOOM[0], BLOOM[1], intensity, 0.0),
                    source_texel: texel(source_tex),
                },
            );
            let groups = pipeline
                .layout
                .bind_groups(
                    b.device,
                    &[
                        ("SourceTexture", wgpu::BindingResource::TextureView(source)),
                        ("LinearSampler", wgpu::BindingResource::Sampler(&b.samplers.linear)),
                        ("Bloom", u.as_entire_binding()),
                    ],
                )?
                .keeping(u);
            bloom.push(Draw { pipeline, groups, target: Some(target), clear: blend.is_none() });
            Ok(())
        };
        add(&setup_ps, &t.scene_color.view, &t.scene_color.texture, 0, None, 1.0)?;
        for i in 1..t.bloom.len() {
            add(&down_ps, &t.bloom[i - 1].view, &t.bloom[i - 1].texture, i, None, 1.0)?;
        }
        for i in (1..t.bloom.len()).rev() {
            add(&up_ps, &t.bloom[i].view, &t.bloom[i].texture, i - 1, Some(blend::ADDITIVE), 1.0)?;
        }
        Ok(bloom)
    }

    /// The tonemapper into the output (with the bloom where the options have it).
    fn tonemap(b: &PassSetup<'_>, output_format: wgpu::TextureFormat) -> Result<Draw, DesktopError> {
        let (p, t) = (b.pipelines, b.targets);
        let vs = keys::name(keys::post_process_vs::Key {}, p.key_level()?)?;
        let pipeline = p.render(&PipelineDesc::fullscreen(
            &vs,
            &keys::name(
                keys::tonemapper_ps::Key {
                    use_bloom: b.options.bloom,
                    use_vignette: b.options.vignette,
                    use_gamma_only: false,
                },
                p.key_level()?,
            )?,
            blended(output_format, None),
        ))?;
        let u = uniform_buffer(
            b.device,
            "Tonemap",
            &TonemapUniforms { params: Vec4::new(b.scene.exposure, BLOOM[2], 0.4, 0.0) },
        );
        let groups = pipeline
            .layout
            .bind_groups(
                b.device,
                &[
                    ("SceneColorTexture", wgpu::BindingResource::TextureView(&t.scene_color.view)),
                    ("LinearSampler", wgpu::BindingResource::Sampler(&b.samplers.linear)),
                    ("Tonemap", u.as_entire_binding()),
                    ("BloomTexture", wgpu::BindingResource::TextureView(&t.bloom[0].view)),
                ],
            )?
            .keeping(u);
        Ok(Draw { pipeline, groups, target: None, clear: true })
    }

    fn run(ctx: &mut PassContext<'_>, d: &Draw, view: &wgpu::TextureView) {
        let ready = d.pipeline.ready(ctx.pipelines());
        let mut pass =
            begin(ctx, "PostProcess", &[color_attachment(view, d.clear.then_some(wgpu::Color::BLACK))], None);
        if let Some(p) = ready {
            pass.set_pipeline(&p.pipeline);
            d.groups.set_render(&mut pass);
            pass.draw(0..3, 0..1);
        }
    }

    pub fn record(&self, ctx: &mut PassContext<'_>, t: &Targets, output: (&wgpu::Texture, &wgpu::TextureView)) {
        if self.tonemap_uses_bloom {
            ctx.step("Bloom", |ctx| {
                for d in &self.bloom {
                    let target = d.target.unwrap_or(0);
                    Self::run(ctx, d, &t.bloom[target].view);
                }
                ctx.output(&t.bloom[0].texture, Visualize::Hdr);
            });
        }
        ctx.step("Tonemapper", |ctx| {
            Self::run(ctx, &self.tonemap, output.1);
            ctx.output(output.0, Visualize::Direct);
        });
    }
}
