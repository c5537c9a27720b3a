//! Forward and deferred mobile frames of the same scene agree with each other and with the
//! desktop frame when the effects one of them lacks are off; each threshold is checked
//! against a control frame that must fall below it, so it separates right from wrong.

use std::sync::Arc;

use crate::mobile_support::*;
use kiln_renderer::mobile::{MobileOptions, ShadingPath};
use kiln_renderer::scene::Scene;
use kiln_renderer::{FramePipeline, Renderer, RendererOptions};
use kiln_runtime::Backend;

/// The bundled scene with its four local lights (three points, one spot), no fog and no
/// translucent meshes.
fn comparable_scene() -> Scene {
    let mut scene = Scene::bundled();
    scene.fog.density = 0.0;
    scene.objects.retain(|o| o.name != "GlassStatues");
    scene.emitters.clear();
    assert_eq!(scene.point_lights.len() + scene.spot_lights.len(), 4, "the comparison scene has four local lights");
    scene
}

/// Forward and deferred differ by GBuffer quantization only (8-bit octahedral normals and
/// base color): about 55 dB on lavapipe. Dropping the four local lights from one of them
/// (about 32 dB) falls below the threshold by 5 dB or more.
const FORWARD_DEFERRED_PSNR: f64 = 40.0;

#[test]
fn forward_and_deferred_agree_with_four_local_lights() {
    let rig = rig(Backend::Vulkan);
    let scene = comparable_scene();
    let forward = rig.render(&scene, MobileOptions::comparable(ShadingPath::Forward));
    let deferred = rig.render(&scene, MobileOptions::comparable(ShadingPath::Deferred));
    let unlit = rig.render(
        &scene,
        MobileOptions { local_light_limit: Some(0), ..MobileOptions::comparable(ShadingPath::Deferred) },
    );
    let (same, control) = (psnr(&forward, &deferred), psnr(&forward, &unlit));
    eprintln!("forward/deferred {same:.1} dB; forward/deferred without local lights {control:.1} dB");
    assert!(same > FORWARD_DEFERRED_PSNR, "forward/deferred PSNR {same:.1} dB");
    assert!(control < FORWARD_DEFERRED_PSNR - 5.0, "the control frame should differ: {control:.1} dB");
}

fn desktop(rig: &Rig, scene: &Scene) -> kiln_renderer::frame::Image {
    let archive = Arc::new(kiln_renderer::embedded_archive().unwrap());
    let renderer = Renderer::new(
        &rig.gpu,
        archive,
        scene,
        RendererOptions { pipeline: FramePipeline::Desktop, width: WIDTH, height: HEIGHT, comparison: true },
    )
    .unwrap_or_else(|e| panic!("desktop frame: {e}"));
    renderer.render(false).unwrap_or_else(|e| panic!("desktop frame: {e}")).image
}

/// Desktop and mobile share the scene, the light units and the shadowing, not the BRDF
/// (GGX with Smith visibility against the mobile GGX approximation and EnvBRDFApprox), the
/// sky (a flat color against the procedural sky) nor the ambient term: with the renderer's
/// comparison settings (the desktop effects the mobile frames lack off) they agree to 22.1 dB
/// on lavapipe. The control frame (the mobile frame without its sun, 14.6 dB) is below the
/// threshold by 3 dB or more.
const DESKTOP_PSNR: f64 = 19.0;

#[test]
fn mobile_frames_agree_with_the_desktop_frame() {
    let rig = rig(Backend::Vulkan);
    let scene = comparable_scene();
    let reference = desktop(&rig, &scene);
    let mut dark = scene.clone();
    dark.sun.enabled = false;
    let control = psnr(&reference, &rig.render(&dark, MobileOptions::comparable(ShadingPath::Forward)));
    for path in [ShadingPath::Forward, ShadingPath::Deferred] {
        let p = psnr(&reference, &rig.render(&scene, MobileOptions::comparable(path)));
        eprintln!("desktop/{} {p:.1} dB (control without the sun {control:.1} dB)", path.name());
        assert!(p > DESKTOP_PSNR, "desktop/{} PSNR {p:.1} dB", path.name());
    }
    assert!(control < DESKTOP_PSNR - 3.0, "the control frame should differ: {control:.1} dB");
}
