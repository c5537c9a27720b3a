//! The build: a permutation set in, an archive (and optionally loose files) out.
//!
//! Takes [`Options`] (the `permutations.toml`, where to write, filters, cache, threads);
//! gives a [`Report`] with the counts of DESIGN.md's `--stats-json`, every file the build
//! read (for `cargo:rerun-if-changed`), the rendered warnings and failures. `kiln build` and
//! [`crate::Build`] both call [`run`]. Guarantees: every kept permutation gets its cache key
//! from the preprocessor's token hash, with one shared [`SourceCache`] (each file read
//! once); permutations whose keys are equal compile once, distinct keys compile in
//! parallel, and the cache serves keys it holds; a failing permutation never stops the
//! others, and every failure is reported with its mapped location and permutation name;
//! the archive is written atomically, and only when nothing failed.
//!
//! Compiling overlaps preprocessing: a key is compiled (or looked up in the cache) by the
//! worker that first preprocesses one of its permutations; the
//! compile phase then only gathers results (and compiles what failed, on the key's first
//! permutation, so that spans map on that text). `seconds.compile` runs from the first key
//! compiled to the last, so it overlaps `seconds.preprocess`.
//!
//! Work is skipped where the result is known: a permutation whose preprocessing record
//! (in the cache) lists files whose contents have not changed is not preprocessed; a
//! permutation that agrees with an already preprocessed one of its shader and level on
//! every define the latter's files name reuses its result; and an archive that is, byte
//! for byte, the output of a build with the same keys is not written again.

use std::collections::{BTreeMap, HashMap};
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::Instant;

use codespan_reporting::diagnostic::{Diagnostic, Label, LabelStyle};
use rayon::prelude::*;

use crate::archive::{self, ArchiveWriter, DimensionRecord, PermutationRecord, ShaderRecord, Target};
use crate::cache::{self, Cache, Key, Lookup};
use crate::compile::{self, Compiled, Limits};
use crate::permute::{self, Config, Permutation};
use crate::preprocess::{self, FileId, SourceCache};

/// What to build and where.
#[derive(Clone, Debug)]
pub struct Options {
    /// The `permutations.toml`.
    pub config: PathBuf,
    /// The archive to write; `None` writes none (a check-only build).
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
    /// Write the counts as JSON here.
    pub stats_json: Option<PathBuf>,
    /// Show a progress bar (only honoured when stderr is a terminal and `CI` is unset).
    pub progress: bool,
    /// Colour in rendered diagnostics.
    pub color: bool,
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
            stats_json: None,
            progress: false,
            color: false,
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

/// The counts of `--stats-json` (DESIGN.md, "Command line").
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct Stats {
    /// Kept permutations.
    pub permutations: usize,
    /// Permutations dropped by skip rules.
    pub skipped: usize,
    /// Distinct cache keys among the kept permutations that preprocessed.
    pub unique_sources: usize,
    /// Distinct keys this build compiled (one naga parse and validation each).
    pub compiled: usize,
    /// Distinct keys served from the cache.
    pub cache_hits: usize,
    /// Distinct blobs in the archive (identical outputs are stored once).
    pub artifacts: usize,
    /// (permutation, target) pairs in the archive.
    pub permutation_artifacts: usize,
    /// Permutations that failed to preprocess or compile.
    pub failed: usize,
    /// Permutations preprocessed by this build (the others matched their cached
    /// preprocessing record: same defines, same file contents).
    pub preprocessed: usize,
    pub seconds: Seconds,
}

#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct Seconds {
    pub total: f64,
    pub preprocess: f64,
    pub compile: f64,
}

/// A dimension that never changes its shader's text at a level.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct DeadDimension {
    pub shader: String,
    pub level: String,
    pub dimension: String,
    /// How many values it takes: the factor of build work it multiplies for nothing.
    pub values: usize,
}

/// What a build did.
#[derive(Debug, Default)]
pub struct Report {
    pub stats: Stats,
    /// The config and every file any permutation read (absolute, sorted, deduplicated).
    pub files_read: Vec<PathBuf>,
    /// Rendered warnings (preprocessor warnings, corrupted cache entries, dead dimensions).
    pub warnings: Vec<String>,
    /// Rendered failures, one per distinct diagnostic, each naming its permutations.
    pub failures: Vec<String>,
    pub dead_dimensions: Vec<DeadDimension>,
    /// The archive written, if any.
    pub archive: Option<PathBuf>,
}

impl Report {
    /// The summary line: kept, skipped, distinct, compiled, cache hits, failed, time.
    pub fn summary(&self) -> String {
        let s = &self.stats;
        format!(
            "{} permutations ({} skipped), {} distinct, {} compiled, {} cache hits, {} failed in {:.2}s",
            s.permutations, s.skipped, s.unique_sources, s.compiled, s.cache_hits, s.failed, s.seconds.total
        )
    }
}

#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The configuration or a command-line choice is wrong (exit code 2). Rendered.
    #[error("{0}")]
    Config(String),
    /// Something outside the shaders failed: a file could not be written (exit code 2).
    #[error("{0}")]
    Io(String),
    /// At least one permutation failed (exit code 1); the report has the failures.
    #[error("{} permutation(s) failed", .0.stats.failed)]
    Failed(Box<Report>),
}

impl Error {
    /// The exit code of DESIGN.md: 1 for shader failures, 2 for the rest.
    pub fn exit_code(&self) -> u8 {
        match self {
            Error::Failed(_) => 1,
            _ => 2,
        }
    }
}

/// One kept permutation after preprocessing (or after its preprocessing record matched).
#[derive(Clone)]
struct Pre {
    key: Key,
    text_hash: blake3::Hash,
    token_hash: blake3::Hash,
    /// Every file it read (absolute).
    files: Vec<PathBuf>,
    /// Its preprocessor warnings, rendered without colour.
    warnings: Vec<String>,
}

