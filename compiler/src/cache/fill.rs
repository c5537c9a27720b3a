//! Remote hits written into the local cache as they arrive: a pack streamed to disk.

use std::fs;
use std::io;
use std::os::unix::fs::{FileExt, OpenOptionsExt};
use std::os::unix::io::AsRawFd;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Mutex;

use super::{Key, PACK_EXTENSION, PACK_HEADER, PACK_MAGIC, ROW};

/// A pack written entry by entry as checked remote entries arrive, so that a fill holds at
/// most a few [`CHUNK`]s of entries in memory: room for `capacity` index rows is left after
/// the header, the entries follow from the next page on, gathered into page-aligned chunks
/// written whole, each chunk's rows written with it in the room left for them (in the order
/// the chunks were placed, hashed as they go: the rows of a large fill are never whole in
/// memory), and the header is written last. Rows left unused (keys the
/// remote lacked) stay a hole between the index and the first entry, and each chunk starts
/// on a page: readers never look between entries (rows give absolute offsets). The file is
/// a temporary one of the cache folder (named as [`crate::output`] names them, after a
/// pack, and locked while written, so that a writer that dies leaves a file the next
/// `open`, `gc` or `clear` removes) and is renamed, named by its content, once whole.
/// Several threads push at once: each copies its entry into one of [`SLOTS`] chunks (the
/// first free one), so that the copies run side by side; the thread that fills a chunk
/// takes its place in the file and its rows under one short lock and writes it outside.
/// Entries are written in chunks of at least this size, page-aligned: ext4 takes several
/// times the system time for entry-sized writes across pages as for large aligned ones,
/// and these writes were a large share of a warm-remote build's CPU.
const CHUNK: usize = 1 << 20;
const PAGE: u64 = 4096;
/// Chunks filled at once (one copy each; a fill runs on 4 connections).
const SLOTS: usize = 4;

pub(super) struct FillPack {
    dir: PathBuf,
    tmp: PathBuf,
    file: fs::File,
    capacity: usize,
    /// Entries taken (at most `capacity`).
    taken: AtomicUsize,
    slots: [Mutex<Slot>; SLOTS],
    /// The next slot to try first.
    next: AtomicUsize,
    rows: Mutex<Rows>,
    /// Chunk buffers written and free for reuse (a fresh buffer per chunk would fault in
    /// every page of the fill once more).
    spare: Mutex<Vec<Vec<u8>>>,
    /// A write failed: the pack is not finished.
    failed: AtomicBool,
    /// Renamed into place.
    finished: bool,
}

/// A chunk being filled: its entries' bytes, and each one's key, length and checksum.
#[derive(Default)]
struct Slot {
    bytes: Vec<u8>,
    entries: Vec<(Key, u64, [u8; 32])>,
}

struct Rows {
    /// Rows placed so far (written, or being written, after the header in this order).
    count: usize,
    /// The blake3 of those rows, for the header.
    hash: blake3::Hasher,
    /// Where the next chunk goes (page-aligned).
    offset: u64,
    /// The entries' checksums, for the pack's name.
    checksums: blake3::Hasher,
}

