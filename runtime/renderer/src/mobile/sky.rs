//! The procedural sky and the reflection captures made from it.
//!
//! [`procedural_sky`] is the same function as `procedural_sky` in `MobileCommon.ush` (the sky
//! the base pass draws behind everything). Captures are cubemaps of that sky, computed on
//! the CPU once, with box-filtered mips that the shaders pick by roughness
//! (`ComputeReflectionCaptureMipFromRoughness`). Each capture is tinted towards the local
//! light nearest to it, so neighbouring captures differ the way real captures of a lit
//! room do; the base pass uses the nearest capture, or blends up to three (`HQ_REFLECTIONS`).

use glam::{Vec3, Vec4};

use crate::scene::Scene;

pub const CAPTURE_SIZE: u32 = 64;
pub const CAPTURE_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba16Float;

/// `procedural_sky` of `MobileCommon.ush`.
pub fn procedural_sky(dir: Vec3, sun_dir: Vec3, sun_color: Vec3) -> Vec3 {
    let zenith = Vec3::new(0.18, 0.36, 0.85);
    let horizon = Vec3::new(0.75, 0.82, 0.95);
    let ground = Vec3::new(0.22, 0.2, 0.18);
    let y = dir.y;
    let mut c = if y >= 0.0 {
        horizon.lerp(zenith, y.clamp(0.0, 1.0).powf(0.5))
    } else {
        horizon.lerp(ground, (-y * 4.0).clamp(0.0, 1.0))
    };
    let sun = dir.dot(sun_dir).max(0.0);
    c += sun_color * (sun.powf(800.0) * 8.0 + sun.powf(12.0) * 0.15);
    c
}

/// The direction through texel (`x`, `y`) of cube face `face` (+X, -X, +Y, -Y, +Z, -Z).
pub fn cube_direction(face: u32, x: u32, y: u32, size: u32) -> Vec3 {
    let u = 2.0 * (x as f32 + 0.5) / size as f32 - 1.0;
    let v = 2.0 * (y as f32 + 0.5) / size as f32 - 1.0;
    let d = match face {
        0 => Vec3::new(1.0, -v, -u),
        1 => Vec3::new(-1.0, -v, u),
        2 => Vec3::new(u, 1.0, v),
        3 => Vec3::new(u, -1.0, -v),
        4 => Vec3::new(u, -v, 1.0),
        _ => Vec3::new(-u, -v, -1.0),
    };
    d.normalize()
}

/// IEEE single to half precision (round to nearest even, no NaN payloads needed here).
pub fn f32_to_f16(value: f32) -> u16 {
    let bits = value.to_bits();
    let sign = ((bits >> 16) & 0x8000) as u16;
    let exp = ((bits >> 23) & 0xff) as i32;
    let mant = bits & 0x7f_ffff;
    if exp == 0xff {
        return sign | 0x7c00 | if mant != 0 { 0x200 } else { 0 };
    }
    let e = exp - 127 + 15;
    if e >= 0x1f {
        return sign | 0x7c00;
    }
    if e <= 0 {
        if e < -10 {
            return sign;
        }
        let m = (mant | 0x80_0000) >> (1 - e);
        let round = (m >> 13) + u32::from((m & 0x1fff) > 0x1000 || ((m & 0x1fff) == 0x1000 && (m >> 13) & 1 == 1));
        return sign | round as u16;
    }
    let half = ((e as u32) << 10) | (mant >> 13);
    let rest = mant & 0x1fff;
    let round = u32::from(rest > 0x1000 || (rest == 0x1000 && half & 1 == 1));
    sign | (half + round) as u16
}

/// The reflection captures of a frame.
pub struct Captures {
    /// xyz position, w influence radius.
    pub positions: Vec<Vec4>,
    pub textures: Vec<wgpu::Texture>,
    pub views: Vec<wgpu::TextureView>,
    pub sampler: wgpu::Sampler,
    mips: u32,
}

impl Captures {
    pub fn max_mip(&self) -> u32 {
        self.mips - 1
    }

