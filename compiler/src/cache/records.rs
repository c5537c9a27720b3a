//! Preprocessing records (one set per configuration and options) and archive stamps:
//! small files beside the packs, each replaced atomically.

use super::*;
use std::io::Write;

/// A body handed out in pieces: calls its argument on each, in order.
pub type StreamedBody<'a> = dyn Fn(&mut dyn FnMut(&[u8]) -> std::io::Result<()>) -> std::io::Result<()> + 'a;

impl Cache {
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
        // Checked before it is kept; the body is the value's tail, moved, not copied.
        if !super::records_whole(&bytes) {
            return None;
        }
        let _ = self.write_file(&path, &bytes);
        let mut body = bytes;
        body.drain(..40);
        Some((body, true))
    }

    /// The records file under `key` in this folder, opened and its checksum checked (read
    /// through a small buffer, not into memory), with where its body starts and how long
    /// the body is: a reader looks its rows up in place, so that a large set of records
    /// is never whole in memory. `None` when missing or damaged.
    pub fn open_local_records(&self, key: &Key) -> Option<(fs::File, u64, u64)> {
        let path = self.records_path(key);
        let (file, meta) = crate::archive::input::open_regular(&path).ok()?;
        if meta.len() > MAX_RECORDS || meta.len() < 40 {
            return None;
        }
        let mut head = [0u8; 40];
        file.read_exact_at(&mut head, 0).ok()?;
        if &head[..8] != RECORD_MAGIC {
            return None;
        }
        let mut hasher = blake3::Hasher::new();
        let mut buffer = vec![0u8; 1 << 18];
        let mut at = 40u64;
        while at < meta.len() {
            let n = (meta.len() - at).min(buffer.len() as u64) as usize;
            file.read_exact_at(&mut buffer[..n], at).ok()?;
            hasher.update(&buffer[..n]);
            at += n as u64;
        }
        if hasher.finalize().as_bytes() != &head[8..40] {
            return None;
        }
        if let Ok(f) = fs::File::options().append(true).open(&path) {
            let _ = f.set_modified(SystemTime::now());
        }
        Some((file, 40, meta.len() - 40))
    }

    /// Replaces the records file under `key` with `body` (checksummed), atomically, and
    /// stores it in the remote cache too.
    pub fn put_records_bytes(&self, key: &Key, body: &[u8]) -> Result<(), Error> {
        let sum = blake3::hash(body);
        if let Some(remote) = self.remote() {
            remote.store_from(key, &super::remote::Pieces(&[RECORD_MAGIC, sum.as_bytes(), body]));
        }
        self.write_pieces(&self.records_path(key), &[RECORD_MAGIC, sum.as_bytes(), body])
    }

    /// [`Cache::put_records_bytes`] for a body of `len` bytes that `body` hands out in
    /// pieces (read twice: once for the checksum in front, once to write), so that a large
    /// one need not be in memory. Only a remote cache's value is made whole in memory.
    pub fn put_records_streamed(&self, key: &Key, len: u64, body: &StreamedBody<'_>) -> Result<(), Error> {
        let path = self.records_path(key);
        let err = |source| Error { path: path.clone(), source };
        let mut hasher = blake3::Hasher::new();
        body(&mut |b| {
            hasher.update(b);
            Ok(())
        })
        .map_err(err)?;
        let sum = hasher.finalize();
        if let Some(remote) = self.remote() {
            let mut whole = Vec::with_capacity(usize::try_from(len).unwrap_or(0));
            body(&mut |b| {
                whole.extend_from_slice(b);
                Ok(())
            })
            .map_err(err)?;
            remote.store_from(key, &super::remote::Pieces(&[RECORD_MAGIC, sum.as_bytes(), &whole]));
        }
        crate::archive::output::write_with(&path, false, |f, _| {
            let mut out = std::io::BufWriter::new(f);
            out.write_all(RECORD_MAGIC)?;
            out.write_all(sum.as_bytes())?;
            body(&mut |b| out.write_all(b))?;
            out.flush()
        })
        .map_err(err)
    }

    /// Replaces the records file under `key` with `body` (checksummed), atomically, in this
    /// folder only: for what only this machine's paths find, not worth a remote value.
    pub fn put_local_records_bytes(&self, key: &Key, body: &[u8]) -> Result<(), Error> {
        let sum = blake3::hash(body);
        self.write_pieces(&self.records_path(key), &[RECORD_MAGIC, sum.as_bytes(), body])
    }

    /// Whether a remote cache that stores values is configured.
    pub fn remote_writes(&self) -> bool {
        self.remote().is_some_and(|r| r.writes())
    }

    /// The body of the records under `key` in the remote cache only (never kept locally:
    /// a piece of a shard's records is read once); `None` when missing or damaged (its
    /// checksum is checked, so that a damaged piece is preprocessed again, never trusted).
    pub fn get_remote_records_bytes(&self, key: &Key) -> Option<Vec<u8>> {
        self.remote().and_then(|r| r.get(key)).and_then(records_body)
    }

    /// Stores `body` (checksummed) under `key` in the remote cache only; whether it was.
    pub fn put_remote_records_bytes(&self, key: &Key, body: &[u8]) -> bool {
        let sum = blake3::hash(body);
        self.remote().is_some_and(|r| r.store_from(key, &super::remote::Pieces(&[RECORD_MAGIC, sum.as_bytes(), body])))
    }

    /// The body of the records file under `key` in this folder (never the remote cache's);
    /// `None` when missing or damaged.
    pub fn get_local_records_bytes(&self, key: &Key) -> Option<Vec<u8>> {
        let path = self.records_path(key);
        let body = crate::archive::input::read_regular(&path, MAX_RECORDS).ok().and_then(records_body)?;
        if let Ok(f) = fs::File::options().append(true).open(&path) {
            let _ = f.set_modified(SystemTime::now());
        }
        Some(body)
    }

    /// The stamp of the archive at `archive`: `DIR/<blake3 of its absolute path>.stamp`.
    pub(super) fn stamp_path(&self, archive: &Path) -> PathBuf {
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

    /// [`Cache::stamp_archive`] for the archive whose content hashes to `content`, written to `file`, a temporary file
    /// about to be renamed to `archive` (the rename keeps its length and modification
    /// time): the stamp is written while the build still waits on other work. A stamp whose
    /// file is not renamed after all matches no archive.
    pub fn stamp_archive_file(
        &self,
        archive: &Path,
        file: &fs::File,
        content: blake3::Hash,
        fingerprint: &blake3::Hash,
        counts: (usize, usize),
    ) -> Result<(), Error> {
        let err = |source| Error { path: archive.to_path_buf(), source };
        let meta = file.metadata().map_err(err)?;
        let id = identity(&meta, content).map_err(err)?;
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
        mut keys: &mut dyn Iterator<Item = Key>,
    ) -> Option<(usize, usize)> {
        // The stamp first: without one (a first build) the keys are not looked at. Then the
        // fingerprint and the archive: only when both match is the index read (a build whose
        // archive is gone or out of date does not load it where grouping peaks).
        let text = crate::archive::input::read_regular_to_string(&self.stamp_path(archive), 4096).ok()?;
        let mut lines = text.lines();
        if lines.next()? != fingerprint().to_hex().as_str() || lines.next()? != archive_identity(archive).ok()? {
            return None;
        }
        let counts = (lines.next()?.parse().ok()?, lines.next()?.parse().ok()?);
        self.with_index(|index| Iterator::all(&mut keys, |k| index.contains(&k))).then_some(counts)
    }
}
