//! Precaching a recorded pipeline manifest, and non-blocking pipelines (`Missing`), on
//! lavapipe under the Khronos validation layer.

use std::sync::Arc;
use std::time::{Duration, Instant};

use kiln::archive::usage::Usage;
use kiln::archive::PipelineRecord;
use kiln_renderer::scene::Scene;
use kiln_renderer::{FramePipeline, Renderer, RendererOptions};
use kiln_runtime::pipelines::{
    manifest_keys, Fallback, Missing, PipelineCache, PipelineError, PipelineKey, Ready, RenderKey,
};
use kiln_runtime::{Backend, GpuOptions, ModuleSource, ShaderArchive};

fn gpu() -> kiln_runtime::validation::CheckedGpu {
    kiln_runtime::validation::CheckedGpu::new(&GpuOptions {
        backend: Backend::Vulkan,
        module_source: ModuleSource::Auto,
        timestamps: false,
        validation: true,
    })
    .unwrap_or_else(|e| panic!("render tests need a Vulkan adapter: {e}"))
}

fn archive() -> Arc<ShaderArchive> {
    Arc::new(kiln_renderer::embedded_archive().unwrap())
}

/// The desktop frame's pipelines as a manifest records them (first-use order), recorded
/// from one rendered frame.
fn recorded(gpu: &kiln_runtime::Gpu) -> Vec<PipelineKey> {
    let options = RendererOptions { pipeline: FramePipeline::Desktop, width: 64, height: 36, comparison: false };
    let renderer = Renderer::new(gpu, archive(), &Scene::bundled(), options).unwrap();
    renderer.render(false).unwrap();
    let usage = Usage::parse(&renderer.pipeline_cache().usage().to_text()).unwrap();
    let mut records: Vec<PipelineRecord> =
        usage.records.iter().map(|(key, c)| PipelineRecord { key: key.clone(), first_frame: c.first_frame }).collect();
    records.sort_by(|a, b| (a.first_frame, &a.key).cmp(&(b.first_frame, &b.key)));
    manifest_keys(&records).unwrap()
}

/// Polls `f` until it gives `Some`, for at most a minute.
fn poll<T>(mut f: impl FnMut() -> Option<T>) -> T {
    let start = Instant::now();
    loop {
        if let Some(t) = f() {
            return t;
        }
        assert!(start.elapsed() < Duration::from_secs(60), "nothing after a minute");
        std::thread::sleep(Duration::from_millis(5));
    }
}

fn render_keys(keys: &[PipelineKey]) -> Vec<RenderKey> {
    keys.iter().filter_map(|k| if let PipelineKey::Render(r) = k { Some(r.clone()) } else { None }).collect()
}

#[test]
fn precaching_a_recorded_manifest_creates_every_pipeline_once() {
    let gpu = gpu();
    let keys = recorded(&gpu);
    let renders = render_keys(&keys).len();
    assert!(renders > 10 && keys.len() > renders, "{} keys, {renders} render", keys.len());
    let cache = PipelineCache::new(&gpu, archive());
    let precache = cache.precache(keys.clone());
    // The frame asks for the same keys meanwhile, last first: each is still created once.
    for key in keys.iter().rev() {
        match key {
            PipelineKey::Render(k) => drop(cache.render_key(k).unwrap()),
            PipelineKey::Compute(k) => drop(cache.compute_key(k).unwrap()),
        }
    }
    let progress = poll(|| Some(precache.progress()).filter(|_| precache.finished()));
    assert_eq!((progress.done, progress.failed, progress.total), (keys.len(), 0, keys.len()));
    assert!(precache.wait().is_empty());
    let stats = cache.stats();
    assert_eq!((stats.render_pipelines, stats.compute_pipelines), (renders, keys.len() - renders));
}

