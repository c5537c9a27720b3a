//! Compile: each distinct key once, from the cache where it holds it, else with naga.
//!
//! A key is compiled (or looked up) by the worker that first preprocesses one of its
//! permutations ([`Compiler::early`]), so that compiling overlaps preprocessing; the compile
//! stage ([`Compiler::run`]) then gathers those results and produces the other keys (those
//! whose permutations were all served by preprocessing records). A key's artifacts go to
//! the store and the assembler as soon as they exist and are dropped there; what stays is
//! its small [`Outcome`]. A failure is compiled again on the key's first permutation, so
//! that its spans map on that text.
//!
//! `seconds.compile` runs from the first key compiled to the last, so it overlaps
//! `seconds.preprocess`.

use std::collections::{HashMap, HashSet};
use std::sync::Mutex;
use std::time::Instant;

use codespan_reporting::diagnostic::{Diagnostic, Label, LabelStyle};
use rayon::prelude::*;

use super::assemble::Assembler;
use super::plan::{level_limits, Keys, Plan};
use super::preprocess::{Pre, Preprocessed, Preprocessor};
use super::report::Progress;
use super::store::{Fetched, Store};
use crate::cache::Key;
use crate::compile::{self, Compiled};
use crate::permute::Permutation;
use crate::preprocess::{self, FileId};

/// What became of a key (its artifacts went on to the store and the assembler).
pub(super) enum Outcome {
    /// Served by the cache.
    Hit,
    /// Compiled now; the warning when its cache entry was corrupted.
    Compiled(Option<String>),
    Failed(compile::Error, Option<String>),
    /// Another shard's.
    Elsewhere,
}

pub(super) struct Compiler<'a> {
    plan: &'a Plan<'a>,
    store: &'a Store,
    assembler: &'a Assembler<'a>,
    progress: &'a Progress,
    /// Keys claimed during preprocessing, and the outcomes of those that succeeded.
    early: Mutex<(HashSet<Key>, HashMap<Key, Outcome>)>,
    /// When the first key began compiling.
    start: Mutex<Option<Instant>>,
}

impl<'a> Compiler<'a> {
    pub fn new(plan: &'a Plan<'a>, store: &'a Store, assembler: &'a Assembler<'a>, progress: &'a Progress) -> Self {
        Compiler { plan, store, assembler, progress, early: Mutex::default(), start: Mutex::default() }
    }

    /// During preprocessing: compiles `pre`'s key from `output` if `p` is the first of its
    /// permutations preprocessed (and, with `--shard`, nothing yet: a shard knows its share
    /// only once every key is known).
    pub fn early(&self, p: &Permutation<'_>, pre: &Pre, output: &preprocess::Output) {
        if self.plan.options.shard.is_some() || p.error.is_some() {
            return;
        }
        if !self.early.lock().expect("no panics while locked").0.insert(pre.key) {
            return;
        }
        self.started();
        let outcome = self.produce(&pre.key, p, &output.text);
        // A failure is compiled again on the key's first permutation; only successes are kept.
        if !matches!(outcome, Outcome::Failed(..)) {
            self.early.lock().expect("no panics while locked").1.insert(pre.key, outcome);
        }
    }

    fn started(&self) {
        self.start.lock().expect("no panics while locked").get_or_insert_with(Instant::now);
    }

    /// When the first key began compiling.
    pub fn first_start(&self) -> Option<Instant> {
        *self.start.lock().expect("no panics while locked")
    }

    /// Every key's outcome, in `keys` order.
    pub fn run(&self, keys: &Keys, preprocessor: &Preprocessor<'_>) -> Vec<Outcome> {
        self.progress.stage("compiling", keys.len());
        self.started();
        let assembling = self.plan.assembles();
        let outcomes = keys
            .groups
            .par_iter()
            .zip(&keys.share)
            .map(|((key, members), &mine)| {
                let outcome = self.key(key, members, mine || assembling, preprocessor);
                self.progress.inc();
                outcome
            })
            .collect();
        self.progress.finish();
        outcomes
    }

