//! The desktop deferred frame (`--pipeline desktop`, feature level `sm5`), pass by pass as
//! the seeds describe Unreal's: PrePass, ComputeLightGrid, ShadowDepths, BasePass,
//! AmbientOcclusion, Lighting, ExponentialHeightFog, Translucency, PostProcessing.
//!
//! Takes a [`Scene`], a [`PipelineCache`] over an archive holding the `sm5` permutations of
//! `shader_src/Private/Desktop/` and [`DesktopOptions`]; gives the tonemapped sRGB frame and,
//! through the [`FrameRecorder`], every pass's (and named step's) output and GPU time.
//! Guarantees: every pipeline the frame uses is created in [`DesktopFrame::new`] (the
//! warm-up; with [`crate::frame::Creation::Lazy`], when a frame first asks for it), and each
//! draw asks the cache for its pipeline as it is recorded; a permutation missing from the
//! archive, or a resource a permutation binds that the frame does not have, is an error
//! naming it, never a panic.

mod ambient_occlusion;
mod base_pass;
mod fog;
mod light_grid;
mod lighting;
mod pipelines;
mod post_processing;
mod prepass;
mod resources;
mod shadow_depths;
mod translucency;
pub mod view;

// The stateful effects: particles (`crate::passes::particles`), occlusion, HZB, volumetric fog, velocity, translucency
// volumes, reflections, distortion, temporal post-processing, driven by `effects::Effects`.
pub mod distortion;
pub mod effects;
pub mod eye_adaptation;
pub mod frame_view;
pub mod hzb;
pub mod motion_blur;
pub mod occlusion;
pub mod reflections;
pub mod taa;
pub mod translucent_volume;
pub mod velocity;
pub mod volumetric_fog;

use crate::frame::{FramePlan, FrameRecorder, Image, PassResult, Visualize};
use crate::pipelines::{PipelineCache, PipelineError};
use crate::scene::view::SceneView;
use crate::scene::Scene;

pub use resources::{frame_lights, FrameLight, LocalShadow};
pub use shadow_depths::{cascade_matrices, cube_face_matrices, CASCADE_SPLITS};
pub use view::FrameView;

/// Which way unshadowed local lights are shaded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LightingPath {
    /// Per-light volumes, or tiled above `tiled_threshold` lights (Unreal's rule).
    Auto,
    /// Always per-light volumes.
    PerLight,
    /// Always the tiled compute pass.
    Tiled,
}

#[derive(Clone, Debug)]
pub struct DesktopOptions {
    pub width: u32,
    pub height: u32,
    /// Above this many unshadowed local lights, `Auto` shades them in one tiled compute
    /// pass (Unreal switches above 80).
    pub tiled_threshold: usize,
    pub lighting_path: LightingPath,
    /// The tiled pass reads each pixel's lights from the light grid (`USE_LIGHT_GRID=1`)
    /// instead of culling them per 16x16 tile itself, as Unreal 4.17 does.
    pub tiled_uses_light_grid: bool,
    /// Shadow filtering, 1 to 3 (1x1, 3x3, 5x5 PCF): `SHADOW_QUALITY`.
    pub shadow_quality: u32,
    /// Ambient occlusion quality, 0 to 2 (4, 8, 12 samples): `SHADER_QUALITY`.
    pub ao_quality: u32,
    /// Size of one cascade of the directional light's shadow atlas (others are half).
    pub shadow_map_size: u32,
    /// Selects the AO jitter of this frame.
    pub frame_index: u32,
    /// Effects the mobile paths lack, on by default; the cross-check against the mobile
    /// frames turns them off. `ambient_occlusion`: the AmbientOcclusion pass; `bloom` and
    /// `vignette`: the tonemapper's inputs; `sky_gradient`: the sky's horizon gradient and sun
    /// disk (off: the flat sky color the mobile frames clear to).
    pub ambient_occlusion: bool,
    pub bloom: bool,
    pub vignette: bool,
    pub sky_gradient: bool,
    /// Format of the output target (sRGB, so the tonemapper's output is encoded on write).
    pub output_format: wgpu::TextureFormat,
    /// What the effects change in the frame: TAA, motion blur, eye adaptation,
    /// volumetric fog, sprites, reflections (`EffectOptions::off()` for none).
    pub effects: effects::EffectOptions,
    /// The scene's particle emitters are warmed up when the frame is built
    /// ([`crate::passes::particles::PREWARM_STEPS`] steps, as Unreal's WarmupTime), so the
    /// first image shows the fire burning. Off by default: the frame starts its emitters
    /// cold (its golden image); the [`crate::Renderer`] (kiln-view) turns it on.
    pub warm_up_particles: bool,
    /// When the passes' pipelines are created (eagerly, when the frame is built, by default).
    pub pipelines: crate::frame::Creation,
}

