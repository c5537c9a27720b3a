//! `#[repr(C)]` Pod types shared with the shaders, and the texture formats of the frame.
//! Each uniform struct mirrors a WGSL struct of `shader_src/` member for member (vec4 and
//! mat4 members only, so no padding rules apply).

use crate::gpu::BufferInit;
use bytemuck::{Pod, Zeroable};
use glam::{Mat4, UVec4, Vec4};

/// A uniform buffer holding `value`, writable with `queue.write_buffer` (and the target of
/// GPU copies, like the eye adaptation's exposure).
pub fn uniform_buffer<T: Pod>(device: &wgpu::Device, label: &str, value: &T) -> wgpu::Buffer {
    device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some(label),
        contents: bytemuck::bytes_of(value),
        usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
    })
}

/// Formats of the frame's render targets, by their Unreal names.
pub mod formats {
    use wgpu::TextureFormat;
    /// Reverse-Z scene depth (copyable, so passes can dump it).
    pub const SCENE_DEPTH: TextureFormat = TextureFormat::Depth32Float;
    pub const SHADOW_DEPTH: TextureFormat = TextureFormat::Depth32Float;
    /// HDR scene color: emissive, indirect and lights accumulate here.
    pub const SCENE_COLOR: TextureFormat = TextureFormat::Rgba16Float;
    /// World normal (desktop) or octahedral normal + precomputed shadow (mobile).
    pub const GBUFFER_A: TextureFormat = TextureFormat::Rgb10a2Unorm;
    /// Metallic, specular, roughness, shading model.
    pub const GBUFFER_B: TextureFormat = TextureFormat::Rgba8Unorm;
    /// Base color (sRGB encoded) and ambient occlusion.
    pub const GBUFFER_C: TextureFormat = TextureFormat::Rgba8UnormSrgb;
    /// The tonemapped output.
    pub const OUTPUT: TextureFormat = TextureFormat::Rgba8UnormSrgb;
}

/// The frames' vertex layouts, described to the runtime's pipeline cache.
pub mod layouts {
    use kiln_runtime::pipelines::{VertexBuffer, VertexLayout};

    use super::{InstanceData, MeshVertex};

    const MESH_ATTRIBUTES: [wgpu::VertexAttribute; 3] =
        wgpu::vertex_attr_array![0 => Float32x3, 1 => Float32x3, 2 => Float32x2];
    const INSTANCE_ATTRIBUTES: [wgpu::VertexAttribute; 4] =
        wgpu::vertex_attr_array![3 => Float32x4, 4 => Float32x4, 5 => Float32x4, 6 => Float32x4];
    const POSITION_ATTRIBUTES: [wgpu::VertexAttribute; 1] = wgpu::vertex_attr_array![0 => Float32x3];
    const MESH_BUFFER: VertexBuffer =
        VertexBuffer::new(std::mem::size_of::<MeshVertex>() as u64, wgpu::VertexStepMode::Vertex, &MESH_ATTRIBUTES);

    const MESH_INSTANCED_BUFFERS: &[VertexBuffer] = &[
        MESH_BUFFER,
        VertexBuffer::new(
            std::mem::size_of::<InstanceData>() as u64,
            wgpu::VertexStepMode::Instance,
            &INSTANCE_ATTRIBUTES,
        ),
    ];
    const MESH_BUFFERS: &[VertexBuffer] = &[MESH_BUFFER];
    const POSITION_BUFFERS: &[VertexBuffer] =
        &[VertexBuffer::new(12, wgpu::VertexStepMode::Vertex, &POSITION_ATTRIBUTES)];

    /// [`MeshVertex`] in buffer 0 (locations 0 to 2) and [`InstanceData`] (one local-to-world
    /// matrix per instance, locations 3 to 6) in buffer 1.
    pub const MESH_INSTANCED: VertexLayout = VertexLayout::from_static(MESH_INSTANCED_BUFFERS);

    /// [`MeshVertex`] in buffer 0 only (instances come from a storage buffer indexed by
    /// `instance_index`).
    pub const MESH: VertexLayout = VertexLayout::from_static(MESH_BUFFERS);

    /// A `vec3<f32>` position in buffer 0 (location 0): light volumes.
    pub const POSITION: VertexLayout = VertexLayout::from_static(POSITION_BUFFERS);
}

/// One mesh vertex (vertex buffer 0; locations 0 to 2).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct MeshVertex {
    pub position: [f32; 3],
    pub normal: [f32; 3],
    pub uv: [f32; 2],
}

/// One instance (vertex buffer 1; locations 3 to 6): the local-to-world matrix by columns.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct InstanceData {
    pub local_to_world: [[f32; 4]; 4],
}

impl InstanceData {
    pub fn new(m: Mat4) -> InstanceData {
        InstanceData { local_to_world: m.to_cols_array_2d() }
    }
}

/// `InstanceData` of `DesktopCommon.ush`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct InstanceGpu {
    pub local_to_world: Mat4,
    pub normal_to_world: Mat4,
    pub material: UVec4,
    pub bounds: Vec4,
}

/// `MaterialData` of `DesktopCommon.ush`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct MaterialGpu {
    pub base_color: Vec4,
    pub params: Vec4,
    pub emissive: Vec4,
    pub pattern: Vec4,
}

/// `FMaterialUniforms` of `MaterialCommon.ush`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct MaterialUniforms {
    pub base_color: Vec4,
    pub emissive: Vec4,
    pub params: Vec4,
    pub flags: UVec4,
}

/// `FLightData` of `DeferredLightingCommon.ush`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct LightData {
    pub position_and_inv_radius: Vec4,
    pub color_and_falloff: Vec4,
    pub direction: Vec4,
    pub spot_angles: Vec4,
}

/// `FMobileLocalLights` of `MobileBasePassPixelShader.usf`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct MobileLocalLights {
    pub lights: [LightData; 4],
    pub count: UVec4,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_match_the_wgsl_structs() {
        assert_eq!(std::mem::size_of::<MeshVertex>(), 32);
        assert_eq!(std::mem::size_of::<InstanceData>(), 64);
        assert_eq!(std::mem::size_of::<MaterialUniforms>(), 64);
        assert_eq!(std::mem::size_of::<LightData>(), 64);
        assert_eq!(std::mem::size_of::<MobileLocalLights>(), 4 * 64 + 16);
    }
}
