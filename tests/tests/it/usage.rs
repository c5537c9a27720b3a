//! Usage recording: the bundled frames' recorded pipelines, merged in any order, give the
//! same bytes.

use std::sync::Arc;

use kiln::archive::usage::{Usage, UsageKey};
use kiln_renderer::scene::Scene;
use kiln_renderer::{FramePipeline, Renderer, RendererOptions};
use kiln_runtime::{Backend, GpuOptions, LookupError, ModuleSource, ShaderArchive};

/// The usage file of `frames` frames of `pipeline`, as `kiln-view --record-usage` writes it.
fn record(gpu: &kiln_runtime::Gpu, pipeline: FramePipeline, frames: u32) -> String {
    let archive = Arc::new(kiln_renderer::embedded_archive().unwrap());
    render(gpu, archive, pipeline, frames).1
}

/// The last of `frames` frames of `pipeline` from `archive`, and the usage file of them.
fn render(
    gpu: &kiln_runtime::Gpu,
    archive: Arc<ShaderArchive>,
    pipeline: FramePipeline,
    frames: u32,
) -> (Vec<u8>, String) {
    let options = RendererOptions { pipeline, width: 64, height: 36, comparison: false };
    let renderer = Renderer::new(gpu, archive, &Scene::bundled(), options).unwrap();
    let mut image = Vec::new();
    for _ in 0..frames {
        image = renderer.render(false).unwrap().image.rgba;
        renderer.pipeline_cache().next_frame();
    }
    assert_eq!(renderer.pipeline_cache().frame(), u64::from(frames));
    (image, renderer.pipeline_cache().usage().to_text())
}

fn gpu(module_source: ModuleSource) -> kiln_runtime::validation::CheckedGpu {
    kiln_runtime::validation::CheckedGpu::new(&GpuOptions {
        backend: Backend::Vulkan,
        module_source,
        timestamps: false,
        validation: true,
    })
    .unwrap_or_else(|e| panic!("render tests need a Vulkan adapter: {e}"))
}

#[test]
fn every_recorded_render_state_reads_back_to_its_text() {
    use kiln_runtime::pipelines::{state_text, RenderState};
    let gpu = gpu(ModuleSource::Auto);
    let mut states = std::collections::BTreeSet::new();
    for pipeline in [FramePipeline::Desktop, FramePipeline::MobileForward, FramePipeline::MobileDeferred] {
        let usage = Usage::parse(&record(&gpu, pipeline, 1)).unwrap();
        for key in usage.records.keys() {
            if let UsageKey::Render { state, .. } = key {
                states.insert(state.clone());
            }
        }
    }
    // The frames draw with many states: depth only, blending, stencil, vertex layouts.
    assert!(states.len() >= 10, "{states:?}");
    assert!(states.iter().any(|s| s.contains("stencil=")) || states.iter().any(|s| s.contains("depth=-")));
    for text in &states {
        let state = RenderState::from_state_text(text).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(&state_text(&state), text);
    }
}

#[test]
fn recorded_frames_merge_in_any_order_to_the_same_bytes() {
    let gpu = gpu(ModuleSource::Auto);
    let runs = [
        record(&gpu, FramePipeline::Desktop, 2),
        record(&gpu, FramePipeline::MobileForward, 1),
        record(&gpu, FramePipeline::MobileDeferred, 2),
    ];
    let parsed: Vec<Usage> = runs.iter().map(|t| Usage::parse(t).unwrap()).collect();
    for (text, usage) in runs.iter().zip(&parsed) {
        // Each file reads back to itself, sorted, one record a line, with the archive's hash.
        assert_eq!(&usage.to_text(), text);
        assert_eq!(usage.runs, 1);
        assert_eq!(usage.archive, kiln_renderer::embedded_archive().unwrap().archive().content_hash());
        assert!(text.lines().all(|l| !l.is_empty()));
    }
    // The desktop frame asks for render and compute pipelines at sm5; the mobile ones at es3_1.
    let desktop = &parsed[0];
    assert!(desktop.records.keys().any(|k| matches!(k, UsageKey::Compute { .. })));
    assert!(desktop.permutations().iter().all(|p| p.contains("@sm5{")), "{:?}", desktop.permutations());
    assert!(parsed[1].permutations().iter().all(|p| p.contains("@es3_1{")));
    assert!(parsed[2].permutations().iter().any(|p| p.contains("DEFERRED_SHADING_PATH=1")));

    let orders = [[0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]];
    let merged: Vec<String> = orders
        .iter()
        .map(|o| {
            // Left to right for some orders, right-nested for others: associative too.
            let mut m = parsed[o[0]].clone();
            if o[0] % 2 == 0 {
                m.merge(&parsed[o[1]]).unwrap();
                m.merge(&parsed[o[2]]).unwrap();
            } else {
                let mut rest = parsed[o[1]].clone();
                rest.merge(&parsed[o[2]]).unwrap();
                m.merge(&rest).unwrap();
            }
            m.to_text()
        })
        .collect();
    assert!(merged.iter().all(|m| *m == merged[0]));
    let all = Usage::parse(&merged[0]).unwrap();
    assert_eq!(all.runs, 3);
    let records: usize = parsed.iter().map(|u| u.records.len()).sum();
    // The frames share a few pipelines (the full-screen copies): never more than the sum.
    assert!(all.records.len() <= records && all.records.len() >= parsed[0].records.len());
    // This renderer creates its pipelines when it is built: frame 0 asks, once.
    assert!(all.records.values().all(|c| c.first_frame == 0));
}

