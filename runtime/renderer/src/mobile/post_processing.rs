//! PostProcessing of mobile HDR: Bloom (BloomSetup thresholds SceneColor into half
//! resolution, BloomDown halves three times, BloomUp walks back up adding each level) and the
//! Tonemapper (SceneColor plus bloom, filmic curve, sRGB encoding into the 8-bit output).
//! Each step is a full-screen triangle in its own render pass, stored for the next step.

use crate::gpu::BufferInit;
use glam::Vec4;

use crate::frame::{replace, PassContext, PassDecl, PipelineDesc, VertexInput, Visualize};
use crate::keys;
use crate::pipelines::PipelineError;

use super::pipeline::{Draw, MobilePipelines};
use super::uniforms::{BloomUniforms, TonemapUniforms};
use super::{target, MobileOptions, MobileTargets, SharedResources, Target, OUTPUT_FORMAT, SCENE_COLOR_FORMAT};

/// Bloom and the Tonemapper into the output.
pub const PASS: PassDecl = PassDecl { name: "PostProcessing", reads: &["SceneColor"], writes: &["Output"] };

/// Bloom levels below full resolution: 1/2, 1/4, 1/8, 1/16.
const BLOOM_LEVELS: usize = 4;
const BLOOM_THRESHOLD: f32 = 1.0;
const BLOOM_INTENSITY: f32 = 0.6;

/// One planned bloom step: its shader, what it reads (bloom target indices, or SceneColor)
/// and which bloom target it writes.
struct BloomStep {
    name: String,
    /// The pixel shader permutation's canonical name.
    shader: String,
    input: usize,
    additive: Option<usize>,
    output: usize,
    uniforms: BloomUniforms,
}

/// `BloomStep::input` naming SceneColor rather than a bloom target.
const SCENE_COLOR_INPUT: usize = usize::MAX;

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

const LEVEL: keys::Level = keys::Level::Es31;

/// The bloom levels: down to a sixteenth, then back up to a half.
fn bloom_targets(device: &wgpu::Device, w: u32, h: u32) -> Vec<Target> {
    const NAMES: [&str; 4] = ["BloomHalf", "BloomQuarter", "BloomEighth", "BloomSixteenth"];
    const UP_NAMES: [&str; 3] = ["BloomUpEighth", "BloomUpQuarter", "BloomUpHalf"];
    let mut targets = Vec::new();
    for (level, name) in NAMES.iter().enumerate() {
        targets.push(target(device, name, SCENE_COLOR_FORMAT, level_size(w, h, level), 1));
    }
    for (i, name) in UP_NAMES.iter().enumerate() {
        targets.push(target(device, name, SCENE_COLOR_FORMAT, level_size(w, h, BLOOM_LEVELS - 2 - i), 1));
    }
    targets
}

/// The bloom steps in order: setup, down, then up (each adding the finer level).
fn bloom_plan(w: u32, h: u32) -> Result<Vec<BloomStep>, PipelineError> {
    let texel = |(x, y): (u32, u32)| Vec4::new(1.0 / x as f32, 1.0 / y as f32, 0.0, 0.0);
    let mut plan = vec![BloomStep {
        name: "BloomSetup".into(),
        shader: keys::name(keys::mobile_bloom_setup_ps::Key {}, LEVEL)?,
        input: SCENE_COLOR_INPUT,
        additive: None,
        output: 0,
        uniforms: BloomUniforms { texel: texel((w, h)), params: Vec4::new(BLOOM_THRESHOLD, 0.0, 0.0, 0.0) },
    }];
    for level in 1..BLOOM_LEVELS {
        let src = level_size(w, h, level - 1);
        plan.push(BloomStep {
            name: format!("BloomDown{level}"),
            shader: keys::name(keys::mobile_bloom_down_ps::Key {}, LEVEL)?,
            input: level - 1,
            additive: None,
            output: level,
            uniforms: BloomUniforms { texel: texel(src), params: Vec4::ZERO },
        });
    }
    for i in 0..BLOOM_LEVELS - 1 {
        let input = if i == 0 { BLOOM_LEVELS - 1 } else { BLOOM_LEVELS + i - 1 };
        let fine = BLOOM_LEVELS - 2 - i;
        let coarse = if i == 0 { level_size(w, h, BLOOM_LEVELS - 1) } else { level_size(w, h, BLOOM_LEVELS - 1 - i) };
        plan.push(BloomStep {
            name: format!("BloomUp{}", i + 1),
            shader: keys::name(keys::mobile_bloom_up_ps::Key {}, LEVEL)?,
            input,
            additive: Some(fine),
            output: BLOOM_LEVELS + i,
            uniforms: BloomUniforms { texel: texel(coarse), params: Vec4::new(0.0, 0.5, 0.5, 0.0) },
        });
    }
    Ok(plan)
}

