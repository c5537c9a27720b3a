//! The build: a permutation set in, an archive (and optionally loose files) out.
//!
//! Takes [`Options`] (the `permutations.toml`, where to write, filters, cache, threads,
//! shard); gives a [`Report`] with the counts of DESIGN.md's `--stats-json`, every file the
//! build read (for `cargo:rerun-if-changed`), the rendered warnings and failures. `kiln
//! build` and [`crate::Build`] both call [`run`].
//!
//! The stages, one file each, in the order data flows:
//!
//! - [`plan`]: load the configuration, enumerate and keep permutations, choose a shard's
//!   share of the distinct keys;
//! - [`preprocess`]: each kept permutation's cache key (from the preprocessor's token hash,
//!   one shared [`crate::preprocess::SourceCache`]), or its preprocessing record's when its
//!   files have not changed, or an earlier permutation's when it agrees on every define
//!   that permutation's files name;
//! - [`compile`]: each distinct key once, from the cache where it holds it, else with naga;
//!   a key is compiled by the worker that first preprocesses one of its permutations, so
//!   compiling overlaps preprocessing (a shard, which knows its share only once every key
//!   is known, keeps each key's text for then: [`shard`]);
//! - [`store`]: the one place that talks to the cache: lookups, the packs that the
//!   compiled entries stream into, and the remote cache's archives (a fresh local cache
//!   with a remote holding this build's archive and entries copies them and assembles
//!   nothing);
//! - [`assemble`]: the archive and the loose files of `--emit-dir`, fed each key's
//!   artifacts as they are produced;
//! - [`report`]: counts, warnings, dead dimensions, failures rendered with their mapped
//!   locations and permutation names.
//!
//! Guarantees: a failing permutation never stops the others, and every failure is reported;
//! the archive is written atomically, only when nothing failed, and its bytes depend only on
//! the configuration and sources (not on `-j`, the cache state or shards); an archive that
//! is, byte for byte, the output of a build with the same keys is not written again.

// The stage list above names private modules on purpose: it is the map a maintainer reads
// (`cargo doc --document-private-items`), and the public docs show the names as code.
#![allow(rustdoc::private_intra_doc_links)]

use std::path::PathBuf;
use std::time::Instant;

use crate::archive::Target;
use crate::permute::Config;

mod assemble;
mod budget;
mod compile;
mod group;
mod outputs;
mod pieces;
mod plan;
mod preprocess;
mod progress;
mod records;
mod report;
mod shard;
mod store;
mod usage;

pub use crate::cache::remote::{Mode as RemoteMode, RemoteCache};
pub use compile::map_error;
pub use plan::Shard;
pub use report::{DeadDimension, Report, Seconds, Stats};
pub use store::default_cache_dir;
pub use usage::{matches as usage_pattern_matches, ShaderUsage};

/// What to build and where.
#[derive(Clone, Debug)]
pub struct Options {
    /// The `permutations.toml`.
    pub config: PathBuf,
    /// The archive to write; `None` writes none (a check-only build, or a shard's).
    pub output: Option<PathBuf>,
    /// Write each distinct artifact once as `DIR/<hash>.<ext>`, plus `DIR/index.json`.
    pub emit_dir: Option<PathBuf>,
    /// Build only these levels (all when empty).
    pub levels: Vec<String>,
    /// Write only these targets (each level's own when empty).
    pub targets: Vec<Target>,
    /// Worker threads; `None` uses one per core.
    pub jobs: Option<usize>,
    /// Where the cache lives: [`CacheDir::Auto`] finds cargo's target folder.
    pub cache: CacheDir,
    /// The shared remote cache layered under the local one ([`RemoteCache::Auto`]:
    /// `KILN_REMOTE_CACHE`). None without a local cache.
    pub remote_cache: RemoteCache,
    /// `None`: `KILN_REMOTE_CACHE_MODE`, else read-write.
    pub remote_cache_mode: Option<RemoteMode>,
    /// Write the counts as JSON here.
    pub stats_json: Option<PathBuf>,
    /// Show a progress bar (only honoured when stderr is a terminal and `CI` is unset).
    pub progress: bool,
    /// Colour in rendered diagnostics.
    pub color: bool,
    /// Compile only this shard's share of the distinct keys into the cache.
    pub shard: Option<Shard>,
    /// The most permutations, of one shader at one level or of all together (`--max-permutations`); `None`
    /// takes `[compiler] max_permutations`, else [`crate::permute::DEFAULT_MAX_PERMUTATIONS`].
    pub max_permutations: Option<u64>,
    /// Called on every worker between stages, so that the pages one stage freed do not stay
    /// resident under the next stage's tables (the `kiln` binary passes mimalloc's
    /// `mi_collect`); the first build of the process that passes one fixes it.
    pub release_freed: Option<fn()>,
    /// Usage files (`kiln_archive::usage`) of the permutations a renderer asked for.
    pub usage: Vec<PathBuf>,
    /// Build only the recorded permutations, those `[usage] keep` matches and those of
    /// `always = true` shaders; the archive records the others as left out.
    pub usage_only: bool,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            config: PathBuf::from("permutations.toml"),
            output: Some(PathBuf::from("shaders.kpak")),
            emit_dir: None,
            levels: Vec::new(),
            targets: Vec::new(),
            jobs: None,
            cache: CacheDir::Auto,
            remote_cache: RemoteCache::Auto,
            remote_cache_mode: None,
            stats_json: None,
            progress: false,
            color: false,
            shard: None,
            max_permutations: None,
            release_freed: None,
            usage: Vec::new(),
            usage_only: false,
        }
    }
}