#[test]
fn background_skip_is_not_ready_then_exact_and_counts_fallbacks() {
    let gpu = gpu();
    let keys = render_keys(&recorded(&gpu));
    let cache = PipelineCache::new(&gpu, archive());
    cache.set_missing(Missing::Background { fallback: Fallback::Skip });
    assert!(matches!(cache.render_ready(&keys[0]).unwrap(), Ready::NotReady));
    assert_eq!(cache.fallbacks(), 1);
    poll(|| match cache.render_ready(&keys[0]).unwrap() {
        Ready::Exact(p) => Some(p),
        Ready::NotReady => None,
        Ready::Nearest(_) => panic!("no nearest under Skip"),
    });
    let fallbacks = cache.fallbacks();
    assert!(fallbacks >= 1);
    assert!(matches!(cache.render_ready(&keys[0]).unwrap(), Ready::Exact(_)));
    assert_eq!(cache.fallbacks(), fallbacks, "an exact answer is no fallback");
    assert_eq!(cache.stats().render_pipelines, 1, "created once however often it was asked for");
    // The asks are recorded like render_key's.
    assert_eq!(cache.usage().records.len(), 1);
    // Blocking (the default) is exact at once.
    let block = PipelineCache::new(&gpu, archive());
    assert_eq!(block.missing(), Missing::Block);
    assert!(matches!(block.render_ready(&keys[1]).unwrap(), Ready::Exact(_)));
    assert_eq!(block.fallbacks(), 0);
}

#[test]
fn background_nearest_draws_with_a_ready_permutation_of_the_same_shader() {
    let gpu = gpu();
    let archive = archive();
    let keys = render_keys(&recorded(&gpu));
    let cache = PipelineCache::new(&gpu, archive.clone());
    // A recorded pipeline whose fragment permutation has a near one with the same bindings
    // that makes a pipeline with the same vertex permutation and state.
    let same_shader = |a: &str, b: &str| a.split('{').next() == b.split('{').next();
    let (wanted, near) = keys
        .iter()
        .find_map(|k| {
            let f = k.fragment.as_deref()?;
            let bindings = &archive.get(f).ok()?.reflection().bindings;
            archive.archive().nearest(f, 9).ok()?.into_iter().find_map(|n| {
                let p = archive.get(&n.name).ok()?;
                if n.name == f || !same_shader(&n.name, f) || &p.reflection().bindings != bindings {
                    return None;
                }
                let near = RenderKey { fragment: Some(n.name.clone()), ..k.clone() };
                cache.render_key(&near).ok().map(|_| (k.clone(), near))
            })
        })
        .expect("a recorded fragment permutation with a near one of the same bindings");
    cache.set_missing(Missing::Background { fallback: Fallback::Nearest });
    match cache.render_ready(&wanted).unwrap() {
        Ready::Nearest(p) => {
            assert_eq!(p.fragment, near.fragment);
            assert_ne!(p.fragment, wanted.fragment);
            assert_eq!(p.vertex, wanted.vertex);
        }
        other => panic!("expected the nearest ready pipeline, got {other:?}"),
    }
    assert_eq!(cache.fallbacks(), 1);
    poll(|| matches!(cache.render_ready(&wanted).unwrap(), Ready::Exact(_)).then_some(()));
}

#[test]
fn errors_are_errors_in_the_background_and_when_precaching() {
    let gpu = gpu();
    let keys = render_keys(&recorded(&gpu));
    let cache = PipelineCache::new(&gpu, archive());
    cache.set_missing(Missing::Background { fallback: Fallback::Nearest });
    // An unknown permutation is the caller's error at once.
    let unknown = RenderKey { vertex: "NoSuchVS@sm5{}".into(), ..keys[0].clone() };
    assert!(matches!(cache.render_ready(&unknown), Err(PipelineError::Lookup(_))));
    // A state wgpu rejects fails on the worker: the error comes back on a later ask, naming
    // the pipeline, and the next ask tries again.
    let mut bad = keys[0].clone();
    bad.state.sample_count = 3;
    let first = cache.render_ready(&bad).unwrap();
    assert!(matches!(first, Ready::NotReady), "{first:?}");
    let e = poll(|| cache.render_ready(&bad).err());
    assert!(matches!(e, PipelineError::Wgpu { .. }), "{e}");
    assert!(e.to_string().contains(&bad.vertex), "{e}");
    assert!(matches!(cache.render_ready(&bad).unwrap(), Ready::NotReady));
    // Precaching reports it with the pipeline's name, and creates the rest.
    let precache = PipelineCache::new(&gpu, archive())
        .precache([PipelineKey::Render(bad.clone()), PipelineKey::Render(keys[0].clone())]);
    let errors = precache.wait();
    assert_eq!(errors.len(), 1);
    assert!(errors[0].pipeline.contains(&bad.vertex), "{}", errors[0]);
    assert!(matches!(errors[0].error, PipelineError::Wgpu { .. }));
}