    /// Three captures spread over the room, of the procedural sky.
    pub fn new(device: &wgpu::Device, queue: &wgpu::Queue, scene: &Scene) -> Captures {
        let sun_dir = -scene.sun.direction.normalize();
        let sun_color = if scene.sun.enabled { scene.sun.color * scene.sun.intensity } else { Vec3::ZERO };
        let positions =
            [Vec4::new(-4.0, 2.0, -3.0, 10.0), Vec4::new(0.0, 2.0, 2.0, 10.0), Vec4::new(5.0, 2.0, -2.0, 10.0)];
        let mips = CAPTURE_SIZE.ilog2() + 1;
        let mut textures = Vec::new();
        let mut views = Vec::new();
        for (i, p) in positions.iter().enumerate() {
            let tint = capture_tint(scene, p.truncate());
            let texture = device.create_texture(&wgpu::TextureDescriptor {
                label: Some(&format!("ReflectionCapture{i}")),
                size: wgpu::Extent3d { width: CAPTURE_SIZE, height: CAPTURE_SIZE, depth_or_array_layers: 6 },
                mip_level_count: mips,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format: CAPTURE_FORMAT,
                usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
                view_formats: &[],
            });
            for face in 0..6 {
                let mut level: Vec<Vec3> = (0..CAPTURE_SIZE * CAPTURE_SIZE)
                    .map(|t| {
                        procedural_sky(
                            cube_direction(face, t % CAPTURE_SIZE, t / CAPTURE_SIZE, CAPTURE_SIZE),
                            sun_dir,
                            sun_color,
                        ) * tint
                    })
                    .collect();
                let mut size = CAPTURE_SIZE;
                for mip in 0..mips {
                    let bytes: Vec<u8> = level
                        .iter()
                        .flat_map(|c| [c.x, c.y, c.z, 1.0])
                        .flat_map(|v| f32_to_f16(v).to_le_bytes())
                        .collect();
                    queue.write_texture(
                        wgpu::TexelCopyTextureInfo {
                            texture: &texture,
                            mip_level: mip,
                            origin: wgpu::Origin3d { x: 0, y: 0, z: face },
                            aspect: wgpu::TextureAspect::All,
                        },
                        &bytes,
                        wgpu::TexelCopyBufferLayout {
                            offset: 0,
                            bytes_per_row: Some(size * 8),
                            rows_per_image: Some(size),
                        },
                        wgpu::Extent3d { width: size, height: size, depth_or_array_layers: 1 },
                    );
                    if size > 1 {
                        level = downsample(&level, size);
                        size /= 2;
                    }
                }
            }
            views.push(texture.create_view(&wgpu::TextureViewDescriptor {
                label: Some(&format!("ReflectionCapture{i}")),
                dimension: Some(wgpu::TextureViewDimension::Cube),
                ..Default::default()
            }));
            textures.push(texture);
        }
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("ReflectionSampler"),
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            mipmap_filter: wgpu::MipmapFilterMode::Linear,
            ..Default::default()
        });
        Captures { positions: positions.to_vec(), textures, views, sampler, mips }
    }
}

/// A capture near a colored local light picks up some of its color.
fn capture_tint(scene: &Scene, at: Vec3) -> Vec3 {
    let nearest = scene
        .point_lights
        .iter()
        .map(|l| (l.position.distance(at), l.color))
        .chain(scene.spot_lights.iter().map(|l| (l.position.distance(at), l.color)))
        .min_by(|a, b| a.0.total_cmp(&b.0));
    match nearest {
        Some((_, color)) => Vec3::ONE.lerp(color / color.max_element().max(1e-3), 0.35),
        None => Vec3::ONE,
    }
}

fn downsample(level: &[Vec3], size: u32) -> Vec<Vec3> {
    let half = size / 2;
    let at = |x: u32, y: u32| level[(y * size + x) as usize];
    (0..half * half)
        .map(|t| {
            let (x, y) = (2 * (t % half), 2 * (t / half));
            (at(x, y) + at(x + 1, y) + at(x, y + 1) + at(x + 1, y + 1)) * 0.25
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn half_floats_round_trip_common_values() {
        assert_eq!(f32_to_f16(0.0), 0x0000);
        assert_eq!(f32_to_f16(1.0), 0x3c00);
        assert_eq!(f32_to_f16(-2.0), 0xc000);
        assert_eq!(f32_to_f16(0.5), 0x3800);
        assert_eq!(f32_to_f16(65504.0), 0x7bff);
        assert_eq!(f32_to_f16(1.0e6), 0x7c00);
        assert_eq!(f32_to_f16(0.000_061_035_156), 0x0400);
    }

    #[test]
    fn cube_faces_point_along_their_axes() {
        let c = CAPTURE_SIZE / 2;
        let axes = [Vec3::X, Vec3::NEG_X, Vec3::Y, Vec3::NEG_Y, Vec3::Z, Vec3::NEG_Z];
        for (face, axis) in axes.iter().enumerate() {
            let d = cube_direction(face as u32, c, c, CAPTURE_SIZE);
            assert!(d.dot(*axis) > 0.99, "face {face}: {d}");
        }
    }

    #[test]
    fn the_sky_is_bluer_up_and_brightest_at_the_sun() {
        let sun = Vec3::new(0.3, 0.8, 0.2).normalize();
        let up = procedural_sky(Vec3::Y, sun, Vec3::ONE);
        assert!(up.z > up.x);
        let at_sun = procedural_sky(sun, sun, Vec3::ONE);
        assert!(at_sun.x > up.x + 5.0);
        let down = procedural_sky(Vec3::NEG_Y, sun, Vec3::ONE);
        assert!(down.max_element() < 0.3);
    }
}
