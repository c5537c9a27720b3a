//! The archive a writer replaces: a blob it already holds is added by reference (its bytes
//! neither spooled nor read back), and its compressed bytes are copied into the new archive
//! where compressing again would give the same bytes, so that a build that rewrites its
//! archive after a small change compresses only what changed.
//!
//! A blob's stored bytes depend only on its raw bytes, the compression level and the
//! dictionary it was compressed with (zstd is deterministic for a given input, parameters
//! and library). So a stored blob is copied only when the previous archive was written by
//! this version of the archive crate in this format, holds the same bytes (its blake3 and
//! length) and was compressed with a dictionary of the same blake3 as the new archive's for
//! its target, or with none when the new archive has none for it. Other referenced blobs
//! (another dictionary, or stored uncompressed: whether zstd shrank them depended on the
//! dictionary their target had then) are decompressed from the previous archive, checked
//! against their blake3, and compressed again.
//!
//! Trust: the table entry of a blob (its blake3, lengths, codec and the check sum of its
//! stored bytes) is covered by the archive's chunk hashes; its stored bytes are checked
//! against that check sum ([`stored_sum`]) when the archive is opened, in one pass over the
//! file (a blob that fails is not found, so the writer's caller spools its bytes as usual),
//! and again when it is copied. A damaged previous archive therefore costs time, never
//! different bytes: the new archive is byte for byte the one a writer without a previous
//! archive writes. Memory holds about 5 bytes a blob: a cell of an index by the first 32
//! bits of its blake3, with its id; a candidate found there is confirmed by the whole blake3
//! of its entry, read from the file (not through the map, whose pages, read out of the
//! order of the file, would stay in the build's resident set), and its length is checked
//! when it is copied.

use std::borrow::Cow;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};

use super::format::{stored_sum, BlobId, Entry, CODEC_ZSTD, CODEC_ZSTD_DICT, ENTRY_LEN, FORMAT_VERSION, NO_DICTIONARY};
use super::{Archive, Target};
use std::fs::File;

/// The previous archive, mapped, and its blobs found by the start of their blake3.
pub(crate) struct Previous {
    archive: Archive,
    /// Each blob whose stored bytes match their check sum, by the first 32 bits of its
    /// blake3: open addressing with linear probing, a cell a `u32` (about 5 bytes a blob,
    /// where 64 bits of each identity and its id took 12), the blob's id plus one in its low
    /// `bits` bits (0: empty) and the rest of those 32 bits above them as a tag. A tag that
    /// matches is a candidate only, confirmed by the whole blake3 in the archive's table.
    cells: Vec<u32>,
    bits: u32,
    /// The archive's file, where a candidate's entry is read to confirm it (a read, not the
    /// map: the map's pages, faulted in out of the file's order with the pages around them,
    /// would stay in the resident set or cost a release every few reads), and where the
    /// blob table starts in it.
    file: File,
    table_start: u64,
    /// Each dictionary's target and blake3, by index.
    dictionaries: Vec<(Target, [u8; 32])>,
    /// Tells this archive's lookups from another's in [`FOUND`] (never 0).
    serial: u64,
}

/// The blobs this thread found last in a previous archive: (its serial, the blob's
/// identity, its id), 0 for none. A build asks whether the previous archive holds each
/// artifact of a cache entry, then adds each by reference, on the same thread: the second
/// lookup is answered here instead of from the index and the archive's table.
struct Found {
    slots: [(u64, u128, u32); FOUND_SLOTS],
    next: usize,
}

/// How many lookups [`Found`] remembers: more than a cache entry has artifacts.
const FOUND_SLOTS: usize = 8;

thread_local! {
    static FOUND: std::cell::RefCell<Found> =
        const { std::cell::RefCell::new(Found { slots: [(0, 0, 0); FOUND_SLOTS], next: 0 }) };
}

/// The serial of the next [`Previous`] opened.
static SERIAL: AtomicU64 = AtomicU64::new(1);