impl Default for DesktopOptions {
    fn default() -> Self {
        DesktopOptions {
            width: 640,
            height: 360,
            tiled_threshold: 80,
            lighting_path: LightingPath::Auto,
            tiled_uses_light_grid: true,
            shadow_quality: 2,
            ao_quality: 2,
            shadow_map_size: 512,
            frame_index: 0,
            ambient_occlusion: true,
            bloom: true,
            vignette: true,
            sky_gradient: true,
            output_format: wgpu::TextureFormat::Rgba8UnormSrgb,
            effects: effects::EffectOptions::default(),
            warm_up_particles: false,
            pipelines: crate::frame::Creation::Eager,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum DesktopError {
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    #[error("{what}: wgpu rejected it: {message}")]
    Wgpu { what: String, message: String },
    #[error(
        "pipeline `{pipeline}`: bind group {group} binding {binding} `{name}` is not a resource of the desktop frame"
    )]
    MissingResource { pipeline: String, group: u32, binding: u32, name: String },
    #[error("the scene was uploaded for the mobile frames, not in the desktop's rows layout")]
    SceneLayout,
}

impl From<crate::shaders::LookupError> for DesktopError {
    fn from(e: crate::shaders::LookupError) -> Self {
        DesktopError::Pipeline(e.into())
    }
}

/// What passes read while they are built.
pub(crate) struct PassSetup<'a> {
    pub device: &'a wgpu::Device,
    pub pipelines: &'a pipelines::Pipelines<'a>,
    pub scene: &'a Scene,
    pub buffers: &'a resources::SceneBuffers,
    pub targets: &'a resources::Targets,
    pub samplers: &'a resources::Samplers,
    pub view: &'a FrameView,
    pub view_buffer: &'a wgpu::Buffer,
    pub lights: &'a [FrameLight],
    pub lights_buffer: &'a wgpu::Buffer,
    pub options: &'a DesktopOptions,
}

impl PassSetup<'_> {
    /// View, instances and materials: what every mesh pass binds.
    pub fn scene_resources(&self) -> Vec<(&'static str, wgpu::BindingResource<'_>)> {
        vec![
            ("View", self.view_buffer.as_entire_binding()),
            ("Instances", self.buffers.instances.as_entire_binding()),
            ("Materials", self.buffers.materials.as_entire_binding()),
        ]
    }
}

/// The desktop frame, built once per (scene, size): resources, pipelines, bind groups.
pub struct DesktopFrame {
    device: wgpu::Device,
    queue: wgpu::Queue,
    timestamps: bool,
    options: DesktopOptions,
    buffers: resources::SceneBuffers,
    targets: resources::Targets,
    output: resources::Texture,
    /// Bound where the directional light has no cascades (kept alive with the bind groups).
    _dummy_shadow: resources::Texture,
    _lights_buffer: wgpu::Buffer,
    /// The one `SceneView` buffer every pass binds as `View`.
    view_buffer: wgpu::Buffer,
    _samplers: resources::Samplers,
    /// This frame's view (the camera the effects render with, unjittered), refreshed as every
    /// frame begins: everything camera-dependent is computed from it per frame.
    view: std::sync::Mutex<FrameView>,
    lights: Vec<FrameLight>,
    prepass: prepass::PrePass,
    light_grid: light_grid::LightGrid,
    shadows: shadow_depths::ShadowDepths,
    base_pass: base_pass::BasePass,
    ambient_occlusion: ambient_occlusion::AmbientOcclusion,
    lighting: lighting::Lighting,
    fog: fog::HeightFog,
    translucency: translucency::Translucency,
    post: post_processing::PostProcessing,
    effects: effects::Effects,
    /// The `SceneView` as built: what the scene and the light grid decide; each frame sets
    /// its camera (the effects', jittered) and writes it.
    base_view: SceneView,
    /// Every object's instance rows: (object, first row, local bounds centre, row).
    object_rows: Vec<(usize, u32, glam::Vec3, view::InstanceGpu)>,
    /// ShadowFrustumQueries skip the shadow work of lights whose volume is hidden (on by
    /// default; off renders every shadow, for comparisons).
    shadow_frustum_culling: std::sync::atomic::AtomicBool,
}

