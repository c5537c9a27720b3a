//! The renderer's own passes and the resources they share: the one particle system
//! ([`particles`], which the desktop frame builds and records); the frames themselves are
//! `crate::desktop` and `crate::mobile`. A pass is a struct built once (pipelines, bind groups, uniform
//! buffers) and a `record` that says what it reads and writes. Building a pass creates every
//! pipeline it will use (the warm-up); recording never creates pipelines.
//!
//! Adding a pass:
//! 1. Write its shaders in `shader_src/` and declare them in `permutations.toml` (the build
//!    script recompiles the embedded archive).
//! 2. Add `passes/<name>.rs` with a `struct` and `new(init: &PassInit) -> Result<_, PipelineError>`:
//!    name permutations with [`PassInit::permutation`] (`("LIGHT_TYPE", "POINT")`), get
//!    pipelines with `init.cache.render(vs, Some(ps), &RenderState::...)` (or `.compute(cs)`)
//!    and build bind groups by resource name with `pipeline.layout.bind_group(device, group,
//!    label, &[("SceneColorTexture", ...)])`: the reflection says which binding each name is.
//!    New render targets go in [`Targets`] with a format constant in
//!    [`crate::gpu_types::formats`]; uniforms are `#[repr(C)]` Pod structs in `gpu_types`.
//! 3. Add `record(&self, ctx: &mut PassContext, ...)`: open render passes with
//!    `ctx.render_pass(&desc, |pass| ...)` (compute: `ctx.compute_pass`), wrap named steps
//!    in `ctx.step("Bloom", |ctx| ...)`, and declare what was written with
//!    `ctx.output(&texture, Visualize::Hdr)` / `ctx.output_named("GBufferA", ...)`: that is
//!    what `--dump-passes` writes and what the timings cover.
//! 4. Build it in [`crate::renderer::Renderer::new`] for the frames that use it and record
//!    it in frame order: its own `frame.pass("Name", |ctx| pass.record(ctx, ...))`, or a
//!    step of a frame's pass (the particles: the desktop effects' `ParticleSimulation` pass
//!    and its `Fire` step).

pub mod particles;

use crate::gpu_types::formats;
use crate::pipelines::PipelineCache;
use crate::scene::gpu::GpuScene;
use crate::scene::Scene;

/// What every pass needs to build itself.
pub struct PassInit<'a> {
    pub device: &'a wgpu::Device,
    pub cache: &'a PipelineCache,
    pub scene: &'a Scene,
    pub gpu_scene: &'a GpuScene,
    /// The feature level whose permutations the frame uses (`sm5`, `es3_1`).
    pub level: &'a str,
    /// The frame's shared resources.
    pub shared: &'a SharedResources,
}

/// A render target: texture, default view and the name it is dumped under.
pub struct Target {
    pub name: &'static str,
    pub texture: wgpu::Texture,
    pub view: wgpu::TextureView,
}

impl Target {
    pub fn new(
        device: &wgpu::Device,
        name: &'static str,
        format: wgpu::TextureFormat,
        width: u32,
        height: u32,
    ) -> Target {
        let texture = device.create_texture(&wgpu::TextureDescriptor {
            label: Some(name),
            size: wgpu::Extent3d { width, height, depth_or_array_layers: 1 },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT
                | wgpu::TextureUsages::TEXTURE_BINDING
                | wgpu::TextureUsages::COPY_SRC,
            view_formats: &[],
        });
        let view = texture.create_view(&wgpu::TextureViewDescriptor { label: Some(name), ..Default::default() });
        Target { name, texture, view }
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

/// Resources the renderer's passes bind: a `SceneView` buffer of the scene's camera (passes
/// built with [`PassInit`]; the frames keep their own, written every frame) and the targets.
pub struct SharedResources {
    pub view: wgpu::Buffer,
    pub targets: Targets,
}

impl SharedResources {
    /// Group-0 resources by their names in the shaders (`View` of `SceneView.ush`). Bind
    /// groups take the ones their reflection lists.
    pub fn view_resources(&self) -> Vec<(&'static str, wgpu::BindingResource<'_>)> {
        vec![("View", self.view.as_entire_binding())]
    }
}
