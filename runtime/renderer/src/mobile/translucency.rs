//! Translucency: translucent meshes, back to front, forward lit in both paths (the
//! `MobileBasePassPS` translucent permutations), blended premultiplied over SceneColor. In the
//! forward frame with MSAA this pass resolves the multisampled color at its end and stores
//! nothing multisampled; the depth is tested, never written, and discarded at the end.

use crate::frame::{premultiplied, untouched, PassContext, PassDecl, PipelineDesc, VertexInput, Visualize};
use crate::pipelines::PipelineError;
use crate::scene::gpu::GpuScene;
use crate::scene::{BlendMode, Scene};

use super::base_pass::{base_pass_formats, base_pass_ps, base_pass_vs, depth_format};
use super::pipeline::{Draw, MobilePipelines};
use super::{MobileOptions, MobileTargets, ShadingPath, SharedResources};

/// Blends over SceneColor, tested against the depth.
pub const PASS: PassDecl = PassDecl {
    name: "Translucency",
    reads: &["Scene", "View", "ShadowAtlas", "ReflectionCaptures", "SceneDepth", "SceneColor"],
    writes: &["SceneColor"],
};

pub struct Translucency {
    path: ShadingPath,
    hdr: bool,
    /// (object index, draw), farthest first.
    draws: Vec<(usize, Draw)>,
}

impl Translucency {
    /// `None` when the scene has nothing translucent.
    pub fn new(
        pipelines: &MobilePipelines<'_>,
        gpu_scene: &GpuScene,
        scene: &Scene,
        options: &MobileOptions,
        targets: &MobileTargets,
        shared: &SharedResources,
    ) -> Result<Option<Translucency>, PipelineError> {
        let forward = options.path == ShadingPath::Forward;
        let vs = base_pass_vs(forward && options.vertex_fog)?;
        // Translucency in the deferred frame runs after lighting, on SceneColor alone.
        let formats = if forward { base_pass_formats(options) } else { vec![super::SCENE_COLOR_FORMAT] };
        let view = shared.view_resources(targets);
        let camera = scene.camera.position;
        let mut items: Vec<(f32, usize)> = Vec::new();
        for (i, object) in gpu_scene.objects.iter().enumerate() {
            if gpu_scene.material(object).blend != BlendMode::Translucent {
                continue;
            }
            // Sort by the nearest instance's distance, drawn far to near.
            let distance = scene.objects[i]
                .instances
                .iter()
                .map(|m| m.w_axis.truncate().distance(camera))
                .fold(f32::MAX, f32::min);
            items.push((distance, i));
        }
        if items.is_empty() {
            return Ok(None);
        }
        items.sort_by(|a, b| b.0.total_cmp(&a.0));
        let mut draws = Vec::new();
        let options_lit = MobileOptions { vertex_fog: forward && options.vertex_fog, ..options.clone() };
        for (_, i) in items {
            let object = &gpu_scene.objects[i];
            let material = gpu_scene.material(object);
            let ps = base_pass_ps(&options_lit, material, true, shared.cascades > 0)?;
            let mut desc = PipelineDesc::new(&vs, Some(&ps), VertexInput::MeshInstanced);
            desc.cull_mode = Some(wgpu::Face::Back);
            desc.depth_stencil = Some(wgpu::DepthStencilState {
                format: depth_format(options),
                depth_write_enabled: Some(false),
                depth_compare: Some(wgpu::CompareFunction::GreaterEqual),
                stencil: Default::default(),
                bias: Default::default(),
            });
            desc.targets = formats
                .iter()
                .enumerate()
                .map(|(k, f)| if k == 0 { premultiplied(*f) } else { untouched(*f) })
                .collect();
            desc.sample_count = targets.samples;
            let mut resources = view.clone();
            resources.push(("Material", gpu_scene.materials[object.material].uniforms.as_entire_binding()));
            draws.push((i, Draw::new(pipelines.device, pipelines.get(&desc)?, &resources)?));
        }
        Ok(Some(Translucency { path: options.path, hdr: options.hdr, draws }))
    }

    pub fn record(&self, ctx: &mut PassContext<'_>, scene: &GpuScene, targets: &MobileTargets) {
        let msaa = targets.scene_color_msaa.is_some();
        let stencil = self.path == ShadingPath::Deferred;
        let pl = ctx.pipelines();
        {
            ctx.render_pass(
                &wgpu::RenderPassDescriptor {
                    label: Some("Translucency"),
                    color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                        view: &targets.color_attachment().view,
                        depth_slice: None,
                        // MSAA: resolved at the end of the pass; the samples are not kept.
                        resolve_target: msaa.then_some(&targets.scene_color.view),
                        ops: wgpu::Operations {
                            load: wgpu::LoadOp::Load,
                            store: if msaa { wgpu::StoreOp::Discard } else { wgpu::StoreOp::Store },
                        },
                    })],
                    depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                        view: &targets.scene_depth.view,
                        depth_ops: Some(wgpu::Operations { load: wgpu::LoadOp::Load, store: wgpu::StoreOp::Discard }),
                        stencil_ops: stencil
                            .then_some(wgpu::Operations { load: wgpu::LoadOp::Load, store: wgpu::StoreOp::Discard }),
                    }),
                    timestamp_writes: None,
                    occlusion_query_set: None,
                    multiview_mask: None,
                },
                |pass| {
                    for (i, draw) in &self.draws {
                        if draw.bind(pl, pass) {
                            scene.draw(pass, &scene.objects[*i]);
                        }
                    }
                },
            );
        }
        ctx.output(&targets.scene_color.texture, if self.hdr { Visualize::Hdr } else { Visualize::Direct });
    }
}
