//! Compile: each distinct key once, from the cache where it holds it, else with naga.
//!
//! A key is compiled (or looked up) by the worker that first preprocesses one of its
//! permutations ([`Compiler::early`]), so that compiling overlaps preprocessing; the compile
//! stage ([`Compiler::run`]) then gathers those results and produces the other keys (those
//! whose permutations were all served by preprocessing records). A key's artifacts go to
//! the store and the assembler as soon as they exist and are dropped there; what stays is
//! its small [`Outcome`]. A failure is compiled again on the key's first permutation, so
//! that its spans map on that text. Keys whose compacted modules are equal share one run of
//! the writers ([`compile::SharedWriters`]).
//!
//! `seconds.compile` runs from the first key compiled to the last, so it overlaps
//! `seconds.preprocess`.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU8, AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Instant;

use codespan_reporting::diagnostic::{Diagnostic, Label, LabelStyle};
use rayon::prelude::*;

use super::assemble::Assembler;
use super::group::{Keys, KEYS_READ};
use super::plan::{level_limits, level_targets, Plan};
use super::preprocess::{Preprocessed, Preprocessor};
use super::progress::Progress;
use super::store::{Fetched, Store};
use crate::cache::Key;
use crate::compile::prefixes::Seen;
use crate::compile::{self, Compiled};
use crate::permute::Permutation;
use crate::preprocess::{self, FileId};

/// What became of a key (its artifacts went on to the store and the assembler).
pub(super) enum Outcome {
    /// Served by the cache.
    Hit,
    /// Compiled now; the warning when its cache entry was corrupted.
    Compiled(Option<String>),
    /// The error (boxed: outcomes are kept per key) and the corrupted entry's warning.
    Failed(Box<(compile::Error, Option<String>)>),
    /// Another shard's.
    Elsewhere,
}

/// The keys' outcomes, counted: only the few that carry a warning or an error are kept
/// (an [`Outcome`] a key grew with the set where the compile stage peaks).
#[derive(Default)]
pub(super) struct Outcomes {
    pub hits: usize,
    pub elsewhere: usize,
    /// Compiled now, failures included.
    pub compiled: usize,
    /// The outcomes with a warning or an error, by key number (ascending).
    pub notable: Vec<(usize, Outcome)>,
}

/// [`Compiler::early`]'s marks.
const EARLY_HIT: u8 = 1;
const EARLY_COMPILED: u8 = 2;

pub(super) struct Compiler<'a> {
    plan: &'a Plan<'a>,
    store: &'a Store,
    assembler: &'a Assembler<'a>,
    progress: &'a Progress,
    /// Keys claimed during preprocessing, in a set that may take a key for another (a few
    /// in a thousand: that key's compile only moves to the compile stage) and holds 12
    /// bits a permutation.
    claimed: Mutex<Seen>,
    /// Per kept permutation: whether it produced its key during preprocessing
    /// ([`EARLY_HIT`], [`EARLY_COMPILED`]); one byte each, not a map entry per key.
    early: Vec<AtomicU8>,
    /// The warnings of keys produced early (a corrupted cache entry: rare).
    early_warnings: Mutex<HashMap<Key, String>>,
    /// When the first key began compiling.
    start: Mutex<Option<Instant>>,
    /// The writers' outputs of the compacted modules compiled so far.
    shared: compile::SharedWriters,
    /// With `--shard`: each key's text, kept until the shard knows its share.
    texts: Option<super::shard::Texts>,
}

impl<'a> Compiler<'a> {
    pub fn new(plan: &'a Plan<'a>, store: &'a Store, assembler: &'a Assembler<'a>, progress: &'a Progress) -> Self {
        Compiler {
            plan,
            store,
            assembler,
            progress,
            // Sized at its bound (allocated at the first claim).
            claimed: Mutex::new(Seen::with_bound(plan.len())),
            early: (0..plan.len()).map(|_| AtomicU8::new(0)).collect(),
            early_warnings: Mutex::default(),
            start: Mutex::default(),
            shared: shared_writers(plan.len()),
            texts: plan.options.shard.filter(|_| !plan.hashed_shares()).and_then(|_| super::shard::Texts::new()),
        }
    }

    /// Preprocessing is over: lets go of the keys it claimed and of the writers' outputs kept
    /// for sharing, which would otherwise stay under the next stages.
    pub fn end_early(&self) {
        *self.claimed.lock().expect("no panics while locked") = Seen::default();
        self.shared.forget();
    }

    /// How many keys took their artifacts from another key's compacted module.
    pub fn shared_modules(&self) -> usize {
        self.shared.shared()
    }

