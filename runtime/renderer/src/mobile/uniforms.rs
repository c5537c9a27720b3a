//! The uniform blocks of the mobile shaders (`MobileCommon.ush`,
//! `MobileDeferredShading.usf`, `MobileBloom.usf`, `MobileTonemap.usf`), member for member
//! (vec4 and mat4 members only, so no padding rules apply), and how the scene fills them.

use bytemuck::{Pod, Zeroable};
use glam::{Mat4, Vec3, Vec4};

use crate::scene::{Scene, SpotLight};

use super::shadows::{ShadowLayout, MAX_CASCADES};
use super::sky::Captures;
use super::MobileOptions;

/// Most local lights the forward base pass shades (`MAX_DYNAMIC_POINT_LIGHTS` at most 4).
pub const MAX_LOCAL_LIGHTS: usize = 4;

/// `LocalLight` of `MobileCommon.ush`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct LocalLightData {
    /// xyz position, w = 1 / radius
    pub position_inv_radius: Vec4,
    /// rgb color times intensity, w = specular scale
    pub color: Vec4,
    /// xyz the direction the spot points, w = 1 for a spot light
    pub direction: Vec4,
    /// cos(outer), 1 / (cos(inner) - cos(outer)), shadow slot (-1: none), shadow bias
    pub spot_angles: Vec4,
    /// world -> shadow atlas
    pub shadow_matrix: Mat4,
}

/// `MobileView` of `MobileCommon.ush`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct MobileViewUniforms {
    pub view_proj: Mat4,
    pub inv_view_proj: Mat4,
    pub camera_pos: Vec4,
    pub camera_forward: Vec4,
    pub viewport: Vec4,
    pub light_direction: Vec4,
    pub light_color: Vec4,
    pub csm_splits: Vec4,
    pub csm_matrix: [Mat4; MAX_CASCADES],
    pub shadow_params: Vec4,
    pub sky_sh: [Vec4; 4],
    pub sky_color: Vec4,
    pub fog_color: Vec4,
    pub fog_params: Vec4,
    pub counts: Vec4,
    pub local_lights: [LocalLightData; MAX_LOCAL_LIGHTS],
    pub capture_positions: [Vec4; 3],
    pub capture_brightness: [Vec4; 3],
}

/// `DeferredLight` of `MobileDeferredShading.usf`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct DeferredLightUniforms {
    pub volume_to_world: Mat4,
    pub light: LocalLightData,
}

/// `BloomParams` of `MobileBloom.usf`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct BloomUniforms {
    pub texel: Vec4,
    pub params: Vec4,
}

/// `TonemapParams` of `MobileTonemap.usf`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct TonemapUniforms {
    pub params: Vec4,
}

/// A local light of the scene, point or spot, as the mobile shaders see it.
#[derive(Clone, Debug, PartialEq)]
pub struct LocalLight {
    pub name: String,
    pub data: LocalLightData,
    pub is_spot: bool,
    pub position: Vec3,
    pub radius: f32,
    /// Spot lights: the direction and the outer cone angle.
    pub direction: Vec3,
    pub outer_angle: f32,
}

/// Every local light of the scene (points first, then spots, in scene order) with the spot
/// shadow slots of `shadows` filled in.
pub fn local_lights(scene: &Scene, shadows: &ShadowLayout) -> Vec<LocalLight> {
    let mut out = Vec::new();
    for l in &scene.point_lights {
        out.push(LocalLight {
            name: l.name.clone(),
            data: LocalLightData {
                position_inv_radius: l.position.extend(1.0 / l.radius.max(1e-3)),
                color: (l.color * l.intensity).extend(1.0),
                direction: Vec4::ZERO,
                spot_angles: Vec4::new(0.0, 0.0, -1.0, 0.0),
                shadow_matrix: Mat4::IDENTITY,
            },
            is_spot: false,
            position: l.position,
            radius: l.radius,
            direction: Vec3::NEG_Y,
            outer_angle: 0.0,
        });
    }
    for (i, l) in scene.spot_lights.iter().enumerate() {
        out.push(spot_light(l, shadows.spot_tile(i)));
    }
    out
}

fn spot_light(l: &SpotLight, shadow: Option<(usize, Mat4)>) -> LocalLight {
    let cos_outer = l.outer_angle.cos();
    let cos_inner = l.inner_angle.cos();
    let (slot, matrix) = match shadow {
        Some((slot, m)) => (slot as f32, m),
        None => (-1.0, Mat4::IDENTITY),
    };
    LocalLight {
        name: l.name.clone(),
        data: LocalLightData {
            position_inv_radius: l.position.extend(1.0 / l.radius.max(1e-3)),
            color: (l.color * l.intensity).extend(1.0),
            direction: l.direction.normalize().extend(1.0),
            spot_angles: Vec4::new(cos_outer, 1.0 / (cos_inner - cos_outer).max(1e-4), slot, 0.0005),
            shadow_matrix: matrix,
        },
        is_spot: true,
        position: l.position,
        radius: l.radius,
        direction: l.direction.normalize(),
        outer_angle: l.outer_angle,
    }
}

