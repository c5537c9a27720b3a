//! The scene on the GPU, uploaded once per renderer: the meshes both frames draw, the
//! instances and materials in the layout of the frame that reads them, and the uniform
//! blocks (view, lights) computed from the scene for a frame.

use crate::gpu::BufferInit;
use glam::{Mat4, UVec4, Vec3, Vec4};

use super::{BlendMode, Material, Mesh, Mobility, Object, Pattern, PointLight, Scene, SpotLight};
use crate::gpu_types::{InstanceData, InstanceGpu, LightData, MaterialGpu, MaterialUniforms, MobileLocalLights};

/// A mesh's vertex and index buffers, as both frames draw it (a clone shares the buffers).
#[derive(Clone)]
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

/// An object of the mobile frames: its own instance vertex buffer.
pub struct GpuObject {
    pub name: String,
    pub mesh: usize,
    pub material: usize,
    pub instances: wgpu::Buffer,
    pub instance_count: u32,
    pub casts_shadow: bool,
}

/// A material of the mobile frames: its own uniform buffer.
pub struct GpuMaterial {
    pub material: Material,
    pub uniforms: wgpu::Buffer,
}

/// How the frame that reads the scene wants its instances and materials: the meshes are
/// the same for both.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SceneLayout {
    /// The mobile frames: an instance vertex buffer per object and a uniform buffer per
    /// material ([`GpuScene::objects`], [`GpuScene::materials`]).
    PerObject,
    /// The desktop frame: every instance a row of one storage buffer, every material a row
    /// of another, and a draw per object ([`GpuScene::rows`]).
    Rows,
}

/// One object's draw in the desktop layout: a mesh, a range of rows in the instance buffer.
#[derive(Clone, Debug)]
pub struct Draw {
    /// The scene object's name (a debug label).
    pub name: String,
    pub mesh: usize,
    pub first_instance: u32,
    pub instance_count: u32,
    pub blend: BlendMode,
    pub unlit: bool,
    pub movable: bool,
    pub casts_shadow: bool,
    /// World bounding sphere of all its instances.
    pub bounds: (Vec3, f32),
}

/// The scene's instances and materials as the desktop shaders read them.
pub struct SceneRows {
    /// `InstanceData` rows of `DesktopCommon.ush`, object after object.
    pub instances: wgpu::Buffer,
    /// `MaterialData` rows, in scene order.
    pub materials: wgpu::Buffer,
    /// One draw per scene object, in scene order.
    pub draws: Vec<Draw>,
}

/// The uploaded scene.
pub struct GpuScene {
    /// Every mesh of the scene, in scene order: both layouts draw these.
    pub meshes: Vec<GpuMesh>,
    /// [`SceneLayout::PerObject`]: one per scene object (empty in the other layout).
    pub objects: Vec<GpuObject>,
    /// [`SceneLayout::PerObject`]: one per scene material (empty in the other layout).
    pub materials: Vec<GpuMaterial>,
    /// [`SceneLayout::Rows`]: the instance and material rows (`None` in the other layout).
    pub rows: Option<SceneRows>,
}

impl GpuScene {
    /// Uploads `scene`'s meshes, and its instances and materials in `layout`.
    pub fn upload(device: &wgpu::Device, scene: &Scene, layout: SceneLayout) -> GpuScene {
        let meshes = scene.meshes.iter().map(|m| GpuMesh::upload(device, m)).collect();
        match layout {
            SceneLayout::PerObject => GpuScene {
                meshes,
                objects: scene.objects.iter().map(|o| upload_object(device, o)).collect(),
                materials: scene.materials.iter().map(|m| upload_material(device, m)).collect(),
                rows: None,
            },
            SceneLayout::Rows => {
                GpuScene { meshes, objects: Vec::new(), materials: Vec::new(), rows: Some(upload_rows(device, scene)) }
            }
        }
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

/// An object's instance vertex buffer (rewritable: the mobile effects move props).
fn upload_object(device: &wgpu::Device, o: &Object) -> GpuObject {
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
}

fn upload_material(device: &wgpu::Device, m: &Material) -> GpuMaterial {
    GpuMaterial {
        material: m.clone(),
        uniforms: device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(&format!("{} material uniforms", m.name)),
            contents: bytemuck::bytes_of(&material_uniforms(m)),
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        }),
    }
}

/// The desktop layout: every object's instances as rows (with their world bounds), and a
/// draw over each object's range.
fn upload_rows(device: &wgpu::Device, scene: &Scene) -> SceneRows {
    let mut instances = Vec::new();
    let mut draws = Vec::new();
    for o in &scene.objects {
        let first = instances.len() as u32;
        let bounds = push_instance_rows(scene, o, &mut instances);
        let material = &scene.materials[o.material];
        draws.push(Draw {
            name: o.name.clone(),
            mesh: o.mesh,
            first_instance: first,
            instance_count: o.instances.len() as u32,
            blend: material.blend,
            unlit: material.unlit,
            movable: o.mobility == Mobility::Movable,
            casts_shadow: o.casts_shadow && material.blend != BlendMode::Translucent,
            bounds,
        });
    }
    let materials: Vec<MaterialGpu> = scene.materials.iter().map(material_gpu).collect();
    let buffer = |label: &str, bytes: &[u8], usage: wgpu::BufferUsages| {
        device.create_buffer_init(&wgpu::util::BufferInitDescriptor { label: Some(label), contents: bytes, usage })
    };
    SceneRows {
        // movable props' rows are rewritten every frame (the effects move them)
        instances: buffer(
            "Instances",
            bytemuck::cast_slice(&instances),
            wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
        ),
        materials: buffer("Materials", bytemuck::cast_slice(&materials), wgpu::BufferUsages::STORAGE),
        draws,
    }
}

