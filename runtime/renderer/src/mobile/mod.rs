//! The mobile frames: forward and deferred shading at the `es3_1` level, as Unreal's
//! `FMobileSceneRenderer` renders them (seed 001).
//!
//! Takes the bundled scene, the shared pipeline cache (every shader is an `es3_1` permutation
//! of the archive) and [`MobileOptions`]; gives a frame recorded pass by pass into a
//! [`FrameRecorder`], in the seed's order:
//! - forward (`--pipeline mobile-forward`): ShadowDepths (CSM, spot shadows, one atlas),
//!   optional PrePass, BasePass (lighting in the pixel shader, up to
//!   `MAX_DYNAMIC_POINT_LIGHTS` local lights, reflections, sky light, MSAA of
//!   `MobileOptions::msaa` samples), Translucency (resolves the MSAA color at the end of the
//!   pass), PostProcessing (Bloom, Tonemapper) in HDR, or gamma-space output straight from
//!   the base pass when mobile HDR is off;
//! - deferred (`--pipeline mobile-deferred`): ShadowDepths, optional PrePass, BasePass into
//!   SceneColor + the mobile GBuffer (A: octahedral normal, precomputed shadow, per-object
//!   data; B: metallic, specular, roughness, shading model; C: base color, AO), with the
//!   shading model in the stencil; MobileDeferredShading (the directional light as one
//!   full-screen draw, then each local light as a sphere or cone with stencil culling, default
//!   lit pixels only); Translucency; PostProcessing.
//!
//! Guarantees: at most 4 color attachments and 16 samplers per stage (the archive validated
//! every `es3_1` permutation with downlevel limits); the same passes on Vulkan and GL; every
//! pipeline is built in [`MobileFrame::new`], recording builds none. Load and store ops are
//! the ones a tile-based GPU wants wherever wgpu lets them be: transient MSAA color and depth
//! are never stored, the GBuffer and the stencil die with the lighting pass. wgpu has no
//! subpasses, so what Unreal keeps on chip between subpasses (the GBuffer, the depth) is
//! stored between render passes here.

mod base_pass;
mod deferred_shading;
mod light_volumes;
mod pipeline;
mod post_processing;
mod shadows;
mod sky;
mod translucency;
mod uniforms;

use crate::gpu::BufferInit;

use crate::frame::{FramePlan, FrameRecorder, Image, PassResult, Visualize};
use crate::gpu::Gpu;
use crate::pipelines::{PipelineCache, PipelineError};
use crate::scene::gpu::GpuScene;
use crate::scene::Scene;

pub use crate::frame::{PipelineDesc, VertexInput};
pub use pipeline::MobilePipelines;
pub use shadows::{cascade_splits, ShadowLayout};
pub use sky::{f32_to_f16, procedural_sky};
pub use uniforms::LocalLight;

/// The feature level of every mobile permutation.
pub const LEVEL: &str = "es3_1";

/// Formats of the mobile targets.
pub const SCENE_COLOR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba16Float;
/// Scene color when mobile HDR is off: gamma space, straight to the 8-bit back buffer.
pub const LDR_COLOR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
pub const OUTPUT_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
pub const FORWARD_DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;
/// Deferred: the stencil holds the shading model and the light culling bit.
pub const DEFERRED_DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth24PlusStencil8;
pub const SCENE_DEPTH_AUX_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;
pub const SHADOW_ATLAS_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;
/// GBufferA: octahedral normal (rg), precomputed shadow, per-object data.
pub const GBUFFER_A_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
/// GBufferB: metallic, specular, roughness, shading model.
pub const GBUFFER_B_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
/// GBufferC: base color (sRGB encoded), AO.
pub const GBUFFER_C_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8UnormSrgb;

/// Stencil bits of the deferred path: bit 0 marks pixels in front of a light volume (the
/// sandbox bit), bits 4 to 6 hold the shading model (`GET_STENCIL_MOBILE_SM_MASK`).
pub const STENCIL_SANDBOX: u32 = 0x01;
pub const STENCIL_SHADING_MODEL_SHIFT: u32 = 4;
pub const STENCIL_SHADING_MODEL_MASK: u32 = 0x70;
/// Stencil value of a default lit pixel.
pub const STENCIL_DEFAULT_LIT: u32 = 1 << STENCIL_SHADING_MODEL_SHIFT;

