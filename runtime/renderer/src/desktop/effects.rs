//! The desktop frame's stateful effects (`Effects`), hooked into the frame function one call per
//! pass: ParticleSimulation, BeginOcclusionTests, BuildHZB, VolumetricFog, the colliding
//! ParticleSimulation after the BasePass, Velocity, InjectTranslucentVolume and
//! FilterTranslucentVolume (steps of Lighting), Reflections, the volumetric fog's
//! composition (a step of ExponentialHeightFog), the particle sprites (a step of
//! Translucency), Distortion, and TAA, MotionBlur and EyeAdaptation (steps of
//! PostProcessing before Bloom and the Tonemapper).
//!
//! Takes the frame's targets and the scene; keeps everything that lives from one frame to the
//! next (TAA and fog histories, particle state, occlusion read-backs, the previous camera and
//! transforms), so a frame function renders several frames in a row by calling
//! [`Effects::begin_frame`] and the pass calls once per frame. Every pipeline is created when
//! the effects are built (the warm-up); recording creates none.

use std::sync::{Arc, Mutex, MutexGuard};

use bytemuck::{Pod, Zeroable};
use glam::camera::rh::proj::directx;
use glam::camera::rh::view::{look_at_mat4, look_to_mat4};
use glam::{Mat4, Quat, Vec2, Vec3, Vec4};

use crate::frame::{ComputeSlot, FrameRecorder, PassContext, Slots, Visualize};
use crate::keys;
use crate::pipelines::PipelineError;
use crate::scene::{Camera, Mobility, Scene};

use super::distortion::Distortion;
use super::eye_adaptation::EyeAdaptation;
use super::frame_view::{
    groups, is_volume, taa_jitter, target_2d, uniform_buffer, view, volume_view, DirectionalShadow, EffectPassInit,
    InstancedMesh,
};
use super::hzb::Hzb;
use super::motion_blur::MotionBlur;
use super::occlusion::{world_bounds, LightBounds, OcclusionCulling};
use super::reflections::{CaptureDesc, ReflectionInputs, Reflections};
use super::taa::TemporalAA;
use super::translucent_volume::{InjectedLight, LocalLightShadow, TranslucentVolumes};
use super::velocity::Velocity;
pub use super::volumetric_fog::LightGridInputs;
use super::volumetric_fog::{FogSettings, ShadowInputs, VolumetricFog};
use crate::passes::particles::{
    CollisionInputs, EmitterDesc, LightingVolume, ParticleFormats, Particles, ParticlesInit, TIME_STEP,
};
use crate::scene::view::{CameraState, FrameTime};

/// Which effects run (all by default).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EffectOptions {
    /// Jittered projection and TAA.
    pub taa: bool,
    pub motion_blur: bool,
    pub eye_adaptation: bool,
    /// Movable props move (the rock circles); off for still frames.
    pub animate: bool,
    pub volumetric_fog: bool,
    /// The particle effects' sprites (sparks, smoke) and the fire's heat haze are drawn (they
    /// are always simulated; the scene's fire is always drawn).
    pub particles: bool,
    /// ReflectionEnvironmentAndSky adds the reflections to SceneColor (SSR is always traced).
    pub reflections: bool,
    /// Extinction of the volumetric fog at the fog height.
    pub fog_density: f32,
    /// How the translucent surfaces (the glass) are lit: per pixel from the light grid, or
    /// the diffuse light of the volumes' lights from the translucency lighting volumes.
    pub translucency_lighting: TranslucencyLightingMode,
    /// InjectTranslucentVolume shadows each light by its own shadow: the directional light
    /// by its cascades, the shadow-casting local lights by their cube or per-object shadows
    /// (off: the volumes receive every light as if nothing occluded it).
    pub translucency_volume_shadows: bool,
}

/// Unreal's TranslucencyLightingMode for the lit translucent surfaces (the
/// `TRANSLUCENCY_LIGHTING_MODE` dimension of `DeferredBasePassPS`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TranslucencyLightingMode {
    /// TLM_SurfacePerPixelLighting: every light per pixel (the local lights of the light grid).
    SurfaceForwardShading,
    /// TLM_Surface: the diffuse light of the lights the translucency lighting volumes hold
    /// (the shadowed directional light and the shadow-casting local lights) from the volumes'
    /// two cascades, their specular and the other lights per pixel.
    SurfaceLightingVolume,
}

impl TranslucencyLightingMode {
    /// The dimension's value.
    pub fn label(self) -> &'static str {
        match self {
            TranslucencyLightingMode::SurfaceForwardShading => "SURFACE_FORWARD_SHADING",
            TranslucencyLightingMode::SurfaceLightingVolume => "SURFACE_LIGHTING_VOLUME",
        }
    }
}

impl EffectOptions {
    /// Every pass still runs and is dumped, but none changes the frame: no jitter, TAA, motion
    /// blur, eye adaptation, volumetric fog, sprites or reflections, nothing moves, and the
    /// glass is forward shaded per pixel (for comparisons with frames that lack these effects).
    pub fn off() -> EffectOptions {
        EffectOptions {
            taa: false,
            motion_blur: false,
            eye_adaptation: false,
            animate: false,
            volumetric_fog: false,
            particles: false,
            reflections: false,
            translucency_lighting: TranslucencyLightingMode::SurfaceForwardShading,
            ..EffectOptions::default()
        }
    }
}

impl Default for EffectOptions {
    fn default() -> Self {
        EffectOptions {
            taa: true,
            motion_blur: true,
            eye_adaptation: true,
            animate: true,
            volumetric_fog: true,
            particles: true,
            reflections: true,
            fog_density: 0.01,
            translucency_lighting: TranslucencyLightingMode::SurfaceLightingVolume,
            translucency_volume_shadows: true,
        }
    }
}

