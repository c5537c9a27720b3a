//! The desktop frame's effects: every pass appears in frame order among the core
//! ones, with a non-trivial image, over several frames.

use crate::desktop_support::*;
use kiln_renderer::scene::Scene;
use kiln_renderer::RendererOptions;

/// The passes and steps of the effects, as dumped (`Pass` or `Pass_Step`).
const PART2_IMAGES: &[&str] = &[
    "ParticleSimulation_Position",
    "ParticleSimulation_Velocity",
    "BeginOcclusionTests",
    "BuildHZB",
    "VolumetricFog_InitializeVolumeAttributes",
    "VolumetricFog_LightScattering",
    "VolumetricFog_FinalIntegration",
    "BasePass_ParticleCollision",
    "Velocity",
    "Lighting_InjectTranslucentVolume",
    "Lighting_FilterTranslucentVolume",
    "Reflections_ScreenSpaceReflections",
    "Reflections_ReflectionEnvironmentAndSky",
    "ExponentialHeightFog_VolumetricFog",
    "Translucency_ParticleSprites",
    "Distortion_DistortionAccum",
    "Distortion_DistortionApply",
    "PostProcessing_TAA",
    "PostProcessing_EyeAdaptation",
    "PostProcessing_MotionBlur",
];

#[test]
fn every_effect_pass_is_dumped_in_frame_order_with_a_non_trivial_image() {
    let gpu = gpu();
    let scene = Scene::bundled();
    let r = renderer(&gpu, &scene, RendererOptions { width: 320, height: 180, ..Default::default() });
    let dir = dump_dir("desktop_passes");
    let mut last = None;
    for _ in 0..4 {
        last = Some(r.render(true).unwrap_or_else(|e| panic!("{e}")));
    }
    let frame = last.unwrap();
    let mut names = Vec::new();
    for p in &frame.passes {
        for (name, image) in &p.images {
            save(&dir, name, image);
            names.push((name.clone(), image.clone()));
        }
    }
    save(&dir, "Output", &frame.image);
    let mut previous = 0;
    for wanted in PART2_IMAGES {
        let Some(index) = names.iter().position(|(n, _)| n == wanted) else {
            panic!(
                "no image `{wanted}`; the frame dumped: {:?}",
                names.iter().map(|(n, _)| n.as_str()).collect::<Vec<_>>()
            );
        };
        assert!(index >= previous, "`{wanted}` is out of frame order");
        previous = index;
        let image = &names[index].1;
        assert!(
            image.distinct_colors() > 1 && luma_stddev(image) > 0.5,
            "`{wanted}` is a flat image ({} colours, luma stddev {:.2})",
            image.distinct_colors(),
            luma_stddev(image)
        );
    }
    for p in &frame.passes {
        if gpu.timestamps {
            assert!(p.gpu_ms.is_some(), "pass {} has no GPU time", p.name);
        }
    }
}
