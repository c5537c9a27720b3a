//! What a frame gets when a pipeline it asks for is not created yet ([`Missing`]), and the
//! machinery every creation shares: an in-flight set, so that one key is created once
//! however many threads ask (the render thread, [`PipelineCache::precache`]'s workers, the
//! background workers), and bounded background workers for [`Missing::Background`].
//!
//! The shared state lives in [`super::inflight`]. Workers hold a view of the cache ([`PipelineCache::worker`]) that shares its maps, so
//! what they create is found by the render thread's next ask. wgpu's error scopes are per
//! thread here (wgpu 30 with `std`), so a worker's creation errors are caught by the scopes
//! the worker pushes: they come back to the caller as a [`PipelineError`] on its next ask for
//! that key, never as a panic (a panic inside a creation is caught and turned into one too).

use std::sync::atomic::Ordering;
use std::sync::Arc;

use kiln_archive::Stage;

use super::cache::{ComputePipeline, PipelineCache, RenderPipeline};
use super::inflight::{lock, max_workers};
use super::{ComputeKey, PipelineError, PipelineKey, RenderKey};

/// What a frame gets when a pipeline it asks for is not created yet.
#[non_exhaustive]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Missing {
    /// Create it on the asking thread, then draw: images are exact (the default).
    #[default]
    Block,
    /// Create it on a worker thread; meanwhile the frame does what `fallback` says.
    Background {
        /// Skip the draw, or draw with the nearest ready permutation.
        fallback: Fallback,
    },
}

/// Under [`Missing::Background`]: skip the draw, or draw with the nearest ready permutation.
#[non_exhaustive]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Fallback {
    /// Nothing is drawn until the pipeline is ready.
    Skip,
    /// A ready pipeline of the same state whose permutations are the archive's nearest
    /// (`Archive::nearest`) of the same shaders, with the same bindings.
    Nearest,
}

/// The answer of a non-blocking lookup.
pub enum Ready<T> {
    /// The pipeline asked for.
    Exact(Arc<T>),
    /// Another ready pipeline to draw with meanwhile ([`Fallback::Nearest`]).
    Nearest(Arc<T>),
    /// Nothing to draw with yet.
    NotReady,
}

impl<T> std::fmt::Debug for Ready<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Ready::Exact(_) => "Exact",
            Ready::Nearest(_) => "Nearest",
            Ready::NotReady => "NotReady",
        })
    }
}

/// How many nearest permutations of one are tried for a [`Fallback::Nearest`] answer.
const NEAR: usize = 8;

impl PipelineCache {
    /// What a frame gets when a pipeline is not created yet (see [`Missing`]).
    pub fn set_missing(&self, missing: Missing) {
        *lock(&self.background.missing) = missing;
    }

    /// The current [`Missing`] mode.
    pub fn missing(&self) -> Missing {
        *lock(&self.background.missing)
    }

    /// `Nearest` and `NotReady` answers so far (a renderer asks once per draw, so this
    /// counts draws).
    pub fn fallbacks(&self) -> u64 {
        self.background.fallbacks.load(Ordering::Relaxed)
    }

    /// Like [`PipelineCache::render_key`] (records usage the same way). Under
    /// [`Missing::Block`]: creates if needed and returns `Exact`. Under
    /// [`Missing::Background`]: `Exact` if created; otherwise starts creating it on a worker
    /// thread (once per key) and returns `Nearest(p)` ([`Fallback::Nearest`], and such a
    /// ready pipeline exists) or `NotReady`. An error of an earlier background creation of
    /// the key is returned once; the next ask tries again.
    pub fn render_ready(&self, key: &RenderKey) -> Result<Ready<RenderPipeline>, PipelineError> {
        let Missing::Background { fallback } = self.missing() else {
            return self.render_key(key).map(Ready::Exact);
        };
        let found = {
            let mut inner = self.lock();
            inner.recorder.render(key);
            inner.render.get(key).cloned()
        };
        if let Some(p) = found {
            return Ok(Ready::Exact(p));
        }
        // The permutations must exist and be of the right stages: that is the caller's
        // error now, not a fallback.
        self.reflection(&key.vertex, Stage::Vertex)?;
        if let Some(f) = &key.fragment {
            self.reflection(f, Stage::Fragment)?;
        }
        let pkey = PipelineKey::Render(key.clone());
        if let Some(e) = lock(&self.background.failed).remove(&pkey) {
            return Err(e);
        }
        self.start(pkey.clone());
        let near = match fallback {
            Fallback::Nearest => self.nearest_render(key)?,
            Fallback::Skip => None,
        };
        self.fell_back(&pkey, near.as_ref().map(|p| format!("{} + {:?}", p.vertex, p.fragment)));
        Ok(near.map_or(Ready::NotReady, Ready::Nearest))
    }