impl PostProcessing {
    pub fn new(
        pipelines: &MobilePipelines<'_>,
        options: &MobileOptions,
        targets: &MobileTargets,
        shared: &SharedResources,
    ) -> Result<PostProcessing, PipelineError> {
        let device = pipelines.device;
        let vs = keys::name(keys::mobile_fullscreen_vs::Key {}, LEVEL)?;
        let fullscreen = |ps: String, format| -> Result<_, PipelineError> {
            let mut desc = PipelineDesc::new(&vs, Some(&ps), VertexInput::None);
            desc.targets = vec![replace(format)];
            pipelines.get(&desc)
        };
        let (w, h) = (targets.width, targets.height);
        let mut steps = Vec::new();
        let mut buffers = Vec::new();
        let sampler = wgpu::BindingResource::Sampler(&shared.linear_sampler);
        let uniform = |label: &str, u: BloomUniforms| {
            device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytemuck::bytes_of(&u),
                usage: wgpu::BufferUsages::UNIFORM,
            })
        };
        let (bloom_targets, plan) =
            if options.bloom { (bloom_targets(device, w, h), bloom_plan(w, h)?) } else { (Vec::new(), Vec::new()) };
        let scene_color = wgpu::BindingResource::TextureView(&targets.scene_color.view);
        let view_of = |i: usize| {
            if i == SCENE_COLOR_INPUT {
                scene_color.clone()
            } else {
                wgpu::BindingResource::TextureView(&bloom_targets[i].view)
            }
        };
        for step in plan {
            let b = uniform(&step.name, step.uniforms);
            let pipeline = fullscreen(step.shader.clone(), SCENE_COLOR_FORMAT)?;
            let mut r = vec![
                ("Input", view_of(step.input)),
                ("InputSampler", sampler.clone()),
                ("Bloom", b.as_entire_binding()),
            ];
            if let Some(a) = step.additive {
                r.push(("Additive", view_of(a)));
            }
            steps.push(Step { name: step.name, draw: Draw::new(device, pipeline, &r)?, target: step.output });
            buffers.push(b);
        }
        let bloom_result = if options.bloom { view_of(bloom_targets.len() - 1) } else { scene_color.clone() };
        let tonemap_params =
            TonemapUniforms { params: Vec4::new(1.0, BLOOM_INTENSITY, if options.bloom { 1.0 } else { 0.0 }, 0.0) };
        let tb = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("Tonemap"),
            contents: bytemuck::bytes_of(&tonemap_params),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let tonemap = Draw::new(
            device,
            fullscreen(keys::name(keys::mobile_tonemap_ps::Key {}, LEVEL)?, OUTPUT_FORMAT)?,
            &[
                ("SceneColor", scene_color.clone()),
                ("BloomTexture", bloom_result),
                ("LinearSampler", sampler.clone()),
                ("Tonemap", tb.as_entire_binding()),
            ],
        )?;
        buffers.push(tb);
        Ok(PostProcessing { targets: bloom_targets, steps, tonemap, _buffers: buffers })
    }

    fn fullscreen_pass(ctx: &mut PassContext<'_>, label: &str, target: &Target, draw: &Draw) {
        let pl = ctx.pipelines();
        ctx.render_pass(
            &wgpu::RenderPassDescriptor {
                label: Some(label),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: &target.view,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Clear(wgpu::Color::BLACK),
                        store: wgpu::StoreOp::Store,
                    },
                })],
                depth_stencil_attachment: None,
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            },
            |pass| {
                if draw.bind(pl, pass) {
                    pass.draw(0..3, 0..1);
                }
            },
        );
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