/// The passes of the desktop frame, and the cleared shadow map bound where a light has none.
struct BuiltPasses {
    dummy_shadow: resources::Texture,
    prepass: prepass::PrePass,
    light_grid: light_grid::LightGrid,
    shadows: shadow_depths::ShadowDepths,
    base_pass: base_pass::BasePass,
    ambient_occlusion: ambient_occlusion::AmbientOcclusion,
    lighting: lighting::Lighting,
    fog: fog::HeightFog,
    post: post_processing::PostProcessing,
    effects: effects::Effects,
    translucency: translucency::Translucency,
}

/// Builds every pass, each after the passes whose outputs it binds.
fn build_passes(b: &PassSetup<'_>, queue: &wgpu::Queue, base_view: &SceneView) -> Result<BuiltPasses, DesktopError> {
    let dummy_shadow = shadow_depths::dummy_shadow_texture(b.device, queue);
    let prepass = prepass::PrePass::new(b)?;
    let light_grid = light_grid::LightGrid::new(b)?;
    let shadows = shadow_depths::ShadowDepths::new(b)?;
    let base_pass = base_pass::BasePass::new(b)?;
    let ambient_occlusion = ambient_occlusion::AmbientOcclusion::new(b)?;
    let lighting = lighting::Lighting::new(b, &shadows, &dummy_shadow, &light_grid)?;
    let fog = fog::HeightFog::new(b)?;
    let post = post_processing::PostProcessing::new(b, b.options.output_format)?;
    let grid = effects::LightGridInputs {
        lights: b.lights_buffer,
        num_culled_lights: &light_grid.num_culled_lights,
        culled_light_data: &light_grid.culled_light_data,
        size: base_view.light_grid_size,
        z_params: base_view.light_grid_z_params,
    };
    let inputs =
        EffectInputs { shadows: &shadows, dummy_shadow: &dummy_shadow, light_grid: grid, view_buffer: b.view_buffer };
    let effects = build_effects(b, queue, inputs)?;
    effects.set_options(b.options.effects);
    let translucency =
        translucency::Translucency::new(b, &light_grid, &shadows, &dummy_shadow, &effects.translucency_volume())?;
    Ok(BuiltPasses {
        dummy_shadow,
        prepass,
        light_grid,
        shadows,
        base_pass,
        ambient_occlusion,
        lighting,
        fog,
        post,
        effects,
        translucency,
    })
}

impl DesktopFrame {
    /// Uploads the scene, creates the targets and builds every pass (and, unless the options
    /// say [`crate::frame::Creation::Lazy`], every pipeline).
    /// `timestamps`: the device has timestamp queries inside encoders.
    pub fn new(
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        timestamps: bool,
        cache: &PipelineCache,
        scene: &Scene,
        options: DesktopOptions,
    ) -> Result<DesktopFrame, DesktopError> {
        use crate::scene::gpu::{GpuScene, SceneLayout};
        let gpu_scene = GpuScene::upload(device, scene, SceneLayout::Rows);
        DesktopFrame::with_gpu_scene(device, queue, timestamps, cache, scene, &gpu_scene, options)
    }

