//! The glass lit by the translucency lighting volumes (TranslucencyLightingMode
//! `SURFACE_LIGHTING_VOLUME`): what InjectTranslucentVolume writes shows on the glass, and a
//! light the volumes see occluded darkens the glass that lies in its shadow, not the rest.

use crate::desktop_support::*;
use glam::{Mat4, Vec3};
use kiln_renderer::desktop::effects::{EffectOptions, TranslucencyLightingMode};
use kiln_renderer::frame::Image;
use kiln_renderer::scene::{Material, Mesh, Mobility, Object, Scene, SpotLight};
use kiln_renderer::RendererOptions;

const W: u32 = 320;
const H: u32 = 180;

/// Still frames without the effects that move or blur (so two renders differ only by what a
/// test changes), with the glass lit as `mode` and the volumes' directional light shadowed
/// when `volume_shadows`.
fn options(mode: TranslucencyLightingMode, volume_shadows: bool) -> EffectOptions {
    EffectOptions {
        taa: false,
        motion_blur: false,
        eye_adaptation: false,
        animate: false,
        volumetric_fog: false,
        particles: false,
        translucency_lighting: mode,
        translucency_volume_shadows: volume_shadows,
        ..EffectOptions::default()
    }
}

/// The scene without the fire (its sprites would share the separate translucency target
/// with the glass).
fn scene_without_fire() -> Scene {
    let mut scene = Scene::bundled();
    scene.emitters.clear();
    scene
}

/// One frame's captures by name.
fn captures(scene: &Scene, options: EffectOptions) -> Vec<(String, Image)> {
    let gpu = gpu();
    let r = renderer(&gpu, scene, RendererOptions { width: W, height: H, ..Default::default() });
    r.desktop_effects().expect("the desktop frame's effects").set_options(options);
    let frame = r.render(true).unwrap_or_else(|e| panic!("{e}"));
    frame.passes.into_iter().flat_map(|p| p.images).collect()
}

fn named(images: &[(String, Image)], name: &str) -> Image {
    images.iter().find(|(n, _)| n == name).map(|(_, i)| i.clone()).unwrap_or_else(|| panic!("no image `{name}`"))
}

fn luma(p: &[u8]) -> f64 {
    0.299 * f64::from(p[0]) + 0.587 * f64::from(p[1]) + 0.114 * f64::from(p[2])
}

/// Pixels the glass covers in a separate translucency capture (the target is cleared to
/// black; the glass adds at least its sky light).
fn glass_mask(image: &Image) -> Vec<bool> {
    image.rgba.chunks(4).map(|p| luma(p) > 2.0).collect()
}

/// Mean luma of `image` over the pixels where `mask` holds.
fn masked_mean(image: &Image, mask: &[bool]) -> f64 {
    let (sum, n) =
        image.rgba.chunks(4).zip(mask).filter(|(_, m)| **m).fold((0.0, 0usize), |(s, n), (p, _)| (s + luma(p), n + 1));
    assert!(n > 0, "empty mask");
    sum / n as f64
}

/// Mean absolute luma difference over the pixels where `mask` holds.
fn masked_diff(a: &Image, b: &Image, mask: &[bool]) -> f64 {
    let (sum, n) = a
        .rgba
        .chunks(4)
        .zip(b.rgba.chunks(4))
        .zip(mask)
        .filter(|(_, m)| **m)
        .fold((0.0, 0usize), |(s, n), ((p, q), _)| (s + (luma(p) - luma(q)).abs(), n + 1));
    assert!(n > 0, "empty mask");
    sum / n as f64
}

