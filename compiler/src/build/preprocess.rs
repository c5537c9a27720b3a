//! Preprocess: each kept permutation's cache key.
//!
//! Work is skipped where the result is known: a permutation whose preprocessing record (in
//! the cache) lists files whose contents have not changed is not preprocessed; a
//! permutation that agrees with an already preprocessed one of its shader and level on
//! every define the latter's files name reuses its result. A freshly preprocessed
//! permutation's output is handed to the compile stage (which compiles its key at once if
//! it is the key's first) and then dropped. What is kept is small: per permutation the
//! number of its [`Row`], per distinct result a fixed-size row whose lists are
//! numbers in one [`Interner`] (in a temporary file, so not beside the compile work that
//! overlaps it, and read again from there where it is needed: even the rows' keys, 32 bytes
//! a distinct result, are never held all at once). What may be reused is kept per (shader,
//! level) until its last permutation is taken. The records for the next build are made from
//! the rows when they are saved (each permutation's direct key is made again then).

use std::collections::{HashMap, HashSet};
use std::hash::BuildHasherDefault;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU32, AtomicU8, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, RwLock};

use codespan_reporting::diagnostic::Diagnostic;

use super::pieces::Pieces;
use super::plan::{level_limits, level_targets, Plan};
use super::progress::Progress;
use super::records::{self, Direct, Interner, Records, Row};
use super::store::Store;
use super::Options;
use crate::cache::Key;
use crate::compile::Limits;
use crate::permute::{Config, Permutation};
use crate::preprocess::{self, FileId, SourceCache};

/// A permutation that failed to preprocess.
const FAILED: u32 = u32::MAX;

/// Each kept permutation's result, in the plan's order: the number of its row (rows are
/// shared by the permutations that reuse them), or its failure. Of each row only the key is
/// in memory; the rest (the text's length and the numbers of its lists) stays in
/// the rows' temporary file and is read again by the few that need it (so it is not held
/// through the compile and assembly stages).
pub(super) struct Preprocessed {
    of: Vec<u32>,
    rows: Rows,
    /// The failures, by permutation (ascending).
    errors: Vec<(usize, Box<Diagnostic<FileId>>)>,
}

/// The rows, in their temporary file (read again through [`Preprocessed::keys`] and
/// [`Preprocessed::each_row`]); or in memory where no temporary file could be made.
enum Rows {
    File { count: usize, file: std::fs::File },
    Memory(Vec<Row>),
}

impl Preprocessed {
    pub fn len(&self) -> usize {
        self.of.len()
    }

    /// The number of distinct results (a key may have several: results that differ in what
    /// was read).
    pub fn row_count(&self) -> usize {
        match &self.rows {
            Rows::File { count, .. } => *count,
            Rows::Memory(rows) => rows.len(),
        }
    }

    /// The number of permutation `i`'s row; `None` where it failed.
    pub fn row_number(&self, i: usize) -> Option<usize> {
        Some(self.of[i] as usize).filter(|&r| r < self.row_count())
    }

    /// Calls `f` on every row, in order, read again from their file through a small buffer.
    pub fn each_row(&self, mut f: impl FnMut(Row)) -> std::io::Result<()> {
        use std::os::unix::fs::FileExt;
        let file = match &self.rows {
            Rows::Memory(rows) => {
                rows.iter().for_each(|r| f(*r));
                return Ok(());
            }
            Rows::File { file, .. } => file,
        };
        let count = self.row_count();
        let mut buffer = vec![0u8; ROWS_READ * ROW_LEN];
        let mut at = 0;
        while at < count {
            let n = ROWS_READ.min(count - at);
            let bytes = &mut buffer[..n * ROW_LEN];
            file.read_exact_at(bytes, (at * ROW_LEN) as u64)?;
            bytes.chunks_exact(ROW_LEN).for_each(|b| f(decode_row(b.try_into().expect("a row's bytes"))));
            at += n;
        }
        Ok(())
    }

    /// A reader of the rows' keys, which stay in their file (read a block of rows at a
    /// time, the last few blocks kept): with a row a distinct result, they were the largest
    /// table from preprocessing to the manifest.
    pub fn keys(&self) -> RowKeys<'_> {
        RowKeys { pre: self, blocks: Vec::new(), next: 0 }
    }

    /// Permutations whose results are rows of `keys` (each its own row, in their file), the
    /// `i`th permutation's the `i`th row.
    #[cfg(test)]
    pub fn of_keys(keys: &[Key]) -> Preprocessed {
        let mut log = RowLog::new();
        let of = keys
            .iter()
            .enumerate()
            .map(|(n, key)| log.push(&Row { key: *key, text_len: n as u32, files: 0, absent: 0, warnings: 0 }))
            .collect();
        Preprocessed { of, rows: log.load().expect("rows read back"), errors: Vec::new() }
    }

    /// The failures, by permutation (ascending).
    pub fn errors(&self) -> &[(usize, Box<Diagnostic<FileId>>)] {
        &self.errors
    }
}

/// [`Preprocessed::keys`].
pub(super) struct RowKeys<'p> {
    pre: &'p Preprocessed,
    /// The blocks read last: each one's first row and its rows' keys.
    blocks: Vec<(usize, Vec<Key>)>,
    /// The block to replace next.
    next: usize,
}

/// Rows a block of [`RowKeys`] (12 KiB read), and how many blocks it keeps.
const KEY_BLOCK: usize = 256;
const KEY_BLOCKS: usize = 8;

