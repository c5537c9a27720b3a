//! ParticleSimulation (desktop, first in the frame): the fire emitter's particles simulated
//! in a compute shader, one thread per particle, in a storage buffer that the Translucency
//! pass then draws as additive camera-facing sprites.

use std::cell::Cell;
use std::sync::Arc;

use glam::{UVec4, Vec4};
use wgpu::util::DeviceExt;

use crate::frame::{PassContext, Visualize};
use crate::gpu_types::{formats, EmitterUniforms, Particle};
use crate::keys;
use crate::pipelines::{
    Blend, ColorTarget, ComputePipeline, DepthState, PipelineError, RenderPipeline, RenderState, VertexLayout,
};
use crate::scene::ParticleEmitter;

use super::{PassInit, Target};

/// Simulation step (seconds); the frame is simulated at a fixed rate so images repeat.
pub const TIME_STEP: f32 = 1.0 / 60.0;
/// Steps simulated when the system is built, so the first frame shows a burning fire.
pub const PREWARM_STEPS: u32 = 120;

/// One emitter's particles on the GPU.
pub struct ParticleSystem {
    queue: wgpu::Queue,
    emitter: EmitterUniforms,
    uniforms: wgpu::Buffer,
    particles: wgpu::Buffer,
    simulation: Arc<ComputePipeline>,
    simulation_group: wgpu::BindGroup,
    count: u32,
    frame: Cell<u32>,
}

impl ParticleSystem {
    /// Builds the buffers and the simulation pipeline and prewarms the particles.
    pub fn new(init: &PassInit<'_>, queue: &wgpu::Queue, e: &ParticleEmitter) -> Result<ParticleSystem, PipelineError> {
        let count = e.max_particles.max(1);
        let emitter = EmitterUniforms {
            position_radius: e.position.extend(e.spawn_radius),
            velocity_jitter: e.initial_velocity.extend(e.velocity_jitter),
            params: Vec4::new(e.lifetime.0, e.lifetime.1, e.buoyancy, TIME_STEP),
            size: Vec4::new(e.size.0, e.size.1, 0.0, 0.0),
            color_start: e.color_start.extend(1.0),
            color_end: e.color_end.extend(1.0),
            counts: UVec4::new(count, 0, 0, 0),
        };
        let uniforms = init.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(&format!("{} emitter uniforms", e.name)),
            contents: bytemuck::bytes_of(&emitter),
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        });
        // Every particle starts dead (age past lifetime): the first step spawns them all,
        // with respawn times spread by their random lifetimes.
        let dead =
            vec![
                Particle { position_age: e.position.extend(1.0), velocity_lifetime: Vec4::new(0.0, 0.0, 0.0, 0.0) };
                count as usize
            ];
        let particles = init.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(&format!("{} particles", e.name)),
            contents: bytemuck::cast_slice(&dead),
            usage: wgpu::BufferUsages::STORAGE,
        });
        let simulation =
            init.cache.compute(&keys::name(keys::particle_simulation_cs::Key {}, keys::level(init.level)?)?)?;
        let simulation_group = simulation.layout.bind_group(
            init.device,
            0,
            &format!("{} simulation", e.name),
            &[("Emitter", uniforms.as_entire_binding()), ("Particles", particles.as_entire_binding())],
        )?;
        let system = ParticleSystem {
            queue: queue.clone(),
            emitter,
            uniforms,
            particles,
            simulation,
            simulation_group,
            count,
            frame: Cell::new(0),
        };
        // Prewarm: the particles all spawn on the first step and die at their random
        // lifetimes, which spreads their ages out. One submit per step: each step has its
        // own frame index in the uniform block.
        for step in 0..PREWARM_STEPS {
            let mut u = system.emitter;
            u.counts.y = u32::MAX - PREWARM_STEPS + step;
            system.queue.write_buffer(&system.uniforms, 0, bytemuck::bytes_of(&u));
            let mut encoder =
                init.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("particle prewarm") });
            {
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("particle prewarm"),
                    timestamp_writes: None,
                });
                system.dispatch(&mut pass);
            }
            system.queue.submit([encoder.finish()]);
        }
        Ok(system)
    }

    fn dispatch(&self, pass: &mut wgpu::ComputePass<'_>) {
        pass.set_pipeline(&self.simulation.pipeline);
        pass.set_bind_group(0, &self.simulation_group, &[]);
        pass.dispatch_workgroups(self.count.div_ceil(self.simulation.workgroup_size[0].max(1)), 1, 1);
    }

    /// ParticleSimulation: one step. Reads and writes the particle buffer.
    pub fn record_simulation(&self, ctx: &mut PassContext<'_>) {
        let frame = self.frame.get();
        self.frame.set(frame.wrapping_add(1));
        let mut u = self.emitter;
        u.counts.y = frame;
        self.queue.write_buffer(&self.uniforms, 0, bytemuck::bytes_of(&u));
        ctx.compute_pass("ParticleSimulation", |pass| self.dispatch(pass));
    }

    /// The emitter uniforms, the particle buffer and the particle count, for frames that
    /// draw the sprites with their own pipelines (the desktop frame's Translucency).
    pub fn sprite_buffers(&self) -> (&wgpu::Buffer, &wgpu::Buffer, u32) {
        (&self.uniforms, &self.particles, self.count)
    }

    pub fn count(&self) -> u32 {
        self.count
    }
}

