//! Every render permutation of the bundled archive becomes a pipeline on a real device
//! (lavapipe in CI), from SPIR-V passthrough and from WGSL, with layouts from reflection.

use std::sync::Arc;

use kiln::archive::{PermutationRef, ScalarKind};
use kiln::Stage;
use kiln_renderer::gpu_types::formats;
use kiln_runtime::pipelines::{
    Blend, ColorTarget, ComputeKey, DepthState, PipelineCache, PipelineKey, RenderKey, RenderState, VertexLayout,
};
use kiln_runtime::{Backend, GpuOptions, ModuleSource, ShaderArchive};

/// A device, or a failing test that says what to install: a render test never passes by
/// skipping.
fn gpu(module_source: ModuleSource) -> kiln_runtime::validation::CheckedGpu {
    kiln_runtime::validation::CheckedGpu::new(&GpuOptions {
        backend: Backend::Vulkan,
        module_source,
        timestamps: true,
        validation: true,
    })
    .unwrap_or_else(|e| panic!("render tests need a Vulkan adapter: {e}"))
}

/// The vertex shader a fragment permutation runs with in the frames: same interface.
fn partner(archive: &ShaderArchive, fs: &PermutationRef<'_>) -> String {
    let shader = fs.shader();
    let value = |dim: &str| {
        let i = shader.dimensions.iter().position(|d| d.name == dim).unwrap();
        fs.values()[i]
    };
    let q = match shader.name.as_str() {
        // The desktop frame's mesh pixel shaders (runtime/src/desktop); its other pixel shaders
        // read only the pixel position and pair with any full-screen vertex shader.
        "DepthPassPS" => archive.shader("DepthPassVS").level(&shader.level).with("MATERIAL_MASKED", 1),
        "DeferredBasePassPS" => archive.shader("DeferredBasePassVS").level(&shader.level),
        "MobileBasePassPS" => {
            archive.shader("MobileBasePassVS").level(&shader.level).with("USE_VERTEX_FOG", value("USE_VERTEX_FOG"))
        }
        "GPUSpritePS" | "GPUSpriteDistortionPS" => archive.shader("GPUSpriteVS").level(&shader.level),
        "StandardDeferredLightingPS" => {
            // LIGHT_TYPE_DIRECTIONAL is 0; the other lights draw light volumes.
            archive
                .shader("DeferredLightVS")
                .level(&shader.level)
                .with("RADIAL_LIGHT", u32::from(value("LIGHT_TYPE") != 0))
        }
        "MobileRadialLightPS" => archive.shader("MobileDeferredLightVS").level(&shader.level),
        name => {
            // `FooPS` pairs with `FooVS` where the archive has one (the effects' passes, the mobile
            // sky), else with the full-screen vertex shader of its frame.
            let own = name.strip_suffix("PS").map(|stem| format!("{stem}VS"));
            match own.filter(|vs| archive.shader(vs).level(&shader.level).find().is_ok()) {
                Some(vs) => return archive.shader(&vs).level(&shader.level).find().unwrap().name().to_string(),
                None if shader.level == "es3_1" && name.starts_with("Mobile") => {
                    archive.shader("MobileFullscreenVS").level(&shader.level)
                }
                None => archive.shader("ScreenVS").level(&shader.level),
            }
        }
    };
    q.find().unwrap_or_else(|e| panic!("no vertex shader for {}: {e}", fs.name())).name().to_string()
}

fn state_for(vs: &PermutationRef<'_>, fs: Option<&PermutationRef<'_>>) -> RenderState {
    let mesh = !vs.reflection().vertex_inputs.is_empty();
    let mut state = RenderState::triangles(if mesh {
        kiln_renderer::gpu_types::layouts::MESH_INSTANCED
    } else {
        VertexLayout::NONE
    });
    // Depth-only pipelines, and pixel shaders that write only depth (MobileSceneDepthAuxPS).
    if mesh || fs.is_none_or(|f| f.reflection().color_outputs.is_empty()) {
        state = state.with_depth(DepthState::reverse_z(formats::SCENE_DEPTH, true));
    }
    if let Some(fs) = fs {
        let targets: Vec<ColorTarget> = fs
            .reflection()
            .color_outputs
            .iter()
            .map(|o| {
                assert_eq!(o.ty.scalar, ScalarKind::Float, "{}", fs.name());
                // A target with as many channels as the output (Velocity writes two).
                let format = match o.ty.components {
                    1 => wgpu::TextureFormat::R16Float,
                    2 => wgpu::TextureFormat::Rg16Float,
                    _ => formats::SCENE_COLOR,
                };
                ColorTarget::new(format, Blend::Replace)
            })
            .collect();
        state = state.with_targets(&targets);
    }
    state
}

