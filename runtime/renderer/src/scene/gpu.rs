//! The scene on the GPU: vertex, index and instance buffers, material uniform buffers, and
//! the uniform blocks (view, lights) computed from the scene for a frame.

use crate::gpu::BufferInit;
use glam::{UVec4, Vec4};

use super::{Material, Mesh, PointLight, Scene, SpotLight};
use crate::gpu_types::{InstanceData, LightData, MaterialUniforms, MobileLocalLights};

/// A mesh's vertex and index buffers, as both frames draw it.
pub struct GpuMesh {
    pub vertices: wgpu::Buffer,
    pub indices: wgpu::Buffer,
    pub index_count: u32,
}

impl GpuMesh {
    /// Uploads `mesh`'s vertices and indices, labelled with its name.
    pub fn upload(device: &wgpu::Device, mesh: &Mesh) -> GpuMesh {
        GpuMesh {
            vertices: device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(&format!("{} vertices", mesh.name)),
                contents: bytemuck::cast_slice(&mesh.vertices),
                usage: wgpu::BufferUsages::VERTEX,
            }),
            indices: device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(&format!("{} indices", mesh.name)),
                contents: bytemuck::cast_slice(&mesh.indices),
                usage: wgpu::BufferUsages::INDEX,
            }),
            index_count: mesh.indices.len() as u32,
        }
    }
}

pub struct GpuObject {
    pub name: String,
    pub mesh: usize,
    pub material: usize,
    pub instances: wgpu::Buffer,
    pub instance_count: u32,
    pub casts_shadow: bool,
}

pub struct GpuMaterial {
    pub material: Material,
    pub uniforms: wgpu::Buffer,
}

/// The uploaded scene.
pub struct GpuScene {
    pub meshes: Vec<GpuMesh>,
    pub objects: Vec<GpuObject>,
    pub materials: Vec<GpuMaterial>,
}

impl GpuScene {
    pub fn upload(device: &wgpu::Device, scene: &Scene) -> GpuScene {
        let meshes = scene.meshes.iter().map(|m| GpuMesh::upload(device, m)).collect();
        let objects = scene
            .objects
            .iter()
            .map(|o| {
                let instances: Vec<InstanceData> = o.instances.iter().map(|m| InstanceData::new(*m)).collect();
                GpuObject {
                    name: o.name.clone(),
                    mesh: o.mesh,
                    material: o.material,
                    instances: device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                        label: Some(&format!("{} instances", o.name)),
                        contents: bytemuck::cast_slice(&instances),
                        usage: wgpu::BufferUsages::VERTEX | wgpu::BufferUsages::COPY_DST,
                    }),
                    instance_count: instances.len() as u32,
                    casts_shadow: o.casts_shadow,
                }
            })
            .collect();
        let materials = scene
            .materials
            .iter()
            .map(|m| GpuMaterial {
                material: m.clone(),
                uniforms: device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(&format!("{} material uniforms", m.name)),
                    contents: bytemuck::bytes_of(&material_uniforms(m)),
                    usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                }),
            })
            .collect();
        GpuScene { meshes, objects, materials }
    }

    /// Binds an object's buffers and draws all its instances with one call.
    pub fn draw(&self, pass: &mut wgpu::RenderPass<'_>, object: &GpuObject) {
        let mesh = &self.meshes[object.mesh];
        pass.set_vertex_buffer(0, mesh.vertices.slice(..));
        pass.set_vertex_buffer(1, object.instances.slice(..));
        pass.set_index_buffer(mesh.indices.slice(..), wgpu::IndexFormat::Uint32);
        pass.draw_indexed(0..mesh.index_count, 0, 0..object.instance_count);
    }

    pub fn material(&self, object: &GpuObject) -> &Material {
        &self.materials[object.material].material
    }
}

pub fn material_uniforms(m: &Material) -> MaterialUniforms {
    MaterialUniforms {
        base_color: m.base_color.extend(m.opacity),
        emissive: m.emissive.extend(0.0),
        params: Vec4::new(m.metallic, m.roughness, m.specular, m.opacity_mask_clip),
        flags: UVec4::new(m.pattern as u32, if m.unlit { 0 } else { 1 }, 0, 0),
    }
}

/// Size of the directional light's shadow map (square).
pub const SHADOW_MAP_SIZE: u32 = 2048;

pub fn point_light_data(l: &PointLight) -> LightData {
    LightData {
        position_and_inv_radius: l.position.extend(1.0 / l.radius),
        color_and_falloff: (l.color * l.intensity).extend(8.0),
        direction: Vec4::ZERO,
        spot_angles: Vec4::ZERO,
    }
}

pub fn spot_light_data(l: &SpotLight) -> LightData {
    let cos_outer = l.outer_angle.cos();
    let cos_inner = l.inner_angle.cos();
    LightData {
        position_and_inv_radius: l.position.extend(1.0 / l.radius),
        color_and_falloff: (l.color * l.intensity).extend(8.0),
        direction: l.direction.extend(1.0),
        spot_angles: Vec4::new(cos_outer, 1.0 / (cos_inner - cos_outer).max(1e-4), 0.0, 0.0),
    }
}

pub fn directional_light_data(scene: &Scene) -> LightData {
    let sun = &scene.sun;
    let on = if sun.enabled { 1.0 } else { 0.0 };
    LightData {
        position_and_inv_radius: Vec4::ZERO,
        color_and_falloff: (sun.color * sun.intensity * on).extend(0.0),
        direction: sun.direction.extend(0.0),
        spot_angles: Vec4::ZERO,
    }
}

/// The local lights of the mobile forward base pass: up to 4, nearest the camera first.
pub fn mobile_local_lights(scene: &Scene) -> MobileLocalLights {
    let mut lights: Vec<(f32, LightData)> = scene
        .point_lights
        .iter()
        .map(|l| (l.position.distance(scene.camera.position), point_light_data(l)))
        .chain(scene.spot_lights.iter().map(|l| (l.position.distance(scene.camera.position), spot_light_data(l))))
        .collect();
    lights.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut out = MobileLocalLights::default();
    for (i, (_, l)) in lights.iter().take(4).enumerate() {
        out.lights[i] = *l;
    }
    out.count = UVec4::new(lights.len().min(4) as u32, 0, 0, 0);
    out
}
