//! Assemble: the archive, the loose files of `--emit-dir` and the archive's stamp.
//!
//! Each key's artifacts arrive ([`Assembler::add`]) as they are produced, from any worker
//! and in any order: their bytes go at once to the archive's spool (a
//! [`StreamingWriter`]) and to the loose files, and are dropped; what stays per key is its
//! reflection's number and its blobs' numbers in the writer.
//! [`Assembler::finish`] then adds the permutations, whose records are the manifest: with
//! the writer's per-blob identities, what grows with the set.
//! The writer orders everything by content and name, so the bytes depend only on the set
//! (not on `-j`, the cache state or shards). Nothing is kept when the build writes neither
//! an archive nor loose files (a check or a shard).

use std::collections::{BTreeMap, HashMap, HashSet};
use std::io::{Read, Seek, Write};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use super::group::Keys;
use super::plan::Plan;
use super::preprocess::Preprocessed;
use super::store::Store;
use super::Error;
use crate::archive::{
    self, ArtifactRange, DimensionRecord, NewPermutation, Reflection, ShaderRecord, Stage, StreamingWriter, Target,
};
use crate::cache::{Held, Key};
use crate::compile::{self, Compiled};

/// What stays of a key once its artifacts are written, its artifacts in its record
/// (`first` counts the artifacts of the records before it): 8 bytes a key, held for every
/// key while the manifest is added
/// (its reflection's number and its artifacts' count share a word: a key has fewer than 256
/// artifacts, one a target, and a build fewer than 2^24 reflections).
#[derive(Clone, Copy)]
struct KeyEntry {
    first: u32,
    reflection_count: u32,
}

impl KeyEntry {
    /// `None` past what an entry holds (a damaged record).
    fn new(reflection: u32, first: u32, count: u32) -> Option<KeyEntry> {
        (reflection < 1 << 24 && count < 1 << 8)
            .then_some(KeyEntry { first, reflection_count: reflection << 8 | count })
    }

    fn reflection(&self) -> u32 {
        self.reflection_count >> 8
    }

    fn count(&self) -> u32 {
        self.reflection_count & 0xFF
    }
}

/// What stays of the keys produced, as they are produced: each key's record (its key,
/// reflection number, and each artifact's target and blob number) goes to an unlinked temporary file, read back by [`Assembler::finish`] once the
/// stages before it have let go of their tables, so that it adds nothing to the build's
/// peak. In memory where no temporary file can be made.
struct Log {
    records: Records,
    /// Records written.
    keys: usize,
    /// Artifacts in them.
    artifacts: usize,
    /// Each artifact's blake3 (the `k`th artifact written's is `hashes[k]`), with loose files
    /// only: what `--emit-dir` names them by.
    hashes: Vec<blake3::Hash>,
    reflections: Vec<Arc<Reflection>>,
    reflection_index: HashMap<Arc<Reflection>, u32>,
}

/// Where the key records wait.
enum Records {
    File(std::io::BufWriter<std::fs::File>),
    Memory(Vec<u8>),
}

impl Log {
    /// A log whose records go to a temporary file if `spill` (and one can be made).
    fn new(spill: bool) -> Log {
        let records = match spill.then(tempfile::tempfile) {
            Some(Ok(f)) => Records::File(std::io::BufWriter::new(f)),
            _ => Records::Memory(Vec::new()),
        };
        Log {
            records,
            keys: 0,
            artifacts: 0,
            hashes: Vec::new(),
            reflections: Vec::new(),
            reflection_index: HashMap::new(),
        }
    }

    /// Records `key`'s reflection number and artifacts.
    fn write(&mut self, key: &Key, reflection: u32, artifacts: &[(Target, u32)]) -> std::io::Result<()> {
        let mut record = Vec::with_capacity(RECORD_HEAD + RECORD_ARTIFACT * artifacts.len());
        record.extend_from_slice(&key.0);
        record.extend_from_slice(&reflection.to_le_bytes());
        record.extend_from_slice(&(artifacts.len() as u32).to_le_bytes());
        for (t, n) in artifacts {
            record.push(Target::ALL.iter().position(|a| a == t).expect("a target") as u8);
            record.extend_from_slice(&n.to_le_bytes());
        }
        match &mut self.records {
            Records::File(f) => f.write_all(&record)?,
            Records::Memory(v) => v.extend_from_slice(&record),
        }
        self.keys += 1;
        self.artifacts += artifacts.len();
        Ok(())
    }

    /// The records read back into a table: each key's prefix and record number, sorted (the
    /// whole keys only of the few whose prefix another key shares). Their entries and
    /// artifacts are read in a second pass ([`Produced::by_permutation`]), once the
    /// permutations' keys are gone.
    fn load(self) -> std::io::Result<Produced> {
        let mut input: Box<dyn Input> = match self.records {
            Records::File(f) => Box::new(f.into_inner().map_err(|e| e.into_error())?),
            Records::Memory(v) => Box::new(std::io::Cursor::new(v)),
        };
        let mut slots = Vec::with_capacity(self.keys);
        let mut record = 0;
        each_record(input.as_mut(), self.keys, |key, _, _| {
            slots.push(Slot { prefix: split(key_hash(key)), record });
            record += 1;
        })?;
        slots.sort_unstable_by_key(|s| s.prefix);
        // A prefix seen twice (a key produced twice, or two keys that share it) is settled
        // by the whole keys, read again: of a key produced twice the later record wins.
        let repeated: HashSet<[u32; 2]> =
            slots.windows(2).filter(|w| w[0].prefix == w[1].prefix).map(|w| w[0].prefix).collect();
        let mut shared = Vec::new();
        if !repeated.is_empty() {
            slots.retain(|s| !repeated.contains(&s.prefix));
            let mut whole: HashMap<Key, u32> = HashMap::new();
            let mut record = 0;
            each_record(input.as_mut(), self.keys, |key, _, _| {
                if repeated.contains(&split(key_hash(key))) {
                    whole.insert(*key, record);
                }
                record += 1;
            })?;
            shared = whole.into_iter().collect();
            shared.sort_unstable_by_key(|s: &(Key, u32)| s.0);
        }
        let (keys, artifacts, hashes, reflections) = (self.keys, self.artifacts, self.hashes, self.reflections);
        Ok(Produced { slots, shared, input, keys, artifacts, hashes, reflections })
    }
}

