//! Hot reload (cargo feature `hot-reload`, which links the Kiln compiler and naga: shipping
//! builds leave it off).
//!
//! [`HotReload`] builds a permutation set in-process through the Kiln library and its cache
//! ([`kiln::watch::Watch`] over [`kiln::build::run`]), then watches every file the build read
//! (the configuration, every source and header any permutation read). On a change it builds
//! again: the cache compiles only the permutations whose preprocessed text changed, and
//! [`Reload::changed`] names the permutations whose artifacts or reflection differ from the
//! archive in use. A renderer (the bundled one: `kiln_renderer::Renderer::reload`) then swaps exactly those modules and pipelines
//! between frames, keeping the others. A broken edit is a [`Event::Failed`] with Kiln's mapped
//! diagnostics; the caller keeps rendering with the last good archive.

use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use kiln::build::{self, CacheDir};
use kiln_archive::{Archive, Target};

use crate::shaders::ShaderArchive;

/// Why hot reloading could not start or go on.
#[derive(Debug, thiserror::Error)]
pub enum HotReloadError {
    /// The first build failed: the rendered diagnostics.
    #[error("{0}")]
    Build(String),
    /// The file watcher failed.
    #[error(transparent)]
    Watch(#[from] kiln::watch::Error),
    /// The rebuilt archive does not open.
    #[error("cannot open the rebuilt archive {path}: {source}")]
    Archive {
        /// The archive.
        path: PathBuf,
        /// Why.
        source: kiln_archive::ArchiveError,
    },
    /// A file of the watch could not be made.
    #[error("cannot create {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What the system said.
        source: std::io::Error,
    },
}

/// A rebuild that succeeded.
pub struct Reload {
    /// The rebuilt archive.
    pub archive: Arc<ShaderArchive>,
    /// The permutations whose artifacts or reflection changed (or that are new).
    pub changed: HashSet<String>,
    /// Distinct sources the build compiled (the rest came from the cache).
    pub compiled: usize,
    /// The files whose change started the rebuild.
    pub files: Vec<PathBuf>,
    /// When the change was seen.
    pub seen: Instant,
    /// How long the rebuild took.
    pub build_time: Duration,
}

/// What a change gave.
pub enum Event {
    /// The edit built: swap in the changed permutations.
    Reloaded(Reload),
    /// The edit does not build: Kiln's diagnostics, mapped to the original files.
    Failed {
        /// Kiln's rendered diagnostics.
        diagnostics: String,
        /// The files whose change started the build.
        files: Vec<PathBuf>,
        /// When the change was seen.
        seen: Instant,
    },
}

/// A permutation set built in-process and rebuilt when its files change.
pub struct HotReload {
    watch: kiln::watch::Watch,
    archive_path: PathBuf,
    /// The private folder (mode 0700) holding the archive, removed on drop.
    _folder: tempfile::TempDir,
    current: Arc<ShaderArchive>,
}

impl HotReload {
    /// Builds `config` (only `levels`, all when empty; SPIR-V and WGSL, the targets the
    /// runtime loads) with the cache of `kiln build`, and starts watching.
    pub fn start(config: &Path, levels: &[&str]) -> Result<HotReload, HotReloadError> {
        let folder = tempfile::Builder::new()
            .prefix("kiln-hot-reload-")
            .tempdir()
            .map_err(|source| HotReloadError::Io { path: std::env::temp_dir(), source })?;
        let archive_path = folder.path().join("shaders.kpak");
        let options = build::Options {
            config: config.to_path_buf(),
            output: Some(archive_path.clone()),
            levels: levels.iter().map(|l| l.to_string()).collect(),
            targets: vec![Target::Spirv, Target::Wgsl],
            cache: CacheDir::Auto,
            progress: false,
            color: false,
            ..build::Options::default()
        };
        let (watch, first) = kiln::watch::Watch::start(options)?;
        if let Err(e) = first.result {
            return Err(HotReloadError::Build(failure_text(&e)));
        }
        let current = Arc::new(open(&archive_path)?);
        Ok(HotReload { watch, archive_path, _folder: folder, current })
    }

    /// The archive of the last build the caller accepted.
    pub fn archive(&self) -> Arc<ShaderArchive> {
        self.current.clone()
    }

    /// How many files are watched.
    pub fn watched_files(&self) -> usize {
        self.watch.files().count()
    }

    /// Waits up to `timeout` for a change; on one, rebuilds. `None` when nothing changed.
    pub fn poll(&mut self, timeout: Duration) -> Result<Option<Event>, HotReloadError> {
        let Some(outcome) = self.watch.wait(timeout)? else {
            return Ok(None);
        };
        let files = outcome.changed;
        let report = match outcome.result {
            Ok(r) => r,
            Err(e) => return Ok(Some(Event::Failed { diagnostics: failure_text(&e), files, seen: outcome.seen })),
        };
        let archive = open(&self.archive_path)?;
        let changed = changed_permutations(self.current.archive(), archive.archive())
            .map_err(|source| HotReloadError::Archive { path: self.archive_path.clone(), source })?;
        Ok(Some(Event::Reloaded(Reload {
            archive: Arc::new(archive),
            changed,
            compiled: report.stats.compiled,
            files,
            seen: outcome.seen,
            build_time: outcome.build_time,
        })))
    }

    /// Makes `archive` the one later reloads compare with (after the caller swapped to it).
    pub fn accept(&mut self, archive: Arc<ShaderArchive>) {
        self.current = archive;
    }
}

/// Opens an archive this process's Kiln build just wrote, trusted for SPIR-V passthrough.
fn open(path: &Path) -> Result<ShaderArchive, HotReloadError> {
    let archive =
        ShaderArchive::open(path).map_err(|source| HotReloadError::Archive { path: path.to_path_buf(), source })?;
    // SAFETY: Kiln's compiler in this very process wrote the archive from the sources into a
    // folder only this user can write (a private temporary folder), as a renderer's `build.rs`
    // writes its embedded one: it is Kiln's own, unaltered output.
    Ok(unsafe { archive.assume_trusted() })
}

/// The rendered failures of a build, or its error.
fn failure_text(e: &build::Error) -> String {
    match e {
        build::Error::Failed(report) => {
            let mut s = String::new();
            for f in &report.failures {
                s.push_str(f.trim_end());
                s.push_str("\n\n");
            }
            s.push_str(&format!("error: {} of {} permutations failed", report.stats.failed, report.stats.permutations));
            s
        }
        other => other.to_string(),
    }
}

/// The permutations of `new` that `old` lacks or holds with other artifacts or reflection
/// (or a damaged record in `old`). A damaged record in `new` is an error.
pub fn changed_permutations(old: &Archive, new: &Archive) -> Result<HashSet<String>, kiln_archive::ArchiveError> {
    Ok(new
        .permutations()?
        .filter(|p| match old.get(p.name()) {
            Ok(None) | Err(_) => true,
            Ok(Some(o)) => {
                o.reflection() != p.reflection()
                    || o.targets().count() != p.targets().count()
                    || p.targets().any(|t| o.artifact(t).ok().flatten() != p.artifact(t).ok().flatten())
            }
        })
        .map(|p| p.name().to_string())
        .collect())
}