    /// During preprocessing: compiles `key` from `output` if `p` is the first of its
    /// permutations preprocessed. With `--shard`, only a key of its share by hash
    /// ([`Plan::hashed_shares`]); with shares by cost, none yet: the shard knows its share
    /// only once every key is known, so it keeps the text for then.
    pub fn early(&self, index: usize, p: &Permutation<'_>, key: &Key, output: &preprocess::Output) {
        if p.error.is_some() {
            return;
        }
        match self.plan.options.shard {
            Some(shard) if self.plan.hashed_shares() && !shard.hashes_to(key) => return,
            Some(_) if !self.plan.hashed_shares() => {
                if let Some(texts) = &self.texts {
                    texts.keep(key, &output.text);
                }
                return;
            }
            _ => {}
        }
        let hash = u128::from_le_bytes(key.0[..16].try_into().expect("16 of 32 bytes"));
        if !self.claimed.lock().expect("no panics while locked").insert(hash) {
            return;
        }
        self.started();
        // A failure is compiled again on the key's first permutation; only successes are kept.
        match self.produce(key, p, &output.text) {
            Outcome::Hit => self.early[index].store(EARLY_HIT, Ordering::Relaxed),
            Outcome::Compiled(warning) => {
                if let Some(w) = warning {
                    self.early_warnings.lock().expect("no panics while locked").insert(*key, w);
                }
                self.early[index].store(EARLY_COMPILED, Ordering::Relaxed);
            }
            Outcome::Failed(_) | Outcome::Elsewhere => {}
        }
    }

    /// Whether one of `members` produced its key during preprocessing.
    pub fn produced_early(&self, members: &[u32]) -> bool {
        members.iter().any(|&m| self.early[m as usize].load(Ordering::Relaxed) != 0)
    }

    /// The outcome of a key one of whose `members` produced it during preprocessing.
    fn early_outcome(&self, key: &Key, members: &[u32]) -> Option<Outcome> {
        let produced = members.iter().map(|&m| self.early[m as usize].load(Ordering::Relaxed)).find(|&e| e != 0)?;
        Some(match produced {
            EARLY_HIT => Outcome::Hit,
            _ => Outcome::Compiled(self.early_warnings.lock().expect("no panics while locked").remove(key)),
        })
    }

    fn started(&self) {
        self.start.lock().expect("no panics while locked").get_or_insert_with(Instant::now);
    }

    /// When the first key began compiling.
    pub fn first_start(&self) -> Option<Instant> {
        *self.start.lock().expect("no panics while locked")
    }

    /// Every key's outcome; an error when the keys cannot be read back.
    pub fn run(&self, keys: &Keys<'_>, preprocessor: &Preprocessor<'_>) -> std::io::Result<Outcomes> {
        self.progress.stage("compiling", keys.len());
        self.started();
        let assembling = self.plan.assembles();
        if assembling {
            self.assembler.expect_blobs(self.artifact_bound(keys));
        }
        let [hits, elsewhere, compiled] = [(); 3].map(|_| AtomicUsize::new(0));
        // The keys are read back a block at a time (they are in a file, not memory).
        let read_error = Mutex::new(None);
        let notable = (0..keys.len().div_ceil(KEYS_READ))
            .into_par_iter()
            .flat_map_iter(|b| {
                let range = b * KEYS_READ..keys.len().min((b + 1) * KEYS_READ);
                let block = keys.read(range.clone()).unwrap_or_else(|e| {
                    read_error.lock().expect("no panics while locked").get_or_insert(e);
                    Vec::new()
                });
                let (hits, elsewhere, compiled) = (&hits, &elsewhere, &compiled);
                range.zip(block).filter_map(move |(k, key)| {
                    let outcome = self.key(&key, keys.members(k), keys.share[k] || assembling, preprocessor);
                    self.progress.inc();
                    let count = match &outcome {
                        Outcome::Hit => hits,
                        Outcome::Elsewhere => elsewhere,
                        Outcome::Compiled(_) | Outcome::Failed(_) => compiled,
                    };
                    count.fetch_add(1, Ordering::Relaxed);
                    matches!(outcome, Outcome::Compiled(Some(_)) | Outcome::Failed(_)).then_some((k, outcome))
                })
            })
            .collect();
        self.progress.finish();
        if let Some(e) = read_error.into_inner().expect("no panics while locked") {
            return Err(e);
        }
        Ok(Outcomes {
            hits: hits.into_inner(),
            elsewhere: elsewhere.into_inner(),
            compiled: compiled.into_inner(),
            notable,
        })
    }

    /// The most artifacts the keys not produced during preprocessing add: each one's targets
    /// (its first permutation's level's), summed. A key's targets are the same for all its
    /// permutations (they are in its key). A cold build produced its keys early, so its
    /// table, grown then, stays as it is.
    fn artifact_bound(&self, keys: &Keys<'_>) -> usize {
        // Counted by level (a few) rather than a list of targets made per key.
        let mut last: Option<(*const crate::permute::Level, usize)> = None;
        let mut count = |level: &crate::permute::Level| match last {
            Some((l, n)) if std::ptr::eq(l, level) => n,
            _ => {
                let n = level_targets(level, &self.plan.options.targets).len();
                last = Some((level, n));
                n
            }
        };
        (0..keys.len())
            .map(|k| keys.members(k))
            .filter(|members| !self.produced_early(members))
            .filter_map(|members| members.first())
            .map(|&m| count(self.plan.shader_level(m as usize).1))
            .sum()
    }

