//! Diagnostics: the active permutation of a shader checked at once, the rest of its domain
//! in the background (distinct sources only, cancellable), each error at its original file,
//! line and column.

use std::collections::{HashMap, HashSet};
use std::path::PathBuf;
use std::sync::Arc;

use codespan_reporting::diagnostic::{Diagnostic, LabelStyle, Severity};
use lsp_types::{DiagnosticSeverity, Position, Range};

use crate::compile;
use crate::permute::{Config, Permutation};
use crate::preprocess::{self, FileId, SourceCache};

use super::text::thousands;
pub use super::workspace::FileDiag;
use super::workspace::{cache_with, Active, Overlays};

/// A codespan diagnostic from `cache`'s files as a [`FileDiag`] at its primary label
/// (`fallback`'s first line when it has none).
fn locate(d: &Diagnostic<FileId>, cache: &SourceCache, fallback: &std::path::Path) -> FileDiag {
    let label = d.labels.iter().find(|l| l.style == LabelStyle::Primary).or(d.labels.first());
    let (path, range) = match label {
        Some(l) => {
            let pos = |o: usize| {
                let (line, col) = cache.location(l.file_id, o);
                Position { line: line.saturating_sub(1) as u32, character: col.saturating_sub(1) as u32 }
            };
            (cache.path(l.file_id), Range { start: pos(l.range.start), end: pos(l.range.end) })
        }
        None => (fallback.to_path_buf(), Range::default()),
    };
    let mut message = d.message.clone();
    if let Some(l) = label.filter(|l| !l.message.is_empty()) {
        message.push_str(&format!(" ({})", l.message));
    }
    let severity = match d.severity {
        Severity::Warning => DiagnosticSeverity::WARNING,
        Severity::Note | Severity::Help => DiagnosticSeverity::INFORMATION,
        _ => DiagnosticSeverity::ERROR,
    };
    FileDiag { path, range, severity, message, context: String::new() }
}

/// What one permutation's text gave: its errors (none when it validates).
fn check_text(
    p: &Permutation<'_>,
    config: &Config,
    cache: &SourceCache,
) -> (Option<preprocess::Output>, Vec<FileDiag>) {
    let source = &p.shader.source_path;
    let opts = p.preprocess_options(config);
    match preprocess::preprocess_file(source, &opts, cache) {
        Err(e) => (None, vec![locate(&e.diagnostic, cache, source)]),
        Ok(out) => {
            let mut diags: Vec<FileDiag> = out.warnings.iter().map(|w| locate(w, cache, source)).collect();
            let limits = compile::Limits::for_level(p.level);
            if let Err(e) = compile::check(&out.text, &p.shader.entry, p.shader.stage, &limits) {
                diags.push(locate(&crate::build::map_error(&e, &out.map), cache, source));
            }
            (Some(out), diags)
        }
    }
}

/// Preprocesses and validates permutation `p` with the open buffers' text.
///
/// `cache` holds the open buffers (see [`cache_with`]); one serves every shader checked
/// after one edit, so each file is read and lexed once.
pub fn check_active(config: &Config, p: &Permutation<'_>, level: usize, cache: &Arc<SourceCache>) -> Active {
    let cache = cache.clone();
    let name = p.name();
    let (output, mut diags) = check_text(p, config, &cache);
    for d in &mut diags {
        d.context = format!("in the active permutation `{name}`");
    }
    let (files, skipped) = match &output {
        Some(o) => (
            o.files.iter().map(|f| cache.path(*f)).collect(),
            inactive_lines(o).into_iter().map(|(f, r)| (cache.path(f), r)).collect(),
        ),
        None => (vec![p.shader.source_path.clone()], Vec::new()),
    };
    Active { level, values: p.values.clone(), name, files, diags, skipped, output: output.map(|o| (o, cache)) }
}

