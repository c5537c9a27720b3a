//! Velocity: the screen-space motion of movable meshes (`VelocityShader.usf`) into an RG16F
//! target, uv of this frame minus uv of the previous one, jitter removed. Only movable
//! objects are drawn (in the bundled scene the rock); everything else keeps zero and TAA and
//! motion blur reproject it from depth and the camera. Depth-tested against the prepass
//! depth (reverse-Z, greater-or-equal), no depth write.

use crate::frame::{PassContext, PassDecl, RenderSlot, Slots};
use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use glam::Mat4;

use crate::keys;
use crate::pipelines::{Blend, ColorTarget, DepthState, PipelineError, RenderState};

use super::frame_view::{target_2d, uniform_buffer, view, InstancedMesh, MAX_MESH_INSTANCES};

/// The Velocity declaration.
pub const PASS: PassDecl =
    PassDecl { name: "Velocity", reads: &["Scene", "View", "SceneDepth"], writes: &["Velocity"] };

pub const VELOCITY_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rg16Float;

/// `PreviousTransforms` of `VelocityShader.usf`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
struct PreviousTransforms {
    prev_local_to_world: [Mat4; MAX_MESH_INSTANCES],
}

struct MovableMesh {
    mesh: InstancedMesh,
    previous: wgpu::Buffer,
    bind_group: wgpu::BindGroup,
}

pub struct Velocity {
    pub texture: wgpu::Texture,
    pub view: wgpu::TextureView,
    pipeline: Arc<RenderSlot>,
    meshes: Vec<MovableMesh>,
}

impl Velocity {
    /// `movable`: the meshes that move, each with its own instance buffer.
    pub fn new(
        device: &wgpu::Device,
        cache: Slots<'_>,
        frame_view: &wgpu::Buffer,
        size: [u32; 2],
        depth_format: wgpu::TextureFormat,
        movable: Vec<InstancedMesh>,
    ) -> Result<Velocity, PipelineError> {
        let state = RenderState::triangles(crate::gpu_types::layouts::MESH_INSTANCED)
            .with_targets(&[ColorTarget::new(VELOCITY_FORMAT, Blend::Replace)])
            .with_depth(DepthState::reverse_z(depth_format, false));
        let pipeline = cache.render(
            &keys::name(keys::velocity_vs::Key {}, keys::Level::Sm5)?,
            Some(&keys::name(keys::velocity_ps::Key {}, keys::Level::Sm5)?),
            &state,
        )?;
        let texture = target_2d(
            device,
            "Velocity",
            size,
            VELOCITY_FORMAT,
            wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING,
        );
        let mut meshes = Vec::new();
        for mesh in movable {
            let previous = uniform_buffer(device, "Velocity previous transforms", &PreviousTransforms::default());
            let bind_group = pipeline.layout.bind_group(
                device,
                0,
                "Velocity",
                &[("View", frame_view.as_entire_binding()), ("previous", previous.as_entire_binding())],
            )?;
            meshes.push(MovableMesh { mesh, previous, bind_group });
        }
        Ok(Velocity { view: view(&texture), texture, pipeline, meshes })
    }

    /// Draws the movable meshes: `transforms[i]` holds mesh `i`'s instances this frame and in
    /// the previous frame, as the other passes drew them.
    pub fn record(
        &mut self,
        queue: &wgpu::Queue,
        ctx: &mut PassContext<'_>,
        scene_depth: &wgpu::TextureView,
        transforms: &[(Vec<Mat4>, Vec<Mat4>)],
    ) {
        for (m, (current, previous)) in self.meshes.iter_mut().zip(transforms) {
            m.mesh.set_transforms(queue, current);
            let mut uniforms = PreviousTransforms::default();
            for (i, t) in previous.iter().take(MAX_MESH_INSTANCES).enumerate() {
                uniforms.prev_local_to_world[i] = *t;
            }
            queue.write_buffer(&m.previous, 0, bytemuck::bytes_of(&uniforms));
        }
        let ready = self.pipeline.ready(ctx.pipelines());
        let mut pass = ctx.open_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("Velocity"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: &self.view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT),
                    store: wgpu::StoreOp::Store,
                },
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
        let Some(p) = ready else { return };
        pass.set_pipeline(&p.pipeline);
        for m in &self.meshes {
            pass.set_bind_group(0, &m.bind_group, &[]);
            m.mesh.draw(&mut pass);
        }
    }
}
