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
mod fault;
mod fill;
mod http_batch;
pub(crate) mod remote;

pub use remote::Remote;

/// An entry of version 2 (uncompressed): still read; version 3 ([`codec`]) is written.
const MAGIC: &[u8; 8] = b"KILNCE\0\x02";
const PACK_MAGIC: &[u8; 8] = b"KILNCP\0\x02";
const PACK_EXTENSION: &str = "kcp";
const RECORD_MAGIC: &[u8; 8] = b"KILNPP\0\x01";
/// A remote cache value ([`remote_value`]); its header: magic, xxh3-128 of its key and entry.
/// Version 3 holds a compressed entry ([`codec`], without dictionaries); version 2 values
/// (uncompressed entries) are still read.
const REMOTE_MAGIC: &[u8; 8] = b"KILNCER\x03";
const REMOTE_MAGIC_V2: &[u8; 8] = b"KILNCER\x02";
const REMOTE_HEADER: usize = 8 + 16;
const RECORD_EXTENSION: &str = "kpp";
/// The largest records file read (a record is 64 bytes: about 16M permutations).
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
    Hit(Compiled),
    Miss,
    /// Every copy of the entry fails its checksum or cannot be decoded: the reason. The
    /// caller recompiles; the new copy, in a newer pack, is the one read from then on.
    Corrupt(String),
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

/// Every pack's index, read once per [`Cache`] (and extended by its own writes, unless
/// [`Cache::without_indexing_puts`]: then by its remote fills only).
#[derive(Debug, Default)]
struct Index {
    /// The newest copy of each key: one location inline, no list per key (a warm 100k
    /// build's index is 75k keys).
    by_key: HashMap<Key, Location>,
    /// The other copies of the keys that have more than one, newest pack first.
    older: HashMap<Key, Vec<Location>>,
    /// Packs whose index was damaged: (path, why, whether it was removed: not when Kiln did
    /// not write it). Their entries are misses.
    damaged: Vec<(PathBuf, String, bool)>,
}

impl Index {
    fn add(&mut self, pack: Arc<Pack>, rows: Vec<(Key, u64, u64)>) {
        for (key, offset, len) in rows {
            let mut location = Location { pack: pack.clone(), offset, len };
            let newest = match self.by_key.entry(key) {
                std::collections::hash_map::Entry::Vacant(v) => {
                    v.insert(location);
                    continue;
                }
                std::collections::hash_map::Entry::Occupied(o) => o.into_mut(),
            };
            if newest.pack.modified < location.pack.modified {
                std::mem::swap(newest, &mut location);
            }
            let older = self.older.entry(key).or_default();
            let at = older.iter().position(|l| l.pack.modified < location.pack.modified).unwrap_or(older.len());
            older.insert(at, location);
        }
    }

