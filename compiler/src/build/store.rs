//! Store: the build's one door to the cache. Lookups of compiled keys, the compiled entries
//! streamed into packs (one pack per [`PACK_BYTES`] of artifacts, written as the build
//! goes, so that no pack holds the whole build in memory), preprocessing records, the
//! archive's up-to-date stamp, and the archive in the remote cache: stored there under the
//! build's fingerprint when the build writes it, taken from there (with every entry copied
//! into the local cache) instead of assembling when the local cache is fresh.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;
use std::thread::JoinHandle;

use super::{CacheDir, Error, Options};
use crate::cache::{Cache, Held, Key, Lookup, Packing};
use crate::compile::Compiled;
use crate::permute::Config;

/// Artifact bytes gathered before a pack is written. They wait in memory (with their
/// encoding while the pack is written), and a large set always has a pack's worth waiting,
/// so a smaller pack lowers the peaks of the preprocessing, group and compile stages; the
/// cost is more, smaller packs in the cache folder.
const PACK_BYTES: usize = 2 << 20;

// A build whose compiled entries all fit one pack (less than [`PACK_BYTES`] of artifacts,
// written when the build ends) stores them uncompressed ([`Packing::Stored`]): on a set of
// about a hundred sources, compressing them was a large share of what the build costs beyond
// naga's own work, for a cache of a few megabytes either way. Any larger build compresses
// every pack, so a large cache stays compressed.

/// A key looked up in the cache.
pub(super) enum Fetched {
    /// The entry, with the blake3 of each artifact (checked against the entry's checksum).
    Hit(Compiled, Vec<blake3::Hash>),
    /// The entry without its artifacts' bytes, which the archive being replaced holds.
    Held(Held),
    /// Not there (or not usable): the warning when the entry was corrupted.
    Miss(Option<String>),
}

/// The cache of a build (or none, with `--no-cache`).
pub(super) struct Store {
    cache: Option<Cache>,
    /// Artifact bytes gathered before a pack is written ([`PACK_BYTES`]).
    pack_bytes: usize,
    pending: Mutex<Pending>,
    /// Whether a pack was written before the build's end (its packs are then compressed).
    packed: AtomicBool,
    /// Packs that could not be written: (entries, why); (0, warning) for a corrupted
    /// remote archive.
    failed: Mutex<Vec<(usize, String)>>,
    /// Why there is no cache, when one was asked for but its folder cannot be made.
    unavailable: Option<String>,
    /// Whether the preprocessing records came from the remote cache ([`Store::records`]).
    records_from_remote: AtomicBool,
    /// The fill started by [`Store::prefill`], once joined: its keys (sorted), whether each
    /// is local now, and those it filled (sorted; not yet counted as remote hits).
    prefill: Mutex<Option<JoinHandle<Prefilled>>>,
}

/// What the fill of [`Store::prefill`] did: its keys (sorted), whether each is local now,
/// which it filled (a bit a key, by place: see [`Cache::prefill_from_remote`]).
type Prefilled = (Vec<Key>, bool, Vec<u64>);

#[derive(Default)]
struct Pending {
    entries: Vec<(Key, Compiled, Vec<blake3::Hash>)>,
    bytes: usize,
}

/// `cache` with the remote cache of `options` under it, refusing values larger than any
/// this build can store ([`value_limit`]).
fn with_remote(cache: Cache, options: &Options, config: &Config) -> Result<Cache, Error> {
    let remote = crate::cache::remote::Options::resolve(&options.remote_cache, options.remote_cache_mode)
        .and_then(|o| o.map(|o| crate::cache::Remote::open(&o)).transpose())
        .map_err(|e| Error::Config(format!("error: {e}")))?;
    Ok(match remote {
        Some(r) => {
            r.limit_values(value_limit(config));
            cache.with_remote(r)
        }
        None => cache,
    })
}