fn create_every_pipeline(module_source: ModuleSource, wanted: impl Fn(&PermutationRef<'_>) -> bool) -> (usize, bool) {
    let gpu = gpu(module_source);
    let archive = Arc::new(kiln_renderer::embedded_archive().unwrap());
    let cache = PipelineCache::new(&gpu, archive.clone());
    let mut created = 0;
    for p in archive.permutations().unwrap().filter(|p| wanted(p)) {
        match p.reflection().stage {
            Stage::Fragment => {
                let vs_name = partner(&archive, &p);
                let vs = archive.get(&vs_name).unwrap();
                cache
                    .render(&vs_name, Some(p.name()), &state_for(&vs, Some(&p)))
                    .unwrap_or_else(|e| panic!("{}: {e}", p.name()));
            }
            Stage::Vertex => {
                cache.render(p.name(), None, &state_for(&p, None)).unwrap_or_else(|e| panic!("{}: {e}", p.name()));
            }
            Stage::Compute => {
                cache.compute(p.name()).unwrap_or_else(|e| panic!("{}: {e}", p.name()));
            }
        }
        created += 1;
    }
    let stats = cache.stats();
    let target =
        if cache.uses_spirv_passthrough() { kiln::archive::Target::Spirv } else { kiln::archive::Target::Wgsl };
    let used: std::collections::HashSet<String> = cache.permutations_used().into_iter().collect();
    let blobs: std::collections::HashSet<_> = archive
        .permutations()
        .unwrap()
        .filter(|p| used.contains(p.name()))
        .map(|p| p.blob_id(target).unwrap())
        .collect();
    // One module per distinct artifact, and for SPIR-V passthrough one per numbering of its
    // bindings by the pipeline layouts it serves (see `kiln_runtime::spirv`).
    if target == kiln::archive::Target::Wgsl {
        assert_eq!(stats.modules, blobs.len(), "one module per distinct artifact");
    } else {
        assert!(stats.modules >= blobs.len(), "{} modules for {} artifacts", stats.modules, blobs.len());
    }
    assert!(archive.permutations().unwrap().filter(|p| wanted(p)).all(|p| used.contains(p.name())));
    (created, cache.uses_spirv_passthrough())
}

/// The permutations the frames create from SPIR-V where the device has passthrough: all.
fn created_from_spirv(_: &PermutationRef<'_>) -> bool {
    true
}

#[test]
fn every_permutation_makes_a_pipeline_from_spirv_passthrough() {
    let (created, passthrough) = create_every_pipeline(ModuleSource::Auto, created_from_spirv);
    assert!(created > 50);
    // lavapipe offers PASSTHROUGH_SHADERS and the embedded archive is trusted.
    assert!(passthrough, "every permutation's module from SPIR-V passthrough");
}

#[test]
fn every_permutation_makes_a_pipeline_from_wgsl() {
    let (created, passthrough) = create_every_pipeline(ModuleSource::Wgsl, |_| true);
    assert!(created > 50);
    assert!(!passthrough);
}

#[test]
fn pipelines_are_cached_per_permutation_and_state() {
    let gpu = gpu(ModuleSource::Auto);
    let archive = Arc::new(kiln_renderer::embedded_archive().unwrap());
    let cache = PipelineCache::new(&gpu, archive);
    let state = RenderState::fullscreen(ColorTarget::new(formats::OUTPUT, Blend::Replace));
    let a = cache.render("ScreenVS@sm5{}", Some("VisualizeDepthPS@sm5{}"), &state).unwrap();
    let b = cache.render("ScreenVS@sm5{}", Some("VisualizeDepthPS@sm5{}"), &state).unwrap();
    assert!(Arc::ptr_eq(&a, &b));
    let other = RenderState::fullscreen(ColorTarget::new(formats::SCENE_COLOR, Blend::Additive));
    let c = cache.render("ScreenVS@sm5{}", Some("VisualizeDepthPS@sm5{}"), &other).unwrap();
    assert!(!Arc::ptr_eq(&a, &c));
    let stats = cache.stats();
    assert_eq!((stats.modules, stats.render_pipelines), (2, 2));
    // Layouts come from reflection: group 1 holds the depth texture the pass draws.
    let names: Vec<_> = a.layout.groups[1].iter().map(|b| b.name.clone().unwrap()).collect();
    assert_eq!(names, ["SourceDepthTexture"]);
    assert_eq!(a.layout.groups[1][0].visibility, wgpu::ShaderStages::FRAGMENT);
    // Bind groups are built by name; a missing resource is named.
    let e = a.layout.bind_group(&gpu.device, 1, "depth input", &[]).unwrap_err().to_string();
    assert_eq!(e, "bind group 1 of `ScreenVS@sm5{} + VisualizeDepthPS@sm5{}`: no resource given for binding 0 `SourceDepthTexture`");
}

#[test]
fn missing_permutation_and_wrong_stage_are_errors() {
    let gpu = gpu(ModuleSource::Auto);
    let cache = PipelineCache::new(&gpu, Arc::new(kiln_renderer::embedded_archive().unwrap()));
    let state = RenderState::fullscreen(ColorTarget::new(formats::OUTPUT, Blend::Replace));
    let e = cache
        .render(
            "PostProcessVS@sm5{}",
            Some("ExponentialHeightFogPS@sm5{SUPPORT_FOG_DIRECTIONAL_LIGHT_INSCATTERING=2}"),
            &state,
        )
        .unwrap_err()
        .to_string();
    assert!(e.starts_with("permutation `ExponentialHeightFogPS@sm5{SUPPORT_FOG_DIRECTIONAL_LIGHT_INSCATTERING=2}` is not in the archive; nearest:"), "{e}");
    assert!(e.contains("SUPPORT_FOG_DIRECTIONAL_LIGHT_INSCATTERING: 2 -> 0"), "{e}");
    let e = cache.render("VisualizeDepthPS@sm5{}", None, &state).unwrap_err().to_string();
    assert_eq!(e, "permutation `VisualizeDepthPS@sm5{}` is a fragment shader, used as a vertex shader");
}

#[test]
fn a_warm_up_from_a_list_of_keys_creates_every_pipeline_once() {
    let gpu = gpu(ModuleSource::Auto);
    let archive = Arc::new(kiln_renderer::embedded_archive().unwrap());
    // The keys of a whole frame, taken from a renderer's cache.
    let renderer = kiln_renderer::Renderer::new(
        &gpu,
        archive.clone(),
        &kiln_renderer::scene::Scene::bundled(),
        kiln_renderer::RendererOptions {
            pipeline: kiln_renderer::FramePipeline::MobileDeferred,
            width: 64,
            height: 32,
            comparison: false,
        },
    )
    .unwrap();
    let keys = renderer.pipeline_cache().keys();
    assert!(keys.iter().any(|k| matches!(k, PipelineKey::Render(_))));
    let cache = PipelineCache::new(&gpu, archive);
    cache.warm_up(&keys).unwrap();
    let stats = cache.stats();
    assert_eq!(stats.render_pipelines + stats.compute_pipelines, keys.len());
    cache.warm_up(&keys).unwrap();
    assert_eq!(cache.stats(), stats, "a second warm-up finds every pipeline");
    // A key naming a permutation the archive lacks fails the warm-up with its name.
    let bad = [PipelineKey::Compute(ComputeKey { compute: "NoSuchCS@sm5{}".into() })];
    let e = cache.warm_up(&bad).unwrap_err().to_string();
    assert!(e.starts_with("permutation `NoSuchCS@sm5{}` is not in the archive"), "{e}");
}

#[test]
fn every_piece_of_fixed_function_state_is_part_of_the_key() {
    let gpu = gpu(ModuleSource::Auto);
    let cache = PipelineCache::new(&gpu, Arc::new(kiln_renderer::embedded_archive().unwrap()));
    let base = RenderState::fullscreen(ColorTarget::new(formats::SCENE_COLOR, Blend::Replace));
    let depth = DepthState::reverse_z(formats::SCENE_DEPTH, false);
    let variants = [
        base.clone(),
        base.clone().with_cull(Some(wgpu::Face::Front)),
        base.clone().with_targets(&[ColorTarget::new(formats::SCENE_COLOR, Blend::Additive)]),
        base.clone().with_targets(&[
            ColorTarget::new(formats::SCENE_COLOR, Blend::Replace).with_write_mask(wgpu::ColorWrites::RED)
        ]),
        base.clone().with_depth(depth),
        base.clone().with_depth(DepthState { slope_scale_bits: 2.0f32.to_bits(), ..depth }),
        base.clone().with_depth(DepthState { bias: 4, ..depth }),
        base.clone().with_depth(DepthState { write: true, ..depth }),
    ];
    let mut seen = Vec::new();
    for state in &variants {
        let p = cache.render("ScreenVS@sm5{}", Some("VisualizeDepthPS@sm5{}"), state).unwrap();
        assert!(!seen.iter().any(|q| Arc::ptr_eq(q, &p)), "{state:?} shares a pipeline with another state");
        seen.push(p);
    }
    assert_eq!(cache.stats().render_pipelines, variants.len());
    // The same state described in wgpu's terms is the same key.
    let wgpu_depth = wgpu::DepthStencilState {
        format: formats::SCENE_DEPTH,
        depth_write_enabled: Some(false),
        depth_compare: Some(wgpu::CompareFunction::GreaterEqual),
        stencil: Default::default(),
        bias: Default::default(),
    };
    let target =
        wgpu::ColorTargetState { format: formats::SCENE_COLOR, blend: None, write_mask: wgpu::ColorWrites::ALL };
    let from_wgpu = RenderState::from_wgpu(VertexLayout::NONE, None, Some(&wgpu_depth), &[target], 1);
    let key = RenderKey {
        vertex: "ScreenVS@sm5{}".into(),
        fragment: Some("VisualizeDepthPS@sm5{}".into()),
        state: from_wgpu,
    };
    assert!(Arc::ptr_eq(&cache.render_key(&key).unwrap(), &seen[4]));
}

#[test]
fn the_driver_pipeline_cache_persists_per_adapter_and_a_corrupt_file_is_ignored() {
    let gpu = gpu(ModuleSource::Auto);
    let dir = tempfile::tempdir().unwrap();
    let archive = Arc::new(kiln_renderer::embedded_archive().unwrap());
    let key = gpu.pipeline_cache_key().expect("lavapipe offers PIPELINE_CACHE");
    let state = RenderState::fullscreen(ColorTarget::new(formats::OUTPUT, Blend::Replace));
    let (cache, warning) = PipelineCache::with_disk_cache(&gpu, archive.clone(), dir.path());
    assert_eq!(warning, None, "no file yet is no warning");
    assert!(cache.has_disk_cache());
    cache.render("ScreenVS@sm5{}", Some("VisualizeDepthPS@sm5{}"), &state).unwrap();
    let path = cache.save().unwrap().expect("lavapipe gives cache data");
    assert_eq!(path, dir.path().join(&key));
    let saved = std::fs::read(&path).unwrap();
    // Nothing but the file itself is left in the folder (temp file renamed over it).
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    let (again, warning) = PipelineCache::with_disk_cache(&gpu, archive.clone(), dir.path());
    assert_eq!(warning, None);
    again.render("ScreenVS@sm5{}", Some("VisualizeDepthPS@sm5{}"), &state).unwrap();
    // A flipped byte, a truncated file and a foreign file: a warning naming the file, then an
    // empty cache that still makes pipelines.
    let mut flipped = saved.clone();
    *flipped.last_mut().unwrap() ^= 0x40;
    for (bytes, why) in
        [(flipped, "checksum does not match"), (saved[..20].to_vec(), "truncated"), (b"hello".to_vec(), "not a Kiln")]
    {
        std::fs::write(&path, &bytes).unwrap();
        let (cache, warning) = PipelineCache::with_disk_cache(&gpu, archive.clone(), dir.path());
        let warning = warning.expect("a corrupt file is a warning");
        assert!(warning.contains(why) && warning.contains(&key), "{warning}");
        assert!(cache.has_disk_cache());
        cache.render("ScreenVS@sm5{}", Some("VisualizeDepthPS@sm5{}"), &state).unwrap();
        cache.save().unwrap();
        assert_eq!(std::fs::read(&path).unwrap()[..8], saved[..8], "rewritten whole");
    }
}
