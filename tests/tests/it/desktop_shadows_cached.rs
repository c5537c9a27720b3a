//! ShadowDepths of a movable point light with a cached static depth (CopyCachedShadowMap).

use crate::desktop_support::*;
use glam::{Mat4, Vec3};
use kiln_renderer::scene::Scene;
use kiln_renderer::RendererOptions;

/// While the light is still, the cube shadow's static depth is rendered once and copied
/// every frame, with only the movable rock drawn on top; when the light moves it is
/// rendered again.
#[test]
fn cached_cube_shadow_is_not_redrawn_while_the_light_is_still() {
    let gpu = gpu();
    let mut scene = Scene::bundled();
    // bring the movable rock next to the movable fire light, inside its cube shadow
    let rock = scene.objects.iter().position(|o| o.name == "Rock").unwrap();
    scene.objects[rock].instances = vec![Mat4::from_translation(Vec3::new(3.6, 0.55, -2.0))];
    let r = renderer(&gpu, &scene, RendererOptions { width: 160, height: 90, ..Default::default() });
    let frame = r.desktop_frame().expect("the desktop frame");
    let mut last = None;
    for _ in 0..3 {
        last = Some(r.render(true).unwrap());
    }
    assert_eq!(
        frame.cached_shadow_rebuilds(),
        1,
        "the cached static depth was rendered again while the light stood still"
    );

    let images: Vec<_> = last.unwrap().passes.into_iter().flat_map(|p| p.images).collect();
    let find = |name: &str| {
        images.iter().find(|(n, _)| n == name).map(|(_, i)| i.clone()).unwrap_or_else(|| panic!("no image {name}"))
    };
    let cached = find("ShadowDepths_CopyCachedShadowMap");
    let full = find("ShadowDepths_Cubemap_FireLight");
    let dir = dump_dir("desktop_shadows_cached");
    save(&dir, "cached", &cached);
    save(&dir, "with_movable", &full);
    assert!(luma_stddev(&cached) > 1.0, "the cached static depth is empty");
    assert!(mean_abs_diff(&cached, &full) > 0.05, "the movable rock is not drawn over the cached depth");

    frame.invalidate_cached_shadows();
    r.render(false).unwrap();
    r.render(false).unwrap();
    assert_eq!(frame.cached_shadow_rebuilds(), 2, "the cache was not rebuilt (once) after the light moved");
}