/// The frame's targets the effects read and write.
pub struct EffectTargets<'a> {
    pub size: [u32; 2],
    /// The frame's one `SceneView` buffer (written by the frame as each frame begins), which
    /// every effect pass binds as `View`.
    pub view: &'a wgpu::Buffer,
    pub scene_depth: &'a wgpu::Texture,
    pub scene_color: &'a wgpu::Texture,
    pub gbuffer_a: &'a wgpu::Texture,
    pub gbuffer_b: &'a wgpu::Texture,
    pub gbuffer_c: &'a wgpu::Texture,
    /// The directional light's shadow map (a single map or the 3x1 cascade atlas).
    pub shadow_depth: &'a wgpu::Texture,
    /// Lit where `receiver OP stored` holds (reverse-Z shadow maps: GreaterEqual).
    pub shadow_compare: wgpu::CompareFunction,
    /// ComputeLightGrid's lists: the local lights the volumetric fog scatters.
    pub light_grid: LightGridInputs<'a>,
    /// Per local light (point lights, then spot lights, as `frame_lights` orders them): its own
    /// shadow, where it casts one that InjectTranslucentVolume can read.
    pub local_shadows: Vec<Option<LocalLightShadow<'a>>>,
}

/// The filtered translucency lighting volumes and their boxes this frame, as the translucent
/// surfaces bind them (cascade 0 inner, 1 outer).
pub struct TranslucencyVolumeInputs {
    /// `TranslucencyLightingVolumeParams`, written every frame by InjectTranslucentVolume.
    pub params: wgpu::Buffer,
    pub ambient: [wgpu::Texture; 2],
    pub directional: [wgpu::Texture; 2],
}

/// What the effects are built with: the device, the runtime's pipeline cache and the scene
/// with its meshes on the GPU (`meshes`, by mesh index).
#[derive(Clone, Copy)]
pub struct EffectContext<'a> {
    pub device: &'a wgpu::Device,
    pub queue: &'a wgpu::Queue,
    pub cache: Slots<'a>,
    pub scene: &'a Scene,
    pub meshes: &'a [MeshRef<'a>],
    /// Warm the scene's emitters up when they are built ([`EmitterDesc::prewarm`]).
    pub warm_up_particles: bool,
}

/// A mesh's GPU buffers: vertices (`MeshVertex`), 32-bit indices, index count.
pub struct MeshRef<'a> {
    pub vertices: &'a wgpu::Buffer,
    pub indices: &'a wgpu::Buffer,
    pub index_count: u32,
}

/// This frame's camera as the frame renders with it (jittered: `current.jittered_proj()`),
/// the previous frame's, and the frame's time: what the frame's `SceneView` is built from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameCamera {
    pub current: CameraState,
    pub previous: CameraState,
    pub time: FrameTime,
}

/// A visualization of a target that is not a colour (velocities, particle state, volumes).
struct Visualization {
    pipeline: Arc<ComputeSlot>,
    group: wgpu::BindGroup,
    image: wgpu::Texture,
    params: wgpu::Buffer,
    values: VisualizeParams,
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
struct VisualizeParams {
    scale: Vec4,
    bias: Vec4,
    slice: [u32; 4],
}

impl Visualization {
    fn new(
        device: &wgpu::Device,
        cache: Slots<'_>,
        label: &str,
        source: &wgpu::Texture,
        size: [u32; 2],
        values: VisualizeParams,
    ) -> Result<Visualization, PipelineError> {
        let volume = is_volume(source);
        let pipeline = cache
            .compute(&keys::name(keys::visualize_texture_cs::Key { visualize_volume: volume }, keys::Level::Sm5)?)?;
        let image = target_2d(
            device,
            label,
            size,
            wgpu::TextureFormat::Rgba8Unorm,
            wgpu::TextureUsages::STORAGE_BINDING | wgpu::TextureUsages::TEXTURE_BINDING,
        );
        let params = uniform_buffer(device, label, &values);
        let src = if volume { volume_view(source) } else { view(source) };
        let dst = view(&image);
        let group = pipeline.layout.bind_group(
            device,
            0,
            label,
            &[
                ("params", params.as_entire_binding()),
                ("SourceDepthTexture", wgpu::BindingResource::TextureView(&src)),
                ("out_image", wgpu::BindingResource::TextureView(&dst)),
            ],
        )?;
        Ok(Visualization { pipeline, group, image, params, values })
    }

    /// Shows slice `slice` of a volume from now on.
    fn set_slice(&self, queue: &wgpu::Queue, slice: u32) {
        let values = VisualizeParams { slice: [slice, 0, 0, 0], ..self.values };
        queue.write_buffer(&self.params, 0, bytemuck::bytes_of(&values));
    }

