//! The lit smoke reads both translucency lighting volume cascades, blended as the glass reads
//! them: near the camera it sees the inner cascade's detail. A small point light (radius
//! 0.4 m) hangs in the smoke column at a corner of the outer cascade's grid: every outer cell
//! centre is 0.54 m from it, beyond its radius, so the outer cascade holds none of its light,
//! while inner cells (0.156 m) around it do. Smoke that read only the outer cascade would not
//! see the light at all.

use crate::desktop_support::*;
use glam::Vec3;
use kiln_renderer::desktop::effects::EffectOptions;
use kiln_renderer::desktop::translucent_volume::TranslucentVolumes;
use kiln_renderer::frame::Image;
use kiln_renderer::scene::{Camera, Mobility, PointLight, Scene};
use kiln_renderer::RendererOptions;

const W: u32 = 320;
const H: u32 = 180;
/// Frames rendered: 1.5 s of smoke (it spawns 1 m over the fire and rises about 0.5 m/s).
const FRAMES: usize = 45;

/// 3 m from the smoke column, well inside the inner cascade (5 m around the camera; the
/// column is 1.5 m and 2.5 m away along x and z, inside the box's middle two thirds, where
/// only the inner cascade is read).
fn camera() -> Camera {
    Camera {
        position: Vec3::new(3.5, 2.0, -0.5),
        target: Vec3::new(5.0, 1.5, -3.0),
        fov_y: 60f32.to_radians(),
        near: 0.1,
    }
}

/// The outer cascade's grid corner nearest the smoke column at 1.6 m (the cascades' boxes are
/// snapped to whole cells, so a corner of the outer grid is one of the inner grid too).
fn light_position() -> Vec3 {
    let (origin, cell) = TranslucentVolumes::cascade_box(camera().position, 1);
    origin + ((Vec3::new(5.0, 1.6, -3.0) - origin) / cell).round() * cell
}

fn scene(with_light: bool) -> Scene {
    let mut scene = Scene::bundled();
    scene.camera = camera();
    if with_light {
        // shadow-casting, so the volumes hold it; it reaches no opaque surface
        scene.point_lights.push(PointLight {
            name: "SmokeLight".into(),
            position: light_position(),
            color: Vec3::ONE,
            intensity: 40.0,
            radius: 0.4,
            mobility: Mobility::Movable,
            casts_shadows: true,
        });
    }
    scene
}

/// The last frame's image after the particle sprites (Translucency's ParticleSprites step).
fn smoke_frame(with_light: bool) -> Image {
    let gpu = gpu();
    let r = renderer(&gpu, &scene(with_light), RendererOptions { width: W, height: H, ..Default::default() });
    // still frames, nothing that adds the light elsewhere (the volumetric fog scatters it too)
    r.desktop_effects().unwrap().set_options(EffectOptions {
        taa: false,
        motion_blur: false,
        eye_adaptation: false,
        animate: false,
        volumetric_fog: false,
        ..EffectOptions::default()
    });
    for _ in 1..FRAMES {
        r.render(false).unwrap_or_else(|e| panic!("{e}"));
    }
    let frame = r.render(true).unwrap_or_else(|e| panic!("{e}"));
    frame
        .passes
        .into_iter()
        .flat_map(|p| p.images)
        .find(|(n, _)| n == "Translucency_ParticleSprites")
        .map(|(_, i)| i)
        .expect("no ParticleSprites image")
}

/// Luma gained per pixel, summed over the image.
fn luma_gain(lit: &Image, dark: &Image) -> f64 {
    let luma = |p: &[u8]| 0.299 * f64::from(p[0]) + 0.587 * f64::from(p[1]) + 0.114 * f64::from(p[2]);
    lit.rgba.chunks(4).zip(dark.rgba.chunks(4)).map(|(p, q)| (luma(p) - luma(q)).max(0.0)).sum()
}

/// Measured on lavapipe (320x180, summed luma gain of the HDR capture in 0..255): the same
/// frame rendered twice without the light 0.0 (the smoke is deterministic); with the light
/// at (5, 1.875, -3.125), smoke reading both cascades 76681 (a white glow where the column
/// passes the light), smoke reading only the outer cascade (the runtime before this test)
/// 0.0. Bound: far below the measured gain, far above the noise.
#[test]
fn smoke_near_the_camera_sees_light_only_the_inner_cascade_holds() {
    let dark = smoke_frame(false);
    let dark_again = smoke_frame(false);
    let lit = smoke_frame(true);
    let dir = dump_dir("desktop_smoke_cascades");
    save(&dir, "dark", &dark);
    save(&dir, "lit", &lit);
    let (noise, gain) = (luma_gain(&dark_again, &dark) + luma_gain(&dark, &dark_again), luma_gain(&lit, &dark));
    eprintln!("light at {}: luma gain {gain:.1} (two renders without it: {noise:.1})", light_position());
    assert!(noise < 1.0, "two renders of the same smoke differ ({noise})");
    assert!(gain > 5000.0, "the smoke does not see the light the inner cascade holds (gain {gain:.1})");
}
