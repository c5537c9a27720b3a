//! Velocity: the screen-space motion of movable meshes (`VelocityShader.usf`) into an RG16F
//! target, uv of this frame minus uv of the previous one, jitter removed. Only movable
//! objects are drawn (in the bundled scene the rock); everything else keeps zero and TAA and
//! motion blur reproject it from depth and the camera. Depth-tested against the prepass
//! depth (reverse-Z, greater-or-equal), no depth write.

use std::collections::HashMap;
use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use glam::Mat4;

use crate::gpu_types::formats;
use crate::pipelines::{Blend, ColorTarget, DepthState, PipelineCache, PipelineError, RenderPipeline, RenderState};
use crate::scene::gpu::GpuScene;

use super::frame_view::{target_2d, uniform_buffer, view};

pub const VELOCITY_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rg16Float;

/// `PreviousTransforms` of `VelocityShader.usf`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
struct PreviousTransforms {
    prev_local_to_world: [Mat4; 2],
}

struct MovableObject {
    object: usize,
    previous: wgpu::Buffer,
    bind_group: wgpu::BindGroup,
}

pub struct Velocity {
    pub texture: wgpu::Texture,
    pub view: wgpu::TextureView,
    pipeline: Arc<RenderPipeline>,
    objects: Vec<MovableObject>,
    /// Each movable object's transforms of the last frame recorded.
    last: HashMap<usize, Vec<Mat4>>,
}

impl Velocity {
    /// `movable`: indices into the scene's objects of the meshes that move.
    pub fn new(device: &wgpu::Device, cache: &PipelineCache, frame_view: &wgpu::Buffer, size: [u32; 2], movable: &[usize]) -> Result<Velocity, PipelineError> {
        let state = RenderState::mesh()
            .with_targets(&[ColorTarget { format: VELOCITY_FORMAT, blend: Blend::Replace }])
            .with_depth(DepthState::reverse_z(formats::SCENE_DEPTH, false));
        let pipeline = cache.render("VelocityVS@sm5", Some("VelocityPS@sm5"), &state)?;
        let texture = target_2d(device, "Velocity", size, VELOCITY_FORMAT, wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING);
        let mut objects = Vec::new();
        for &object in movable {
            let previous = uniform_buffer(device, "Velocity previous transforms", &PreviousTransforms::default());
            let bind_group = pipeline.layout.bind_group(device, 0, "Velocity", &[
                ("view", frame_view.as_entire_binding()),
                ("previous", previous.as_entire_binding()),
            ])?;
            objects.push(MovableObject { object, previous, bind_group });
        }
        Ok(Velocity { view: view(&texture), texture, pipeline, objects, last: HashMap::new() })
    }

    /// Draws the movable objects; `transforms(object)` gives their instances' local-to-world
    /// matrices this frame (as uploaded in their instance buffers). The previous frame's are
    /// remembered from the last call (the same on the first frame: no motion).
    pub fn record(&mut self, queue: &wgpu::Queue, encoder: &mut wgpu::CommandEncoder, scene: &GpuScene, scene_depth: &wgpu::TextureView, transforms: &dyn Fn(usize) -> Vec<Mat4>) {
        for o in &self.objects {
            let current = transforms(o.object);
            let previous = self.last.get(&o.object).cloned().unwrap_or_else(|| current.clone());
            let mut uniforms = PreviousTransforms::default();
            for (i, m) in previous.iter().take(2).enumerate() {
                uniforms.prev_local_to_world[i] = *m;
            }
            queue.write_buffer(&o.previous, 0, bytemuck::bytes_of(&uniforms));
            self.last.insert(o.object, current);
        }
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("Velocity"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: &self.view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations { load: wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT), store: wgpu::StoreOp::Store },
            })],
            depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                view: scene_depth,
                depth_ops: Some(wgpu::Operations { load: wgpu::LoadOp::Load, store: wgpu::StoreOp::Store }),
                stencil_ops: None,
            }),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_pipeline(&self.pipeline.pipeline);
        for o in &self.objects {
            pass.set_bind_group(0, &o.bind_group, &[]);
            scene.draw(&mut pass, &scene.objects[o.object]);
        }
    }
}