/// The lines excluded in every inclusion of their file (a header included twice, once
/// skipped whole by a guard written as `#if !defined(X)`, is active where the other
/// inclusion kept it).
fn inactive_lines(o: &preprocess::Output) -> Vec<(FileId, std::ops::Range<u32>)> {
    let mut inclusions: HashMap<FileId, u32> = HashMap::new();
    if let Some(main) = o.files.first() {
        inclusions.insert(*main, 1);
    }
    for (_, _, child) in o.map.includes() {
        *inclusions.entry(child).or_default() += 1;
    }
    if inclusions.values().all(|&n| n <= 1) {
        return o.skipped.clone();
    }
    let mut counts: HashMap<(FileId, u32), u32> = HashMap::new();
    for (f, r) in &o.skipped {
        for line in r.clone() {
            *counts.entry((*f, line)).or_default() += 1;
        }
    }
    let mut lines: Vec<(FileId, u32)> = counts
        .into_iter()
        .filter(|((f, _), n)| *n >= inclusions.get(f).copied().unwrap_or(1))
        .map(|(k, _)| k)
        .collect();
    lines.sort_unstable();
    let mut out: Vec<(FileId, std::ops::Range<u32>)> = Vec::new();
    for (f, line) in lines {
        match out.last_mut() {
            Some((g, r)) if *g == f && r.end == line => r.end += 1,
            _ => out.push((f, line..line + 1)),
        }
    }
    out
}

/// One error over a domain: how many permutations it breaks and one of them.
struct Tally {
    diag: FileDiag,
    count: u64,
    example: String,
}

/// What checking a shader's domain found.
pub struct Domain {
    /// Each error with how many kept permutations it breaks.
    pub diags: Vec<FileDiag>,
    /// Every file some kept permutation read.
    pub files: HashSet<PathBuf>,
}

/// Checks every kept permutation of shader `i` (each distinct preprocessed text validated
/// once). `None` when `cancelled` said so before the end.
pub fn check_domain(config: &Config, i: usize, overlays: &Overlays, cancelled: &dyn Fn() -> bool) -> Option<Domain> {
    let shader = config.shaders.get(i)?;
    let mut out = Vec::new();
    let mut files = HashSet::new();
    for level in config.levels.iter().filter(|l| shader.levels.contains(&l.name)) {
        let cache = cache_with(overlays, &config.dir);
        let limits = compile::Limits::for_level(level);
        let mut by_hash: HashMap<blake3::Hash, Vec<usize>> = HashMap::new();
        let mut tallies: Vec<Tally> = Vec::new();
        let mut total = 0u64;
        for p in config.kept_where(|s, l| std::ptr::eq(s, shader) && std::ptr::eq(l, level)) {
            if cancelled() {
                return None;
            }
            total += 1;
            let opts = p.preprocess_options(config);
            match preprocess::preprocess_file(&shader.source_path, &opts, &cache) {
                Err(e) => {
                    tally(&mut tallies, locate(&e.diagnostic, &cache, &shader.source_path), &p);
                }
                Ok(o) => {
                    for f in &o.files {
                        if !files.contains(&cache.path(*f)) {
                            files.insert(cache.path(*f));
                        }
                    }
                    let hash = o.token_hash();
                    if let Some(known) = by_hash.get(&hash) {
                        for &k in known {
                            tallies[k].count += 1;
                        }
                        continue;
                    }
                    let found = compile::check(&o.text, &shader.entry, shader.stage, &limits).err();
                    let found =
                        found.map(|e| locate(&crate::build::map_error(&e, &o.map), &cache, &shader.source_path));
                    let ids: Vec<usize> = found.into_iter().map(|d| tally(&mut tallies, d, &p)).collect();
                    by_hash.insert(hash, ids);
                }
            }
        }
        let whole = format!("{}@{}", shader.name, level.name);
        for t in tallies {
            let mut d = t.diag;
            d.context = format!(
                "in {} of {} permutations of {whole}, e.g. `{}`",
                thousands(t.count),
                thousands(total),
                t.example
            );
            out.push(d);
        }
    }
    Some(Domain { diags: out, files })
}

/// Counts one permutation `p` against error `d`; its index in `tallies`.
fn tally(tallies: &mut Vec<Tally>, d: FileDiag, p: &Permutation<'_>) -> usize {
    if let Some(i) = tallies.iter().position(|t| t.diag.same(&d)) {
        tallies[i].count += 1;
        return i;
    }
    tallies.push(Tally { diag: d, count: 1, example: p.name() });
    tallies.len() - 1
}