/// The first (lowest index) preprocessed permutation's output of a key.
struct Representative {
    index: usize,
    output: preprocess::Output,
}

/// The identifiers of each file read this build, and whether it pastes tokens (`##`).
#[derive(Default)]
struct FileIdentifiers {
    map: Mutex<HashMap<FileId, std::sync::Arc<(std::collections::HashSet<String>, bool)>>>,
}

impl FileIdentifiers {
    fn get(&self, id: FileId, sources: &SourceCache) -> std::sync::Arc<(std::collections::HashSet<String>, bool)> {
        use codespan_reporting::files::Files;
        if let Some(v) = self.map.lock().expect("no panics while locked").get(&id) {
            return v.clone();
        }
        let text = sources.source(id).map(|t| t.as_ref().to_string()).unwrap_or_default();
        let mut names = std::collections::HashSet::new();
        let mut pastes = false;
        for tok in preprocess::tokens(&text) {
            if tok.starts_with(|c: char| c.is_ascii_alphabetic() || c == '_') {
                names.insert(tok.to_string());
            } else if tok == "##" || tok == "%:%:" {
                pastes = true;
            }
        }
        let v = std::sync::Arc::new((names, pastes));
        self.map.lock().expect("no panics while locked").insert(id, v.clone());
        v
    }
}

/// Results reused between permutations of one shader at one level. The preprocessor's
/// output depends only on the texts of the files it reads and on the values of the macros
/// those texts name; a permutation that agrees with an earlier one on every define named
/// in the earlier one's files reads the same files, takes the same branches and gives the
/// same output. (Files that paste tokens with `##` can make names that appear nowhere, so
/// their permutations are never reused.)
#[derive(Default)]
struct Reuse {
    /// (shader, level) → [(define names that mattered, values of those names → result)].
    groups: Mutex<HashMap<(String, String), Vec<(Vec<String>, HashMap<Vec<i64>, (Pre, Option<cache::Record>)>)>>>,
}

fn define_values(p: &Permutation<'_>) -> HashMap<String, i64> {
    p.defines().into_iter().map(|d| (d.name, d.value)).collect()
}

impl Reuse {
    fn find(&self, p: &Permutation<'_>, values: &HashMap<String, i64>) -> Option<(Pre, Option<cache::Record>)> {
        let groups = self.groups.lock().expect("no panics while locked");
        let sets = groups.get(&(p.shader.name.clone(), p.level.name.clone()))?;
        for (names, results) in sets {
            let signature: Option<Vec<i64>> = names.iter().map(|n| values.get(n).copied()).collect();
            if let Some(hit) = signature.and_then(|sig| results.get(&sig)) {
                return Some(hit.clone());
            }
        }
        None
    }

    fn insert(
        &self,
        p: &Permutation<'_>,
        values: &HashMap<String, i64>,
        output: &preprocess::Output,
        pre: &Pre,
        record: Option<cache::Record>,
        identifiers: &FileIdentifiers,
        sources: &SourceCache,
    ) {
        let mut used = std::collections::HashSet::new();
        for &f in &output.files {
            let ids = identifiers.get(f, sources);
            if ids.1 {
                return;
            }
            used.extend(values.keys().filter(|n| ids.0.contains(*n)).cloned());
        }
        let mut names: Vec<String> = used.into_iter().collect();
        names.sort();
        let signature: Vec<i64> = names.iter().map(|n| values[n]).collect();
        let mut groups = self.groups.lock().expect("no panics while locked");
        let sets = groups.entry((p.shader.name.clone(), p.level.name.clone())).or_default();
        let i = match sets.iter().position(|(n, _)| *n == names) {
            Some(i) => i,
            None => {
                sets.push((names, HashMap::new()));
                sets.len() - 1
            }
        };
        sets[i].1.entry(signature).or_insert_with(|| (pre.clone(), record));
    }
}

/// blake3 of files' texts, each read once per build (for checking preprocessing records).
#[derive(Default)]
struct FileHashes {
    map: Mutex<HashMap<PathBuf, Option<String>>>,
}

impl FileHashes {
    /// The hash of the file's text as it is on disk now.
    fn get(&self, path: &Path) -> Option<String> {
        self.get_or_insert_with(path, || {
            std::fs::read(path).ok().map(|bytes| {
                let text =
                    String::from_utf8(bytes).unwrap_or_else(|e| String::from_utf8_lossy(e.as_bytes()).into_owned());
                blake3::hash(text.as_bytes()).to_hex().to_string()
            })
        })
    }

    fn get_or_insert_with(&self, path: &Path, f: impl FnOnce() -> Option<String>) -> Option<String> {
        if let Some(h) = self.map.lock().expect("no panics while locked").get(path) {
            return h.clone();
        }
        let h = f();
        self.map.lock().expect("no panics while locked").insert(path.to_path_buf(), h.clone());
        h
    }
}

/// Runs a build.
pub fn run(options: &Options) -> Result<Report, Error> {
    let start = Instant::now();
    let config = permute::load(&options.config).map_err(|e| Error::Config(e.render()))?;
    for l in &options.levels {
        if config.level(l).is_none() {
            let names: Vec<&str> = config.levels.iter().map(|l| l.name.as_str()).collect();
            return Err(Error::Config(format!(
                "error: no level named `{l}` in {} (its levels: {})",
                options.config.display(),
                names.join(", ")
            )));
        }
    }
    let cache = match open_cache(options, &config) {
        Ok(c) => c,
        Err(e) => return Err(Error::Io(format!("error: {e}"))),
    };
    let pool = {
        // Workers with the preprocessor's stack run it in place (no thread per permutation).
        let mut b = rayon::ThreadPoolBuilder::new()
            .stack_size(preprocess::STACK_BYTES)
            .start_handler(|_| preprocess::big_stack_thread());
        if let Some(j) = options.jobs {
            b = b.num_threads(j.max(1));
        }
        b.build().map_err(|e| Error::Io(format!("error: cannot start worker threads: {e}")))?
    };
    pool.install(|| run_in_pool(options, &config, cache.as_ref(), start))
}

