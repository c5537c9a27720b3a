//! The TAA jitter sequence, the directional light's cascades as the fog and the translucency
//! volumes read them, and small helpers the passes of the desktop frame share (targets,
//! uniform buffers, samplers, full-screen draws). The view they bind is the one
//! [`crate::scene::view::SceneView`].

use glam::{Mat4, Vec2, Vec4};

pub use crate::frame::target_2d;
use crate::frame::{GroupedRenderPass, PassContext};

/// Element `index` (from 1) of the Halton sequence in `base`, in [0, 1).
pub fn halton(mut index: u32, base: u32) -> f32 {
    let mut f = 1.0;
    let mut r = 0.0;
    while index > 0 {
        f /= base as f32;
        r += f * (index % base) as f32;
        index /= base;
    }
    r
}

/// The TAA jitter of frame `frame` in NDC units for a `width` x `height` target: Halton (2, 3)
/// over 8 frames, within +-half a pixel, as Unreal's TemporalAASamples = 8.
pub fn taa_jitter(frame: u64, width: u32, height: u32) -> Vec2 {
    let i = (frame % 8) as u32 + 1;
    let pixel = Vec2::new(halton(i, 2) - 0.5, halton(i, 3) - 0.5);
    Vec2::new(pixel.x * 2.0 / width as f32, -pixel.y * 2.0 / height as f32)
}

/// What an effect pass is built with: the device, the runtime's pipeline cache and the frame's
/// one `SceneView` buffer, which the pass binds as `View`.
#[derive(Clone, Copy)]
pub struct EffectPassInit<'a> {
    pub device: &'a wgpu::Device,
    pub cache: crate::frame::Slots<'a>,
    pub frame_view: &'a wgpu::Buffer,
}

/// The directional light's shadow map as the fog and the translucency volumes read it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DirectionalShadow {
    /// World -> clip of each cascade.
    pub cascades: [Mat4; 3],
    /// View distances where cascades 0, 1, 2 end.
    pub splits: [f32; 3],
    /// Where each cascade lies in the atlas: uv offset (xy) and scale (zw).
    pub rects: [Vec4; 3],
}

impl DirectionalShadow {
    /// One shadow map covering every distance.
    pub fn single(view_proj: Mat4) -> DirectionalShadow {
        DirectionalShadow { cascades: [view_proj; 3], splits: [f32::MAX; 3], rects: [Vec4::new(0.0, 0.0, 1.0, 1.0); 3] }
    }

    /// The shaders' matrices, splits (w: 1 with a shadow) and rects.
    pub fn uniforms(shadow: Option<&DirectionalShadow>) -> ([Mat4; 3], Vec4, [Vec4; 3]) {
        match shadow {
            Some(s) => (s.cascades, Vec4::new(s.splits[0], s.splits[1], s.splits[2], 1.0), s.rects),
            None => ([Mat4::IDENTITY; 3], Vec4::ZERO, [Vec4::ZERO; 3]),
        }
    }
}

/// A scene mesh the effect passes draw again (Velocity, DistortionAccum), with the
/// instance vertex buffer they keep themselves (the local vertex factory's layout:
/// `MeshVertex` in buffer 0, one local-to-world matrix per instance in buffer 1).
pub struct InstancedMesh {
    pub vertices: wgpu::Buffer,
    pub indices: wgpu::Buffer,
    pub index_count: u32,
    pub instances: wgpu::Buffer,
    pub instance_count: u32,
}

/// Most instances of one [`InstancedMesh`].
pub const MAX_MESH_INSTANCES: usize = 2;

impl InstancedMesh {
    pub fn new(
        device: &wgpu::Device,
        label: &str,
        vertices: &wgpu::Buffer,
        indices: &wgpu::Buffer,
        index_count: u32,
    ) -> InstancedMesh {
        let instances = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(&format!("{label} instances")),
            size: (MAX_MESH_INSTANCES * 64) as u64,
            usage: wgpu::BufferUsages::VERTEX | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        InstancedMesh {
            vertices: vertices.clone(),
            indices: indices.clone(),
            index_count,
            instances,
            instance_count: 0,
        }
    }

    /// This frame's transforms (at most [`MAX_MESH_INSTANCES`]).
    pub fn set_transforms(&mut self, queue: &wgpu::Queue, transforms: &[Mat4]) {
        let n = transforms.len().min(MAX_MESH_INSTANCES);
        let cols: Vec<[[f32; 4]; 4]> = transforms[..n].iter().map(|m| m.to_cols_array_2d()).collect();
        if n > 0 {
            queue.write_buffer(&self.instances, 0, bytemuck::cast_slice(&cols));
        }
        self.instance_count = n as u32;
    }

    pub fn draw(&self, pass: &mut wgpu::RenderPass<'_>) {
        pass.set_vertex_buffer(0, self.vertices.slice(..));
        pass.set_vertex_buffer(1, self.instances.slice(..));
        pass.set_index_buffer(self.indices.slice(..), wgpu::IndexFormat::Uint32);
        pass.draw_indexed(0..self.index_count, 0, 0..self.instance_count);
    }
}

