//! The volumes of the desktop frame (VolumetricFog's froxels, the translucency lighting
//! volumes) on wgpu's GL backend: 2D array textures with one layer per depth slice, which GL
//! binds layered, so the volumetric fog and the volume-lit glass render on GL as on Vulkan.
//! (As 3D textures, GL bound one slice of each storage volume and the fog turned the frame
//! black.)

use std::sync::Arc;

use crate::desktop_support::*;
use crate::support::psnr;
use kiln_renderer::desktop::effects::{EffectOptions, TranslucencyLightingMode};
use kiln_renderer::frame::Image;
use kiln_renderer::scene::Scene;
use kiln_renderer::{Renderer, RendererOptions};
use kiln_runtime::gpu::{Backend, ModuleSource};
use kiln_runtime::{Gpu, GpuOptions};

const W: u32 = 320;
const H: u32 = 180;

fn device(backend: Backend) -> kiln_runtime::validation::CheckedGpu {
    kiln_runtime::validation::CheckedGpu::new(&GpuOptions {
        backend,
        module_source: ModuleSource::Auto,
        timestamps: false,
        validation: true,
    })
    .unwrap_or_else(|e| panic!("this test needs a {backend} adapter: {e}"))
}

/// One still frame (nothing moves, no TAA, motion blur, eye adaptation or reflections) with
/// the volumetric fog applied (`fog`), the glass lit by the volumes and the sprites (the
/// smoke lit by the volumes).
fn frame(gpu: &Gpu, fog: bool) -> (Image, Vec<(String, Image)>) {
    let r = Renderer::new(
        gpu,
        Arc::new(kiln_renderer::embedded_archive().unwrap()),
        &Scene::bundled(),
        RendererOptions { width: W, height: H, ..Default::default() },
    )
    .unwrap_or_else(|e| panic!("{e}"));
    r.desktop_effects().expect("the desktop frame's effects").set_options(EffectOptions {
        taa: false,
        motion_blur: false,
        eye_adaptation: false,
        animate: false,
        reflections: false,
        volumetric_fog: fog,
        fog_density: 0.03,
        translucency_lighting: TranslucencyLightingMode::SurfaceLightingVolume,
        ..EffectOptions::default()
    });
    let out = r.render(true).unwrap_or_else(|e| panic!("{e}"));
    (out.image, out.passes.into_iter().flat_map(|p| p.images).collect())
}

fn named<'a>(images: &'a [(String, Image)], name: &str) -> &'a Image {
    images.iter().find(|(n, _)| n == name).map(|(_, i)| i).unwrap_or_else(|| panic!("no image `{name}`"))
}

/// Vulkan and GL render the frame with the volumetric fog applied and the glass and smoke lit
/// by the volumes alike: every volume step's capture, the glass and the sprites within the
/// per-pass bound of the GL/Vulkan comparison (35 dB), the output within 40 dB; the fog
/// itself is far above that difference (the frame without it is a control that must differ).
///
/// Measured on llvmpipe/lavapipe: the five volume steps and the separate translucency
/// identical (inf dB), the sprites 92.7 dB, the output 50.2 dB; the control (Vulkan without
/// the fog against GL with it) 19.3 dB.
#[test]
fn volumetric_fog_and_volume_lit_glass_render_on_gl_like_on_vulkan() {
    let (vk, gl) = (device(Backend::Vulkan), device(Backend::Gl));
    let (vk_image, vk_steps) = frame(&vk, true);
    let (gl_image, gl_steps) = frame(&gl, true);
    let (vk_no_fog, _) = frame(&vk, false);
    let dir = dump_dir("desktop_volumes_gl");
    save(&dir, "vulkan", &vk_image);
    save(&dir, "gl", &gl_image);
    save(&dir, "vulkan_without_fog", &vk_no_fog);
    for step in [
        "VolumetricFog_InitializeVolumeAttributes",
        "VolumetricFog_LightScattering",
        "VolumetricFog_FinalIntegration",
        "Lighting_InjectTranslucentVolume",
        "Lighting_FilterTranslucentVolume",
        "Translucency_SeparateTranslucency",
        "Translucency_ParticleSprites",
    ] {
        let p = psnr(named(&vk_steps, step), named(&gl_steps, step));
        eprintln!("{step}: Vulkan vs GL {p:.1} dB");
        assert!(p > 35.0, "{step}: Vulkan vs GL {p:.1} dB");
    }
    let p = psnr(&vk_image, &gl_image);
    let control = psnr(&vk_no_fog, &gl_image);
    eprintln!("output: Vulkan vs GL {p:.1} dB; control (Vulkan without the fog) {control:.1} dB");
    assert!(p > 40.0, "the frame with the volumetric fog differs between Vulkan and GL: {p:.1} dB");
    assert!(control < p - 10.0, "the volumetric fog hardly changes the frame ({control:.1} dB against {p:.1} dB)");
}