    /// As [`DesktopFrame::new`], over `gpu_scene`: `scene` uploaded in
    /// [`SceneLayout::Rows`](crate::scene::gpu::SceneLayout::Rows) (the renderer's upload,
    /// whose buffers the frame shares).
    #[allow(clippy::too_many_arguments)]
    pub fn with_gpu_scene(
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        timestamps: bool,
        cache: &PipelineCache,
        scene: &Scene,
        gpu_scene: &crate::scene::gpu::GpuScene,
        options: DesktopOptions,
    ) -> Result<DesktopFrame, DesktopError> {
        let (w, h) = (options.width.max(1), options.height.max(1));
        let view = FrameView::new(scene, w, h);
        let lights = frame_lights(scene);
        let gpu_lights: Vec<view::LocalLightGpu> = lights.iter().map(|l| l.gpu).collect();
        let lights_buffer = resources::storage(device, "LocalLights", &gpu_lights, wgpu::BufferUsages::empty());
        let base_view =
            view.scene_view(scene, lights.len() as u32, options.frame_index, u32::from(!options.sky_gradient));
        // the frame's one View buffer
        let view_buffer = crate::gpu_types::uniform_buffer(device, "View", &base_view);
        let buffers = resources::SceneBuffers::new(device, gpu_scene)?;
        let targets = resources::Targets::new(device, w, h);
        let samplers = resources::Samplers::new(device, queue);
        let output = resources::Texture::target(device, "Output", options.output_format, w, h);
        let pipelines = pipelines::Pipelines::new(cache, "sm5", options.pipelines);
        let b = PassSetup {
            device,
            pipelines: &pipelines,
            scene,
            buffers: &buffers,
            targets: &targets,
            samplers: &samplers,
            view: &view,
            view_buffer: &view_buffer,
            lights: &lights,
            lights_buffer: &lights_buffer,
            options: &options,
        };
        let BuiltPasses {
            dummy_shadow,
            prepass,
            light_grid,
            shadows,
            base_pass,
            ambient_occlusion,
            lighting,
            fog,
            post,
            effects,
            translucency,
        } = build_passes(&b, queue, &base_view)?;
        let object_rows = object_rows(scene, &buffers);
        Ok(DesktopFrame {
            device: device.clone(),
            queue: queue.clone(),
            timestamps,
            options,
            buffers,
            targets,
            output,
            _dummy_shadow: dummy_shadow,
            _lights_buffer: lights_buffer,
            view_buffer,
            _samplers: samplers,
            view: std::sync::Mutex::new(view),
            lights,
            prepass,
            light_grid,
            shadows,
            base_pass,
            ambient_occlusion,
            lighting,
            fog,
            translucency,
            post,
            effects,
            base_view,
            object_rows,
            shadow_frustum_culling: std::sync::atomic::AtomicBool::new(true),
        })
    }

    /// Records the frame, pass by pass in frame order, tonemapping into `output` (a target
    /// of `DesktopOptions::output_format` and the frame's size).
    pub fn record_into(&self, frame: &mut FrameRecorder<'_>, output: (&wgpu::Texture, &wgpu::TextureView)) {
        let (s, t) = (&self.buffers, &self.targets);
        let effects = &self.effects;
        let camera = effects.begin_frame();
        let view = FrameView::from_camera(&effects.camera(), self.options.width.max(1), self.options.height.max(1));
        self.write_camera(&camera, &view);
        self.follow_camera(&view);
        effects.particle_simulation(frame);
        frame.pass(prepass::PASS.name, |ctx| self.prepass.record(ctx, s, t));
        frame.pass(light_grid::PASS.name, |ctx| self.light_grid.record(ctx, t));
        effects.begin_occlusion_tests(frame);
        effects.build_hzb(frame);
        // this frame's verdict of the ShadowFrustumQueries (read back a frame or more ago)
        let casts_shadow = |light: usize| self.casts_shadow(light);
        frame.pass(shadow_depths::PASS.name, |ctx| self.shadows.record(ctx, s, &casts_shadow));
        effects.volumetric_fog(frame);
        frame.pass(base_pass::PASS.name, |ctx| {
            self.base_pass.record(ctx, s, t);
            effects.particle_collision(ctx);
        });
        effects.velocity(frame);
        if self.options.ambient_occlusion {
            frame.pass(ambient_occlusion::PASS.name, |ctx| self.ambient_occlusion.record(ctx, t));
        }
        frame.pass(lighting::PASS.name, |ctx| {
            self.lighting.record(ctx, s, t, &casts_shadow);
            effects.translucent_volumes(ctx, &casts_shadow);
        });
        effects.reflections(frame);
        frame.pass(fog::PASS.name, |ctx| {
            self.fog.record(ctx, t);
            effects.apply_volumetric_fog(ctx);
        });
        frame.pass(translucency::PASS.name, |ctx| {
            self.translucency.record(ctx, s, t, effects.options().translucency_lighting);
            effects.particle_sprites(ctx);
        });
        effects.distortion(frame);
        frame.pass(post_processing::PASS.name, |ctx| {
            effects.temporal_post_processing(ctx);
            self.post.record(ctx, t, output);
        });
        effects.end_frame();
    }

