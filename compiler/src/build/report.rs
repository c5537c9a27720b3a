//! Report: the counts of `--stats-json`, the files read, warnings, dead dimensions, and
//! failures rendered once per distinct diagnostic with the permutations they hit.

use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet};
use std::path::PathBuf;
use std::time::Instant;

use codespan_reporting::diagnostic::Diagnostic;

use super::assemble::Written;
use super::compile::{self, Compiler, Outcome, Outcomes};
use super::group::Keys;
use super::plan::Plan;
use super::preprocess::{Preprocessed, Preprocessor};
use super::{Error, Options};
use crate::archive;
use crate::permute;
use crate::preprocess::{self, FileId, SourceCache};

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
    /// Distinct keys left to the other shards (`--shard`).
    pub other_shards: usize,
    /// Distinct blobs in the archive (identical outputs are stored once).
    pub artifacts: usize,
    /// (permutation, target) pairs in the archive.
    pub permutation_artifacts: usize,
    /// Blobs of the archive copied, compressed as they were, from the archive it replaced
    /// (the output file, when this version wrote it) instead of compressed again.
    pub archive_reused_blobs: usize,
    /// Permutations that failed to preprocess or compile.
    pub failed: usize,
    /// Permutations preprocessed by this build (the others matched their cached
    /// preprocessing record: same defines, same file contents).
    pub preprocessed: usize,
    /// Compiled keys whose compacted module equalled an earlier key's: their writers did not
    /// run, the artifacts were that key's (see [`crate::compile::SharedWriters`]).
    pub shared_modules: usize,
    /// Distinct keys served by the remote cache (counted in `cache_hits` too).
    pub remote_hits: u64,
    /// Entries this build stored to the remote cache.
    pub remote_writes: u64,
    /// Failed remote operations (the first one turns the remote off for the build).
    pub remote_errors: u64,
    /// The estimated single-core compile time of every distinct key, in milliseconds
    /// (`kiln::permute::budget::estimate_compile_ms`); only when `[budget] max_distinct` or
    /// `max_compile_ms` is set.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub estimated_compile_ms: Option<f64>,
    /// With `--usage`: permutations built that the usage files record or that `[usage]
    /// keep` or `always` keep.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub used: Option<usize>,
    /// With `--usage`: permutations `--usage-only` left out (0 without it).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub left_out: Option<usize>,
    /// With `--usage`: `used` and `left_out` per shader.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub shaders: Option<std::collections::BTreeMap<String, super::ShaderUsage>>,
    /// With `--usage`: pipelines in the archive's pipeline manifest.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pipelines: Option<usize>,
    /// With `--usage`: recorded pipelines left out of the manifest (a permutation of theirs
    /// is not in the archive).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pipelines_left_out: Option<usize>,
    /// Where the time went.
    pub seconds: Seconds,
}

/// Wall-clock seconds of a build and its stages.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct Seconds {
    /// The whole build.
    pub total: f64,
    /// Preprocessing (and grouping by key).
    pub preprocess: f64,
    /// Compiling, from the first key to the last artifact.
    pub compile: f64,
}

/// A dimension that never changes its shader's text at a level.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct DeadDimension {
    /// The shader.
    pub shader: String,
    /// The level.
    pub level: String,
    /// The dimension.
    pub dimension: String,
    /// How many values it takes: the factor of build work it multiplies for nothing.
    pub values: usize,
}

/// What a build did.
#[derive(Debug, Default)]
pub struct Report {
    /// The counts (`--stats-json`).
    pub stats: Stats,
    /// The config and every file any permutation read (absolute, sorted, deduplicated).
    pub files_read: Vec<PathBuf>,
    /// Rendered warnings (preprocessor warnings, corrupted cache entries, dead dimensions).
    pub warnings: Vec<String>,
    /// Rendered failures, one per distinct diagnostic, each naming its permutations.
    pub failures: Vec<String>,
    /// The dimensions that never change their shader's text.
    pub dead_dimensions: Vec<DeadDimension>,
    /// The archive written, if any.
    pub archive: Option<PathBuf>,
}