impl RowKeys<'_> {
    /// Row `r`'s key.
    pub fn row(&mut self, r: usize) -> std::io::Result<Key> {
        use std::os::unix::fs::FileExt;
        let file = match &self.pre.rows {
            Rows::Memory(rows) => return Ok(rows[r].key),
            Rows::File { file, .. } => file,
        };
        let start = r - r % KEY_BLOCK;
        if let Some((_, keys)) = self.blocks.iter().find(|b| b.0 == start) {
            return Ok(keys[r - start]);
        }
        let n = KEY_BLOCK.min(self.pre.row_count() - start);
        let mut bytes = vec![0u8; n * ROW_LEN];
        file.read_exact_at(&mut bytes, (start * ROW_LEN) as u64)?;
        let keys: Vec<Key> = bytes.chunks_exact(ROW_LEN).map(|b| Key(b[..32].try_into().expect("32 bytes"))).collect();
        let key = keys[r - start];
        if self.blocks.len() < KEY_BLOCKS {
            self.blocks.push((start, keys));
        } else {
            self.blocks[self.next] = (start, keys);
            self.next = (self.next + 1) % KEY_BLOCKS;
        }
        Ok(key)
    }

    /// Permutation `i`'s key; `None` where it failed.
    pub fn of(&mut self, i: usize) -> std::io::Result<Option<Key>> {
        self.pre.row_number(i).map(|r| self.row(r)).transpose()
    }
}

/// A temporary file of the build that could not be read back.
pub(super) fn read_back(e: std::io::Error) -> super::Error {
    super::Error::Io(format!("error: cannot read back a temporary file of the build: {e}"))
}

/// The preprocessing stage's state: the shared source cache and what lets it skip work.
pub(super) struct Preprocessor<'p> {
    plan: &'p Plan<'p>,
    pub sources: SourceCache,
    hashes: FileHashes,
    text_hashes: FileHashes,
    reuse: Reuse,
    identifiers: FileIdentifiers,
    records: Option<RecordSet>,
    /// A shard's records shared by pieces with the shards that run beside it (see
    /// [`super::pieces`]): only where its configuration's records were not found.
    pieces: Option<Pieces>,
    /// Interned lists (many permutations read the same files).
    interner: Mutex<Interner>,
    /// The distinct results so far: [`Preprocessed`]'s rows.
    rows: Mutex<RowLog>,
    preprocessed: AtomicUsize,
}

/// The preprocessing records of this configuration: those of the last build, and this one's.
struct RecordSet {
    key: Key,
    /// The configuration's folder: paths under it are stored relative to it.
    root: PathBuf,
    base: blake3::Hash,
    /// Let go of once preprocessing ends ([`Preprocessor::release_reuse`]): only
    /// preprocessing matches permutations to them, and kept under the stages after it
    /// they were a warm build's largest table.
    old: Records,
    /// How many records `old` held.
    old_len: usize,
    /// Permutations that matched one of `old`'s records.
    matched: AtomicUsize,
    /// Whether each of `old`'s file lists still holds (every file has its recorded
    /// contents) and each of its absent lists (no file appeared): [`UNKNOWN`] until a row
    /// that names it is matched. Many rows share a list: each is checked once, not once per
    /// permutation (a lock and a path's hash per file).
    /// Grown as pieces' records add lists (see [`super::pieces`]).
    files_hold: RwLock<Vec<AtomicU8>>,
    absent_hold: RwLock<Vec<AtomicU8>>,
}

/// A list's state in [`RecordSet::files_hold`]: not checked yet, holds, does not.
const UNKNOWN: u8 = 0;
const HOLDS: u8 = 1;
const BROKEN: u8 = 2;

/// The last build's preprocessing records of a configuration, read beside its plan (they
/// depend only on the configuration and options) and handed to [`Preprocessor::new`].
pub(super) struct LastRecords {
    records: Option<RecordSet>,
    interner: Interner,
}

impl LastRecords {
    /// The records stored for `config` and `options` (none without a cache).
    pub fn load(config: &Config, options: &Options, store: &Store) -> LastRecords {
        let mut interner = Interner::default();
        let records = store.enabled().then(|| {
            let key = records_key(config, options);
            let root = config.dir.canonicalize().unwrap_or_else(|_| config.dir.clone());
            // A configuration changed since (a material or a shader added) finds the last
            // records of its file: a record's key holds all that decides its permutation.
            let last = || {
                let pointer = store.local_records(&last_records_key(config, options))?;
                store.records(&Key(pointer.try_into().ok()?))
            };
            let stored = store.records(&key).or_else(last);
            let old = stored.and_then(|s| records::decode_stored(s, &mut interner, &root)).unwrap_or_default();
            let base = direct_base(config, &root);
            let unknown = |n: usize| RwLock::new((0..n).map(|_| AtomicU8::new(UNKNOWN)).collect());
            RecordSet {
                old_len: old.len(),
                old,
                key,
                root,
                base,
                matched: AtomicUsize::new(0),
                files_hold: unknown(interner.files.len()),
                absent_hold: unknown(interner.absent.len()),
            }
        });
        LastRecords { records, interner }
    }

    /// The keys of the records (sorted, each once): this build's keys when no source
    /// changed, known before the permutations are matched to the records.
    pub fn keys(&self) -> Vec<Key> {
        let Some(r) = &self.records else { return Vec::new() };
        let mut keys: Vec<Key> = r.old.iter().map(|(_, row)| row.key).collect();
        keys.sort_unstable();
        keys.dedup();
        keys
    }
}

