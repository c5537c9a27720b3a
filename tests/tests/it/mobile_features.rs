//! What the mobile shader macros change, seen in the frames: FULLY_ROUGH removes the
//! specular highlight (forward, and through the GBuffer in deferred),
//! MAX_DYNAMIC_POINT_LIGHTS=0 drops the local lights of the forward base pass, and the
//! frames are the same on GL and on Vulkan.

use crate::mobile_support::*;
use glam::Vec3;
use kiln_renderer::frame::Image;
use kiln_renderer::mobile::{MobileOptions, ShadingPath};
use kiln_renderer::scene::Scene;
use kiln_runtime::Backend;

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
        eprintln!(
            "{}: {changed} pixels changed, {highlight} highlight pixels gone when fully rough, {brighter} brighter",
            path.name()
        );
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
    let options =
        |max| MobileOptions { max_dynamic_point_lights: max, ..MobileOptions::comparable(ShadingPath::Forward) };
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

fn light_sum(img: &Image) -> u64 {
    img.rgba.iter().map(|&v| u64::from(v)).sum()
}

#[test]
fn spot_shadows_come_from_the_shared_atlas() {
    let rig = rig(Backend::Vulkan);
    let mut unshadowed = Scene::bundled();
    // The spot light alone (plus the sky), so its shadow is what changes.
    unshadowed.sun.enabled = false;
    unshadowed.point_lights.clear();
    for l in &mut unshadowed.spot_lights {
        l.casts_shadows = false;
    }
    let mut shadowed = unshadowed.clone();
    for l in &mut shadowed.spot_lights {
        l.casts_shadows = true;
    }
    for path in [ShadingPath::Forward, ShadingPath::Deferred] {
        let options = MobileOptions::comparable(path);
        let (passes, with_shadow) = rig.render_passes(&shadowed, options.clone(), true);
        let without = rig.render(&unshadowed, options);
        // The atlas holds the spot's tile under the cascades (one capture of ShadowDepths).
        let atlas = &passes[0].images[0].1;
        let n = (with_shadow.width * with_shadow.height) as usize;
        let darker = (0..n).filter(|&i| luma(&with_shadow, i) + 8.0 < luma(&without, i)).count();
        let brighter = (0..n).filter(|&i| luma(&with_shadow, i) > luma(&without, i) + 2.0).count();
        eprintln!(
            "{}: spot shadow darkens {darker} pixels, brightens {brighter}; atlas {}x{}",
            path.name(),
            atlas.width,
            atlas.height
        );
        assert!(darker > 50, "{}: the spot light casts no shadow", path.name());
        assert_eq!(brighter, 0, "{}: a shadow added light", path.name());
        assert!(light_sum(&with_shadow) < light_sum(&without));
    }
}

#[test]
fn full_prepass_and_cascade_count_keep_the_frame() {
    let rig = rig(Backend::Vulkan);
    let scene = Scene::bundled();
    for path in [ShadingPath::Forward, ShadingPath::Deferred] {
        let base = MobileOptions::comparable(path);
        let reference = rig.render(&scene, base.clone());
        let (passes, prepass) = rig.render_passes(&scene, MobileOptions { full_prepass: true, ..base.clone() }, true);
        assert_eq!(passes[1].name, "PrePass");
        let p = psnr(&reference, &prepass);
        // Four cascades move shadow edges by a texel here and there, no more.
        let four = psnr(&reference, &rig.render(&scene, MobileOptions { cascades: 4, ..base.clone() }));
        eprintln!("{}: full prepass {p:.1} dB, 4 cascades {four:.1} dB", path.name());
        assert!(p > 50.0, "{}: the prepass changed the frame ({p:.1} dB)", path.name());
        assert!(four > 30.0, "{}: 4 cascades changed the frame ({four:.1} dB)", path.name());
    }
}

#[test]
fn reflections_blend_captures_with_hq_reflections() {
    let rig = rig(Backend::Vulkan);
    let scene = Scene::bundled();
    let base = MobileOptions::comparable(ShadingPath::Forward);
    let none = rig.render(&scene, base.clone());
    let nearest = rig.render(&scene, MobileOptions { reflections: true, hq_reflections: false, ..base.clone() });
    let hq = rig.render(&scene, MobileOptions { reflections: true, hq_reflections: true, ..base });
    let (a, b) = (psnr(&none, &nearest), psnr(&nearest, &hq));
    eprintln!("no reflections / nearest capture {a:.1} dB, nearest / HQ blend {b:.1} dB");
    // Reflections add light to glossy and metal surfaces; blending captures changes them.
    assert!(light_sum(&nearest) > light_sum(&none));
    assert!(a < 45.0 && b < 62.0, "reflections changed nothing: {a:.1} / {b:.1} dB");
}

#[test]
fn msaa_resolves_at_the_end_of_the_last_scene_color_pass() {
    let rig = rig(Backend::Vulkan);
    let mut scene = Scene::bundled();
    scene.objects.retain(|o| o.name != "GlassStatues");
    // Without translucent meshes the frame has no Translucency pass: the base pass resolves.
    let (passes, resolved_in_base) =
        rig.render_passes(&scene, MobileOptions { translucency: true, ..MobileOptions::forward() }, false);
    assert!(!passes.iter().any(|p| p.name == "Translucency"));
    let no_msaa = rig.render(&scene, MobileOptions { msaa: 1, ..MobileOptions::forward() });
    let p = psnr(&resolved_in_base, &no_msaa);
    // Anti-aliasing changes edge pixels only.
    eprintln!("MSAA 4x against no MSAA: {p:.1} dB");
    assert!(p > 28.0 && p.is_finite(), "MSAA {p:.1} dB against no MSAA");
    // With glass statues, Translucency continues the multisampled color and resolves it.
    let (passes, _) = rig.render_passes(&Scene::bundled(), MobileOptions::forward(), false);
    assert_eq!(
        passes.iter().map(|p| p.name.as_str()).collect::<Vec<_>>(),
        ["ShadowDepths", "BasePass", "Translucency", "PostProcessing"]
    );
}