    /// Draws the image and declares it as the current pass or step's output `name`.
    fn output(&self, ctx: &mut PassContext<'_>, name: Option<&str>) {
        {
            let ready = self.pipeline.ready(ctx.pipelines());
            let mut pass = ctx.open_compute_pass("VisualizeTexture");
            if let Some(p) = ready {
                pass.set_pipeline(&p.pipeline);
                pass.set_bind_group(0, &self.group, &[]);
                pass.dispatch_workgroups(groups(self.image.width(), 8), groups(self.image.height(), 8), 1);
            }
        }
        match name {
            Some(n) => ctx.output_named(n, &self.image, Visualize::Direct),
            None => ctx.output(&self.image, Visualize::Direct),
        }
    }
}

struct Visualizations {
    particle_position: [Visualization; 2],
    particle_velocity: [Visualization; 2],
    spark_position: [Visualization; 2],
    velocity: Visualization,
    vbuffer_a: Visualization,
    light_scattering: [Visualization; 2],
    integrated: Visualization,
    volume_ambient: Visualization,
    volume_filtered: Visualization,
    distortion: Visualization,
}

struct State {
    options: EffectOptions,
    device: wgpu::Device,
    queue: wgpu::Queue,
    scene: Scene,
    camera: Camera,
    aspect: f32,
    size: [u32; 2],
    previous: Option<CameraState>,
    current: Option<CameraState>,
    frame: u64,
    time: f32,
    movable: Vec<usize>,
    refracting: Vec<usize>,
    shadow: Option<DirectionalShadow>,
    particles: Particles,
    occlusion: OcclusionCulling,
    hzb: Hzb,
    fog: VolumetricFog,
    velocity: Velocity,
    volumes: TranslucentVolumes,
    reflections: Reflections,
    distortion: Distortion,
    taa: TemporalAA,
    motion_blur: MotionBlur,
    eye: EyeAdaptation,
    vis: Visualizations,
    scene_color: wgpu::Texture,
    scene_color_view: wgpu::TextureView,
    /// Every aspect (depth and stencil, where the format has one): for depth attachments.
    scene_depth_attachment: wgpu::TextureView,
}

/// The effect passes with their state across frames.
pub struct Effects {
    state: Mutex<State>,
}

/// The froxel slice the fog's dumps show (about 8 m from the camera, inside the room).
const FOG_SLICE: u32 = 80;

/// A movable prop's transform at `time` (seconds): the rock circles slowly and turns.
pub fn animate_movable(base: Mat4, time: f32) -> Mat4 {
    let offset = Vec3::new((time * 1.5).sin() * 0.6, 0.0, (time * 1.5).cos() * 0.6 - 0.6);
    Mat4::from_translation(offset) * base * Mat4::from_quat(Quat::from_rotation_y(time * 0.8))
}

/// The lights the translucency volumes hold, with their own shadows: the directional light
/// where it shines (no shadow of its own: it reads the cascades), then the local lights that
/// cast shadows (those ShadowedLights draws).
fn injected_lights<'t>(
    scene: &Scene,
    targets: &EffectTargets<'t>,
) -> (Vec<InjectedLight>, Vec<Option<LocalLightShadow<'t>>>) {
    let mut lights = Vec::new();
    let mut light_shadows = Vec::new();
    let local_shadow = |index: usize| targets.local_shadows.get(index).cloned().flatten();
    if scene.sun.enabled {
        lights.push(InjectedLight::Directional {
            direction: -scene.sun.direction,
            color: scene.sun.color * scene.sun.intensity,
        });
        light_shadows.push(None);
    }
    for (i, l) in scene.point_lights.iter().enumerate().filter(|(_, l)| l.casts_shadows) {
        lights.push(InjectedLight::Point { position: l.position, radius: l.radius, color: l.color * l.intensity });
        light_shadows.push(local_shadow(i));
    }
    for (i, l) in scene.spot_lights.iter().enumerate().filter(|(_, l)| l.casts_shadows) {
        light_shadows.push(local_shadow(scene.point_lights.len() + i));
        lights.push(InjectedLight::Spot {
            position: l.position,
            radius: l.radius,
            color: l.color * l.intensity,
            direction: l.direction,
            inner_angle: l.inner_angle,
            outer_angle: l.outer_angle,
        });
    }
    (lights, light_shadows)
}

/// ParticleSimulation's emitters (the scene's fire, sparks that collide, smoke) and their
/// passes, lit by the translucency volumes.
fn new_particles(
    context: &EffectContext<'_>,
    targets: &EffectTargets<'_>,
    volumes: &TranslucentVolumes,
    depth_view: &wgpu::TextureView,
    gbuffer_a: &wgpu::TextureView,
) -> Result<Particles, PipelineError> {
    let EffectContext { device, queue, cache, scene, warm_up_particles, .. } = *context;
    let mut emitters = Vec::new();
    for e in &scene.emitters {
        emitters.push(EmitterDesc { prewarm: warm_up_particles, ..EmitterDesc::fire(e) });
        emitters.push(EmitterDesc::sparks(e));
        emitters.push(EmitterDesc::smoke(e));
    }
    // the smoke is lit by both translucency volume cascades, blended as the glass reads them
    let ambient = [volume_view(volumes.volumes(0).0), volume_view(volumes.volumes(1).0)];
    let directional = [volume_view(volumes.volumes(0).1), volume_view(volumes.volumes(1).1)];
    let lit = LightingVolume {
        params: volumes.lookup_buffer(),
        ambient: [&ambient[0], &ambient[1]],
        directional: [&directional[0], &directional[1]],
    };
    Particles::new(
        &ParticlesInit {
            device,
            queue,
            cache,
            view: targets.view,
            collision: CollisionInputs { scene_depth: depth_view, gbuffer_a },
            lighting_volume: lit,
            formats: ParticleFormats {
                color: targets.scene_color.format(),
                depth: targets.scene_depth.format(),
                distortion: super::resources::formats::DISTORTION,
            },
            size: targets.size,
        },
        emitters,
    )
}

