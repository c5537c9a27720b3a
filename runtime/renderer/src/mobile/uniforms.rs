//! The uniform blocks of the mobile shaders (`MobileDeferredShading.usf`, `MobileBloom.usf`, `MobileTonemap.usf`), member for member
//! (vec4 and mat4 members only, so no padding rules apply), and how the scene fills them and
//! the mobile part of the one `SceneView` (`shader_src/Private/SceneView.ush`).

use bytemuck::{Pod, Zeroable};
use glam::{Mat4, Vec3, Vec4};

use crate::scene::{Scene, SpotLight};

use crate::scene::view::{CameraState, FrameTime, SceneView};
pub use crate::scene::view::{ForwardLocalLight, MAX_CASCADES, MAX_LOCAL_LIGHTS};

use super::shadows::ShadowLayout;
use super::sky::Captures;
use super::MobileOptions;

/// `DeferredLight` of `MobileDeferredShading.usf`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct DeferredLightUniforms {
    pub volume_to_world: Mat4,
    pub light: ForwardLocalLight,
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
    pub data: ForwardLocalLight,
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
            data: ForwardLocalLight {
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
        data: ForwardLocalLight {
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

/// The `SceneView` of the mobile frames for a `width` x `height` target: the scene's camera
/// (no jitter) and what the mobile shaders add: pre-exposure, the CSM cascades, the sky light's
/// spherical harmonics, the vertex fog (zero unless `vertex_fog`), the forward local lights and
/// the reflection captures.
pub fn view_uniforms(
    scene: &Scene,
    options: &MobileOptions,
    (width, height): (u32, u32),
    shadows: &ShadowLayout,
    forward_lights: &[LocalLight],
    captures: &Captures,
) -> SceneView {
    let camera = CameraState::of_scene(scene, width, height);
    let mut u = SceneView::new(scene, &camera, &camera, width, height, FrameTime::default());
    u.time.w = scene.exposure;
    u.shadow_params = Vec4::new(
        1.0 / shadows.atlas_width as f32,
        0.0008,
        shadows.cascades.len() as f32,
        1.0 / shadows.atlas_height as f32,
    );
    let mut splits = [f32::MAX; MAX_CASCADES];
    let atlas = glam::Vec2::new(shadows.atlas_width as f32, shadows.atlas_height as f32);
    for (i, c) in shadows.cascades.iter().enumerate() {
        splits[i] = c.far;
        u.csm_view_proj[i] = c.view_proj;
        let [x, y, w, h] = c.viewport.map(|v| v as f32);
        u.csm_rects[i] = Vec4::new(x / atlas.x, y / atlas.y, w / atlas.x, h / atlas.y);
    }
    u.csm_splits = Vec4::from_array(splits);
    // The sky light: the scene's sky color at the zenith fading to a third of it at the nadir
    // (irradiance = sh0 + sh1 * n.y), an L1 spherical harmonic of the sky dome.
    if options.sky_light {
        u.sky_sh[0] = (scene.sky_color * 0.665).extend(0.0);
        u.sky_sh[1] = (scene.sky_color * 0.335).extend(0.0);
    }
    u.ground_color.w = captures.max_mip() as f32;
    if !options.vertex_fog {
        u.fog_color = Vec4::ZERO;
        u.fog_params = Vec4::ZERO;
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
        assert_eq!(std::mem::size_of::<DeferredLightUniforms>(), 192);
    }

    #[test]
    fn forward_lights_are_the_nearest_and_capped() {
        let mk = |name: &str, x: f32| LocalLight {
            name: name.into(),
            data: ForwardLocalLight::default(),
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
