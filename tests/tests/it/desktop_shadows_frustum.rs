//! ShadowFrustumQueries gate the shadow work of local lights: a light whose shadow volume is
//! hidden behind the depth buffer renders no shadow depths and no ShadowProjection once its
//! query result has come back, and gets them back once the camera sees the volume again.

use crate::desktop_support::*;
use glam::{Mat4, Vec3};
use kiln_renderer::renderer::FrameOutput;
use kiln_renderer::scene::{Camera, Mobility, PointLight, Scene};
use kiln_renderer::RendererOptions;

const HIDDEN_LAMP: &str = "HiddenLamp";
const HIDDEN_FIRE: &str = "HiddenFire";

/// The bundled scene with two shadowed point lights behind the back wall (z = -6 .. -6.2,
/// 4 m high): a stationary one (frustum query: the 4 m cube around it, z = -11 .. -7,
/// y up to 3.2) with the movable rock 2.8 m from it (its per-object shadow tile; its bounding sphere, 2 m, must not hold the light), and a movable
/// one (sphere query, radius 2.2: z = -11.2 .. -6.8, y up to 3.4). From the bundled camera
/// (y = 3.4, z = 9.5) the wall hides both volumes. No particle emitters, so that two frames
/// of the comparison settings (nothing animated) render the same image.
fn scene() -> Scene {
    let mut scene = Scene::bundled();
    scene.emitters.clear();
    let rock = scene.objects.iter().position(|o| o.name == "Rock").unwrap();
    scene.objects[rock].instances = vec![Mat4::from_translation(Vec3::new(5.5, 0.55, -10.0))];
    let lamp = |name: &str, x: f32, radius: f32, mobility: Mobility| PointLight {
        name: name.into(),
        position: Vec3::new(x, 1.2, -9.0),
        color: Vec3::new(1.0, 0.9, 0.8),
        intensity: 6.0,
        radius,
        mobility,
        casts_shadows: true,
    };
    scene.point_lights.push(lamp(HIDDEN_LAMP, 3.0, 2.0, Mobility::Stationary));
    scene.point_lights.push(lamp(HIDDEN_FIRE, -3.0, 2.2, Mobility::Movable));
    scene
}

/// Every step name of the frame (`Pass_Step`), as `passes.json` lists them.
fn steps(frame: &FrameOutput) -> Vec<String> {
    frame.passes.iter().flat_map(|p| p.steps.iter().map(move |s| format!("{}_{}", p.name, s.name))).collect()
}

fn images(frame: &FrameOutput) -> Vec<String> {
    frame.passes.iter().flat_map(|p| p.images.iter().map(|(n, _)| n.clone())).collect()
}

/// The shadow steps and images of one light present in a frame.
fn shadow_work(frame: &FrameOutput, light: &str) -> Vec<String> {
    let mut found: Vec<String> =
        steps(frame).into_iter().chain(images(frame)).filter(|n| n.ends_with(&format!("_{light}"))).collect();
    found.sort();
    found.dedup();
    found
}

fn max_channel_diff(a: &kiln_renderer::frame::Image, b: &kiln_renderer::frame::Image) -> u8 {
    a.rgba.iter().zip(&b.rgba).map(|(x, y)| x.abs_diff(*y)).max().unwrap_or(0)
}