impl FillPack {
    /// A new pack in `dir` with room for `capacity` entries.
    pub fn create(dir: &Path, capacity: usize) -> io::Result<FillPack> {
        use std::sync::atomic::AtomicU64;
        static COUNTER: AtomicU64 = AtomicU64::new(0);
        let nanos =
            std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos()).unwrap_or(0);
        let n = COUNTER.fetch_add(1, Ordering::Relaxed);
        let pid = std::process::id();
        let stem = blake3::hash(format!("kiln fill {pid} {nanos} {n}").as_bytes()).to_hex();
        let tmp = dir.join(format!(".{}.{PACK_EXTENSION}.{pid}.{}.{n}.tmp", &stem[..32], nanos % 1_000_000_000));
        let file = fs::OpenOptions::new().write(true).read(true).create_new(true).mode(0o644).open(&tmp)?;
        // Held until the file is closed: a cleaner in another pid namespace sees it is alive.
        // SAFETY: flock on a descriptor we own.
        unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
        let capacity = capacity.max(1);
        let first = ((PACK_HEADER + capacity * ROW) as u64).div_ceil(PAGE) * PAGE;
        Ok(FillPack {
            dir: dir.to_path_buf(),
            tmp,
            file,
            capacity,
            taken: AtomicUsize::new(0),
            slots: Default::default(),
            next: AtomicUsize::new(0),
            rows: Mutex::new(Rows {
                count: 0,
                hash: blake3::Hasher::new(),
                offset: first,
                checksums: blake3::Hasher::new(),
            }),
            spare: Mutex::default(),
            failed: AtomicBool::new(false),
            finished: false,
        })
    }

    /// Entries taken so far.
    pub fn len(&self) -> usize {
        self.taken.load(Ordering::Relaxed).min(self.capacity)
    }

    pub fn is_full(&self) -> bool {
        self.len() >= self.capacity
    }

    /// Adds the checked entry `bytes` of `key`, written with its chunk. An error when the
    /// pack is full or a write fails (then the pack is not finished).
    pub fn push(&self, key: &Key, bytes: &[u8]) -> io::Result<()> {
        if bytes.len() < 40 || self.taken.fetch_add(1, Ordering::Relaxed) >= self.capacity {
            return Err(io::Error::other("the fill pack is full"));
        }
        // The first free slot from a rotating start; else wait on that one.
        let start = self.next.fetch_add(1, Ordering::Relaxed);
        let mut slot = (0..SLOTS)
            .find_map(|i| self.slots[(start + i) % SLOTS].try_lock().ok())
            .unwrap_or_else(|| self.slots[start % SLOTS].lock().expect("no panics while locked"));
        if slot.bytes.capacity() == 0 {
            slot.bytes = self.spare.lock().expect("no panics while locked").pop().unwrap_or_default();
            slot.bytes.reserve(CHUNK + bytes.len());
        }
        slot.entries.push((*key, bytes.len() as u64, bytes[8..40].try_into().expect("32 bytes")));
        slot.bytes.extend_from_slice(bytes);
        if slot.bytes.len() < CHUNK {
            return Ok(());
        }
        let full = std::mem::take(&mut *slot);
        drop(slot);
        self.place(full)
    }

    /// Gives the entries of `slot` their place in the file and their rows, and writes both.
    fn place(&self, mut slot: Slot) -> io::Result<()> {
        if slot.entries.is_empty() {
            return Ok(());
        }
        let mut rows = Vec::with_capacity(slot.entries.len() * ROW);
        let (at, first_row) = {
            let mut r = self.rows.lock().expect("no panics while locked");
            let (at, first_row) = (r.offset, r.count);
            let mut offset = at;
            for (key, len, checksum) in &slot.entries {
                rows.extend_from_slice(&key.0);
                rows.extend_from_slice(&offset.to_le_bytes());
                rows.extend_from_slice(&len.to_le_bytes());
                r.checksums.update(checksum);
                offset += len;
            }
            // Hashed in the order of the rows in the file (taken under this lock).
            r.hash.update(&rows);
            r.count += slot.entries.len();
            r.offset = offset.div_ceil(PAGE) * PAGE;
            (at, first_row)
        };
        let written =
            self.write(&slot.bytes, at).and_then(|()| self.write_rows(&rows, (PACK_HEADER + first_row * ROW) as u64));
        slot.bytes.clear();
        self.spare.lock().expect("no panics while locked").push(slot.bytes);
        written
    }

    /// Writes index rows at `at` (within the room left after the header).
    fn write_rows(&self, rows: &[u8], at: u64) -> io::Result<()> {
        self.file.write_all_at(rows, at).inspect_err(|_| self.failed.store(true, Ordering::Relaxed))
    }

    /// Writes `bytes` at `at`, its blocks allocated first: ext4 then takes the chunk's pages
    /// without reserving blocks page by page (less system time). A file
    /// system without `fallocate` just writes.
    fn write(&self, bytes: &[u8], at: u64) -> io::Result<()> {
        // SAFETY: fallocate on a descriptor we own; failing only costs its speed-up.
        unsafe { libc::fallocate(self.file.as_raw_fd(), 0, at as libc::off_t, bytes.len() as libc::off_t) };
        self.file.write_all_at(bytes, at).inspect_err(|_| self.failed.store(true, Ordering::Relaxed))
    }

    /// Writes the header and renames the pack into place; its path (none when
    /// it is empty: nothing is left behind).
    pub fn finish(mut self) -> io::Result<Option<PathBuf>> {
        let path = self.write_index()?;
        self.finished = path.is_some();
        Ok(path)
    }

    fn write_index(&self) -> io::Result<Option<PathBuf>> {
        for slot in &self.slots {
            let rest = std::mem::take(&mut *slot.lock().expect("no panics while locked"));
            self.place(rest)?;
        }
        if self.failed.load(Ordering::Relaxed) {
            return Err(io::Error::other("an entry could not be written"));
        }
        let r = self.rows.lock().expect("no panics while locked");
        if r.count == 0 {
            return Ok(None);
        }
        let rows_hash = r.hash.finalize();
        let mut head = Vec::with_capacity(PACK_HEADER);
        head.extend_from_slice(PACK_MAGIC);
        head.extend_from_slice(&(r.count as u64).to_le_bytes());
        head.extend_from_slice(rows_hash.as_bytes());
        self.file.write_all_at(&head, 0)?;
        let mut name = blake3::Hasher::new();
        name.update(rows_hash.as_bytes());
        name.update(r.checksums.finalize().as_bytes());
        let path = self.dir.join(format!("{}.{PACK_EXTENSION}", &name.finalize().to_hex()[..32]));
        fs::rename(&self.tmp, &path)?;
        Ok(Some(path))
    }
}

impl Drop for FillPack {
    /// A pack not finished (or whose finishing failed) leaves nothing behind.
    fn drop(&mut self) {
        if !self.finished {
            let _ = fs::remove_file(&self.tmp);
        }
    }
}

impl std::fmt::Debug for FillPack {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FillPack").field("tmp", &self.tmp).field("entries", &self.len()).finish()
    }
}