/// The entries of the `count` records of `input`, by record number.
fn read_entries(input: &mut dyn Input, count: usize) -> std::io::Result<Vec<KeyEntry>> {
    let mut entries = Vec::with_capacity(count);
    each_record(input, count, |_, entry, _| entries.push(entry))?;
    Ok(entries)
}

/// The artifacts of the `count` records of `input` (`artifacts` in all), one after another.
fn read_artifacts(input: &mut dyn Input, count: usize, artifacts: usize) -> std::io::Result<Artifacts> {
    let mut a = Artifacts { targets: Vec::with_capacity(artifacts), numbers: Vec::with_capacity(artifacts) };
    each_record(input, count, |_, _, artifacts| {
        a.targets.extend(artifacts.iter().map(|x| x.0));
        a.numbers.extend(artifacts.iter().map(|x| x.1));
    })?;
    Ok(a)
}

/// Where key records are read back from: their file, or memory.
trait Input: Read + Seek {
    /// Fills `buf` from `offset` on (the position after it is unspecified).
    fn read_exact_at(&mut self, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
        self.seek(std::io::SeekFrom::Start(offset))?;
        self.read_exact(buf)
    }
}

impl Input for std::io::Cursor<Vec<u8>> {}

/// One read a call, not a seek and a read.
impl Input for std::fs::File {
    fn read_exact_at(&mut self, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
        std::os::unix::fs::FileExt::read_exact_at(self, buf, offset)
    }
}

/// The length of a key record before its artifacts: the key, its reflection's number and
/// its artifacts' count.
const RECORD_HEAD: usize = 40;

/// The length of an artifact in a key record: its target's index and its blob's number.
const RECORD_ARTIFACT: usize = 5;

/// Calls `f` with each of the `count` records of `input`, from its start: the key, its entry
/// (`first` counting the artifacts of the records before it) and its artifacts.
fn each_record(
    input: &mut dyn Input,
    count: usize,
    mut f: impl FnMut(&Key, KeyEntry, &[(Target, u32)]),
) -> std::io::Result<()> {
    input.seek(std::io::SeekFrom::Start(0))?;
    let mut input = std::io::BufReader::new(input);
    let damaged = || std::io::Error::other("a temporary file of the build was changed");
    let mut first = 0u32;
    let mut artifacts = Vec::new();
    for _ in 0..count {
        let mut head = [0u8; RECORD_HEAD];
        input.read_exact(&mut head)?;
        let key = Key(head[..32].try_into().expect("32 bytes"));
        let reflection = u32::from_le_bytes(head[32..36].try_into().expect("4 bytes"));
        let n = u32::from_le_bytes(head[36..40].try_into().expect("4 bytes"));
        artifacts.clear();
        for _ in 0..n {
            let mut a = [0u8; RECORD_ARTIFACT];
            input.read_exact(&mut a)?;
            artifacts.push(decode_artifact(&a).ok_or_else(damaged)?);
        }
        f(&key, KeyEntry::new(reflection, first, n).ok_or_else(damaged)?, &artifacts);
        first = first.checked_add(n).ok_or_else(damaged)?;
    }
    Ok(())
}

/// An artifact of a key record: its target and blob number (`None` for no target).
fn decode_artifact(a: &[u8]) -> Option<(Target, u32)> {
    let target = *Target::ALL.get(a[0] as usize)?;
    Some((target, u32::from_le_bytes(a[1..RECORD_ARTIFACT].try_into().expect("4 bytes"))))
}

/// A produced key's prefix and the number of its record (its entry is read with the
/// artifacts, once each permutation's record number is found: 12 bytes a key, not 20).
#[derive(Clone, Copy)]
struct Slot {
    /// [`key_hash`] as two halves, so that a slot is not padded to eight bytes' alignment.
    prefix: [u32; 2],
    record: u32,
}

fn split(prefix: u64) -> [u32; 2] {
    [(prefix >> 32) as u32, prefix as u32]
}

/// What stays of the keys produced, read back for the manifest.
struct Produced {
    /// Each key produced by its prefix, sorted, but for the keys whose prefix another
    /// produced key shares (rare), which are in `shared` whole: a prefix found here is the
    /// key's (only produced keys are looked up). Not the whole keys and a table to find
    /// them, which held three times as much where the assembly peaks.
    slots: Vec<Slot>,
    shared: Vec<(Key, u32)>,
    /// The records, for their entries and artifacts.
    input: Box<dyn Input>,
    /// Records and artifacts in them.
    keys: usize,
    artifacts: usize,
    /// [`Log::hashes`].
    hashes: Vec<blake3::Hash>,
    reflections: Vec<Arc<Reflection>>,
}

/// A prefix of a key: already uniform (a blake3).
fn key_hash(key: &Key) -> u64 {
    u64::from_le_bytes(key.0[..8].try_into().expect("8 of 32 bytes"))
}

impl Produced {
    /// The number of `key`'s entry: its slot's, else past the slots, its place in `shared`.
    fn position(&self, key: &Key) -> Option<u32> {
        let prefix = split(key_hash(key));
        match self.slots.binary_search_by_key(&prefix, |s| s.prefix) {
            Ok(n) => Some(self.slots[n].record),
            Err(_) => self.shared.binary_search_by_key(key, |s| s.0).ok().map(|n| self.shared[n].1),
        }
    }