impl Report {
    /// The summary line: kept, skipped, distinct, compiled, cache hits, failed, time.
    pub fn summary(&self) -> String {
        let s = &self.stats;
        let shard = match s.other_shards {
            0 => String::new(),
            n => format!(", {n} left to other shards"),
        };
        format!(
            "{} permutations ({} skipped), {} distinct, {} compiled, {} cache hits{shard}, {} failed in {:.2}s",
            s.permutations, s.skipped, s.unique_sources, s.compiled, s.cache_hits, s.failed, s.seconds.total
        )
    }
}

/// The report as the stages fill it in.
pub(super) struct Builder<'o> {
    options: &'o Options,
    start: Instant,
    report: Report,
    /// Diagnostics not yet rendered, each with the permutations it hit.
    failures: Vec<(Diagnostic<FileId>, Vec<usize>)>,
}

impl<'o> Builder<'o> {
    pub fn new(options: &'o Options, start: Instant) -> Self {
        Builder { options, start, report: Report::default(), failures: Vec::new() }
    }

    pub fn planned(&mut self, plan: &Plan<'_>) {
        self.report.stats.permutations = plan.len();
        self.report.stats.skipped = usize::try_from(plan.skipped).unwrap_or(usize::MAX);
        if let Some(u) = &plan.usage {
            self.report.stats.used = Some(u.shaders.values().map(|s| s.used).sum());
            self.report.stats.left_out = Some(u.left_out.len());
            self.report.stats.shaders = Some(u.shaders.clone());
            self.report.stats.pipelines = Some(u.pipelines.len());
            self.report.stats.pipelines_left_out = Some(u.pipelines_left_out);
            self.report.warnings.push(u.summary(self.options.usage_only));
        }
        if plan.is_empty() && plan.skipped > 0 {
            self.report.warnings.push(format!(
                "warning: skip rules skip every one of the {} permutations: nothing is compiled",
                plan.skipped
            ));
        }
    }

    pub fn estimated_compile_ms(&mut self, ms: Option<f64>) {
        self.report.stats.estimated_compile_ms = ms.map(|m| (m * 10.0).round() / 10.0);
    }

    /// Every file the build read so far (after [`Builder::preprocessed`]).
    pub fn files_read(&self) -> &[std::path::PathBuf] {
        &self.report.files_read
    }

    /// Counts, warnings (each distinct one once), preprocessing failures, files read.
    pub fn preprocessed(
        &mut self,
        plan: &Plan<'_>,
        preprocessor: &Preprocessor<'_>,
        pre: &Preprocessed,
        t: Instant,
    ) -> Result<(), Error> {
        let report = &mut self.report;
        report.stats.preprocessed = preprocessor.count();
        report.stats.seconds.preprocess = t.elapsed().as_secs_f64();
        let lists = preprocessor.lists();
        let (mut seen, mut warning_lists, mut file_lists) = (HashSet::new(), HashSet::new(), HashSet::new());
        let mut files = BTreeSet::new();
        files.insert(plan.config.path.clone());
        // Each row's lists (the rows are in their file).
        let mut row_lists = Vec::with_capacity(pre.row_count());
        pre.each_row(|r| row_lists.push((r.warnings, r.files))).map_err(super::preprocess::read_back)?;
        for (warnings, file_list) in (0..pre.len()).filter_map(|i| pre.row_number(i)).map(|r| row_lists[r]) {
            if warning_lists.insert(warnings) {
                for w in lists.warnings.get(warnings).iter() {
                    if seen.insert(w) {
                        report.warnings.push(w.clone());
                    }
                }
            }
            if file_lists.insert(file_list) {
                files.extend(lists.files.get(file_list).iter().map(|(path, _)| path.clone()));
            }
        }
        for (i, d) in pre.errors() {
            self.failures.push(((**d).clone(), vec![*i]));
            // A failed permutation still read files: the failing header among them.
            for l in &d.labels {
                files.insert(preprocessor.sources.path(l.file_id));
            }
        }
        files.retain(|f| !f.as_os_str().is_empty());
        report.files_read = files.into_iter().collect();
        Ok(())
    }