pub use crate::gpu_types::uniform_buffer;

/// A storage volume (froxels, translucency lighting volumes) of `size` cells: a 2D array
/// texture with one layer per z cell (`VolumeTextureCommon.ush`). wgpu-hal 30's GL backend
/// binds a D3 storage view with one slice only (`ImageBinding::array_layer` is `Some(0)` for
/// every view dimension but D2Array and CubeArray, so `glBindImageTexture` gets
/// layered = false) and a compute shader's writes to the other slices are lost; a D2Array
/// storage view is bound layered, on GL as on Vulkan.
pub fn volume(device: &wgpu::Device, label: &str, size: [u32; 3], format: wgpu::TextureFormat) -> wgpu::Texture {
    device.create_texture(&wgpu::TextureDescriptor {
        label: Some(label),
        size: wgpu::Extent3d { width: size[0], height: size[1], depth_or_array_layers: size[2] },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format,
        usage: wgpu::TextureUsages::STORAGE_BINDING
            | wgpu::TextureUsages::TEXTURE_BINDING
            | wgpu::TextureUsages::COPY_SRC,
        view_formats: &[],
    })
}

pub fn view(texture: &wgpu::Texture) -> wgpu::TextureView {
    texture.create_view(&wgpu::TextureViewDescriptor::default())
}

/// Whether `texture` is a [`volume`] (more than one layer).
pub fn is_volume(texture: &wgpu::Texture) -> bool {
    texture.dimension() == wgpu::TextureDimension::D2 && texture.depth_or_array_layers() > 1
}

/// A view of every layer of a [`volume`] (D2Array, also for a volume of one layer).
pub fn volume_view(texture: &wgpu::Texture) -> wgpu::TextureView {
    texture.create_view(&wgpu::TextureViewDescriptor {
        dimension: Some(wgpu::TextureViewDimension::D2Array),
        ..Default::default()
    })
}

/// Bilinear, clamped.
pub fn linear_sampler(device: &wgpu::Device, label: &str) -> wgpu::Sampler {
    device.create_sampler(&wgpu::SamplerDescriptor {
        label: Some(label),
        address_mode_u: wgpu::AddressMode::ClampToEdge,
        address_mode_v: wgpu::AddressMode::ClampToEdge,
        address_mode_w: wgpu::AddressMode::ClampToEdge,
        mag_filter: wgpu::FilterMode::Linear,
        min_filter: wgpu::FilterMode::Linear,
        mipmap_filter: wgpu::MipmapFilterMode::Linear,
        ..Default::default()
    })
}

/// Groups of `workgroup` threads covering `n` items.
pub fn groups(n: u32, workgroup: u32) -> u32 {
    n.div_ceil(workgroup.max(1))
}

/// A render pass over one colour target (no depth).
pub fn color_pass<'e>(
    ctx: &'e mut PassContext<'_>,
    label: &str,
    target: &wgpu::TextureView,
    load: wgpu::LoadOp<wgpu::Color>,
) -> GroupedRenderPass<'e> {
    ctx.open_render_pass(&wgpu::RenderPassDescriptor {
        label: Some(label),
        color_attachments: &[Some(wgpu::RenderPassColorAttachment {
            view: target,
            depth_slice: None,
            resolve_target: None,
            ops: wgpu::Operations { load, store: wgpu::StoreOp::Store },
        })],
        depth_stencil_attachment: None,
        timestamp_writes: None,
        occlusion_query_set: None,
        multiview_mask: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::view::jitter_projection;
    use glam::Vec3;

    #[test]
    fn halton_sequence_starts_as_published() {
        let base2: Vec<f32> = (1..=4).map(|i| halton(i, 2)).collect();
        assert_eq!(base2, vec![0.5, 0.25, 0.75, 0.125]);
        let base3: Vec<f32> = (1..=3).map(|i| halton(i, 3)).collect();
        assert!(
            (base3[0] - 1.0 / 3.0).abs() < 1e-6
                && (base3[1] - 2.0 / 3.0).abs() < 1e-6
                && (base3[2] - 1.0 / 9.0).abs() < 1e-6
        );
    }

    #[test]
    fn jitter_stays_within_half_a_pixel_and_moves_the_projection_by_it() {
        for frame in 0..16 {
            let j = taa_jitter(frame, 320, 180);
            assert!(j.x.abs() <= 1.0 / 320.0 && j.y.abs() <= 1.0 / 180.0, "{j}");
        }
        let proj = glam::camera::rh::proj::directx::perspective_infinite_reverse(1.0, 16.0 / 9.0, 0.1);
        let j = Vec2::new(0.01, -0.02);
        let p = Vec3::new(0.3, -0.2, -4.0);
        let a = proj.project_point3(p);
        let b = jitter_projection(proj, j).project_point3(p);
        assert!((b.x - a.x - j.x).abs() < 1e-5 && (b.y - a.y - j.y).abs() < 1e-5 && (b.z - a.z).abs() < 1e-6);
    }
}
