//! The renderer's one particle system: GPU sprite particles (`Desktop/ParticleSimulation.usf`,
//! `Desktop/ParticleSpriteShader.usf`), every emitter stepped at one fixed [`TIME_STEP`].
//! Each emitter keeps its state in two pairs of textures, positions in RGBA32F (xyz, age) and
//! velocities in RGBA16F (xyz, lifetime), one texel per particle, read by one simulation and
//! written by the next (ping-pong). The emitters that do not collide (the scene's fire and its
//! smoke) are simulated at the start of the frame (ParticleSimulation, whose `Fire` step also
//! pictures them over black when capturing); the sparks collide with the scene, so they are
//! simulated after the base pass against the depth buffer and GBuffer normals. All are drawn
//! as camera-facing sprites, instanced (one instance per particle, 6 vertices), in
//! Translucency; the fire's heat haze is drawn again into the distortion offsets. The scene's
//! emitters can be warmed up when the system is built ([`EmitterDesc::prewarm`]), so the first
//! frame shows a burning fire.
//!
//! Sorting: the sprites are emissive (added) or faint premultiplied smoke, drawn in emitter
//! order without a per-particle sort. The mobile frames draw no particles.

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use glam::{UVec4, Vec3, Vec4};

use crate::frame::{ComputeSlot, FramePipelines, PassContext, PassDecl, RenderSlot, Slots, Visualize};
use crate::gpu_types::uniform_buffer;
use crate::keys;
use crate::pipelines::{Blend, ColorTarget, DepthState, PipelineCache, PipelineError, RenderState, VertexLayout};
use crate::scene::ParticleEmitter;

/// The ParticleSimulation pass at the start of the frame (the emitters that do not collide).
pub const SIMULATION_PASS: PassDecl =
    PassDecl { name: "ParticleSimulation", reads: &["ParticleState"], writes: &["ParticleState"] };

/// The step that simulates the colliding emitters once the depth is final (in the BasePass).
pub const COLLISION_STEP: PassDecl =
    PassDecl { name: "ParticleCollision", reads: &["View", "SceneDepth", "ParticleState"], writes: &["ParticleState"] };

/// The step that draws the sprites over SceneColor (in Translucency).
pub const SPRITES_STEP: PassDecl = PassDecl {
    name: "ParticleSprites",
    reads: &["View", "SceneDepth", "ParticleState", "SceneColor"],
    writes: &["SceneColor"],
};

pub const POSITION_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba32Float;
pub const VELOCITY_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba16Float;
/// Particles per row of the state textures.
pub const STATE_WIDTH: u32 = 64;
/// The one fixed simulation step of every emitter (the desktop frame's time step is the same,
/// so frames are reproducible).
pub const TIME_STEP: f32 = 1.0 / 30.0;
/// Steps simulated when the system is built for the emitters that are prewarmed (the scene's
/// own: longer than the fire's longest lifetime), so the first frame shows them burning.
pub const PREWARM_STEPS: u32 = 60;

/// `SimulationParams` of `ParticleSimulation.usf`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
struct SimulationParams {
    emitter: Vec4,
    initial_velocity: Vec4,
    acceleration: Vec4,
    timing: Vec4,
    counts: UVec4,
}

/// `SpriteParams` of `ParticleSpriteShader.usf`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
struct SpriteParams {
    color_birth: Vec4,
    color_death: Vec4,
    size: Vec4,
    counts: UVec4,
    lighting: Vec4,
}