    /// The number of distinct keys.
    pub fn distinct(&mut self, keys: usize) {
        self.report.stats.unique_sources = keys;
    }

    /// The dimensions that never change a shader's text.
    pub fn dead_dimensions(&mut self, plan: &Plan<'_>, pre: &Preprocessed, same: &[u32]) {
        let report = &mut self.report;
        report.dead_dimensions = dead_dimensions(plan, pre, same);
        for d in &report.dead_dimensions {
            report.warnings.push(format!(
                "warning: dimension `{}` of `{}` never changes the shader's text at level `{}`: its {} values multiply the permutations for nothing",
                d.dimension, d.shader, d.level, d.values
            ));
        }
    }

    /// Whether some permutation failed so far.
    pub fn failed(&self) -> bool {
        !self.failures.is_empty() || self.report.stats.failed > 0
    }

    /// The archive is already the output of this build: every key counts as a hit.
    pub fn up_to_date(mut self, keys: usize, counts: (usize, usize)) -> Result<Report, Error> {
        self.report.stats.cache_hits = keys;
        self.report.stats.artifacts = counts.0;
        self.report.stats.permutation_artifacts = counts.1;
        self.report.archive = self.options.output.clone();
        self.finish()
    }

    /// Counts the keys' outcomes, maps compile failures onto each permutation's text and
    /// renders every failure.
    pub fn compiled(
        &mut self,
        plan: &Plan<'_>,
        preprocessor: &Preprocessor<'_>,
        compiler: &Compiler<'_>,
        keys: &Keys,
        outcomes: Outcomes,
        pre: &Preprocessed,
    ) {
        let stats = &mut self.report.stats;
        stats.seconds.compile = compiler.first_start().map_or(0.0, |t| t.elapsed().as_secs_f64());
        stats.shared_modules = compiler.shared_modules();
        stats.cache_hits += outcomes.hits;
        stats.other_shards += outcomes.elsewhere;
        stats.compiled += outcomes.compiled;
        for (k, outcome) in outcomes.notable {
            match outcome {
                Outcome::Hit | Outcome::Elsewhere => {}
                Outcome::Compiled(w) => self.report.warnings.extend(w),
                Outcome::Failed(failed) => {
                    let (e, w) = *failed;
                    self.report.warnings.extend(w);
                    // (A key that cannot be read back is not checked against the text made again.)
                    let key = keys.key(k).ok();
                    self.failures.extend(compile::failures(plan, preprocessor, pre, key.as_ref(), keys.members(k), &e));
                }
            }
        }
        let failures = std::mem::take(&mut self.failures);
        self.report.stats.failed = failures.iter().map(|f| f.1.len()).sum();
        self.report.failures = render_failures(failures, plan, &preprocessor.sources, self.options.color);
    }

    /// The remote cache's counts.
    pub fn remote(&mut self, remote: crate::cache::remote::Stats) {
        let stats = &mut self.report.stats;
        (stats.remote_hits, stats.remote_writes, stats.remote_errors) = (remote.hits, remote.writes, remote.errors);
    }

    pub fn warnings(&mut self, warnings: Vec<String>) {
        self.report.warnings.extend(warnings);
    }

    pub fn assembled(&mut self, written: Written) {
        self.report.stats.artifacts = written.artifacts;
        self.report.stats.permutation_artifacts = written.permutation_artifacts;
        self.report.stats.archive_reused_blobs = written.reused_blobs;
        self.report.archive = written.archive;
    }

    /// The total time, and `--stats-json` written.
    pub fn finish(mut self) -> Result<Report, Error> {
        self.report.stats.seconds.total = self.start.elapsed().as_secs_f64();
        if let Some(path) = &self.options.stats_json {
            let json = serde_json::to_vec_pretty(&self.report.stats).expect("stats serialize");
            archive::write_atomic_unsynced(path, &json)
                .map_err(|e| Error::Io(format!("error: cannot write {}: {e}", path.display())))?;
        }
        Ok(self.report)
    }
}

