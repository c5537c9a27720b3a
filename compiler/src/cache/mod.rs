//! The content-addressed artifact cache.
//!
//! Takes a [`Key`] (blake3 of everything that decides a compile's output: the token hash
//! of the preprocessed text, entry point, stage, level name, limits and targets, Kiln's and
//! naga's versions, a fingerprint of Kiln's own sources) and the [`Compiled`] outputs of
//! that key; gives them back on a later build. It also keeps, per permutation, a
//! preprocessing [`Record`] (so unchanged permutations skip the preprocessor) and, per
//! archive, a stamp (so an up-to-date archive is not rewritten).
//!
//! Entries are compressed (`codec.rs`: zstd, with a dictionary per kind of entry kept in the
//! folder once a build wrote enough to train one), as ccache's and sccache's are; entries of
//! the older uncompressed format are still read.
//!
//! Entries are stored in packs, like git's pack files: [`Cache::put_pack`] writes every
//! entry a build compiled into one `.kcp` file, an index of keys followed by the entries.
//! One file per build instead of one per key: creating hundreds of small files costs more
//! kernel time than naga takes to compile some of them. Guarantees: a pack is written to a
//! temporary file in the cache folder and renamed into place, so readers (other processes
//! included) see a whole pack or none, and two builds sharing a cache both succeed (each
//! writes its own pack; a key held by two packs is read from the newest that is intact);
//! every entry carries a checksum of its content and the index one of its own, so a
//! corrupted entry is reported ([`Lookup::Corrupt`]) and recompiled, never trusted; a hit
//! refreshes its pack's modification time, which `gc` uses to evict the least recently
//! used packs first.
//!
//! A [`remote::Remote`] may be layered under the local folder ([`Cache::with_remote`]), as
//! Unreal layers its shared DDC under the local one: a lookup tries the local packs, then
//! the remote; a remote value carries the same entry encoding behind one checksum of the
//! whole value, which is checked before the entry is filled into the local cache (and the
//! entry's own checksum when it is used); every entry a build stores goes to the local cache
//! and, in read-write mode, to the remote. [`Cache::fill_from_remote`] copies many entries at
//! once (batched round trips), streaming them into a pack on disk as they arrive. A remote
//! that fails is one warning and the build goes on with the local cache only.

use std::collections::{HashMap, HashSet};
use std::fs;
use std::io;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, RwLock};
use std::time::SystemTime;

use rayon::prelude::*;

use crate::archive::{Reflection, Stage, Target};
use crate::compile::{Compiled, Limits};

mod bundle;
mod codec;
mod exchange;
mod fault;
mod files;
mod fill;
mod http_batch;
mod local;
mod records;
pub(crate) mod remote;

pub use remote::Remote;

/// How the entries of a pack are stored ([`Cache::put_pack_hashed`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Packing {
    /// Compressed with zstd (with the cache's dictionary of each kind, trained when a pack
    /// brings enough of it).
    Compressed,
    /// In zstd frames of raw blocks: the same entry format, read and checked alike, with
    /// no compression work (a build too small for compression to pay: `build::store`).
    Stored,
}

/// An entry of version 2 (uncompressed): still read; version 3 ([`codec`]) is written.
const MAGIC: &[u8; 8] = b"KILNCE\0\x02";
const PACK_MAGIC: &[u8; 8] = b"KILNCP\0\x02";
const PACK_EXTENSION: &str = "kcp";
const RECORD_MAGIC: &[u8; 8] = b"KILNPP\0\x01";
/// A remote cache value ([`remote_value_of`]); its header: magic, xxh3-128 of its key and entry.
/// Version 4 holds a compressed entry ([`codec`]) as the writer's local cache holds it: with
/// a dictionary, which the remote then holds too ([`remote_dict_key`]). Versions 3 (a
/// compressed entry without a dictionary) and 2 (an uncompressed entry) are still read.
const REMOTE_MAGIC: &[u8; 8] = b"KILNCER\x04";
const REMOTE_MAGIC_V3: &[u8; 8] = b"KILNCER\x03";
const REMOTE_MAGIC_V2: &[u8; 8] = b"KILNCER\x02";
const REMOTE_HEADER: usize = 8 + 16;
const RECORD_EXTENSION: &str = "kpp";
/// The largest records file read (far more records than a set has permutations).
const MAX_RECORDS: u64 = 1 << 30;
/// Pack header: magic, entry count (u64), blake3 of the index rows.
const PACK_HEADER: usize = 8 + 8 + 32;
/// Index row: key, offset of the entry in the pack (u64), its length (u64).
const ROW: usize = 32 + 8 + 8;
/// Remote hits of single lookups ([`Cache::get`]) are streamed into a pack of this many
/// entries at most (written whole at the next [`Cache::put_pack`] in any case).
const FILL_ROWS: usize = 4096;
/// The cache folder's tag (<https://bford.info/cachedir/>), written by [`Cache::open`].
const TAG_NAME: &str = "CACHEDIR.TAG";
const TAG: &str = "Signature: 8a477f597d28d172789f06886806bc55\n\
# This file is a cache directory tag created by kiln (the shader compiler's artifact cache).\n\
# For information about cache directory tags see https://bford.info/cachedir/\n";

/// Preprocessing records of one configuration, by the hex key of each permutation's
/// inputs (see `build`): a later build skips the preprocessor for every permutation whose
/// record still matches (like ccache's direct mode).
pub type Records = std::collections::BTreeMap<String, Record>;