    /// The frame's passes in the order [`DesktopFrame::record_into`] records them, each
    /// with what it reads and writes (the volumetric fog step is listed where the options
    /// have it, though a scene without fog skips it).
    pub fn plan(options: &DesktopOptions) -> FramePlan {
        let e = &options.effects;
        let mut history =
            vec!["ParticleState", "OcclusionQueries", "VolumetricFog", "TranslucencyVolume", "TAAHistory"];
        let mut inputs = vec!["Scene", "View"];
        // without eye adaptation the exposure is a constant written before the frame
        if e.eye_adaptation {
            history.push("EyeAdaptation");
        } else {
            inputs.push("EyeAdaptation");
        }
        let mut plan = FramePlan::new(&inputs, &history)
            .pass(&crate::passes::particles::SIMULATION_PASS)
            .pass(&prepass::PASS)
            .pass(&light_grid::PASS)
            .pass(&occlusion::PASS)
            .pass(&hzb::PASS)
            .pass(&shadow_depths::PASS)
            .pass(&volumetric_fog::PASS)
            .pass(&base_pass::PASS)
            .step(&crate::passes::particles::COLLISION_STEP)
            .pass(&velocity::PASS);
        if options.ambient_occlusion {
            plan = plan.pass(&ambient_occlusion::PASS);
        }
        plan = plan
            .pass(&lighting::PASS)
            .step(&translucent_volume::INJECT_STEP)
            .step(&translucent_volume::FILTER_STEP)
            .pass(&reflections::PASS)
            .pass(&fog::PASS);
        if e.volumetric_fog {
            plan = plan.step(&volumetric_fog::APPLY_STEP);
        }
        plan = plan
            .pass(&translucency::PASS)
            .step(&crate::passes::particles::SPRITES_STEP)
            .pass(&distortion::PASS)
            .pass(&post_processing::PASS)
            .step_first(if e.taa { &taa::STEP } else { &taa::BYPASS });
        if e.eye_adaptation {
            plan = plan.step_first(&eye_adaptation::STEP);
        }
        plan.step_first(&motion_blur::STEP)
    }

    /// Whether local light `light` renders its shadow depths and projection this frame: its
    /// ShadowFrustumQuery has not come back with 0 samples (or the culling is off).
    pub fn casts_shadow(&self, light: usize) -> bool {
        !self.shadow_frustum_culling.load(std::sync::atomic::Ordering::Relaxed) || self.effects.is_light_visible(light)
    }

    /// Turns the skipping of occluded lights' shadow work on (the default) or off.
    pub fn set_shadow_frustum_culling(&self, on: bool) {
        self.shadow_frustum_culling.store(on, std::sync::atomic::Ordering::Relaxed);
    }

    /// The shadowed local lights whose shadow work the last frame skipped (their
    /// ShadowFrustumQuery found their volume hidden).
    pub fn shadow_skipped_lights(&self) -> Vec<String> {
        self.lights
            .iter()
            .enumerate()
            .filter(|(i, l)| l.shadow != LocalShadow::None && !self.casts_shadow(*i))
            .map(|(_, l)| l.name.clone())
            .collect()
    }

    /// How many times the movable lights' cube shadows rendered their cached static depth.
    pub fn cached_shadow_rebuilds(&self) -> u32 {
        self.shadows.cached_shadow_rebuilds()
    }

    /// A movable light moved: its cube shadow's static depth is rendered again.
    pub fn invalidate_cached_shadows(&self) {
        self.shadows.invalidate_cached_shadows();
    }

    /// The frame's effects (their state across frames: camera, histories, occlusion).
    pub fn effects(&self) -> &effects::Effects {
        &self.effects
    }

