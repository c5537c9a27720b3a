//! Procedural meshes: boxes, spheres (with optional noise for the rock) and compositions of
//! them, as indexed triangle lists with per-face normals and uvs.

use glam::{Mat4, Vec2, Vec3};

use crate::gpu_types::MeshVertex;

/// An indexed triangle list (counter-clockwise front faces).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    pub name: String,
    pub vertices: Vec<MeshVertex>,
    pub indices: Vec<u32>,
}

impl Mesh {
    pub fn new(name: &str) -> Mesh {
        Mesh { name: name.to_string(), ..Default::default() }
    }

    pub fn triangle_count(&self) -> usize {
        self.indices.len() / 3
    }

    /// The axis-aligned bounds of the vertices (min, max).
    pub fn bounds(&self) -> (Vec3, Vec3) {
        let mut lo = Vec3::splat(f32::MAX);
        let mut hi = Vec3::splat(f32::MIN);
        for v in &self.vertices {
            lo = lo.min(Vec3::from(v.position));
            hi = hi.max(Vec3::from(v.position));
        }
        (lo, hi)
    }

    fn push(&mut self, p: Vec3, n: Vec3, uv: Vec2) -> u32 {
        self.vertices.push(MeshVertex { position: p.into(), normal: n.into(), uv: uv.into() });
        (self.vertices.len() - 1) as u32
    }

    /// A quad from `origin` spanning `u` and `v`; the normal is `u x v`.
    pub fn add_quad(&mut self, origin: Vec3, u: Vec3, v: Vec3, uv_scale: Vec2) -> &mut Mesh {
        let n = u.cross(v).normalize();
        let a = self.push(origin, n, Vec2::ZERO);
        let b = self.push(origin + u, n, Vec2::new(uv_scale.x, 0.0));
        let c = self.push(origin + u + v, n, uv_scale);
        let d = self.push(origin + v, n, Vec2::new(0.0, uv_scale.y));
        self.indices.extend_from_slice(&[a, b, c, a, c, d]);
        self
    }

    /// An axis-aligned box from `min` to `max`, faces pointing out. Uvs span each face
    /// once, scaled by `uv_density` per unit of length.
    pub fn add_box(&mut self, min: Vec3, max: Vec3, uv_density: f32) -> &mut Mesh {
        let s = max - min;
        let d = uv_density;
        let (x, y, z) = (Vec3::X * s.x, Vec3::Y * s.y, Vec3::Z * s.z);
        // +x, -x, +y, -y, +z, -z
        self.add_quad(Vec3::new(max.x, min.y, max.z), -z, y, Vec2::new(s.z, s.y) * d);
        self.add_quad(Vec3::new(min.x, min.y, min.z), z, y, Vec2::new(s.z, s.y) * d);
        self.add_quad(Vec3::new(min.x, max.y, max.z), x, -z, Vec2::new(s.x, s.z) * d);
        self.add_quad(Vec3::new(min.x, min.y, min.z), x, z, Vec2::new(s.x, s.z) * d);
        self.add_quad(Vec3::new(min.x, min.y, max.z), x, y, Vec2::new(s.x, s.y) * d);
        self.add_quad(Vec3::new(max.x, min.y, min.z), -x, y, Vec2::new(s.x, s.y) * d);
        self
    }

    /// A UV sphere; `noise` displaces the radius by up to that fraction (a rock), with
    /// normals recomputed from the displaced surface.
    pub fn add_sphere(
        &mut self,
        center: Vec3,
        radius: f32,
        rings: u32,
        segments: u32,
        noise: f32,
        seed: u32,
    ) -> &mut Mesh {
        let base = self.vertices.len() as u32;
        let mut positions = Vec::new();
        for r in 0..=rings {
            let theta = std::f32::consts::PI * r as f32 / rings as f32;
            for s in 0..=segments {
                let phi = std::f32::consts::TAU * (s % segments) as f32 / segments as f32;
                let dir = Vec3::new(theta.sin() * phi.cos(), theta.cos(), theta.sin() * phi.sin());
                let k = 1.0 + noise * fbm(dir * 2.5, seed);
                positions.push(center + dir * radius * k);
            }
        }
        let stride = segments + 1;
        let mut normals = vec![Vec3::ZERO; positions.len()];
        let mut tris = Vec::new();
        for r in 0..rings {
            for s in 0..segments {
                let a = r * stride + s;
                let b = a + stride;
                let quad = [(a, a + 1, b + 1), (a, b + 1, b)];
                for (i, j, k) in quad {
                    let (pi, pj, pk) = (positions[i as usize], positions[j as usize], positions[k as usize]);
                    let n = (pj - pi).cross(pk - pi);
                    if n.length_squared() < 1e-12 {
                        continue;
                    }
                    for v in [i, j, k] {
                        normals[v as usize] += n;
                    }
                    tris.push([i, j, k]);
                }
            }
        }
        // Seam and pole vertices share a position: average their normals.
        for r in 0..=rings {
            let (first, last) = ((r * stride) as usize, (r * stride + segments) as usize);
            let n = normals[first] + normals[last];
            normals[first] = n;
            normals[last] = n;
        }
        for r in [0, rings] {
            let row = (r * stride) as usize..(r * stride + stride) as usize;
            let n: Vec3 = normals[row.clone()].iter().copied().sum();
            for i in row {
                normals[i] = n;
            }
        }
        for (i, p) in positions.iter().enumerate() {
            let uv = Vec2::new((i as u32 % stride) as f32 / segments as f32, (i as u32 / stride) as f32 / rings as f32);
            let n = normals[i].normalize_or(Vec3::Y);
            self.push(*p, n, uv);
        }
        for t in tris {
            self.indices.extend(t.iter().map(|i| base + i));
        }
        self
    }