    /// Every copy of `key`, newest pack first.
    fn copies(&self, key: &Key) -> Vec<Location> {
        let older = self.older.get(key).map_or(&[][..], Vec::as_slice);
        self.by_key.get(key).into_iter().chain(older).cloned().collect()
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
    /// build never looks up a key it compiled, and at 100k keys the index of its own puts
    /// is about 10 MiB of its peak. Remote hits filled into the local cache still join it
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

    /// Frees the in-memory index of every pack (about 70 bytes per key); the next lookup
    /// reads it again. A build calls this once it looks nothing up any more, before it writes
    /// the archive.
    pub fn release_index(&self) {
        *self.index.write().expect("no panics while locked") = None;
    }

    fn read_index(&self) -> Index {
        let mut index = Index::default();
        let packs: Vec<PathBuf> = self.files().map(|(path, _)| path).filter(|p| Self::is_pack(p)).collect();
        // The map at its size once (the packs' headers say how many rows they hold), not
        // doubled while the packs are read: at 75k keys the old and new tables of a doubling
        // were about 11 MB at once. Slots never filled are never touched.
        let rows: u64 = packs.iter().filter_map(|p| pack_rows(p)).sum();
        index.by_key.reserve(usize::try_from(rows).unwrap_or(0));
        for path in packs {
            match open_pack(&path) {
                Ok(Some((pack, rows))) => index.add(Arc::new(pack), rows),
                Ok(None) => {} // removed meanwhile (gc or clear in another process)
                Err(why) => {
                    // Packs appear whole (renamed into place), so one of ours was damaged
                    // afterwards: it can serve nothing. A file Kiln did not write is left alone.
                    let removed = Self::is_own(&path) && fs::remove_file(&path).is_ok();
                    index.damaged.push((path, why, removed));
                }
            }
        }
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

    /// Whether some pack holds `key` (its content is checked by [`Cache::get`]).
    pub fn contains(&self, key: &Key) -> bool {
        self.with_index(|index| index.by_key.contains_key(key))
    }

    /// The newest pack holding `key`.
    pub fn pack_of(&self, key: &Key) -> Option<PathBuf> {
        self.with_index(|index| index.by_key.get(key).map(|l| l.pack.path.clone()))
    }

    /// The entry of `key`: from a local pack, else from the remote cache (checked, then
    /// queued to be filled into the local cache).
    pub fn get(&self, key: &Key) -> Lookup {
        let local = self.get_local(key);
        let Some(layer) = &self.remote else { return local };
        if matches!(local, Lookup::Hit(_)) {
            return local;
        }
        if layer.absent.lock().expect("no panics while locked").contains(key) {
            return local;
        }
        let Some(bytes) = layer.remote.get(key) else {
            layer.absent.lock().expect("no panics while locked").insert(*key);
            return local;
        };
        match remote_entry(key, &bytes).and_then(|entry| Ok((self.decode(key, entry)?, entry))) {
            Ok((c, entry)) => {
                layer.remote.count_hit();
                let mut fills = layer.fills.lock().expect("no panics while locked");
                if fills.as_ref().is_some_and(fill::FillPack::is_full) {
                    self.finish_fills(fills.take());
                }
                if fills.is_none() {
                    *fills = fill::FillPack::create(&self.dir, FILL_ROWS).ok();
                }
                // Failing to fill only costs a remote lookup next time.
                if fills.as_mut().is_some_and(|p| p.push(key, entry).is_err()) {
                    *fills = None;
                }
                Lookup::Hit(c)
            }
            Err(why) => Lookup::Corrupt(format!(
                "remote cache entry {key} at {} is corrupted ({why}); recompiling",
                layer.remote.url()
            )),
        }
    }

    /// Copies into the local cache the remote entries of `keys` that it lacks: from the parts
    /// of the bundle of `keys` most of whose keys it lacks when the remote streams
    /// ([`bundle`]), the rest fetched in batches ([`Remote::get_each`]); each checked as
    /// [`Cache::get`] checks it, and streamed into one pack as they arrive (no entry waits in
    /// memory). Whether every key is now held locally. A key the remote lacks is not asked
    /// for again this build; a corrupted entry is left to the build, which looks it up again,
    /// reports and recompiles it.
    pub fn fill_from_remote(&self, keys: &[Key]) -> bool {
        self.fill(keys, None)
    }

    /// [`Cache::fill_from_remote`] without counting its hits: whether every key is held
    /// locally now, and the keys it filled (sorted), for a caller that fetched them before
    /// it knew which it uses to count those it does ([`Remote::count_hits`]).
    pub fn prefill_from_remote(&self, keys: &[Key]) -> (bool, Vec<Key>) {
        let filled = Mutex::new(Vec::new());
        let complete = self.fill(keys, Some(&filled));
        let mut filled = filled.into_inner().expect("no panics while locked");
        filled.sort_unstable();
        (complete, filled)
    }

    /// [`Cache::fill_from_remote`]; each key filled is counted as a hit, or added to
    /// `filled`.
    fn fill(&self, keys: &[Key], filled: Option<&Mutex<Vec<Key>>>) -> bool {
        let Some(layer) = &self.remote else { return false };
        let hit = |key: &Key| match filled {
            Some(f) => f.lock().expect("no panics while locked").push(*key),
            None => layer.remote.count_hit(),
        };
        // The single lookups' hits first: then the index knows them.
        let pending = layer.fills.lock().expect("no panics while locked").take();
        self.finish_fills(pending);
        let absent = layer.absent.lock().expect("no panics while locked").clone();
        let mut missing: Vec<Key> = self.with_index(|index| {
            let known = |k: &Key| index.by_key.contains_key(k) || absent.contains(k);
            keys.iter().filter(|k| !known(k)).copied().collect()
        });
        let complete = AtomicBool::new(absent.is_empty() || keys.iter().all(|k| !absent.contains(k)));
        // Not with signed values: a part is used as it streams, before its end could be
        // checked (each value is checked by itself; see `Remote::get_each`).
        let bundle = (layer.remote.streams() && !layer.remote.signs() && keys.len() >= bundle::MIN_KEYS)
            .then(|| bundle::Bundle::new(keys));
        let mut parts = vec![None; bundle.as_ref().map_or(0, |b| b.ids().len())];
        if missing.is_empty() {
            self.keep_bundle(layer, bundle, parts);
            return complete.into_inner();
        }
        // Room for every key asked; failing to fill only costs a remote lookup next time.
        let pack = fill::FillPack::create(&self.dir, missing.len()).ok();
        if let (Some(b), Some(p), true) = (&bundle, &pack, missing.len() >= bundle::MIN_KEYS) {
            missing.sort_unstable();
            let from_parts;
            (from_parts, parts) = self.fill_from_bundle(layer, b, &missing, p);
            missing.retain(|k| from_parts.binary_search(k).is_err());
            from_parts.iter().for_each(hit);
        }
        self.keep_bundle(layer, bundle, parts);
        layer.remote.get_each(&missing, |key, value| {
            let Some(bytes) = value else {
                layer.absent.lock().expect("no panics while locked").insert(*key);
                complete.store(false, Ordering::Relaxed);
                return;
            };
            // The value's one checksum (one blake3 of the whole value, several times faster
            // than one per artifact); the entry's own is checked when the build uses it.
            let Ok(entry) = remote_entry(key, bytes) else {
                // Looked up again by the build, which reports it and recompiles.
                complete.store(false, Ordering::Relaxed);
                return;
            };
            hit(key);
            // A failed write leaves the pack unfinished (removed).
            if let Some(p) = &pack {
                let _ = p.push(key, entry);
            }
        });
        // Written now, so that the build's lookups find them here (not in the remote again).
        self.finish_fills(pack);
        complete.into_inner()
    }

    /// The entries of `wanted` (sorted) that the parts of `bundle` most of whose keys are
    /// wanted hold (else most of a part would be dropped), checked and pushed into `pack` as
    /// they arrive: the keys filled (sorted), and whether each part was whole (`None`: not
    /// read).
    fn fill_from_bundle(
        &self,
        layer: &Layer,
        bundle: &bundle::Bundle,
        wanted: &[Key],
        pack: &fill::FillPack,
    ) -> (Vec<Key>, Vec<Option<bool>>) {
        let read: Vec<usize> = (0..bundle.ids().len())
            .filter(|&i| {
                let part = bundle.part(i);
                part.iter().filter(|k| wanted.binary_search(k).is_ok()).count() * 2 >= part.len()
            })
            .collect();
        let ids: Vec<Key> = read.iter().map(|&i| bundle.ids()[i]).collect();
        let filled = Mutex::new(Vec::with_capacity(wanted.len()));
        let parts = Mutex::new(vec![None; bundle.ids().len()]);
        layer.remote.get_streamed(&ids, |n, body| {
            let i = read[n];
            let mut mine = Vec::new();
            let whole = body.is_some_and(|body| {
                // One entry at a time (a part is never held whole).
                let mut value = Vec::new();
                bundle::read_part(body, bundle.part(i), &mut value, |key, entry| {
                    if wanted.binary_search(key).is_ok() && pack.push(key, entry).is_ok() {
                        mine.push(*key);
                    }
                })
            });
            parts.lock().expect("no panics while locked")[i] = Some(whole);
            filled.lock().expect("no panics while locked").extend(mine);
        });
        let mut filled = filled.into_inner().expect("no panics while locked");
        filled.sort_unstable();
        (filled, parts.into_inner().expect("no panics while locked"))
    }

    /// Keeps `bundle` for [`Cache::put_bundle`] when this build writes and a part of it is
    /// not known whole.
    fn keep_bundle(&self, layer: &Layer, bundle: Option<bundle::Bundle>, parts: Vec<Option<bool>>) {
        let keep = layer.remote.writes() && parts.iter().any(|p| *p != Some(true));
        *layer.bundle.lock().expect("no panics while locked") = bundle.filter(|_| keep).map(|b| (b, parts));
    }

    /// Stores the parts of the bundle of the last fill's keys ([`bundle`]) that the remote
    /// lacks (asked with `HEAD` when the fill did not read them) or held damaged, from the
    /// local cache's entries, in read-write mode. A build calls this once every key's entry
    /// is in the local cache (after writing the archive); failing to only costs the next
    /// fresh cache a `GET` per key.
    pub fn put_bundle(&self) {
        let Some(layer) = &self.remote else { return };
        let Some((bundle, parts)) = layer.bundle.lock().expect("no panics while locked").take() else { return };
        (0..parts.len()).into_par_iter().for_each(|i| {
            let id = &bundle.ids()[i];
            if !layer.remote.writes() || parts[i].or_else(|| layer.remote.contains(id)) != Some(false) {
                return;
            }
            let keys = bundle.part(i);
            let size = bundle::part_overhead(keys.len()) + self.local_size(keys);
            if let Some(value) = bundle::encode_part(keys, size, |key, out| self.append_local_entry(key, out)) {
                layer.remote.store(id, &value);
            }
        });
    }

    /// Appends the newest local entry of `key` to `out`; whether there was one. Only its
    /// magic and key are checked: a build that assembles compiled or checked (on lookup or
    /// from the remote) every entry of its keys, and its readers check the entry's own
    /// checksum on use (a blake3 of the 130 MB of a 10k set's entries would cost the writing
    /// build about a tenth of a second more).
    fn append_local_entry(&self, key: &Key, out: &mut Vec<u8>) -> bool {
        let Some(l) = self.with_index(|index| index.by_key.get(key).cloned()) else {
            return false;
        };
        let start = out.len();
        out.resize(start + l.len as usize, 0);
        let entry = &mut out[start..];
        let ok = l.pack.file.read_exact_at(entry, l.offset).is_ok()
            && entry.len() >= 72
            && (&entry[..8] == MAGIC || &entry[..8] == codec::MAGIC)
            && entry[40..72] == key.0;
        if !ok {
            out.truncate(start);
            return false;
        }
        // An entry compressed with this cache's dictionaries goes out without them.
        if out[start..].starts_with(codec::MAGIC) && codec::uses_dictionary(&out[start..]) != Ok(false) {
            let portable = codec::decode(key, &out[start..], &|id| self.dicts.get(&self.dir, id))
                .map(|(c, hashes)| codec::encode(key, &c, &hashes, &HashMap::new()));
            out.truncate(start);
            match portable {
                Ok(entry) => out.extend_from_slice(&entry),
                Err(_) => return false,
            }
        }
        true
    }

    /// The bytes of the local entries of `keys` (the newest copy of each).
    fn local_size(&self, keys: &[Key]) -> usize {
        self.with_index(|index| keys.iter().filter_map(|k| index.by_key.get(k).map(|l| l.len as usize)).sum())
    }

    /// Writes the index of a fill pack and renames it into place; the index of this `Cache`
    /// (if read) then knows its entries. Failing to only costs remote lookups next time.
    fn finish_fills(&self, pack: Option<fill::FillPack>) {
        let Some(Ok(Some(path))) = pack.map(fill::FillPack::finish) else { return };
        let mut index = self.index.write().expect("no panics while locked");
        if let Some(index) = index.as_mut() {
            if let Ok(Some((pack, rows))) = open_pack(&path) {
                index.add(Arc::new(pack), rows);
            }
        }
    }

    /// The entry `bytes` of `key`, of either version, checked.
    fn decode(&self, key: &Key, bytes: &[u8]) -> Result<Compiled, String> {
        if bytes.starts_with(codec::MAGIC) {
            return codec::decode(key, bytes, &|id| self.dicts.get(&self.dir, id)).map(|(c, _)| c);
        }
        decode_v2(key, bytes)
    }

    fn get_local(&self, key: &Key) -> Lookup {
        let locations = self.with_index(|index| index.copies(key));
        let mut corrupt = None;
        for l in &locations {
            let mut bytes = vec![0; l.len as usize];
            let decoded = match l.pack.file.read_exact_at(&mut bytes, l.offset) {
                Ok(()) => self.decode(key, &bytes),
                Err(_) => Err("entry is truncated".to_string()),
            };
            match decoded {
                Ok(c) => {
                    l.pack.touch();
                    return Lookup::Hit(c);
                }
                Err(why) => {
                    corrupt.get_or_insert_with(|| {
                        format!("cache entry {key} in {} is corrupted ({why}); recompiling", l.pack.path.display())
                    });
                }
            }
        }
        corrupt.map_or(Lookup::Miss, Lookup::Corrupt)
    }

    /// Stores one entry (a pack of one).
    pub fn put(&self, key: &Key, compiled: &Compiled) -> Result<(), Error> {
        self.put_pack(&[(*key, compiled)])
    }

    /// Stores `entries` as one pack, atomically.
    pub fn put_pack(&self, entries: &[(Key, &Compiled)]) -> Result<(), Error> {
        let hashes: Vec<Vec<blake3::Hash>> =
            entries.par_iter().map(|(_, c)| c.artifacts.iter().map(|(_, b)| blake3::hash(b)).collect()).collect();
        let entries: Vec<(Key, &Compiled, &[blake3::Hash])> =
            entries.iter().zip(&hashes).map(|((k, c), h)| (*k, *c, &h[..])).collect();
        self.put_pack_hashed(&entries)
    }

    /// [`Cache::put_pack`] with the blake3 of every artifact already known (in the order of
    /// each entry's artifacts). With a remote cache, the pack also holds the remote hits not
    /// yet filled in (finished as a pack of their own), and each of `entries` is stored to
    /// the remote (in read-write mode).
    pub fn put_pack_hashed(&self, entries: &[(Key, &Compiled, &[blake3::Hash])]) -> Result<(), Error> {
        if let Some(layer) = &self.remote {
            let pending = layer.fills.lock().expect("no panics while locked").take();
            self.finish_fills(pending);
        }
        let local = self.write_pack(entries);
        if let Some(layer) = self.remote.as_ref().filter(|l| l.remote.writes()) {
            entries.par_iter().for_each(|(key, c, hashes)| layer.remote.put(key, &remote_value(key, c, hashes)));
        }
        local
    }

    /// Writes `entries` as one pack, each entry compressed ([`codec`]; a dictionary is
    /// trained first for each kind the cache has none of, when `entries` hold enough of it).
    fn write_pack(&self, entries: &[(Key, &Compiled, &[blake3::Hash])]) -> Result<(), Error> {
        if entries.is_empty() {
            return Ok(());
        }
        let files = || self.files().map(|(p, _)| p).collect();
        let write = |path: &Path, bytes: &[u8]| self.write_file(path, bytes).is_ok();
        let dicts = codec::dictionaries_for(&self.dicts, &self.dir, files, entries, write);
        let encoded: Vec<Vec<u8>> =
            entries.par_iter().map(|(key, c, hashes)| codec::encode(key, c, hashes, &dicts)).collect();
        let count = entries.len();
        let mut rows = Vec::with_capacity(count * ROW);
        let mut offset = (PACK_HEADER + count * ROW) as u64;
        for (key, entry) in entries.iter().map(|e| e.0).zip(&encoded) {
            rows.extend_from_slice(&key.0);
            rows.extend_from_slice(&offset.to_le_bytes());
            rows.extend_from_slice(&(entry.len() as u64).to_le_bytes());
            offset += entry.len() as u64;
        }
        let rows_hash = blake3::hash(&rows);
        let count = (count as u64).to_le_bytes();
        // Named by content: two builds writing the same pack rename one over the other.
        let mut name = blake3::Hasher::new();
        name.update(rows_hash.as_bytes());
        for entry in &encoded {
            name.update(&entry[8..40]);
        }
        let path = self.dir.join(format!("{}.{PACK_EXTENSION}", &name.finalize().to_hex()[..32]));
        let mut pieces: Vec<&[u8]> = vec![PACK_MAGIC, &count, rows_hash.as_bytes(), &rows];
        pieces.extend(encoded.iter().map(Vec::as_slice));
        self.write_pieces(&path, &pieces)?;
        // Later lookups through this `Cache` see the new pack.
        let mut index = self.index.write().expect("no panics while locked");
        if let Some(index) = index.as_mut().filter(|_| self.index_puts) {
            if let Ok(Some((pack, rows))) = open_pack(&path) {
                index.add(Arc::new(pack), rows);
            }
        }
        Ok(())
    }

    /// The file of a set of preprocessing records: `DIR/<key>.kpp`.
    pub fn records_path(&self, key: &Key) -> PathBuf {
        self.dir.join(format!("{}.{RECORD_EXTENSION}", key.to_hex()))
    }

    /// The preprocessing records stored under `key` (one set per configuration and
    /// options), by permutation key; empty when missing or damaged.
    ///
    /// Without a local copy, the remote cache's (stored by any machine that built the same
    /// configuration) is used and kept locally. Records name every file's blake3: where the
    /// sources differ they simply do not match, and the permutations are preprocessed.
    pub fn get_records(&self, key: &Key) -> Records {
        self.get_records_bytes(key).and_then(|body| serde_json::from_slice(&body).ok()).unwrap_or_default()
    }

    /// Replaces the records stored under `key`, atomically.
    pub fn put_records(&self, key: &Key, records: &Records) -> Result<(), Error> {
        self.put_records_bytes(key, &serde_json::to_vec(records).expect("records serialize"))
    }

    /// The body of the records file under `key`, in whatever encoding its writer chose;
    /// `None` when missing or damaged (its checksum is checked). Without a local copy, the
    /// remote cache's is used and kept locally.
    pub fn get_records_bytes(&self, key: &Key) -> Option<Vec<u8>> {
        self.get_records_found(key).map(|(body, _)| body)
    }

    /// [`Cache::get_records_bytes`], and whether the body came from the remote cache (no
    /// local copy: this local cache never built that configuration).
    pub fn get_records_found(&self, key: &Key) -> Option<(Vec<u8>, bool)> {
        let path = self.records_path(key);
        // Only a regular file, bounded (a FIFO or a device there is ignored).
        if let Some(body) = crate::archive::input::read_regular(&path, MAX_RECORDS).ok().and_then(records_body) {
            if let Ok(f) = fs::File::options().append(true).open(&path) {
                let _ = f.set_modified(SystemTime::now());
            }
            return Some((body, false));
        }
        let bytes = self.remote().and_then(|r| r.get(key))?;
        let body = records_body(bytes.clone())?;
        let _ = self.write_file(&path, &bytes);
        Some((body, true))
    }

    /// Replaces the records file under `key` with `body` (checksummed), atomically, and
    /// stores it in the remote cache too.
    pub fn put_records_bytes(&self, key: &Key, body: &[u8]) -> Result<(), Error> {
        let sum = blake3::hash(body);
        if let Some(remote) = self.remote() {
            let mut bytes = Vec::with_capacity(40 + body.len());
            bytes.extend_from_slice(RECORD_MAGIC);
            bytes.extend_from_slice(sum.as_bytes());
            bytes.extend_from_slice(body);
            remote.store(key, &bytes);
        }
        self.write_pieces(&self.records_path(key), &[RECORD_MAGIC, sum.as_bytes(), body])
    }

    /// The stamp of the archive at `archive`: `DIR/<blake3 of its absolute path>.stamp`.
    fn stamp_path(&self, archive: &Path) -> PathBuf {
        let abs = std::path::absolute(archive).unwrap_or_else(|_| archive.to_path_buf());
        let name = blake3::hash(abs.to_string_lossy().as_bytes()).to_hex();
        self.dir.join(format!("{}.stamp", &name[..32]))
    }

    /// Records that the archive now at `archive` is the output of the build with
    /// `fingerprint` (with its artifact counts), identified by its length, modification
    /// time and the blake3 of its whole content.
    pub fn stamp_archive(
        &self,
        archive: &Path,
        fingerprint: &blake3::Hash,
        counts: (usize, usize),
    ) -> Result<(), Error> {
        let err = |source| Error { path: archive.to_path_buf(), source };
        let id = archive_identity(archive).map_err(err)?;
        let text = format!("{}\n{}\n{}\n{}\n", fingerprint.to_hex(), id, counts.0, counts.1);
        self.write_file(&self.stamp_path(archive), text.as_bytes())
    }

    /// [`Cache::stamp_archive`] for the archive `bytes` written to `file`, a temporary file
    /// about to be renamed to `archive` (the rename keeps its length and modification
    /// time): the stamp is written while the build still waits on other work. A stamp whose
    /// file is not renamed after all matches no archive.
    pub fn stamp_archive_file(
        &self,
        archive: &Path,
        file: &fs::File,
        bytes: &[u8],
        fingerprint: &blake3::Hash,
        counts: (usize, usize),
    ) -> Result<(), Error> {
        let err = |source| Error { path: archive.to_path_buf(), source };
        let meta = file.metadata().map_err(err)?;
        let id = identity(&meta, blake3::hash(bytes)).map_err(err)?;
        let text = format!("{}\n{}\n{}\n{}\n", fingerprint.to_hex(), id, counts.0, counts.1);
        self.write_file(&self.stamp_path(archive), text.as_bytes())
    }

    /// The artifact counts of the archive at `archive` if it is, untouched, the output of a
    /// build with `fingerprint` (hashed only when there is a stamp), and every key of `keys`
    /// still has its entry.
    pub fn fresh_archive(
        &self,
        archive: &Path,
        fingerprint: &dyn Fn() -> blake3::Hash,
        mut keys: &mut dyn Iterator<Item = &Key>,
    ) -> Option<(usize, usize)> {
        // The stamp first: without one (a first build) the keys are not looked at.
        let text = crate::archive::input::read_regular_to_string(&self.stamp_path(archive), 4096).ok()?;
        if !self.with_index(|index| Iterator::all(&mut keys, |k| index.by_key.contains_key(k))) {
            return None;
        }
        let mut lines = text.lines();
        if lines.next()? != fingerprint().to_hex().as_str() || lines.next()? != archive_identity(archive).ok()? {
            return None;
        }
        Some((lines.next()?.parse().ok()?, lines.next()?.parse().ok()?))
    }

    fn write_file(&self, path: &Path, bytes: &[u8]) -> Result<(), Error> {
        self.write_pieces(path, &[bytes])
    }

    /// Writes the concatenation of `pieces` to a temporary file in the cache folder, then
    /// renames it to `path` ([`crate::output`]: the folder is made again if it was removed
    /// under us, and whatever is not a regular file at `path` is never renamed over).
    fn write_pieces(&self, path: &Path, pieces: &[&[u8]]) -> Result<(), Error> {
        crate::archive::write_pieces(path, pieces, false).map_err(|source| Error { path: path.to_path_buf(), source })
    }

    fn files(&self) -> impl Iterator<Item = (PathBuf, fs::Metadata)> {
        walkdir::WalkDir::new(&self.dir)
            .min_depth(1)
            .max_depth(1)
            .into_iter()
            .filter_map(Result::ok)
            .filter(|e| e.file_type().is_file())
            .filter_map(|e| Some((e.path().to_path_buf(), e.metadata().ok()?)))
    }

    fn is_pack(path: &Path) -> bool {
        path.extension().is_some_and(|e| e == PACK_EXTENSION)
    }

    fn is_dictionary(path: &Path) -> bool {
        path.extension().is_some_and(|e| e == codec::DICT_EXTENSION)
    }

    fn is_record(path: &Path) -> bool {
        path.extension().is_some_and(|e| e == RECORD_EXTENSION)
    }

    /// A temporary file of a write into the cache (named by [`crate::output`] after a cache
    /// file).
    fn is_temporary(path: &Path) -> bool {
        path.file_name()
            .and_then(|n| n.to_str())
            .and_then(crate::output::temporary_parts)
            .is_some_and(|(name, _)| Self::is_cache_file_name(name))
    }

    /// `<32 or 64 hex digits>.kcp`, `.kpp` or `.stamp`: how the cache names its files.
    fn is_cache_file_name(name: &str) -> bool {
        let Some((stem, ext)) = name.split_once('.') else { return false };
        (stem.len() == 32 || stem.len() == 64)
            && stem.bytes().all(|b| b.is_ascii_hexdigit())
            && [PACK_EXTENSION, RECORD_EXTENSION, codec::DICT_EXTENSION, "stamp"].contains(&ext)
    }

    /// Whether the file at `path` is one Kiln wrote into a cache: a pack or a record with its
    /// magic bytes, a stamp in its format, a temporary file named after one of those. Only
    /// these are ever counted, evicted or cleared; anything else in the folder is left alone.
    fn is_own(path: &Path) -> bool {
        use std::io::Read;
        if Self::is_temporary(path) {
            return true;
        }
        let Some(name) = path.file_name().and_then(|n| n.to_str()) else { return false };
        let Some((stem, ext)) = name.split_once('.') else { return false };
        if !(stem.len() == 32 || stem.len() == 64) || !stem.bytes().all(|b| b.is_ascii_hexdigit()) {
            return false;
        }
        let mut head = [0u8; 65];
        let n = match crate::archive::input::open_regular(path).and_then(|(mut f, _)| f.read(&mut head)) {
            Ok(n) => n,
            Err(_) => return false,
        };
        let head = &head[..n];
        match ext {
            PACK_EXTENSION => head.starts_with(PACK_MAGIC),
            RECORD_EXTENSION => head.starts_with(RECORD_MAGIC),
            codec::DICT_EXTENSION => head.starts_with(codec::DICT_MAGIC),
            "stamp" => n == 65 && head[..64].iter().all(u8::is_ascii_hexdigit) && head[64] == b'\n',
            _ => false,
        }
    }

    /// The keys of the pack at `path` (none when it is damaged or gone).
    fn pack_keys(path: &Path) -> Vec<Key> {
        match open_pack(path) {
            Ok(Some((_, rows))) => rows.into_iter().map(|r| r.0).collect(),
            _ => Vec::new(),
        }
    }

    pub fn stats(&self) -> Stats {
        let mut s = Stats::default();
        let mut keys = HashSet::new();
        for (path, meta) in self.files().filter(|(p, _)| Self::is_own(p)) {
            if Self::is_pack(&path) {
                s.packs += 1;
                s.bytes += meta.len();
                let Ok(Some((pack, rows))) = open_pack(&path) else { continue };
                for (key, offset, len) in rows {
                    if !keys.insert(key) {
                        continue;
                    }
                    // The raw size from the entry's header (version 3), else its length.
                    let mut header = [0u8; codec::HEADER];
                    let read = len >= codec::HEADER as u64 && pack.file.read_exact_at(&mut header, offset).is_ok();
                    s.raw += read.then(|| codec::raw_len(&header)).flatten().unwrap_or(len);
                    s.stored += len;
                }
            } else if Self::is_dictionary(&path) {
                s.dictionaries += 1;
                s.dictionary_bytes += meta.len();
                s.bytes += meta.len();
            } else if Self::is_record(&path) {
                s.records += 1;
                s.bytes += meta.len();
            } else if Self::is_temporary(&path) {
                s.temporaries += 1;
            }
        }
        s.entries = keys.len() as u64;
        s
    }

    /// Evicts the least recently used packs and records until they take at most
    /// `max_bytes`; removes temporary files older than a minute (left by interrupted
    /// writes).
    pub fn gc(&self, max_bytes: u64) -> GcReport {
        let mut files = Vec::new();
        let now = SystemTime::now();
        for (path, meta) in self.files().filter(|(p, _)| Self::is_own(p)) {
            if Self::is_temporary(&path) {
                let age = meta.modified().ok().and_then(|m| now.duration_since(m).ok()).unwrap_or_default();
                if age.as_secs() >= 60 || crate::output::is_stale_temporary(&path) {
                    let _ = fs::remove_file(&path);
                }
            } else if Self::is_pack(&path) || Self::is_record(&path) {
                files.push((meta.modified().unwrap_or(SystemTime::UNIX_EPOCH), meta.len(), path));
            }
        }
        files.sort();
        let mut total: u64 = files.iter().map(|e| e.1).sum();
        let mut report = GcReport::default();
        let mut removed_keys = HashSet::new();
        let mut kept_keys = HashSet::new();
        for (_, len, path) in &files {
            let pack = Self::is_pack(path);
            if total > max_bytes {
                let keys = if pack { Self::pack_keys(path) } else { Vec::new() };
                if fs::remove_file(path).is_ok() {
                    total -= len;
                    if pack {
                        report.removed_packs += 1;
                        removed_keys.extend(keys);
                    } else {
                        report.removed_records += 1;
                    }
                    report.freed += len;
                    continue;
                }
            }
            if pack {
                kept_keys.extend(Self::pack_keys(path));
            }
        }
        report.removed = removed_keys.difference(&kept_keys).count() as u64;
        report.kept = kept_keys.len() as u64;
        report.kept_bytes = total;
        // This `Cache`'s index may name removed packs: read it again on next use.
        *self.index.write().expect("no panics while locked") = None;
        report
    }

    /// Removes every pack, record, archive stamp and temporary file Kiln wrote (checked by
    /// name and header, see `is_own`: nothing else in the folder is touched); returns how
    /// many distinct entries were removed.
    pub fn clear(&self) -> Result<u64, Error> {
        let mut keys = HashSet::new();
        for (path, _) in self.files().filter(|(p, _)| Self::is_own(p)) {
            if Self::is_pack(&path) {
                keys.extend(Self::pack_keys(&path));
            }
            match fs::remove_file(&path) {
                Ok(()) => {}
                Err(e) if e.kind() == io::ErrorKind::NotFound => {}
                Err(source) => return Err(Error { path: path.clone(), source }),
            }
        }
        *self.index.write().expect("no panics while locked") = None;
        self.dicts.reset();
        Ok(keys.len() as u64)
    }
}

/// A set of preprocessing records, if `bytes` is a whole one.
/// The body of a records file (magic, blake3 of the body, body), when whole.
fn records_body(mut bytes: Vec<u8>) -> Option<Vec<u8>> {
    if bytes.len() < 40 || &bytes[..8] != RECORD_MAGIC || blake3::hash(&bytes[40..]).as_bytes() != &bytes[8..40] {
        return None;
    }
    bytes.drain(..40);
    Some(bytes)
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

/// Opens the pack at `path` and reads its index: `Ok(None)` when the file is gone,
/// `Err(why)` when it is not a whole pack of this Kiln.
fn open_pack(path: &Path) -> Result<Option<(Pack, Vec<(Key, u64, u64)>)>, String> {
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
    let count = u64::from_le_bytes(header[8..16].try_into().unwrap());
    let rows_len =
        count.checked_mul(ROW as u64).filter(|&n| PACK_HEADER as u64 + n <= size).ok_or("truncated index")?;
    let mut rows = vec![0u8; rows_len as usize];
    file.read_exact_at(&mut rows, PACK_HEADER as u64).map_err(|_| "truncated index".to_string())?;
    if blake3::hash(&rows).as_bytes() != &header[16..48] {
        return Err("index checksum mismatch".into());
    }
    let rows = rows
        .chunks_exact(ROW)
        .map(|r| {
            let key = Key(r[..32].try_into().unwrap());
            (key, u64::from_le_bytes(r[32..40].try_into().unwrap()), u64::from_le_bytes(r[40..48].try_into().unwrap()))
        })
        .collect();
    let modified = meta.modified().unwrap_or(SystemTime::UNIX_EPOCH);
    Ok(Some((Pack { path: path.to_path_buf(), file, modified, touched: AtomicBool::new(false) }, rows)))
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

// Entry layout: MAGIC, blake3(body) (32 bytes), body.
// body: key (32), artifact count (u32), per artifact: target name length (u8) + name, length
// (u64) + bytes; then the reflection as JSON (u64 length + bytes).
/// The small framing pieces of an entry's body: the artifact count, one frame per artifact
/// (target name and length), the reflection's length and the reflection.
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
/// (as a pack holds it). The value's checksum guards against damage and truncation (not
/// against a hostile server, which could write any value under any key whatever the hash):
/// one pass of a non-cryptographic hash over a whole buffer, which a fill checks about ten
/// times faster than a blake3 (a blake3 of the 130 MB of a 10k set's entries was a fifth of
/// a warm-remote build's CPU). The entry's own checksum (blake3) is checked when the entry
/// is used.
fn remote_value(key: &Key, c: &Compiled, hashes: &[blake3::Hash]) -> Vec<u8> {
    let entry = codec::encode(key, c, hashes, &HashMap::new());
    let mut out = Vec::with_capacity(REMOTE_HEADER + entry.len());
    out.extend_from_slice(REMOTE_MAGIC);
    out.extend_from_slice(&[0; REMOTE_HEADER - 8]);
    out.extend_from_slice(&entry);
    let sum = remote_checksum(key, &out[REMOTE_HEADER..]);
    out[8..REMOTE_HEADER].copy_from_slice(&sum);
    out
}

/// The checksum of a remote value: xxh3-128 of `key` then `entry`.
fn remote_checksum(key: &Key, entry: &[u8]) -> [u8; 16] {
    let mut h = xxhash_rust::xxh3::Xxh3::new();
    h.update(&key.0);
    h.update(entry);
    h.digest128().to_le_bytes()
}

/// The entry of a whole remote `value` of `key` ([`remote_value`]): its checksum matches and
/// it is an entry of `key` (magic, length and key; its own checksum is not checked here).
fn remote_entry<'a>(key: &Key, value: &'a [u8]) -> Result<&'a [u8], String> {
    if value.len() < REMOTE_HEADER || (&value[..8] != REMOTE_MAGIC && &value[..8] != REMOTE_MAGIC_V2) {
        return Err("not a remote cache entry of this kiln".into());
    }
    let entry = &value[REMOTE_HEADER..];
    if remote_checksum(key, entry) != value[8..REMOTE_HEADER] {
        return Err("checksum mismatch".into());
    }
    if entry.len() < 72 || (&entry[..8] != MAGIC && &entry[..8] != codec::MAGIC) || entry[40..72] != key.0 {
        return Err("the entry belongs to another key".into());
    }
    Ok(entry)
}

/// A version 2 entry (uncompressed), checked.
fn decode_v2(key: &Key, bytes: &[u8]) -> Result<Compiled, String> {
    decode_v2_hashed(key, bytes).map(|(c, _)| c)
}

/// [`decode_v2`], and the blake3 of each artifact.
fn decode_v2_hashed(key: &Key, bytes: &[u8]) -> Result<(Compiled, Vec<blake3::Hash>), String> {
    let (artifacts, json) = parse(key, bytes)?;
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

fn parse<'a>(key: &Key, bytes: &'a [u8]) -> Result<Parsed<'a>, String> {
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
    let mut artifacts = Vec::new();
    for _ in 0..count {
        let frame = r.at;
        let n = r.take(1)?[0] as usize;
        let name = r.take(n)?;
        let len = r.u64()? as usize;
        h.update(&body[frame..r.at]);
        let artifact = r.take(len)?;
        let hash = blake3::hash(artifact);
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
}

#[cfg(test)]
mod tests;
