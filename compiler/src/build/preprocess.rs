//! Preprocess: each kept permutation's cache key.
//!
//! Work is skipped where the result is known: a permutation whose preprocessing record (in
//! the cache) lists files whose contents have not changed is not preprocessed; a
//! permutation that agrees with an already preprocessed one of its shader and level on
//! every define the latter's files name reuses its result. A freshly preprocessed
//! permutation's output is handed to the compile stage (which compiles its key at once if
//! it is the key's first) and then dropped: only the small [`Pre`] is kept per permutation.

use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

use codespan_reporting::diagnostic::Diagnostic;

use super::plan::{level_limits, level_targets, Plan};
use super::records::{self, Interner, Records, Row};
use super::report::Progress;
use super::store::Store;
use super::Options;
use crate::cache::Key;
use crate::compile::Limits;
use crate::permute::{Config, Permutation};
use crate::preprocess::{self, FileId, SourceCache};

/// One kept permutation's preprocessing result, shared by the permutations that reuse it.
pub(super) type Pre = Arc<Row>;

/// One kept permutation's result (the diagnostic boxed: most permutations succeed).
pub(super) type PreResult = Result<Pre, Box<Diagnostic<FileId>>>;

/// Each kept permutation's result, in [`Plan::kept`] order.
pub(super) type Preprocessed = Vec<PreResult>;

/// The preprocessing stage's state: the shared source cache and what lets it skip work.
pub(super) struct Preprocessor<'p> {
    plan: &'p Plan<'p>,
    pub sources: SourceCache,
    hashes: FileHashes,
    text_hashes: FileHashes,
    reuse: Reuse,
    identifiers: FileIdentifiers,
    records: Option<RecordSet>,
    /// Interned lists (many permutations read the same files).
    interner: Mutex<Interner>,
    preprocessed: AtomicUsize,
}

/// The preprocessing records of this configuration: those of the last build, and this one's.
struct RecordSet {
    key: Key,
    /// The configuration's folder: paths under it are stored relative to it.
    root: PathBuf,
    base: blake3::Hash,
    old: Records,
    new: Mutex<Records>,
}