impl<'p> Preprocessor<'p> {
    pub fn new(plan: &'p Plan<'p>, last: LastRecords) -> Preprocessor<'p> {
        let LastRecords { records, interner } = last;
        let pieces = match (&records, plan.options.shard) {
            (Some(r), Some(shard)) if r.old_len == 0 => Some(Pieces::new(plan.len(), &shard, r.key)),
            _ => None,
        };
        Preprocessor {
            pieces,
            plan,
            sources: SourceCache::new(plan.config.dir.clone()),
            hashes: FileHashes::default(),
            text_hashes: FileHashes::default(),
            reuse: Reuse::default(),
            identifiers: FileIdentifiers::default(),
            records,
            interner: Mutex::new(interner),
            rows: Mutex::new(RowLog::new()),
            preprocessed: AtomicUsize::new(0),
        }
    }

    /// Whether this build's records are the last build's (or there are none to save): every
    /// permutation matched one of the old records and there are no others (a warm build's
    /// case: no direct key hashed again to find it).
    pub fn records_unchanged(&self) -> bool {
        self.records
            .as_ref()
            .is_none_or(|r| r.matched.load(Ordering::Relaxed) == self.plan.len() && r.old_len == self.plan.len())
    }

    /// Permutations run through the preprocessor (the others matched a record or reused).
    pub fn count(&self) -> usize {
        self.preprocessed.load(Ordering::Relaxed)
    }

    /// The interned lists of the rows (files read, missing candidates, warnings).
    pub fn lists(&self) -> MutexGuard<'_, Interner> {
        self.interner.lock().expect("no panics while locked")
    }

    /// Every kept permutation's result. `fresh` sees each output made by the preprocessor
    /// (with its permutation's index and key), on the worker that made it, before it is
    /// dropped; `ended` runs once the last permutation is done, before the rows are
    /// handed on (so that what `fresh` fed is let go first: not held beside what follows). A
    /// shard's pieces of records go through `store`'s remote cache.
    pub fn run(
        &mut self,
        progress: &Progress,
        store: &Store,
        fresh: impl Fn(usize, &Permutation<'_>, &Key, &preprocess::Output) + Sync,
        ended: impl FnOnce(),
    ) -> Result<Preprocessed, super::Error> {
        let plan = self.plan;
        progress.stage("preprocessing", plan.len());
        let pieces = self.pieces.as_ref().filter(|_| store.has_remote());
        let position = |i: usize| pieces.map_or(i, |p| p.position(i));
        let (order, ahead) = match pieces {
            Some(p) => (Box::new(p.order()) as Box<dyn Iterator<Item = usize> + Send>, 0),
            None => self.order(),
        };
        let order = Mutex::new(order.enumerate());
        let of: Vec<AtomicU32> = (0..plan.len()).map(|_| AtomicU32::new(FAILED)).collect();
        let errors = Mutex::new(Vec::new());
        self.reuse.plan_ends(plan, &|run| pieces.map_or(run.end, |p| p.run_end(run)));
        rayon::scope(|s| {
            for _ in 0..rayon::current_num_threads() {
                s.spawn(|_| loop {
                    let next = {
                        let mut order = order.lock().expect("no panics while locked");
                        let next = order.next();
                        // A piece is looked for before any of its permutations is taken.
                        if let (Some((_, i)), Some(p)) = (next, pieces) {
                            self.fetch_piece(p, i, store);
                        }
                        next
                    };
                    let Some((n, i)) = next else { break };
                    if n >= ahead {
                        // In order now: groups whose last permutation was taken are done.
                        self.reuse.retire_before(position(i));
                    }
                    match self.one(i, &plan.permutation(i), pieces, &fresh) {
                        Ok(row) => of[i].store(row, Ordering::Relaxed),
                        Err(d) => errors.lock().expect("no panics while locked").push((i, d)),
                    }
                    if let Some((p, (piece, range))) = pieces.and_then(|p| Some((p, p.done(i)?))) {
                        self.store_piece(store, &p.key(piece), range, &of);
                    }
                    progress.inc();
                });
            }
        });
        let mut errors = errors.into_inner().expect("no panics while locked");
        errors.sort_by_key(|e| e.0);
        // What may be reused, and the last build's records, go before the rows are handed on.
        drop(order);
        self.release_reuse();
        ended();
        let rows = std::mem::replace(&mut *self.rows.lock().expect("no panics while locked"), RowLog::new())
            .load()
            .map_err(read_back)?;
        Ok(Preprocessed { of: of.into_iter().map(AtomicU32::into_inner).collect(), rows, errors })
    }

    /// The order of a build's permutations, and how many come ahead of plan order: the
    /// first permutation of each (shader, level) first, so that the others find what they
    /// may reuse; then the permutations the usage files record (`--usage`: compiled first),
    /// then the rest in plan order. Workers take the next permutation from one shared
    /// iterator: in order, one at a time (compile times differ widely between shaders), and
    /// with no barrier between the parts. The order is made as it is taken, not held as a
    /// table.
    fn order(&self) -> (Box<dyn Iterator<Item = usize> + Send + '_>, usize) {
        let plan = self.plan;
        let mut seen_groups = HashSet::new();
        let firsts: Vec<usize> = plan
            .runs()
            .filter(|(shader, level, range)| !range.is_empty() && seen_groups.insert((&shader.name, &level.name)))
            .map(|(_, _, range)| range.start)
            .collect();
        let recorded: Vec<usize> = plan.recorded.iter().copied().filter(|i| firsts.binary_search(i).is_err()).collect();
        let ahead = firsts.len() + recorded.len();
        let rest = (0..plan.len()).filter({
            let (firsts, recorded) = (firsts.clone(), recorded.clone());
            move |i| firsts.binary_search(i).is_err() && recorded.binary_search(i).is_err()
        });
        (Box::new(firsts.into_iter().chain(recorded).chain(rest)), ahead)
    }

    /// Looks for the records of the piece that permutation `i` starts (if it starts one) in
    /// the remote cache; a damaged or unreadable piece is not used.
    fn fetch_piece(&self, pieces: &Pieces, i: usize, store: &Store) {
        let (Some(n), Some(records)) = (pieces.starts(i), &self.records) else { return };
        let Some(bytes) = store.remote_records(&pieces.key(n)) else { return };
        let (decoded, files, absent) = {
            let mut interner = self.lists();
            let decoded = records::decode(bytes, &mut interner, &records.root);
            (decoded, interner.files.len(), interner.absent.len())
        };
        let Some(decoded) = decoded else { return };
        // The lists the piece added are checked once each, like the last build's.
        for (hold, len) in [(&records.files_hold, files), (&records.absent_hold, absent)] {
            let mut hold = hold.write().expect("no panics while locked");
            let grow = len.saturating_sub(hold.len());
            hold.extend((0..grow).map(|_| AtomicU8::new(UNKNOWN)));
        }
        pieces.found(n, decoded);
    }

    /// Stores the records of the permutations `range` (a piece just done) in the remote
    /// cache under `key`; failing to only costs the other shards preprocessing them.
    fn store_piece(&self, store: &Store, key: &Key, range: std::ops::Range<usize>, of: &[AtomicU32]) {
        let Some(r) = &self.records else { return };
        let (plan, targets) = (self.plan, &self.plan.options.targets);
        let mut rows = Vec::with_capacity(range.len());
        {
            let mut log = self.rows.lock().expect("no panics while locked");
            for i in range {
                let n = of[i].load(Ordering::Relaxed);
                if n == FAILED {
                    continue;
                }
                let Ok(row) = log.get(n) else { return };
                rows.push((i, row));
            }
        }
        let rows: Vec<(Direct, Row)> = rows
            .into_iter()
            .map(|(i, row)| {
                let p = plan.permutation(i);
                (direct_key(&r.base, &p, &p.defines(), targets), row)
            })
            .collect();
        let body = records::encode_small(rows, &self.lists(), &r.root);
        store.put_remote_records(key, &body);
    }

    /// Lets go of what only preprocessing needed (what may be reused, the last build's
    /// records): later stages only preprocess a key's first permutation again, for its text.
    /// Without the old records, this build's are written whenever they are not the last
    /// build's as a whole ([`Preprocessor::records_unchanged`]): a permutation that matched
    /// no record has a row no record had.
    fn release_reuse(&mut self) {
        self.reuse = Reuse::default();
        if let Some(r) = &mut self.records {
            r.old = Records::default();
        }
    }

    /// Stores this build's preprocessing records where they changed. Failing to only costs
    /// preprocessing next time. Called once the compile stage's tables are gone: the
    /// records' bytes (64 per permutation) are the largest transient of a build.
    pub fn save_records(&mut self, store: &Store, pre: &Preprocessed) {
        if self.records_unchanged() {
            return;
        }
        let Some(mut r) = self.records.take() else { return };
        if r.matched.load(Ordering::Relaxed) < self.plan.len() {
            // A permutation that matched no record (new, changed or failed) gives rows other
            // than the last build's, so they need not be kept to compare with while the new
            // ones are encoded (where a rewrite after a change peaks).
            r.old = Records::default();
        }
        // Each preprocessed permutation's direct key, made again here rather than kept
        // through the build (where it would add to the peak), straight into the bytes.
        let (plan, targets) = (self.plan, &self.plan.options.targets);
        // What the rows hold besides their keys, read again: the text's length and the
        // number of its three lists together (few rows differ in them), half of what a row
        // holds (where the records are the build's largest transient).
        let mut rests = Vec::with_capacity(pre.row_count());
        let (mut lists, mut numbers) = (Vec::new(), HashMap::new());
        let read = pre.each_row(|r| {
            let three = [r.files, r.absent, r.warnings];
            let n = *numbers.entry(three).or_insert_with(|| {
                lists.push(three);
                lists.len() as u32 - 1
            });
            rests.push([r.text_len, n]);
        });
        if read.is_err() {
            return;
        }
        drop(numbers);
        // The keys a few blocks at a time (the workers share the reader); a key that cannot
        // be read back leaves the records as they were.
        let (keys, unreadable) = (Mutex::new(pre.keys()), std::sync::atomic::AtomicBool::new(false));
        let whole = |n: usize| {
            let [text_len, three] = rests[n];
            let [files, absent, warnings] = lists[three as usize];
            let key = keys
                .lock()
                .expect("no panics while locked")
                .row(n)
                .map_err(|_| unreadable.store(true, Ordering::Relaxed));
            Some(Row { key: key.ok()?, text_len, files, absent, warnings })
        };
        let row = |i: usize| {
            let p = plan.permutation(i);
            Some((direct_key(&r.base, &p, &p.defines(), targets), whole(pre.row_number(i)?)?))
        };
        let encoded = records::encode(plan.len(), row, &self.lists(), &r.root, r.old);
        drop(rests);
        super::trace_memory("records encoded");
        if let Some(encoded) = encoded.filter(|_| !unreadable.load(Ordering::Relaxed)) {
            store.put_records(&r.key, &encoded);
            store.put_local_records(&last_records_key(plan.config, plan.options), &r.key.0);
        }
    }

    /// Permutation `p`'s row number.
    fn one(
        &self,
        index: usize,
        p: &Permutation<'_>,
        pieces: Option<&Pieces>,
        fresh: &(impl Fn(usize, &Permutation<'_>, &Key, &preprocess::Output) + Sync),
    ) -> Result<u32, Box<Diagnostic<FileId>>> {
        let defines = p.defines();
        // A permutation the configuration rejects has no record: its error is reported.
        if let Some(records) = self.records.as_ref().filter(|_| p.error.is_none()) {
            let dk = direct_key(&records.base, p, &defines, &self.plan.options.targets);
            if let Some(row) = records.old.get(&dk).filter(|row| self.still_holds(records, row)) {
                records.matched.fetch_add(1, Ordering::Relaxed);
                return Ok(self.push(row));
            }
            // Another shard's piece: not counted as matched (the records are not the last
            // build's, and are saved whole at the end).
            let piece = pieces.and_then(|pieces| pieces.records(index));
            if let Some(row) = piece.and_then(|r| r.get(&dk)).filter(|row| self.still_holds(records, row)) {
                return Ok(self.push(row));
            }
        }
        let values: HashMap<String, i64> = defines.into_iter().map(|d| (d.name, d.value)).collect();
        if p.error.is_none() {
            if let Some(n) = self.reuse.find(p, &values) {
                return Ok(n);
            }
        }
        self.preprocessed.fetch_add(1, Ordering::Relaxed);
        let (row, output) = self.preprocess(p)?;
        let n = self.push(row);
        self.reuse.insert(p, &values, &output, n, &self.identifiers, &self.sources);
        fresh(index, p, &row.key, &output);
        Ok(n)
    }

    /// Adds a distinct result; its number.
    fn push(&self, row: Row) -> u32 {
        self.rows.lock().expect("no panics while locked").push(&row)
    }

    /// Preprocesses `p` (no record, no reuse): its result and its output.
    pub fn preprocess(&self, p: &Permutation<'_>) -> Result<(Row, preprocess::Output), Box<Diagnostic<FileId>>> {
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
        let files: Vec<records::FileEntry> = output
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
        let mut interner = self.lists();
        let row = Row {
            key,
            text_len: u32::try_from(output.text.len()).unwrap_or(u32::MAX),
            files: interner.files.intern(files),
            absent: interner.absent.intern(output.absent.clone()),
            warnings: interner.warnings.intern(warnings),
        };
        drop(interner);
        Ok((row, output))
    }

    /// Whether a record still holds: every file it lists still has the recorded contents
    /// and no file has appeared where an include looked and found none (it would be found
    /// first now).
    fn still_holds(&self, records: &RecordSet, r: &Row) -> bool {
        let once = |states: &[AtomicU8], list: u32, check: &dyn Fn() -> bool| {
            let state = states.get(list as usize);
            match state.map_or(UNKNOWN, |s| s.load(Ordering::Relaxed)) {
                HOLDS => true,
                BROKEN => false,
                _ => {
                    let holds = check();
                    if let Some(s) = state {
                        s.store(if holds { HOLDS } else { BROKEN }, Ordering::Relaxed);
                    }
                    holds
                }
            }
        };
        once(&records.files_hold.read().expect("no panics while locked"), r.files, &|| {
            let files = self.lists().files.get(r.files).clone();
            files.iter().all(|(path, hash)| self.hashes.get(path) == Some(*hash))
        }) && once(&records.absent_hold.read().expect("no panics while locked"), r.absent, &|| {
            let absent = self.lists().absent.get(r.absent).clone();
            !absent.iter().any(|path| self.hashes.get(path).is_some())
        })
    }
}

/// The rows made while preprocessing, in order: in an unlinked temporary file (fixed-size
/// rows, through a buffer), read back into one table when preprocessing ends, so that
/// they are not held beside the compile stage's work that overlaps preprocessing. In
/// memory where no temporary file can be made.
struct RowLog {
    out: RowsOut,
    count: u32,
    /// The first write that failed (the build fails when the rows are read back).
    error: Option<std::io::Error>,
    /// The latest rows added, by a hash of their key: a row equal to one of them takes its
    /// number instead of a new one. A warm build adds a row a permutation matched to a
    /// record, and the permutations of a key mostly come close together: without this, its
    /// rows were one a permutation rather than about one a key.
    recent: Vec<Option<(Row, u32)>>,
}

/// How many of the latest rows [`RowLog::push`] looks among for an equal one.
const RECENT_ROWS: usize = 4096;

enum RowsOut {
    File(std::io::BufWriter<std::fs::File>),
    Memory(Vec<Row>),
}

/// A row's bytes in a [`RowLog`]'s file.
const ROW_LEN: usize = 48;

/// Rows read at a time when they are read again.
const ROWS_READ: usize = 1024;

fn encode_row(row: &Row) -> [u8; ROW_LEN] {
    let mut b = [0u8; ROW_LEN];
    b[..32].copy_from_slice(&row.key.0);
    for (i, n) in [row.text_len, row.files, row.absent, row.warnings].into_iter().enumerate() {
        b[32 + 4 * i..36 + 4 * i].copy_from_slice(&n.to_le_bytes());
    }
    b
}

fn decode_row(b: &[u8; ROW_LEN]) -> Row {
    let n = |i: usize| u32::from_le_bytes(b[32 + 4 * i..36 + 4 * i].try_into().expect("4 bytes"));
    Row { key: Key(b[..32].try_into().expect("32 bytes")), text_len: n(0), files: n(1), absent: n(2), warnings: n(3) }
}

impl RowLog {
    fn new() -> RowLog {
        let out = match tempfile::tempfile() {
            Ok(f) => RowsOut::File(std::io::BufWriter::with_capacity(1 << 16, f)),
            Err(_) => RowsOut::Memory(Vec::new()),
        };
        RowLog { out, count: 0, error: None, recent: vec![None; RECENT_ROWS] }
    }

    /// Adds `row`; its number (an equal row's among the latest added).
    fn push(&mut self, row: &Row) -> u32 {
        let slot = u16::from_le_bytes([row.key.0[0], row.key.0[1]]) as usize % RECENT_ROWS;
        match self.recent[slot] {
            Some((recent, n)) if recent == *row => return n,
            _ => self.recent[slot] = Some((*row, self.count)),
        }
        match &mut self.out {
            RowsOut::Memory(v) => v.push(*row),
            RowsOut::File(f) => {
                if let Err(e) = std::io::Write::write_all(f, &encode_row(row)) {
                    self.error.get_or_insert(e);
                }
            }
        }
        self.count += 1;
        self.count - 1
    }

    /// Row `n`, read back while rows are still added (a piece's, to store it).
    fn get(&mut self, n: u32) -> std::io::Result<Row> {
        use std::os::unix::fs::FileExt;
        if let Some(e) = &self.error {
            return Err(std::io::Error::new(e.kind(), e.to_string()));
        }
        match &mut self.out {
            RowsOut::Memory(v) => v.get(n as usize).copied().ok_or_else(|| std::io::ErrorKind::NotFound.into()),
            RowsOut::File(f) => {
                std::io::Write::flush(f)?;
                let mut b = [0u8; ROW_LEN];
                f.get_ref().read_exact_at(&mut b, u64::from(n) * ROW_LEN as u64)?;
                Ok(decode_row(&b))
            }
        }
    }

    /// The rows, their file kept for reading them again.
    fn load(self) -> std::io::Result<Rows> {
        if let Some(e) = self.error {
            return Err(e);
        }
        match self.out {
            RowsOut::Memory(v) => Ok(Rows::Memory(v)),
            RowsOut::File(f) => {
                Ok(Rows::File { count: self.count as usize, file: f.into_inner().map_err(|e| e.into_error())? })
            }
        }
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

/// (shader, level) → [(define names that mattered, values of those names → row number)].
type ReuseGroups =
    HashMap<(String, String), Vec<(Vec<String>, HashMap<u32, u32, BuildHasherDefault<crate::compile::IdentHasher>>)>>;

/// The values of the defines that mattered, hashed (a fixed size per entry, whatever their
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
///
/// A (shader, level)'s results are let go once its last permutation has been taken
/// (permutations are taken in plan order): the maps hold the largest group's results, not
/// the whole set's.
///
/// A map holds each result by the first 32 bits of its signature and the number of its
/// entry in [`ReuseLog`], which has the whole signature and the row (read back to confirm a
/// match): 8 bytes a result in memory, not 20, in maps that hold a group's every result. (Of
/// two results whose signatures begin alike, a few in a set of a million, the second is not
/// kept for reuse: its permutations are preprocessed, to the same result.)
#[derive(Default)]
struct Reuse {
    groups: Mutex<ReuseGroups>,
    log: Mutex<ReuseLog>,
    /// Each group's end in the plan (one past its last permutation), latest first; and the
    /// groups let go.
    ends: Mutex<GroupEnds>,
}

/// Each group's end in the plan, latest first, and the groups let go.
type GroupEnds = (Vec<(usize, GroupName)>, HashSet<GroupName>);

/// A (shader, level) by name.
type GroupName = (String, String);

impl Reuse {
    /// Each group's end in `plan`, as a position in the order permutations are taken: one
    /// past its last taken (`run_end` of each of its runs).
    fn plan_ends(&self, plan: &Plan<'_>, run_end: &dyn Fn(std::ops::Range<usize>) -> usize) {
        let mut last: HashMap<GroupName, usize> = HashMap::new();
        for (shader, level, range) in plan.runs().filter(|r| !r.2.is_empty()) {
            let end = last.entry((shader.name.clone(), level.name.clone())).or_default();
            *end = (*end).max(run_end(range));
        }
        let mut ends: Vec<(usize, GroupName)> = last.into_iter().map(|(g, end)| (end, g)).collect();
        ends.sort_unstable_by(|a, b| b.cmp(a));
        *self.ends.lock().expect("no panics while locked") = (ends, HashSet::new());
    }

    /// Lets go of the groups that end at or before permutation `i`: their last permutation
    /// was taken (one still in flight finds nothing and keeps nothing: no wrong result).
    fn retire_before(&self, i: usize) {
        let mut ends = self.ends.lock().expect("no panics while locked");
        let (ends, retired) = &mut *ends;
        if ends.last().is_none_or(|(end, _)| *end > i) {
            return;
        }
        let mut groups = self.groups.lock().expect("no panics while locked");
        while let Some((_, g)) = ends.pop_if(|(end, _)| *end <= i) {
            groups.remove(&g);
            retired.insert(g);
        }
        if groups.is_empty() {
            *groups = ReuseGroups::default();
            *self.log.lock().expect("no panics while locked") = ReuseLog::default();
        }
    }

    fn find(&self, p: &Permutation<'_>, values: &HashMap<String, i64>) -> Option<u32> {
        let groups = self.groups.lock().expect("no panics while locked");
        let sets = groups.get(&(p.shader.name.clone(), p.level.name.clone()))?;
        for (names, results) in sets {
            let Some(vals) = names.iter().map(|n| values.get(n).copied()).collect::<Option<Vec<i64>>>() else {
                continue;
            };
            let signature = signature(vals.into_iter());
            let Some(&entry) = results.get(&half(&signature)) else { continue };
            // A failed read finds nothing: the permutation is preprocessed (same result).
            match self.log.lock().expect("no panics while locked").get(entry) {
                Ok((whole, row)) if whole == signature => return Some(row),
                _ => {}
            }
        }
        None
    }

    fn insert(
        &self,
        p: &Permutation<'_>,
        values: &HashMap<String, i64>,
        output: &preprocess::Output,
        row: u32,
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
        let g = (p.shader.name.clone(), p.level.name.clone());
        // The same order of locks as `retire_before`.
        let ends = self.ends.lock().expect("no panics while locked");
        if ends.1.contains(&g) {
            return;
        }
        let mut groups = self.groups.lock().expect("no panics while locked");
        let sets = groups.entry(g).or_default();
        let i = match sets.iter().position(|(n, _)| *n == names) {
            Some(i) => i,
            None => {
                sets.push((names, HashMap::default()));
                sets.len() - 1
            }
        };
        if let std::collections::hash_map::Entry::Vacant(v) = sets[i].1.entry(half(&signature)) {
            // A result that cannot be logged is not kept for reuse.
            if let Ok(entry) = self.log.lock().expect("no panics while locked").push(&signature, row) {
                v.insert(entry);
            }
        }
    }
}

/// A signature's first 32 bits, what a reuse map holds it by.
fn half(signature: &Signature) -> u32 {
    u32::from_le_bytes(signature[..4].try_into().expect("4 of 16 bytes"))
}

/// Each result put in a reuse map, by number: its whole signature and its row, in an
/// unlinked temporary file (the latest in memory until a chunk is written; all in memory
/// where no file can be made).
#[derive(Default)]
struct ReuseLog {
    file: Option<std::fs::File>,
    /// Whether a file was tried (made on the first push).
    tried: bool,
    /// Entries before this one are in `file`.
    flushed: u32,
    pending: Vec<[u8; REUSE_ENTRY]>,
}

/// An entry of [`ReuseLog`]: the signature, then the row.
const REUSE_ENTRY: usize = 20;

/// Entries held before they are written (80 KiB).
const REUSE_CHUNK: usize = 4096;

impl ReuseLog {
    /// Logs `signature` and `row`: the entry's number.
    fn push(&mut self, signature: &Signature, row: u32) -> std::io::Result<u32> {
        use std::os::unix::fs::FileExt;
        if !self.tried {
            self.tried = true;
            self.file = tempfile::tempfile().ok();
        }
        let n = self.flushed.checked_add(self.pending.len() as u32).ok_or_else(|| std::io::Error::other("too many"))?;
        let mut entry = [0u8; REUSE_ENTRY];
        entry[..16].copy_from_slice(signature);
        entry[16..].copy_from_slice(&row.to_le_bytes());
        self.pending.push(entry);
        if let (Some(file), REUSE_CHUNK) = (&self.file, self.pending.len()) {
            file.write_all_at(self.pending.as_flattened(), u64::from(self.flushed) * REUSE_ENTRY as u64)?;
            self.flushed += REUSE_CHUNK as u32;
            self.pending.clear();
        }
        Ok(n)
    }

    /// Entry `n`: the signature and the row.
    fn get(&self, n: u32) -> std::io::Result<(Signature, u32)> {
        use std::os::unix::fs::FileExt;
        let entry = match n.checked_sub(self.flushed) {
            Some(i) => *self.pending.get(i as usize).ok_or_else(|| std::io::Error::other("no such entry"))?,
            None => {
                let file = self.file.as_ref().ok_or_else(|| std::io::Error::other("no such entry"))?;
                let mut entry = [0u8; REUSE_ENTRY];
                file.read_exact_at(&mut entry, u64::from(n) * REUSE_ENTRY as u64)?;
                entry
            }
        };
        let row = u32::from_le_bytes(entry[16..].try_into().expect("4 bytes"));
        Ok((entry[..16].try_into().expect("16 bytes"), row))
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
            crate::archive::input::read_regular(path, crate::preprocess::source::MAX_FILE_BYTES).ok().map(|bytes| {
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

/// What every permutation's preprocessing record key shares: the include folders (those
/// under the configuration's folder `root` relative to it, so that records hold in
/// another checkout of the same sources, like the paths they store: see
/// [`records::encode`]), the preprocessor's limits and the versions. Not the
/// configuration's text: a record holds as long as its own permutation's inputs do
/// ([`direct_key`]), so that adding a material or a shader preprocesses only what it adds.
fn direct_base(config: &Config, root: &Path) -> blake3::Hash {
    let mut h = blake3::Hasher::new();
    let mut field = |bytes: &[u8]| {
        h.update(&(bytes.len() as u64).to_le_bytes());
        h.update(bytes);
    };
    field(b"kiln direct v4");
    let relative = |p: &Path| {
        let p = p.strip_prefix(root).or_else(|_| p.strip_prefix(&config.dir)).unwrap_or(p);
        p.as_os_str().as_encoded_bytes().to_vec()
    };
    let opts = config.preprocess_options();
    field(&(opts.include_roots.len() as u64).to_le_bytes());
    for r in &opts.include_roots {
        field(&relative(r));
    }
    field(&(opts.virtual_roots.len() as u64).to_le_bytes());
    for (prefix, r) in &opts.virtual_roots {
        field(prefix.as_bytes());
        field(&relative(r));
    }
    field(&(opts.max_expansion_depth as u64).to_le_bytes());
    field(&(opts.max_output_bytes as u64).to_le_bytes());
    field(crate::compile::NAGA_VERSION.as_bytes());
    h.finalize()
}

/// The key of a permutation's preprocessing record: everything preprocessing and the
/// compile key depend on, except the files' contents (checked against the record): `base`,
/// its source file as the configuration names it, its defines (`defines`: the level's, the
/// shader's, its dimensions' values and derived values, as the preprocessor is given
/// them), entry, stage, level, limits and targets.
fn direct_key(
    base: &blake3::Hash,
    p: &Permutation<'_>,
    defines: &[crate::permute::Define],
    targets: &[crate::archive::Target],
) -> Direct {
    let mut h = blake3::Hasher::new();
    h.update(base.as_bytes());
    // As the configuration names it (its folder and the roots that resolve it are in `base`).
    h.update(&(p.shader.source.len() as u64).to_le_bytes());
    h.update(p.shader.source.as_bytes());
    h.update(&(defines.len() as u64).to_le_bytes());
    for d in defines {
        h.update(&(d.name.len() as u64).to_le_bytes());
        h.update(d.name.as_bytes());
        h.update(&d.value.to_le_bytes());
    }
    let targets = level_targets(p.level, targets);
    let key = Key::new(&h.finalize(), &p.shader.entry, p.shader.stage, &p.level.name, &level_limits(p.level), &targets);
    key.0[..16].try_into().expect("16 of 32 bytes")
}

/// The configuration's bytes now (a marker no record has when it cannot be read, or is no
/// longer a regular file).
fn read_config(config: &Config) -> Vec<u8> {
    crate::archive::input::read_regular(&config.path, crate::permute::MAX_CONFIG_BYTES)
        .unwrap_or_else(|_| b"\0unreadable".to_vec())
}

/// The key of a configuration's set of preprocessing records: its text and the options
/// that choose its permutations; not its path, so that another checkout (another machine,
/// another folder) finds the set in the remote cache. (v4: paths relative to the
/// configuration's folder; v5: compact rows; v6: 16-byte direct keys; v7: direct keys
/// of each permutation's own inputs.)
fn records_key(config: &Config, options: &Options) -> Key {
    let text = read_config(config);
    let inputs =
        format!("kiln records v7\n{}\n{:?}\n{:?}", blake3::hash(&text).to_hex(), options.levels, options.targets);
    Key::new(&blake3::hash(inputs.as_bytes()), "", crate::Stage::Compute, "", &Limits::desktop(), &[])
}

/// The key under which the local cache (only: the path is this machine's) keeps the
/// [`records_key`] of the last records saved for the configuration file at this path and
/// these options: what a build whose configuration changed since starts from.
fn last_records_key(config: &Config, options: &Options) -> Key {
    let path = config.path.canonicalize().unwrap_or_else(|_| config.path.clone());
    let inputs = format!("kiln last records v1\n{}\n{:?}\n{:?}", path.display(), options.levels, options.targets);
    Key::new(&blake3::hash(inputs.as_bytes()), "", crate::Stage::Compute, "", &Limits::desktop(), &[])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_reuse_log_gives_back_each_entry_across_its_chunks() {
        let signature = |n: u32| -> Signature { std::array::from_fn(|i| (n as usize * 7 + i) as u8) };
        for file in [true, false] {
            // Without a file (none could be made), every entry stays in memory.
            let mut log = ReuseLog { tried: !file, ..ReuseLog::default() };
            let count = REUSE_CHUNK as u32 * 2 + 5;
            for n in 0..count {
                assert_eq!(log.push(&signature(n), n * 3).unwrap(), n);
            }
            assert_eq!(log.file.is_some(), file);
            assert_eq!(log.flushed, if file { REUSE_CHUNK as u32 * 2 } else { 0 });
            for n in [0, 1, REUSE_CHUNK as u32 - 1, REUSE_CHUNK as u32, count - 1] {
                assert_eq!(log.get(n).unwrap(), (signature(n), n * 3), "entry {n}");
            }
            assert!(log.get(count).is_err(), "past the last entry");
        }
    }

    #[test]
    fn row_keys_are_read_back_a_block_at_a_time() {
        let mut log = RowLog::new();
        let row = |n: u32| Row { key: Key([n as u8; 32]), text_len: n, files: 0, absent: 0, warnings: 0 };
        // More rows than the reader keeps blocks of, each distinct (no row is taken for another).
        let count = (KEY_BLOCK * (KEY_BLOCKS + 2)) as u32;
        for n in 0..count {
            let mut r = row(n);
            r.key.0[1] = (n >> 8) as u8;
            assert_eq!(log.push(&r), n);
        }
        let pre = Preprocessed { of: vec![3, FAILED], rows: log.load().unwrap(), errors: Vec::new() };
        assert_eq!(pre.row_count(), count as usize);
        let mut keys = pre.keys();
        for n in [0, count - 1, 5, (KEY_BLOCK * 3) as u32 + 1, 5] {
            let key = keys.row(n as usize).unwrap();
            assert_eq!((key.0[0], key.0[1]), (n as u8, (n >> 8) as u8), "row {n}");
        }
        assert_eq!(keys.of(0).unwrap().map(|k| k.0[0]), Some(3));
        assert_eq!(keys.of(1).unwrap(), None, "a failed permutation has no key");
    }
}