    /// Each kept permutation's key's record number (`NOT_KEPT` for the others), the records'
    /// entries by number, their hashes and the reflections: what stays once `pre` goes. The
    /// entries are read only then, so that they and `pre` are never held together; the
    /// artifacts stay in the records ([`ByPermutation::load_artifacts`]).
    fn by_permutation(self, plan: &Plan<'_>, pre: Preprocessed) -> std::io::Result<ByPermutation> {
        let mut keys = pre.keys();
        let of = (0..plan.len())
            .map(|i| {
                Ok(keys
                    .of(i)?
                    .map_or(NOT_KEPT, |k| self.position(&k).expect("every kept permutation's key was produced")))
            })
            .collect::<std::io::Result<_>>()?;
        drop(keys);
        drop(pre);
        // The prefixes are not needed past here: they go before the entries come.
        let Produced { slots, shared, mut input, keys, artifacts, hashes, reflections } = self;
        drop((slots, shared));
        super::release_freed();
        let entries = read_entries(input.as_mut(), keys)?;
        let artifacts_in_all = artifacts;
        Ok(ByPermutation {
            of,
            entries,
            artifacts: Artifacts::default(),
            artifacts_in_all,
            records: input,
            hashes,
            reflections,
        })
    }
}

/// [`Produced::by_permutation`]: a fraction of what the keys produced and `pre` took, which
/// it replaces.
struct ByPermutation {
    of: Vec<u32>,
    entries: Vec<KeyEntry>,
    /// The keys' artifacts one after another, once loaded ([`ByPermutation::load_artifacts`]);
    /// else each is read from `records` as its permutation is added.
    artifacts: Artifacts,
    /// The artifacts of all the records.
    artifacts_in_all: usize,
    records: Box<dyn Input>,
    hashes: Vec<blake3::Hash>,
    reflections: Vec<Arc<Reflection>>,
}

/// Artifacts one after another: each one's target and blob number, packed (a table of
/// pairs would be padded, and is held while the manifest is added).
#[derive(Default)]
struct Artifacts {
    targets: Vec<Target>,
    numbers: Vec<u32>,
}

/// How the permutations added to the archive name their artifacts
/// ([`ByPermutation::ready_writer`]).
#[derive(Clone, Copy)]
enum Naming {
    /// In name order, each with its artifacts read from the key records as it comes.
    Sorted,
    /// By range of the keys' artifacts handed to the writer, the first's number.
    Ranged(u32),
    /// Each with a copy of its key's artifacts (with loose files).
    Numbered,
}

fn archive_error(e: archive::ArchiveError) -> Error {
    Error::Io(format!("error: {e}"))
}

fn read_back(e: std::io::Error) -> Error {
    Error::Io(format!("error: cannot read back a temporary file of the build: {e}"))
}

/// [`ByPermutation::of`] a permutation that is not kept (it failed, or was skipped).
const NOT_KEPT: u32 = u32::MAX;

impl ByPermutation {
    /// Permutation `i`'s key's entry, if it is kept.
    fn get(&self, i: usize) -> Option<&KeyEntry> {
        self.entries.get(self.of[i] as usize)
    }

    /// Reserves the manifest's exact size in `w`, so that its arenas are allocated once.
    /// Artifacts are reserved unless the permutations name their keys' (`ranged`).
    fn reserve_manifest(&self, plan: &Plan<'_>, w: &StreamingWriter, ranged: bool) {
        let (mut n, mut values, mut artifacts) = (0, 0, 0);
        for i in 0..plan.len() {
            let Some(e) = self.get(i) else { continue };
            n += 1;
            values += plan.shader_level(i).0.dimensions.len();
            artifacts += e.count() as usize;
        }
        // No room for names: canonical names are made again from the values, never kept
        // (and making each name here to count its bytes cost a name a permutation).
        w.reserve(n, 0, values, if ranged { 0 } else { artifacts });
    }

    /// Readies `w` for the manifest and says how each permutation's artifacts will be
    /// named: when the permutations come in name order (`sorted` of them), a sorted
    /// manifest begun, each permutation's artifacts read as it comes; else the keys'
    /// artifacts loaded, the manifest's size reserved and, when the permutations name
    /// their keys' artifacts by range (`ranged`), the artifacts handed over.
    fn ready_writer(
        &mut self,
        plan: &Plan<'_>,
        w: &StreamingWriter,
        ranged: bool,
        sorted: Option<usize>,
    ) -> Result<Naming, Error> {
        if let Some(n) = sorted {
            w.begin_sorted(n).map_err(archive_error)?;
            return Ok(Naming::Sorted);
        }
        self.load_artifacts().map_err(read_back)?;
        self.reserve_manifest(plan, w, ranged);
        if !ranged {
            return Ok(Naming::Numbered);
        }
        let a = std::mem::take(&mut self.artifacts);
        w.add_artifacts(a.targets, a.numbers).map(Naming::Ranged).map_err(archive_error)
    }

    /// Adds permutation `i` (kept) to `w`, its shader's record `shader`, its artifacts
    /// named as `naming` says.
    fn add(
        &mut self,
        w: &StreamingWriter,
        plan: &Plan<'_>,
        i: usize,
        shader: &ShaderRecord,
        naming: Naming,
    ) -> Result<(), Error> {
        let record = self.of[i] as usize;
        let entry = *self.entries.get(record).expect("a kept permutation");
        let artifacts = match naming {
            Naming::Sorted => self.read_artifacts(record, &entry).map_err(read_back)?,
            Naming::Ranged(_) => Vec::new(),
            Naming::Numbered => self.artifacts(&entry),
        };
        let (name, values) = (plan.name(i), plan.values(i));
        let reflection = &self.reflections[entry.reflection() as usize];
        let p = NewPermutation { name, shader, values, reflection, artifacts };
        let added = match naming {
            Naming::Sorted => w.add_permutation_sorted_numbered(p),
            Naming::Ranged(first) => {
                w.add_permutation_ranged(p, ArtifactRange { first: first + entry.first, count: entry.count() as u8 })
            }
            Naming::Numbered => w.add_permutation_numbered(p),
        };
        added.map_err(archive_error)
    }