/// What preprocessing one permutation gave: the files read with the blake3 of their
/// contents, the hashes, the compile key, and the rendered warnings.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Record {
    pub key: String,
    pub token_hash: String,
    pub text_hash: String,
    /// (absolute path, blake3 of the text the preprocessor read).
    pub files: Vec<(PathBuf, String)>,
    /// Include candidates that were missing: the record holds only while they still are.
    #[serde(default)]
    pub absent: Vec<PathBuf>,
    pub warnings: Vec<String>,
}

/// The cache key of one distinct compile. Ordered as its bytes are.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Key(pub [u8; 32]);

impl Ord for Key {
    /// The bytes' order, as four big-endian words compared inline: sorted key tables are
    /// searched many times a permutation (the derived order called `memcmp` each time, a
    /// thirtieth of a warm-remote build's CPU).
    fn cmp(&self, other: &Key) -> std::cmp::Ordering {
        let word = |k: &Key, i: usize| u64::from_be_bytes(k.0[i * 8..i * 8 + 8].try_into().expect("8 bytes"));
        (0..4).map(|i| word(self, i).cmp(&word(other, i))).find(|o| o.is_ne()).unwrap_or(std::cmp::Ordering::Equal)
    }
}

impl PartialOrd for Key {
    fn partial_cmp(&self, other: &Key) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}

impl Key {
    /// blake3 over every input that decides the outputs, each length-prefixed.
    pub fn new(
        token_hash: &blake3::Hash,
        entry: &str,
        stage: Stage,
        level: &str,
        limits: &Limits,
        targets: &[Target],
    ) -> Key {
        let mut h = blake3::Hasher::new();
        let mut field = |bytes: &[u8]| {
            h.update(&(bytes.len() as u64).to_le_bytes());
            h.update(bytes);
        };
        field(b"kiln cache key v2");
        field(&shared_digest(limits));
        field(token_hash.as_bytes());
        field(entry.as_bytes());
        field(stage.name().as_bytes());
        field(level.as_bytes());
        for t in targets {
            field(t.name().as_bytes());
        }
        Key(*h.finalize().as_bytes())
    }

    pub fn to_hex(&self) -> String {
        blake3::Hash::from_bytes(self.0).to_hex().to_string()
    }
}

/// blake3 of what a key shares with every key of the same `limits`: the limits (as their
/// `Debug` text) and the versions of Kiln, of its sources and of naga. Kept per thread for
/// the last limits seen (a build has a few): formatting the limits cost more than the rest
/// of a key, and a build makes two keys per permutation.
fn shared_digest(limits: &Limits) -> [u8; 32] {
    thread_local! {
        static LAST: std::cell::RefCell<Option<(Limits, [u8; 32])>> = const { std::cell::RefCell::new(None) };
    }
    LAST.with(|last| {
        let mut last = last.borrow_mut();
        if let Some((_, digest)) = last.as_ref().filter(|(l, _)| l == limits) {
            return *digest;
        }
        let mut h = blake3::Hasher::new();
        for bytes in [
            format!("{limits:?}").as_bytes(),
            crate::VERSION.as_bytes(),
            env!("KILN_SOURCE_HASH").as_bytes(),
            crate::compile::NAGA_VERSION.as_bytes(),
        ] {
            h.update(&(bytes.len() as u64).to_le_bytes());
            h.update(bytes);
        }
        let digest = *h.finalize().as_bytes();
        *last = Some((limits.clone(), digest));
        digest
    })
}

impl std::fmt::Display for Key {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.to_hex())
    }
}

/// The answer to [`Cache::get`].
#[derive(Debug)]
pub enum Lookup {
    /// The entry, with the blake3 of each artifact (computed or read to check the entry, so
    /// that the caller need not hash the artifacts again).
    Hit(Compiled, Vec<blake3::Hash>),
    /// The entry, whose artifacts the caller said it holds ([`Cache::get_unless_held`]):
    /// its reflection and each artifact's target, length and blake3, its artifacts not
    /// decompressed.
    Held(Held),
    Miss,
    /// Every copy of the entry fails its checksum or cannot be decoded: the reason. The
    /// caller recompiles; the new copy, in a newer pack, is the one read from then on.
    Corrupt(String),
}

/// An entry without its artifacts' bytes ([`Lookup::Held`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Held {
    pub reflection: Reflection,
    /// Each artifact's target, length and blake3.
    pub artifacts: Vec<(Target, u64, blake3::Hash)>,
}

/// Counts of [`Cache::stats`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Stats {
    /// Distinct keys held by the packs.
    pub entries: u64,
    /// Pack files (`.kcp`).
    pub packs: u64,
    /// Sets of preprocessing records (`.kpp`, one per configuration and options).
    pub records: u64,
    /// Bytes of packs, records and dictionaries.
    pub bytes: u64,
    /// Bytes the distinct entries would take uncompressed (as version 2 entries).
    pub raw: u64,
    /// Bytes the distinct entries take in their packs (their newest copy each).
    pub stored: u64,
    /// Compression dictionaries (`.kcd`) and their bytes.
    pub dictionaries: u64,
    pub dictionary_bytes: u64,
    /// Temporary files left by interrupted writes (removed by `gc` and `clear`).
    pub temporaries: u64,
}