    /// The compute twin of [`PipelineCache::render_ready`].
    pub fn compute_ready(&self, key: &ComputeKey) -> Result<Ready<ComputePipeline>, PipelineError> {
        let Missing::Background { fallback } = self.missing() else {
            return self.compute_key(key).map(Ready::Exact);
        };
        let found = {
            let mut inner = self.lock();
            inner.recorder.compute(key);
            inner.compute.get(key).cloned()
        };
        if let Some(p) = found {
            return Ok(Ready::Exact(p));
        }
        self.reflection(&key.compute, Stage::Compute)?;
        let pkey = PipelineKey::Compute(key.clone());
        if let Some(e) = lock(&self.background.failed).remove(&pkey) {
            return Err(e);
        }
        self.start(pkey.clone());
        let near = match fallback {
            Fallback::Nearest => self.nearest_compute(key)?,
            Fallback::Skip => None,
        };
        self.fell_back(&pkey, near.as_ref().map(|p| p.compute.clone()));
        Ok(near.map_or(Ready::NotReady, Ready::Nearest))
    }

    /// Counts a fallback answer and logs the first one of each key.
    fn fell_back(&self, key: &PipelineKey, instead: Option<String>) {
        self.background.fallbacks.fetch_add(1, Ordering::Relaxed);
        if lock(&self.background.logged).insert(key.clone()) {
            let what = match key {
                PipelineKey::Render(k) => format!("render pipeline {} + {:?}", k.vertex, k.fragment),
                PipelineKey::Compute(k) => format!("compute pipeline {}", k.compute),
            };
            match instead {
                Some(n) => log::info!("{what} is not ready: drawing with the nearest ready one ({n}) meanwhile"),
                None => log::info!("{what} is not ready: skipping its draws until it is"),
            }
        }
    }

    /// A view of this cache for a worker thread: the same maps, archive and device.
    pub(super) fn worker(&self) -> PipelineCache {
        PipelineCache {
            archive: self.archive.clone(),
            device: self.device.clone(),
            passthrough: self.passthrough,
            limits: self.limits.clone(),
            inner: self.inner.clone(),
            disk: self
                .disk
                .as_ref()
                .map(|d| super::disk_cache::DiskCache { cache: d.cache.clone(), path: d.path.clone() }),
            background: self.background.clone(),
        }
    }

    /// Creates `key` (found if made), not recorded as a frame's use; a panic inside the
    /// creation is an error naming the pipeline.
    pub(super) fn create_any(&self, key: &PipelineKey) -> Result<(), PipelineError> {
        let run = std::panic::AssertUnwindSafe(|| match key {
            PipelineKey::Render(k) => self.create_render(k).map(drop),
            PipelineKey::Compute(k) => self.create_compute(k).map(drop),
        });
        std::panic::catch_unwind(run).unwrap_or_else(|panic| {
            let message = panic
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_else(|| "a panic".to_string());
            Err(PipelineError::Wgpu { what: pipeline_name(key), message: format!("creation panicked: {message}") })
        })
    }

    /// Queues `key` for a background worker (once while it is queued), starting one if
    /// fewer than [`max_workers`] run.
    fn start(&self, key: PipelineKey) {
        let mut jobs = lock(&self.background.jobs);
        if !jobs.queued.insert(key.clone()) {
            return;
        }
        jobs.queue.push_back(key);
        if jobs.workers >= max_workers() {
            return;
        }
        jobs.workers += 1;
        drop(jobs);
        let view = self.worker();
        let spawned = std::thread::Builder::new().name("kiln-pipelines".into()).spawn(move || view.work());
        if spawned.is_err() {
            // No thread to be had: this one does the work, as under `Block`.
            lock(&self.background.jobs).workers -= 1;
            self.worker().work_once();
        }
    }

