//! The archive a writer replaces: its compressed blobs are copied into the new archive where
//! compressing again would give the same bytes, so that a build that rewrites its archive
//! after a small change compresses only what changed.
//!
//! A blob's stored bytes depend only on its raw bytes, the compression level and the
//! dictionary it was compressed with (zstd is deterministic for a given input, parameters
//! and library). So a stored blob is copied only when the previous archive was written by
//! this version of the archive crate, holds the same bytes (its blake3) and was compressed
//! with a dictionary of the same blake3 as the new archive's for its target, or with none
//! when the new archive has none for it. Blobs stored uncompressed are compressed again:
//! whether zstd shrank them depended on the dictionary their target had then. A copied blob
//! is decompressed and checked against its blake3 first, so a damaged previous archive costs
//! time, never different bytes: the new archive is byte for byte the one a writer without a
//! previous archive writes.

use std::path::Path;

use super::format::{BlobId, CODEC_STORED, CODEC_ZSTD, CODEC_ZSTD_DICT, NO_DICTIONARY};
use super::{Archive, Target};

/// The previous archive, mapped, and its compressed blobs found by the start of their
/// blake3.
pub(crate) struct Previous {
    archive: Archive,
    /// (start of the blake3 as two `u32`, blob id), sorted.
    index: Vec<[u32; 3]>,
    /// Each dictionary's target and blake3, by index.
    dictionaries: Vec<(Target, [u8; 32])>,
}

/// A blob as the previous archive stores it: codec, stored bytes, blake3.
pub(crate) type Stored = (u8, Vec<u8>, [u8; 32]);

fn key(hash: &[u8]) -> [u32; 2] {
    [
        u32::from_be_bytes(hash[0..4].try_into().expect("4 bytes")),
        u32::from_be_bytes(hash[4..8].try_into().expect("4 bytes")),
    ]
}

impl Previous {
    /// The archive at `path` when there is one this crate's version wrote; `None` otherwise
    /// (missing, unreadable, damaged in its header or tables, or another version's).
    pub(crate) fn open(path: &Path) -> Option<Previous> {
        let archive = Archive::open(path).ok()?;
        if archive.kiln_version() != crate::VERSION {
            return None;
        }
        let mut index = Vec::with_capacity(archive.blob_count());
        for id in 0..archive.blob_count() {
            match archive.stored_blob(BlobId(id as u32)) {
                Ok((e, _)) if e.codec != CODEC_STORED => {
                    let [a, b] = key(&e.hash);
                    index.push([a, b, id as u32]);
                }
                Ok(_) => {}
                // A damaged table: nothing of it is trusted.
                Err(_) => return None,
            }
        }
        index.sort_unstable();
        let dictionaries = archive.dictionary_hashes();
        // The table's pages were only read: the file keeps them.
        archive.release_pages();
        Some(Previous { archive, index, dictionaries })
    }

    /// The blob whose blake3 starts with `ident` and that is `len` bytes long, as stored by
    /// the previous archive, when compressing it with `dictionary` (the blake3 of the new
    /// archive's dictionary for the blob's target, or `None` for none) gives those bytes.
    pub(crate) fn stored(&self, ident: &[u8], len: u64, dictionary: Option<&[u8; 32]>) -> Option<Stored> {
        let k = key(ident);
        let first = self.index.partition_point(|e| [e[0], e[1]] < k);
        for e in self.index[first..].iter().take_while(|e| [e[0], e[1]] == k) {
            let id = BlobId(e[2]);
            let Ok((entry, bytes)) = self.archive.stored_blob(id) else { continue };
            let same_dictionary = match (entry.codec, dictionary) {
                (CODEC_ZSTD, None) => entry.dictionary == NO_DICTIONARY,
                (CODEC_ZSTD_DICT, Some(d)) => {
                    self.dictionaries.get(entry.dictionary as usize).is_some_and(|p| &p.1 == d)
                }
                _ => false,
            };
            if !same_dictionary || entry.raw_len != len || entry.hash[..ident.len()] != *ident {
                continue;
            }
            // Checked against its blake3 (decompressed) before it is trusted.
            if self.archive.blob(id).is_err() {
                return None;
            }
            return Some((entry.codec, bytes.to_vec(), entry.hash));
        }
        None
    }

    /// Gives back the previous archive's pages read so far (the file keeps them).
    pub(crate) fn release_pages(&self) {
        self.archive.release_pages();
    }
}