    fn key(&self, key: &Key, members: &[usize], wanted: bool, preprocessor: &Preprocessor<'_>) -> Outcome {
        if let Some(outcome) = self.early.lock().expect("no panics while locked").1.remove(key) {
            return outcome;
        }
        if !wanted {
            return Outcome::Elsewhere;
        }
        let p = &self.plan.kept[members[0]];
        let mut warning = None;
        match self.store.get(key) {
            Fetched::Hit(c) => {
                self.deliver(key, p, c, false);
                return Outcome::Hit;
            }
            Fetched::Miss(w) => warning = w.or(warning),
        }
        let Some(text) = representative(preprocessor, p, key) else {
            let e = compile::Error {
                kind: compile::ErrorKind::Parse,
                message: "the sources changed during the build".into(),
                labels: Vec::new(),
                notes: vec!["run the build again".into()],
            };
            return Outcome::Failed(e, warning);
        };
        self.compile(key, p, &text.text, warning)
    }

    /// A key from the cache, else compiled from `text` (a permutation `p` of that key).
    fn produce(&self, key: &Key, p: &Permutation<'_>, text: &str) -> Outcome {
        match self.store.get(key) {
            Fetched::Hit(c) => {
                self.deliver(key, p, c, false);
                Outcome::Hit
            }
            Fetched::Miss(warning) => self.compile(key, p, text, warning),
        }
    }

    fn compile(&self, key: &Key, p: &Permutation<'_>, text: &str, warning: Option<String>) -> Outcome {
        let opts = compile::Options { targets: self.plan.targets(p), limits: level_limits(p.level) };
        match compile::compile(text, &p.shader.entry, p.shader.stage, &opts) {
            Ok(c) => {
                self.deliver(key, p, c, true);
                Outcome::Compiled(warning)
            }
            Err(e) => Outcome::Failed(e, warning),
        }
    }

    /// Hands a key's artifacts to the assembler, and (when compiled now) to the store.
    fn deliver(&self, key: &Key, p: &Permutation<'_>, c: Compiled, fresh: bool) {
        // Every artifact's blake3, once: the archive deduplicates blobs by it and the
        // cache's checksums are made of it.
        let hashes: Vec<blake3::Hash> = c.artifacts.iter().map(|(_, bytes)| blake3::hash(bytes)).collect();
        self.assembler.add(key, p.shader.stage, &c, &hashes);
        if fresh {
            self.store.put(*key, c, hashes);
        }
    }
}

/// The preprocessed output of a key's first permutation, made again (outputs are not kept
/// past their compile). `None` if it no longer gives that key.
fn representative(preprocessor: &Preprocessor<'_>, p: &Permutation<'_>, key: &Key) -> Option<preprocess::Output> {
    let (pre, output) = preprocessor.preprocess(p).ok()?;
    (pre.key == *key).then_some(output)
}

/// The diagnostics of a failed key, one per permutation, mapped onto each one's text.
pub(super) fn failures(
    plan: &Plan<'_>,
    preprocessor: &Preprocessor<'_>,
    pre: &Preprocessed,
    key: &Key,
    members: &[usize],
    e: &compile::Error,
) -> Vec<(Diagnostic<FileId>, Vec<usize>)> {
    let rep = representative(preprocessor, &plan.kept[members[0]], key);
    let rep_hash = rep.as_ref().map(|r| blake3::hash(r.text.as_bytes()));
    let mut out = Vec::new();
    for &m in members {
        let Ok(pm) = &pre[m] else { continue };
        let mut diagnostic = match &rep {
            Some(rep) if Some(pm.text_hash) == rep_hash => map_error(e, &rep.map),
            // Same tokens, other spacing: this member's own spans.
            _ => remap_member(plan, preprocessor, &plan.kept[m], e),
        };
        if e.kind == compile::ErrorKind::EntryPoint {
            let s = plan.kept[m].shader;
            let file = plan.config.path.file_name().map(|f| f.to_string_lossy().into_owned()).unwrap_or_default();
            diagnostic.notes.push(format!(
                "shader `{}` of {file} names entry point `{}` ({}) in {}",
                s.name,
                s.entry,
                s.stage,
                preprocessor.sources.display_name(&s.source_path)
            ));
        }
        out.push((diagnostic, vec![m]));
    }
    out
}

/// A failing key's error on a member whose text differs from the representative's only in
/// spacing: preprocess and compile that member again for spans into its own text.
fn remap_member(
    plan: &Plan<'_>,
    preprocessor: &Preprocessor<'_>,
    p: &Permutation<'_>,
    fallback: &compile::Error,
) -> Diagnostic<FileId> {
    let unmapped = || Diagnostic::error().with_message(fallback.message.clone()).with_notes(fallback.notes.clone());
    let Ok((_, output)) = preprocessor.preprocess(p) else {
        return unmapped();
    };
    let opts = compile::Options { targets: plan.targets(p), limits: level_limits(p.level) };
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