/// What [`Cache::gc`] did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct GcReport {
    /// Keys no longer held by any pack.
    pub removed: u64,
    /// Packs removed.
    pub removed_packs: u64,
    /// Preprocessing records removed.
    pub removed_records: u64,
    pub freed: u64,
    /// Keys still held.
    pub kept: u64,
    pub kept_bytes: u64,
}

#[derive(Debug, thiserror::Error)]
#[error("cache {path}: {source}")]
pub struct Error {
    pub path: PathBuf,
    pub source: io::Error,
}

/// One pack file, open for positioned reads (not mapped: a file truncated by someone else
/// must give an error, not a SIGBUS).
#[derive(Debug)]
struct Pack {
    path: PathBuf,
    file: fs::File,
    modified: SystemTime,
    /// The file's length when opened (no row may point past it).
    size: u64,
    /// The blake3 of the index rows, as the header says.
    rows_hash: [u8; 32],
    touched: AtomicBool,
}

impl Pack {
    /// Refreshes the time gc sorts by, once per process; failing to is harmless.
    fn touch(&self) {
        if !self.touched.swap(true, Ordering::Relaxed) {
            let _ = self.file.set_modified(SystemTime::now());
        }
    }
}

/// Where one copy of an entry lies.
#[derive(Clone, Debug)]
struct Location {
    pack: Arc<Pack>,
    offset: u64,
    len: u64,
}

/// One key of the in-memory index, in 8 bytes: the number of its row among all indexed
/// packs' rows in the low [`Index::row_bits`] bits, and above them as many of the key's
/// first bits as fit. The rest of the row (the whole key, where the entry lies) is read
/// from the pack on lookup and the whole key compared there, so a shorter prefix costs at
/// most a read more, never a wrong entry; the index holds a small fixed share of each key
/// rather than the key and its location.
type Slot = u64;

/// The slot of `key`'s row `row`, of `row_bits` bits (`row` fits in them).
fn slot(key: &Key, row: u32, row_bits: u32) -> Slot {
    let prefix = u64::from_be_bytes(key.0[..8].try_into().expect("8 of 32 bytes"));
    (prefix >> row_bits << row_bits) | u64::from(row)
}

/// The bits that number `rows` rows (at least one).
fn row_bits(rows: u64) -> u32 {
    (u64::BITS - rows.saturating_sub(1).leading_zeros()).max(1)
}

/// Index rows read from a pack at a time (its checksum is computed as they stream).
const INDEX_CHUNK_ROWS: usize = 8192;

/// Every pack's index, read once per [`Cache`] (and extended by its own writes, unless
/// [`Cache::without_indexing_puts`]: then by its remote fills only).
#[derive(Debug, Default)]
struct Index {
    /// The indexed packs, by the number of their first row (rows are numbered in the order
    /// packs were added).
    packs: Vec<(u32, Arc<Pack>)>,
    /// The number the next pack's first row gets.
    next_row: u32,
    /// The bits of a slot that number its row (see [`Slot`]): enough for every row
    /// indexed, widened when a pack added later needs more.
    row_bits: u32,
    /// Sorted runs of slots, the largest first: a pack added later is a run of its own,
    /// merged into the one before it once that is at most twice its size (each slot is then
    /// re-sorted a logarithmic number of times however many packs a build adds).
    runs: Vec<Vec<Slot>>,
    /// Packs whose index was damaged: (path, why, whether it was removed: not when Kiln did
    /// not write it). Their entries are misses.
    damaged: Vec<(PathBuf, String, bool)>,
}

impl Index {
    /// Reads the index of the pack at `path` into `slots` (unsorted): `Ok(false)` when the
    /// file is gone (or there are too many rows to number), `Err(why)` when it is not a
    /// whole pack of this Kiln (then nothing of it is kept).
    fn read_pack(&mut self, path: &Path, slots: &mut Vec<Slot>) -> Result<bool, String> {
        let Some((pack, count)) = open_pack_header(path)? else { return Ok(false) };
        let Some(next) = u32::try_from(count).ok().and_then(|c| self.next_row.checked_add(c)) else {
            return Ok(false);
        };
        self.widen(row_bits(u64::from(next)), slots);
        let kept = slots.len();
        let mut hasher = blake3::Hasher::new();
        let mut chunk = vec![0u8; INDEX_CHUNK_ROWS.min(count as usize) * ROW];
        let mut row = 0usize;
        while row < count as usize {
            let n = INDEX_CHUNK_ROWS.min(count as usize - row);
            let bytes = &mut chunk[..n * ROW];
            if pack.file.read_exact_at(bytes, (PACK_HEADER + row * ROW) as u64).is_err() {
                slots.truncate(kept);
                return Err("truncated index".into());
            }
            hasher.update(bytes);
            for (i, r) in bytes.chunks_exact(ROW).enumerate() {
                let key = Key(r[..32].try_into().expect("32 bytes"));
                slots.push(slot(&key, self.next_row + (row + i) as u32, self.row_bits));
            }
            row += n;
        }
        if hasher.finalize().as_bytes() != &pack.rows_hash {
            slots.truncate(kept);
            return Err("index checksum mismatch".into());
        }
        self.packs.push((self.next_row, Arc::new(pack)));
        self.next_row = next;
        Ok(true)
    }