    /// This frame's `SceneView` (the camera jittered for TAA, the previous frame's, the time)
    /// into the one View buffer, and the movable props' transforms into their instance rows.
    /// `view`: the same camera unjittered (its near plane places the light grid's slices).
    fn write_camera(&self, camera: &effects::FrameCamera, view: &FrameView) {
        let mut v = self.base_view;
        v.set_camera(&camera.current, &camera.previous, view.width, view.height, camera.time);
        v.light_grid_z_params = view.grid_z_params.extend(0.0);
        self.queue.write_buffer(&self.view_buffer, 0, bytemuck::bytes_of(&v));
        // every object's rows: movable props move, props that occlusion culling found hidden
        // get empty transforms (nothing rasterised) until a query finds them visible again
        for (object, first, local_center, template) in &self.object_rows {
            let visible = self.effects.is_visible(*object);
            for (i, m) in self.effects.object_transforms(*object).into_iter().enumerate() {
                let m = if visible { m } else { glam::Mat4::ZERO };
                let row = view::InstanceGpu {
                    local_to_world: m,
                    normal_to_world: if visible {
                        glam::Mat4::from_mat3(glam::Mat3::from_mat4(m).inverse().transpose())
                    } else {
                        glam::Mat4::ZERO
                    },
                    material: template.material,
                    bounds: m.transform_point3(*local_center).extend(template.bounds.w),
                };
                let offset = u64::from(first + i as u32) * std::mem::size_of::<view::InstanceGpu>() as u64;
                self.queue.write_buffer(&self.buffers.instances, offset, bytemuck::bytes_of(&row));
            }
        }
    }

    /// What the passes built with the first camera computed from it, recomputed for this
    /// frame's `view`: the cascades of the directional light (their depth matrices, the
    /// projections Lighting, the translucency and the effects' fog and volumes read), each local
    /// light's depth bounds and whether the camera is inside its volume, the light grid's depth
    /// slicing as the volumetric fog reads it. (The `SceneView`, which every pass reads the
    /// camera from, is written by [`DesktopFrame::write_camera`].)
    fn follow_camera(&self, view: &FrameView) {
        let cascaded = self.shadows.update_cascades(&self.queue, view);
        self.lighting.update(&self.queue, view, cascaded.as_ref());
        self.translucency.update(&self.queue, cascaded.as_ref());
        self.effects.set_directional_shadow(cascaded.as_ref().map(directional_shadow));
        self.effects.set_light_grid_z_params(view.grid_z_params.extend(0.0));
        *self.view.lock().unwrap_or_else(|e| e.into_inner()) = *view;
    }

    /// Records the frame into its own output target.
    pub fn record(&self, frame: &mut FrameRecorder<'_>) {
        self.record_into(frame, (&self.output.texture, &self.output.view));
    }

    /// Renders one frame with the pipelines of `cache` (the one the frame was built with):
    /// the output image and every pass (with images when `capture`).
    pub fn render(
        &self,
        cache: &PipelineCache,
        capture: bool,
    ) -> Result<(Option<Image>, Vec<PassResult>), PipelineError> {
        let mut frame = FrameRecorder::new(&self.device, &self.queue, cache, self.timestamps, capture, None);
        self.record(&mut frame);
        let passes = frame.finish()?;
        let mut readback = FrameRecorder::new(&self.device, &self.queue, cache, false, true, None);
        readback.pass("Output", |ctx| ctx.output(&self.output.texture, Visualize::Direct));
        let image = readback.finish()?.pop().and_then(|mut p| p.images.pop()).map(|(_, i)| i);
        Ok((image, passes))
    }

    pub fn options(&self) -> &DesktopOptions {
        &self.options
    }