/// The pictures the dumps show of what is not an image: particle states, velocities, the
/// fog's and the translucency volumes' slices, the distortion offsets.
#[allow(clippy::too_many_arguments)] // one per effect it pictures
fn visualizations(
    device: &wgpu::Device,
    cache: Slots<'_>,
    size: [u32; 2],
    scene: &Scene,
    particles: &Particles,
    velocity: &Velocity,
    fog: &VolumetricFog,
    volumes: &TranslucentVolumes,
    distortion: &Distortion,
) -> Result<Visualizations, PipelineError> {
    let v = |label: &str, source: &wgpu::Texture, scale: Vec4, bias: Vec4, slice: u32| {
        let s = if is_volume(source) { [size[0] / 2, size[1] / 2] } else { [source.width(), source.height()] };
        Visualization::new(device, cache, label, source, s, VisualizeParams { scale, bias, slice: [slice, 0, 0, 0] })
    };
    let sparks = particles.state_textures(true);
    let fire = particles.state_textures(false);
    let pos_scale = Vec4::new(0.1, 0.25, 0.1, 0.0);
    let pos_bias = Vec4::new(0.0, 0.0, 0.5, 0.0);
    let vel_scale = Vec4::new(0.5, 0.3, 0.5, 0.0);
    // the dumps show the large cascade's slice through the middle of the room (z = 0),
    // chosen again every frame as the cascade follows the camera
    let volume_slice = room_slice(scene.camera.position);
    Ok(Visualizations {
        particle_position: [
            v("ParticleStatePosition", &fire.0[0], pos_scale, pos_bias, 0)?,
            v("ParticleStatePosition", &fire.0[1], pos_scale, pos_bias, 0)?,
        ],
        particle_velocity: [
            v("ParticleStateVelocity", &fire.1[0], vel_scale, Vec4::ZERO, 0)?,
            v("ParticleStateVelocity", &fire.1[1], vel_scale, Vec4::ZERO, 0)?,
        ],
        spark_position: [
            v("SparkStatePosition", &sparks.0[0], pos_scale, pos_bias, 0)?,
            v("SparkStatePosition", &sparks.0[1], pos_scale, pos_bias, 0)?,
        ],
        velocity: v("Velocity", &velocity.texture, Vec4::new(40.0, 40.0, 0.0, 0.0), Vec4::ZERO, 0)?,
        vbuffer_a: v("VBufferA", &fog.vbuffer_a, Vec4::splat(10.0), Vec4::ZERO, FOG_SLICE)?,
        light_scattering: [
            v("LightScattering", &fog.light_scattering[0], Vec4::splat(100.0), Vec4::ZERO, FOG_SLICE)?,
            v("LightScattering", &fog.light_scattering[1], Vec4::splat(100.0), Vec4::ZERO, FOG_SLICE)?,
        ],
        integrated: v(
            "IntegratedLightScattering",
            &fog.integrated,
            Vec4::new(2.0, 2.0, 2.0, 0.0),
            Vec4::ZERO,
            super::volumetric_fog::DEPTH_SLICES - 1,
        )?,
        volume_ambient: v("TranslucentVolume1", volumes.injected(1).0, Vec4::splat(0.25), Vec4::ZERO, volume_slice)?,
        volume_filtered: v("TranslucentVolume1", volumes.volumes(1).0, Vec4::splat(0.25), Vec4::ZERO, volume_slice)?,
        distortion: v("Distortion", &distortion.offsets, Vec4::new(25.0, 25.0, 0.0, 0.0), Vec4::ZERO, 0)?,
    })
}

/// The frame's targets as the effects read them.
struct TargetViews {
    depth: wgpu::TextureView,
    color: wgpu::TextureView,
    gbuffer: [wgpu::TextureView; 3],
    shadow: wgpu::TextureView,
    depth_format: wgpu::TextureFormat,
    color_format: wgpu::TextureFormat,
}

impl TargetViews {
    fn new(targets: &EffectTargets<'_>) -> TargetViews {
        TargetViews {
            depth: targets.scene_depth.create_view(&wgpu::TextureViewDescriptor {
                label: Some("SceneDepth (effects)"),
                aspect: wgpu::TextureAspect::DepthOnly,
                ..Default::default()
            }),
            color: view(targets.scene_color),
            gbuffer: [view(targets.gbuffer_a), view(targets.gbuffer_b), view(targets.gbuffer_c)],
            shadow: targets.shadow_depth.create_view(&wgpu::TextureViewDescriptor {
                label: Some("ShadowDepth (effects)"),
                aspect: wgpu::TextureAspect::DepthOnly,
                ..Default::default()
            }),
            depth_format: targets.scene_depth.format(),
            color_format: targets.scene_color.format(),
        }
    }
}

/// The objects of `scene` that `keep` selects, by index.
fn objects_where(scene: &Scene, keep: impl Fn(&crate::scene::Object) -> bool) -> Vec<usize> {
    scene.objects.iter().enumerate().filter(|(_, o)| keep(o)).map(|(i, _)| i).collect()
}

/// Instanced meshes of the objects `objects`, for a pass that draws them alone.
fn instanced_meshes(context: &EffectContext<'_>, objects: &[usize], label: &str) -> Vec<InstancedMesh> {
    objects
        .iter()
        .map(|&i| {
            let o = &context.scene.objects[i];
            let m = &context.meshes[o.mesh];
            InstancedMesh::new(context.device, &format!("{label} {}", o.name), m.vertices, m.indices, m.index_count)
        })
        .collect()
}

/// BeginOcclusionTests: every object's box; local lights' bounds.
fn new_occlusion(
    init: &EffectPassInit<'_>,
    scene: &Scene,
    size: [u32; 2],
    depth_format: wgpu::TextureFormat,
) -> Result<OcclusionCulling, PipelineError> {
    let bounds: Vec<(Vec3, Vec3)> =
        scene.objects.iter().map(|o| world_bounds(scene.meshes[o.mesh].bounds(), &o.instances)).collect();
    OcclusionCulling::new(init, size, depth_format, bounds, scene.point_lights.len() + scene.spot_lights.len())
}