/// What an emitter simulates and draws.
#[derive(Clone, Debug, PartialEq)]
pub struct EmitterDesc {
    pub name: String,
    pub position: Vec3,
    pub spawn_radius: f32,
    pub max_particles: u32,
    pub lifetime: (f32, f32),
    pub initial_velocity: Vec3,
    pub velocity_jitter: f32,
    pub acceleration: Vec3,
    pub drag: f32,
    /// Collides with the depth buffer (simulated after the base pass).
    pub collides: bool,
    /// Velocity kept along the normal after a bounce.
    pub restitution: f32,
    pub size: (f32, f32),
    /// Stretch of the sprite along its velocity, per m/s.
    pub stretch: f32,
    pub color_birth: Vec4,
    pub color_death: Vec4,
    /// Heat haze strength (0: no distortion).
    pub distortion: f32,
    /// Lit by the translucency lighting volume (the colours are albedo); else emissive.
    pub lit: bool,
    /// One of the frame's particle effects (sparks, smoke): drawn only while the effects'
    /// particles are on. The scene's own emitters (the fire) are drawn always.
    pub effect: bool,
    /// Simulated [`PREWARM_STEPS`] steps when the system is built (only for emitters that do
    /// not collide: there is no depth buffer yet).
    pub prewarm: bool,
}

impl EmitterDesc {
    /// The scene's fire emitter (no collision, rising with buoyancy, with heat haze).
    pub fn fire(e: &ParticleEmitter) -> EmitterDesc {
        EmitterDesc {
            name: e.name.clone(),
            position: e.position,
            spawn_radius: e.spawn_radius,
            max_particles: e.max_particles,
            lifetime: e.lifetime,
            initial_velocity: e.initial_velocity,
            velocity_jitter: e.velocity_jitter,
            acceleration: Vec3::Y * e.buoyancy,
            drag: 0.5,
            collides: false,
            restitution: 0.0,
            size: e.size,
            stretch: 0.0,
            color_birth: e.color_start.extend(0.6),
            color_death: e.color_end.extend(0.0),
            distortion: 0.6,
            lit: false,
            effect: false,
            prewarm: true,
        }
    }

    /// Smoke rising from the fire: grey, growing, lit by the translucency lighting volume.
    pub fn smoke(e: &ParticleEmitter) -> EmitterDesc {
        EmitterDesc {
            name: format!("{}Smoke", e.name),
            position: e.position + Vec3::Y * 0.9,
            spawn_radius: e.spawn_radius,
            max_particles: 256,
            lifetime: (2.5, 4.0),
            initial_velocity: Vec3::new(0.0, 0.5, 0.0),
            velocity_jitter: 0.15,
            acceleration: Vec3::new(0.1, 0.2, 0.0),
            drag: 0.3,
            collides: false,
            restitution: 0.0,
            size: (0.4, 1.4),
            stretch: 0.0,
            color_birth: Vec4::new(0.5, 0.5, 0.52, 0.35),
            color_death: Vec4::new(0.6, 0.6, 0.62, 0.0),
            distortion: 0.0,
            lit: true,
            effect: true,
            prewarm: false,
        }
    }

    /// Sparks thrown out of the fire: they fall and bounce off the floor and walls
    /// (collision with the depth buffer).
    pub fn sparks(e: &ParticleEmitter) -> EmitterDesc {
        EmitterDesc {
            name: format!("{}Sparks", e.name),
            position: e.position + Vec3::Y * 0.4,
            spawn_radius: e.spawn_radius * 0.5,
            max_particles: 512,
            lifetime: (1.5, 3.0),
            initial_velocity: Vec3::new(0.0, 3.0, 0.0),
            velocity_jitter: 1.6,
            acceleration: Vec3::new(0.0, -9.8, 0.0),
            drag: 0.2,
            collides: true,
            restitution: 0.5,
            size: (0.05, 0.02),
            stretch: 0.08,
            color_birth: Vec4::new(12.0, 6.0, 1.5, 0.0),
            color_death: Vec4::new(2.0, 0.4, 0.05, 0.0),
            distortion: 0.0,
            lit: false,
            effect: true,
            prewarm: false,
        }
    }
}