    /// The view of the frame rendered last (before the first frame: of the scene's camera).
    pub fn view(&self) -> FrameView {
        *self.view.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The scene's local lights as the light grid indexes them.
    pub fn lights(&self) -> &[FrameLight] {
        &self.lights
    }

    /// Whether Lighting shades the unshadowed local lights in the tiled compute pass.
    pub fn uses_tiled_lighting(&self) -> bool {
        self.lighting.tiled_path
    }

    /// Names of the lights drawn under ShadowedLights, in order.
    pub fn shadowed_lights(&self) -> Vec<String> {
        self.lighting.shadowed_light_names()
    }

    /// Reads the light grid back after a frame: (count, offset) per cell and the compacted
    /// light indices.
    pub fn read_light_grid(&self) -> (Vec<[u32; 2]>, Vec<u32>) {
        let read = |src: &wgpu::Buffer| -> Vec<u32> {
            let size = src.size();
            let staging = self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("light grid readback"),
                size,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            let mut encoder = self
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("light grid readback") });
            encoder.copy_buffer_to_buffer(src, 0, &staging, 0, size);
            self.queue.submit([encoder.finish()]);
            staging.slice(..).map_async(wgpu::MapMode::Read, |_| {});
            let _ = self.device.poll(wgpu::PollType::wait_indefinitely());
            let words = match staging.slice(..).get_mapped_range() {
                Ok(view) => bytemuck::pod_collect_to_vec(&view),
                Err(_) => Vec::new(),
            };
            words
        };
        let cells = read(&self.light_grid.num_culled_lights);
        let counts = cells.chunks_exact(2).take(self.view().grid_cells() as usize).map(|c| [c[0], c[1]]).collect();
        (counts, read(&self.light_grid.culled_light_data))
    }
}

/// What the effects read of the frame besides its [`Build`] context.
struct EffectInputs<'a> {
    shadows: &'a shadow_depths::ShadowDepths,
    /// Bound where the directional light has no cascades.
    dummy_shadow: &'a resources::Texture,
    light_grid: effects::LightGridInputs<'a>,
    /// The frame's one `SceneView` buffer, which every effect pass binds as `View`.
    view_buffer: &'a wgpu::Buffer,
}

/// The frame's effects over the frame's targets and the directional light's cascades.
fn build_effects(
    b: &PassSetup<'_>,
    queue: &wgpu::Queue,
    inputs: EffectInputs<'_>,
) -> Result<effects::Effects, DesktopError> {
    let EffectInputs { shadows, dummy_shadow, light_grid, view_buffer } = inputs;
    let (buffers, targets, lights) = (b.buffers, b.targets, b.lights);
    let (w, h) = (b.options.width.max(1), b.options.height.max(1));
    let meshes: Vec<effects::MeshRef<'_>> = buffers
        .meshes
        .iter()
        .map(|m| effects::MeshRef { vertices: &m.vertices, indices: &m.indices, index_count: m.index_count })
        .collect();
    let shadow = match (shadows.csm_texture(), &shadows.setup.cascaded) {
        (Some(_), Some(c)) => Some(directional_shadow(c)),
        _ => None,
    };
    let shadow_depth = shadows.csm_texture().map_or(&dummy_shadow.texture, |t| &t.texture);
    let local_shadows = translucent_volume_shadows(shadows, lights);
    let effect_targets = effects::EffectTargets {
        size: [w, h],
        view: view_buffer,
        scene_depth: &targets.scene_depth.texture,
        scene_color: &targets.scene_color.texture,
        gbuffer_a: &targets.gbuffer_a.texture,
        gbuffer_b: &targets.gbuffer_b.texture,
        gbuffer_c: &targets.gbuffer_c.texture,
        shadow_depth,
        // the cascades are stored with standard depth (lit where receiver <= stored)
        shadow_compare: wgpu::CompareFunction::LessEqual,
        light_grid,
        local_shadows,
    };
    let context = effects::EffectContext {
        device: b.device,
        queue,
        cache: b.pipelines.slots(),
        scene: b.scene,
        meshes: &meshes,
        warm_up_particles: b.options.warm_up_particles,
    };
    Ok(effects::Effects::new(&context, &effect_targets, shadow, effects::EffectOptions::default())?)
}