/// A blob of the previous archive as it goes into the new one.
pub(crate) enum Reused<'a> {
    /// Its codec and stored bytes, copied as they are, and their check sum (as the table
    /// keeps it, checked against them).
    Stored(u8, &'a [u8], u64),
    /// Its raw bytes (checked against its blake3), to be compressed again.
    Raw(Cow<'a, [u8]>),
}

/// Bytes read through the map between two releases of its pages (the pages of a mapped
/// file count in the resident set).
const RELEASE_BYTES: u64 = 4 << 20;

/// A blob's identity: the first 16 bytes of its blake3, as the writer's own identities.
fn identity(hash: &[u8; 32]) -> u128 {
    u128::from_be_bytes(hash[..16].try_into().expect("16 of 32 bytes"))
}

/// The first 32 bits of an identity, what the index finds it by (uniform already).
fn prefix(identity: u128) -> u32 {
    (identity >> 96) as u32
}

impl Previous {
    /// The archive at `path` when there is one this crate's version wrote in this format;
    /// `None` otherwise (missing, unreadable, damaged in its header or tables, an older
    /// format without check sums of stored bytes, or another version's).
    pub(crate) fn open(path: &Path) -> Option<Previous> {
        let archive = Archive::open(path).ok()?;
        let file = File::open(path).ok()?;
        if archive.kiln_version() != crate::VERSION || archive.format_version() != FORMAT_VERSION {
            return None;
        }
        let count = archive.blob_count();
        // One pass in the order of the file checks each blob's stored bytes; a second reads
        // the table alone and puts each intact one in the index.
        let mut intact = vec![0u64; count.div_ceil(64)];
        let mut held = 0;
        let read = AtomicU64::new(0);
        for id in 0..count {
            // A damaged table: nothing of it is trusted.
            let (e, bytes) = archive.stored_blob(BlobId(id as u32)).ok()?;
            if stored_sum(bytes) == e.sum {
                intact[id / 64] |= 1 << (id % 64);
                held += 1;
            }
            count_read(&archive, &read, (bytes.len() + ENTRY_LEN) as u64);
        }
        // Fewer than four fifths of the cells full: a probe reads a few cells on average.
        let mut cells = vec![0u32; (held / 4 + 1) * 5];
        // Enough bits for every id plus one.
        let bits = u32::BITS - (count as u32).leading_zeros();
        for id in (0..count).filter(|id| intact[id / 64] & (1 << (id % 64)) != 0) {
            let ident = identity(&archive.stored_blob(BlobId(id as u32)).ok()?.0.hash);
            count_read(&archive, &read, ENTRY_LEN as u64);
            let p = prefix(ident);
            let mut at = home(p, cells.len());
            while cells[at] != 0 {
                at = (at + 1) % cells.len();
            }
            cells[at] = tag(p, bits) | (id as u32 + 1);
        }
        drop(intact);
        let dictionaries = archive.dictionary_hashes();
        // The pages were only read: the file keeps them.
        archive.release_pages();
        let serial = SERIAL.fetch_add(1, Ordering::Relaxed);
        let table_start = archive.table_start();
        Some(Previous { archive, cells, bits, file, table_start, dictionaries, serial })
    }

    /// The id of the blob whose blake3 is `hash` when the archive holds it intact: the
    /// writer may then let go of its bytes and take it from here ([`Previous::reuse`]).
    pub(crate) fn find(&self, hash: &[u8; 32]) -> Option<u32> {
        let ident = identity(hash);
        if let Some(id) = self.remembered(ident) {
            return Some(id);
        }
        let id = self.candidate(ident, |id| self.confirm(id, hash))?;
        FOUND.with(|f| {
            let mut f = f.borrow_mut();
            let next = f.next;
            f.slots[next] = (self.serial, ident, id);
            f.next = (next + 1) % FOUND_SLOTS;
        });
        Some(id)
    }

    /// Whether the archive may hold the blob whose blake3 is `hash`: a candidate in the
    /// index, not confirmed (a few in a thousand that it lacks answer yes: [`Previous::find`]
    /// then finds nothing). A build asks this of each artifact of a cache entry and then
    /// adds the artifacts it has not added yet: those alone are confirmed.
    pub(crate) fn may_hold(&self, hash: &[u8; 32]) -> bool {
        let ident = identity(hash);
        self.remembered(ident).is_some() || self.candidate(ident, |_| true).is_some()
    }

    /// The id this thread found last for `ident` in this archive, if it is remembered.
    fn remembered(&self, ident: u128) -> Option<u32> {
        FOUND.with(|f| f.borrow().slots.iter().find(|s| s.0 == self.serial && s.1 == ident).map(|s| s.2))
    }

    /// The first blob of the index whose tag is `ident`'s that `accept` takes.
    fn candidate(&self, ident: u128, accept: impl Fn(u32) -> bool) -> Option<u32> {
        if self.cells.is_empty() {
            return None;
        }
        let (p, mask) = (prefix(ident), id_mask(self.bits));
        let mut at = home(p, self.cells.len());
        loop {
            match self.cells[at] {
                0 => return None,
                cell if cell & !mask == tag(p, self.bits) && accept((cell & mask) - 1) => {
                    return Some((cell & mask) - 1)
                }
                _ => at = (at + 1) % self.cells.len(),
            }
        }
    }

    /// Whether blob `id`'s blake3 in the archive's table is `hash` (a failed read: no).
    fn confirm(&self, id: u32, hash: &[u8; 32]) -> bool {
        use std::os::unix::fs::FileExt;
        let mut entry = [0u8; ENTRY_LEN];
        let at = self.table_start + u64::from(id) * ENTRY_LEN as u64;
        self.file.read_exact_at(&mut entry, at).is_ok() && Entry::decode(&entry).hash == *hash
    }

    /// Lets go of the index: [`Previous::find`] finds nothing from here on, while the blobs
    /// it found are still taken by id ([`Previous::reuse`]). The index is the largest
    /// table a rewrite holds beyond another build's, and the manifest's stages that follow
    /// the last lookup are a build's peak.
    pub(crate) fn drop_index(&mut self) {
        self.cells = Vec::new();
    }

    /// Blob `id` (one [`Previous::find`] gave) for a new archive whose dictionary for its
    /// target has blake3 `dictionary` (`None`: none): its stored bytes where compressing its
    /// raw bytes again would give them, else its raw bytes; and its blake3. An error when
    /// the previous archive changed since (the writer let go of the bytes), or the blob is
    /// not `len` bytes long (another blob whose blake3 starts the same).
    pub(crate) fn reuse(
        &self,
        id: u32,
        len: u64,
        dictionary: Option<&[u8; 32]>,
    ) -> Result<([u8; 32], Reused<'_>), String> {
        let (entry, bytes) = self.archive.stored_blob(BlobId(id))?;
        if entry.raw_len != len {
            return Err(format!("blob {id} of the previous archive is not the one it was taken for"));
        }
        let same_dictionary = match (entry.codec, dictionary) {
            (CODEC_ZSTD, None) => entry.dictionary == NO_DICTIONARY,
            (CODEC_ZSTD_DICT, Some(d)) => self.dictionaries.get(entry.dictionary as usize).is_some_and(|p| &p.1 == d),
            _ => false,
        };
        if same_dictionary && stored_sum(bytes) == entry.sum {
            return Ok((entry.hash, Reused::Stored(entry.codec, bytes, entry.sum)));
        }
        self.raw(id).map(|raw| (entry.hash, Reused::Raw(raw)))
    }

    /// The raw bytes of blob `id`, decompressed and checked against its blake3.
    pub(crate) fn raw(&self, id: u32) -> Result<Cow<'_, [u8]>, String> {
        self.archive.blob(BlobId(id)).map_err(|why| format!("the previous archive changed during the build: {why}"))
    }

    /// Gives back the previous archive's pages read so far (the file keeps them).
    pub(crate) fn release_pages(&self) {
        self.archive.release_pages();
    }
}

/// Where `prefix`'s probe starts: the prefix scaled onto the table.
fn home(prefix: u32, cells: usize) -> usize {
    ((u64::from(prefix) * cells as u64) >> 32) as usize
}

/// The cell bits above an id's `bits`: the prefix's low bits.
fn tag(prefix: u32, bits: u32) -> u32 {
    prefix.checked_shl(bits).unwrap_or(0)
}

/// The cell bits of an id plus one.
fn id_mask(bits: u32) -> u32 {
    ((1u64 << bits) - 1) as u32
}

/// Counts `len` more bytes read from `archive`'s map, and gives its pages back each
/// [`RELEASE_BYTES`].
fn count_read(archive: &Archive, read: &AtomicU64, len: u64) {
    let before = read.fetch_add(len, Ordering::Relaxed);
    if before / RELEASE_BYTES != (before + len) / RELEASE_BYTES {
        archive.release_pages();
    }
}