impl<'p> Preprocessor<'p> {
    pub fn new(plan: &'p Plan<'p>, store: &Store) -> Preprocessor<'p> {
        let records = store.enabled().then(|| {
            let key = records_key(plan.config, plan.options);
            let root = plan.config.dir.canonicalize().unwrap_or_else(|_| plan.config.dir.clone());
            RecordSet {
                old: store.records(&key).and_then(|b| records::decode_relative(&b, &root)).unwrap_or_default(),
                key,
                root,
                base: direct_base(plan.config),
                new: Mutex::new(Records::new()),
            }
        });
        Preprocessor {
            plan,
            sources: SourceCache::new(plan.config.dir.clone()),
            hashes: FileHashes::default(),
            text_hashes: FileHashes::default(),
            reuse: Reuse::default(),
            identifiers: FileIdentifiers::default(),
            records,
            interner: Mutex::default(),
            preprocessed: AtomicUsize::new(0),
        }
    }

    /// Permutations run through the preprocessor (the others matched a record or reused).
    pub fn count(&self) -> usize {
        self.preprocessed.load(Ordering::Relaxed)
    }

    /// Every kept permutation's result. `fresh` sees each output made by the preprocessor
    /// (with its permutation's index),
    /// on the worker that made it, before it is dropped.
    pub fn run(
        &self,
        progress: &Progress,
        fresh: impl Fn(usize, &Permutation<'_>, &Pre, &preprocess::Output) + Sync,
    ) -> Preprocessed {
        let kept = &self.plan.kept;
        progress.stage("preprocessing", kept.len());
        // The first permutation of each (shader, level) first, so that the others find what
        // they may reuse; then all the others. Workers take the next permutation from a
        // shared counter: in order, one at a time (compile times differ widely between
        // shaders), and with no barrier between the two halves.
        let mut first_of_group = vec![false; kept.len()];
        let mut seen_groups = HashSet::new();
        for (i, p) in kept.iter().enumerate() {
            first_of_group[i] = seen_groups.insert((p.shader.name.as_str(), p.level.name.as_str()));
        }
        let order: Vec<usize> = (0..kept.len())
            .filter(|&i| first_of_group[i])
            .chain((0..kept.len()).filter(|&i| !first_of_group[i]))
            .collect();
        let next = AtomicUsize::new(0);
        let done: Mutex<Vec<Option<PreResult>>> = Mutex::new((0..kept.len()).map(|_| None).collect());
        rayon::scope(|s| {
            for _ in 0..rayon::current_num_threads() {
                s.spawn(|_| loop {
                    let n = next.fetch_add(1, Ordering::Relaxed);
                    let Some(&i) = order.get(n) else { break };
                    let r = self.one(i, &kept[i], &fresh);
                    progress.inc();
                    done.lock().expect("no panics while locked")[i] = Some(r);
                });
            }
        });
        let pre = done.into_inner().expect("no panics while locked");
        pre.into_iter().map(|r| r.expect("every permutation was preprocessed")).collect()
    }

    /// Stores this build's preprocessing records where they changed. Failing to only costs
    /// preprocessing next time.
    ///
    /// Then lets go of what only preprocessing needed (the records, what may be reused):
    /// later stages only preprocess a key's first permutation again, for its text.
    pub fn save_records(&mut self, store: &Store) {
        if let Some(r) = &self.records {
            let new = r.new.lock().expect("no panics while locked");
            if *new != r.old {
                store.put_records(&r.key, &records::encode_relative(&new, &r.root));
            }
        }
        self.records = None;
        self.reuse = Reuse::default();
    }

    fn one(
        &self,
        index: usize,
        p: &Permutation<'_>,
        fresh: &(impl Fn(usize, &Permutation<'_>, &Pre, &preprocess::Output) + Sync),
    ) -> PreResult {
        let direct = self.records.as_ref().map(|r| (r, direct_key(&r.base, p, &self.plan.options.targets)));
        let remember = |pre: &Pre| {
            if let Some((records, dk)) = &direct {
                records.new.lock().expect("no panics while locked").insert(*dk, pre.clone());
            }
        };
        if let Some((records, dk)) = &direct {
            if let Some(row) = records.old.get(dk).filter(|row| self.still_holds(row)) {
                remember(row);
                return Ok(row.clone());
            }
        }
        let values = define_values(p);
        if p.error.is_none() {
            if let Some(pre) = self.reuse.find(p, &values) {
                remember(&pre);
                return Ok(pre);
            }
        }
        self.preprocessed.fetch_add(1, Ordering::Relaxed);
        let (pre, output) = self.preprocess(p)?;
        remember(&pre);
        self.reuse.insert(p, &values, &output, &pre, &self.identifiers, &self.sources);
        fresh(index, p, &pre, &output);
        Ok(pre)
    }

    /// Preprocesses `p` (no record, no reuse): its result and its output.
    pub fn preprocess(&self, p: &Permutation<'_>) -> Result<(Pre, preprocess::Output), Box<Diagnostic<FileId>>> {
        use codespan_reporting::files::Files;
        if let Some(message) = &p.error {
            return Err(Box::new(Diagnostic::error().with_message(message.clone())));
        }
        let opts = p.preprocess_options(self.plan.config);
        let output = preprocess::preprocess_file(&p.shader.source_path, &opts, &self.sources)
            .map_err(|e| Box::new(e.diagnostic))?;
        let token_hash = output.token_hash();
        let key = Key::new(
            &token_hash,
            &p.shader.entry,
            p.shader.stage,
            &p.level.name,
            &level_limits(p.level),
            &level_targets(p.level, &self.plan.options.targets),
        );
        let files: Vec<(PathBuf, [u8; 32])> = output
            .files
            .iter()
            .map(|&f| {
                let path = self.sources.path(f);
                let hash = self.text_hashes.get_or_insert_with(&path, || {
                    self.sources.source(f).ok().map(|t| *blake3::hash(t.as_ref().as_bytes()).as_bytes())
                });
                (path, hash.unwrap_or_default())
            })
            .collect();
        let warnings: Vec<String> =
            output.warnings.iter().map(|w| preprocess::render(std::slice::from_ref(w), &self.sources, false)).collect();
        let mut interner = self.interner.lock().expect("no panics while locked");
        let row = Row {
            key,
            token_hash,
            text_hash: blake3::hash(output.text.as_bytes()),
            text_len: output.text.len() as u64,
            files: interner.files(files),
            absent: interner.absent(output.absent.clone()),
            warnings: interner.warnings(warnings),
        };
        drop(interner);
        Ok((Arc::new(row), output))
    }

    /// Whether a record still holds: every file it lists still has the recorded contents
    /// and no file has appeared where an include looked and found none (it would be found
    /// first now).
    fn still_holds(&self, r: &Row) -> bool {
        r.files.iter().all(|(path, hash)| self.hashes.get(path) == Some(*hash))
            && !r.absent.iter().any(|path| self.hashes.get(path).is_some())
    }
}

/// The identifiers of each file read this build, and whether it pastes tokens (`##`).
#[derive(Default)]
struct FileIdentifiers {
    map: Mutex<HashMap<FileId, Identifiers>>,
}

/// A file's identifiers, and whether it pastes tokens.
type Identifiers = Arc<(HashSet<String>, bool)>;

impl FileIdentifiers {
    fn get(&self, id: FileId, sources: &SourceCache) -> Identifiers {
        use codespan_reporting::files::Files;
        if let Some(v) = self.map.lock().expect("no panics while locked").get(&id) {
            return v.clone();
        }
        let text = sources.source(id).map(|t| t.as_ref().to_string()).unwrap_or_default();
        let mut names = HashSet::new();
        let mut pastes = false;
        for tok in preprocess::tokens(&text) {
            if tok.starts_with(|c: char| c.is_ascii_alphabetic() || c == '_') {
                names.insert(tok.to_string());
            } else if tok == "##" || tok == "%:%:" {
                pastes = true;
            }
        }
        let v = Arc::new((names, pastes));
        self.map.lock().expect("no panics while locked").insert(id, v.clone());
        v
    }
}

/// (shader, level) → [(define names that mattered, values of those names → result)].
type ReuseGroups = HashMap<(String, String), Vec<(Vec<String>, HashMap<Signature, Pre>)>>;

/// The values of the defines that mattered, hashed (16 bytes per entry, whatever their
/// number: these maps hold an entry per distinct preprocessing result).
type Signature = [u8; 16];

fn signature(values: impl Iterator<Item = i64>) -> Signature {
    let mut h = blake3::Hasher::new();
    for v in values {
        h.update(&v.to_le_bytes());
    }
    h.finalize().as_bytes()[..16].try_into().expect("16 of 32 bytes")
}

/// Results reused between permutations of one shader at one level. The preprocessor's
/// output depends only on the texts of the files it reads and on the values of the macros
/// those texts name; a permutation that agrees with an earlier one on every define named
/// in the earlier one's files reads the same files, takes the same branches and gives the
/// same output. (Files that paste tokens with `##` can make names that appear nowhere, so
/// their permutations are never reused.)
#[derive(Default)]
struct Reuse {
    groups: Mutex<ReuseGroups>,
}

fn define_values(p: &Permutation<'_>) -> HashMap<String, i64> {
    p.defines().into_iter().map(|d| (d.name, d.value)).collect()
}

impl Reuse {
    fn find(&self, p: &Permutation<'_>, values: &HashMap<String, i64>) -> Option<Pre> {
        let groups = self.groups.lock().expect("no panics while locked");
        let sets = groups.get(&(p.shader.name.clone(), p.level.name.clone()))?;
        for (names, results) in sets {
            let Some(vals) = names.iter().map(|n| values.get(n).copied()).collect::<Option<Vec<i64>>>() else {
                continue;
            };
            if let Some(hit) = results.get(&signature(vals.into_iter())) {
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
        identifiers: &FileIdentifiers,
        sources: &SourceCache,
    ) {
        let mut used = HashSet::new();
        for &f in &output.files {
            let ids = identifiers.get(f, sources);
            if ids.1 {
                return;
            }
            used.extend(values.keys().filter(|n| ids.0.contains(*n)).cloned());
        }
        let mut names: Vec<String> = used.into_iter().collect();
        names.sort();
        let signature = signature(names.iter().map(|n| values[n]));
        let mut groups = self.groups.lock().expect("no panics while locked");
        let sets = groups.entry((p.shader.name.clone(), p.level.name.clone())).or_default();
        let i = match sets.iter().position(|(n, _)| *n == names) {
            Some(i) => i,
            None => {
                sets.push((names, HashMap::new()));
                sets.len() - 1
            }
        };
        sets[i].1.entry(signature).or_insert_with(|| pre.clone());
    }
}

/// blake3 of files' texts, each read once per build (for checking preprocessing records).
#[derive(Default)]
struct FileHashes {
    map: Mutex<HashMap<PathBuf, Option<[u8; 32]>>>,
}

impl FileHashes {
    /// The hash of the file's text as it is on disk now.
    fn get(&self, path: &Path) -> Option<[u8; 32]> {
        self.get_or_insert_with(path, || {
            std::fs::read(path).ok().map(|bytes| {
                let text =
                    String::from_utf8(bytes).unwrap_or_else(|e| String::from_utf8_lossy(e.as_bytes()).into_owned());
                *blake3::hash(text.as_bytes()).as_bytes()
            })
        })
    }

    fn get_or_insert_with(&self, path: &Path, f: impl FnOnce() -> Option<[u8; 32]>) -> Option<[u8; 32]> {
        if let Some(h) = self.map.lock().expect("no panics while locked").get(path) {
            return *h;
        }
        let h = f();
        self.map.lock().expect("no panics while locked").insert(path.to_path_buf(), h);
        h
    }
}

/// What every permutation's preprocessing record key shares: the configuration's text (its
/// defines, derived values, roots and sources) and the versions. Read once per build. Not
/// the configuration's folder: records store the paths under it relative to it (see
/// [`records::encode_relative`]), so that they hold in another checkout of the same sources.
fn direct_base(config: &Config) -> blake3::Hash {
    let mut h = blake3::Hasher::new();
    let mut field = |bytes: &[u8]| {
        h.update(&(bytes.len() as u64).to_le_bytes());
        h.update(bytes);
    };
    field(b"kiln direct v3");
    // Unreadable now (removed during the build): a key no record has.
    field(&std::fs::read(&config.path).unwrap_or_else(|_| b"\0unreadable".to_vec()));
    let opts = preprocess::Options::default();
    field(&(opts.max_expansion_depth as u64).to_le_bytes());
    field(&(opts.max_output_bytes as u64).to_le_bytes());
    field(crate::compile::NAGA_VERSION.as_bytes());
    h.finalize()
}

/// The key of a permutation's preprocessing record: everything preprocessing and the
/// compile key depend on, except the files' contents (checked against the record). Its
/// defines follow from the configuration's text (in `base`) and its canonical name.
fn direct_key(base: &blake3::Hash, p: &Permutation<'_>, targets: &[crate::archive::Target]) -> Key {
    let mut h = blake3::Hasher::new();
    h.update(base.as_bytes());
    h.update(p.name().as_bytes());
    let targets = level_targets(p.level, targets);
    Key::new(&h.finalize(), &p.shader.entry, p.shader.stage, &p.level.name, &level_limits(p.level), &targets)
}

/// The key of a configuration's set of preprocessing records: its text and the options
/// that choose its permutations; not its path, so that another checkout (another machine,
/// another folder) finds the set in the remote cache. (v4: paths relative to the
/// configuration's folder.)
fn records_key(config: &Config, options: &Options) -> Key {
    let text = std::fs::read(&config.path).unwrap_or_else(|_| b"\0unreadable".to_vec());
    let inputs =
        format!("kiln records v4\n{}\n{:?}\n{:?}", blake3::hash(&text).to_hex(), options.levels, options.targets);
    Key::new(&blake3::hash(inputs.as_bytes()), "", crate::Stage::Compute, "", &Limits::desktop(), &[])
}