/// Screen-space reflections over the HZB and the room's reflection capture.
fn new_reflections(
    init: &EffectPassInit<'_>,
    size: [u32; 2],
    v: &TargetViews,
    hzb: &Hzb,
) -> Result<Reflections, PipelineError> {
    let hzb_view = view(&hzb.texture);
    Reflections::new(
        init,
        size,
        &ReflectionInputs {
            scene_color: &v.color,
            scene_depth: &v.depth,
            gbuffer_a: &v.gbuffer[0],
            gbuffer_b: &v.gbuffer[1],
            gbuffer_c: &v.gbuffer[2],
            hzb: &hzb_view,
            hzb_size: hzb.size,
            hzb_mips: hzb.mip_count,
        },
        &CaptureDesc { position: Vec3::new(0.0, 1.8, 0.0), radius: 9.0, room_color: Vec3::new(0.3, 0.28, 0.25) },
        v.color_format,
    )
}

impl Effects {
    /// Builds every pass (and so every pipeline) of the effects on `context`'s device, over
    /// the frame's `targets` and the directional light's cascades (`shadow`).
    pub fn new(
        context: &EffectContext<'_>,
        targets: &EffectTargets<'_>,
        shadow: Option<DirectionalShadow>,
        options: EffectOptions,
    ) -> Result<Effects, PipelineError> {
        let EffectContext { device, queue, cache, scene, .. } = *context;
        let size = targets.size;
        let frame_view = targets.view.clone();
        let v = TargetViews::new(targets);
        let (lights, light_shadows) = injected_lights(scene, targets);
        let init = EffectPassInit { device, cache, frame_view: &frame_view };
        let volumes = TranslucentVolumes::new(&init, &v.shadow, targets.shadow_compare, lights, &light_shadows)?;
        let particles = new_particles(context, targets, &volumes, &v.depth, &v.gbuffer[0])?;
        let occlusion = new_occlusion(&init, scene, size, v.depth_format)?;
        let hzb = Hzb::new(device, cache, &v.depth, size)?;
        let shadow_inputs = ShadowInputs { atlas: &v.shadow, compare: targets.shadow_compare };
        let fog = VolumetricFog::new(&init, size, &v.depth, &shadow_inputs, &targets.light_grid, v.color_format)?;
        let movable = objects_where(scene, |o| o.mobility == Mobility::Movable);
        let velocity_meshes = instanced_meshes(context, &movable, "Velocity");
        let velocity = Velocity::new(device, cache, &frame_view, size, v.depth_format, velocity_meshes)?;
        let reflections = new_reflections(&init, size, &v, &hzb)?;
        let refracting =
            objects_where(scene, |o| scene.materials[o.material].blend == crate::scene::BlendMode::Translucent);
        let distortion_meshes = instanced_meshes(context, &refracting, "Distortion");
        let distortion = Distortion::new(&init, size, v.color_format, v.depth_format, distortion_meshes)?;
        let taa = TemporalAA::new(&init, size, &v.color, &velocity.view, &v.depth)?;
        let [h0, h1] = taa.history_views();
        let eye = EyeAdaptation::new(device, cache, &[h0, h1], size)?;
        let motion_blur = MotionBlur::new(&init, &[h0, h1], &velocity.view, &v.depth, &eye.result, v.color_format)?;
        let vis = visualizations(device, cache, size, scene, &particles, &velocity, &fog, &volumes, &distortion)?;
        let state = State {
            options,
            device: device.clone(),
            queue: queue.clone(),
            scene: scene.clone(),
            camera: scene.camera.clone(),
            aspect: size[0] as f32 / size[1] as f32,
            size,
            previous: None,
            current: None,
            frame: 0,
            time: 0.0,
            movable,
            refracting,
            shadow,
            particles,
            occlusion,
            hzb,
            fog,
            velocity,
            volumes,
            reflections,
            distortion,
            taa,
            motion_blur,
            eye,
            vis,
            scene_color: targets.scene_color.clone(),
            scene_color_view: v.color,
            scene_depth_attachment: view(targets.scene_depth),
        };
        Ok(Effects { state: Mutex::new(state) })
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    pub fn options(&self) -> EffectOptions {
        self.lock().options
    }

    /// Turns effects on or off (from the next frame on; every pipeline exists already).
    pub fn set_options(&self, options: EffectOptions) {
        self.lock().options = options;
    }

    /// Moves the camera (from the next frame on). Everything that depends on the camera
    /// (light volumes' depth bounds, the cascades, the translucency volumes' boxes, the
    /// light grid) follows it from that frame on.
    pub fn set_camera(&self, camera: Camera) {
        self.lock().camera = camera;
    }

    /// The camera the next frame (or the frame being recorded) renders with, unjittered.
    pub fn camera(&self) -> Camera {
        self.lock().camera.clone()
    }

    /// The light grid's depth slicing this frame (ComputeLightGrid's, from the camera's near
    /// plane), which the volumetric fog reads the grid with.
    pub fn set_light_grid_z_params(&self, z_params: Vec4) {
        self.lock().fog.set_light_grid_z_params(z_params);
    }

    /// The directional light's cascades this frame, refitted to the camera (the fog and the
    /// translucency volumes read them); `None` without cascades.
    pub fn set_directional_shadow(&self, shadow: Option<DirectionalShadow>) {
        self.lock().shadow = shadow;
    }

    /// A camera cut: forgets the temporal histories (TAA, fog; the eye adaptation stays
    /// valid) and the occlusion queries' results, which the old camera's depth decided
    /// (every prop and light counts as visible until the new camera's queries come back).
    pub fn reset_history(&self) {
        let mut s = self.lock();
        s.taa.reset_history();
        s.fog.reset_history();
        s.occlusion.camera_cut();
        s.previous = None;
    }

    /// Starts a frame: advances time, moves the movable props, computes this frame's jittered
    /// camera. The frame renders with the camera returned (and its `SceneView`)
    /// and draws object `i` with `transforms(i)` (see [`Effects::object_transforms`]).
    pub fn begin_frame(&self) -> FrameCamera {
        let mut s = self.lock();
        let s = &mut *s;
        s.frame += 1;
        if s.options.animate && s.frame > 1 {
            s.time += TIME_STEP;
        }
        let cam = &s.camera;
        let view = cam.view();
        let proj = cam.projection(s.aspect);
        let jitter = if s.options.taa { taa_jitter(s.frame, s.size[0], s.size[1]) } else { Vec2::ZERO };
        let current = CameraState::new(view, proj, cam.near, jitter);
        let previous = s.previous.unwrap_or(current);
        s.current = Some(current);
        FrameCamera { current, previous, time: FrameTime { time: s.time, delta: TIME_STEP, index: s.frame } }
    }

    /// Object `index`'s instance transforms this frame (movable props animated).
    pub fn object_transforms(&self, index: usize) -> Vec<Mat4> {
        let s = self.lock();
        object_transforms(&s, index)
    }

    /// The movable objects (their instance buffers change every frame).
    pub fn movable_objects(&self) -> Vec<usize> {
        self.lock().movable.clone()
    }

    /// Whether occlusion culling lets object `index` be drawn this frame.
    pub fn is_visible(&self, index: usize) -> bool {
        self.lock().occlusion.is_visible(index)
    }

    /// Whether local light `index` (in `frame_lights` order: point lights, then spot lights)
    /// renders its shadow this frame: its ShadowFrustumQuery has not come back with 0 samples.
    pub fn is_light_visible(&self, index: usize) -> bool {
        self.lock().occlusion.is_light_visible(index)
    }

    /// Object `index`'s visibility as the occlusion queries last found it.
    pub fn visibility(&self, index: usize) -> Option<super::occlusion::PropVisibility> {
        self.lock().occlusion.visibility(index)
    }

    pub fn occlusion_stats(&self) -> super::occlusion::OcclusionStats {
        self.lock().occlusion.stats.clone()
    }

    /// ParticleSimulation at the start of the frame: the `Fire` step simulates the emitters
    /// without collision (the fire and its smoke; pictured alone when capturing), then the
    /// fire's state textures are shown.
    pub fn particle_simulation(&self, frame: &mut FrameRecorder) {
        let mut s = self.lock();
        let s = &mut *s;
        frame.pass(crate::passes::particles::SIMULATION_PASS.name, |ctx| {
            ctx.step("Fire", |ctx| {
                s.particles.simulate(&s.queue, ctx, false);
                s.particles.record_preview(ctx);
            });
            let i = s.particles.current_index(false);
            s.vis.particle_position[i].output(ctx, Some("Position"));
            s.vis.particle_velocity[i].output(ctx, Some("Velocity"));
        });
    }

    /// BeginOcclusionTests, after the PrePass.
    pub fn begin_occlusion_tests(&self, frame: &mut FrameRecorder) {
        let mut s = self.lock();
        let s = &mut *s;
        let camera = s.current.map(|c| c.position).unwrap_or(s.camera.position);
        let mut lights = Vec::new();
        for l in &s.scene.point_lights {
            lights.push(match l.mobility {
                Mobility::Movable => LightBounds::Sphere { center: l.position, radius: l.radius },
                _ => LightBounds::Frustum { view_proj: point_light_frustum(l.position, l.radius) },
            });
        }
        for l in &s.scene.spot_lights {
            let view =
                look_to_mat4(l.position, l.direction, if l.direction.y.abs() > 0.99 { Vec3::Z } else { Vec3::Y });
            let proj = directx::perspective(l.outer_angle * 2.0, 1.0, 0.1, l.radius);
            lights.push(LightBounds::Frustum { view_proj: proj * view });
        }
        for (i, &o) in s.movable.iter().enumerate() {
            let _ = i;
            let b = world_bounds(s.scene.meshes[s.scene.objects[o].mesh].bounds(), &object_transforms(s, o));
            s.occlusion.set_bounds(o, b);
        }
        frame.pass(super::occlusion::PASS.name, |ctx| {
            s.occlusion.record(&s.device, &s.queue, ctx, &s.scene_depth_attachment, camera, &lights);
            ctx.output(&s.occlusion.debug, Visualize::Direct);
        });
    }

    /// BuildHZB, after the occlusion tests.
    pub fn build_hzb(&self, frame: &mut FrameRecorder) {
        let s = self.lock();
        frame.pass(super::hzb::PASS.name, |ctx| {
            s.hzb.record(ctx);
            ctx.output(&s.hzb.texture, Visualize::Depth);
        });
    }

    /// VolumetricFog, after ShadowDepths.
    pub fn volumetric_fog(&self, frame: &mut FrameRecorder) {
        let mut s = self.lock();
        let s = &mut *s;
        let settings = fog_settings(s);
        frame.pass(super::volumetric_fog::PASS.name, |ctx| {
            ctx.step("InitializeVolumeAttributes", |ctx| {
                s.fog.record_initialize(&s.queue, ctx, &settings);
                s.vis.vbuffer_a.output(ctx, None);
            });
            ctx.step("LightScattering", |ctx| {
                s.fog.record_light_scattering(ctx);
                s.vis.light_scattering[s.fog.current_index()].output(ctx, None);
            });
            ctx.step("FinalIntegration", |ctx| {
                s.fog.record_final_integration(ctx);
                s.vis.integrated.output(ctx, None);
            });
        });
    }

    /// The particles that collide with the depth buffer, simulated once the BasePass has
    /// written it (Unreal's PostRenderOpaque).
    /// Recorded as the `ParticleCollision` step at the end of the BasePass (the frame has
    /// one ParticleSimulation pass, at its start).
    pub fn particle_collision(&self, ctx: &mut PassContext<'_>) {
        let mut s = self.lock();
        let s = &mut *s;
        ctx.step(crate::passes::particles::COLLISION_STEP.name, |ctx| {
            s.particles.simulate(&s.queue, ctx, true);
            let i = s.particles.current_index(true);
            s.vis.spark_position[i].output(ctx, None);
        });
    }

    /// Velocity, after the BasePass.
    pub fn velocity(&self, frame: &mut FrameRecorder) {
        let mut s = self.lock();
        let s = &mut *s;
        // the previous frame's transforms: where the props were one time step ago (on the
        // first frame too: they were already moving)
        let transforms: Vec<(Vec<Mat4>, Vec<Mat4>)> = s
            .movable
            .iter()
            .map(|&o| (object_transforms(s, o), object_transforms_at(s, o, s.time - TIME_STEP)))
            .collect();
        frame.pass(super::velocity::PASS.name, |ctx| {
            s.velocity.record(&s.queue, ctx, &s.scene_depth_attachment, &transforms);
            s.vis.velocity.output(ctx, None);
        });
    }

    /// InjectTranslucentVolume and FilterTranslucentVolume: steps of the Lighting pass.
    /// `casts_shadow(light)`: whether local light `light` rendered its shadow depths this
    /// frame (ShadowFrustumQueries); a light that did not is injected unshadowed.
    pub fn translucent_volumes(&self, ctx: &mut PassContext<'_>, casts_shadow: &dyn Fn(usize) -> bool) {
        // asked before locking: the frame's answer may come from this part's own queries
        let local_lights = {
            let s = self.lock();
            s.scene.point_lights.len() + s.scene.spot_lights.len()
        };
        let rendered: Vec<bool> = (0..local_lights).map(casts_shadow).collect();
        let casts_shadow = |light: usize| rendered.get(light).copied().unwrap_or(true);
        let s = self.lock();
        let camera = s.current.map(|c| c.position).unwrap_or(s.camera.position);
        let slice = room_slice(camera);
        s.vis.volume_ambient.set_slice(&s.queue, slice);
        s.vis.volume_filtered.set_slice(&s.queue, slice);
        ctx.step(super::translucent_volume::INJECT_STEP.name, |ctx| {
            s.volumes.record_inject(
                &s.queue,
                ctx,
                camera,
                s.shadow.as_ref(),
                s.options.translucency_volume_shadows,
                &casts_shadow,
            );
            s.vis.volume_ambient.output(ctx, None);
        });
        ctx.step(super::translucent_volume::FILTER_STEP.name, |ctx| {
            s.volumes.record_filter(ctx);
            s.vis.volume_filtered.output(ctx, None);
        });
    }

    /// Reflections, after Lighting.
    pub fn reflections(&self, frame: &mut FrameRecorder) {
        let mut s = self.lock();
        let s = &mut *s;
        frame.pass(super::reflections::PASS.name, |ctx| {
            s.reflections.record_capture(ctx);
            ctx.step("ScreenSpaceReflections", |ctx| {
                s.reflections.record_ssr(ctx);
                ctx.output(&s.reflections.ssr, Visualize::Hdr);
            });
            let apply = s.options.reflections;
            ctx.step("ReflectionEnvironmentAndSky", |ctx| {
                if apply {
                    s.reflections.record_environment(ctx, &s.scene_color_view);
                }
                ctx.output(&s.scene_color, Visualize::Hdr);
            });
        });
    }

    /// The volumetric fog composited over SceneColor: a step of ExponentialHeightFog.
    pub fn apply_volumetric_fog(&self, ctx: &mut PassContext<'_>) {
        let s = self.lock();
        // off with the option, and where the scene has no fog
        if !s.options.volumetric_fog || s.scene.fog.density <= 0.0 {
            return;
        }
        ctx.step(super::volumetric_fog::APPLY_STEP.name, |ctx| {
            s.fog.apply(ctx, &s.scene_color_view);
            ctx.output(&s.scene_color, Visualize::Hdr);
        });
    }

    /// The particle sprites over SceneColor: a step of Translucency.
    pub fn particle_sprites(&self, ctx: &mut PassContext<'_>) {
        let s = self.lock();
        ctx.step(crate::passes::particles::SPRITES_STEP.name, |ctx| {
            {
                let pl = ctx.pipelines();
                let mut pass = ctx.open_render_pass(&wgpu::RenderPassDescriptor {
                    label: Some("ParticleSprites"),
                    color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                        view: &s.scene_color_view,
                        depth_slice: None,
                        resolve_target: None,
                        ops: wgpu::Operations { load: wgpu::LoadOp::Load, store: wgpu::StoreOp::Store },
                    })],
                    depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                        view: &s.scene_depth_attachment,
                        depth_ops: Some(wgpu::Operations { load: wgpu::LoadOp::Load, store: wgpu::StoreOp::Store }),
                        stencil_ops: None,
                    }),
                    timestamp_writes: None,
                    occlusion_query_set: None,
                    multiview_mask: None,
                });
                s.particles.draw_sprites(pl, &mut pass, s.options.particles);
            }
            ctx.output(&s.scene_color, Visualize::Hdr);
        });
    }

    /// Distortion, after Translucency.
    pub fn distortion(&self, frame: &mut FrameRecorder) {
        let mut s = self.lock();
        let s = &mut *s;
        let transforms: Vec<Vec<Mat4>> = s.refracting.iter().map(|&o| object_transforms(s, o)).collect();
        frame.pass(super::distortion::PASS.name, |ctx| {
            ctx.step("DistortionAccum", |ctx| {
                let particles = s.options.particles.then_some(&s.particles);
                s.distortion.record_accumulate(&s.queue, ctx, &s.scene_depth_attachment, &transforms, particles);
                s.vis.distortion.output(ctx, None);
            });
            ctx.step("DistortionApply", |ctx| {
                s.distortion.record_apply(ctx, &s.scene_color, &s.scene_color_view);
                ctx.output(&s.scene_color, Visualize::Hdr);
            });
        });
    }

    /// TAA, EyeAdaptation and MotionBlur: the first steps of PostProcessing, before Bloom
    /// and the Tonemapper. TAA resolves SceneColor into its history; the histogram measures
    /// that; MotionBlur writes it back to SceneColor, blurred and times the exposure.
    pub fn temporal_post_processing(&self, ctx: &mut PassContext<'_>) {
        let mut s = self.lock();
        let s = &mut *s;
        if s.options.taa {
            ctx.step(super::taa::STEP.name, |ctx| {
                s.taa.record(&s.queue, ctx);
                ctx.output(s.taa.output(), Visualize::Hdr);
            });
        } else {
            s.taa.bypass(ctx, &s.scene_color);
        }
        let input = s.taa.current();
        if s.options.eye_adaptation {
            ctx.step(super::eye_adaptation::STEP.name, |ctx| {
                s.eye.record(&s.queue, ctx, input, TIME_STEP);
                ctx.output(&s.eye.debug, Visualize::Direct);
            });
        } else {
            s.eye.set_fixed(&s.queue, 1.0);
        }
        let blur = s.options.motion_blur;
        ctx.step(super::motion_blur::STEP.name, |ctx| {
            s.motion_blur.record(&s.queue, ctx, input, &s.scene_color_view, blur);
            ctx.output(&s.scene_color, Visualize::Hdr);
        });
    }

    /// Ends the frame: this frame's camera becomes the previous one.
    pub fn end_frame(&self) {
        let mut s = self.lock();
        s.previous = s.current;
    }

    /// The eye adaptation's result buffer (exposure, average luminance, target), for tests.
    pub fn eye_adaptation_buffer(&self) -> wgpu::Buffer {
        self.lock().eye.result.clone()
    }

    /// The velocity target (RG16F), for tests.
    pub fn velocity_texture(&self) -> wgpu::Texture {
        self.lock().velocity.texture.clone()
    }

    /// The scene depth texture the effects read, for tests.
    pub fn scene_depth(&self) -> wgpu::Texture {
        self.lock().scene_depth_attachment.texture().clone()
    }

    /// The HZB texture and its mip count, for tests.
    pub fn hzb(&self) -> (wgpu::Texture, u32) {
        let s = self.lock();
        (s.hzb.texture.clone(), s.hzb.mip_count)
    }

    /// What the lit translucent surfaces read of the translucency lighting volumes.
    pub fn translucency_volume(&self) -> TranslucencyVolumeInputs {
        let s = self.lock();
        let (a0, d0) = s.volumes.volumes(0);
        let (a1, d1) = s.volumes.volumes(1);
        TranslucencyVolumeInputs {
            params: s.volumes.lookup_buffer().clone(),
            ambient: [a0.clone(), a1.clone()],
            directional: [d0.clone(), d1.clone()],
        }
    }

    /// The LightScattering volume written last, for tests.
    pub fn light_scattering(&self) -> wgpu::Texture {
        let s = self.lock();
        s.fog.current_light_scattering().clone()
    }
}