    /// A background worker: creates queued keys until the queue is empty.
    fn work(self) {
        while self.work_once() {}
    }

    /// Creates the next queued key; `false` (and this worker gone) when there is none.
    fn work_once(&self) -> bool {
        let key = {
            let mut jobs = lock(&self.background.jobs);
            match jobs.queue.pop_front() {
                Some(k) => k,
                None => {
                    jobs.workers = jobs.workers.saturating_sub(1);
                    return false;
                }
            }
        };
        if let Err(e) = self.create_any(&key) {
            lock(&self.background.failed).insert(key.clone(), e);
        }
        lock(&self.background.jobs).queued.remove(&key);
        true
    }

    /// The archive's nearest permutations of `name` (same shader and level) whose bindings
    /// are `name`'s, best first.
    fn near(&self, name: &str) -> Result<Arc<Vec<String>>, PipelineError> {
        if let Some(n) = lock(&self.background.near).get(name) {
            return Ok(n.clone());
        }
        let prefix = |n: &str| n.split('{').next().unwrap_or_default().to_string();
        let wanted = self.archive.get(name)?.reflection().bindings.clone();
        let found = self
            .archive
            .archive()
            .nearest(name, NEAR + 1)
            .map_err(|e| PipelineError::BadArtifact { name: name.to_string(), message: e.to_string() })?;
        let mut near = Vec::new();
        for n in found.into_iter().filter(|n| n.name != name && prefix(&n.name) == prefix(name)) {
            if matches!(self.archive.get(&n.name), Ok(p) if p.reflection().bindings == wanted) {
                near.push(n.name);
            }
        }
        let near = Arc::new(near);
        lock(&self.background.near).insert(name.to_string(), near.clone());
        Ok(near)
    }

    /// A ready render pipeline of `key`'s state whose permutations are `key`'s or their
    /// nearest (not both `key`'s), the closest first.
    fn nearest_render(&self, key: &RenderKey) -> Result<Option<Arc<RenderPipeline>>, PipelineError> {
        let vertex: Vec<String> =
            std::iter::once(key.vertex.clone()).chain(self.near(&key.vertex)?.iter().cloned()).collect();
        let fragment: Vec<Option<String>> = match &key.fragment {
            Some(f) => std::iter::once(Some(f.clone())).chain(self.near(f)?.iter().cloned().map(Some)).collect(),
            None => vec![None],
        };
        let mut pairs: Vec<(usize, &String, &Option<String>)> = Vec::new();
        for (i, v) in vertex.iter().enumerate() {
            for (j, f) in fragment.iter().enumerate() {
                if i + j > 0 {
                    pairs.push((i + j, v, f));
                }
            }
        }
        pairs.sort_by_key(|p| p.0);
        let inner = self.lock();
        for (_, v, f) in pairs {
            let k = RenderKey { vertex: v.clone(), fragment: f.clone(), state: key.state.clone() };
            if let Some(p) = inner.render.get(&k) {
                return Ok(Some(p.clone()));
            }
        }
        Ok(None)
    }

    fn nearest_compute(&self, key: &ComputeKey) -> Result<Option<Arc<ComputePipeline>>, PipelineError> {
        let near = self.near(&key.compute)?;
        let inner = self.lock();
        Ok(near.iter().find_map(|n| inner.compute.get(&ComputeKey { compute: n.clone() }).cloned()))
    }
}

/// A pipeline's name in messages: `render pipeline `V + F``, `compute pipeline `C``.
pub(super) fn pipeline_name(key: &PipelineKey) -> String {
    match key {
        PipelineKey::Render(k) => match &k.fragment {
            Some(f) => format!("render pipeline `{} + {f}`", k.vertex),
            None => format!("render pipeline `{}`", k.vertex),
        },
        PipelineKey::Compute(k) => format!("compute pipeline `{}`", k.compute),
    }
}