/// The largest remote value this build reads, from its own figures with a wide margin:
/// 32 MiB, plus 256 bytes per byte of its shaders' sources (an entry's artifacts and
/// reflection come to a few times its preprocessed text), plus 256 bytes per permutation
/// it may have (a record is 64 bytes; an archive's index rows are smaller). An archive is
/// far smaller than this (a fraction of its entries).
fn value_limit(config: &Config) -> u64 {
    let mut sources: Vec<&Path> = config.shaders.iter().map(|s| s.source_path.as_path()).collect();
    sources.sort_unstable();
    sources.dedup();
    let source_bytes: u64 = sources.iter().filter_map(|p| std::fs::metadata(p).ok()).map(|m| m.len()).sum();
    let permutations = config.shaders.iter().fold(0u64, |n, s| {
        let each = s.dimensions.iter().fold(s.levels.len() as u64, |m, d| m.saturating_mul(d.values.len() as u64));
        n.saturating_add(each)
    });
    (32u64 << 20).saturating_add(source_bytes.saturating_mul(256)).saturating_add(permutations.saturating_mul(256))
}

impl Store {
    pub fn open(options: &Options, config: &Config) -> Result<Store, Error> {
        let dir = match &options.cache {
            CacheDir::Disabled => None,
            CacheDir::Dir(d) => Some(d.clone()),
            CacheDir::Auto => Some(default_cache_dir(&config.dir)),
        };
        // A cache folder that cannot be made costs only speed, like an unwritable one.
        // The build never looks up what it compiles: its puts stay out of the index.
        let (cache, unavailable) = match dir.map(|d| Cache::open(d).map(Cache::without_indexing_puts)) {
            None => (None, None),
            Some(Ok(c)) => (Some(with_remote(c, options, config)?), None),
            Some(Err(e)) => (None, Some(format!("warning: {e}; building without a cache"))),
        };
        Ok(Store {
            cache,
            pack_bytes: PACK_BYTES,
            pending: Mutex::default(),
            packed: AtomicBool::new(false),
            failed: Mutex::default(),
            unavailable,
            records_from_remote: AtomicBool::new(false),
            prefill: Mutex::default(),
        })
    }

    /// The remote cache's counts (zero without one).
    pub fn remote_stats(&self) -> crate::cache::remote::Stats {
        self.cache.as_ref().and_then(Cache::remote).map(|r| r.stats()).unwrap_or_default()
    }

    /// Whether there is a cache.
    pub fn enabled(&self) -> bool {
        self.cache.is_some()
    }

    pub fn get(&self, key: &Key) -> Fetched {
        self.get_unless_held(key, &|_| false)
    }

    /// [`Store::get`], or [`Fetched::Held`] for an entry whose artifacts all satisfy `held`
    /// ([`Cache::get_unless_held`]).
    pub fn get_unless_held(&self, key: &Key, held: &dyn Fn(&blake3::Hash) -> bool) -> Fetched {
        match self.cache.as_ref().map(|c| c.get_unless_held(key, held)) {
            Some(Lookup::Hit(c, hashes)) => Fetched::Hit(c, hashes),
            Some(Lookup::Held(h)) => Fetched::Held(h),
            Some(Lookup::Corrupt(why)) => Fetched::Miss(Some(format!("warning: {why}"))),
            Some(Lookup::Miss) | None => Fetched::Miss(None),
        }
    }

    /// Stores a compiled key (with the blake3 of each artifact); written with the next pack.
    pub fn put(&self, key: Key, compiled: Compiled, hashes: Vec<blake3::Hash>) {
        if self.cache.is_none() {
            return;
        }
        let full = {
            let mut p = self.pending.lock().expect("no panics while locked");
            p.bytes += compiled.artifacts.iter().map(|(_, b)| b.len()).sum::<usize>();
            p.entries.push((key, compiled, hashes));
            if p.bytes >= self.pack_bytes {
                Some(std::mem::take(&mut *p))
            } else {
                None
            }
        };
        if let Some(p) = full {
            self.packed.store(true, Ordering::Relaxed);
            self.write(p, Packing::Compressed);
        }
    }

    fn write(&self, pending: Pending, packing: Packing) {
        let Some(c) = &self.cache else { return };
        let entries: Vec<(Key, &Compiled, &[blake3::Hash])> =
            pending.entries.iter().map(|(k, c, h)| (*k, c, &h[..])).collect();
        if let Err(e) = c.put_pack_hashed(&entries, packing) {
            self.failed.lock().expect("no panics while locked").push((entries.len(), e.to_string()));
        }
    }

