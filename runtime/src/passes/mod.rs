//! One module per pass. A pass is a struct built once (pipelines, bind groups, uniform
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
//! 4. Build it in [`crate::renderer::Renderer::new`] for the frames that use it and call it
//!    from the frame function with `frame.pass("Name", |ctx| pass.record(ctx, ...))` in
//!    frame order.

pub mod particles;

use std::sync::Arc;

use crate::gpu_types::formats;
use crate::pipelines::{PipelineCache, PipelineError};
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

impl PassInit<'_> {
    /// The canonical name of `shader` at this pass's level with the given dimension values.
    pub fn permutation(&self, shader: &str, values: &[(&str, &str)]) -> Result<String, PipelineError> {
        let mut q = self.cache.archive().shader(shader).level(self.level);
        for (d, v) in values {
            q = q.with(d, v);
        }
        Ok(q.find()?.name().to_string())
    }
}

/// A render target: texture, default view and the name it is dumped under.
pub struct Target {
    pub name: &'static str,
    pub texture: wgpu::Texture,
    pub view: wgpu::TextureView,
}

impl Target {
    pub fn new(device: &wgpu::Device, name: &'static str, format: wgpu::TextureFormat, width: u32, height: u32) -> Target {
        let texture = device.create_texture(&wgpu::TextureDescriptor {
            label: Some(name),
            size: wgpu::Extent3d { width, height, depth_or_array_layers: 1 },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_SRC,
            view_formats: &[],
        });
        let view = texture.create_view(&wgpu::TextureViewDescriptor { label: Some(name), ..Default::default() });
        Target { name, texture, view }
    }
}

/// The render targets of a frame, created once per size.
pub struct Targets {
    pub width: u32,
    pub height: u32,
    pub scene_depth: Target,
    pub scene_color: Target,
    pub gbuffer_a: Target,
    pub gbuffer_b: Target,
    pub gbuffer_c: Target,
    pub shadow_depth: Target,
    pub output: Target,
    /// Scratch HDR target for pictures of passes that write buffers (ParticleSimulation).
    pub preview: Target,
}

impl Targets {
    pub fn new(device: &wgpu::Device, width: u32, height: u32) -> Targets {
        let s = crate::scene::gpu::SHADOW_MAP_SIZE;
        Targets {
            width,
            height,
            scene_depth: Target::new(device, "SceneDepth", formats::SCENE_DEPTH, width, height),
            scene_color: Target::new(device, "SceneColor", formats::SCENE_COLOR, width, height),
            gbuffer_a: Target::new(device, "GBufferA", formats::GBUFFER_A, width, height),
            gbuffer_b: Target::new(device, "GBufferB", formats::GBUFFER_B, width, height),
            gbuffer_c: Target::new(device, "GBufferC", formats::GBUFFER_C, width, height),
            shadow_depth: Target::new(device, "ShadowDepth", formats::SHADOW_DEPTH, s, s),
            output: Target::new(device, "Output", formats::OUTPUT, width, height),
            preview: Target::new(device, "Preview", formats::SCENE_COLOR, width, height),
        }
    }
}

/// Resources many passes bind: the view uniforms (camera and light), the shadow map and its
/// comparison sampler, the mobile local lights.
pub struct SharedResources {
    pub view: wgpu::Buffer,
    pub shadow_view: wgpu::Buffer,
    pub mobile_lights: wgpu::Buffer,
    pub shadow_sampler: wgpu::Sampler,
    pub linear_sampler: wgpu::Sampler,
    pub targets: Targets,
}

impl SharedResources {
    /// Group-0 resources by their names in `Common.ush` and friends. Bind groups take the
    /// ones their reflection lists.
    pub fn view_resources(&self) -> Vec<(&'static str, wgpu::BindingResource<'_>)> {
        vec![
            ("View", self.view.as_entire_binding()),
            ("ShadowDepthTexture", wgpu::BindingResource::TextureView(&self.targets.shadow_depth.view)),
            ("ShadowDepthSampler", wgpu::BindingResource::Sampler(&self.shadow_sampler)),
            ("MobileLocalLights", self.mobile_lights.as_entire_binding()),
        ]
    }
}

/// A pipeline and the bind groups it draws with, per material where it has a material group.
pub struct MaterialDraw {
    pub pipeline: Arc<crate::pipelines::RenderPipeline>,
    pub view_group: Option<wgpu::BindGroup>,
    pub material_group: Option<wgpu::BindGroup>,
}

impl MaterialDraw {
    /// Builds the bind groups: group 0 from `view` resources, group 1 from the material.
    pub fn new(
        device: &wgpu::Device,
        pipeline: Arc<crate::pipelines::RenderPipeline>,
        view: &[(&str, wgpu::BindingResource<'_>)],
        material: Option<&wgpu::Buffer>,
    ) -> Result<MaterialDraw, PipelineError> {
        let layout = &pipeline.layout;
        let view_group = if layout.uses_group(0) { Some(layout.bind_group(device, 0, &format!("{} view", layout.label), view)?) } else { None };
        let material_group = match material {
            Some(buffer) if layout.uses_group(1) => {
                Some(layout.bind_group(device, 1, &format!("{} material", layout.label), &[("Material", buffer.as_entire_binding())])?)
            }
            _ => None,
        };
        Ok(MaterialDraw { pipeline, view_group, material_group })
    }

    pub fn bind(&self, pass: &mut wgpu::RenderPass<'_>) {
        pass.set_pipeline(&self.pipeline.pipeline);
        if let Some(g) = &self.view_group {
            pass.set_bind_group(0, g, &[]);
        }
        if let Some(g) = &self.material_group {
            pass.set_bind_group(1, g, &[]);
        }
    }
}

/// The clear color of SceneColor: the sky, seen where nothing is drawn.
pub fn sky_clear(scene: &Scene) -> wgpu::Color {
    let c = scene.sky_color * 1.6;
    wgpu::Color { r: f64::from(c.x), g: f64::from(c.y), b: f64::from(c.z), a: 0.0 }
}