fn level_targets(level: &permute::Level, filter: &[Target]) -> Vec<Target> {
    level.targets.iter().copied().filter(|t| filter.is_empty() || filter.contains(t)).collect()
}

fn level_limits(level: &permute::Level) -> Limits {
    let mut limits = match level.limits {
        permute::Limits::Default => Limits::desktop(),
        permute::Limits::Downlevel => Limits::downlevel(),
    };
    for (field, value) in &level.limit_overrides {
        limits.set(field, *value);
    }
    limits
}

fn run_in_pool(options: &Options, config: &Config, cache: Option<&Cache>, start: Instant) -> Result<Report, Error> {
    let mut report = Report::default();
    let progress = Progress::new(options.progress);

    // 1. Enumerate.
    let mut kept: Vec<Permutation<'_>> = Vec::new();
    for p in config.permutations_where(|_, level| options.levels.is_empty() || options.levels.contains(&level.name)) {
        if p.is_kept() {
            kept.push(p);
        } else {
            report.stats.skipped += 1;
        }
    }
    report.stats.permutations = kept.len();

    // 2. Preprocess, keeping one output per key. A permutation whose preprocessing record
    //    is in the cache and whose files all still have the recorded contents is not
    //    preprocessed again.
    let t_pre = Instant::now();
    let sources = SourceCache::new(config.dir.clone());
    progress.stage("preprocessing", kept.len());
    let reps: Mutex<HashMap<Key, Representative>> = Mutex::new(HashMap::new());
    let hashes = FileHashes::default();
    let text_hashes = FileHashes::default();
    let preprocessed = std::sync::atomic::AtomicUsize::new(0);
    let records_key = cache.map(|_| records_key(config, options));
    let direct_base = cache.map(|_| direct_base(config));
    let old_records = match (cache, &records_key) {
        (Some(c), Some(k)) => c.get_records(k),
        _ => cache::Records::default(),
    };
    let new_records: Mutex<cache::Records> = Mutex::new(cache::Records::new());
    let reuse = Reuse::default();
    let identifiers = FileIdentifiers::default();
    // Keys compiled (or found in the cache) as soon as their first permutation is
    // preprocessed, so that compiling overlaps preprocessing.
    let early = Early::default();
    let one = |index: usize, p: &Permutation<'_>| -> Result<Pre, Diagnostic<FileId>> {
        let direct = direct_base.as_ref().map(|base| direct_key(base, p, &options.targets).to_hex());
        if let Some(dk) = &direct {
            if let Some(record) = old_records.get(dk) {
                if let Some(pre) = from_record(record, &hashes) {
                    new_records.lock().expect("no panics while locked").insert(dk.clone(), record.clone());
                    progress.inc();
                    return Ok(pre);
                }
            }
        }
        let values = define_values(p);
        if p.error.is_none() {
            if let Some((pre, record)) = reuse.find(p, &values) {
                if let (Some(dk), Some(record)) = (direct, record) {
                    new_records.lock().expect("no panics while locked").insert(dk, record);
                }
                progress.inc();
                return Ok(pre);
            }
        }
        preprocessed.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let result = preprocess_one(config, p, &options.targets, &sources);
        progress.inc();
        let (pre, output) = result?;
        let record = direct.as_ref().map(|_| to_record(&pre, &output, &sources, &text_hashes));
        if let (Some(dk), Some(record)) = (direct, &record) {
            new_records.lock().expect("no panics while locked").insert(dk, record.clone());
        }
        reuse.insert(p, &values, &output, &pre, record, &identifiers, &sources);
        if p.error.is_none() && early.claim(pre.key) {
            early.started();
            let got = lookup_or_compile(cache, &pre.key, p, &output.text, &options.targets);
            // A failure is compiled again on the key's representative (its spans are mapped
            // on that text); only successes are kept.
            if !matches!(got, Got::Failed(..)) {
                early.done(pre.key, got);
            }
        }
        let mut reps = reps.lock().expect("no panics while locked");
        let replace = reps.get(&pre.key).is_none_or(|r| r.index > index);
        if replace {
            reps.insert(pre.key, Representative { index, output });
        }
        Ok(pre)
    };
    // The first permutation of each (shader, level) first, so that the others find what
    // they may reuse; then all the others. Workers take the next permutation from a shared
    // counter: in order, one at a time (compile times differ widely between shaders), and
    // with no barrier between the two halves.
    let mut first_of_group = vec![false; kept.len()];
    let mut seen_groups = std::collections::HashSet::new();
    for (i, p) in kept.iter().enumerate() {
        first_of_group[i] = seen_groups.insert((p.shader.name.as_str(), p.level.name.as_str()));
    }
    let order: Vec<usize> =
        (0..kept.len()).filter(|&i| first_of_group[i]).chain((0..kept.len()).filter(|&i| !first_of_group[i])).collect();
    let next = std::sync::atomic::AtomicUsize::new(0);
    let done: Mutex<Vec<Option<Result<Pre, Diagnostic<FileId>>>>> = Mutex::new((0..kept.len()).map(|_| None).collect());
    rayon::scope(|s| {
        for _ in 0..rayon::current_num_threads() {
            s.spawn(|_| loop {
                let n = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                let Some(&i) = order.get(n) else { break };
                let r = one(i, &kept[i]);
                done.lock().expect("no panics while locked")[i] = Some(r);
            });
        }
    });
    let pre = done.into_inner().expect("no panics while locked");
    let pre: Vec<Result<Pre, Diagnostic<FileId>>> =
        pre.into_iter().map(|r| r.expect("every permutation was preprocessed")).collect();
    let reps = reps.into_inner().expect("no panics while locked");
    report.stats.preprocessed = preprocessed.into_inner();
    if let (Some(c), Some(k)) = (cache, &records_key) {
        let new_records = new_records.into_inner().expect("no panics while locked");
        if new_records != old_records {
            // Failing to store the records only costs preprocessing next time.
            let _ = c.put_records(k, &new_records);
        }
    }
    report.stats.seconds.preprocess = t_pre.elapsed().as_secs_f64();

    // Warnings: each distinct rendered warning once.
    let mut seen_warnings = std::collections::HashSet::new();
    for w in pre.iter().flatten().flat_map(|p| &p.warnings) {
        if seen_warnings.insert(w.clone()) {
            report.warnings.push(w.clone());
        }
    }
    let mut failures: Vec<(Diagnostic<FileId>, Vec<usize>)> = Vec::new();
    let mut files = std::collections::BTreeSet::new();
    files.insert(config.path.clone());
    for (i, r) in pre.iter().enumerate() {
        match r {
            Ok(p) => files.extend(p.files.iter().cloned()),
            Err(d) => {
                failures.push((d.clone(), vec![i]));
                // A failed permutation still read files: the failing header among them.
                for l in &d.labels {
                    files.insert(sources.path(l.file_id));
                }
            }
        }
    }
    files.retain(|f| !f.as_os_str().is_empty());
    report.files_read = files.into_iter().collect();

    // 3. Group by key, in order of first appearance.
    let mut groups: Vec<(Key, Vec<usize>)> = Vec::new();
    let mut group_of: HashMap<Key, usize> = HashMap::new();
    for (i, r) in pre.iter().enumerate() {
        if let Ok(p) = r {
            let g = *group_of.entry(p.key).or_insert_with(|| {
                groups.push((p.key, Vec::new()));
                groups.len() - 1
            });
            groups[g].1.push(i);
        }
    }
    report.stats.unique_sources = groups.len();
    report.dead_dimensions = dead_dimensions(&kept, &pre);
    for d in &report.dead_dimensions {
        report.warnings.push(format!(
            "warning: dimension `{}` of `{}` never changes the shader's text at level `{}`: its {} values multiply the permutations for nothing",
            d.dimension, d.shader, d.level, d.values
        ));
    }

    // Up to date? When every permutation has the key it had when the archive was written,
    // and the archive is the file that build wrote, there is nothing to do (like cargo's
    // freshness check). Only with a cache (the stamp lives there) and without --emit-dir.
    let stamp = match (cache, &options.output, &options.emit_dir, failures.is_empty()) {
        (Some(c), Some(out), None, true) => Some((c, out, build_fingerprint(&kept, &pre))),
        _ => None,
    };
    if let Some((c, out, fingerprint)) = &stamp {
        let keys: Vec<Key> = groups.iter().map(|g| g.0).collect();
        if let Some(counts) = c.fresh_archive(out, fingerprint, &keys) {
            report.stats.cache_hits = groups.len();
            report.stats.artifacts = counts.0;
            report.stats.permutation_artifacts = counts.1;
            report.archive = Some(out.to_path_buf());
            progress.finish();
            write_stats(options, &mut report, start)?;
            return Ok(report);
        }
    }

    // 4. Compile each distinct key once (or take it from the cache).
    let t_compile = Instant::now();
    progress.stage("compiling", groups.len());
    let results: Vec<Got> = groups
        .par_iter()
        .map(|(key, members)| {
            if let Some(got) = early.take(key) {
                progress.inc();
                return got;
            }
            let p = &kept[members[0]];
            let mut warning = None;
            if let Some(cache) = cache {
                match cache.get(key) {
                    Lookup::Hit(c) => {
                        progress.inc();
                        return Got::Hit(c);
                    }
                    Lookup::Miss => {}
                    Lookup::Corrupt(why) => warning = Some(format!("warning: {why}")),
                }
            }
            let Some(rep) = representative(&reps, key, members, &kept, config, &options.targets, &sources) else {
                progress.inc();
                let e = compile::Error {
                    kind: compile::ErrorKind::Parse,
                    message: "the sources changed during the build".into(),
                    labels: Vec::new(),
                    notes: vec!["run the build again".into()],
                };
                return Got::Failed(e, warning);
            };
            let opts =
                compile::Options { targets: level_targets(p.level, &options.targets), limits: level_limits(p.level) };
            let got = match compile::compile(&rep.text, &p.shader.entry, p.shader.stage, &opts) {
                Ok(c) => Got::Compiled(c, warning),
                Err(e) => Got::Failed(e, warning),
            };
            progress.inc();
            got
        })
        .collect();
    // Compiling began during preprocessing: from the first key compiled to the last.
    let first_compile = early.first_start().map_or(t_compile, |t| t.min(t_compile));
    report.stats.seconds.compile = first_compile.elapsed().as_secs_f64();
    progress.finish();

    let mut compiled: HashMap<Key, Compiled> = HashMap::new();
    let mut fresh: Vec<Key> = Vec::new();
    for ((key, members), got) in groups.iter().zip(results) {
        match got {
            Got::Hit(c) => {
                report.stats.cache_hits += 1;
                compiled.insert(*key, c);
            }
            Got::Compiled(c, w) => {
                report.stats.compiled += 1;
                report.warnings.extend(w);
                compiled.insert(*key, c);
                fresh.push(*key);
            }
            Got::Failed(e, w) => {
                report.stats.compiled += 1;
                report.warnings.extend(w);
                let rep = representative(&reps, key, members, &kept, config, &options.targets, &sources);
                let rep_hash = rep.as_ref().map(|r| blake3::hash(r.text.as_bytes()));
                for &m in members {
                    let Ok(pm) = &pre[m] else { continue };
                    let mut diagnostic = if Some(pm.text_hash) == rep_hash {
                        map_error(&e, &rep.as_ref().expect("hash of it").map)
                    } else {
                        // Same tokens, other spacing: this member's own spans.
                        remap_member(config, &kept[m], &options.targets, &sources, &e)
                    };
                    if e.kind == compile::ErrorKind::EntryPoint {
                        let s = kept[m].shader;
                        let file =
                            config.path.file_name().map(|f| f.to_string_lossy().into_owned()).unwrap_or_default();
                        diagnostic.notes.push(format!(
                            "shader `{}` of {file} names entry point `{}` ({}) in {}",
                            s.name,
                            s.entry,
                            s.stage,
                            sources.display_name(&s.source_path)
                        ));
                    }
                    failures.push((diagnostic, vec![m]));
                }
            }
        }
    }
    drop(reps);

    if let Some(c) = cache {
        report.warnings.extend(c.warnings());
    }

    // Render failures: identical diagnostics once, naming every permutation they hit.
    report.stats.failed = failures.iter().map(|f| f.1.len()).sum();
    report.failures = render_failures(failures, &kept, &sources, options.color);

    // Every artifact's blake3, once, on all threads: the archive deduplicates blobs by it
    // and the cache's checksums are made of it.
    let hashes: HashMap<Key, Vec<blake3::Hash>> = compiled
        .par_iter()
        .map(|(k, c)| (*k, c.artifacts.iter().map(|(_, bytes)| blake3::hash(bytes)).collect()))
        .collect();

    // 5. Store what was compiled in the cache (on the other thread), while the archive and
    //    the loose files are written.
    let store = || -> Vec<String> {
        let Some(c) = cache else { return Vec::new() };
        let entries: Vec<(Key, &Compiled, &[blake3::Hash])> =
            fresh.iter().map(|k| (*k, &compiled[k], &hashes[k][..])).collect();
        match c.put_pack_hashed(&entries) {
            Ok(()) => Vec::new(),
            Err(e) => vec![format!("warning: cannot store {} cache entries: {e}", entries.len())],
        }
    };
    if report.stats.failed > 0 {
        let warnings = store();
        report.warnings.extend(warnings);
        write_stats(options, &mut report, start)?;
        return Err(Error::Failed(Box::new(report)));
    }
    let (written, warnings) =
        rayon::join(|| write_outputs(options, &kept, &pre, &compiled, &hashes, stamp.as_ref(), &mut report), store);
    report.warnings.extend(warnings);
    written?;
    write_stats(options, &mut report, start)?;
    Ok(report)
}

