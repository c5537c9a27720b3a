//! Usage recording: the bundled frames' recorded pipelines, merged in any order, give the
//! same bytes.

use std::sync::Arc;

use kiln::archive::usage::{Usage, UsageKey};
use kiln_renderer::scene::Scene;
use kiln_renderer::{FramePipeline, Renderer, RendererOptions};
use kiln_runtime::{Backend, GpuOptions, ModuleSource};

/// The usage file of `frames` frames of `pipeline`, as `kiln-view --record-usage` writes it.
fn record(gpu: &kiln_runtime::Gpu, pipeline: FramePipeline, frames: u32) -> String {
    let archive = Arc::new(kiln_renderer::embedded_archive().unwrap());
    let options = RendererOptions { pipeline, width: 64, height: 36, comparison: false };
    let renderer = Renderer::new(gpu, archive, &Scene::bundled(), options).unwrap();
    for _ in 0..frames {
        renderer.render(false).unwrap();
        renderer.pipeline_cache().next_frame();
    }
    assert_eq!(renderer.pipeline_cache().frame(), u64::from(frames));
    renderer.pipeline_cache().usage().to_text()
}

#[test]
fn recorded_frames_merge_in_any_order_to_the_same_bytes() {
    let gpu = kiln_runtime::validation::CheckedGpu::new(&GpuOptions {
        backend: Backend::Vulkan,
        module_source: ModuleSource::Auto,
        timestamps: false,
        validation: true,
    })
    .unwrap_or_else(|e| panic!("render tests need a Vulkan adapter: {e}"));
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