/// The glass's pixels follow what InjectTranslucentVolume wrote: injecting the directional
/// light shadowed (the room's walls occlude most of it) instead of unshadowed darkens the glass
/// lit by the volumes, while the glass shaded per pixel and the opaque scene do not change.
///
/// Measured on lavapipe (320x180, luma of the tone-mapped capture in 0..255): volume-lit
/// glass 111.1 unshadowed, 107.3 shadowed, mean |difference| 3.8 over the glass; the
/// per-pixel glass and SceneColor before Translucency 0.000. Bounds: half the measured change.
#[test]
fn glass_lit_by_the_volumes_changes_with_the_volumes_lighting() {
    let mut scene = scene_without_fire();
    // seen from the window's side, where the sun would light the statues if no wall stood
    // in its way
    scene.camera.position = Vec3::new(6.0, 2.6, 5.0);
    scene.camera.target = Vec3::new(-0.5, 1.2, -1.0);
    let dir = dump_dir("desktop_translucency_volume");
    let volume_shadowed = captures(&scene, options(TranslucencyLightingMode::SurfaceLightingVolume, true));
    let volume_unshadowed = captures(&scene, options(TranslucencyLightingMode::SurfaceLightingVolume, false));
    let forward_shadowed = captures(&scene, options(TranslucencyLightingMode::SurfaceForwardShading, true));
    let forward_unshadowed = captures(&scene, options(TranslucencyLightingMode::SurfaceForwardShading, false));
    let glass = |c: &[(String, Image)]| named(c, "Translucency_SeparateTranslucency");
    let opaque = |c: &[(String, Image)]| named(c, "ExponentialHeightFog");
    for (name, c) in [
        ("volume_shadowed", &volume_shadowed),
        ("volume_unshadowed", &volume_unshadowed),
        ("forward", &forward_shadowed),
    ] {
        save(&dir, &format!("{name}_glass"), &glass(c));
        save(&dir, &format!("{name}_output"), &named(c, "Translucency_ComposeSeparateTranslucency"));
    }
    let mask = glass_mask(&glass(&forward_shadowed));
    let covered = mask.iter().filter(|m| **m).count();
    assert!(covered > 500, "the glass covers only {covered} pixels");

    let (dark, bright) = (masked_mean(&glass(&volume_shadowed), &mask), masked_mean(&glass(&volume_unshadowed), &mask));
    let changed = masked_diff(&glass(&volume_shadowed), &glass(&volume_unshadowed), &mask);
    let forward_changed = masked_diff(&glass(&forward_shadowed), &glass(&forward_unshadowed), &mask);
    let opaque_changed = mean_abs_diff(&opaque(&volume_shadowed), &opaque(&volume_unshadowed));
    eprintln!("volume-lit glass: {dark:.2} shadowed, {bright:.2} unshadowed, |diff| {changed:.2}; per-pixel glass |diff| {forward_changed:.3}; opaque |diff| {opaque_changed:.3}");
    assert!(changed > 2.0, "the volume-lit glass does not follow the volumes ({changed:.2})");
    assert!(dark < bright - 2.0, "the shadowed volumes do not darken the glass ({dark:.2} vs {bright:.2})");
    assert!(forward_changed < 0.05, "the per-pixel glass reads the volumes ({forward_changed:.3})");
    assert!(opaque_changed < 0.05, "the translucency volumes changed the opaque scene ({opaque_changed:.3})");
}