fn render_failures(
    failures: Vec<(Diagnostic<FileId>, Vec<usize>)>,
    plan: &Plan<'_>,
    sources: &SourceCache,
    color: bool,
) -> Vec<String> {
    // Group by level and the diagnostic as rendered without colour and without the
    // permutation note.
    let mut order: Vec<(String, String)> = Vec::new();
    let mut groups: HashMap<(String, String), (Diagnostic<FileId>, Vec<usize>)> = HashMap::new();
    for (d, members) in failures {
        let text = preprocess::render(std::slice::from_ref(&d), sources, false);
        let key = (plan.shader_level(members[0]).1.name.clone(), text);
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
        let (_, level) = plan.shader_level(members[0]);
        let mut limits = match level.limits {
            permute::Limits::Default => "default",
            permute::Limits::Downlevel => "downlevel",
        }
        .to_string();
        for (field, value) in &level.limit_overrides {
            limits.push_str(&format!(" with {field} = {value}"));
        }
        let note = if members.len() == 1 {
            format!("in permutation {} (level `{}`, {limits} limits)", plan.name(members[0]), level.name)
        } else {
            let names: Vec<String> = members.iter().map(|&m| format!("  {}", plan.name(m))).collect();
            format!("in {} permutations (level `{}`, {limits} limits):\n{}", names.len(), level.name, names.join("\n"))
        };
        d.notes.push(note);
        out.push(preprocess::render(std::slice::from_ref(&d), sources, color));
    }
    out
}

/// Dimensions whose value never changes the token stream: in every set of kept permutations
/// that differ only in that dimension, all have one token hash. (Within one shader at one
/// level, keys differ exactly where token hashes do: the rest of a key is the shader's and
/// the level's.)
fn dead_dimensions(plan: &Plan<'_>, pre: &Preprocessed, same: &[u32]) -> Vec<DeadDimension> {
    type Runs<'c> = (&'c [permute::Dimension], Vec<std::ops::Range<usize>>);
    let mut by_shader: BTreeMap<(usize, &str, &str), Runs<'_>> = BTreeMap::new();
    let mut first: HashMap<(&str, &str), usize> = HashMap::new();
    for (shader, level, range) in plan.runs() {
        let n = first.len();
        let order = *first.entry((&shader.name, &level.name)).or_insert(n);
        by_shader.entry((order, &shader.name, &level.name)).or_insert((&shader.dimensions, Vec::new())).1.push(range);
    }
    let mut out = Vec::new();
    for ((_, shader, level), (dims, ranges)) in by_shader {
        // The members, through their runs (not collected: 8 B a permutation of the group).
        let count: usize = ranges.iter().map(|r| r.len()).sum();
        if count == 0 {
            continue;
        }
        let members = || ranges.iter().flat_map(|r| r.clone());
        for (d, dim) in dims.iter().enumerate() {
            if dim.values.len() < 2 {
                continue;
            }
            // Per set of values of the other dimensions (by a 64-bit hash of them: a
            // collision could only move a warning), its first member's row, whether it has
            // several members and whether they all have that row's key: 16 bytes a set, where
            // the sets' values and members in vectors took much more a permutation.
            // Sized once for the sets of a full product of the values (so no old and new
            // table at once while it doubles; skip rules that leave more sets grow it).
            let sets = count / dim.values.len();
            let mut rows: HashMap<u64, (u32, bool, bool)> = HashMap::with_capacity(sets);
            let mut complete = true;
            for m in members() {
                let Some(row) = pre.row_number(m) else {
                    complete = false;
                    break;
                };
                let mut h = xxhash_rust::xxh3::Xxh3::new();
                for (_, v) in plan.values(m).into_iter().enumerate().filter(|&(i, _)| i != d) {
                    h.update(&v.to_le_bytes());
                }
                // Row numbers fit in 32 bits: the plan's permutations do ([`Plan::new`]).
                rows.entry(h.digest())
                    .and_modify(|(first, several, all_same)| {
                        *several = true;
                        *all_same &= same[*first as usize] == same[row];
                    })
                    .or_insert((row as u32, false, true));
            }
            let varies = rows.values().any(|r| r.1);
            let dead = complete && varies && rows.values().all(|r| r.2);
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
