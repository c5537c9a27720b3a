//! Issue 25, section 4 (the renderer's side): the passes hold pipeline keys and ask the cache
//! for each pipeline when they record a draw. A renderer built with `Creation::Lazy` creates
//! no render pipeline when it is built; with the cache's blocking lookup its frames are
//! byte-identical to those of a renderer that created every pipeline up front.

use std::sync::Arc;

use kiln_renderer::frame::Creation;
use kiln_renderer::scene::Scene;
use kiln_renderer::{FramePipeline, Renderer, RendererOptions};
use kiln_runtime::pipelines::PipelineCache;
use kiln_runtime::{Backend, GpuOptions, ModuleSource};

/// The first two frames of a fresh renderer built as `creation` says, and the cache's
/// counts when it was built and after the frames.
fn frames(
    gpu: &kiln_runtime::Gpu,
    pipeline: FramePipeline,
    creation: Creation,
) -> (Vec<Vec<u8>>, kiln_runtime::pipelines::CacheStats, kiln_runtime::pipelines::CacheStats) {
    let archive = Arc::new(kiln_renderer::embedded_archive().unwrap());
    let options = RendererOptions { pipeline, width: 64, height: 36, comparison: false };
    let cache = PipelineCache::new(gpu, archive);
    let renderer = Renderer::with_creation(gpu, cache, &Scene::bundled(), options, creation)
        .unwrap_or_else(|e| panic!("{pipeline:?} {creation:?}: {e}"));
    let built = renderer.cache_stats();
    let images = (0..2)
        .map(|_| renderer.render(false).unwrap_or_else(|e| panic!("{pipeline:?} {creation:?}: {e}")).image.rgba)
        .collect();
    (images, built, renderer.cache_stats())
}

#[test]
fn a_lazy_renderer_creates_its_pipelines_as_frames_ask_and_draws_the_same_frames() {
    let gpu = kiln_runtime::validation::CheckedGpu::new(&GpuOptions {
        backend: Backend::Vulkan,
        module_source: ModuleSource::Auto,
        timestamps: false,
        validation: true,
    })
    .unwrap_or_else(|e| panic!("render tests need a Vulkan adapter: {e}"));
    for pipeline in FramePipeline::ALL {
        let (eager, eager_built, eager_after) = frames(&gpu, pipeline, Creation::Eager);
        let (lazy, lazy_built, lazy_after) = frames(&gpu, pipeline, Creation::Lazy);
        // Eager: every pipeline exists before the first frame, and frames create none.
        assert!(eager_built.render_pipelines > 0, "{pipeline:?}: {eager_built:?}");
        assert_eq!(eager_after, eager_built, "{pipeline:?}: a frame created a pipeline");
        // Lazy: no render pipeline before the first frame (only the particles' prewarm,
        // which runs while the desktop frame is built, creates its compute pipeline).
        assert_eq!(lazy_built.render_pipelines, 0, "{pipeline:?}: {lazy_built:?}");
        assert!(lazy_built.compute_pipelines <= 1, "{pipeline:?}: {lazy_built:?}");
        // The frames created what they drew: never more than the eager renderer made.
        assert!(lazy_after.render_pipelines > 0, "{pipeline:?}: {lazy_after:?}");
        assert!(lazy_after.render_pipelines <= eager_built.render_pipelines, "{pipeline:?}: {lazy_after:?}");
        assert!(lazy_after.compute_pipelines <= eager_built.compute_pipelines, "{pipeline:?}: {lazy_after:?}");
        // Same bytes, frame by frame.
        for (i, (e, l)) in eager.iter().zip(&lazy).enumerate() {
            assert!(e == l, "{pipeline:?}: frame {i} differs between eager and lazy pipelines");
        }
        gpu.check();
    }
}