/// Where the cache lives.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum CacheDir {
    /// `KILN_CACHE_DIR`, else `CARGO_TARGET_DIR/kiln-cache`, else `target/kiln-cache` of the
    /// cargo workspace holding the config, else `.kiln-cache` next to the config.
    Auto,
    /// This folder.
    Dir(PathBuf),
    /// No cache: compile everything.
    Disabled,
}

/// Why a build failed.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The configuration or a command-line choice is wrong (exit code 2). Rendered.
    #[error("{0}")]
    Config(String),
    /// Something outside the shaders failed: a file could not be written (exit code 2).
    #[error("{0}")]
    Io(String),
    /// A budget is exceeded (exit code 3): `[budget]` or a shader's `budget`. Rendered.
    #[error("{0}")]
    Budget(String),
    /// At least one permutation failed (exit code 1); the report has the failures.
    #[error("{} permutation(s) failed", .0.stats.failed)]
    Failed(Box<Report>),
}

impl Error {
    /// The exit code of DESIGN.md: 1 for shader failures, 3 for a budget exceeded, 2 for
    /// the rest.
    pub fn exit_code(&self) -> u8 {
        match self {
            Error::Failed(_) => 1,
            Error::Budget(_) => 3,
            _ => 2,
        }
    }
}

/// Runs a build.
pub fn run(options: &Options) -> Result<Report, Error> {
    let start = Instant::now();
    if let Some(release) = options.release_freed {
        set_release_freed(release);
    }
    let config = plan::load(options)?;
    let store = store::Store::open(options, &config)?;
    let report = worker_pool(options.jobs)?.install(|| stages(options, &config, &store, start))?;
    if let Some(archive) = &report.archive {
        budget::archive(&config, archive, options)?;
    }
    Ok(report)
}