    /// Makes the slots' row numbers `bits` bits wide if they are narrower, in `slots` (being
    /// read) and in every run (sorted again: a shorter prefix may tie where rows were not
    /// in order). Only a pack added after the index was read can need it.
    fn widen(&mut self, bits: u32, slots: &mut [Slot]) {
        if bits <= self.row_bits {
            return;
        }
        let (old, mask) = (self.row_bits, (1u64 << self.row_bits) - 1);
        let rewrite = |s: &mut Slot| *s = ((*s & !mask) >> bits << bits) | (*s & mask);
        slots.iter_mut().for_each(rewrite);
        for run in &mut self.runs {
            run.iter_mut().for_each(rewrite);
            run.sort_unstable();
        }
        debug_assert!(old < bits);
        self.row_bits = bits;
    }

    /// Reads the index of the pack at `path` and adds it as the newest run; a pack that is
    /// gone or damaged is not added (the caller wrote it whole, so it was damaged since).
    fn add(&mut self, path: &Path) {
        let mut run = Vec::new();
        if !matches!(self.read_pack(path, &mut run), Ok(true)) {
            return;
        }
        run.sort_unstable();
        self.runs.push(run);
        while let [.., before, last] = &self.runs[..] {
            if before.len() > 2 * last.len() {
                break;
            }
            let last = self.runs.pop().expect("two runs");
            let before = self.runs.last_mut().expect("two runs");
            before.extend_from_slice(&last);
            before.sort_unstable();
        }
    }

    /// Where the row numbered `row` says the entry of `key` lies, when it is the row of
    /// `key` (the slot holds only the key's first bytes) and within its pack.
    fn location(&self, row: u32, key: &Key) -> Option<Location> {
        let at = self.packs.partition_point(|(first, _)| *first <= row).checked_sub(1)?;
        let (first, pack) = &self.packs[at];
        let mut bytes = [0u8; ROW];
        let offset = PACK_HEADER as u64 + u64::from(row - first) * ROW as u64;
        pack.file.read_exact_at(&mut bytes, offset).ok()?;
        if bytes[..32] != key.0 {
            return None;
        }
        let word = |i: usize| u64::from_le_bytes(bytes[i..i + 8].try_into().expect("8 bytes"));
        let (offset, len) = (word(32), word(40));
        // A row changed since its checksum was read must not make a lookup allocate more
        // than the pack held (a pack truncated since still gives its entries, which then
        // read as truncated).
        (len <= pack.size).then(|| Location { pack: pack.clone(), offset, len })
    }

    /// Every copy of `key`, newest pack first (of packs as new, the one added first).
    fn copies(&self, key: &Key) -> Vec<Location> {
        let mask = (1u64 << self.row_bits) - 1;
        let wanted = slot(key, 0, self.row_bits);
        let mut rows: Vec<u32> = Vec::new();
        for run in &self.runs {
            let from = run.partition_point(|&s| s < wanted);
            rows.extend(run[from..].iter().take_while(|&&s| s & !mask == wanted).map(|&s| (s & mask) as u32));
        }
        rows.sort_unstable();
        let mut copies: Vec<Location> = rows.into_iter().filter_map(|row| self.location(row, key)).collect();
        copies.sort_by_key(|l| std::cmp::Reverse(l.pack.modified));
        copies
    }

    /// The newest copy of `key`.
    fn newest(&self, key: &Key) -> Option<Location> {
        self.copies(key).into_iter().next()
    }

    fn contains(&self, key: &Key) -> bool {
        self.newest(key).is_some()
    }
}

/// A cache folder, and the remote cache layered under it, if any.
#[derive(Clone, Debug)]
pub struct Cache {
    dir: PathBuf,
    index: Arc<RwLock<Option<Index>>>,
    remote: Option<Arc<Layer>>,
    /// The compression dictionaries of the folder ([`codec`]).
    dicts: Arc<codec::Dicts>,
    /// Whether the entries put through this `Cache` join its in-memory index (see
    /// [`Cache::without_indexing_puts`]).
    index_puts: bool,
}

/// The remote cache under a local one, and the pack its hits are being written into.
#[derive(Debug)]
struct Layer {
    remote: Remote,
    fills: Mutex<Option<fill::FillPack>>,
    /// Keys the remote did not have when asked during this build: not asked again (a build
    /// that fills in bulk, then compiles what was missing, asks once per key).
    absent: Mutex<HashSet<Key>>,
    /// The bundle of the keys of this build's fill ([`bundle`]), with what its parts were
    /// when read (`None`: not read), kept for [`Cache::put_bundle`] while a part is not
    /// known whole and this build writes.
    bundle: Mutex<Option<(bundle::Bundle, Vec<Option<bool>>)>>,
    /// The dictionaries this build stored to the remote (or found there), by id: each is
    /// stored once, before the first value that names it.
    dicts_shared: Mutex<HashSet<[u8; 16]>>,
    /// Held while a dictionary is fetched: the first entries that name it are decoded by
    /// several workers at once, and one fetch serves them all.
    dict_fetch: Mutex<()>,
}

impl Cache {
    /// Opens (creating it if needed) the cache at `dir`, marks a new or empty one as Kiln's (a
    /// `CACHEDIR.TAG` of the Cache Directory Tagging spec that names Kiln, so backup tools skip
    /// it; a folder that already holds other files is never tagged) and removes the temporary
    /// files of writers that died.
    pub fn open(dir: impl Into<PathBuf>) -> Result<Cache, Error> {
        let dir = dir.into();
        fs::create_dir_all(&dir).map_err(|source| Error { path: dir.clone(), source })?;
        let empty = fs::read_dir(&dir).is_ok_and(|mut entries| entries.next().is_none());
        if empty {
            // A read-only cache still serves hits: failing to tag it is harmless.
            let _ = crate::output::write(&dir.join(TAG_NAME), TAG.as_bytes(), false);
        }
        crate::output::remove_stale_temporaries(&dir, &Self::is_cache_file_name);
        Ok(Cache { dir, index: Arc::default(), remote: None, dicts: Arc::default(), index_puts: true })
    }

