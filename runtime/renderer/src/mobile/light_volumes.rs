//! The stencil geometry of local lights (`StencilingGeometry::DrawSphere` / `DrawCone`): a
//! unit sphere and a unit cone (apex at the origin, axis +Z, base at z = 1 with radius 1),
//! both slightly enlarged so that their faces enclose the true volume.

use crate::gpu::BufferInit;
use glam::{Mat4, Quat, Vec3};

use super::uniforms::LocalLight;

const SEGMENTS: u32 = 16;
const RINGS: u32 = 12;

/// Positions and indices (counter-clockwise seen from outside).
pub fn unit_sphere() -> (Vec<[f32; 3]>, Vec<u32>) {
    let mut positions = Vec::new();
    for r in 0..=RINGS {
        let theta = std::f32::consts::PI * r as f32 / RINGS as f32;
        for s in 0..=SEGMENTS {
            let phi = 2.0 * std::f32::consts::PI * s as f32 / SEGMENTS as f32;
            positions.push([theta.sin() * phi.cos(), theta.cos(), theta.sin() * phi.sin()]);
        }
    }
    let mut indices = Vec::new();
    let row = SEGMENTS + 1;
    for r in 0..RINGS {
        for s in 0..SEGMENTS {
            let (a, b, c, d) = (r * row + s, r * row + s + 1, (r + 1) * row + s, (r + 1) * row + s + 1);
            indices.extend_from_slice(&[a, b, c, b, d, c]);
        }
    }
    (positions, indices)
}

pub fn unit_cone() -> (Vec<[f32; 3]>, Vec<u32>) {
    let mut positions = vec![[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
    for s in 0..SEGMENTS {
        let phi = 2.0 * std::f32::consts::PI * s as f32 / SEGMENTS as f32;
        positions.push([phi.cos(), phi.sin(), 1.0]);
    }
    let mut indices = Vec::new();
    for s in 0..SEGMENTS {
        let (a, b) = (2 + s, 2 + (s + 1) % SEGMENTS);
        // Side (apex, b, a) and base cap (center, a, b), outward facing.
        indices.extend_from_slice(&[0, b, a, 1, a, b]);
    }
    (positions, indices)
}

/// How much a polygonal volume is scaled to enclose the round one.
fn enclose() -> f32 {
    1.0 / ((std::f32::consts::PI / SEGMENTS as f32).cos() * (std::f32::consts::PI / (2 * RINGS) as f32).cos())
}

/// The light's bounding volume: unit sphere or unit cone to world.
pub fn volume_to_world(light: &LocalLight) -> Mat4 {
    if light.is_spot {
        let r = light.radius;
        let spread = r * light.outer_angle.min(1.45).tan() * enclose();
        let rotation = Quat::from_rotation_arc(Vec3::Z, light.direction.normalize());
        Mat4::from_scale_rotation_translation(Vec3::new(spread, spread, r), rotation, light.position)
    } else {
        Mat4::from_scale_rotation_translation(Vec3::splat(light.radius * enclose()), Quat::IDENTITY, light.position)
    }
}

/// A volume mesh on the GPU.
pub struct VolumeMesh {
    pub vertices: wgpu::Buffer,
    pub indices: wgpu::Buffer,
    pub index_count: u32,
}

impl VolumeMesh {
    pub fn new(device: &wgpu::Device, name: &str, (positions, indices): (Vec<[f32; 3]>, Vec<u32>)) -> VolumeMesh {
        VolumeMesh {
            vertices: device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(name),
                contents: bytemuck::cast_slice(&positions),
                usage: wgpu::BufferUsages::VERTEX,
            }),
            indices: device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(name),
                contents: bytemuck::cast_slice(&indices),
                usage: wgpu::BufferUsages::INDEX,
            }),
            index_count: indices.len() as u32,
        }
    }

    pub fn draw(&self, pass: &mut wgpu::RenderPass<'_>) {
        pass.set_vertex_buffer(0, self.vertices.slice(..));
        pass.set_index_buffer(self.indices.slice(..), wgpu::IndexFormat::Uint32);
        pass.draw_indexed(0..self.index_count, 0, 0..1);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn outward(positions: &[[f32; 3]], indices: &[u32], inside: Vec3) -> bool {
        indices.chunks(3).all(|t| {
            let [a, b, c] = [t[0], t[1], t[2]].map(|i| Vec3::from(positions[i as usize]));
            let n = (b - a).cross(c - a);
            // Degenerate pole triangles have no normal.
            n.length() < 1e-6 || n.dot(a - inside) > 0.0
        })
    }

    #[test]
    fn volumes_face_outwards() {
        let (p, i) = unit_sphere();
        assert!(outward(&p, &i, Vec3::ZERO));
        let (p, i) = unit_cone();
        assert!(outward(&p, &i, Vec3::new(0.0, 0.0, 0.6)));
    }

    #[test]
    fn a_spot_volume_points_along_the_light() {
        let light = LocalLight {
            name: "s".into(),
            data: Default::default(),
            is_spot: true,
            position: Vec3::new(1.0, 3.0, 0.0),
            radius: 5.0,
            direction: Vec3::NEG_Y,
            outer_angle: 0.5,
        };
        let m = volume_to_world(&light);
        let tip = m.transform_point3(Vec3::ZERO);
        let base = m.transform_point3(Vec3::new(0.0, 0.0, 1.0));
        assert!(tip.distance(light.position) < 1e-5);
        assert!(base.distance(Vec3::new(1.0, -2.0, 0.0)) < 1e-4, "{base}");
    }
}