/// The pixels of each instance of the glass statue: inside the screen box of its bounds and
/// covered by glass, and not inside the other's box.
fn statue_masks(scene: &Scene, glass: &[bool]) -> [Vec<bool>; 2] {
    let o = scene.objects.iter().find(|o| o.name == "GlassStatues").unwrap();
    let (lo, hi) = scene.meshes[o.mesh].bounds();
    let view_proj = scene.camera.projection(W as f32 / H as f32) * scene.camera.view();
    let boxes: Vec<(f32, f32, f32, f32)> = o
        .instances
        .iter()
        .map(|m| {
            let mut b = (f32::MAX, f32::MAX, f32::MIN, f32::MIN);
            for i in 0..8 {
                let corner = Vec3::new(
                    if i & 1 == 0 { lo.x } else { hi.x },
                    if i & 2 == 0 { lo.y } else { hi.y },
                    if i & 4 == 0 { lo.z } else { hi.z },
                );
                let clip = view_proj * m.transform_point3(corner).extend(1.0);
                let (x, y) = ((clip.x / clip.w * 0.5 + 0.5) * W as f32, (0.5 - clip.y / clip.w * 0.5) * H as f32);
                b = (b.0.min(x), b.1.min(y), b.2.max(x), b.3.max(y));
            }
            b
        })
        .collect();
    let inside = |b: &(f32, f32, f32, f32), i: usize| {
        let (x, y) = ((i as u32 % W) as f32 + 0.5, (i as u32 / W) as f32 + 0.5);
        x >= b.0 && x <= b.2 && y >= b.1 && y <= b.3
    };
    let mask =
        |k: usize| (0..glass.len()).map(|i| glass[i] && inside(&boxes[k], i) && !inside(&boxes[1 - k], i)).collect();
    [mask(0), mask(1)]
}

/// A canopy over the second glass statue, the sun high and no walls: the volumes see the sun
/// occluded under the canopy only. Injecting it shadowed darkens the statue under the
/// canopy and leaves the one in the open as it was.
///
/// Measured on lavapipe (320x180): the statue under the canopy keeps 0.626 of its unshadowed
/// luma, the one in the open 0.954 (the volumes' 0.6 m cells, blurred by the filter, still see
/// some of the other objects' shadows near it).
#[test]
fn a_light_occluded_in_the_volumes_darkens_the_glass_in_its_shadow() {
    let mut scene = scene_without_fire();
    scene.objects.retain(|o| o.name != "Walls" && o.name != "WindowWall");
    // the sun from above and behind the camera's left, lighting the faces the camera sees;
    // no other light the volumes hold
    scene.sun.direction = Vec3::new(0.4, -0.8, -0.45).normalize();
    scene.point_lights.clear();
    let statue = scene.objects.iter().find(|o| o.name == "GlassStatues").unwrap();
    let covered = statue.instances[1].transform_point3(Vec3::ZERO);
    // shifted against the sun so that the shadow of the canopy (at 3.5 m) falls on the
    // statue's middle (1.3 m)
    let towards_sun = -scene.sun.direction * ((3.5 - 1.3) / -scene.sun.direction.y);
    let canopy_offset = Vec3::new(covered.x + towards_sun.x, 0.0, covered.z + towards_sun.z);
    let mut canopy = Mesh::new("Canopy");
    canopy.add_box(Vec3::new(-1.75, 3.4, -1.75), Vec3::new(1.75, 3.6, 1.75), 1.0);
    scene.meshes.push(canopy);
    scene.materials.push(Material::opaque("CanopyPaint", Vec3::splat(0.5), 0.0, 0.8));
    scene.objects.push(Object {
        name: "Canopy".into(),
        mesh: scene.meshes.len() - 1,
        material: scene.materials.len() - 1,
        instances: vec![Mat4::from_translation(canopy_offset)],
        mobility: Mobility::Static,
        casts_shadow: true,
    });
    let dir = dump_dir("desktop_translucency_volume_canopy");
    let shadowed = named(
        &captures(&scene, options(TranslucencyLightingMode::SurfaceLightingVolume, true)),
        "Translucency_SeparateTranslucency",
    );
    let unshadowed = named(
        &captures(&scene, options(TranslucencyLightingMode::SurfaceLightingVolume, false)),
        "Translucency_SeparateTranslucency",
    );
    save(&dir, "shadowed", &shadowed);
    save(&dir, "unshadowed", &unshadowed);
    let [open, under] = statue_masks(&scene, &glass_mask(&unshadowed));
    for (name, m) in [("open", &open), ("under the canopy", &under)] {
        let n = m.iter().filter(|v| **v).count();
        assert!(n > 100, "the statue {name} covers only {n} pixels");
    }
    let ratio = |m: &[bool]| masked_mean(&shadowed, m) / masked_mean(&unshadowed, m);
    let (open_ratio, under_ratio) = (ratio(&open), ratio(&under));
    eprintln!("shadowed / unshadowed luma: statue in the open {open_ratio:.3}, under the canopy {under_ratio:.3}");
    assert!(under_ratio < 0.8, "the glass under the canopy is not darkened by the occluded light ({under_ratio:.3})");
    assert!(open_ratio > 0.9, "the glass in the open is darkened too ({open_ratio:.3})");
}