    /// The cache at `dir` if there is one, for commands that only read or remove: nothing
    /// is created or tagged (a mistyped folder stays absent). `Ok(None)` when `dir` does
    /// not exist; an error when it is not a folder.
    pub fn open_existing(dir: impl Into<PathBuf>) -> Result<Option<Cache>, Error> {
        let dir = dir.into();
        match fs::metadata(&dir) {
            Ok(m) if m.is_dir() => {
                Ok(Some(Cache { dir, index: Arc::default(), remote: None, dicts: Arc::default(), index_puts: true }))
            }
            Ok(_) => Err(Error { path: dir, source: io::Error::other("it is not a folder") }),
            Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(None),
            Err(source) => Err(Error { path: dir, source }),
        }
    }

    /// This cache, with the entries put through it left out of its in-memory index: a
    /// build never looks up a key it compiled, and the index of its own puts grows with the
    /// set at its peak. Remote hits filled into the local cache still join it
    /// (the build looks them up after a batched fill). A put key is then a miss through
    /// this `Cache` until its index is read again (after [`Cache::release_index`]).
    pub fn without_indexing_puts(mut self) -> Cache {
        self.index_puts = false;
        self
    }

    /// This cache with `remote` layered under it.
    pub fn with_remote(mut self, remote: Remote) -> Cache {
        self.remote = Some(Arc::new(Layer {
            remote,
            fills: Mutex::default(),
            absent: Mutex::default(),
            bundle: Mutex::default(),
            dicts_shared: Mutex::default(),
            dict_fetch: Mutex::default(),
        }));
        self
    }

