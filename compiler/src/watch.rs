//! Rebuild on change: `kiln build --watch` and the runtime's hot reload.
//!
//! Takes [`build::Options`]; gives a [`Watch`] that has built once and then waits for a change
//! to any file the last build read (the configuration and every source and header any
//! permutation read: [`build::Report::files_read`]), rebuilds through the same
//! [`build::run`] and its cache (so only the permutations whose preprocessed text changed are
//! compiled again), and says what happened. Files are watched through their folders (the
//! `notify` crate), so an editor that saves by writing a new file and renaming it over the
//! old one is seen too; a burst of events is one change.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use notify::Watcher as _;

use crate::build::{self, Report};

/// Events closer together than this are one change (an editor's write, truncate and rename).
const SETTLE: Duration = Duration::from_millis(8);

/// A watch that could not start.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The file watcher failed.
    #[error("cannot watch files: {0}")]
    Notify(#[from] notify::Error),
}

/// What one build gave.
pub struct Outcome {
    /// The build's result (a [`build::Error::Failed`] holds the rendered failures).
    pub result: Result<Report, build::Error>,
    /// The files that changed since the last build (empty for the first).
    pub changed: Vec<PathBuf>,
    /// When the first change of this build was seen (the build's start for the first).
    pub seen: Instant,
    /// How long the build took.
    pub build_time: Duration,
}

/// A build that rebuilds when its inputs change.
pub struct Watch {
    options: build::Options,
    watcher: notify::RecommendedWatcher,
    events: mpsc::Receiver<notify::Result<notify::Event>>,
    files: BTreeSet<PathBuf>,
    folders: BTreeSet<PathBuf>,
}

impl Watch {
    /// Builds once with `options` and starts watching what the build read.
    pub fn start(options: build::Options) -> Result<(Watch, Outcome), Error> {
        let (tx, events) = mpsc::channel();
        let watcher = notify::recommended_watcher(move |e| {
            let _ = tx.send(e);
        })?;
        let mut watch = Watch { options, watcher, events, files: BTreeSet::new(), folders: BTreeSet::new() };
        let first = watch.build(Vec::new(), Instant::now())?;
        Ok((watch, first))
    }

    /// The files watched now.
    pub fn files(&self) -> impl Iterator<Item = &Path> {
        self.files.iter().map(PathBuf::as_path)
    }

    /// The options each rebuild runs with.
    pub fn options(&self) -> &build::Options {
        &self.options
    }

    /// Waits up to `timeout` for a change to a watched file; on one, rebuilds and returns
    /// what the build gave. `None` when nothing changed in time.
    pub fn wait(&mut self, timeout: Duration) -> Result<Option<Outcome>, Error> {
        let deadline = Instant::now() + timeout;
        let mut changed: BTreeSet<PathBuf> = BTreeSet::new();
        let mut seen = None;
        loop {
            let now = Instant::now();
            let wait = match seen {
                // Collect the rest of the burst.
                Some(_) => SETTLE,
                None if now >= deadline => return Ok(None),
                None => deadline - now,
            };
            match self.events.recv_timeout(wait) {
                Ok(Ok(event)) => {
                    if matches!(event.kind, notify::EventKind::Access(_)) {
                        continue;
                    }
                    for p in event.paths {
                        if self.files.contains(&p) {
                            seen.get_or_insert_with(Instant::now);
                            changed.insert(p);
                        }
                    }
                }
                Ok(Err(e)) => return Err(Error::Notify(e)),
                Err(mpsc::RecvTimeoutError::Timeout) if seen.is_some() => break,
                Err(mpsc::RecvTimeoutError::Timeout) => return Ok(None),
                Err(mpsc::RecvTimeoutError::Disconnected) => return Ok(None),
            }
        }
        let seen = seen.expect("a change was seen");
        self.build(changed.into_iter().collect(), seen).map(Some)
    }

    /// Runs the build and watches what it read (the previous files as well when it failed
    /// before reading any).
    fn build(&mut self, changed: Vec<PathBuf>, seen: Instant) -> Result<Outcome, Error> {
        let start = Instant::now();
        let result = build::run(&self.options);
        let build_time = start.elapsed();
        let read = match &result {
            Ok(r) => Some(&r.files_read),
            Err(build::Error::Failed(r)) => Some(&r.files_read),
            Err(_) => None,
        };
        let mut files: BTreeSet<PathBuf> = read.map(|f| f.iter().cloned().collect()).unwrap_or_default();
        if files.is_empty() {
            files = self.files.clone();
        }
        files.insert(absolute(&self.options.config));
        self.watch_files(files)?;
        Ok(Outcome { result, changed, seen, build_time })
    }

    fn watch_files(&mut self, files: BTreeSet<PathBuf>) -> Result<(), Error> {
        let folders: BTreeSet<PathBuf> = files.iter().filter_map(|f| f.parent().map(Path::to_path_buf)).collect();
        for gone in self.folders.difference(&folders) {
            let _ = self.watcher.unwatch(gone);
        }
        for new in folders.difference(&self.folders) {
            self.watcher.watch(new, notify::RecursiveMode::NonRecursive)?;
        }
        self.folders = folders;
        self.files = files;
        Ok(())
    }
}

fn absolute(p: &Path) -> PathBuf {
    p.canonicalize().or_else(|_| std::path::absolute(p)).unwrap_or_else(|_| p.to_path_buf())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_header_edit_rebuilds_and_an_unrelated_file_does_not() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path().canonicalize().unwrap();
        std::fs::write(
            d.join("permutations.toml"),
            "[compiler]\ninclude = [\".\"]\n[levels.sm5]\ntargets = [\"wgsl\"]\n[[shader]]\nname = \"S\"\nsource = \"s.usf\"\nstage = \"compute\"\nentry = \"main\"\n",
        )
        .unwrap();
        std::fs::write(d.join("s.usf"), "#include \"h.ush\"\n@compute @workgroup_size(1) fn main() { let x = K; }\n")
            .unwrap();
        std::fs::write(d.join("h.ush"), "const K: f32 = 1.0;\n").unwrap();
        let options = build::Options {
            config: d.join("permutations.toml"),
            output: Some(d.join("out.kpak")),
            cache: build::CacheDir::Dir(d.join("cache")),
            ..build::Options::default()
        };
        let (mut watch, first) = Watch::start(options).unwrap();
        assert_eq!(first.result.as_ref().unwrap().stats.compiled, 1);
        assert!(watch.files().any(|f| f == d.join("h.ush")));
        std::fs::write(d.join("unrelated.txt"), "x").unwrap();
        assert!(watch.wait(Duration::from_millis(200)).unwrap().is_none());
        std::fs::write(d.join("h.ush"), "const K: f32 = 2.0;\n").unwrap();
        let o = watch.wait(Duration::from_secs(10)).unwrap().expect("a rebuild");
        assert_eq!(o.changed, [d.join("h.ush")]);
        assert_eq!(o.result.as_ref().unwrap().stats.compiled, 1);
        std::fs::write(d.join("h.ush"), "const K: f32 = ;\n").unwrap();
        let o = watch.wait(Duration::from_secs(10)).unwrap().expect("a rebuild");
        assert!(matches!(o.result, Err(build::Error::Failed(_))));
    }
}