/// Mean luma of each glass statue in a frame's separate translucency (pixel masks from
/// `masks`).
fn statue_lumas(scene: &Scene, options: EffectOptions, masks: &[Vec<bool>; 2]) -> [f64; 2] {
    let glass = named(&captures(scene, options), "Translucency_SeparateTranslucency");
    [masked_mean(&glass, &masks[0]), masked_mean(&glass, &masks[1])]
}

/// A shadow-casting spot light over the second glass statue, nothing else lighting the room
/// but the sky: injected into the volumes with its cone, it lights that statue through the
/// volumes about as the per-pixel shading does, and leaves the statue outside its cone as
/// it was.
///
/// Measured on lavapipe (320x180, mean luma of each statue): without the spot 61.5 (open),
/// 62.6 (under the spot); with it, lit through the volumes, 61.5 and 71.8 (+9.2); shaded per
/// pixel (diffuse and specular), 74.7 (+12.1): the volumes give 0.76 of the per-pixel
/// brightening. Bounds: half the measured gain, a factor of 2 either way of the per-pixel one.
#[test]
fn shadowed_spot_light_lights_the_glass_through_the_volumes_inside_its_cone() {
    let mut dark = scene_without_fire();
    dark.sun.enabled = false;
    dark.point_lights.clear();
    dark.spot_lights.clear();
    let statue = dark.objects.iter().find(|o| o.name == "GlassStatues").unwrap();
    let under = statue.instances[1].transform_point3(Vec3::ZERO);
    let mut lit = dark.clone();
    lit.spot_lights.push(SpotLight {
        name: "GlassSpot".into(),
        position: under + Vec3::Y * 4.5,
        direction: -Vec3::Y,
        color: Vec3::ONE,
        intensity: 20.0,
        radius: 8.0,
        inner_angle: 12f32.to_radians(),
        outer_angle: 24f32.to_radians(),
        mobility: Mobility::Stationary,
        casts_shadows: true,
    });
    let volume = options(TranslucencyLightingMode::SurfaceLightingVolume, true);
    let forward = options(TranslucencyLightingMode::SurfaceForwardShading, true);
    let mask_source = named(&captures(&lit, forward), "Translucency_SeparateTranslucency");
    let masks = statue_masks(&lit, &glass_mask(&mask_source));
    let without = statue_lumas(&dark, volume, &masks);
    let through_volumes = statue_lumas(&lit, volume, &masks);
    let per_pixel = statue_lumas(&lit, forward, &masks);
    eprintln!("statue lumas (open, under the spot): without the spot {without:.1?}, through the volumes {through_volumes:.1?}, per pixel {per_pixel:.1?}");
    let gain = through_volumes[1] - without[1];
    let per_pixel_gain = per_pixel[1] - without[1];
    assert!(gain > 4.5, "the spot does not light the glass through the volumes (+{gain:.1})");
    assert!(
        (0.5..2.0).contains(&(gain / per_pixel_gain)),
        "the volumes light the glass {:.2} times as much as per-pixel shading",
        gain / per_pixel_gain
    );
    assert!(
        (through_volumes[0] - without[0]).abs() < 1.0,
        "the statue outside the cone changed ({:.1} -> {:.1})",
        without[0],
        through_volumes[0]
    );
}