/// The stages, in order; every stage's state lives in its own type.
fn stages(options: &Options, config: &Config, store: &store::Store, start: Instant) -> Result<Report, Error> {
    let mut report = report::Builder::new(options, start);
    let progress = progress::Progress::new(options.progress);
    // The last build's preprocessing records beside the plan (see `last_records`).
    let (plan, last) = rayon::join(|| plan::Plan::new(config, options), || last_records(config, options, store));
    let plan = plan?;
    RELEASE_SKIPPED.store(plan.len() < RELEASE_FROM, std::sync::atomic::Ordering::Relaxed);
    report.planned(&plan);
    budget::permutations(config, &plan, options)?;
    trace_memory("plan");

    let mut assembler = assemble::Assembler::new(&plan)?;
    let compiler = compile::Compiler::new(&plan, store, &assembler, &progress);
    let mut preprocessor = preprocess::Preprocessor::new(&plan, last);
    let t = Instant::now();
    // The keys claimed and the writers' outputs kept for sharing go before the stages that
    // follow preprocessing.
    let ended = || {
        compiler.end_early();
        release_freed();
    };
    let pre = preprocessor.run(&progress, store, |i, p, key, output| compiler.early(i, p, key, output), ended)?;
    report.preprocessed(&plan, &preprocessor, &pre, t)?;
    release_freed();
    trace_memory("preprocess");
    outputs::check_aliases(
        &outputs::output_files(options),
        report.files_read().iter().map(|p| ("a file the build reads", p.as_path())),
    )?;
    // Each row's representative (the first row with its key: the keys stay in the rows'
    // file), the dead dimensions (their tables handed back), then the archive's up-to-date
    // check on the rows' keys (each distinct key is a row's), then grouping: an up-to-date
    // build lets the cache's index go before grouping's tables come in (all at once were
    // its peak). Neither the search nor the check changes the failures.
    let same = group::representatives(&pre).map_err(preprocess::read_back)?;
    report.dead_dimensions(&plan, &pre, &same);
    release_freed();
    let failed = report.failed();
    if let Some(counts) = assembler.up_to_date(store, &pre, failed) {
        let warnings = store.finish();
        release_freed();
        let distinct = group(config, options, &plan, (&pre, same), &mut report)?.len();
        trace_memory("group");
        progress.finish();
        return up_to_date(report, (distinct, warnings), &mut preprocessor, store, &pre, (counts, false));
    }
    let keys = group(config, options, &plan, (&pre, same), &mut report)?;
    let fresh = assembler.copied_from_remote(store, &pre, &keys, failed);
    trace_memory("group");
    if let Some(counts) = fresh {
        progress.finish();
        let distinct = keys.len();
        drop(keys);
        let warnings = store.finish();
        return up_to_date(report, (distinct, warnings), &mut preprocessor, store, &pre, (counts, true));
    }
    before_compile(options, store, &keys, &compiler);
    let outcomes = compiler.run(&keys, &preprocessor).map_err(preprocess::read_back)?;
    report.compiled(&plan, &preprocessor, &compiler, &keys, outcomes, &pre);
    // The keys' tables are not needed past here.
    drop((keys, compiler));
    // Every artifact is in: the archive's tables that find blobs by content go.
    assembler.seal_blobs();
    trace_memory("compile");
    report.warnings(store.finish());
    release_freed();
    trace_memory("cache written");
    // The records once the cache's index is released (a warm build's is large).
    preprocessor.save_records(store, &pre);
    report.remote(store.remote_stats());
    if report.failed() {
        return Err(Error::Failed(Box::new(report.finish()?)));
    }
    // Only the manifest is left to write: keep each permutation's key, drop the rest.
    drop(preprocessor);
    release_freed();
    trace_memory("drop");
    report.assembled(assembler.finish(pre, store)?);
    trace_memory("assemble");
    report.finish()
}

/// The last build's preprocessing records; a fresh local cache (its records came from the
/// remote cache) starts filling their keys from the remote. Not for a shard, which fetches
/// its share.
fn last_records(config: &Config, options: &Options, store: &store::Store) -> preprocess::LastRecords {
    let last = preprocess::LastRecords::load(config, options, store);
    if options.shard.is_none() {
        store.prefill(|| last.keys());
    }
    last
}

/// The distinct keys, checked against the budget and counted in the report.
fn group<'p>(
    config: &Config,
    options: &Options,
    plan: &plan::Plan<'_>,
    (pre, same): (&'p preprocess::Preprocessed, Vec<u32>),
    report: &mut report::Builder<'_>,
) -> Result<group::Keys<'p>, Error> {
    let keys = plan.group(pre, same)?;
    report.estimated_compile_ms(budget::keys(config, plan, pre, &keys, options)?);
    report.distinct(keys.len());
    Ok(keys)
}

/// The end of a build whose archive is up to date, or was copied from the remote cache:
/// `distinct` keys, the cache's `warnings` (its index already let go), the artifact
/// `counts` and whether they came from the remote.
fn up_to_date(
    mut report: report::Builder<'_>,
    (distinct, warnings): (usize, Vec<String>),
    preprocessor: &mut preprocess::Preprocessor<'_>,
    store: &store::Store,
    pre: &preprocess::Preprocessed,
    (counts, from_remote): ((usize, usize), bool),
) -> Result<Report, Error> {
    // The records are made once the cache's index is gone; when they are the last build's,
    // nothing is made and the build ends here (handing memory back would only cost time).
    report.warnings(warnings);
    if !preprocessor.records_unchanged() {
        release_freed();
    }
    preprocessor.save_records(store, pre);
    if from_remote {
        report.remote(store.remote_stats());
    }
    report.up_to_date(distinct, counts)
}