/// Forward or deferred (`r.Mobile.ShadingPath`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ShadingPath {
    Forward,
    Deferred,
}

impl ShadingPath {
    /// The `--pipeline` name.
    pub fn name(self) -> &'static str {
        match self {
            ShadingPath::Forward => "mobile-forward",
            ShadingPath::Deferred => "mobile-deferred",
        }
    }
}

/// The project settings of the mobile renderer.
#[derive(Clone, Debug, PartialEq)]
pub struct MobileOptions {
    pub path: ShadingPath,
    /// Mobile HDR: linear scene color and PostProcessing. Off (forward only): the base pass
    /// writes gamma-space color straight to the output (`OUTPUT_GAMMA_SPACE`).
    pub hdr: bool,
    /// MSAA samples of the forward frame (1 or 4); deferred never multisamples. Lowered to 1
    /// where the adapter cannot multisample the targets.
    pub msaa: u32,
    /// CSM cascades of the directional light (1 to 4; Unreal's default 2).
    pub cascades: u32,
    /// View distance the cascades cover (meters).
    pub shadow_distance: f32,
    /// `DIRECTIONAL_LIGHT_CSM`.
    pub csm: bool,
    /// Shadows of spot lights that cast them, in the shared atlas.
    pub spot_shadows: bool,
    /// The full depth prepass (`r.Mobile.EarlyZPass`).
    pub full_prepass: bool,
    /// `MAX_DYNAMIC_POINT_LIGHTS` of the forward base pass: 0, 1, 2 or 4.
    pub max_dynamic_point_lights: u32,
    /// Image-based reflections from the captures.
    pub reflections: bool,
    /// `HQ_REFLECTIONS`: blend up to 3 captures instead of the nearest one.
    pub hq_reflections: bool,
    /// `ENABLE_SKY_LIGHT`.
    pub sky_light: bool,
    /// `USE_VERTEX_FOG` (forward).
    pub vertex_fog: bool,
    pub bloom: bool,
    pub translucency: bool,
    /// Local lights of the scene to use, in scene order (points, then spots); `None`: all.
    pub local_light_limit: Option<usize>,
    /// When the passes' pipelines are created (eagerly, when the frame is built, by default).
    pub pipelines: crate::frame::Creation,
}

impl Default for MobileOptions {
    fn default() -> Self {
        MobileOptions {
            path: ShadingPath::Forward,
            hdr: true,
            msaa: 4,
            cascades: 2,
            shadow_distance: 30.0,
            csm: true,
            spot_shadows: true,
            full_prepass: false,
            max_dynamic_point_lights: 4,
            reflections: true,
            hq_reflections: true,
            sky_light: true,
            vertex_fog: true,
            bloom: true,
            translucency: true,
            local_light_limit: None,
            pipelines: crate::frame::Creation::Eager,
        }
    }
}

impl MobileOptions {
    pub fn forward() -> MobileOptions {
        MobileOptions::default()
    }

    pub fn deferred() -> MobileOptions {
        MobileOptions { path: ShadingPath::Deferred, msaa: 1, vertex_fog: false, ..MobileOptions::default() }
    }

    /// The settings under which forward, deferred and desktop frames can be compared: effects
    /// one of them lacks are off (MSAA, vertex fog, reflections, bloom, translucency).
    pub fn comparable(path: ShadingPath) -> MobileOptions {
        MobileOptions {
            path,
            msaa: 1,
            vertex_fog: false,
            reflections: false,
            hq_reflections: false,
            bloom: false,
            translucency: false,
            ..MobileOptions::default()
        }
    }