/// A key's compiled result: from the cache, compiled now, or failed.
enum Got {
    Hit(Compiled),
    Compiled(Compiled, Option<String>),
    Failed(compile::Error, Option<String>),
}

/// The results of keys compiled during preprocessing.
#[derive(Default)]
struct Early {
    map: Mutex<(std::collections::HashSet<Key>, HashMap<Key, Got>)>,
    /// When the first key began compiling.
    start: Mutex<Option<Instant>>,
}

impl Early {
    /// True for the first caller with this key (who then compiles it).
    fn claim(&self, key: Key) -> bool {
        self.map.lock().expect("no panics while locked").0.insert(key)
    }
    fn done(&self, key: Key, got: Got) {
        self.map.lock().expect("no panics while locked").1.insert(key, got);
    }
    fn take(&self, key: &Key) -> Option<Got> {
        self.map.lock().expect("no panics while locked").1.remove(key)
    }
    fn started(&self) {
        self.start.lock().expect("no panics while locked").get_or_insert_with(Instant::now);
    }
    fn first_start(&self) -> Option<Instant> {
        *self.start.lock().expect("no panics while locked")
    }
}

/// A key from the cache, else compiled from `text` (a permutation `p` of that key).
fn lookup_or_compile(cache: Option<&Cache>, key: &Key, p: &Permutation<'_>, text: &str, targets: &[Target]) -> Got {
    let mut warning = None;
    if let Some(cache) = cache {
        match cache.get(key) {
            Lookup::Hit(c) => return Got::Hit(c),
            Lookup::Miss => {}
            Lookup::Corrupt(why) => warning = Some(format!("warning: {why}")),
        }
    }
    let opts = compile::Options { targets: level_targets(p.level, targets), limits: level_limits(p.level) };
    match compile::compile(text, &p.shader.entry, p.shader.stage, &opts) {
        Ok(c) => Got::Compiled(c, warning),
        Err(e) => Got::Failed(e, warning),
    }
}