/// Appends `o`'s instance rows and returns the world bounding sphere of all of them.
fn push_instance_rows(scene: &Scene, o: &Object, rows: &mut Vec<InstanceGpu>) -> (Vec3, f32) {
    let (lo, hi) = scene.meshes[o.mesh].bounds();
    let local_center = (lo + hi) * 0.5;
    let local_radius = (hi - lo).length() * 0.5;
    let mut all_lo = Vec3::splat(f32::MAX);
    let mut all_hi = Vec3::splat(f32::MIN);
    for m in &o.instances {
        let center = m.transform_point3(local_center);
        let scale = m.to_scale_rotation_translation().0.max_element();
        let radius = local_radius * scale;
        all_lo = all_lo.min(center - Vec3::splat(radius));
        all_hi = all_hi.max(center + Vec3::splat(radius));
        rows.push(InstanceGpu {
            local_to_world: *m,
            normal_to_world: Mat4::from_mat3(glam::Mat3::from_mat4(*m).inverse().transpose()),
            material: UVec4::new(o.material as u32, u32::from(o.mobility == Mobility::Movable), 0, 0),
            bounds: center.extend(radius),
        });
    }
    ((all_lo + all_hi) * 0.5, (all_hi - all_lo).length() * 0.5)
}

/// `MaterialData` of a scene material: patterns map onto `MaterialTemplate.ush`'s.
pub fn material_gpu(m: &Material) -> MaterialGpu {
    let (pattern, scale, contrast) = match m.pattern {
        Pattern::None => (0.0, 1.0, 0.0),
        // The scene's patterns, as `MaterialCommon.ush` defines them: a checker tinting the
        // base color, vertical slats masking (the counts are per uv unit).
        Pattern::Checker => (7.0, 8.0, 1.0),
        Pattern::Slats => (6.0, 6.0, 0.0),
    };
    let opacity = if m.blend == BlendMode::Translucent { m.opacity } else { 1.0 };
    MaterialGpu {
        base_color: m.base_color.extend(opacity),
        params: Vec4::new(m.metallic, m.specular, m.roughness, 1.0),
        emissive: m.emissive.extend(pattern),
        pattern: Vec4::new(scale, contrast, 0.0, 0.0),
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn instance_rows_carry_material_mobility_and_the_bounds_of_every_instance() {
        let mut scene = Scene::bundled();
        let mut cube = Mesh::new("Cube");
        cube.add_box(Vec3::splat(-1.0), Vec3::splat(1.0), 1.0);
        scene.meshes.push(cube);
        let object = Object {
            name: "Cubes".into(),
            mesh: scene.meshes.len() - 1,
            material: 2,
            instances: vec![
                Mat4::from_translation(Vec3::new(-4.0, 0.0, 0.0)),
                Mat4::from_scale_rotation_translation(Vec3::splat(2.0), glam::Quat::IDENTITY, Vec3::new(4.0, 0.0, 0.0)),
            ],
            mobility: Mobility::Movable,
            casts_shadow: true,
        };
        let mut rows = vec![InstanceGpu::default()];
        let (center, radius) = push_instance_rows(&scene, &object, &mut rows);
        assert_eq!(rows.len(), 3, "appended after the row already there");
        let half_diagonal = Vec3::splat(1.0).length();
        assert_eq!(rows[1].bounds, Vec4::new(-4.0, 0.0, 0.0, half_diagonal));
        assert_eq!(rows[2].bounds, Vec4::new(4.0, 0.0, 0.0, 2.0 * half_diagonal));
        for row in &rows[1..] {
            assert_eq!(row.material, UVec4::new(2, 1, 0, 0));
        }
        // A uniform scale of 2 scales normals by 1/2 (before they are normalized).
        assert!(rows[2].normal_to_world.abs_diff_eq(Mat4::from_scale(Vec3::splat(0.5)), 1e-6));
        // The sphere around both: from the left one's left edge to the right one's right edge.
        let (lo, hi) = (-4.0 - half_diagonal, 4.0 + 2.0 * half_diagonal);
        assert!((center.x - (lo + hi) * 0.5).abs() < 1e-5, "{center}");
        assert!(radius >= (hi - lo) * 0.5, "{radius}");
    }

    #[test]
    fn desktop_materials_map_patterns_and_keep_opacity_for_translucent_ones_only() {
        let scene = Scene::bundled();
        let find = |name: &str| &scene.materials[scene.material_index(name).unwrap()];
        let floor = material_gpu(find("Floor"));
        assert_eq!((floor.emissive.w, floor.pattern.x, floor.pattern.y), (7.0, 8.0, 1.0));
        assert_eq!(floor.base_color.w, 1.0);
        let glass = find("Glass");
        assert_eq!(material_gpu(glass).base_color.w, glass.opacity);
        assert_eq!(material_gpu(find("ChairWood")).emissive.w, 6.0);
    }
}