    fn check(&self) -> Result<(), PipelineError> {
        // Options outside these ranges name no permutation of the archive (or no frame).
        let bad =
            |m: &str| Err(PipelineError::Lookup(crate::shaders::LookupError::BadName(format!("mobile options: {m}"))));
        if ![0, 1, 2, 4].contains(&self.max_dynamic_point_lights) {
            return bad("MAX_DYNAMIC_POINT_LIGHTS is 0, 1, 2 or 4");
        }
        if !(1..=4).contains(&self.cascades) {
            return bad("the directional light has 1 to 4 cascades");
        }
        if self.path == ShadingPath::Deferred && !self.hdr {
            return bad("mobile deferred shading needs mobile HDR");
        }
        if ![1, 4].contains(&self.msaa) {
            return bad("MSAA is 1 or 4 samples");
        }
        Ok(())
    }
}

pub use crate::passes::Target;

/// A render target of the mobile frames: a multisampled one is an attachment only; a
/// single-sampled one is also sampled and (but for the 24-bit depth-stencil, which cannot
/// be copied) dumped.
fn target(
    device: &wgpu::Device,
    name: &'static str,
    format: wgpu::TextureFormat,
    size: (u32, u32),
    samples: u32,
) -> Target {
    let mut usage = wgpu::TextureUsages::RENDER_ATTACHMENT;
    if samples == 1 {
        usage |= wgpu::TextureUsages::TEXTURE_BINDING;
        // Depth-stencil with a 24-bit depth cannot be copied out; everything else can be dumped.
        if format != DEFERRED_DEPTH_FORMAT {
            usage |= wgpu::TextureUsages::COPY_SRC;
        }
    }
    Target::with_usage(device, name, format, size, samples, usage)
}

/// The render targets of one mobile frame.
pub struct MobileTargets {
    pub width: u32,
    pub height: u32,
    pub samples: u32,
    pub shadow_atlas: Target,
    /// Forward with MSAA: the multisampled color and depth (never stored).
    pub scene_color_msaa: Option<Target>,
    pub scene_depth: Target,
    /// The (resolved) scene color: HDR, or the gamma-space output when HDR is off.
    pub scene_color: Target,
    pub gbuffer_a: Option<Target>,
    pub gbuffer_b: Option<Target>,
    pub gbuffer_c: Option<Target>,
    pub scene_depth_aux: Option<Target>,
    /// The tonemapped 8-bit frame (HDR only).
    pub output: Option<Target>,
}

impl MobileTargets {
    fn new(
        device: &wgpu::Device,
        options: &MobileOptions,
        samples: u32,
        width: u32,
        height: u32,
        shadows: &ShadowLayout,
    ) -> MobileTargets {
        let size = (width, height);
        let deferred = options.path == ShadingPath::Deferred;
        let color_format = if options.hdr { SCENE_COLOR_FORMAT } else { LDR_COLOR_FORMAT };
        let depth_format = if deferred { DEFERRED_DEPTH_FORMAT } else { FORWARD_DEPTH_FORMAT };
        let gbuffer = |name, format| deferred.then(|| target(device, name, format, size, 1));
        MobileTargets {
            width,
            height,
            samples,
            shadow_atlas: target(
                device,
                "ShadowAtlas",
                SHADOW_ATLAS_FORMAT,
                (shadows.atlas_width, shadows.atlas_height),
                1,
            ),
            scene_color_msaa: (samples > 1).then(|| target(device, "SceneColorMSAA", color_format, size, samples)),
            scene_depth: target(device, "SceneDepth", depth_format, size, samples),
            scene_color: target(device, "SceneColor", color_format, size, 1),
            gbuffer_a: gbuffer("GBufferA", GBUFFER_A_FORMAT),
            gbuffer_b: gbuffer("GBufferB", GBUFFER_B_FORMAT),
            gbuffer_c: gbuffer("GBufferC", GBUFFER_C_FORMAT),
            scene_depth_aux: deferred.then(|| target(device, "SceneDepthAux", SCENE_DEPTH_AUX_FORMAT, size, 1)),
            output: options.hdr.then(|| target(device, "Output", OUTPUT_FORMAT, size, 1)),
        }
    }

    /// The color attachment the base pass draws into (multisampled where MSAA is on).
    pub fn color_attachment(&self) -> &Target {
        self.scene_color_msaa.as_ref().unwrap_or(&self.scene_color)
    }

