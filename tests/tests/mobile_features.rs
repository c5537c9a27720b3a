//! What the mobile shader macros change, seen in the frames: FULLY_ROUGH removes the
//! specular highlight (forward, and through the GBuffer in deferred),
//! MAX_DYNAMIC_POINT_LIGHTS=0 drops the local lights of the forward base pass, and the
//! frames are the same on GL and on Vulkan.

mod mobile_support;

use glam::Vec3;
use kiln_runtime::frame::Image;
use kiln_runtime::mobile::{MobileOptions, ShadingPath};
use kiln_runtime::scene::Scene;
use kiln_runtime::Backend;
use mobile_support::*;

fn luma(img: &Image, i: usize) -> f64 {
    let p = &img.rgba[i * 4..i * 4 + 3];
    0.299 * f64::from(p[0]) + 0.587 * f64::from(p[1]) + 0.114 * f64::from(p[2])
}

/// The bundled scene with the two statues made of a glossy white dielectric, lit by the sun
/// alone (no sky light, no reflections): only GGX adds to Lambert on them.
fn glossy_statues(fully_rough: bool) -> Scene {
    let mut scene = Scene::bundled();
    let i = scene.material_index("Bronze").unwrap();
    let m = &mut scene.materials[i];
    m.base_color = Vec3::splat(0.5);
    m.metallic = 0.0;
    m.roughness = 0.3;
    m.specular = 1.0;
    m.fully_rough = fully_rough;
    scene.point_lights.clear();
    scene.spot_lights.clear();
    scene
}

fn sun_only(path: ShadingPath) -> MobileOptions {
    MobileOptions { sky_light: false, ..MobileOptions::comparable(path) }
}

#[test]
fn a_fully_rough_material_shows_no_specular_highlight() {
    let rig = rig(Backend::Vulkan);
    for path in [ShadingPath::Forward, ShadingPath::Deferred] {
        let glossy = rig.render(&glossy_statues(false), sun_only(path));
        let rough = rig.render(&glossy_statues(true), sun_only(path));
        // Only the statues' material changes, and only by its specular lobe.
        let n = (glossy.width * glossy.height) as usize;
        let changed = (0..n).filter(|&i| glossy.rgba[i * 4..i * 4 + 3] != rough.rgba[i * 4..i * 4 + 3]).count();
        // The glossy statues have a highlight: pixels far brighter than the same pixel fully rough.
        let highlight = (0..n).filter(|&i| luma(&glossy, i) > luma(&rough, i) + 25.0).count();
        // Fully rough removes light and never adds it.
        let brighter = (0..n).filter(|&i| luma(&rough, i) > luma(&glossy, i) + 2.0).count();
        eprintln!("{}: {changed} pixels changed, {highlight} highlight pixels gone when fully rough, {brighter} brighter", path.name());
        assert!(highlight >= 5, "{}: no specular highlight to remove", path.name());
        assert_eq!(brighter, 0, "{}: FULLY_ROUGH made pixels brighter", path.name());
    }
}

#[test]
fn max_dynamic_point_lights_zero_drops_the_local_lights_in_forward() {
    let rig = rig(Backend::Vulkan);
    let scene = Scene::bundled();
    let mut no_lights = scene.clone();
    no_lights.point_lights.clear();
    no_lights.spot_lights.clear();
    let options = |max| MobileOptions { max_dynamic_point_lights: max, ..MobileOptions::comparable(ShadingPath::Forward) };
    let four = rig.render(&scene, options(4));
    let zero = rig.render(&scene, options(0));
    let unlit = rig.render(&no_lights, options(4));
    let (dropped, lit) = (psnr(&zero, &unlit), psnr(&four, &unlit));
    eprintln!("MAX_DYNAMIC_POINT_LIGHTS=0 vs a scene without local lights: {dropped:.1} dB; =4: {lit:.1} dB");
    // 0 renders exactly what a scene without local lights renders; 4 does not.
    assert!(dropped > 60.0, "MAX_DYNAMIC_POINT_LIGHTS=0 still shades local lights ({dropped:.1} dB)");
    assert!(lit < 40.0, "MAX_DYNAMIC_POINT_LIGHTS=4 shades no local light ({lit:.1} dB)");
    // Fewer lights light less: each step removes light and never adds it.
    let two = rig.render(&scene, options(2));
    let sum = |img: &Image| img.rgba.iter().map(|&v| u64::from(v)).sum::<u64>();
    assert!(sum(&four) > sum(&two) && sum(&two) > sum(&zero), "light sums {} {} {}", sum(&four), sum(&two), sum(&zero));
}

/// GL (llvmpipe) and Vulkan (lavapipe) rasterize and filter slightly differently; the frames
/// agree to better than 35 dB (the same frame with its local lights dropped is about 30 dB
/// away).
const GL_VULKAN_PSNR: f64 = 35.0;

#[test]
fn gl_and_vulkan_draw_the_same_mobile_frames() {
    let vulkan = rig(Backend::Vulkan);
    let gl = rig(Backend::Gl);
    let scene = Scene::bundled();
    for options in [MobileOptions::forward(), MobileOptions::deferred()] {
        let name = options.path.name();
        let a = vulkan.render(&scene, options.clone());
        let b = gl.render(&scene, options);
        let p = psnr(&a, &b);
        eprintln!("{name}: GL/Vulkan {p:.1} dB");
        assert!(p > GL_VULKAN_PSNR, "{name}: GL/Vulkan PSNR {p:.1} dB");
    }
}