    /// Reads every key's artifacts into memory, where they are handed to the writer or
    /// named by loose files (a manifest added in name order reads each permutation's from
    /// the records instead: [`ByPermutation::read_artifacts`]).
    fn load_artifacts(&mut self) -> std::io::Result<()> {
        self.artifacts = read_artifacts(self.records.as_mut(), self.entries.len(), self.artifacts_in_all)?;
        Ok(())
    }

    /// The artifacts of the key of `e`, read from its record: a read a permutation, where
    /// the artifacts of every key would be held until the manifest's end (a fifth of the
    /// build's tables at this stage, at a million permutations).
    fn read_artifacts(&mut self, record: usize, e: &KeyEntry) -> std::io::Result<Vec<(Target, u32)>> {
        let mut bytes = [0u8; RECORD_ARTIFACT * 255];
        let bytes = &mut bytes[..RECORD_ARTIFACT * e.count() as usize];
        let at = RECORD_HEAD * (record + 1) + RECORD_ARTIFACT * e.first as usize;
        self.records.read_exact_at(bytes, at as u64)?;
        let damaged = || std::io::Error::other("a temporary file of the build was changed");
        bytes.chunks_exact(RECORD_ARTIFACT).map(|a| decode_artifact(a).ok_or_else(damaged)).collect()
    }

    fn artifacts(&self, e: &KeyEntry) -> Vec<(Target, u32)> {
        let range = e.first as usize..(e.first + e.count()) as usize;
        let a = &self.artifacts;
        a.targets[range.clone()].iter().copied().zip(a.numbers[range].iter().copied()).collect()
    }
}

pub(super) struct Assembler<'p> {
    plan: &'p Plan<'p>,
    /// The archive's writer, with `-o`.
    writer: Option<StreamingWriter>,
    produced: Mutex<Log>,
    /// Loose files written (`--emit-dir`): blake3 → file name.
    emitted: Mutex<HashMap<blake3::Hash, String>>,
    /// The first artifact that could not be written.
    error: Mutex<Option<String>>,
    fingerprint: std::sync::OnceLock<blake3::Hash>,
}

/// [`Assembler::fingerprint`] with `key` giving each kept permutation's key: the text of
/// each permutation (`\0name\0entry\0stage\0values\0dimensions\0`, values and dimensions
/// as their `Debug`) then its key; what a shader's permutations share is formatted once
/// per run.
fn fingerprint(plan: &Plan<'_>, mut key: impl FnMut(usize) -> Option<Key>) -> blake3::Hash {
    let mut h = blake3::Hasher::new();
    h.update(b"kiln build fingerprint v1\0");
    h.update(crate::VERSION.as_bytes());
    h.update(b"\0");
    h.update(compile::NAGA_VERSION.as_bytes());
    // An archive of an older format is rewritten (its blobs are not reused: see
    // `kiln_archive`'s `reuse`), not kept as up to date.
    h.update(format!("\0archive format {}", archive::FORMAT_VERSION).as_bytes());
    for (shader, level, range) in plan.runs() {
        let dims: Vec<(&str, &[String])> =
            shader.dimensions.iter().map(|d| (d.name.as_str(), d.labels.as_slice())).collect();
        let entry_stage = format!("\0{}\0{}\0", shader.entry, shader.stage);
        let dims = format!("\0{dims:?}\0");
        let mut values = String::new();
        for i in range {
            let Some(key) = key(i) else { continue };
            let v = plan.values(i);
            values.clear();
            std::fmt::Write::write_fmt(&mut values, format_args!("{v:?}")).expect("a String takes any text");
            h.update(b"\0");
            h.update(crate::permute::canonical_name(shader, level, &v).as_bytes());
            h.update(entry_stage.as_bytes());
            h.update(values.as_bytes());
            h.update(dims.as_bytes());
            h.update(&key.0);
        }
    }
    // A partial archive names what it left out; a whole one's fingerprint is as it was.
    if let Some(left_out) = plan.usage.as_ref().map(|u| &u.left_out).filter(|l| !l.is_empty()) {
        h.update(b"\0left out\0");
        for name in left_out {
            h.update(name.as_bytes());
            h.update(b"\0");
        }
    }
    // So is one without a pipeline manifest.
    if let Some(pipelines) = plan.usage.as_ref().map(|u| &u.pipelines).filter(|p| !p.is_empty()) {
        h.update(b"\0pipelines\0");
        for r in pipelines {
            h.update(serde_json::to_string(r).expect("a pipeline record serializes").as_bytes());
            h.update(b"\0");
        }
    }
    h.finalize()
}

/// What [`Assembler::finish`] wrote: distinct blobs and (permutation, target) pairs.
pub(super) struct Written {
    pub artifacts: usize,
    pub permutation_artifacts: usize,
    pub reused_blobs: usize,
    pub archive: Option<PathBuf>,
}