    /// Writes what is pending; gives the cache's warnings (damaged packs, packs not written).
    pub fn finish(&self) -> Vec<String> {
        self.wait_prefill(std::iter::empty());
        let pending = std::mem::take(&mut *self.pending.lock().expect("no panics while locked"));
        // The only pack of the build: a small build's (see `PACK_BYTES`).
        let packing = if self.packed.load(Ordering::Relaxed) { Packing::Compressed } else { Packing::Stored };
        self.write(pending, packing);
        let mut warnings = self.cache.as_ref().map(|c| c.warnings()).unwrap_or_default();
        // The build looks nothing up past here, nor writes an entry: the index and what
        // compresses entries need not stay while the archive is written.
        if let Some(c) = &self.cache {
            c.release_index();
            c.release_compression();
        }
        warnings.extend(self.unavailable.clone());
        for (n, why) in self.failed.lock().expect("no panics while locked").drain(..) {
            // n == 0: a remote archive's warning, whole.
            warnings.push(if n == 0 { why } else { format!("warning: cannot store {n} cache entries: {why}") });
        }
        warnings
    }

    /// Copies into the local cache the entries of `keys` that the remote cache holds and
    /// the local one lacks, fetched in batches (redis MGET, parallel HTTP GETs) rather than
    /// one round trip per key as the compile stage would. A shard's share, before it compiles.
    pub fn prefetch(&self, keys: &[Key]) {
        if let Some(c) = self.cache.as_ref().filter(|c| c.remote().is_some()) {
            c.fill_from_remote(keys);
        }
    }

    /// Starts copying into the local cache the entries of `keys()` that the remote cache
    /// holds and the local one lacks, on a thread of its own (see [`Cache::fill_from_remote`]),
    /// when the preprocessing records came from the remote: a local cache that never built
    /// this configuration, whose build's keys are most likely those of the records (the
    /// last build's). The build matches its permutations to the records meanwhile; the fill
    /// of [`Store::archive_from_remote`] waits on this one and asks only for what it did
    /// not cover, and the compile stage waits on it before it looks keys up
    /// ([`Store::wait_prefill`]). Remote hits count the keys it filled that the build uses.
    pub fn prefill(&self, keys: impl FnOnce() -> Vec<Key>) {
        let Some(cache) = self.cache.as_ref().filter(|c| c.remote().is_some()) else { return };
        if !self.records_from_remote.load(Ordering::Relaxed) {
            return;
        }
        let mut keys = keys();
        if keys.is_empty() {
            return;
        }
        // Made from a row a permutation, each key once: held through the fill at its length.
        keys.shrink_to_fit();
        let cache = cache.clone();
        let fill = move || {
            let (complete, filled) = cache.prefill_from_remote(&keys);
            (keys, complete, filled)
        };
        // A thread that cannot start only costs the overlap: the later fill asks for all.
        *self.prefill.lock().expect("no panics while locked") =
            std::thread::Builder::new().name("kiln-prefill".into()).spawn(fill).ok();
    }

    /// Waits for the fill of [`Store::prefill`], if one runs, and counts the keys it filled
    /// among `used` (the build's keys, each once) as remote hits.
    pub fn wait_prefill(&self, used: impl Iterator<Item = Key>) {
        let _ = self.prefilled(used);
    }

    /// Waits for the fill of [`Store::prefill`] and counts the keys it filled among `used`
    /// (each once) as remote hits: whether its keys were exactly `used`, and whether each
    /// is in the local cache now. `None` when none ran (or it panicked).
    fn prefilled(&self, used: impl Iterator<Item = Key>) -> Option<(bool, bool)> {
        let handle = self.prefill.lock().expect("no panics while locked").take()?;
        let (keys, complete, filled) = handle.join().ok()?;
        let (mut used_n, mut known, mut hits) = (0, 0, 0);
        for key in used {
            used_n += 1;
            if let Ok(i) = keys.binary_search(&key) {
                known += 1;
                hits += filled[i / 64] >> (i % 64) & 1;
            }
        }
        if let Some(remote) = self.cache.as_ref().and_then(Cache::remote) {
            remote.count_hits(hits);
        }
        // Each key once on both sides: as many keys, each one of `keys`, are `keys`.
        Some((used_n == keys.len() && known == used_n, complete))
    }

