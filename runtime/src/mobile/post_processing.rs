//! PostProcessing of mobile HDR: Bloom (BloomSetup thresholds SceneColor into half
//! resolution, BloomDown halves three times, BloomUp walks back up adding each level) and the
//! Tonemapper (SceneColor plus bloom, filmic curve, sRGB encoding into the 8-bit output).
//! Each step is a full-screen triangle in its own render pass, stored for the next step.

use glam::Vec4;
use wgpu::util::DeviceExt;

use crate::frame::{PassContext, Visualize};
use crate::pipelines::PipelineError;

use super::pipeline::{replace, Draw, MobilePipelines, PipelineDesc, VertexInput};
use super::uniforms::{BloomUniforms, TonemapUniforms};
use super::{MobileOptions, MobileTargets, SharedResources, Target, OUTPUT_FORMAT, SCENE_COLOR_FORMAT};

/// Bloom levels below full resolution: 1/2, 1/4, 1/8, 1/16.
const BLOOM_LEVELS: usize = 4;
const BLOOM_THRESHOLD: f32 = 1.0;
const BLOOM_INTENSITY: f32 = 0.6;

struct Step {
    name: String,
    draw: Draw,
    target: usize,
}

pub struct PostProcessing {
    /// Bloom targets: setup and down levels, then up levels (index into `targets`).
    targets: Vec<Target>,
    steps: Vec<Step>,
    tonemap: Draw,
    _buffers: Vec<wgpu::Buffer>,
}

fn level_size(width: u32, height: u32, level: usize) -> (u32, u32) {
    ((width >> (level + 1)).max(1), (height >> (level + 1)).max(1))
}