impl<'p> Assembler<'p> {
    pub fn new(plan: &'p Plan<'p>) -> Result<Assembler<'p>, Error> {
        let writer = match &plan.options.output {
            Some(out) => Some(StreamingWriter::new(out).map_err(|e| Error::Io(format!("error: {e}")))?),
            None => None,
        };
        if let Some(w) = &writer {
            w.set_naga_version(compile::NAGA_VERSION);
            if let Some(left_out) = plan.usage.as_ref().map(|u| &u.left_out).filter(|l| !l.is_empty()) {
                w.set_partial(crate::archive::Partial { left_out: left_out.clone() });
            }
            if let Some(pipelines) = plan.usage.as_ref().map(|u| &u.pipelines).filter(|p| !p.is_empty()) {
                w.set_pipelines(pipelines.clone());
            }
            w.set_hooks(crate::archive::WriterHooks { trace: super::trace_memory, release: super::release_freed });
            // The blob table at its bound once (see [`Plan::max_targets`]).
            w.reserve_blobs(plan.len() * plan.max_targets());
        }
        Ok(Assembler {
            plan,
            writer,
            produced: Mutex::new(Log::new(plan.assembles())),
            emitted: Mutex::default(),
            error: Mutex::default(),
            fingerprint: std::sync::OnceLock::new(),
        })
    }

    /// A key's artifacts, with the blake3 of each: written now, then only their blob
    /// numbers kept.
    pub fn add(&self, key: &Key, stage: Stage, c: &Compiled, hashes: &[blake3::Hash]) {
        if !self.plan.assembles() {
            return;
        }
        let mut numbers = Vec::with_capacity(hashes.len());
        for ((t, bytes), hash) in c.artifacts.iter().zip(hashes) {
            match self.write_artifact(*t, stage, bytes, *hash) {
                Ok(n) => numbers.push((*t, n)),
                Err(e) => {
                    // The build fails at `finish`; the key need not be kept.
                    self.error.lock().expect("no panics while locked").get_or_insert(e);
                    return;
                }
            }
        }
        self.record(key, &c.reflection, numbers, hashes);
    }

    /// Whether artifacts may be added by reference to the archive being replaced
    /// ([`Assembler::add_held`]): only into an archive, without loose files (they need the
    /// bytes).
    pub fn by_reference(&self) -> bool {
        self.plan.assembles() && self.writer.is_some() && self.plan.options.emit_dir.is_none()
    }

    /// Whether the archive being replaced holds the blob whose blake3 is `hash`.
    pub fn holds(&self, hash: &blake3::Hash) -> bool {
        self.writer.as_ref().is_some_and(|w| w.holds(hash))
    }

    /// A key's artifacts by reference to the archive being replaced (a cache entry read
    /// without them): false, adding nothing of the key, when that archive lacks one (the
    /// caller then reads the whole entry and calls [`Assembler::add`]).
    pub fn add_held(&self, key: &Key, h: &Held) -> bool {
        let Some(w) = self.writer.as_ref().filter(|_| self.by_reference()) else { return false };
        let mut numbers = Vec::with_capacity(h.artifacts.len());
        for &(t, len, hash) in &h.artifacts {
            match w.add_blob_reference(hash, len) {
                Ok(Some(n)) => numbers.push((t, n)),
                Ok(None) => return false,
                Err(e) => {
                    self.error.lock().expect("no panics while locked").get_or_insert(format!("error: {e}"));
                    return true;
                }
            }
        }
        let hashes: Vec<blake3::Hash> = h.artifacts.iter().map(|a| a.2).collect();
        self.record(key, &h.reflection, numbers, &hashes);
        true
    }

    /// Keeps a key's reflection and blob numbers (each artifact's blake3 `hashes`).
    fn record(&self, key: &Key, reflection: &Reflection, mut numbers: Vec<(Target, u32)>, hashes: &[blake3::Hash]) {
        let mut p = self.produced.lock().expect("no panics while locked");
        let reflection = match p.reflection_index.get(reflection) {
            Some(&r) => r,
            None => {
                let r = Arc::new(reflection.clone());
                let n = p.reflections.len() as u32;
                p.reflections.push(r.clone());
                p.reflection_index.insert(r, n);
                n
            }
        };
        if self.plan.options.emit_dir.is_some() {
            // Without an archive, that number is the artifact's hash's.
            for (a, hash) in numbers.iter_mut().zip(hashes) {
                if self.writer.is_none() {
                    a.1 = p.hashes.len() as u32;
                }
                p.hashes.push(*hash);
            }
        }
        if let Err(e) = p.write(key, reflection, &numbers) {
            drop(p);
            let e = format!("error: cannot write a temporary file of the build: {e}");
            self.error.lock().expect("no panics while locked").get_or_insert(e);
        }
    }

    /// At most `more` distinct artifacts come beyond those added so far (a close bound: the
    /// archive writer's table that finds them is made at that size rather than grown).
    pub fn expect_blobs(&self, more: usize) {
        if let Some(Err(e)) = self.writer.as_ref().map(|w| w.expect_blobs(more)) {
            self.error.lock().expect("no panics while locked").get_or_insert(format!("error: {e}"));
        }
    }

    /// No more artifacts come: the archive writer lets go of the table that finds its blobs
    /// by content (it grows with the set).
    pub fn seal_blobs(&mut self) {
        if let Some(w) = &mut self.writer {
            w.seal_blobs();
        }
    }

    /// Writes an artifact to the archive's spool and the loose files; its blob number in the
    /// archive (0 without one).
    fn write_artifact(&self, t: Target, stage: Stage, bytes: &[u8], hash: blake3::Hash) -> Result<u32, String> {
        let mut number = 0;
        if let Some(w) = &self.writer {
            number = w.add_blob_numbered(bytes, hash).map_err(|e| format!("error: {e}"))?;
        }
        if let Some(dir) = &self.plan.options.emit_dir {
            if self.emitted.lock().expect("no panics while locked").contains_key(&hash) {
                return Ok(number);
            }
            let f = format!("{}.{}", &hash.to_hex()[..32], t.extension(stage));
            archive::write_atomic_unsynced(&dir.join(&f), bytes)
                .map_err(|e| format!("error: cannot write {}: {e}", dir.join(&f).display()))?;
            self.emitted.lock().expect("no panics while locked").insert(hash, f);
        }
        Ok(number)
    }

    /// Everything the archive's content depends on: each kept permutation's name, shader
    /// record and key, in order, and the versions. Computed once per build (a warm build
    /// asks for it two or three times).
    fn fingerprint(&self, pre: &Preprocessed) -> blake3::Hash {
        // (A key that cannot be read back gives a fingerprint no build has: the archive is
        // not taken as up to date, and the build fails where it reads the keys again.)
        *self.fingerprint.get_or_init(|| {
            let mut keys = pre.keys();
            fingerprint(self.plan, |i| keys.of(i).unwrap_or(Some(Key([0xFF; 32]))))
        })
    }

    /// The archive's path when this build writes one whole archive there (an output, no
    /// `--emit-dir`, nothing failed): where an existing or remote archive may stand for it.
    fn whole_archive_output(&self, failed: bool) -> Option<&'p std::path::Path> {
        let options = self.plan.options;
        options.output.as_deref().filter(|_| options.emit_dir.is_none() && !failed)
    }

    /// The artifact counts of the archive when it is already the output of this build:
    /// every permutation has the key it had when the archive was written, and the archive
    /// is the file that build wrote (like cargo's freshness check). Only with a cache (the
    /// stamp lives there), nothing failed, and no `--emit-dir`. The keys looked for are the
    /// rows' (each distinct key is a row's), so that grouping need not have run.
    pub fn up_to_date(&self, store: &Store, pre: &Preprocessed, failed: bool) -> Option<(usize, usize)> {
        let out = self.whole_archive_output(failed)?;
        let mut keys = pre.keys();
        // (The keys end at one that cannot be read back: then they are not the archive's.)
        let mut rows = (0..pre.row_count()).map_while(|r| keys.row(r).ok());
        store.fresh_archive(out, &|| self.fingerprint(pre), &mut rows)
    }

    /// The artifact counts of the archive when the remote cache holds this build's archive
    /// and every key's entry: the entries are copied into the local cache and the archive
    /// written (see [`Store::archive_from_remote`]). Same conditions as [`Self::up_to_date`].
    pub fn copied_from_remote(
        &self,
        store: &Store,
        pre: &Preprocessed,
        keys: &Keys<'_>,
        failed: bool,
    ) -> Option<(usize, usize)> {
        let out = self.whole_archive_output(failed)?;
        // The keys are the rows' here (never read from a file).
        store.archive_from_remote(out, &|| self.fingerprint(pre), &|| Box::new(keys.iter().map_while(Result::ok)))
    }

    /// Adds every permutation (the manifest) and writes the archive, the loose files'
    /// index, and the archive's stamp.
    /// `pre` gives each kept permutation's key; it is dropped once the manifest has them,
    /// before the archive is written.
    pub fn finish(self, pre: Preprocessed, store: &Store) -> Result<Written, Error> {
        let options = self.plan.options;
        let mut written = Written { artifacts: 0, permutation_artifacts: 0, reused_blobs: 0, archive: None };
        if !self.plan.assembles() {
            return Ok(written);
        }
        if let Some(e) = self.error.lock().expect("no panics while locked").take() {
            return Err(Error::Io(e));
        }
        let fingerprint = self.fingerprint(&pre);
        let produced = self.produced.into_inner().expect("no panics while locked").load().map_err(read_back)?;
        super::trace_memory("keys read back");
        let plan = self.plan;
        let mut produced = produced.by_permutation(plan, pre).map_err(read_back)?;
        // Not kept resident under the manifest's arenas.
        super::release_freed();
        super::trace_memory("keys by permutation");
        let writer = self.writer;
        let emitted = self.emitted.into_inner().expect("no panics while locked");
        let mut index: BTreeMap<String, BTreeMap<&'static str, &str>> = BTreeMap::new();
        let mut shaders: HashMap<(&str, &str), ShaderRecord> = HashMap::new();
        let mut distinct: HashSet<blake3::Hash> = HashSet::new();
        // Into an archive alone, the keys' artifacts go to the writer once, each permutation
        // naming its key's (not a copy per permutation beside the keys' own).
        let ranged = options.emit_dir.is_none();
        // Into an archive alone, the permutations go in the archive's order, which the
        // writer then need not hold to sort (see `StreamingWriter::begin_sorted`).
        let order = (writer.is_some() && ranged).then(|| name_order(plan, |i| produced.get(i).is_some())).flatten();
        // The ordering's tables (each run's values and keys) are not kept under the writer's.
        super::release_freed();
        super::trace_memory("permutations ordered");
        let naming = match &writer {
            Some(w) => produced.ready_writer(plan, w, ranged, order.as_ref().map(Vec::len))?,
            None => {
                produced.load_artifacts().map_err(read_back)?;
                Naming::Numbered
            }
        };
        let each: Box<dyn Iterator<Item = usize>> = match order {
            Some(order) => Box::new(order.into_iter().map(|i| i as usize)),
            None => Box::new(0..plan.len()),
        };
        for i in each {
            let Some(entry) = produced.get(i) else { continue };
            let (shader_of, level) = plan.shader_level(i);
            if options.emit_dir.is_some() {
                // With loose files, each artifact's hash is kept beside it.
                let hashes = &produced.hashes[entry.first as usize..][..entry.count() as usize];
                let files = index.entry(plan.name(i)).or_default();
                for ((t, _), hash) in produced.artifacts(entry).iter().zip(hashes) {
                    files.insert(t.name(), emitted[hash].as_str());
                }
                if writer.is_none() {
                    distinct.extend(hashes);
                }
            }
            written.permutation_artifacts += entry.count() as usize;
            let Some(w) = &writer else { continue };
            let shader =
                shaders.entry((&shader_of.name, &level.name)).or_insert_with(|| shader_record(shader_of, level));
            produced.add(w, plan, i, shader, naming)?;
        }
        drop(produced);
        super::release_freed();
        super::trace_memory("manifest added");
        written.artifacts = distinct.len();
        if let Some(dir) = &options.emit_dir {
            write_index(dir, &index)?;
        }
        if let (Some(out), Some(w)) = (&options.output, writer) {
            let summary = w.finish_unsynced().map_err(archive_error)?;
            written.artifacts = summary.blobs;
            written.reused_blobs = summary.reused_blobs;
            written.archive = Some(out.clone());
            if options.emit_dir.is_none() {
                store.stamp_archive(out, &fingerprint, (written.artifacts, written.permutation_artifacts));
            }
        }
        Ok(written)
    }
}