    fn key(&self, key: &Key, members: &[u32], wanted: bool, preprocessor: &Preprocessor<'_>) -> Outcome {
        if let Some(outcome) = self.early_outcome(key, members) {
            return outcome;
        }
        if !wanted {
            return Outcome::Elsewhere;
        }
        let p = &self.plan.permutation(members[0] as usize);
        let mut warning = None;
        match self.fetch(key, p) {
            Some(Fetched::Miss(w)) => warning = w.or(warning),
            _ => return Outcome::Hit,
        }
        // A shard's kept text, else the key's first permutation preprocessed again.
        let kept = self.texts.as_ref().and_then(|t| t.take(key));
        let Some(text) = kept.or_else(|| representative(preprocessor, p, key).map(|o| o.text)) else {
            let e = compile::Error {
                kind: compile::ErrorKind::Parse,
                message: "the sources changed during the build".into(),
                labels: Vec::new(),
                notes: vec!["run the build again".into()],
            };
            return Outcome::Failed(Box::new((e, warning)));
        };
        self.compile(key, p, &text, warning)
    }

    /// A key from the cache, else compiled from `text` (a permutation `p` of that key).
    fn produce(&self, key: &Key, p: &Permutation<'_>, text: &str) -> Outcome {
        match self.fetch(key, p) {
            Some(Fetched::Miss(warning)) => self.compile(key, p, text, warning),
            _ => Outcome::Hit,
        }
    }

    /// A key from the cache, delivered (`None`), else the miss. An entry whose artifacts the
    /// archive being replaced holds is read without them and added by reference; should
    /// that fail, the whole entry is read.
    fn fetch(&self, key: &Key, p: &Permutation<'_>) -> Option<Fetched> {
        let fetched = match self.assembler.by_reference() {
            true => self.store.get_unless_held(key, &|h| self.assembler.holds(h)),
            false => self.store.get(key),
        };
        let fetched = match fetched {
            Fetched::Held(h) if self.assembler.add_held(key, &h) => return None,
            Fetched::Held(_) => self.store.get(key),
            other => other,
        };
        match fetched {
            Fetched::Hit(c, hashes) => {
                self.deliver(key, p, c, Some(hashes));
                None
            }
            other => Some(other),
        }
    }

    fn compile(&self, key: &Key, p: &Permutation<'_>, text: &str, warning: Option<String>) -> Outcome {
        let opts = compile::Options { targets: self.plan.targets(p), limits: level_limits(p.level) };
        match self.shared.compile(text, &p.shader.entry, p.shader.stage, &opts) {
            Ok(c) => {
                self.deliver(key, p, c, None);
                Outcome::Compiled(warning)
            }
            Err(e) => Outcome::Failed(Box::new((e, warning))),
        }
    }

    /// Hands a key's artifacts to the assembler, and (when compiled now: `cached` is `None`)
    /// to the store. `cached` holds the blake3 of each artifact of an entry read from the
    /// cache, computed when its checksum was checked.
    fn deliver(&self, key: &Key, p: &Permutation<'_>, c: Compiled, cached: Option<Vec<blake3::Hash>>) {
        // Every artifact's blake3, once per build: the archive deduplicates blobs by it and
        // the cache's checksums are made of it.
        let fresh = cached.is_none();
        let hashes = cached.unwrap_or_else(|| c.artifacts.iter().map(|(_, bytes)| blake3::hash(bytes)).collect());
        self.assembler.add(key, p.shader.stage, &c, &hashes);
        if fresh {
            self.store.put(*key, c, hashes);
        }
    }
}

/// The writers' outputs shared between keys with one compacted module. `KILN_SHARED_MODULES=0`
/// turns the sharing off (every key runs its own writers: the same artifacts, more time).
/// The build's shared writers, with room for `keys` modules.
fn shared_writers(keys: usize) -> compile::SharedWriters {
    let off = std::env::var_os("KILN_SHARED_MODULES").is_some_and(|v| v == "0");
    if off {
        compile::SharedWriters::disabled()
    } else {
        compile::SharedWriters::with_capacity(keys)
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
    key: Option<&Key>,
    members: &[u32],
    e: &compile::Error,
) -> Vec<(Diagnostic<FileId>, Vec<usize>)> {
    let first = members[0] as usize;
    let rep = match key {
        Some(key) => representative(preprocessor, &plan.permutation(first), key),
        None => preprocessor.preprocess(&plan.permutation(first)).ok().map(|(_, o)| o),
    };
    let mut out = Vec::new();
    for m in members.iter().map(|&m| m as usize) {
        if pre.row_number(m).is_none() {
            continue;
        }
        let p = plan.permutation(m);
        // The others' texts are not kept: each member is preprocessed again.
        let own = (m != first).then(|| preprocessor.preprocess(&p).ok().map(|(_, o)| o)).flatten();
        let mut diagnostic = match (&rep, &own) {
            (Some(rep), None) if m == first => map_error(e, &rep.map),
            (Some(rep), Some(own)) if own.text == rep.text => map_error(e, &own.map),
            // Same tokens, other spacing: this member's own spans.
            _ => remap_member(plan, preprocessor, &p, e),
        };
        if e.kind == compile::ErrorKind::EntryPoint {
            let s = p.shader;
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