/// Readies the compile stage: memory handed back, the cache's prefill done, and a shard's
/// share fetched.
fn before_compile(options: &Options, store: &store::Store, keys: &group::Keys<'_>, compiler: &compile::Compiler<'_>) {
    // Grouping's sort and counting tables go back before the compile stage.
    release_freed();
    // The compile stage looks keys up once the prefill is done (else it would ask the remote
    // for them one by one).
    // (A key that cannot be read back ends the count here; the compile stage reports it.)
    store.wait_prefill(keys.iter().map_while(Result::ok));
    if options.shard.is_some() {
        // A shard's share comes from the remote cache in batches, not key by key (but for
        // the keys it produced while preprocessing, with shares by hash).
        let share: Vec<_> = keys
            .iter()
            .map_while(Result::ok)
            .enumerate()
            .filter(|&(k, _)| keys.share[k] && !compiler.produced_early(keys.members(k)))
            .map(|(_, key)| key)
            .collect();
        store.prefetch(&share);
    }
}

/// `KILN_TRACE_MEMORY=1`: the process's resident memory after a stage and its peak so far
/// (`VmRSS` and `VmHWM` of `/proc/self/status`, so whatever the allocator: the `kiln` binary
/// runs on mimalloc, a library user on theirs), on stderr; what grows with the set shows
/// between sizes.
pub(crate) fn trace_memory(stage: &str) {
    if std::env::var_os("KILN_TRACE_MEMORY").is_none() {
        return;
    }
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let mib = |field: &str| -> Option<f64> {
        let line = status.lines().find_map(|l| l.strip_prefix(field))?;
        let kib: f64 = line.trim().trim_end_matches("kB").trim().parse().ok()?;
        Some(kib / 1024.0)
    };
    match (mib("VmRSS:"), mib("VmHWM:")) {
        (Some(now), Some(peak)) => eprintln!("memory after {stage}: {now:.1} MiB resident, {peak:.1} MiB at peak"),
        _ => eprintln!("memory after {stage}: unknown (no /proc/self/status)"),
    }
    // `KILN_TRACE_MEMORY=stage`: each peak is the stage's own (the kernel's high-water mark
    // is reset to the resident memory after each line).
    if std::env::var_os("KILN_TRACE_MEMORY").is_some_and(|v| v == "stage") {
        let _ = std::fs::write("/proc/self/clear_refs", "5");
    }
}

/// What hands the memory freed so far on the calling thread back to the system
/// ([`set_release_freed`]).
static RELEASE_FREED: std::sync::OnceLock<fn()> = std::sync::OnceLock::new();

/// Builds of fewer permutations skip [`release_freed`]: their tables are small, and each
/// release wakes every worker (about 3% of the CPU of a build of 144 permutations).
const RELEASE_FROM: usize = 1 << 15;

/// This build skips [`release_freed`] ([`RELEASE_FROM`]); set once its plan is made.
static RELEASE_SKIPPED: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Has a build call `release` on every worker between stages ([`Options::release_freed`]).
/// With mimalloc a page freed on another thread than the one that allocated it waits on its
/// owner's list, and an idle worker never takes it back, so the next stage faulted in new
/// pages beside them. The first call wins.
fn set_release_freed(release: fn()) {
    let _ = RELEASE_FREED.set(release);
}

pub(crate) fn release_freed() {
    if RELEASE_SKIPPED.load(std::sync::atomic::Ordering::Relaxed) {
        return;
    }
    if let Some(&release) = RELEASE_FREED.get() {
        rayon::broadcast(|_| release());
    }
}

/// Workers with the preprocessor's stack run it in place (no thread per permutation).
fn worker_pool(jobs: Option<usize>) -> Result<rayon::ThreadPool, Error> {
    let mut b = rayon::ThreadPoolBuilder::new()
        .stack_size(crate::preprocess::STACK_BYTES)
        .start_handler(|_| crate::preprocess::big_stack_thread());
    if let Some(j) = jobs {
        b = b.num_threads(j.max(1));
    }
    b.build().map_err(|e| Error::Io(format!("error: cannot start worker threads: {e}")))
}