/// The kept permutations (those `kept` says) in the order of their canonical names, as the
/// archive holds them; `None` where that order is not the one [`sort_run`] can give (names
/// whose values' texts run into each other), and the writer sorts them itself.
/// Each (shader, level) run's names share its `name@level{`: runs are ordered by that, and
/// then must follow each other (checked at each run's first name).
fn name_order(plan: &Plan<'_>, kept: impl Fn(usize) -> bool) -> Option<Vec<u32>> {
    let mut runs: Vec<_> = plan.runs().map(|(s, l, r)| (format!("{}@{}{{", s.name, l.name), s, r)).collect();
    runs.sort_by(|a, b| a.0.cmp(&b.0));
    let mut order = Vec::with_capacity((0..plan.len()).filter(|&i| kept(i)).count());
    let mut last: Option<String> = None;
    for (_, shader, range) in runs {
        let start = order.len();
        sort_run(plan, shader, range, &kept, &mut order)?;
        let Some(&first) = order.get(start) else { continue };
        let name = plan.name(first as usize);
        if last.as_ref().is_some_and(|l| *l >= name) {
            return None;
        }
        last = Some(plan.name(*order.last().expect("a permutation was added") as usize));
    }
    Some(order)
}

/// Appends the kept permutations of one run (`range`, of `shader`) to `order` in the order of
/// their names, which differ only in their values: each value's text in the name (with
/// the `,` or `}` that follows it) ranked among the run's values of its dimension, and the
/// ranks compared one dimension after another. `None` where a text is a prefix of
/// another's (then the next dimension's text decides, not the rank), two values have one
/// text, or the ranks do not fit in one number.
fn sort_run(
    plan: &Plan<'_>,
    shader: &crate::permute::Shader,
    range: std::ops::Range<usize>,
    kept: &impl Fn(usize) -> bool,
    order: &mut Vec<u32>,
) -> Option<()> {
    let dims = &shader.dimensions;
    let mut seen: Vec<HashSet<i64>> = vec![HashSet::new(); dims.len()];
    for i in range.clone().filter(|&i| kept(i)) {
        for (d, v) in seen.iter_mut().zip(plan.values(i)) {
            d.insert(v);
        }
    }
    let mut ranks: Vec<HashMap<i64, u64>> = Vec::with_capacity(dims.len());
    let mut radix: Vec<u64> = Vec::with_capacity(dims.len());
    for (k, (d, values)) in dims.iter().zip(seen).enumerate() {
        let end = if k + 1 == dims.len() { '}' } else { ',' };
        let mut texts: Vec<(String, i64)> = values.into_iter().map(|v| (format!("{}{end}", d.display(v)), v)).collect();
        texts.sort_unstable();
        if texts.windows(2).any(|w| w[1].0.starts_with(&w[0].0)) {
            return None;
        }
        radix.push(texts.len() as u64);
        ranks.push(texts.into_iter().enumerate().map(|(r, (_, v))| (v, r as u64)).collect());
    }
    // Each dimension's weight: the product of the later dimensions' counts.
    let mut weights = vec![1u64; dims.len()];
    for k in (0..dims.len().saturating_sub(1)).rev() {
        weights[k] = weights[k + 1].checked_mul(radix[k + 1])?;
    }
    let keys = weights.first().zip(radix.first()).map_or(Some(1), |(w, r)| w.checked_mul(*r))?;
    let key = |i: usize| -> u64 { plan.values(i).iter().zip(&ranks).zip(&weights).map(|((v, r), w)| r[v] * w).sum() };
    let start = order.len();
    order.extend(range.clone().filter(|&i| kept(i)).map(|i| i as u32));
    // Each permutation's key by its place in the run, as narrow as the keys allow: the
    // run's own table, beside the order of the whole set.
    match u32::try_from(keys) {
        Ok(_) => sort_by_keys(&mut order[start..], range.start, |i| key(i) as u32),
        Err(_) => sort_by_keys(&mut order[start..], range.start, key),
    }
}

