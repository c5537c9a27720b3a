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
//! archive writes. Finding a blob touches nothing of the file: the blobs are found by an
//! identity as long as the writer's own (a prefix of their blake3), and their pages, read in
//! the order of the file, would otherwise stay in the build's resident set.

use std::borrow::Cow;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};

use super::format::{stored_sum, BlobId, CODEC_ZSTD, CODEC_ZSTD_DICT, ENTRY_LEN, FORMAT_VERSION, NO_DICTIONARY};
use super::{Archive, Target};

/// The previous archive, mapped, and its blobs found by the start of their blake3.
pub(crate) struct Previous {
    archive: Archive,
    /// (the blob's identity, the first [`IDENT_WORDS`] words of its blake3; blob id),
    /// sorted: the blobs whose stored bytes match their check sum.
    index: Vec<[u32; IDENT_WORDS + 1]>,
    /// Where each bucket of `index` starts (its entries whose identity's first word has
    /// the same top `bucket_bits` bits), and where the last one ends: identities are
    /// uniform, so a lookup reads a few entries after one read of this table instead of
    /// halving the whole index, a cache miss a step.
    buckets: Vec<u32>,
    /// About eight entries a bucket, at most [`MAX_BUCKET_BITS`] bits.
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
    slots: [(u64, [u32; IDENT_WORDS], u32); FOUND_SLOTS],
    next: usize,
}

/// How many lookups [`Found`] remembers: more than a cache entry has artifacts.
const FOUND_SLOTS: usize = 8;

thread_local! {
    static FOUND: std::cell::RefCell<Found> =
        const { std::cell::RefCell::new(Found { slots: [(0, [0; IDENT_WORDS], 0); FOUND_SLOTS], next: 0 }) };
}

/// The serial of the next [`Previous`] opened.
static SERIAL: AtomicU64 = AtomicU64::new(1);

/// A blob of the previous archive as it goes into the new one.
pub(crate) enum Reused<'a> {
    /// Its stored bytes, copied as they are, and their codec.
    Stored(u8, &'a [u8]),
    /// Its raw bytes (checked against its blake3), to be compressed again.
    Raw(Cow<'a, [u8]>),
}

/// Bytes read through the map between two releases of its pages (the pages of a mapped
/// file count in the resident set).
const RELEASE_BYTES: u64 = 4 << 20;

/// The `u32` words of a blob's identity: 16 bytes of its blake3, as the writer's own
/// identities (a collision between artifacts is not a practical concern).
const IDENT_WORDS: usize = 4;

/// The most bits of an identity that choose its bucket of the index (see
/// [`Previous::buckets`]).
const MAX_BUCKET_BITS: u32 = 16;

/// The bucket of an identity's first word, of `bits` bits.
fn bucket(first: u32, bits: u32) -> usize {
    first.checked_shr(32 - bits).unwrap_or(0) as usize
}

fn key(hash: &[u8]) -> [u32; IDENT_WORDS] {
    std::array::from_fn(|i| u32::from_be_bytes(hash[4 * i..4 * i + 4].try_into().expect("4 bytes")))
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
        let mut index = Vec::with_capacity(archive.blob_count());
        let read = AtomicU64::new(0);
        for id in 0..archive.blob_count() {
            match archive.stored_blob(BlobId(id as u32)) {
                Ok((e, bytes)) => {
                    if stored_sum(bytes) == e.sum {
                        let mut entry = [id as u32; IDENT_WORDS + 1];
                        entry[..IDENT_WORDS].copy_from_slice(&key(&e.hash));
                        index.push(entry);
                    }
                    count_read(&archive, &read, (bytes.len() + ENTRY_LEN) as u64);
                }
                // A damaged table: nothing of it is trusted.
                Err(_) => return None,
            }
        }
        index.sort_unstable();
        let bucket_bits = (usize::BITS - (index.len() / 8).leading_zeros()).min(MAX_BUCKET_BITS);
        let mut buckets = vec![0u32; (1 << bucket_bits) + 1];
        for e in &index {
            buckets[bucket(e[0], bucket_bits) + 1] += 1;
        }
        for b in 1..buckets.len() {
            buckets[b] += buckets[b - 1];
        }
        let dictionaries = archive.dictionary_hashes();
        // The pages were only read: the file keeps them.
        archive.release_pages();
        let serial = SERIAL.fetch_add(1, Ordering::Relaxed);
        Some(Previous { archive, index, buckets, bucket_bits, dictionaries, serial })
    }

    /// The id of the blob whose blake3 is `hash` when the archive holds it intact: the
    /// writer may then let go of its bytes and take it from here ([`Previous::reuse`]).
    pub(crate) fn find(&self, hash: &[u8; 32]) -> Option<u32> {
        let k = key(hash);
        let serial = self.serial;
        let remembered = FOUND.with(|f| f.borrow().slots.iter().find(|s| s.0 == serial && s.1 == k).map(|s| s.2));
        if remembered.is_some() {
            return remembered;
        }
        let b = bucket(k[0], self.bucket_bits);
        let within = &self.index[self.buckets[b] as usize..self.buckets[b + 1] as usize];
        let id = within.iter().find(|e| e[..IDENT_WORDS] == k[..]).map(|e| e[IDENT_WORDS])?;
        FOUND.with(|f| {
            let mut f = f.borrow_mut();
            let next = f.next;
            f.slots[next] = (serial, k, id);
            f.next = (next + 1) % FOUND_SLOTS;
        });
        Some(id)
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
            return Ok((entry.hash, Reused::Stored(entry.codec, bytes)));
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