    /// The frame's final image.
    pub fn final_image(&self) -> &Target {
        self.output.as_ref().unwrap_or(&self.scene_color)
    }
}

/// Resources most passes bind, by their names in the shaders.
pub struct SharedResources {
    pub view: wgpu::Buffer,
    /// The camera's view-projection (the CPU copy of `View.view_proj`).
    pub view_proj: glam::Mat4,
    /// CSM cascades in the atlas (0: `DIRECTIONAL_LIGHT_CSM` off).
    pub cascades: usize,
    pub shadow_sampler: wgpu::Sampler,
    pub linear_sampler: wgpu::Sampler,
    pub captures: sky::Captures,
}

impl SharedResources {
    /// The `View` buffer of `view`, the samplers and the reflection captures.
    fn new(
        device: &wgpu::Device,
        view: &crate::scene::view::SceneView,
        cascades: usize,
        captures: sky::Captures,
    ) -> SharedResources {
        SharedResources {
            view_proj: view.view_proj,
            cascades,
            view: device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("View"),
                contents: bytemuck::bytes_of(view),
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            }),
            shadow_sampler: device.create_sampler(&wgpu::SamplerDescriptor {
                label: Some("ShadowSampler"),
                mag_filter: wgpu::FilterMode::Linear,
                min_filter: wgpu::FilterMode::Linear,
                compare: Some(wgpu::CompareFunction::GreaterEqual),
                ..Default::default()
            }),
            linear_sampler: device.create_sampler(&wgpu::SamplerDescriptor {
                label: Some("LinearSampler"),
                mag_filter: wgpu::FilterMode::Linear,
                min_filter: wgpu::FilterMode::Linear,
                ..Default::default()
            }),
            captures,
        }
    }

    /// Group 0 of the lit shaders: `View`, the shadow atlas and the reflection captures.
    pub fn view_resources<'a>(&'a self, targets: &'a MobileTargets) -> Vec<(&'static str, wgpu::BindingResource<'a>)> {
        let c = &self.captures;
        vec![
            ("View", self.view.as_entire_binding()),
            ("ShadowAtlas", wgpu::BindingResource::TextureView(&targets.shadow_atlas.view)),
            ("ShadowSampler", wgpu::BindingResource::Sampler(&self.shadow_sampler)),
            ("ReflectionCubemap0", wgpu::BindingResource::TextureView(&c.views[0])),
            ("ReflectionCubemap1", wgpu::BindingResource::TextureView(&c.views[1])),
            ("ReflectionCubemap2", wgpu::BindingResource::TextureView(&c.views[2])),
            ("ReflectionSampler", wgpu::BindingResource::Sampler(&c.sampler)),
        ]
    }
}

/// One mobile frame, built once for a scene, options and size.
pub struct MobileFrame {
    pub options: MobileOptions,
    pub targets: MobileTargets,
    pub shadow_layout: ShadowLayout,
    /// The local lights of the frame: all of them (deferred), the forward base pass shades
    /// the first `MAX_DYNAMIC_POINT_LIGHTS` nearest the camera.
    pub local_lights: Vec<LocalLight>,
    pub forward_lights: Vec<LocalLight>,
    shared: SharedResources,
    shadow_depths: shadows::ShadowDepths,
    prepass: Option<base_pass::PrePass>,
    base_pass: base_pass::BasePass,
    deferred_shading: Option<deferred_shading::MobileDeferredShading>,
    translucency: Option<translucency::Translucency>,
    post_processing: Option<post_processing::PostProcessing>,
    pipelines_built: usize,
}

/// What a mobile frame is built with: the device, the runtime's pipeline cache and the scene
/// (with its GPU buffers).
#[derive(Clone, Copy)]
pub struct MobileContext<'a> {
    pub gpu: &'a Gpu,
    pub cache: &'a PipelineCache,
    pub scene: &'a Scene,
    pub gpu_scene: &'a GpuScene,
}