    /// The remote cache under this one.
    pub fn remote(&self) -> Option<&Remote> {
        self.remote.as_ref().map(|l| &l.remote)
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Runs `f` on the index, reading every pack's index first if this is the first use.
    fn with_index<T>(&self, f: impl FnOnce(&Index) -> T) -> T {
        {
            let index = self.index.read().expect("no panics while locked");
            if let Some(index) = index.as_ref() {
                return f(index);
            }
        }
        let mut index = self.index.write().expect("no panics while locked");
        f(index.get_or_insert_with(|| self.read_index()))
    }

    /// Frees the in-memory index of every pack (an entry per key); the next lookup
    /// reads it again. A build calls this once it looks nothing up any more, before it writes
    /// the archive.
    pub fn release_index(&self) {
        *self.index.write().expect("no panics while locked") = None;
    }

    /// Lets go of what writing entries holds: each worker's compression context and the
    /// dictionaries with their compression tables (read again from the folder if an entry
    /// is written after all). A build calls it once its last entry is written: a cold
    /// build's contexts and tables otherwise stayed under the archive's assembly.
    pub fn release_compression(&self) {
        // Every context first: a context refers to the last dictionary it compressed with.
        rayon::broadcast(|_| codec::drop_thread_context());
        codec::drop_thread_context();
        self.dicts.reset();
    }

    fn read_index(&self) -> Index {
        let mut index = Index::default();
        let packs: Vec<PathBuf> = self.files().map(|(path, _)| path).filter(|p| Self::is_pack(p)).collect();
        // The table at its size once (the packs' headers say how many rows they hold), not
        // doubled while the packs are read: a doubling holds the old and new tables at once.
        let rows: u64 = packs.iter().filter_map(|p| pack_rows(p)).sum();
        index.row_bits = row_bits(rows);
        let mut slots = Vec::with_capacity(usize::try_from(rows).unwrap_or(0));
        for path in packs {
            if let Err(why) = index.read_pack(&path, &mut slots) {
                // Packs appear whole (renamed into place), so one of ours was damaged
                // afterwards: it can serve nothing. A file Kiln did not write is left alone.
                let removed = Self::is_own(&path) && fs::remove_file(&path).is_ok();
                index.damaged.push((path, why, removed));
            }
        }
        slots.sort_unstable();
        index.runs.push(slots);
        index
    }

    /// Warnings about packs whose index is damaged (their entries are recompiled): one
    /// line each; and the remote cache's one warning, if it failed (given once: ask again
    /// after the last write).
    pub fn warnings(&self) -> Vec<String> {
        let mut warnings: Vec<String> = self.with_index(|index| {
            index
                .damaged
                .iter()
                .map(|(path, why, removed)| {
                    if *removed {
                        format!(
                            "warning: cache pack {} was damaged ({why}) and is removed; its entries are recompiled",
                            path.display()
                        )
                    } else {
                        format!("warning: cache file {} is ignored ({why}); Kiln did not write it", path.display())
                    }
                })
                .collect()
        });
        warnings.extend(self.remote().and_then(Remote::take_warning));
        warnings
    }
}

/// A set of preprocessing records, if `bytes` is a whole one.
/// The body of a records file (magic, blake3 of the body, body), when whole.
fn records_body(mut bytes: Vec<u8>) -> Option<Vec<u8>> {
    if !records_whole(&bytes) {
        return None;
    }
    bytes.drain(..40);
    Some(bytes)
}

/// Whether `bytes` is a whole records file: magic, then the blake3 of the body after it.
fn records_whole(bytes: &[u8]) -> bool {
    bytes.len() >= 40 && &bytes[..8] == RECORD_MAGIC && blake3::hash(&bytes[40..]).as_bytes() == &bytes[8..40]
}

/// How many rows the index of the pack at `path` says it holds (its header alone is read;
/// [`open_pack`] checks the rest).
fn pack_rows(path: &Path) -> Option<u64> {
    let mut header = [0u8; 16];
    let (file, _) = crate::archive::input::open_regular(path).ok()?;
    file.read_exact_at(&mut header, 0).ok()?;
    let rows = u64::from_le_bytes(header[8..16].try_into().expect("8 bytes"));
    // A damaged count that the file cannot hold reserves nothing.
    let fits = rows.checked_mul(ROW as u64)?.checked_add(PACK_HEADER as u64)? <= file.metadata().ok()?.len();
    (&header[..8] == PACK_MAGIC && fits).then_some(rows)
}

/// Opens the pack at `path` and checks its header: the pack and its row count;
/// `Ok(None)` when the file is gone, `Err(why)` when it is not a pack of this Kiln or too
/// short for its rows (the rows' checksum is checked by whoever reads them).
fn open_pack_header(path: &Path) -> Result<Option<(Pack, u64)>, String> {
    let file = match crate::archive::input::open_regular(path) {
        Ok((f, _)) => f,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(e.to_string()),
    };
    let meta = file.metadata().map_err(|e| e.to_string())?;
    let size = meta.len();
    let mut header = [0u8; PACK_HEADER];
    file.read_exact_at(&mut header, 0).map_err(|_| "truncated header".to_string())?;
    if &header[..8] != PACK_MAGIC {
        return Err("not a cache pack of this kiln".into());
    }
    let count = u64::from_le_bytes(header[8..16].try_into().expect("8 bytes"));
    count.checked_mul(ROW as u64).filter(|&n| PACK_HEADER as u64 + n <= size).ok_or("truncated index")?;
    let modified = meta.modified().unwrap_or(SystemTime::UNIX_EPOCH);
    let rows_hash = header[16..48].try_into().expect("32 bytes");
    let pack = Pack { path: path.to_path_buf(), file, modified, size, rows_hash, touched: AtomicBool::new(false) };
    Ok(Some((pack, count)))
}

/// Opens the pack at `path` and reads its index rows (key, offset, length), checked (for
/// the commands that walk every row: the index of a build holds a slot per key instead).
fn open_pack(path: &Path) -> Result<Option<(Pack, Vec<(Key, u64, u64)>)>, String> {
    let Some((pack, count)) = open_pack_header(path)? else { return Ok(None) };
    let mut rows = vec![0u8; count as usize * ROW];
    pack.file.read_exact_at(&mut rows, PACK_HEADER as u64).map_err(|_| "truncated index".to_string())?;
    if blake3::hash(&rows).as_bytes() != &pack.rows_hash {
        return Err("index checksum mismatch".into());
    }
    let word = |r: &[u8], i: usize| u64::from_le_bytes(r[i..i + 8].try_into().expect("8 bytes"));
    let rows = rows
        .chunks_exact(ROW)
        .map(|r| (Key(r[..32].try_into().expect("32 bytes")), word(r, 32), word(r, 40)))
        .collect();
    Ok(Some((pack, rows)))
}

/// Length, modification time and blake3 of the whole content of an archive file: an
/// archive damaged in place, even with its length and modification time kept, no longer
/// matches its stamp. Hashing costs about a millisecond per few MB (archives are
/// compressed), far less than the warm build it saves. A path that is not a regular file has
/// no identity (and is not opened: a FIFO would block).
fn archive_identity(path: &Path) -> io::Result<String> {
    use std::os::unix::fs::OpenOptionsExt;
    // Only a regular file has an identity (opening a FIFO to read it would block).
    if !fs::metadata(path)?.is_file() {
        return Err(io::Error::other("not a regular file"));
    }
    let mut f = fs::File::options().read(true).custom_flags(libc::O_NONBLOCK).open(path)?;
    let meta = f.metadata()?;
    if !meta.is_file() {
        return Err(io::Error::other("not a regular file"));
    }
    let mut hasher = blake3::Hasher::new();
    hasher.update_reader(&mut f)?;
    identity(&meta, hasher.finalize())
}

/// The identity of a regular file of `meta` whose content hashes to `hash`.
fn identity(meta: &fs::Metadata, hash: blake3::Hash) -> io::Result<String> {
    let mtime = meta.modified()?.duration_since(SystemTime::UNIX_EPOCH).unwrap_or_default();
    Ok(format!("{} {}.{:09} {}", meta.len(), mtime.as_secs(), mtime.subsec_nanos(), hash.to_hex()))
}

/// `10M`, `1G`, `512k`, `2GiB`, `100` (bytes): powers of 1024.
pub fn parse_size(text: &str) -> Result<u64, String> {
    let t = text.trim();
    let digits = t.find(|c: char| !c.is_ascii_digit() && c != '.').unwrap_or(t.len());
    let (num, unit) = t.split_at(digits);
    let value: f64 = num.parse().map_err(|_| format!("invalid size `{text}`: expected a number like 10M or 1G"))?;
    let mult: u64 = match unit.trim().to_ascii_lowercase().as_str() {
        "" | "b" => 1,
        "k" | "kb" | "kib" => 1 << 10,
        "m" | "mb" | "mib" => 1 << 20,
        "g" | "gb" | "gib" => 1 << 30,
        "t" | "tb" | "tib" => 1 << 40,
        other => return Err(format!("invalid size `{text}`: unknown unit `{other}` (use K, M, G or T)")),
    };
    Ok((value * mult as f64) as u64)
}

/// `1.5 MiB`-style rendering for reports.
pub fn format_size(bytes: u64) -> String {
    const UNITS: [&str; 5] = ["B", "KiB", "MiB", "GiB", "TiB"];
    let mut v = bytes as f64;
    let mut u = 0;
    while v >= 1024.0 && u < UNITS.len() - 1 {
        v /= 1024.0;
        u += 1;
    }
    if u == 0 {
        format!("{bytes} B")
    } else {
        format!("{v:.1} {}", UNITS[u])
    }
}

// Entry layout: MAGIC, blake3(body), body.
// body: key (32), artifact count (u32), per artifact: target name length (u8) + name, length
// (u64) + bytes; then the reflection as JSON (u64 length + bytes).
/// The small framing pieces of an entry's body: the artifact count, one frame per artifact
/// (target name and length), the reflection's length and the reflection (tests write old
/// entries with them).
#[cfg(test)]
fn frames(c: &Compiled) -> Vec<Vec<u8>> {
    let mut frames = vec![(c.artifacts.len() as u32).to_le_bytes().to_vec()];
    for (t, bytes) in &c.artifacts {
        let mut frame = vec![t.name().len() as u8];
        frame.extend_from_slice(t.name().as_bytes());
        frame.extend_from_slice(&(bytes.len() as u64).to_le_bytes());
        frames.push(frame);
    }
    let json = serde_json::to_vec(&c.reflection).expect("reflection serializes");
    frames.push((json.len() as u64).to_le_bytes().to_vec());
    frames.push(json);
    frames
}

/// The pieces of a version 2 entry's body, in file order (tests write old entries with it).
#[cfg(test)]
fn body_pieces<'a>(key: &'a Key, c: &'a Compiled, frames: &'a [Vec<u8>]) -> Vec<&'a [u8]> {
    let mut body: Vec<&'a [u8]> = vec![&key.0, &frames[0]];
    for (i, (_, bytes)) in c.artifacts.iter().enumerate() {
        body.push(&frames[1 + i]);
        body.push(bytes);
    }
    let n = frames.len();
    body.push(&frames[n - 2]);
    body.push(&frames[n - 1]);
    body
}