    /// The encoded preprocessing records stored under `key` (none without a cache): the
    /// local file, opened to be read in place, else the remote cache's body.
    pub fn records(&self, key: &Key) -> Option<super::records::Stored> {
        let cache = self.cache.as_ref()?;
        if let Some((file, at, len)) = cache.open_local_records(key) {
            self.records_from_remote.store(false, Ordering::Relaxed);
            return Some(super::records::Stored::File { file, at, len });
        }
        // The remote's, streamed into the local file and read in place like a local one
        // (held in memory only when the local file cannot be written).
        match cache.fetch_remote_records(key) {
            Some(false) => return None,
            Some(true) => {
                if let Some((file, at, len)) = cache.open_local_records(key) {
                    self.records_from_remote.store(true, Ordering::Relaxed);
                    return Some(super::records::Stored::File { file, at, len });
                }
            }
            None => {}
        }
        let (body, remote) = cache.get_records_found(key)?;
        self.records_from_remote.store(remote, Ordering::Relaxed);
        Some(super::records::Stored::Bytes(body))
    }

    /// The records file under `key` in the local cache only.
    pub fn local_records(&self, key: &Key) -> Option<Vec<u8>> {
        self.cache.as_ref()?.get_local_records_bytes(key)
    }

    /// Replaces the records file under `key` in the local cache only; failing to only costs
    /// preprocessing next time.
    pub fn put_local_records(&self, key: &Key, records: &[u8]) {
        if let Some(c) = &self.cache {
            let _ = c.put_local_records_bytes(key, records);
        }
    }

    /// Whether there is a remote cache to share records through.
    pub fn has_remote(&self) -> bool {
        self.cache.as_ref().is_some_and(|c| c.remote().is_some())
    }

    /// The records under `key` in the remote cache only (a piece of a shard's records).
    pub fn remote_records(&self, key: &Key) -> Option<Vec<u8>> {
        self.cache.as_ref()?.get_remote_records_bytes(key)
    }

    /// Stores records under `key` in the remote cache only; failing to only costs another
    /// shard preprocessing them.
    pub fn put_remote_records(&self, key: &Key, body: &[u8]) {
        if let Some(c) = self.cache.as_ref().filter(|c| c.remote_writes()) {
            c.put_remote_records_bytes(key, body);
        }
    }

    /// Replaces the records under `key`; failing to only costs preprocessing next time.
    pub fn put_records(&self, key: &Key, records: &super::records::Encoded) {
        if let Some(c) = &self.cache {
            let _ = c.put_records_streamed(key, records.len(), &|f| records.each_piece(f));
        }
    }

    /// The artifact counts of the archive at `out` if it is the output of the build with
    /// `fingerprint` and the cache still holds every key.
    pub fn fresh_archive(
        &self,
        out: &Path,
        fingerprint: &dyn Fn() -> blake3::Hash,
        keys: &mut dyn Iterator<Item = Key>,
    ) -> Option<(usize, usize)> {
        self.cache.as_ref()?.fresh_archive(out, fingerprint, keys)
    }

    /// Records that `out` is the output of the build with `fingerprint`, and stores it in
    /// the remote cache (in read-write mode) with the bundle of the build's entries (see
    /// [`Cache::put_bundle`]). Failing to only costs a full warm build next time.
    pub fn stamp_archive(&self, out: &Path, fingerprint: &blake3::Hash, counts: (usize, usize)) {
        let Some(c) = &self.cache else { return };
        let _ = c.stamp_archive(out, fingerprint, counts);
        if let Some(remote) = c.remote().filter(|r| r.writes()) {
            // A regular file only (not `-o /dev/null`), streamed from the file: held whole,
            // the archive and its copies were most of a warm build's memory.
            if let Ok(source) = RemoteArchive::open(out, counts) {
                remote.store_from(&remote_archive_key(fingerprint), &source);
            }
            // Every key's entry is in the local cache now: the bundle of the build's keys
            // (with HTTP), for the next fresh local cache.
            c.put_bundle();
        }
    }

