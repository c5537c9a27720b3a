//! The renderer's own passes and targets: the one particle system ([`particles`], which the
//! desktop frame builds and records) and the output target; the frames themselves are
//! `crate::desktop` and `crate::mobile`. A pass is a struct built once (pipeline slots, bind
//! groups, uniform buffers) and a `record` that says what it reads and writes. A slot
//! ([`crate::frame::RenderSlot`]) holds a pipeline's key and layout; building a pass creates
//! its pipelines unless the frame is built with [`crate::frame::Creation::Lazy`], and
//! recording asks for each when it draws.
//!
//! Adding a pass:
//! 1. Write its shaders in `shader_src/` and declare them in `permutations.toml` (the build
//!    script recompiles the embedded archive and its typed keys, [`crate::keys`]).
//! 2. Add a module with a `struct` and a `new` that takes its frame's build context (the
//!    desktop effects' `EffectPassInit`, the particles' [`particles::ParticlesInit`], the
//!    desktop frame's `Build`) and returns `Result<_, PipelineError>`: name permutations with
//!    the typed keys (`keys::name(keys::shadow_projection_ps::Key { .. }, level)`), get
//!    pipeline slots with `slots.render(vs, Some(ps), &RenderState::...)` or the frames'
//!    `PipelineDesc` (or `.compute(cs)`) and build bind groups by resource name with
//!    `slot.layout.bind_group(device, group, label, &[("SceneColorTexture", ...)])`: the
//!    reflection says which binding each name is. Uniforms are `#[repr(C)]` Pod structs.
//! 3. Declare what it reads and writes: `pub const PASS: PassDecl = PassDecl { name:
//!    "Velocity", reads: &["Scene", "View", "SceneDepth"], writes: &["Velocity"] }` (a step
//!    recorded inside another module's pass declares its own, `particles::COLLISION_STEP`).
//! 4. Add `record(&self, ctx: &mut PassContext, ...)`: every render or compute pass goes
//!    through the context, which names it with a debug group (`Pass/Step`):
//!    `ctx.render_pass(&desc, |pass| ...)` (compute: `ctx.compute_pass`), or
//!    `ctx.open_render_pass(&desc)` / `ctx.open_compute_pass(label)` for a pass held as a
//!    value (its group is popped when it drops); copies and clears use `ctx.encoder()`. Wrap
//!    named steps in `ctx.step(STEP.name, |ctx| ...)`, and declare what was written with
//!    `ctx.output(&texture, Visualize::Hdr)` / `ctx.output_named("GBufferA", ...)`: that is
//!    what `--dump-passes` writes and what the timings cover. Ask for each pipeline where
//!    the draw is recorded, before opening the pass that uses it (`let ready =
//!    slot.ready(ctx.pipelines())`), and skip the draw when it is `None`.
//! 5. Build it where its frame builds its passes, record it in frame order under its
//!    declaration's name (`frame.pass(velocity::PASS.name, |ctx| pass.record(ctx, ...))`, or
//!    a step of a frame's pass), and add the declaration to the frame's plan
//!    (`DesktopFrame::plan`, `MobileFrame::plan`) at the same place: the frame's unit tests
//!    check that everything it reads is written by an earlier pass, is an input of the frame
//!    or is history the frame writes for the next one, and the render tests that the frame
//!    records the plan's passes.

pub mod particles;

use crate::gpu_types::formats;

/// A render target of either frame: texture, default view and the name it is dumped under.
pub struct Target {
    pub name: &'static str,
    pub texture: wgpu::Texture,
    pub view: wgpu::TextureView,
}

impl Target {
    /// A single-sampled `width` x `height` target that passes render to, sample and dump.
    pub fn new(
        device: &wgpu::Device,
        name: &'static str,
        format: wgpu::TextureFormat,
        width: u32,
        height: u32,
    ) -> Target {
        let usage = wgpu::TextureUsages::RENDER_ATTACHMENT
            | wgpu::TextureUsages::TEXTURE_BINDING
            | wgpu::TextureUsages::COPY_SRC;
        Target::with_usage(device, name, format, (width, height), 1, usage)
    }

    /// A 2D target of `size` with `samples` per pixel and the given usage.
    pub fn with_usage(
        device: &wgpu::Device,
        name: &'static str,
        format: wgpu::TextureFormat,
        size: (u32, u32),
        samples: u32,
        usage: wgpu::TextureUsages,
    ) -> Target {
        let texture = device.create_texture(&wgpu::TextureDescriptor {
            label: Some(name),
            size: wgpu::Extent3d { width: size.0, height: size.1, depth_or_array_layers: 1 },
            mip_level_count: 1,
            sample_count: samples,
            dimension: wgpu::TextureDimension::D2,
            format,
            usage,
            view_formats: &[],
        });
        let view = texture.create_view(&wgpu::TextureViewDescriptor { label: Some(name), ..Default::default() });
        Target { name, texture, view }
    }

    /// The depth aspect alone (to sample a depth-stencil texture).
    pub fn depth_view(&self) -> wgpu::TextureView {
        self.texture.create_view(&wgpu::TextureViewDescriptor {
            label: Some(self.name),
            aspect: wgpu::TextureAspect::DepthOnly,
            ..Default::default()
        })
    }
}

/// The renderer's own targets, created once per size: the frame's output. The desktop and
/// mobile frames own their other targets.
pub struct Targets {
    pub width: u32,
    pub height: u32,
    pub output: Target,
}

impl Targets {
    pub fn new(device: &wgpu::Device, width: u32, height: u32) -> Targets {
        Targets { width, height, output: Target::new(device, "Output", formats::OUTPUT, width, height) }
    }
}
