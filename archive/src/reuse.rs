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
//! archive writes. Memory holds a bit a blob here (intact or not): the previous archive's
//! blobs are found in the writer's own table, whose first slots they are (a slot's number
//! is the blob's id here), by the first 16 bytes of their blake3 as any blob of the writer
//! is; a blob's length is checked when it is copied. One table for both archives, where an
//! index of the previous archive's beside the writer's was the largest table a rewrite
//! held beyond another build's.

use std::borrow::Cow;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};

use super::format::{stored_sum, BlobId, CODEC_ZSTD, CODEC_ZSTD_DICT, ENTRY_LEN, FORMAT_VERSION, NO_DICTIONARY};
use super::{Archive, Target};

/// The previous archive, mapped, and which of its blobs are intact. The writer finds them
/// in its own table: their blake3s give the first slots of the writer's blob table, each
/// blob's slot its id here ([`Previous::for_each_hash`]), so that one table finds the blobs
/// of both archives.
pub(crate) struct Previous {
    archive: Archive,
    /// One bit a blob: its stored bytes match their check sum (only those are taken).
    intact: Vec<u64>,
    /// Each dictionary's target and blake3, by index.
    dictionaries: Vec<(Target, [u8; 32])>,
}

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
        // One pass in the order of the file checks each blob's stored bytes.
        let mut intact = vec![0u64; count.div_ceil(64)];
        let read = AtomicU64::new(0);
        for id in 0..count {
            // A damaged table: nothing of it is trusted.
            let (e, bytes) = archive.stored_blob(BlobId(id as u32)).ok()?;
            if stored_sum(bytes) == e.sum {
                intact[id / 64] |= 1 << (id % 64);
            }
            count_read(&archive, &read, (bytes.len() + ENTRY_LEN) as u64);
        }
        let dictionaries = archive.dictionary_hashes();
        // The pages were only read: the file keeps them.
        archive.release_pages();
        Some(Previous { archive, intact, dictionaries })
    }

    /// The archive's blobs.
    pub(crate) fn blob_count(&self) -> usize {
        self.archive.blob_count()
    }

    /// Whether blob `id`'s stored bytes matched their check sum when the archive was opened
    /// (it may be taken: [`Previous::reuse`]).
    pub(crate) fn is_intact(&self, id: u32) -> bool {
        self.intact.get(id as usize / 64).is_some_and(|w| w & (1 << (id % 64)) != 0)
    }

    /// Calls `f` with each blob's blake3, in id order (the table read once, its pages given
    /// back as they are read).
    pub(crate) fn for_each_hash(&self, mut f: impl FnMut(&[u8; 32]) -> std::io::Result<()>) -> std::io::Result<()> {
        let read = AtomicU64::new(0);
        for id in 0..self.blob_count() {
            let (entry, _) = self.archive.stored_blob(BlobId(id as u32)).map_err(std::io::Error::other)?;
            f(&entry.hash)?;
            count_read(&self.archive, &read, ENTRY_LEN as u64);
        }
        self.archive.release_pages();
        Ok(())
    }

    /// Blob `id` (an intact one: [`Previous::is_intact`]) for a new archive whose dictionary for its
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