impl MobileFrame {
    /// Builds every target, buffer and pipeline the frame uses, at `size` (width, height).
    pub fn new(
        context: &MobileContext<'_>,
        options: MobileOptions,
        size: (u32, u32),
    ) -> Result<MobileFrame, PipelineError> {
        let MobileContext { gpu, cache, scene, gpu_scene } = *context;
        let (width, height) = size;
        options.check()?;
        let device = &gpu.device;
        let samples = if options.path == ShadingPath::Forward { msaa_samples(&gpu.adapter, &options) } else { 1 };
        let shadow_layout = ShadowLayout::new(scene, &options, width as f32 / height as f32);
        let targets = MobileTargets::new(device, &options, samples, width, height, &shadow_layout);
        let mut local_lights = uniforms::local_lights(scene, &shadow_layout);
        if let Some(limit) = options.local_light_limit {
            local_lights.truncate(limit);
        }
        let forward_lights =
            uniforms::forward_lights(&local_lights, scene.camera.position, options.max_dynamic_point_lights as usize);
        let captures = sky::Captures::new(device, &gpu.queue, scene);
        let view = uniforms::view_uniforms(scene, &options, size, &shadow_layout, &forward_lights, &captures);
        let shared = SharedResources::new(device, &view, shadow_layout.cascades.len(), captures);
        let pipelines = MobilePipelines::new(cache, device, options.pipelines);
        let shadow_depths = shadows::ShadowDepths::new(&pipelines, gpu_scene, &shadow_layout)?;
        let prepass = if options.full_prepass {
            Some(base_pass::PrePass::new(&pipelines, gpu_scene, &options, &targets, &shared)?)
        } else {
            None
        };
        let base_pass = base_pass::BasePass::new(&pipelines, gpu_scene, &options, &targets, &shared)?;
        let deferred_shading = if options.path == ShadingPath::Deferred {
            Some(deferred_shading::MobileDeferredShading::new(&pipelines, &options, &targets, &shared, &local_lights)?)
        } else {
            None
        };
        let translucency = if options.translucency {
            translucency::Translucency::new(&pipelines, gpu_scene, scene, &options, &targets, &shared)?
        } else {
            None
        };
        let post_processing = if options.hdr {
            Some(post_processing::PostProcessing::new(&pipelines, &options, &targets, &shared)?)
        } else {
            None
        };
        let pipelines_built = pipelines.count();
        Ok(MobileFrame {
            options,
            targets,
            shadow_layout,
            local_lights,
            forward_lights,
            shared,
            shadow_depths,
            prepass,
            base_pass,
            deferred_shading,
            translucency,
            post_processing,
            pipelines_built,
        })
    }

    /// How many distinct pipelines the frame uses (all created before its first frame unless
    /// it was built with [`crate::frame::Creation::Lazy`]).
    pub fn pipeline_count(&self) -> usize {
        self.pipelines_built
    }

    /// The frame's passes in the order [`MobileFrame::record`] records them, each with what it
    /// reads and writes (Translucency is listed where the options have it, though a scene
    /// without translucent surfaces skips it).
    pub fn plan(options: &MobileOptions) -> FramePlan {
        let mut plan = FramePlan::new(&["Scene", "View", "ReflectionCaptures"], &[]).pass(&shadows::PASS);
        if options.full_prepass {
            plan = plan.pass(&base_pass::PREPASS);
        }
        plan = plan.pass(Self::base_pass_decl_for(options.path));
        if options.path == ShadingPath::Deferred {
            plan = plan.pass(&deferred_shading::PASS);
        }
        if options.translucency {
            plan = plan.pass(&translucency::PASS);
        }
        if options.hdr {
            plan = plan.pass(&post_processing::PASS);
        }
        plan
    }