/// Sorts `run` (permutation numbers from `first` on) by `key`, made once for each: `None`
/// where two have one key.
fn sort_by_keys<K: Ord + Copy + Default>(run: &mut [u32], first: usize, key: impl Fn(usize) -> K) -> Option<()> {
    let Some(&last) = run.last() else { return Some(()) };
    let mut keys = vec![K::default(); last as usize + 1 - first];
    for &i in run.iter() {
        keys[i as usize - first] = key(i as usize);
    }
    run.sort_unstable_by_key(|&i| keys[i as usize - first]);
    match run.windows(2).any(|w| keys[w[0] as usize - first] == keys[w[1] as usize - first]) {
        true => None,
        false => Some(()),
    }
}

/// The manifest's record of a shader at a level.
fn shader_record(shader: &crate::permute::Shader, level: &crate::permute::Level) -> ShaderRecord {
    ShaderRecord {
        name: shader.name.clone(),
        level: level.name.clone(),
        entry: shader.entry.clone(),
        stage: shader.stage,
        dimensions: shader
            .dimensions
            .iter()
            .map(|d| DimensionRecord { name: d.name.clone(), labels: d.labels.clone() })
            .collect(),
    }
}

/// `--emit-dir`'s `index.json`: each permutation's loose files by target.
fn write_index(dir: &std::path::Path, index: &BTreeMap<String, BTreeMap<&'static str, &str>>) -> Result<(), Error> {
    let json = serde_json::to_vec_pretty(index).expect("index serializes");
    let path = dir.join("index.json");
    archive::write_atomic_unsynced(&path, &json)
        .map_err(|e| Error::Io(format!("error: cannot write {}: {e}", path.display())))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Keys read back are found by their prefix, and those whose prefix another key shares
    /// (or that were produced twice) by the whole key, the later record winning; through
    /// the temporary file and in memory alike.
    #[test]
    fn produced_keys_are_found_by_prefix_and_whole() {
        for spill in [true, false] {
            let mut log = Log::new(spill);
            let key = |first: u8, last: u8| {
                let mut k = [first; 32];
                k[31] = last;
                Key(k)
            };
            let (a, b, c) = (key(1, 0), key(1, 1), key(2, 0));
            log.write(&a, 0, &[(Target::Spirv, 10)]).unwrap();
            log.write(&c, 1, &[(Target::Spirv, 11), (Target::Glsl, 12)]).unwrap();
            log.write(&b, 2, &[]).unwrap();
            log.write(&a, 3, &[(Target::Glsl, 13)]).unwrap();
            let mut p = log.load().unwrap();
            assert_eq!((p.slots.len(), p.shared.len()), (1, 2), "a and b share a prefix");
            assert!(p.position(&key(3, 0)).is_none());
            let records: Vec<u32> = [a, b, c].iter().map(|k| p.position(k).unwrap()).collect();
            let entries = read_entries(p.input.as_mut(), p.keys).unwrap();
            let entry = |n: u32| {
                let e = entries[n as usize];
                (e.reflection(), e.first, e.count())
            };
            assert_eq!(entry(records[0]), (3, 3, 1), "the later record of a key produced twice");
            assert_eq!(entry(records[1]), (2, 3, 0));
            assert_eq!(entry(records[2]), (1, 1, 2));
            let artifacts = read_artifacts(p.input.as_mut(), p.keys, p.artifacts).unwrap();
            assert_eq!(artifacts.numbers, [10, 11, 12, 13]);
            assert_eq!(artifacts.targets, [Target::Spirv, Target::Spirv, Target::Glsl, Target::Glsl]);
            // Each record's artifacts read alone, where a sorted manifest reads them.
            let (keys, artifacts_in_all) = (p.keys, p.artifacts);
            let mut by = ByPermutation {
                of: Vec::new(),
                entries,
                artifacts: Artifacts::default(),
                artifacts_in_all,
                records: p.input,
                hashes: Vec::new(),
                reflections: Vec::new(),
            };
            let mut alone = Vec::new();
            for record in 0..keys {
                let e = by.entries[record];
                alone.extend(by.read_artifacts(record, &e).unwrap());
            }
            by.load_artifacts().unwrap();
            let loaded: Vec<_> =
                by.artifacts.targets.iter().copied().zip(by.artifacts.numbers.iter().copied()).collect();
            assert_eq!(alone, loaded);
        }
    }

    /// The fingerprint hashes the same bytes as the one line per permutation it was defined
    /// by (archives stored under it by earlier builds are still found).
    /// The kept permutations in name order are those of a sort of their names (numbers past 9,
    /// whose text is not their order, labels, shaders whose names are prefixes of others',
    /// a shader without dimensions).
    #[test]
    fn permutations_are_ordered_by_name() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("A.usf"), "fn a() {}\n").unwrap();
        let shader = |name: &str, dims: &str| {
            format!("[[shader]]\nname = \"{name}\"\nsource = \"A.usf\"\nentry = \"main\"\nstage = \"fragment\"\nlevels = [\"sm5\", \"es3\"]\n{dims}\n")
        };
        let head =
            "[compiler]\ninclude = [\".\"]\n[levels.sm5]\ntargets = [\"spirv\"]\n[levels.es3]\ntargets = [\"glsl\"]\n";
        let plan_of = |text: &str| {
            let config = crate::permute::load_str(text, &dir.path().join("permutations.toml")).unwrap();
            let options = super::super::Options::default();
            let plan = Plan::new(&config, &options).unwrap();
            let order = name_order(&plan, |i| i % 5 != 2);
            let mut want: Vec<(String, u32)> =
                (0..plan.len()).filter(|i| i % 5 != 2).map(|i| (plan.name(i), i as u32)).collect();
            want.sort();
            (order, want.into_iter().map(|w| w.1).collect::<Vec<u32>>())
        };
        let dims =
            "dimensions = { X = { range = [0, 12] }, Y = \"bool\", Q = { enum = [\"LOW\", \"HIGH\", \"MID\"] } }";
        let text = format!("{head}{}{}{}", shader("Ab", dims), shader("A", dims), shader("B", ""));
        let (order, want) = plan_of(&text);
        assert_eq!(order, Some(want));
    }

    #[test]
    fn the_fingerprint_is_one_line_per_kept_permutation() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("A.usf"), "fn a() {}\n").unwrap();
        let text = r#"