struct Emitter {
    desc: EmitterDesc,
    seed: u32,
    sim_params: wgpu::Buffer,
    /// The sprites' `SpriteParams` (constant; kept with the bind groups that read it).
    _sprite_params: wgpu::Buffer,
    positions: [wgpu::Texture; 2],
    velocities: [wgpu::Texture; 2],
    /// simulate[i] reads state i and writes state 1 - i.
    simulate: [wgpu::BindGroup; 2],
    /// sprites[i] reads state i (the sprite pipeline; distortion: the heat haze's).
    sprites: [wgpu::BindGroup; 2],
    distortion: [wgpu::BindGroup; 2],
    current: usize,
}

/// Inputs of the colliding simulation.
pub struct CollisionInputs<'a> {
    pub scene_depth: &'a wgpu::TextureView,
    pub gbuffer_a: &'a wgpu::TextureView,
}

/// The formats of the frame's passes the particles draw in.
#[derive(Clone, Copy, Debug)]
pub struct ParticleFormats {
    /// The colour target of the sprites (and of the `Fire` step's picture).
    pub color: wgpu::TextureFormat,
    /// The depth the sprites and the heat haze are tested against (read-only).
    pub depth: wgpu::TextureFormat,
    /// The distortion offsets the heat haze adds to.
    pub distortion: wgpu::TextureFormat,
}

/// What the particle system is built from.
pub struct ParticlesInit<'a> {
    pub device: &'a wgpu::Device,
    /// Submits the prewarm steps.
    pub queue: &'a wgpu::Queue,
    pub cache: Slots<'a>,
    /// The frame's `SceneView` buffer (`View`).
    pub view: &'a wgpu::Buffer,
    pub collision: CollisionInputs<'a>,
    pub lighting_volume: LightingVolume<'a>,
    pub formats: ParticleFormats,
    /// Size of the `Fire` step's picture (the frame's).
    pub size: [u32; 2],
}

pub struct Particles {
    emitters: Vec<Emitter>,
    frame: u32,
    /// [without collision, with collision]
    simulation: [Arc<ComputeSlot>; 2],
    /// The sprites over the frame's colour target (depth tested), the same over the `Fire`
    /// step's picture (no depth), and the heat haze into RG16F offsets.
    sprite_pipeline: Arc<RenderSlot>,
    preview_pipeline: Arc<RenderSlot>,
    distortion_pipeline: Arc<RenderSlot>,
    /// The `Fire` step's picture: the emitters simulated at the start of the frame, alone
    /// over black.
    preview: (wgpu::Texture, wgpu::TextureView),
    /// States of no emitter (1x1), for scenes without one.
    empty: ([wgpu::Texture; 2], [wgpu::Texture; 2]),
}