#[test]
fn a_usage_only_build_compiles_the_recorded_keys_and_draws_the_same_frame() {
    // WGSL on both sides: the embedded archive is trusted (SPIR-V passthrough), a file is not.
    let gpu = gpu(ModuleSource::Wgsl);
    let full = Arc::new(kiln_renderer::embedded_archive().unwrap());
    let (full_frame, recorded) = render(&gpu, full.clone(), FramePipeline::MobileForward, 1);
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("frame.usage"), &recorded).unwrap();
    let usage = Usage::parse(&recorded).unwrap();

    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let options = kiln::build::Options {
        config: root.join("permutations.toml"),
        output: Some(dir.path().join("partial.kpak")),
        cache: kiln::build::CacheDir::Disabled,
        usage: vec![dir.path().join("frame.usage")],
        usage_only: true,
        jobs: Some(2),
        ..kiln::build::Options::default()
    };
    let report = kiln::build::run(&options).unwrap_or_else(|e| panic!("{e}"));
    let s = &report.stats;
    // Exactly the recorded permutations, each distinct key compiled once; the rest left out.
    assert_eq!(s.permutations, usage.permutations().len());
    assert_eq!(s.used, Some(s.permutations));
    assert_eq!(s.permutations + s.left_out.unwrap(), full.archive().permutation_count());
    assert_eq!(s.compiled, s.unique_sources);
    assert!(s.unique_sources <= s.permutations && s.permutations < full.archive().permutation_count() / 10, "{s:?}");
    // The distinct keys are the recorded permutations' distinct artifacts in the full archive.
    let distinct: std::collections::HashSet<_> =
        usage.permutations().iter().map(|n| full.get(n).unwrap().blob_id(kiln::Target::Wgsl).unwrap()).collect();
    assert_eq!(s.unique_sources, distinct.len());
    let per_shader = s.shaders.as_ref().unwrap();
    assert_eq!(per_shader["MobileBasePassPS"].left_out + per_shader["MobileBasePassPS"].used, 484);

    let partial = Arc::new(ShaderArchive::open(&dir.path().join("partial.kpak")).unwrap());
    assert_eq!(partial.archive().permutation_count(), s.permutations);
    let (partial_frame, again) = render(&gpu, partial.clone(), FramePipeline::MobileForward, 1);
    assert!(partial_frame == full_frame, "the frame from the partial archive differs");
    assert_eq!(Usage::parse(&again).unwrap().permutations(), usage.permutations());

    // A left-out permutation is an error naming it, never a substitute.
    let left_out = "DepthPassVS@sm5{MATERIAL_MASKED=0}";
    assert!(full.get(left_out).is_ok());
    let Err(e) = partial.get(left_out) else { panic!("{left_out} was found") };
    assert!(matches!(&e, LookupError::LeftOut { name } if name == left_out), "{e}");
    assert!(e.to_string().contains("was left out of this archive by `kiln build --usage-only`"), "{e}");
    // A name that never was a permutation is still missing, not left out.
    assert!(matches!(partial.get("DepthPassVS@sm5{MATERIAL_MASKED=7}"), Err(LookupError::Missing { .. })));
}