[compiler]
include = ["."]
[levels.sm5]
targets = ["spirv"]
[levels.es3]
targets = ["glsl"]
[[shader]]
name = "A"
source = "A.usf"
entry = "main"
stage = "fragment"
levels = ["sm5", "es3"]
dimensions = { X = { range = [0, 4] }, Y = "bool", Q = { enum = ["LOW", "HIGH"] } }
skip = [ { when = "X == 2 && Y == 1", why = "t" } ]
[[shader]]
name = "B"
source = "A.usf"
entry = "vs"
stage = "vertex"
levels = ["es3"]
"#;
        let config = crate::permute::load_str(text, &dir.path().join("permutations.toml")).unwrap();
        let options = super::super::Options::default();
        let plan = Plan::new(&config, &options).unwrap();
        assert!(plan.len() > 20);
        let keys: Vec<Option<Key>> = (0..plan.len()).map(|i| (i % 7 != 3).then_some(Key([i as u8; 32]))).collect();
        let mut h = blake3::Hasher::new();
        h.update(b"kiln build fingerprint v1\0");
        h.update(crate::VERSION.as_bytes());
        h.update(b"\0");
        h.update(compile::NAGA_VERSION.as_bytes());
        h.update(format!("\0archive format {}", archive::FORMAT_VERSION).as_bytes());
        for (i, key) in keys.iter().enumerate() {
            let Some(key) = key else { continue };
            let (shader, _) = plan.shader_level(i);
            let dims: Vec<(&str, &[String])> =
                shader.dimensions.iter().map(|d| (d.name.as_str(), d.labels.as_slice())).collect();
            let line =
                format!("\0{}\0{}\0{}\0{:?}\0{:?}\0", plan.name(i), shader.entry, shader.stage, plan.values(i), dims);
            h.update(line.as_bytes());
            h.update(&key.0);
        }
        assert_eq!(fingerprint(&plan, |i| keys[i]), h.finalize());
    }
}