#[test]
fn hidden_lights_skip_their_shadow_work_after_the_query_latency_and_get_it_back() {
    let gpu = gpu();
    let scene = scene();
    let r = renderer(&gpu, &scene, RendererOptions { width: 160, height: 90, comparison: true, ..Default::default() });
    let frame = r.desktop_frame().expect("the desktop frame");
    let effects = r.desktop_effects().unwrap();
    let lamp_work = [
        "Lighting_ShadowedLights_ShadowProjectionOnOpaque_HiddenLamp",
        "Lighting_ShadowedLights_StandardDeferredLighting_HiddenLamp",
        "ShadowDepths_PerObject_HiddenLamp",
    ];
    let fire_work = [
        "Lighting_ShadowedLights_ShadowProjectionOnOpaque_HiddenFire",
        "Lighting_ShadowedLights_StandardDeferredLighting_HiddenFire",
        "ShadowDepths_Cubemap_HiddenFire",
    ];

    // frame 1 issues the queries; no result yet, so every light renders its shadow
    let first = r.render(true).unwrap();
    assert_eq!(shadow_work(&first, HIDDEN_LAMP), lamp_work, "before any query result");
    assert_eq!(shadow_work(&first, HIDDEN_FIRE), fire_work, "before any query result");
    assert!(frame.shadow_skipped_lights().is_empty());
    assert!(
        effects.occlusion_stats().light_queries >= 5,
        "not every local light is queried: {:?}",
        effects.occlusion_stats()
    );

    // frame 2 reads frame 1's results without waiting: both hidden volumes counted 0 samples,
    // their shadow depths and projections are gone; the lights in the room keep theirs
    let hidden = r.render(true).unwrap();
    assert_eq!(frame.shadow_skipped_lights(), [HIDDEN_LAMP, HIDDEN_FIRE]);
    assert_eq!(
        shadow_work(&hidden, HIDDEN_LAMP),
        Vec::<String>::new(),
        "the stationary light's shadow work was not skipped"
    );
    assert_eq!(
        shadow_work(&hidden, HIDDEN_FIRE),
        Vec::<String>::new(),
        "the movable light's shadow work was not skipped"
    );
    for light in ["CeilingLampA", "CeilingLampB", "FireLight"] {
        assert!(
            images(&hidden).contains(&format!("Lighting_ShadowedLights_ShadowProjectionOnOpaque_{light}")),
            "{light} lost its shadow"
        );
    }
    assert!(steps(&hidden).contains(&"ShadowDepths_Cubemap_FireLight".to_string()));
    // the atlas of per-object shadows is still cleared and dumped (it has no other light)
    assert!(images(&hidden).contains(&"ShadowDepths_Atlas1".to_string()));
    // the movable light's cached static depth was rendered once, in frame 1, and stays cached
    assert_eq!(frame.cached_shadow_rebuilds(), 2, "the two movable lights' caches, each rendered once");

    // the skipped work changes nothing in the image: the same frame with every shadow
    // rendered. Measured on lavapipe: both differences 0 (the hidden lights light no visible
    // pixel, and nothing in these frames moves); the bound allows a rounding step.
    let skipped = r.render(false).unwrap();
    frame.set_shadow_frustum_culling(false);
    let rendered = r.render(true).unwrap();
    assert_eq!(
        shadow_work(&rendered, HIDDEN_FIRE),
        fire_work,
        "the culling switch does not bring the shadow work back"
    );
    frame.set_shadow_frustum_culling(true);
    let skipped_again = r.render(false).unwrap();
    let dir = dump_dir("desktop_shadows_frustum");
    save(&dir, "skipped", &skipped.image);
    save(&dir, "rendered", &rendered.image);
    let (noise, diff) =
        (max_channel_diff(&skipped.image, &skipped_again.image), max_channel_diff(&skipped.image, &rendered.image));
    eprintln!(
        "max channel difference: skipped vs skipped {noise}, skipped vs rendered {diff}; mean {:.4}",
        mean_abs_diff(&skipped.image, &rendered.image)
    );
    assert!(noise <= 1, "two frames with the same settings differ by {noise}");
    assert!(diff <= 1, "skipping the hidden lights' shadows changed the image by up to {diff}");

    // the camera walks round the wall: the stale verdict holds for one more frame (that
    // frame's queries pass), then the shadow work is back
    effects.set_camera(Camera {
        position: Vec3::new(0.0, 2.0, -14.5),
        target: Vec3::new(0.0, 1.2, -9.0),
        fov_y: 60f32.to_radians(),
        near: 0.1,
    });
    let stale = r.render(true).unwrap();
    assert_eq!(shadow_work(&stale, HIDDEN_FIRE), Vec::<String>::new(), "the query result came back without latency");
    let back = r.render(true).unwrap();
    assert!(frame.shadow_skipped_lights().is_empty(), "still skipped: {:?}", frame.shadow_skipped_lights());
    assert_eq!(shadow_work(&back, HIDDEN_LAMP), lamp_work, "the stationary light's shadow did not come back");
    assert_eq!(shadow_work(&back, HIDDEN_FIRE), fire_work, "the movable light's shadow did not come back");
    // its cache was kept while it was skipped: not rendered again
    assert_eq!(frame.cached_shadow_rebuilds(), 2);
}
