//! Creating a list of pipelines (an archive's pipeline manifest) on worker threads, before
//! or alongside the first frames, with progress a caller can poll.
//!
//! [`PipelineCache::precache`] starts at most `available_parallelism` threads (and no more
//! than there are keys); they take the keys in the order given (the manifest's first-use
//! order), so the first frames' pipelines are ready first. Each key is created once even
//! when a frame asks for it meanwhile (the cache's in-flight set). Precaching is no frame's
//! use: it is not recorded in [`PipelineCache::usage`].

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

use kiln_archive::usage::UsageKey;
use kiln_archive::PipelineRecord;

use super::cache::PipelineCache;
use super::inflight::max_workers;
use super::missing::pipeline_name;
use super::state_text::StateTextError;
use super::{ComputeKey, PipelineError, PipelineKey, RenderKey, RenderState};

/// How far a [`Precache`] is.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Progress {
    /// Keys created (or found already created).
    pub done: usize,
    /// Keys whose creation failed.
    pub failed: usize,
    /// Keys in all.
    pub total: usize,
}

/// A pipeline precaching could not create.
#[derive(Debug, thiserror::Error)]
#[error("{pipeline}: {error}")]
pub struct PrecacheError {
    /// The pipeline, named by its permutations (`render pipeline `V + F``).
    pub pipeline: String,
    /// Why.
    pub error: PipelineError,
}

struct Shared {
    keys: Vec<PipelineKey>,
    next: AtomicUsize,
    done: AtomicUsize,
    failed: AtomicUsize,
    errors: Mutex<Vec<(usize, PrecacheError)>>,
}

/// Pipelines being created on worker threads ([`PipelineCache::precache`]).
pub struct Precache {
    shared: Arc<Shared>,
    threads: Vec<std::thread::JoinHandle<()>>,
}

impl Precache {
    /// Created, failed and total keys so far.
    pub fn progress(&self) -> Progress {
        let s = &self.shared;
        Progress { done: s.done.load(Ordering::Acquire), failed: s.failed.load(Ordering::Acquire), total: s.keys.len() }
    }

    /// Whether every key has been tried.
    pub fn finished(&self) -> bool {
        let p = self.progress();
        p.done + p.failed == p.total
    }

    /// Waits for every key; returns those that failed, in the order of the keys.
    pub fn wait(self) -> Vec<PrecacheError> {
        for t in self.threads {
            // A worker catches every creation's panic, so joining cannot fail.
            let _ = t.join();
        }
        let mut errors = std::mem::take(&mut *self.shared.errors.lock().unwrap_or_else(|e| e.into_inner()));
        errors.sort_by_key(|e| e.0);
        errors.into_iter().map(|e| e.1).collect()
    }
}

impl PipelineCache {
    /// Creates every pipeline of `keys` on worker threads (at most `available_parallelism`),
    /// in the order given; those already created are found. Returns at once: poll
    /// [`Precache::progress`], or [`Precache::wait`] for what failed.
    pub fn precache(&self, keys: impl IntoIterator<Item = PipelineKey>) -> Precache {
        let shared = Arc::new(Shared {
            keys: keys.into_iter().collect(),
            next: AtomicUsize::new(0),
            done: AtomicUsize::new(0),
            failed: AtomicUsize::new(0),
            errors: Mutex::default(),
        });
        let mut threads = Vec::new();
        for _ in 0..max_workers().min(shared.keys.len()) {
            let (view, work) = (self.worker(), shared.clone());
            match std::thread::Builder::new().name("kiln-precache".into()).spawn(move || precache_keys(&view, &work)) {
                Ok(t) => threads.push(t),
                Err(_) if threads.is_empty() => precache_keys(self, &shared),
                Err(_) => break,
            }
        }
        Precache { shared, threads }
    }
}

/// Takes keys from `work` until none is left.
fn precache_keys(cache: &PipelineCache, work: &Shared) {
    loop {
        let i = work.next.fetch_add(1, Ordering::AcqRel);
        let Some(key) = work.keys.get(i) else { return };
        match cache.create_any(key) {
            Ok(()) => {
                work.done.fetch_add(1, Ordering::AcqRel);
            }
            Err(error) => {
                let e = PrecacheError { pipeline: pipeline_name(key), error };
                work.errors.lock().unwrap_or_else(|e| e.into_inner()).push((i, e));
                work.failed.fetch_add(1, Ordering::AcqRel);
            }
        }
    }
}

/// The pipeline key of each record of an archive's pipeline manifest, in its order (the
/// render state read back from its text, [`RenderState::from_state_text`]); the first
/// record whose state text does not read is an error.
pub fn manifest_keys(records: &[PipelineRecord]) -> Result<Vec<PipelineKey>, StateTextError> {
    records
        .iter()
        .map(|r| {
            Ok(match &r.key {
                UsageKey::Compute { compute } => PipelineKey::Compute(ComputeKey { compute: compute.clone() }),
                UsageKey::Render { vertex, fragment, state } => PipelineKey::Render(RenderKey {
                    vertex: vertex.clone(),
                    fragment: fragment.clone(),
                    state: RenderState::from_state_text(state)?,
                }),
            })
        })
        .collect()
}