/// The large translucency volume cascade's slice through z = 0 (the middle of the room) for
/// a camera at `camera`.
fn room_slice(camera: Vec3) -> u32 {
    let (origin, cell) = TranslucentVolumes::cascade_box(camera, 1);
    ((-origin.z / cell).max(0.0) as u32).min(super::translucent_volume::VOLUME_SIZE - 1)
}

fn object_transforms(s: &State, index: usize) -> Vec<Mat4> {
    object_transforms_at(s, index, s.time)
}

fn object_transforms_at(s: &State, index: usize, time: f32) -> Vec<Mat4> {
    let o = &s.scene.objects[index];
    if o.mobility == Mobility::Movable && s.options.animate {
        o.instances.iter().map(|m| animate_movable(*m, time)).collect()
    } else {
        o.instances.clone()
    }
}

/// A stationary point light's shadow frustum for ShadowFrustumQueries: the box its
/// per-object shadows can cover (a cube around the light of its radius).
fn point_light_frustum(position: Vec3, radius: f32) -> Mat4 {
    let view = look_at_mat4(position + Vec3::Y * radius, position, Vec3::Z);
    let proj = directx::orthographic(-radius, radius, -radius, radius, 0.0, 2.0 * radius);
    proj * view
}

fn fog_settings(s: &State) -> FogSettings {
    let f = &s.scene.fog;
    FogSettings {
        density: s.options.fog_density,
        height_falloff: f.height_falloff,
        fog_height: f.base_height,
        start_distance: 0.5,
        albedo: Vec3::splat(0.9),
        emissive: Vec3::ZERO,
        anisotropy: 0.4,
        sun_intensity: 1.0,
        sky_intensity: 0.02,
        local_intensity: 1.0,
        near: 0.5,
        far: 40.0,
        shadow: if s.scene.sun.casts_shadows { s.shadow } else { None },
    }
}