/// An entry's checksum: blake3 of its body with each artifact replaced by the artifact's
/// blake3 (`hashes`), so that artifacts are hashed once per build, for the archive and the
/// cache alike.
#[cfg(test)]
fn entry_checksum(key: &Key, frames: &[Vec<u8>], hashes: &[blake3::Hash]) -> blake3::Hash {
    let mut h = blake3::Hasher::new();
    h.update(&key.0);
    h.update(&frames[0]);
    for (i, hash) in hashes.iter().enumerate() {
        h.update(&frames[1 + i]);
        h.update(hash.as_bytes());
    }
    let n = frames.len();
    h.update(&frames[n - 2]);
    h.update(&frames[n - 1]);
    h.finalize()
}

/// An entry as one buffer (tests).
#[cfg(test)]
fn encode(key: &Key, c: &Compiled) -> Vec<u8> {
    let hashes: Vec<blake3::Hash> = c.artifacts.iter().map(|(_, b)| blake3::hash(b)).collect();
    encode_hashed(key, c, &hashes)
}

/// An entry as one buffer, with its artifacts' blake3.
#[cfg(test)]
fn encode_hashed(key: &Key, c: &Compiled, hashes: &[blake3::Hash]) -> Vec<u8> {
    remote_value(key, c, hashes).split_off(REMOTE_HEADER)
}

/// A remote cache value: [`REMOTE_MAGIC`], the xxh3-128 of the key and the entry, the entry
/// (as a pack holds it, compressed once for both). The value's checksum guards against damage and truncation (not
/// against a hostile server, which could write any value under any key whatever the hash):
/// one pass of a non-cryptographic hash over a whole buffer, which a fill checks many
/// times faster than a blake3 (a blake3 of every entry was a large share of a warm-remote
/// build's CPU). The entry's own checksum (blake3) is checked when the entry
/// is used.
#[cfg(test)]
fn remote_value(key: &Key, c: &Compiled, hashes: &[blake3::Hash]) -> Vec<u8> {
    remote_value_of(key, &codec::encode(key, c, hashes, &HashMap::new()))
}

/// The remote value of the encoded `entry` of `key` ([`remote_value_of`]).
fn remote_value_of(key: &Key, entry: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(REMOTE_HEADER + entry.len());
    out.extend_from_slice(REMOTE_MAGIC);
    out.extend_from_slice(&remote_checksum(key, entry));
    out.extend_from_slice(entry);
    out
}

/// The remote key of the cache dictionary `id`: its value is the dictionary's file
/// ([`codec`]), whose content hashes to `id`, so a reader checks it against the id it asked
/// for.
fn remote_dict_key(id: &[u8; 16]) -> Key {
    let mut h = blake3::Hasher::new();
    h.update(b"kiln remote cache dictionary v1\0");
    h.update(id);
    Key(*h.finalize().as_bytes())
}

/// The checksum of a remote value: xxh3-128 of `key` then `entry`.
fn remote_checksum(key: &Key, entry: &[u8]) -> [u8; 16] {
    let mut h = xxhash_rust::xxh3::Xxh3::new();
    h.update(&key.0);
    h.update(entry);
    h.digest128().to_le_bytes()
}

