//! The state a pipeline cache shares with its worker views ([`super::missing`],
//! [`super::precache`]): the in-flight set that makes the creation of one key happen once
//! however many threads ask, the background job queue, and the [`super::Missing`] mode.

use std::collections::{HashMap, HashSet, VecDeque};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};

use super::{Missing, PipelineError, PipelineKey};

/// The state a cache and its worker views share.
#[derive(Default)]
pub(super) struct Background {
    pub(super) missing: Mutex<Missing>,
    pub(super) fallbacks: AtomicU64,
    pub(super) in_flight: Mutex<HashSet<PipelineKey>>,
    pub(super) finished: Condvar,
    pub(super) jobs: Mutex<Jobs>,
    /// Errors of background creations, until the next ask for the key returns them.
    pub(super) failed: Mutex<HashMap<PipelineKey, PipelineError>>,
    /// Keys whose fallback was logged.
    pub(super) logged: Mutex<HashSet<PipelineKey>>,
    /// Per permutation: the archive's nearest of the same shader and level with the same
    /// bindings, best first.
    pub(super) near: Mutex<HashMap<String, Arc<Vec<String>>>>,
}

#[derive(Default)]
pub(super) struct Jobs {
    pub(super) queue: VecDeque<PipelineKey>,
    pub(super) queued: HashSet<PipelineKey>,
    pub(super) workers: usize,
}

pub(super) fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// A key this thread is creating; others asking for it wait until it is dropped.
pub(super) struct Claim<'a> {
    background: &'a Background,
    key: Option<PipelineKey>,
}

impl Drop for Claim<'_> {
    fn drop(&mut self) {
        if let Some(key) = self.key.take() {
            lock(&self.background.in_flight).remove(&key);
            self.background.finished.notify_all();
        }
    }
}

impl Background {
    /// Waits while another thread creates `key`, then claims it for this one.
    pub(super) fn claim(&self, key: PipelineKey) -> Claim<'_> {
        let mut set = lock(&self.in_flight);
        while set.contains(&key) {
            set = self.finished.wait(set).unwrap_or_else(|e| e.into_inner());
        }
        set.insert(key.clone());
        Claim { background: self, key: Some(key) }
    }

    /// The same mode and count, nothing in flight (a hot-reloaded cache).
    pub(super) fn carried(&self) -> Background {
        let b = Background { missing: Mutex::new(*lock(&self.missing)), ..Background::default() };
        b.fallbacks.store(self.fallbacks.load(Ordering::Relaxed), Ordering::Relaxed);
        b
    }
}

/// The worker threads a cache may run at once, for precaching or in the background.
pub(super) fn max_workers() -> usize {
    std::thread::available_parallelism().map_or(2, |n| n.get())
}
