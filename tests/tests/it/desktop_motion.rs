//! Velocity and eye adaptation of the desktop frame's effects.

use crate::desktop_support::*;
use glam::Vec3;
use kiln_renderer::desktop::effects::EffectOptions;
use kiln_renderer::scene::Scene;
use kiln_renderer::RendererOptions;

/// The moving rock, and only it, has screen-space motion, pointing the way its screen
/// position moved since the previous frame.
#[test]
fn velocity_holds_the_motion_of_the_moving_rock_only() {
    let gpu = gpu();
    let scene = Scene::bundled();
    let r = renderer(&gpu, &scene, RendererOptions { width: 160, height: 90, ..Default::default() });
    let effects = r.desktop_effects().unwrap();
    let rock = scene.objects.iter().position(|o| o.name == "Rock").unwrap();
    r.render(false).unwrap();
    let before = effects.object_transforms(rock)[0].transform_point3(Vec3::ZERO);
    r.render(false).unwrap();
    let after = effects.object_transforms(rock)[0].transform_point3(Vec3::ZERO);
    assert!(before.distance(after) > 0.01, "the rock does not move");
    let (w, h, v) = read_rg16f(&gpu, &effects.velocity_texture());
    let moving: Vec<(u32, u32)> = (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .filter(|&(x, y)| {
            let m = v[(y * w + x) as usize];
            m[0].abs() + m[1].abs() > 1e-4
        })
        .collect();
    assert!(moving.len() > 20, "almost no pixel moves ({})", moving.len());
    // the moving pixels are around the rock's projection
    let aspect = w as f32 / h as f32;
    let ndc = scene.camera.view_proj(aspect).project_point3(after);
    let (cx, cy) = ((ndc.x * 0.5 + 0.5) * w as f32, (0.5 - ndc.y * 0.5) * h as f32);
    let far = moving.iter().filter(|&&(x, y)| (x as f32 - cx).hypot(y as f32 - cy) > 25.0).count();
    assert!(
        far * 10 < moving.len(),
        "{far} of {} moving pixels are away from the rock at ({cx:.0}, {cy:.0})",
        moving.len()
    );
    // and the motion points the way the rock went on screen (uv, y down)
    let prev = scene.camera.view_proj(aspect).project_point3(before);
    let expected = glam::Vec2::new(ndc.x - prev.x, prev.y - ndc.y) * 0.5;
    let mean = moving.iter().fold(glam::Vec2::ZERO, |acc, &(x, y)| acc + glam::Vec2::from(v[(y * w + x) as usize]))
        / moving.len() as f32;
    assert!(mean.dot(expected) > 0.0, "velocity {mean} against the rock's screen motion {expected}");
}

/// Turning the sun off darkens the scene; the eye adaptation measures the darker histogram
/// and raises the exposure frame after frame (and lowers it when the sun is back).
#[test]
fn eye_adaptation_raises_the_exposure_of_a_darker_scene_over_frames() {
    let gpu = gpu();
    let mut scene = Scene::bundled();
    scene.sun.enabled = false;
    let r = renderer(&gpu, &scene, RendererOptions { width: 160, height: 90, ..Default::default() });
    let effects = r.desktop_effects().unwrap();
    effects.set_options(EffectOptions { animate: false, ..EffectOptions::default() });
    let mut exposures = Vec::new();
    for _ in 0..6 {
        r.render(false).unwrap();
        let e = read_buffer_f32(&gpu, &effects.eye_adaptation_buffer(), 4);
        exposures.push((e[0], e[1], e[2]));
    }
    eprintln!("exposure, average luminance, target per frame: {exposures:?}");
    let (first, last) = (exposures[0], exposures[exposures.len() - 1]);
    assert!(first.2 > 1.0, "the darker scene's target exposure is not above 1: {first:?}");
    assert!(
        exposures.windows(2).all(|p| p[1].0 > p[0].0),
        "the exposure does not rise frame after frame: {exposures:?}"
    );
    assert!(last.0 < last.2, "the exposure jumped to its target instead of adapting: {last:?}");
}