/// The archive, the loose files of `--emit-dir` and the archive's stamp.
fn write_outputs(
    options: &Options,
    kept: &[Permutation<'_>],
    pre: &[Result<Pre, Diagnostic<FileId>>],
    compiled: &HashMap<Key, Compiled>,
    hashes: &HashMap<Key, Vec<blake3::Hash>>,
    stamp: Option<&(&Cache, &PathBuf, blake3::Hash)>,
    report: &mut Report,
) -> Result<(), Error> {
    // 5. The archive and the loose files.
    let mut writer = ArchiveWriter::new();
    writer.set_naga_version(compile::NAGA_VERSION);
    let mut index: BTreeMap<String, BTreeMap<&'static str, String>> = BTreeMap::new();
    let mut emitted: HashMap<blake3::Hash, String> = HashMap::new();
    for (i, p) in kept.iter().enumerate() {
        let Ok(pm) = &pre[i] else { continue };
        let c = &compiled[&pm.key];
        let shader = writer.add_shader(ShaderRecord {
            name: p.shader.name.clone(),
            level: p.level.name.clone(),
            entry: p.shader.entry.clone(),
            stage: p.shader.stage,
            dimensions: p
                .shader
                .dimensions
                .iter()
                .map(|d| DimensionRecord { name: d.name.clone(), labels: d.labels.clone() })
                .collect(),
        });
        let reflection = writer.add_reflection(&c.reflection);
        let name = p.name();
        let mut artifacts = Vec::with_capacity(c.artifacts.len());
        for ((t, bytes), hash) in c.artifacts.iter().zip(&hashes[&pm.key]) {
            let hash = *hash;
            artifacts.push((*t, writer.add_blob_ref(bytes, hash)));
            if let Some(dir) = &options.emit_dir {
                let file = match emitted.get(&hash) {
                    Some(f) => f.clone(),
                    None => {
                        let f = format!("{}.{}", &hash.to_hex()[..32], t.extension(p.shader.stage));
                        archive::write_atomic_unsynced(&dir.join(&f), bytes)
                            .map_err(|e| Error::Io(format!("error: cannot write {}: {e}", dir.join(&f).display())))?;
                        emitted.insert(hash, f.clone());
                        f
                    }
                };
                index.entry(name.clone()).or_default().insert(t.name(), file);
            }
        }
        report.stats.permutation_artifacts += artifacts.len();
        writer.add_permutation(PermutationRecord { name, shader, values: p.values.clone(), reflection, artifacts });
    }
    report.stats.artifacts = writer.blob_count();
    if let Some(dir) = &options.emit_dir {
        let json = serde_json::to_vec_pretty(&index).expect("index serializes");
        let path = dir.join("index.json");
        archive::write_atomic_unsynced(&path, &json)
            .map_err(|e| Error::Io(format!("error: cannot write {}: {e}", path.display())))?;
    }
    if let Some(out) = &options.output {
        writer.write_unsynced(out).map_err(|e| Error::Io(format!("error: {e}")))?;
        report.archive = Some(out.clone());
        if let Some((c, out, fingerprint)) = stamp {
            // Failing to stamp only costs a full warm build next time.
            let _ = c.stamp_archive(out, fingerprint, (report.stats.artifacts, report.stats.permutation_artifacts));
        }
    }
    Ok(())
}

fn write_stats(options: &Options, report: &mut Report, start: Instant) -> Result<(), Error> {
    report.stats.seconds.total = start.elapsed().as_secs_f64();
    if let Some(path) = &options.stats_json {
        let json = serde_json::to_vec_pretty(&report.stats).expect("stats serialize");
        archive::write_atomic_unsynced(path, &json)
            .map_err(|e| Error::Io(format!("error: cannot write {}: {e}", path.display())))?;
    }
    Ok(())
}

fn preprocess_one(
    config: &Config,
    p: &Permutation<'_>,
    targets: &[Target],
    sources: &SourceCache,
) -> Result<(Pre, preprocess::Output), Diagnostic<FileId>> {
    if let Some(message) = &p.error {
        return Err(Diagnostic::error().with_message(message.clone()));
    }
    let opts = p.preprocess_options(config);
    let output = preprocess::preprocess_file(&p.shader.source_path, &opts, sources).map_err(|e| e.diagnostic)?;
    let token_hash = output.token_hash();
    let key = Key::new(
        &token_hash,
        &p.shader.entry,
        p.shader.stage,
        &p.level.name,
        &level_limits(p.level),
        &level_targets(p.level, targets),
    );
    let pre = Pre {
        key,
        text_hash: blake3::hash(output.text.as_bytes()),
        token_hash,
        files: output.files.iter().map(|f| sources.path(*f)).collect(),
        warnings: output.warnings.iter().map(|w| preprocess::render(std::slice::from_ref(w), sources, false)).collect(),
    };
    Ok((pre, output))
}

/// Everything the archive's content depends on: each kept permutation's name, shader
/// record and key, in order, and the versions.
fn build_fingerprint(kept: &[Permutation<'_>], pre: &[Result<Pre, Diagnostic<FileId>>]) -> blake3::Hash {
    let mut h = blake3::Hasher::new();
    h.update(b"kiln build fingerprint v1\0");
    h.update(crate::VERSION.as_bytes());
    h.update(b"\0");
    h.update(compile::NAGA_VERSION.as_bytes());
    for (p, r) in kept.iter().zip(pre) {
        let Ok(r) = r else { continue };
        let dims: Vec<(&str, &[String])> =
            p.shader.dimensions.iter().map(|d| (d.name.as_str(), d.labels.as_slice())).collect();
        let line = format!("\0{}\0{}\0{}\0{:?}\0{:?}\0", p.name(), p.shader.entry, p.shader.stage, p.values, dims);
        h.update(line.as_bytes());
        h.update(&r.key.0);
    }
    h.finalize()
}

/// The preprocessed output of a key's first member: kept from preprocessing, or (when every
/// member was served by its record) made now. `None` if it no longer gives that key.
fn representative<'a>(
    reps: &'a HashMap<Key, Representative>,
    key: &Key,
    members: &[usize],
    kept: &[Permutation<'_>],
    config: &Config,
    targets: &[Target],
    sources: &SourceCache,
) -> Option<std::borrow::Cow<'a, preprocess::Output>> {
    if let Some(r) = reps.get(key) {
        return Some(std::borrow::Cow::Borrowed(&r.output));
    }
    let (pre, output) = preprocess_one(config, &kept[members[0]], targets, sources).ok()?;
    (pre.key == *key).then_some(std::borrow::Cow::Owned(output))
}

/// What every permutation's preprocessing record key shares: the configuration's text (its
/// defines, derived values, roots and sources) and folder, and the versions. Read once per
/// build.
fn direct_base(config: &Config) -> blake3::Hash {
    let mut h = blake3::Hasher::new();
    let mut field = |bytes: &[u8]| {
        h.update(&(bytes.len() as u64).to_le_bytes());
        h.update(bytes);
    };
    field(b"kiln direct v2");
    // Unreadable now (removed during the build): a key no record has.
    field(&std::fs::read(&config.path).unwrap_or_else(|_| b"\0unreadable".to_vec()));
    field(config.path.as_os_str().as_encoded_bytes());
    field(config.dir.as_os_str().as_encoded_bytes());
    let opts = preprocess::Options::default();
    field(&(opts.max_expansion_depth as u64).to_le_bytes());
    field(&(opts.max_output_bytes as u64).to_le_bytes());
    field(crate::compile::NAGA_VERSION.as_bytes());
    h.finalize()
}

/// The key of a permutation's preprocessing record: everything preprocessing and the
/// compile key depend on, except the files' contents (checked against the record). Its
/// defines follow from the configuration's text (in `base`) and its canonical name.
fn direct_key(base: &blake3::Hash, p: &Permutation<'_>, targets: &[Target]) -> Key {
    let mut h = blake3::Hasher::new();
    h.update(base.as_bytes());
    h.update(p.name().as_bytes());
    let targets = level_targets(p.level, targets);
    Key::new(&h.finalize(), &p.shader.entry, p.shader.stage, &p.level.name, &level_limits(p.level), &targets)
}

/// The key of a configuration's set of preprocessing records: its path and the options
/// that choose its permutations.
fn records_key(config: &Config, options: &Options) -> Key {
    let inputs = format!("kiln records v1\n{}\n{:?}\n{:?}", config.path.display(), options.levels, options.targets);
    Key::new(&blake3::hash(inputs.as_bytes()), "", crate::Stage::Compute, "", &Limits::desktop(), &[])
}

fn to_record(pre: &Pre, output: &preprocess::Output, sources: &SourceCache, text_hashes: &FileHashes) -> cache::Record {
    use codespan_reporting::files::Files;
    cache::Record {
        key: pre.key.to_hex(),
        token_hash: pre.token_hash.to_hex().to_string(),
        text_hash: pre.text_hash.to_hex().to_string(),
        files: output
            .files
            .iter()
            .map(|&f| {
                let path = sources.path(f);
                let hash = text_hashes.get_or_insert_with(&path, || {
                    sources.source(f).ok().map(|t| blake3::hash(t.as_ref().as_bytes()).to_hex().to_string())
                });
                (path, hash.unwrap_or_default())
            })
            .collect(),
        absent: output.absent.clone(),
        warnings: pre.warnings.clone(),
    }
}

/// The record's result, if every file it lists still has the recorded contents and no file
/// has appeared where an include looked and found none (it would be found first now).
fn from_record(r: &cache::Record, hashes: &FileHashes) -> Option<Pre> {
    for (path, hash) in &r.files {
        if hashes.get(path).as_deref() != Some(hash.as_str()) {
            return None;
        }
    }
    if r.absent.iter().any(|path| hashes.get(path).is_some()) {
        return None;
    }
    let hash = |hex: &str| blake3::Hash::from_hex(hex).ok();
    let key = hash(&r.key)?;
    Some(Pre {
        key: Key(*key.as_bytes()),
        text_hash: hash(&r.text_hash)?,
        token_hash: hash(&r.token_hash)?,
        files: r.files.iter().map(|(p, _)| p.clone()).collect(),
        warnings: r.warnings.clone(),
    })
}

/// A failing key's error on a member whose text differs from the representative's only in
/// spacing: preprocess and compile that member again for spans into its own text.
fn remap_member(
    config: &Config,
    p: &Permutation<'_>,
    targets: &[Target],
    sources: &SourceCache,
    fallback: &compile::Error,
) -> Diagnostic<FileId> {
    let unmapped = || Diagnostic::error().with_message(fallback.message.clone()).with_notes(fallback.notes.clone());
    let Ok((_, output)) = preprocess_one(config, p, targets, sources) else {
        return unmapped();
    };
    let opts = compile::Options { targets: level_targets(p.level, targets), limits: level_limits(p.level) };
    match compile::compile(&output.text, &p.shader.entry, p.shader.stage, &opts) {
        Err(e) => map_error(&e, &output.map),
        Ok(_) => unmapped(),
    }
}

/// Maps a compile error's spans (into preprocessed text) onto the original files.
pub fn map_error(e: &compile::Error, map: &preprocess::SourceMap) -> Diagnostic<FileId> {
    let mut labels: Vec<Label<FileId>> = Vec::new();
    for (i, (range, message)) in e.labels.iter().enumerate() {
        for mut l in map.labels(range.clone(), message) {
            if i > 0 {
                l.style = LabelStyle::Secondary;
            }
            if !labels.iter().any(|x| x.file_id == l.file_id && x.range == l.range && x.message == l.message) {
                labels.push(l);
            }
        }
    }
    Diagnostic::error().with_message(e.message.clone()).with_labels(labels).with_notes(e.notes.clone())
}

fn render_failures(
    failures: Vec<(Diagnostic<FileId>, Vec<usize>)>,
    kept: &[Permutation<'_>],
    sources: &SourceCache,
    color: bool,
) -> Vec<String> {
    // Group by level and the diagnostic as rendered without colour and without the
    // permutation note.
    let mut order: Vec<(String, String)> = Vec::new();
    let mut groups: HashMap<(String, String), (Diagnostic<FileId>, Vec<usize>)> = HashMap::new();
    for (d, members) in failures {
        let text = preprocess::render(std::slice::from_ref(&d), sources, false);
        let key = (kept[members[0]].level.name.clone(), text);
        match groups.get_mut(&key) {
            Some(g) => g.1.extend(members),
            None => {
                order.push(key.clone());
                groups.insert(key, (d, members));
            }
        }
    }
    let mut out = Vec::new();
    for key in order {
        let (mut d, mut members) = groups.remove(&key).expect("grouped above");
        members.sort_unstable();
        let p = &kept[members[0]];
        let mut limits = match p.level.limits {
            permute::Limits::Default => "default",
            permute::Limits::Downlevel => "downlevel",
        }
        .to_string();
        for (field, value) in &p.level.limit_overrides {
            limits.push_str(&format!(" with {field} = {value}"));
        }
        let note = if members.len() == 1 {
            format!("in permutation {} (level `{}`, {limits} limits)", p.name(), p.level.name)
        } else {
            let names: Vec<String> = members.iter().map(|&m| format!("  {}", kept[m].name())).collect();
            format!(
                "in {} permutations (level `{}`, {limits} limits):\n{}",
                names.len(),
                p.level.name,
                names.join("\n")
            )
        };
        d.notes.push(note);
        out.push(preprocess::render(std::slice::from_ref(&d), sources, color));
    }
    out
}

/// Dimensions whose value never changes the token stream: in every set of kept permutations
/// that differ only in that dimension, all have one token hash.
fn dead_dimensions(kept: &[Permutation<'_>], pre: &[Result<Pre, Diagnostic<FileId>>]) -> Vec<DeadDimension> {
    let mut by_shader: BTreeMap<(usize, &str, &str), Vec<usize>> = BTreeMap::new();
    let mut first: HashMap<(&str, &str), usize> = HashMap::new();
    for (i, p) in kept.iter().enumerate() {
        let n = first.len();
        let order = *first.entry((&p.shader.name, &p.level.name)).or_insert(n);
        by_shader.entry((order, &p.shader.name, &p.level.name)).or_default().push(i);
    }
    let mut out = Vec::new();
    for ((_, shader, level), members) in by_shader {
        let dims = &kept[members[0]].shader.dimensions;
        for (d, dim) in dims.iter().enumerate() {
            if dim.values.len() < 2 {
                continue;
            }
            let mut rows: HashMap<Vec<i64>, Vec<blake3::Hash>> = HashMap::new();
            let mut complete = true;
            for &m in &members {
                let Ok(pm) = &pre[m] else {
                    complete = false;
                    break;
                };
                let mut rest = kept[m].values.clone();
                rest.remove(d);
                rows.entry(rest).or_default().push(pm.token_hash);
            }
            let varies = rows.values().any(|hs| hs.len() > 1);
            let dead = complete && varies && rows.values().all(|hs| hs.iter().all(|h| *h == hs[0]));
            if dead {
                out.push(DeadDimension {
                    shader: shader.to_string(),
                    level: level.to_string(),
                    dimension: dim.name.clone(),
                    values: dim.values.len(),
                });
            }
        }
    }
    out
}

/// The cache folder for `options` (see [`CacheDir::Auto`]), opened; `None` without a cache.
fn open_cache(options: &Options, config: &Config) -> Result<Option<Cache>, cache::Error> {
    let dir = match &options.cache {
        CacheDir::Disabled => return Ok(None),
        CacheDir::Dir(d) => d.clone(),
        CacheDir::Auto => default_cache_dir(&config.dir),
    };
    Cache::open(dir).map(Some)
}

/// `KILN_CACHE_DIR`, else `$CARGO_TARGET_DIR/kiln-cache`, else `target/kiln-cache` in the
/// cargo workspace around `config_dir`, else `config_dir/.kiln-cache`.
pub fn default_cache_dir(config_dir: &Path) -> PathBuf {
    if let Some(d) = std::env::var_os("KILN_CACHE_DIR").filter(|d| !d.is_empty()) {
        return PathBuf::from(d);
    }
    if let Some(d) = std::env::var_os("CARGO_TARGET_DIR").filter(|d| !d.is_empty()) {
        return PathBuf::from(d).join("kiln-cache");
    }
    let mut package = None;
    for dir in config_dir.ancestors() {
        let manifest = dir.join("Cargo.toml");
        if let Ok(text) = std::fs::read_to_string(&manifest) {
            if text.contains("[workspace]") {
                return dir.join("target").join("kiln-cache");
            }
            package.get_or_insert_with(|| dir.to_path_buf());
        }
    }
    match package {
        Some(dir) => dir.join("target").join("kiln-cache"),
        None => config_dir.join(".kiln-cache"),
    }
}

/// A progress bar on a terminal; nothing in CI or when stderr is redirected.
struct Progress {
    bar: Option<indicatif::ProgressBar>,
}

impl Progress {
    fn new(wanted: bool) -> Progress {
        let show = wanted && std::io::stderr().is_terminal() && std::env::var_os("CI").is_none();
        let bar = show.then(|| {
            let bar = indicatif::ProgressBar::new(0);
            bar.set_style(
                indicatif::ProgressStyle::with_template("{prefix:>13} [{bar:30}] {pos}/{len} {elapsed}")
                    .expect("valid template")
                    .progress_chars("=> "),
            );
            bar
        });
        Progress { bar }
    }
    fn stage(&self, name: &'static str, len: usize) {
        if let Some(b) = &self.bar {
            b.set_length(len as u64);
            b.set_position(0);
            b.set_prefix(name);
        }
    }
    fn inc(&self) {
        if let Some(b) = &self.bar {
            b.inc(1);
        }
    }
    fn finish(&self) {
        if let Some(b) = &self.bar {
            b.finish_and_clear();
        }
    }
}