    /// With a remote cache holding the archive of the build with `fingerprint` and every
    /// entry of the `count` keys that `key` numbers (a closure, not grouping's table: the
    /// store sits below grouping): the entries copied into the local cache (each checked),
    /// the archive (checked) written to `out` and stamped; its artifact counts. `None`
    /// otherwise: the entries the remote holds are in the local cache all the same (fetched
    /// in batches), and those it lacks are not asked for again, for the compile stage that
    /// follows.
    ///
    /// The archive's bytes depend only on the configuration and the keys (the build is
    /// deterministic), and `fingerprint` hashes both: an archive stored under it by any
    /// machine is the one this build would write. What this saves is assembling: training
    /// the dictionaries and compressing every artifact again.
    ///
    /// The steps overlap: a thread of its own hashes the fingerprint, fetches the archive,
    /// checks it and writes it to a temporary file beside `out` while the build's workers
    /// fetch the entries; the file is renamed into place (and stamped) only once every
    /// entry is local, else removed. (A stream output, such as a FIFO, is written only
    /// then.)
    pub fn archive_from_remote<'k>(
        &self,
        out: &Path,
        fingerprint: &(dyn Fn() -> blake3::Hash + Sync),
        keys: &dyn Fn() -> Box<dyn Iterator<Item = Key> + 'k>,
    ) -> Option<(usize, usize)> {
        let cache = self.cache.as_ref()?;
        let remote = cache.remote()?;
        let (tell, filled) = std::sync::mpsc::channel::<bool>();
        std::thread::scope(|s| {
            let taker = s.spawn(move || {
                let fingerprint = fingerprint();
                let complete = || match filled.recv() {
                    Ok(true) => Ok(()),
                    _ => Err(std::io::Error::other("not every entry is in the remote cache")),
                };
                self.take_remote_archive(remote, out, &fingerprint, complete)
            });
            // The prefill's keys are this build's when every permutation matched a record
            // (the records' keys, each once): then nothing is left to ask for. Else the keys
            // it did not bring are asked for once it is done.
            // The keys are copied only for that fill (they grow with the set, and grouping,
            // where this runs, peaks).
            let complete = match self.prefilled(keys()) {
                Some((true, complete)) => complete,
                _ => cache.fill_from_remote(&keys().collect::<Vec<_>>()),
            };
            // The taker may have stopped already (no archive): nobody to tell.
            let _ = tell.send(complete);
            let counts = taker.join().ok().flatten()?;
            // Bundle parts found missing or damaged, stored again from the entries now local
            // (in read-write mode).
            cache.put_bundle();
            Some(counts)
        })
    }
}

impl Store {
    /// [`Store::archive_from_remote`]'s fetch: the remote archive of the build with
    /// `fingerprint` streamed into a temporary file beside `out` (checked as it arrives),
    /// stamped, and renamed into place once `complete` says every entry is local. Into an
    /// unlinked temporary file first when `out` is a stream, which is written only then.
    fn take_remote_archive(
        &self,
        remote: &crate::cache::Remote,
        out: &Path,
        fingerprint: &blake3::Hash,
        complete: impl FnOnce() -> std::io::Result<()>,
    ) -> Option<(usize, usize)> {
        let cache = self.cache.as_ref()?;
        let key = remote_archive_key(fingerprint);
        let fetch = |to: &mut std::fs::File| -> std::io::Result<((usize, usize), blake3::Hash)> {
            let mut value = ArchiveValue::new(to);
            if !remote.get_to(&key, &mut |piece| value.push(piece)) {
                return Err(std::io::Error::other("no archive in the remote cache"));
            }
            value.finish().ok_or_else(|| {
                let why = format!(
                    "warning: the archive {key} in the remote cache {} is corrupted; assembling it again",
                    remote.url()
                );
                self.failed.lock().expect("no panics while locked").push((0, why));
                std::io::Error::other("a corrupted archive")
            })
        };
        let is_stream = std::fs::metadata(out).is_ok_and(|m| !m.is_file());
        let mut counts = None;
        if is_stream {
            let mut spool = tempfile::tempfile().ok()?;
            counts = Some(fetch(&mut spool).ok()?.0);
            crate::output::write_with(out, false, |f, _| {
                complete()?;
                std::io::Seek::seek(&mut spool, std::io::SeekFrom::Start(0))?;
                std::io::copy(&mut spool, f).map(drop)
            })
            .ok()?;
            return counts;
        }
        crate::output::write_with(out, false, |f, _| {
            let (c, content) = fetch(f)?;
            counts = Some(c);
            // Written back now rather than when renamed over an older archive (which ext4
            // then flushes first, at the end of the build).
            // SAFETY: sync_file_range on a descriptor we own; only a hint.
            unsafe {
                use std::os::unix::io::AsRawFd;
                libc::sync_file_range(f.as_raw_fd(), 0, 0, libc::SYNC_FILE_RANGE_WRITE);
            }
            let _ = cache.stamp_archive_file(out, f, content, fingerprint, c);
            complete()
        })
        .ok()?;
        counts
    }
}