/// Each local light's own shadow as InjectTranslucentVolume reads it (by frame light index):
/// a movable point light's cube, a stationary light's per-object tiles (at most six, the
/// matrices a `ShadowProjectionUniforms` holds; `params.w` says how many). A light without
/// tiles (no movable prop in its reach) has no shadow to read.
fn translucent_volume_shadows<'a>(
    shadows: &'a shadow_depths::ShadowDepths,
    lights: &[FrameLight],
) -> Vec<Option<translucent_volume::LocalLightShadow<'a>>> {
    use translucent_volume::{LocalLightShadow, LocalShadowProjection};
    lights
        .iter()
        .enumerate()
        .map(|(li, l)| match l.shadow {
            LocalShadow::None => None,
            LocalShadow::Cube => {
                shadows.setup.cubes.iter().find(|(i, _, _)| *i == li).map(|(_, cube, u)| LocalLightShadow {
                    light: li,
                    kind: LocalShadowProjection::OnePassPointLight,
                    atlas: &shadows.cube_texture(*cube).view,
                    projection: *u,
                })
            }
            LocalShadow::PerObject => {
                let atlas = shadows.per_object_texture()?;
                let tiles: Vec<&view::ShadowProjectionUniforms> =
                    shadows.setup.per_object.iter().filter(|(i, _)| *i == li).map(|(_, u)| u).take(6).collect();
                let first = tiles.first()?;
                let mut projection = view::ShadowProjectionUniforms {
                    light_position: first.light_position,
                    params: first.params,
                    ..Default::default()
                };
                for (k, t) in tiles.iter().enumerate() {
                    projection.world_to_shadow[k] = t.world_to_shadow[0];
                    projection.atlas_rects[k] = t.atlas_rects[0];
                }
                projection.params.w = tiles.len() as f32;
                Some(LocalLightShadow {
                    light: li,
                    kind: LocalShadowProjection::PerObject,
                    atlas: &atlas.view,
                    projection,
                })
            }
        })
        .collect()
}

/// The cascades as the effects (the volumetric fog, the translucency volumes) reads them.
fn directional_shadow(c: &view::ShadowProjectionUniforms) -> frame_view::DirectionalShadow {
    frame_view::DirectionalShadow {
        cascades: [c.world_to_shadow[0], c.world_to_shadow[1], c.world_to_shadow[2]],
        splits: CASCADE_SPLITS,
        rects: [c.atlas_rects[0], c.atlas_rects[1], c.atlas_rects[2]],
    }
}

/// The objects' instance rows, rewritten every frame (movable props move, culled props hide).
fn object_rows(scene: &Scene, buffers: &resources::SceneBuffers) -> Vec<(usize, u32, glam::Vec3, view::InstanceGpu)> {
    let mut rows = Vec::new();
    for (i, (o, d)) in scene.objects.iter().zip(&buffers.draws).enumerate() {
        let (lo, hi) = scene.meshes[o.mesh].bounds();
        let template = view::InstanceGpu {
            material: glam::UVec4::new(o.material as u32, u32::from(d.movable), 0, 0),
            bounds: glam::Vec4::new(0.0, 0.0, 0.0, (hi - lo).length() * 0.5),
            ..Default::default()
        };
        rows.push((i, d.first_instance, (lo + hi) * 0.5, template));
    }
    rows
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_read_of_the_frame_is_written_before_it() {
        let options = DesktopOptions::default();
        let plan = DesktopFrame::plan(&options);
        assert_eq!(plan.check(), Ok(()));
        assert_eq!(
            plan.names(),
            vec![
                "ParticleSimulation",
                "PrePass",
                "ComputeLightGrid",
                "BeginOcclusionTests",
                "BuildHZB",
                "ShadowDepths",
                "VolumetricFog",
                "BasePass",
                "Velocity",
                "AmbientOcclusion",
                "Lighting",
                "Reflections",
                "ExponentialHeightFog",
                "Translucency",
                "Distortion",
                "PostProcessing",
            ]
        );
    }

    #[test]
    fn the_frame_without_its_effects_still_reads_only_what_is_written() {
        let options =
            DesktopOptions { ambient_occlusion: false, effects: effects::EffectOptions::off(), ..Default::default() };
        let plan = DesktopFrame::plan(&options);
        assert_eq!(plan.check(), Ok(()));
        assert!(!plan.names().contains(&"AmbientOcclusion"));
        let steps: Vec<&str> = plan.decls().map(|d| d.name).collect();
        assert!(steps.contains(&"TAABypass") && !steps.contains(&"EyeAdaptation"), "{steps:?}");
    }
}
