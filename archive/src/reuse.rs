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
//! archive writes. Finding a blob touches nothing of the file (its pages, read out of the
//! order of the file, would stay in the build's resident set): memory holds 12 bytes a
//! blob, the 64 bits of its blake3 after those that choose its bucket, and its id; its
//! length is checked when it is copied.

use std::borrow::Cow;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};

use super::format::{stored_sum, BlobId, CODEC_ZSTD, CODEC_ZSTD_DICT, ENTRY_LEN, FORMAT_VERSION, NO_DICTIONARY};
use super::{Archive, Target};

/// The previous archive, mapped, and its blobs found by the start of their blake3.
pub(crate) struct Previous {
    archive: Archive,
    /// Each blob whose stored bytes match their check sum, by bucket and in id order
    /// within it: the 64 bits of its identity that follow the bits choosing its bucket
    /// (see [`Previous::buckets`]), high word first, then its id. 12 bytes a blob, a
    /// bucket's in a cache line or two (its ids with them: a lookup misses once there).
    index: Vec<[u32; 3]>,
    /// Where each bucket of `index` starts (its blobs' identities begin with the same
    /// `bucket_bits` bits), and where the last one ends: identities are uniform, so a
    /// lookup reads a few entries after one read of this table instead of halving the whole
    /// index, a cache miss a step.
    buckets: Vec<u32>,
    /// About eight blobs a bucket, at most [`MAX_BUCKET_BITS`] bits.
    bucket_bits: u32,
    /// Each dictionary's target and blake3, by index.
    dictionaries: Vec<(Target, [u8; 32])>,
    /// Tells this archive's lookups from another's in [`FOUND`] (never 0).
    serial: u64,
}

/// The blobs this thread found last in a previous archive: (its serial, the blob's
/// identity, its id), 0 for none. A build asks whether the previous archive holds each
/// artifact of a cache entry, then adds each by reference, on the same thread: the second
/// lookup is answered here instead of from the index, a cache miss or two each.
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

/// The most bits of an identity that choose its bucket (see [`Previous::buckets`]), far
/// past the sets a build's memory allows: a bucket stays a few keys long at any size.
const MAX_BUCKET_BITS: u32 = 24;

/// A blob's identity: the first 16 bytes of its blake3, as the writer's own identities.
/// Its bucket's bits and the 64 bits after them tell it from the others in the index (with
/// its length, checked when it is copied); the rest of a blake3 is uniform too, so two
/// blobs that differ there alone are not a practical concern.
fn identity(hash: &[u8; 32]) -> u128 {
    u128::from_be_bytes(hash[..16].try_into().expect("16 of 32 bytes"))
}

/// The bucket of `identity`, of `bits` bits.
fn bucket(identity: u128, bits: u32) -> usize {
    identity.checked_shr(128 - bits).unwrap_or(0) as usize
}

/// The 64 bits of `identity` after its bucket's `bits`.
fn key(identity: u128, bits: u32) -> u64 {
    (identity << bits >> 64) as u64
}

/// An entry of [`Previous::index`]: `key` and `id`.
fn entry(key: u64, id: u32) -> [u32; 3] {
    [(key >> 32) as u32, key as u32, id]
}

impl Previous {
    /// The archive at `path` when there is one this crate's version wrote in this format;
    /// `None` otherwise (missing, unreadable, damaged in its header or tables, an older
    /// format without check sums of stored bytes, or another version's).
    pub(crate) fn open(path: &Path) -> Option<Previous> {
        let archive = Archive::open(path).ok()?;
        if archive.kiln_version() != crate::VERSION || archive.format_version() != FORMAT_VERSION {
            return None;
        }
        let count = archive.blob_count();
        let bucket_bits = (usize::BITS - (count / 8).leading_zeros()).min(MAX_BUCKET_BITS);
        // One pass in the order of the file checks each blob's stored bytes and counts
        // each bucket's blobs; a second reads the table alone and puts each in its bucket.
        let mut intact = vec![0u64; count.div_ceil(64)];
        let mut buckets = vec![0u32; (1 << bucket_bits) + 1];
        let read = AtomicU64::new(0);
        for id in 0..count {
            // A damaged table: nothing of it is trusted.
            let (e, bytes) = archive.stored_blob(BlobId(id as u32)).ok()?;
            if stored_sum(bytes) == e.sum {
                intact[id / 64] |= 1 << (id % 64);
                buckets[bucket(identity(&e.hash), bucket_bits) + 1] += 1;
            }
            count_read(&archive, &read, (bytes.len() + ENTRY_LEN) as u64);
        }
        for b in 1..buckets.len() {
            buckets[b] += buckets[b - 1];
        }
        let held = buckets[buckets.len() - 1] as usize;
        let mut index = vec![[0u32; 3]; held];
        let mut next = buckets.clone();
        for id in (0..count).filter(|id| intact[id / 64] & (1 << (id % 64)) != 0) {
            let ident = identity(&archive.stored_blob(BlobId(id as u32)).ok()?.0.hash);
            count_read(&archive, &read, ENTRY_LEN as u64);
            let at = &mut next[bucket(ident, bucket_bits)];
            index[*at as usize] = entry(key(ident, bucket_bits), id as u32);
            *at += 1;
        }
        drop((intact, next));
        let dictionaries = archive.dictionary_hashes();
        // The pages were only read: the file keeps them.
        archive.release_pages();
        let serial = SERIAL.fetch_add(1, Ordering::Relaxed);
        Some(Previous { archive, index, buckets, bucket_bits, dictionaries, serial })
    }

    /// The id of the blob whose blake3 is `hash` when the archive holds it intact: the
    /// writer may then let go of its bytes and take it from here ([`Previous::reuse`]).
    pub(crate) fn find(&self, hash: &[u8; 32]) -> Option<u32> {
        let ident = identity(hash);
        let serial = self.serial;
        let remembered = FOUND.with(|f| f.borrow().slots.iter().find(|s| s.0 == serial && s.1 == ident).map(|s| s.2));
        if remembered.is_some() {
            return remembered;
        }
        let b = bucket(ident, self.bucket_bits);
        let (start, end) = (self.buckets[b] as usize, self.buckets[b + 1] as usize);
        let k = entry(key(ident, self.bucket_bits), 0);
        let id = self.index[start..end].iter().find(|e| e[..2] == k[..2])?[2];
        FOUND.with(|f| {
            let mut f = f.borrow_mut();
            let next = f.next;
            f.slots[next] = (serial, ident, id);
            f.next = (next + 1) % FOUND_SLOTS;
        });
        Some(id)
    }

    /// Lets go of the index: [`Previous::find`] finds nothing from here on, while the blobs
    /// it found are still taken by id ([`Previous::reuse`]). The index is the largest
    /// table a rewrite holds beyond another build's, and the manifest's stages that follow
    /// the last lookup are a build's peak.
    pub(crate) fn drop_index(&mut self) {
        self.index = Vec::new();
        self.buckets = vec![0; 2];
        self.bucket_bits = 0;
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

/// Counts `len` more bytes read from `archive`'s map, and gives its pages back each
/// [`RELEASE_BYTES`].
fn count_read(archive: &Archive, read: &AtomicU64, len: u64) {
    let before = read.fetch_add(len, Ordering::Relaxed);
    if before / RELEASE_BYTES != (before + len) / RELEASE_BYTES {
        archive.release_pages();
    }
}