/// A remote archive value (see [`RemoteArchive`]) arriving in pieces: its head held, the
/// archive after it written to a file, and both checked at the end.
struct ArchiveValue<'f> {
    to: &'f mut std::fs::File,
    head: Vec<u8>,
    /// Over the counts and the archive, as the head's checksum is.
    sum: blake3::Hasher,
    /// Over the archive alone, for its stamp.
    content: blake3::Hasher,
}

impl<'f> ArchiveValue<'f> {
    fn new(to: &'f mut std::fs::File) -> ArchiveValue<'f> {
        ArchiveValue { to, head: Vec::with_capacity(56), sum: blake3::Hasher::new(), content: blake3::Hasher::new() }
    }

    fn push(&mut self, mut piece: &[u8]) -> std::io::Result<()> {
        if self.head.len() < 56 {
            let take = (56 - self.head.len()).min(piece.len());
            self.head.extend_from_slice(&piece[..take]);
            piece = &piece[take..];
            if self.head.len() < 56 {
                return Ok(());
            }
            self.sum.update(&self.head[40..]);
        }
        // Not an archive value: nothing written, and `finish` says so.
        if &self.head[..8] != REMOTE_ARCHIVE_MAGIC {
            return Ok(());
        }
        self.sum.update(piece);
        self.content.update(piece);
        std::io::Write::write_all(self.to, piece)
    }

    /// The counts and the archive's blake3, if the value was whole.
    fn finish(self) -> Option<((usize, usize), blake3::Hash)> {
        if self.head.len() < 56
            || &self.head[..8] != REMOTE_ARCHIVE_MAGIC
            || self.sum.finalize().as_bytes() != &self.head[8..40]
        {
            return None;
        }
        let count = |at: usize| u64::from_le_bytes(self.head[at..at + 8].try_into().expect("8 bytes")) as usize;
        Some(((count(40), count(48)), self.content.finalize()))
    }
}

impl Drop for Store {
    /// A fill still running (a build that stopped early) ends before the cache goes.
    fn drop(&mut self) {
        self.wait_prefill(std::iter::empty());
    }
}

/// Archives above this size are not stored in the remote cache (below redis's own cap on a
/// value).
const MAX_REMOTE_ARCHIVE: u64 = 256 << 20;
const REMOTE_ARCHIVE_MAGIC: &[u8; 8] = b"KILNAR\0\x01";

/// The remote cache key of the archive of the build with `fingerprint`.
fn remote_archive_key(fingerprint: &blake3::Hash) -> Key {
    let tagged = blake3::hash(&[b"kiln remote archive v1\0".as_slice(), fingerprint.as_bytes()].concat());
    Key::new(&tagged, "", crate::archive::Stage::Compute, "", &crate::compile::Limits::desktop(), &[])
}

/// The remote value of an archive file: magic, blake3 of the rest, the two artifact counts
/// (u64 each), the archive; read from the file each time it is sent.
struct RemoteArchive {
    head: [u8; 56],
    file: std::fs::File,
    len: u64,
}

impl RemoteArchive {
    /// The value of the regular file `path`, at most [`MAX_REMOTE_ARCHIVE`] bytes.
    fn open(path: &Path, counts: (usize, usize)) -> std::io::Result<RemoteArchive> {
        let file = std::fs::File::open(path)?;
        let meta = file.metadata()?;
        if !meta.is_file() || meta.len() > MAX_REMOTE_ARCHIVE {
            return Err(std::io::Error::other("not a regular file of a size the remote cache takes"));
        }
        let mut head = [0u8; 56];
        head[..8].copy_from_slice(REMOTE_ARCHIVE_MAGIC);
        head[40..48].copy_from_slice(&(counts.0 as u64).to_le_bytes());
        head[48..].copy_from_slice(&(counts.1 as u64).to_le_bytes());
        let mut h = blake3::Hasher::new();
        h.update(&head[40..]);
        let len = std::io::copy(&mut std::io::Read::take(&file, meta.len()), &mut h)?;
        head[8..40].copy_from_slice(h.finalize().as_bytes());
        Ok(RemoteArchive { head, file, len })
    }
}

impl crate::cache::remote::Source for RemoteArchive {
    fn len(&self) -> u64 {
        self.head.len() as u64 + self.len
    }