/// The entry of a whole remote `value` of `key` ([`remote_value_of`]): its checksum matches and
/// it is an entry of `key` (magic, length and key; its own checksum is not checked here).
fn remote_entry<'a>(key: &Key, value: &'a [u8]) -> Result<&'a [u8], String> {
    let magic = value.get(..8).unwrap_or_default();
    if value.len() < REMOTE_HEADER || ![REMOTE_MAGIC, REMOTE_MAGIC_V3, REMOTE_MAGIC_V2].iter().any(|m| magic == *m) {
        return Err("not a remote cache entry of this kiln".into());
    }
    let entry = &value[REMOTE_HEADER..];
    if remote_checksum(key, entry) != value[8..REMOTE_HEADER] {
        return Err("checksum mismatch".into());
    }
    if !is_entry_of(entry, key) {
        return Err("the entry belongs to another key".into());
    }
    Ok(entry)
}

/// Whether `entry` (of any version) is one of `key`: a cheap check of its magic and key (or
/// for version 6, which holds no key, its check sum), not of its whole content.
fn is_entry_of(entry: &[u8], key: &Key) -> bool {
    if entry.starts_with(MAGIC) {
        return entry.len() >= 72 && entry[40..72] == key.0;
    }
    codec::is_entry_of(entry, key)
}

/// A version 2 entry (uncompressed), checked, and the blake3 of each artifact: `known`
/// where the entry stored them (then not computed: the checksum checks them), else
/// computed from the artifacts.
fn decode_v2_hashed(
    key: &Key,
    bytes: &[u8],
    known: Option<&[blake3::Hash]>,
) -> Result<(Compiled, Vec<blake3::Hash>), String> {
    let (artifacts, json) = parse(key, bytes, known)?;
    let mut hashes = Vec::with_capacity(artifacts.len());
    let artifacts = artifacts
        .into_iter()
        .map(|(name, bytes, hash)| {
            let name = std::str::from_utf8(name).map_err(|_| "bad target name".to_string())?;
            let target = Target::from_name(name).ok_or_else(|| format!("unknown target `{name}`"))?;
            hashes.push(hash);
            Ok((target, bytes.to_vec()))
        })
        .collect::<Result<Vec<_>, String>>()?;
    let reflection: Reflection = serde_json::from_slice(json).map_err(|e| format!("bad reflection: {e}"))?;
    Ok((Compiled { artifacts, reflection }, hashes))
}

/// An entry's artifacts (target name, bytes, blake3) and reflection JSON, once its checksum
/// and key are checked.
type Parsed<'a> = (Vec<(&'a [u8], &'a [u8], blake3::Hash)>, &'a [u8]);

fn parse<'a>(key: &Key, bytes: &'a [u8], known: Option<&[blake3::Hash]>) -> Result<Parsed<'a>, String> {
    if bytes.len() < 40 || &bytes[..8] != MAGIC {
        return Err("not a cache entry of this kiln".into());
    }
    let body = &bytes[40..];
    // Read the body, hashing it as `entry_checksum` does (each artifact by its hash).
    let mut h = blake3::Hasher::new();
    let mut r = Reader { bytes: body, at: 0 };
    let entry_key = r.take(32)?;
    h.update(entry_key);
    let count_bytes = r.take(4)?;
    h.update(count_bytes);
    let count = u32::from_le_bytes(count_bytes.try_into().unwrap());
    if known.is_some_and(|k| k.len() != count as usize) {
        return Err("checksum mismatch".into());
    }
    let mut artifacts = Vec::new();
    for i in 0..count as usize {
        let frame = r.at;
        let n = r.take(1)?[0] as usize;
        let name = r.take(n)?;
        let len = r.u64()? as usize;
        h.update(&body[frame..r.at]);
        let artifact = r.take(len)?;
        let hash = known.map_or_else(|| blake3::hash(artifact), |k| k[i]);
        h.update(hash.as_bytes());
        artifacts.push((name, artifact, hash));
    }
    let frame = r.at;
    let len = r.u64()? as usize;
    let json = r.take(len)?;
    h.update(&body[frame..r.at]);
    if r.at != body.len() {
        return Err("trailing bytes".into());
    }
    if h.finalize().as_bytes() != &bytes[8..40] {
        return Err("checksum mismatch".into());
    }
    if entry_key != key.0 {
        return Err("the entry belongs to another key".into());
    }
    Ok((artifacts, json))
}

struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], String> {
        let end = self.at.checked_add(n).filter(|&e| e <= self.bytes.len()).ok_or("entry is truncated")?;
        let s = &self.bytes[self.at..end];
        self.at = end;
        Ok(s)
    }
    fn u64(&mut self) -> Result<u64, String> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into().unwrap()))
    }
    /// A LEB128 number (7 bits a byte, low first) of at most 64 bits.
    fn varint(&mut self) -> Result<u64, String> {
        let mut n = 0u64;
        for shift in (0..64).step_by(7) {
            let b = self.take(1)?[0];
            n |= u64::from(b & 0x7f)
                .checked_shl(shift)
                .filter(|v| v >> shift == u64::from(b & 0x7f))
                .ok_or("bad number")?;
            if b & 0x80 == 0 {
                return Ok(n);
            }
        }
        Err("bad number".into())
    }
}

#[cfg(test)]
mod tests;