/// The sprites of a particle system, drawn additively into SceneColor (Translucency).
pub struct ParticleSprites {
    pipeline: Arc<RenderPipeline>,
    groups: Vec<wgpu::BindGroup>,
    count: u32,
}

impl ParticleSprites {
    /// `depth_test`: against SceneDepth (in the frame) or none (the pass's preview image).
    pub fn new(
        init: &PassInit<'_>,
        system: &ParticleSystem,
        depth_test: bool,
    ) -> Result<ParticleSprites, PipelineError> {
        let level = keys::level(init.level)?;
        let vs = keys::name(keys::particle_sprite_vs::Key {}, level)?;
        let ps = keys::name(keys::particle_sprite_ps::Key {}, level)?;
        let mut state = RenderState::triangles(crate::gpu_types::layouts::MESH_INSTANCED);
        if depth_test {
            state = state.with_depth(DepthState::reverse_z(formats::SCENE_DEPTH, false));
        }
        let mut state = state.with_targets(&[ColorTarget::new(formats::SCENE_COLOR, Blend::Additive)]).with_cull(None);
        state.vertex_layout = VertexLayout::NONE;
        let pipeline = init.cache.render(&vs, Some(&ps), &state)?;
        let layout = &pipeline.layout;
        let groups = vec![
            layout.bind_group(init.device, 0, "particle sprites view", &init.shared.view_resources())?,
            layout.bind_group(
                init.device,
                1,
                "particle sprites",
                &[
                    ("Emitter", system.uniforms.as_entire_binding()),
                    ("Particles", system.particles.as_entire_binding()),
                ],
            )?,
        ];
        Ok(ParticleSprites { pipeline, groups, count: system.count })
    }

    /// Draws every particle (six vertices each) into the open render pass.
    pub fn draw(&self, pass: &mut wgpu::RenderPass<'_>) {
        pass.set_pipeline(&self.pipeline.pipeline);
        for (i, g) in self.groups.iter().enumerate() {
            pass.set_bind_group(i as u32, g, &[]);
        }
        pass.draw(0..6, 0..self.count);
    }
}

/// The ParticleSimulation pass of the frame: every emitter steps once. When capturing, the
/// particles are also drawn alone over black (no depth test), as the pass's image.
pub struct ParticleSimulationPass {
    systems: Vec<ParticleSystem>,
    previews: Vec<ParticleSprites>,
}

impl ParticleSimulationPass {
    pub fn new(init: &PassInit<'_>, queue: &wgpu::Queue) -> Result<ParticleSimulationPass, PipelineError> {
        let mut systems = Vec::new();
        let mut previews = Vec::new();
        for e in &init.scene.emitters {
            let system = ParticleSystem::new(init, queue, e)?;
            previews.push(ParticleSprites::new(init, &system, false)?);
            systems.push(system);
        }
        Ok(ParticleSimulationPass { systems, previews })
    }

    pub fn systems(&self) -> &[ParticleSystem] {
        &self.systems
    }

    /// Reads and writes the particle buffers; when capturing, draws them into `preview`.
    pub fn record(&self, ctx: &mut PassContext<'_>, preview: &Target) {
        for s in &self.systems {
            s.record_simulation(ctx);
        }
        if !ctx.capturing() {
            return;
        }
        ctx.render_pass(
            &wgpu::RenderPassDescriptor {
                label: Some("ParticleSimulation preview"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: &preview.view,
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
                for p in &self.previews {
                    p.draw(pass);
                }
            },
        );
        ctx.output(&preview.texture, Visualize::Hdr);
    }
}