    fn open(&self) -> std::io::Result<Box<dyn std::io::Read + '_>> {
        use std::io::{Read, Seek};
        (&self.file).seek(std::io::SeekFrom::Start(0))?;
        Ok(Box::new(self.head.as_slice().chain((&self.file).take(self.len))))
    }
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
        if let Ok(text) = crate::archive::input::read_regular_to_string(&manifest, 16 << 20) {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::archive::{Reflection, Stage, Target};

    fn compiled(tag: u8, len: usize) -> Compiled {
        let reflection = Reflection {
            entry: "main".into(),
            stage: Stage::Fragment,
            bindings: vec![],
            vertex_inputs: vec![],
            color_outputs: vec![],
            workgroup_size: None,
        };
        Compiled { artifacts: vec![(Target::Wgsl, vec![tag; len])], reflection }
    }

    fn store(dir: &Path, pack_bytes: usize) -> Store {
        Store {
            cache: Some(Cache::open(dir).unwrap()),
            pack_bytes,
            pending: Mutex::default(),
            packed: AtomicBool::new(false),
            failed: Mutex::default(),
            unavailable: None,
            records_from_remote: AtomicBool::new(false),
            prefill: Mutex::default(),
        }
    }

    /// The bytes of the packs in `dir`.
    fn pack_bytes(dir: &Path) -> u64 {
        std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.extension().is_some_and(|x| x == "kcp"))
            .map(|p| std::fs::metadata(p).unwrap().len())
            .sum()
    }

    /// A build whose entries fit one pack stores them uncompressed; one that wrote a pack
    /// before its end compresses its last one too. Both read back whole.
    #[test]
    fn only_a_build_of_one_pack_stores_its_entries_uncompressed() {
        for (pack, compressed) in [(1 << 20, false), (1000, true)] {
            let dir = tempfile::tempdir().unwrap();
            let store = store(dir.path(), pack);
            for i in 0..5u8 {
                let c = compiled(i, 400);
                let hashes = c.artifacts.iter().map(|(_, b)| blake3::hash(b)).collect();
                store.put(Key([i; 32]), c, hashes);
            }
            assert!(store.finish().is_empty());
            // Five artifacts of 400 equal bytes: a compressed pack holds far less.
            assert_eq!(pack_bytes(dir.path()) < 5 * 400, compressed, "pack size {}", pack_bytes(dir.path()));
            for i in 0..5u8 {
                match store.get(&Key([i; 32])) {
                    Fetched::Hit(c, _) => assert_eq!(c, compiled(i, 400)),
                    Fetched::Held(_) => panic!("key {i} held though nothing holds its artifacts"),
                    Fetched::Miss(w) => panic!("key {i} missing: {w:?}"),
                }
                // Its artifacts held elsewhere: the entry's head only, the same description.
                let c = compiled(i, 400);
                match store.get_unless_held(&Key([i; 32]), &|h| c.artifacts.iter().any(|(_, b)| blake3::hash(b) == *h))
                {
                    Fetched::Held(h) => {
                        assert_eq!(h.reflection, c.reflection);
                        let want: Vec<_> =
                            c.artifacts.iter().map(|(t, b)| (*t, b.len() as u64, blake3::hash(b))).collect();
                        assert_eq!(h.artifacts, want);
                    }
                    _ => panic!("key {i} not held"),
                }
            }
        }
    }

    #[test]
    fn packs_are_written_as_the_build_goes() {
        let dir = tempfile::tempdir().unwrap();
        let store = store(dir.path(), 1000);
        let key = |i: u8| Key([i; 32]);
        let packs = || {
            std::fs::read_dir(dir.path())
                .unwrap()
                .filter(|e| e.as_ref().unwrap().path().extension().is_some_and(|x| x == "kcp"))
                .count()
        };
        for i in 0..5u8 {
            let c = compiled(i, 400);
            let hashes = c.artifacts.iter().map(|(_, b)| blake3::hash(b)).collect();
            store.put(key(i), c, hashes);
        }
        // 400 bytes each, a pack per 1000 bytes: the first three make a pack; two are pending.
        assert_eq!(packs(), 1, "one pack once 1000 bytes were pending");
        assert!(store.finish().is_empty());
        assert_eq!(packs(), 2, "the rest at the end");
        for i in 0..5u8 {
            match store.get(&key(i)) {
                Fetched::Hit(c, _) => assert_eq!(c, compiled(i, 400)),
                Fetched::Held(_) => panic!("key {i} held though nothing holds its artifacts"),
                Fetched::Miss(w) => panic!("key {i} missing: {w:?}"),
            }
        }
    }
}