impl PostProcessing {
    pub fn new(pipelines: &MobilePipelines<'_>, options: &MobileOptions, targets: &MobileTargets, shared: &SharedResources) -> Result<PostProcessing, PipelineError> {
        let device = pipelines.device;
        let vs = pipelines.permutation("MobileFullscreenVS", &[])?;
        let fullscreen = |ps: &str, format| -> Result<_, PipelineError> {
            let mut desc = PipelineDesc::new(vs.clone(), Some(pipelines.permutation(ps, &[])?), VertexInput::None);
            desc.targets = vec![replace(format)];
            pipelines.get(&desc)
        };
        let (w, h) = (targets.width, targets.height);
        let mut bloom_targets = Vec::new();
        let mut steps = Vec::new();
        let mut buffers = Vec::new();
        let sampler = wgpu::BindingResource::Sampler(&shared.linear_sampler);
        let uniform = |label: &str, u: BloomUniforms| {
            device.create_buffer_init(&wgpu::util::BufferInitDescriptor { label: Some(label), contents: bytemuck::bytes_of(&u), usage: wgpu::BufferUsages::UNIFORM })
        };
        const NAMES: [&str; 4] = ["BloomHalf", "BloomQuarter", "BloomEighth", "BloomSixteenth"];
        const UP_NAMES: [&str; 3] = ["BloomUpEighth", "BloomUpQuarter", "BloomUpHalf"];
        let mut plan: Vec<(String, &str, usize, Option<usize>, usize, BloomUniforms)> = Vec::new();
        if options.bloom {
            for (level, name) in NAMES.iter().enumerate() {
                bloom_targets.push(Target::new(device, name, SCENE_COLOR_FORMAT, level_size(w, h, level), 1));
            }
            for (i, name) in UP_NAMES.iter().enumerate() {
                bloom_targets.push(Target::new(device, name, SCENE_COLOR_FORMAT, level_size(w, h, BLOOM_LEVELS - 2 - i), 1));
            }
            // (step name, shader, input target (usize::MAX = SceneColor), additive, output, uniforms)
            let texel = |(x, y): (u32, u32)| Vec4::new(1.0 / x as f32, 1.0 / y as f32, 0.0, 0.0);
            plan.push(("BloomSetup".into(), "MobileBloomSetupPS", usize::MAX, None, 0, BloomUniforms { texel: texel((w, h)) * 1.0, params: Vec4::new(BLOOM_THRESHOLD, 0.0, 0.0, 0.0) }));
            for level in 1..BLOOM_LEVELS {
                let src = level_size(w, h, level - 1);
                plan.push((format!("BloomDown{level}"), "MobileBloomDownPS", level - 1, None, level, BloomUniforms { texel: texel(src), params: Vec4::ZERO }));
            }
            for i in 0..BLOOM_LEVELS - 1 {
                let input = if i == 0 { BLOOM_LEVELS - 1 } else { BLOOM_LEVELS + i - 1 };
                let fine = BLOOM_LEVELS - 2 - i;
                let coarse = if i == 0 { level_size(w, h, BLOOM_LEVELS - 1) } else { level_size(w, h, BLOOM_LEVELS - 1 - i) };
                plan.push((format!("BloomUp{}", i + 1), "MobileBloomUpPS", input, Some(fine), BLOOM_LEVELS + i, BloomUniforms { texel: texel(coarse), params: Vec4::new(0.0, 0.5, 0.5, 0.0) }));
            }
        }
        let scene_color = wgpu::BindingResource::TextureView(&targets.scene_color.view);
        let view_of = |i: usize| if i == usize::MAX { scene_color.clone() } else { wgpu::BindingResource::TextureView(&bloom_targets[i].view) };
        for (name, shader, input, additive, output, u) in plan {
            let b = uniform(&name, u);
            let pipeline = fullscreen(shader, SCENE_COLOR_FORMAT)?;
            let mut r = vec![("Input", view_of(input)), ("InputSampler", sampler.clone()), ("Bloom", b.as_entire_binding())];
            if let Some(a) = additive {
                r.push(("Additive", view_of(a)));
            }
            steps.push(Step { name, draw: Draw::new(device, pipeline, &r)?, target: output });
            buffers.push(b);
        }
        let bloom_result = if options.bloom { view_of(bloom_targets.len() - 1) } else { scene_color.clone() };
        let tonemap_params = TonemapUniforms { params: Vec4::new(1.0, BLOOM_INTENSITY, if options.bloom { 1.0 } else { 0.0 }, 0.0) };
        let tb = device.create_buffer_init(&wgpu::util::BufferInitDescriptor { label: Some("Tonemap"), contents: bytemuck::bytes_of(&tonemap_params), usage: wgpu::BufferUsages::UNIFORM });
        let tonemap = Draw::new(
            device,
            fullscreen("MobileTonemapPS", OUTPUT_FORMAT)?,
            &[("SceneColor", scene_color.clone()), ("BloomTexture", bloom_result), ("LinearSampler", sampler.clone()), ("Tonemap", tb.as_entire_binding())],
        )?;
        buffers.push(tb);
        Ok(PostProcessing { targets: bloom_targets, steps, tonemap, _buffers: buffers })
    }

    fn fullscreen_pass(ctx: &mut PassContext<'_>, label: &str, target: &Target, draw: &Draw) {
        ctx.render_pass(&wgpu::RenderPassDescriptor {
            label: Some(label),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: &target.view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations { load: wgpu::LoadOp::Clear(wgpu::Color::BLACK), store: wgpu::StoreOp::Store },
            })],
            depth_stencil_attachment: None,
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        }, |pass| {
            draw.bind(pass);
            pass.draw(0..3, 0..1);
        });
    }

    pub fn record(&self, ctx: &mut PassContext<'_>, targets: &MobileTargets) {
        for step in &self.steps {
            let target = &self.targets[step.target];
            ctx.step(&step.name, |ctx| {
                Self::fullscreen_pass(ctx, &step.name, target, &step.draw);
                ctx.output(&target.texture, Visualize::Hdr);
            });
        }
        let output = targets.output.as_ref().expect("HDR frames have an output target");
        ctx.step("Tonemapper", |ctx| {
            Self::fullscreen_pass(ctx, "Tonemapper", output, &self.tonemap);
            ctx.output(&output.texture, Visualize::Direct);
        });
    }
}