/// The lights the forward base pass shades: at most `MAX_DYNAMIC_POINT_LIGHTS`, the ones
/// nearest the camera first (the seed sorts the visible local lights per view).
pub fn forward_lights(lights: &[LocalLight], camera: Vec3, max: usize) -> Vec<LocalLight> {
    let mut sorted: Vec<LocalLight> = lights.to_vec();
    sorted.sort_by(|a, b| a.position.distance(camera).total_cmp(&b.position.distance(camera)));
    sorted.truncate(max.min(MAX_LOCAL_LIGHTS));
    sorted
}

/// The view uniforms of the mobile frames for a `width` x `height` target.
pub fn view_uniforms(
    scene: &Scene,
    options: &MobileOptions,
    width: u32,
    height: u32,
    shadows: &ShadowLayout,
    forward_lights: &[LocalLight],
    captures: &Captures,
) -> MobileViewUniforms {
    let aspect = width as f32 / height as f32;
    let view_proj = scene.camera.view_proj(aspect);
    let forward = (scene.camera.target - scene.camera.position).normalize();
    let sun = &scene.sun;
    let sun_color = if sun.enabled { sun.color * sun.intensity } else { Vec3::ZERO };
    let mut u = MobileViewUniforms {
        view_proj,
        inv_view_proj: view_proj.inverse(),
        camera_pos: scene.camera.position.extend(scene.exposure),
        camera_forward: forward.extend(0.0),
        viewport: Vec4::new(width as f32, height as f32, 1.0 / width as f32, 1.0 / height as f32),
        light_direction: (-sun.direction.normalize()).extend(1.0),
        light_color: sun_color.extend(shadows.cascades.len() as f32),
        shadow_params: Vec4::new(1.0 / shadows.atlas_width as f32, 0.0008, 0.0, 1.0 / shadows.atlas_height as f32),
        ..Default::default()
    };
    let mut splits = [f32::MAX; MAX_CASCADES];
    for (i, c) in shadows.cascades.iter().enumerate() {
        splits[i] = c.far;
        u.csm_matrix[i] = c.atlas_matrix;
    }
    u.csm_splits = Vec4::from_array(splits);
    // The sky light: the scene's sky color at the zenith fading to a third of it at the nadir
    // (irradiance = sh0 + sh1 * n.y), an L1 spherical harmonic of the sky dome.
    if options.sky_light {
        u.sky_sh[0] = (scene.sky_color * 0.665).extend(0.0);
        u.sky_sh[1] = (scene.sky_color * 0.335).extend(0.0);
    }
    u.sky_color = Vec4::new(1.0, 1.0, 1.0, captures.max_mip() as f32);
    if options.vertex_fog {
        u.fog_color = scene.fog.color.extend(scene.fog.density);
        u.fog_params =
            Vec4::new(scene.fog.height_falloff, scene.fog.base_height, scene.fog.start_distance, scene.fog.max_opacity);
    }
    for (i, l) in forward_lights.iter().take(MAX_LOCAL_LIGHTS).enumerate() {
        u.local_lights[i] = l.data;
    }
    let captures_on = if options.reflections { captures.positions.len() } else { 0 };
    u.counts = Vec4::new(forward_lights.len().min(MAX_LOCAL_LIGHTS) as f32, captures_on as f32, 0.0, 0.0);
    for (i, p) in captures.positions.iter().enumerate().take(3) {
        u.capture_positions[i] = *p;
        u.capture_brightness[i] = Vec4::ONE;
    }
    u
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_match_the_wgsl_structs() {
        assert_eq!(std::mem::size_of::<LocalLightData>(), 128);
        // 2 mat4, 6 vec4, 4 mat4, 1 vec4, 4 vec4 (SH), 4 vec4, 4 lights, 6 vec4
        assert_eq!(
            std::mem::size_of::<MobileViewUniforms>(),
            2 * 64 + 6 * 16 + 4 * 64 + 16 + 4 * 16 + 4 * 16 + 4 * 128 + 6 * 16
        );
        assert_eq!(std::mem::size_of::<DeferredLightUniforms>(), 192);
    }

    #[test]
    fn forward_lights_are_the_nearest_and_capped() {
        let mk = |name: &str, x: f32| LocalLight {
            name: name.into(),
            data: LocalLightData::default(),
            is_spot: false,
            position: Vec3::new(x, 0.0, 0.0),
            radius: 1.0,
            direction: Vec3::NEG_Y,
            outer_angle: 0.0,
        };
        let lights = vec![mk("far", 9.0), mk("near", 1.0), mk("mid", 4.0)];
        let names = |v: Vec<LocalLight>| v.into_iter().map(|l| l.name).collect::<Vec<_>>();
        assert_eq!(names(forward_lights(&lights, Vec3::ZERO, 2)), ["near", "mid"]);
        assert_eq!(names(forward_lights(&lights, Vec3::ZERO, 0)), Vec::<String>::new());
        assert_eq!(names(forward_lights(&lights, Vec3::ZERO, 8)), ["near", "mid", "far"]);
    }
}