    /// Appends `other` transformed by `m` (uniform scale assumed for normals).
    pub fn append(&mut self, other: &Mesh, m: Mat4) -> &mut Mesh {
        let base = self.vertices.len() as u32;
        for v in &other.vertices {
            let p = m.transform_point3(Vec3::from(v.position));
            let n = m.transform_vector3(Vec3::from(v.normal)).normalize_or(Vec3::Y);
            self.push(p, n, Vec2::from(v.uv));
        }
        self.indices.extend(other.indices.iter().map(|i| base + i));
        self
    }
}

fn hash(x: i32, y: i32, z: i32, seed: u32) -> f32 {
    let mut h = (x as u32).wrapping_mul(0x8da6_b343)
        ^ (y as u32).wrapping_mul(0xd816_3841)
        ^ (z as u32).wrapping_mul(0xcb1a_b31f)
        ^ seed.wrapping_mul(0x9e37_79b9);
    h ^= h >> 13;
    h = h.wrapping_mul(0x5bd1_e995);
    h ^= h >> 15;
    (h & 0xffff) as f32 / 65535.0 * 2.0 - 1.0
}

/// Trilinear value noise in [-1, 1].
fn value_noise(p: Vec3, seed: u32) -> f32 {
    let i = p.floor();
    let f = p - i;
    let u = f * f * (Vec3::splat(3.0) - 2.0 * f);
    let (x, y, z) = (i.x as i32, i.y as i32, i.z as i32);
    let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
    let c = |dx, dy, dz| hash(x + dx, y + dy, z + dz, seed);
    lerp(
        lerp(lerp(c(0, 0, 0), c(1, 0, 0), u.x), lerp(c(0, 1, 0), c(1, 1, 0), u.x), u.y),
        lerp(lerp(c(0, 0, 1), c(1, 0, 1), u.x), lerp(c(0, 1, 1), c(1, 1, 1), u.x), u.y),
        u.z,
    )
}

/// Three octaves of value noise, roughly in [-1, 1].
pub fn fbm(p: Vec3, seed: u32) -> f32 {
    value_noise(p, seed) * 0.6 + value_noise(p * 2.0, seed + 1) * 0.3 + value_noise(p * 4.0, seed + 2) * 0.1
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_has_outward_normals_and_twelve_triangles() {
        let mut m = Mesh::new("box");
        m.add_box(Vec3::splat(-1.0), Vec3::splat(1.0), 1.0);
        assert_eq!(m.triangle_count(), 12);
        for t in m.indices.chunks(3) {
            let [a, b, c] = [t[0], t[1], t[2]].map(|i| Vec3::from(m.vertices[i as usize].position));
            let face_normal = (b - a).cross(c - a).normalize();
            let centroid = (a + b + c) / 3.0;
            assert!(face_normal.dot(centroid) > 0.0, "triangle {t:?} faces inward");
            assert!((face_normal - Vec3::from(m.vertices[t[0] as usize].normal)).length() < 1e-5);
        }
    }

    #[test]
    fn sphere_winding_is_counter_clockwise_from_outside() {
        let mut m = Mesh::new("sphere");
        m.add_sphere(Vec3::ZERO, 1.0, 8, 12, 0.0, 0);
        assert!(m.triangle_count() > 100);
        for t in m.indices.chunks(3) {
            let [a, b, c] = [t[0], t[1], t[2]].map(|i| Vec3::from(m.vertices[i as usize].position));
            let n = (b - a).cross(c - a);
            assert!(n.dot((a + b + c) / 3.0) > 0.0);
        }
    }

    #[test]
    fn noisy_sphere_is_deterministic_and_not_round() {
        let mut a = Mesh::new("rock");
        a.add_sphere(Vec3::ZERO, 1.0, 12, 16, 0.3, 7);
        let mut b = Mesh::new("rock");
        b.add_sphere(Vec3::ZERO, 1.0, 12, 16, 0.3, 7);
        assert_eq!(a, b);
        let radii: Vec<f32> = a.vertices.iter().map(|v| Vec3::from(v.position).length()).collect();
        let (lo, hi) = radii.iter().fold((f32::MAX, f32::MIN), |(lo, hi), r| (lo.min(*r), hi.max(*r)));
        assert!(hi - lo > 0.1, "radius spread {lo}..{hi}");
    }
}