    fn base_pass_decl_for(path: ShadingPath) -> &'static crate::frame::PassDecl {
        match path {
            ShadingPath::Forward => &base_pass::FORWARD_PASS,
            ShadingPath::Deferred => &base_pass::DEFERRED_PASS,
        }
    }

    fn base_pass_decl(&self) -> &'static crate::frame::PassDecl {
        Self::base_pass_decl_for(if self.deferred_shading.is_some() {
            ShadingPath::Deferred
        } else {
            ShadingPath::Forward
        })
    }

    /// Records the frame's passes, in the seed's order.
    pub fn record(&self, recorder: &mut FrameRecorder<'_>, scene: &GpuScene) {
        let t = &self.targets;
        recorder.pass(shadows::PASS.name, |ctx| self.shadow_depths.record(ctx, scene, &t.shadow_atlas));
        if let Some(prepass) = &self.prepass {
            recorder.pass(base_pass::PREPASS.name, |ctx| prepass.record(ctx, scene, t));
        }
        recorder.pass(self.base_pass_decl().name, |ctx| {
            self.base_pass.record(ctx, scene, t, self.prepass.is_some(), self.translucency.is_some())
        });
        if let Some(d) = &self.deferred_shading {
            recorder.pass(deferred_shading::PASS.name, |ctx| d.record(ctx, t));
        }
        if let Some(tr) = &self.translucency {
            recorder.pass(translucency::PASS.name, |ctx| tr.record(ctx, scene, t));
        }
        if let Some(pp) = &self.post_processing {
            recorder.pass(post_processing::PASS.name, |ctx| pp.record(ctx, t));
        }
    }

    /// The frame's final 8-bit image.
    pub fn output(&self) -> &wgpu::Texture {
        &self.targets.final_image().texture
    }

    /// How the final image is dumped.
    pub fn output_visualize(&self) -> Visualize {
        Visualize::Direct
    }

    pub fn shared(&self) -> &SharedResources {
        &self.shared
    }

    /// Copies the final image back (waits for the GPU).
    pub fn read_output(&self, device: &wgpu::Device, queue: &wgpu::Queue) -> Image {
        read_rgba8(device, queue, self.output())
    }
}

/// Reads an `Rgba8Unorm` texture back into an image.
pub fn read_rgba8(device: &wgpu::Device, queue: &wgpu::Queue, texture: &wgpu::Texture) -> Image {
    let (width, height) = (texture.width(), texture.height());
    let padded = (width * 4).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
    let buffer = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("mobile readback"),
        size: u64::from(padded) * u64::from(height),
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("mobile readback") });
    encoder.copy_texture_to_buffer(
        wgpu::TexelCopyTextureInfo {
            texture,
            mip_level: 0,
            origin: wgpu::Origin3d::ZERO,
            aspect: wgpu::TextureAspect::All,
        },
        wgpu::TexelCopyBufferInfo {
            buffer: &buffer,
            layout: wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(padded),
                rows_per_image: Some(height),
            },
        },
        wgpu::Extent3d { width, height, depth_or_array_layers: 1 },
    );
    queue.submit([encoder.finish()]);
    buffer.slice(..).map_async(wgpu::MapMode::Read, |_| {});
    let _ = device.poll(wgpu::PollType::wait_indefinitely());
    let mut rgba = Vec::with_capacity((width * height * 4) as usize);
    if let Ok(view) = buffer.slice(..).get_mapped_range() {
        for y in 0..height as usize {
            let row = &view[y * padded as usize..][..width as usize * 4];
            rgba.extend_from_slice(row);
        }
    }
    // Alpha carries nothing for the viewer.
    for px in rgba.chunks_exact_mut(4) {
        px[3] = 255;
    }
    Image { width, height, rgba }
}

/// Builds a frame, records it once and returns every pass (with its images when `capture`)
/// and the final image.
pub fn render(
    context: &MobileContext<'_>,
    options: MobileOptions,
    size: (u32, u32),
    capture: bool,
) -> Result<(Vec<PassResult>, Image), PipelineError> {
    let MobileContext { gpu, cache, gpu_scene, .. } = *context;
    let creation = options.pipelines;
    let frame = MobileFrame::new(context, options, size)?;
    let depth_copy = if gpu.depth_copies { None } else { Some(crate::frame::DepthCopy::new(cache, LEVEL, creation)?) };
    let mut recorder = FrameRecorder::new(&gpu.device, &gpu.queue, cache, gpu.timestamps, capture, depth_copy);
    frame.record(&mut recorder, gpu_scene);
    let passes = recorder.finish()?;
    let image = frame.read_output(&gpu.device, &gpu.queue);
    Ok((passes, image))
}

