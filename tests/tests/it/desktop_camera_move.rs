//! Everything camera-dependent follows the camera from frame to frame: a renderer built at
//! camera C1 that moves to C2 renders what a renderer built at C2 renders. The move goes from
//! outside to inside two light volumes (CeilingLampB, a shadowed stationary point light, and
//! StatueSpot, an unshadowed spot light: their spheres are drawn back faces first from inside,
//! with other depth bounds) and changes the view frustum the directional light's cascades are
//! fitted to (their depth maps, ShadowProjectionOnOpaque, the glass, the volumetric fog and the
//! translucency volumes read them), the fire sprites' view and the translucency volumes' boxes.

use crate::desktop_support::*;
use glam::Vec3;
use kiln_renderer::desktop::effects::EffectOptions;
use kiln_renderer::frame::Image;
use kiln_renderer::scene::{Camera, Scene};
use kiln_renderer::{Renderer, RendererOptions};

const W: u32 = 320;
const H: u32 = 180;
/// Frames before the move, and after it.
const BEFORE: usize = 2;
const AFTER: usize = 3;

/// Inside CeilingLampB's sphere (1.9 m from the lamp, radius 6) and StatueSpot's (6.6 m,
/// radius 8), looking down the room; the bundled camera (C1) is outside both (7.2 m, 12.8 m).
/// Its near plane differs too (0.15 m, C1's 0.1 m: the light grid's depth slices follow it).
fn c2() -> Camera {
    Camera {
        position: Vec3::new(1.0, 2.5, 4.5),
        target: Vec3::new(-2.0, 1.0, -4.0),
        fov_y: 60f32.to_radians(),
        near: 0.15,
    }
}

/// The bundled scene without particle emitters: the fire's particles are simulated from the
/// frame count with random spawns that two renderers do not share.
fn scene() -> Scene {
    let mut scene = Scene::bundled();
    scene.emitters.clear();
    scene
}

/// Every effect on but eye adaptation, whose exposure adapts to the images of the frames
/// before the move (TAA's and the fog's histories are reset at the move, in both renderers).
fn options() -> EffectOptions {
    EffectOptions { eye_adaptation: false, ..EffectOptions::default() }
}

fn render(r: &Renderer) -> Image {
    r.render(false).unwrap_or_else(|e| panic!("{e}")).image
}

fn max_channel_diff(a: &Image, b: &Image) -> u8 {
    a.rgba.iter().zip(&b.rgba).map(|(x, y)| x.abs_diff(*y)).max().unwrap_or(0)
}

#[test]
fn a_moved_camera_renders_what_a_renderer_built_there_renders() {
    let gpu = gpu();
    let size = RendererOptions { width: W, height: H, ..Default::default() };

    // A: built at C1, BEFORE frames there, then moved to C2 (histories reset), AFTER frames
    let moved = renderer(&gpu, &scene(), size.clone());
    let effects = moved.desktop_effects().unwrap();
    effects.set_options(options());
    let mut at_c1 = None;
    for _ in 0..BEFORE {
        at_c1 = Some(render(&moved));
    }
    effects.set_camera(c2());
    effects.reset_history();
    let mut after_move = None;
    for _ in 0..AFTER {
        after_move = Some(render(&moved));
    }
    let (at_c1, after_move) = (at_c1.unwrap(), after_move.unwrap());
    assert_eq!(
        moved.desktop_frame().unwrap().view().position,
        c2().position,
        "the frame's view did not follow the camera"
    );

    // B: built at C2, the same frames with the same reset (TAA jitter, animation time and
    // occlusion query latency are per frame count, so both last frames have the same state)
    let mut scene_c2 = scene();
    scene_c2.camera = c2();
    let fresh = renderer(&gpu, &scene_c2, size);
    let effects = fresh.desktop_effects().unwrap();
    effects.set_options(options());
    for _ in 0..BEFORE {
        render(&fresh);
    }
    effects.reset_history();
    let mut built_at_c2 = None;
    for _ in 0..AFTER {
        built_at_c2 = Some(render(&fresh));
    }
    let built_at_c2 = built_at_c2.unwrap();

    let dir = dump_dir("desktop_camera_move");
    save(&dir, "c1", &at_c1);
    save(&dir, "moved_to_c2", &after_move);
    save(&dir, "built_at_c2", &built_at_c2);

    // the move matters: C1's and C2's images are far apart
    let moved_by = mean_abs_diff(&at_c1, &after_move);
    let (mean, max) = (mean_abs_diff(&after_move, &built_at_c2), max_channel_diff(&after_move, &built_at_c2));
    eprintln!("C1 vs C2: mean {moved_by:.3}; moved vs built at C2: mean {mean:.4}, max {max}");
    assert!(moved_by > 10.0, "C1 and C2 render nearly the same image (mean difference {moved_by})");
    // Measured on lavapipe: mean 0.0000, max 0 (the same image, also after 6 frames). With
    // the light volumes' depth bounds and inside test, the cascades and the fire sprites'
    // view kept from C1 and the occlusion verdicts of C1 surviving the cut (the runtime
    // before this test): mean 3.02, max 149 (the floor under CeilingLampB and the fire's
    // pedestal go dark). Without the occlusion reset alone: mean 0.42, max 38 (props hidden
    // from C1 missing in the first frame at C2, carried on by TAA's history). The bounds
    // allow rounding steps only.
    assert!(
        mean < 0.05 && max <= 4,
        "the moved camera renders another image than a renderer built at C2: mean {mean}, max {max}"
    );
}
