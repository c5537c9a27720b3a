//! The mobile frames (issue 8) on lavapipe: both paths render every pass.

use crate::mobile_support::*;
use kiln_renderer::mobile::{MobileFrame, MobileOptions};
use kiln_renderer::scene::Scene;
use kiln_runtime::Backend;

#[test]
fn forward_frame_runs_its_passes_in_order() {
    let rig = rig(Backend::Vulkan);
    let (passes, image) = rig.render_passes(&Scene::bundled(), MobileOptions::forward(), true);
    let names: Vec<&str> = passes.iter().map(|p| p.name.as_str()).collect();
    assert_eq!(names, ["ShadowDepths", "BasePass", "Translucency", "PostProcessing"]);
    // the frame records the passes its plan declares (whose reads the unit tests check)
    assert_eq!(names, MobileFrame::plan(&MobileOptions::forward()).names());
    assert!(image.distinct_colors() > 500, "a lit scene, not a flat image");
}

#[test]
fn deferred_frame_runs_its_passes_in_order() {
    let rig = rig(Backend::Vulkan);
    let (passes, image) = rig.render_passes(&Scene::bundled(), MobileOptions::deferred(), true);
    let names: Vec<&str> = passes.iter().map(|p| p.name.as_str()).collect();
    assert_eq!(names, ["ShadowDepths", "BasePass", "MobileDeferredShading", "Translucency", "PostProcessing"]);
    assert_eq!(names, MobileFrame::plan(&MobileOptions::deferred()).names());
    let base = &passes[1];
    let images: Vec<&str> = base.images.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(images, ["BasePass", "BasePass_GBufferA", "BasePass_GBufferB", "BasePass_GBufferC"]);
    assert!(image.distinct_colors() > 500, "a lit scene, not a flat image");
}