/// 4 where the adapter can multisample and resolve the forward targets, else 1.
fn msaa_samples(adapter: &wgpu::Adapter, options: &MobileOptions) -> u32 {
    if options.msaa <= 1 {
        return 1;
    }
    let color = if options.hdr { SCENE_COLOR_FORMAT } else { LDR_COLOR_FORMAT };
    let c = adapter.get_texture_format_features(color);
    let d = adapter.get_texture_format_features(FORWARD_DEPTH_FORMAT);
    let ok = c.flags.sample_count_supported(options.msaa)
        && c.flags.contains(wgpu::TextureFormatFeatureFlags::MULTISAMPLE_RESOLVE)
        && d.flags.sample_count_supported(options.msaa);
    if ok {
        options.msaa
    } else {
        1
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn options_outside_the_permutations_are_errors() {
        let check = |o: MobileOptions| o.check().map_err(|e| e.to_string());
        assert_eq!(check(MobileOptions::forward()), Ok(()));
        assert_eq!(check(MobileOptions::deferred()), Ok(()));
        assert_eq!(
            check(MobileOptions { max_dynamic_point_lights: 3, ..MobileOptions::forward() }),
            Err("cannot name permutation: mobile options: MAX_DYNAMIC_POINT_LIGHTS is 0, 1, 2 or 4".into())
        );
        assert_eq!(
            check(MobileOptions { hdr: false, ..MobileOptions::deferred() }),
            Err("cannot name permutation: mobile options: mobile deferred shading needs mobile HDR".into())
        );
        assert_eq!(
            check(MobileOptions { cascades: 5, ..MobileOptions::forward() }),
            Err("cannot name permutation: mobile options: the directional light has 1 to 4 cascades".into())
        );
        assert_eq!(
            check(MobileOptions { msaa: 2, ..MobileOptions::forward() }),
            Err("cannot name permutation: mobile options: MSAA is 1 or 4 samples".into())
        );
    }

    #[test]
    fn every_read_of_the_forward_frame_is_written_before_it() {
        for options in [
            MobileOptions::forward(),
            MobileOptions { full_prepass: true, ..MobileOptions::forward() },
            MobileOptions { hdr: false, ..MobileOptions::forward() },
        ] {
            let plan = MobileFrame::plan(&options);
            assert_eq!(plan.check(), Ok(()), "{options:?}");
            assert!(!plan.names().contains(&"MobileDeferredShading"));
        }
        let plan = MobileFrame::plan(&MobileOptions::forward());
        assert_eq!(plan.names(), vec!["ShadowDepths", "BasePass", "Translucency", "PostProcessing"]);
    }

    #[test]
    fn every_read_of_the_deferred_frame_is_written_before_it() {
        for options in [MobileOptions::deferred(), MobileOptions { full_prepass: true, ..MobileOptions::deferred() }] {
            let plan = MobileFrame::plan(&options);
            assert_eq!(plan.check(), Ok(()), "{options:?}");
        }
        let plan = MobileFrame::plan(&MobileOptions::deferred());
        assert_eq!(
            plan.names(),
            vec!["ShadowDepths", "BasePass", "MobileDeferredShading", "Translucency", "PostProcessing"]
        );
        // the shading reads the GBuffer: the forward BasePass in its place would not do
        let wrong = FramePlan::new(&["Scene", "View", "ReflectionCaptures"], &[])
            .pass(&shadows::PASS)
            .pass(&base_pass::FORWARD_PASS)
            .pass(&deferred_shading::PASS);
        assert!(wrong.check().is_err());
    }

    #[test]
    fn comparable_options_turn_off_what_one_path_lacks() {
        for path in [ShadingPath::Forward, ShadingPath::Deferred] {
            let o = MobileOptions::comparable(path);
            assert_eq!((o.msaa, o.vertex_fog, o.reflections, o.bloom, o.translucency), (1, false, false, false, false));
            assert!(o.hdr && o.csm && o.sky_light && o.max_dynamic_point_lights == 4);
        }
    }
}