/// The translucency lighting volumes as the lit sprites read them: both cascades (0 inner,
/// 1 outer) of Ambient and Dir, and their boxes this frame (`TranslucencyLightingVolumeParams`,
/// written every frame by InjectTranslucentVolume).
pub struct LightingVolume<'a> {
    pub params: &'a wgpu::Buffer,
    pub ambient: [&'a wgpu::TextureView; 2],
    pub directional: [&'a wgpu::TextureView; 2],
}

fn view(texture: &wgpu::Texture) -> wgpu::TextureView {
    texture.create_view(&wgpu::TextureViewDescriptor::default())
}

/// The pipelines of the particle system.
struct ParticlePipelines {
    /// [without collision, with collision]
    simulation: [Arc<ComputeSlot>; 2],
    sprite: Arc<RenderSlot>,
    /// The sprite pipeline's shaders without depth: the same layout.
    preview: Arc<RenderSlot>,
    distortion: Arc<RenderSlot>,
}

impl ParticlePipelines {
    fn new(cache: Slots<'_>, formats: ParticleFormats) -> Result<ParticlePipelines, PipelineError> {
        let (vs, ps) = (
            keys::name(keys::gpu_sprite_vs::Key {}, keys::Level::Sm5)?,
            keys::name(keys::gpu_sprite_ps::Key {}, keys::Level::Sm5)?,
        );
        let distortion = cache.render(
            &vs,
            Some(&keys::name(keys::gpu_sprite_distortion_ps::Key {}, keys::Level::Sm5)?),
            &Particles::distortion_state(formats.distortion, Some(formats.depth)),
        )?;
        let sprite = cache.render(&vs, Some(&ps), &sprite_state(formats.color, Some(formats.depth)))?;
        let preview = cache.render(&vs, Some(&ps), &sprite_state(formats.color, None))?;
        let simulation = |collision: bool| {
            let key = keys::gpu_particle_simulation_cs::Key { particle_collision: collision };
            cache.compute(&keys::name(key, keys::Level::Sm5)?)
        };
        Ok(ParticlePipelines { simulation: [simulation(false)?, simulation(true)?], sprite, preview, distortion })
    }
}

/// The `Fire` step's picture.
fn preview_target(device: &wgpu::Device, format: wgpu::TextureFormat, size: [u32; 2]) -> wgpu::Texture {
    device.create_texture(&wgpu::TextureDescriptor {
        label: Some("ParticleSimulation preview"),
        size: wgpu::Extent3d { width: size[0].max(1), height: size[1].max(1), depth_or_array_layers: 1 },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format,
        usage: wgpu::TextureUsages::RENDER_ATTACHMENT
            | wgpu::TextureUsages::TEXTURE_BINDING
            | wgpu::TextureUsages::COPY_SRC,
        view_formats: &[],
    })
}

impl Emitter {
    /// Emitter `index`'s states, uniforms and bind groups.
    fn new(
        init: &ParticlesInit<'_>,
        pipelines: &ParticlePipelines,
        volume_sampler: &wgpu::Sampler,
        index: usize,
        desc: EmitterDesc,
    ) -> Result<Emitter, PipelineError> {
        let ParticlesInit { device, view: frame_view, ref collision, ref lighting_volume, .. } = *init;
        let sim = &pipelines.simulation[usize::from(desc.collides)];
        let rows = desc.max_particles.div_ceil(STATE_WIDTH);
        let state = |label: &str, format| {
            crate::frame::target_2d(
                device,
                &format!("{} {label}", desc.name),
                [STATE_WIDTH, rows],
                format,
                wgpu::TextureUsages::STORAGE_BINDING | wgpu::TextureUsages::TEXTURE_BINDING,
            )
        };
        let positions =
            [state("ParticleStatePosition0", POSITION_FORMAT), state("ParticleStatePosition1", POSITION_FORMAT)];
        let velocities =
            [state("ParticleStateVelocity0", VELOCITY_FORMAT), state("ParticleStateVelocity1", VELOCITY_FORMAT)];
        let sim_params = uniform_buffer(device, &format!("{} simulation", desc.name), &SimulationParams::default());
        let sprite_params = uniform_buffer(device, &format!("{} sprites", desc.name), &sprite_params(&desc));
        let pos_views = [view(&positions[0]), view(&positions[1])];
        let vel_views = [view(&velocities[0]), view(&velocities[1])];
        let make_sim = |i: usize| {
            let mut resources = vec![
                ("sim", sim_params.as_entire_binding()),
                ("prev_position", wgpu::BindingResource::TextureView(&pos_views[i])),
                ("prev_velocity", wgpu::BindingResource::TextureView(&vel_views[i])),
                ("out_position", wgpu::BindingResource::TextureView(&pos_views[1 - i])),
                ("out_velocity", wgpu::BindingResource::TextureView(&vel_views[1 - i])),
            ];
            if desc.collides {
                resources.push(("View", frame_view.as_entire_binding()));
                resources.push(("SceneDepthTexture", wgpu::BindingResource::TextureView(collision.scene_depth)));
                resources.push(("gbuffer_a", wgpu::BindingResource::TextureView(collision.gbuffer_a)));
            }
            sim.layout.bind_group(device, 0, &format!("{} simulation {i}", desc.name), &resources)
        };
        let make_sprites = |i: usize, pipeline: &RenderSlot, lit: bool| {
            let mut resources = vec![
                ("View", frame_view.as_entire_binding()),
                ("sprite", sprite_params.as_entire_binding()),
                ("particle_position", wgpu::BindingResource::TextureView(&pos_views[i])),
                ("particle_velocity", wgpu::BindingResource::TextureView(&vel_views[i])),
            ];
            if lit {
                resources.extend([
                    ("translucency_ambient_inner", wgpu::BindingResource::TextureView(lighting_volume.ambient[0])),
                    ("translucency_dir_inner", wgpu::BindingResource::TextureView(lighting_volume.directional[0])),
                    ("translucency_ambient_outer", wgpu::BindingResource::TextureView(lighting_volume.ambient[1])),
                    ("translucency_dir_outer", wgpu::BindingResource::TextureView(lighting_volume.directional[1])),
                    ("translucency_volume", lighting_volume.params.as_entire_binding()),
                    ("volume_sampler", wgpu::BindingResource::Sampler(volume_sampler)),
                ]);
            }
            pipeline.layout.bind_group(device, 0, &format!("{} sprites {i}", desc.name), &resources)
        };
        // (the preview pipeline has the sprite pipeline's layout: the same shaders)
        let sprites = [make_sprites(0, &pipelines.sprite, true)?, make_sprites(1, &pipelines.sprite, true)?];
        let distortion =
            [make_sprites(0, &pipelines.distortion, false)?, make_sprites(1, &pipelines.distortion, false)?];
        let simulate = [make_sim(0)?, make_sim(1)?];
        Ok(Emitter {
            desc,
            seed: 0x9e37_79b9u32.wrapping_mul(index as u32 + 1),
            sim_params,
            _sprite_params: sprite_params,
            positions,
            velocities,
            simulate,
            sprites,
            distortion,
            current: 0,
        })
    }
}

impl Particles {
    /// Builds the emitters' states and every pipeline, and prewarms the emitters that ask for it.
    pub fn new(init: &ParticlesInit<'_>, descs: Vec<EmitterDesc>) -> Result<Particles, PipelineError> {
        let (device, formats) = (init.device, init.formats);
        let pipelines = ParticlePipelines::new(init.cache, formats)?;
        let volume_sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("particle lighting volume"),
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            mipmap_filter: wgpu::MipmapFilterMode::Linear,
            ..Default::default()
        });
        let emitters = descs
            .into_iter()
            .enumerate()
            .map(|(index, desc)| Emitter::new(init, &pipelines, &volume_sampler, index, desc))
            .collect::<Result<Vec<_>, _>>()?;
        let empty_state = |label: &str, format| {
            device.create_texture(&wgpu::TextureDescriptor {
                label: Some(label),
                size: wgpu::Extent3d { width: 1, height: 1, depth_or_array_layers: 1 },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format,
                usage: wgpu::TextureUsages::STORAGE_BINDING
                    | wgpu::TextureUsages::TEXTURE_BINDING
                    | wgpu::TextureUsages::COPY_SRC,
                view_formats: &[],
            })
        };
        let empty = (
            [
                empty_state("NoParticles position", POSITION_FORMAT),
                empty_state("NoParticles position", POSITION_FORMAT),
            ],
            [
                empty_state("NoParticles velocity", VELOCITY_FORMAT),
                empty_state("NoParticles velocity", VELOCITY_FORMAT),
            ],
        );
        let preview = preview_target(device, formats.color, init.size);
        let preview_view = view(&preview);
        let mut particles = Particles {
            emitters,
            frame: 0,
            simulation: pipelines.simulation,
            sprite_pipeline: pipelines.sprite,
            preview_pipeline: pipelines.preview,
            distortion_pipeline: pipelines.distortion,
            preview: (preview, preview_view),
            empty,
        };
        particles.prewarm(init.cache.cache, device, init.queue)?;
        Ok(particles)
    }

    /// Steps the emitters that ask for it [`PREWARM_STEPS`] times, one submit per step (each
    /// step has its own frame index in the simulation's uniform block). Their ages spread
    /// out over the first lifetime, as they do in a running frame.
    fn prewarm(
        &mut self,
        cache: &PipelineCache,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
    ) -> Result<(), PipelineError> {
        if !self.emitters.iter().any(|e| e.desc.prewarm && !e.desc.collides) {
            return Ok(());
        }
        // no frame waits on this: the system is being built, so the pipeline is made now
        let pipeline = cache.compute_key(self.simulation[0].key())?;
        for step in 0..PREWARM_STEPS {
            // frame indices before the frame's own (which start at 1), for their own seeds
            let frame = u32::MAX - PREWARM_STEPS + 1 + step;
            let mut encoder =
                device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("particle prewarm") });
            for e in self.emitters.iter_mut().filter(|e| e.desc.prewarm && !e.desc.collides) {
                // made with the renderer, before any frame: no pass context to record through
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some(&format!("ParticleSimulation {}", e.desc.name)),
                    timestamp_writes: None,
                });
                Self::step(&pipeline.pipeline, queue, &mut pass, e, frame);
            }
            queue.submit([encoder.finish()]);
        }
        Ok(())
    }

    fn step(
        pipeline: &wgpu::ComputePipeline,
        queue: &wgpu::Queue,
        pass: &mut wgpu::ComputePass<'_>,
        e: &mut Emitter,
        frame: u32,
    ) {
        let d = &e.desc;
        let rows = d.max_particles.div_ceil(STATE_WIDTH);
        let params = SimulationParams {
            emitter: d.position.extend(d.spawn_radius),
            initial_velocity: d.initial_velocity.extend(d.velocity_jitter),
            acceleration: d.acceleration.extend(d.drag),
            timing: Vec4::new(TIME_STEP, d.lifetime.0, d.lifetime.1, d.restitution),
            counts: UVec4::new(STATE_WIDTH, d.max_particles, frame, e.seed),
        };
        queue.write_buffer(&e.sim_params, 0, bytemuck::bytes_of(&params));
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, &e.simulate[e.current], &[]);
        pass.dispatch_workgroups(STATE_WIDTH.div_ceil(8), rows.div_ceil(8), 1);
        e.current = 1 - e.current;
    }

    /// Runs one simulation step of the emitters that collide (`true`, after the base pass)
    /// or of the others (`false`, at the start of the frame).
    pub fn simulate(&mut self, queue: &wgpu::Queue, ctx: &mut PassContext<'_>, colliding: bool) {
        if !colliding {
            self.frame += 1;
        }
        let Some(pipeline) = self.simulation[usize::from(colliding)].ready(ctx.pipelines()) else { return };
        for e in self.emitters.iter_mut().filter(|e| e.desc.collides == colliding) {
            let mut pass = ctx.open_compute_pass(&format!("ParticleSimulation {}", e.desc.name));
            Self::step(&pipeline.pipeline, queue, &mut pass, e, self.frame);
        }
    }

    /// When capturing: draws the emitters simulated at the start of the frame alone over
    /// black (no depth test), as the picture of the step that simulated them.
    pub fn record_preview(&self, ctx: &mut PassContext<'_>) {
        if !ctx.capturing() {
            return;
        }
        {
            let ready = self.preview_pipeline.ready(ctx.pipelines());
            let mut pass = ctx.open_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("ParticleSimulation preview"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: &self.preview.1,
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
            });
            if let Some(p) = ready {
                pass.set_pipeline(&p.pipeline);
                for e in self.emitters.iter().filter(|e| !e.desc.collides) {
                    pass.set_bind_group(0, &e.sprites[e.current], &[]);
                    pass.draw(0..6, 0..e.desc.max_particles);
                }
            }
        }
        ctx.output(&self.preview.0, Visualize::Hdr);
    }

    /// The state textures (positions, velocities) of the first emitter that (does not)
    /// collide.
    /// (A scene without emitters has empty 1x1 states, so the dumps still have a source.)
    pub fn state_textures(&self, colliding: bool) -> (&[wgpu::Texture; 2], &[wgpu::Texture; 2]) {
        match self.emitters.iter().find(|e| e.desc.collides == colliding) {
            Some(e) => (&e.positions, &e.velocities),
            None => (&self.empty.0, &self.empty.1),
        }
    }

    /// Which state of that emitter holds the latest simulation (0 or 1).
    pub fn current_index(&self, colliding: bool) -> usize {
        self.emitters.iter().find(|e| e.desc.collides == colliding).map_or(0, |e| e.current)
    }

    /// The latest position state of the first emitter that (does not) collide, for the dump.
    pub fn position_state(&self, colliding: bool) -> Option<&wgpu::Texture> {
        self.emitters.iter().find(|e| e.desc.collides == colliding).map(|e| &e.positions[e.current])
    }

    pub fn velocity_state(&self, colliding: bool) -> Option<&wgpu::Texture> {
        self.emitters.iter().find(|e| e.desc.collides == colliding).map(|e| &e.velocities[e.current])
    }

    /// Draws the emitters' sprites, instanced, into a translucency pass over the colour target
    /// given to `new`, depth tested (read-only): the scene's emitters always, the particle
    /// effects (sparks, smoke) only with `effects`.
    pub fn draw_sprites(&self, pipelines: FramePipelines<'_>, pass: &mut wgpu::RenderPass<'_>, effects: bool) {
        let Some(p) = self.sprite_pipeline.ready(pipelines) else { return };
        pass.set_pipeline(&p.pipeline);
        for e in self.emitters.iter().filter(|e| effects || !e.desc.effect) {
            pass.set_bind_group(0, &e.sprites[e.current], &[]);
            pass.draw(0..6, 0..e.desc.max_particles);
        }
    }

    /// Draws the heat haze of the emitters that distort into a distortion pass (RG16F,
    /// additive offsets).
    pub fn draw_distortion(&self, pipelines: FramePipelines<'_>, pass: &mut wgpu::RenderPass<'_>) {
        let Some(p) = self.distortion_pipeline.ready(pipelines) else { return };
        pass.set_pipeline(&p.pipeline);
        for e in self.emitters.iter().filter(|e| e.desc.distortion > 0.0) {
            pass.set_bind_group(0, &e.distortion[e.current], &[]);
            pass.draw(0..6, 0..e.desc.max_particles);
        }
    }

    /// The fixed-function state of the sprites: premultiplied over the target, depth-tested
    /// (read-only).
    pub fn sprite_state(format: wgpu::TextureFormat, depth: Option<wgpu::TextureFormat>) -> RenderState {
        sprite_state(format, depth)
    }

    /// The fixed-function state of the heat haze: additive offsets.
    pub fn distortion_state(format: wgpu::TextureFormat, depth: Option<wgpu::TextureFormat>) -> RenderState {
        let mut state = sprite_state(format, depth);
        state.color_targets[0].blend = Blend::Additive.state();
        state
    }
}

fn sprite_params(d: &EmitterDesc) -> SpriteParams {
    SpriteParams {
        color_birth: d.color_birth,
        color_death: d.color_death,
        size: Vec4::new(d.size.0, d.size.1, d.stretch, d.distortion * 0.02),
        counts: UVec4::new(STATE_WIDTH, d.max_particles, 0, 0),
        lighting: Vec4::new(if d.lit { 1.0 } else { 0.0 }, 0.0, 0.0, 0.0),
    }
}

fn sprite_state(format: wgpu::TextureFormat, depth: Option<wgpu::TextureFormat>) -> RenderState {
    let mut state = RenderState::fullscreen(ColorTarget::new(format, Blend::PremultipliedAlpha));
    state.vertex_layout = VertexLayout::NONE;
    if let Some(depth) = depth {
        state = state.with_depth(DepthState::reverse_z(depth, false));
    }
    state
}
