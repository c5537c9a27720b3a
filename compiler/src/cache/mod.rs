//! The content-addressed artifact cache.
//!
//! Takes a [`Key`] (blake3 of everything that decides a compile's output: the token hash
//! of the preprocessed text, entry point, stage, level name, limits and targets, Kiln's and
//! naga's versions, a fingerprint of Kiln's own sources) and the [`Compiled`] outputs of
//! that key; gives them back on a later build. It also keeps, per permutation, a
//! preprocessing [`Record`] (so unchanged permutations skip the preprocessor) and, per
//! archive, a stamp (so an up-to-date archive is not rewritten). Guarantees: an entry is one file written to a temporary file in the cache folder
//! and renamed into place, so readers (other processes included) see a whole entry or none,
//! and two builds sharing a cache both succeed; every entry carries a checksum of its
//! content, so a corrupted entry is reported ([`Lookup::Corrupt`]) and recompiled, never
//! trusted; a hit refreshes the entry's modification time, which `gc` uses to evict the
//! least recently used entries first.

use std::fs;
use std::io::{self, Write};
use std::path::{Path, PathBuf};
use std::time::SystemTime;

use crate::archive::{Reflection, Stage, Target};
use crate::compile::{Compiled, Limits};

const MAGIC: &[u8; 8] = b"KILNCE\0\x01";
const EXTENSION: &str = "kce";
const RECORD_MAGIC: &[u8; 8] = b"KILNPP\0\x01";
const RECORD_EXTENSION: &str = "kpp";

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
    pub warnings: Vec<String>,
}

/// The cache key of one distinct compile.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Key(pub [u8; 32]);

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
        field(b"kiln cache key v1");
        field(token_hash.as_bytes());
        field(entry.as_bytes());
        field(stage.name().as_bytes());
        field(level.as_bytes());
        field(format!("{limits:?}").as_bytes());
        for t in targets {
            field(t.name().as_bytes());
        }
        field(crate::VERSION.as_bytes());
        field(env!("KILN_SOURCE_HASH").as_bytes());
        field(crate::compile::NAGA_VERSION.as_bytes());
        Key(*h.finalize().as_bytes())
    }

    pub fn to_hex(&self) -> String {
        blake3::Hash::from_bytes(self.0).to_hex().to_string()
    }
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
    /// The entry exists but does not match its checksum or cannot be decoded: the reason.
    /// The entry has been removed; the caller recompiles.
    Corrupt(String),
}

/// Counts of [`Cache::stats`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Stats {
    /// Compiled entries (`.kce`).
    pub entries: u64,
    /// Sets of preprocessing records (`.kpp`, one per configuration and options).
    pub records: u64,
    /// Bytes of entries and records.
    pub bytes: u64,
    /// Temporary files left by interrupted writes (removed by `gc` and `clear`).
    pub temporaries: u64,
}

/// What [`Cache::gc`] did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct GcReport {
    /// Compiled entries removed.
    pub removed: u64,
    /// Preprocessing records removed.
    pub removed_records: u64,
    pub freed: u64,
    pub kept: u64,
    pub kept_bytes: u64,
}

#[derive(Debug, thiserror::Error)]
#[error("cache {path}: {source}")]
pub struct Error {
    pub path: PathBuf,
    pub source: io::Error,
}

/// A cache folder.
#[derive(Clone, Debug)]
pub struct Cache {
    dir: PathBuf,
}

impl Cache {
    /// Opens (creating it if needed) the cache at `dir`.
    pub fn open(dir: impl Into<PathBuf>) -> Result<Cache, Error> {
        let dir = dir.into();
        fs::create_dir_all(&dir).map_err(|source| Error { path: dir.clone(), source })?;
        Ok(Cache { dir })
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The file of `key`: `DIR/abcdef….kce`. One flat folder: creating fan-out folders
    /// costs more than ext4's hashed directories save.
    pub fn path(&self, key: &Key) -> PathBuf {
        self.dir.join(format!("{}.{EXTENSION}", key.to_hex()))
    }

    pub fn get(&self, key: &Key) -> Lookup {
        let path = self.path(key);
        let bytes = match fs::read(&path) {
            Ok(b) => b,
            Err(_) => return Lookup::Miss,
        };
        match decode(key, &bytes) {
            Ok(c) => {
                // Refresh the time gc sorts by; failing to is harmless.
                if let Ok(f) = fs::File::options().append(true).open(&path) {
                    let _ = f.set_modified(SystemTime::now());
                }
                Lookup::Hit(c)
            }
            Err(why) => {
                let _ = fs::remove_file(&path);
                Lookup::Corrupt(format!("cache entry {} is corrupted ({why}); recompiling", path.display()))
            }
        }
    }

    /// Stores `compiled` under `key` atomically.
    pub fn put(&self, key: &Key, compiled: &Compiled) -> Result<(), Error> {
        let mut scratch = Vec::new();
        let body = encode_pieces(key, compiled, &mut scratch);
        let mut h = blake3::Hasher::new();
        for piece in &body {
            h.update(piece);
        }
        let checksum = h.finalize();
        let mut pieces: Vec<&[u8]> = vec![MAGIC, checksum.as_bytes()];
        pieces.extend(body);
        self.write_pieces(&self.path(key), &pieces)
    }

    /// The file of a set of preprocessing records: `DIR/<key>.kpp`.
    pub fn records_path(&self, key: &Key) -> PathBuf {
        self.dir.join(format!("{}.{RECORD_EXTENSION}", key.to_hex()))
    }

    /// The preprocessing records stored under `key` (one set per configuration and
    /// options), by permutation key; empty when missing or damaged.
    pub fn get_records(&self, key: &Key) -> Records {
        let path = self.records_path(key);
        let Ok(bytes) = fs::read(&path) else { return Records::default() };
        if bytes.len() < 40 || &bytes[..8] != RECORD_MAGIC || blake3::hash(&bytes[40..]).as_bytes() != &bytes[8..40] {
            return Records::default();
        }
        let records = serde_json::from_slice(&bytes[40..]).unwrap_or_default();
        if let Ok(f) = fs::File::options().append(true).open(&path) {
            let _ = f.set_modified(SystemTime::now());
        }
        records
    }

    /// Replaces the records stored under `key`, atomically.
    pub fn put_records(&self, key: &Key, records: &Records) -> Result<(), Error> {
        let body = serde_json::to_vec(records).expect("records serialize");
        let mut bytes = Vec::with_capacity(40 + body.len());
        bytes.extend_from_slice(RECORD_MAGIC);
        bytes.extend_from_slice(blake3::hash(&body).as_bytes());
        bytes.extend_from_slice(&body);
        self.write_file(&self.records_path(key), &bytes)
    }

    /// The stamp of the archive at `archive`: `DIR/<blake3 of its absolute path>.stamp`.
    fn stamp_path(&self, archive: &Path) -> PathBuf {
        let abs = std::path::absolute(archive).unwrap_or_else(|_| archive.to_path_buf());
        let name = blake3::hash(abs.to_string_lossy().as_bytes()).to_hex();
        self.dir.join(format!("{}.stamp", &name[..32]))
    }

    /// Records that the archive now at `archive` is the output of the build with
    /// `fingerprint` (with its artifact counts), identified by its length, modification
    /// time and header checksum.
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

    /// The artifact counts of the archive at `archive` if it is, untouched, the output of a
    /// build with `fingerprint`, and every key of `keys` still has its entry.
    pub fn fresh_archive(&self, archive: &Path, fingerprint: &blake3::Hash, keys: &[Key]) -> Option<(usize, usize)> {
        if !keys.iter().all(|k| self.path(k).is_file()) {
            return None;
        }
        let text = fs::read_to_string(self.stamp_path(archive)).ok()?;
        let mut lines = text.lines();
        if lines.next()? != fingerprint.to_hex().as_str() || lines.next()? != archive_identity(archive).ok()? {
            return None;
        }
        Some((lines.next()?.parse().ok()?, lines.next()?.parse().ok()?))
    }

    fn write_file(&self, path: &Path, bytes: &[u8]) -> Result<(), Error> {
        self.write_pieces(path, &[bytes])
    }

    /// Writes the concatenation of `pieces` to a temporary file in the cache folder, then
    /// renames it to `path`.
    fn write_pieces(&self, path: &Path, pieces: &[&[u8]]) -> Result<(), Error> {
        let err = |source| Error { path: path.to_path_buf(), source };
        let mut tmp = match tempfile::Builder::new().prefix(".tmp-").tempfile_in(&self.dir) {
            Ok(t) => t,
            Err(_) => {
                // The folder was removed under us (`kiln cache clear` by hand): make it again.
                fs::create_dir_all(&self.dir).map_err(err)?;
                tempfile::Builder::new().prefix(".tmp-").tempfile_in(&self.dir).map_err(err)?
            }
        };
        let mut out = std::io::BufWriter::with_capacity(64 << 10, tmp.as_file_mut());
        for piece in pieces {
            out.write_all(piece).map_err(err)?;
        }
        out.flush().map_err(err)?;
        drop(out);
        tmp.persist(path).map_err(|e| err(e.error))?;
        Ok(())
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

    fn is_entry(path: &Path) -> bool {
        path.extension().is_some_and(|e| e == EXTENSION)
    }

    fn is_record(path: &Path) -> bool {
        path.extension().is_some_and(|e| e == RECORD_EXTENSION)
    }

    fn is_temporary(path: &Path) -> bool {
        path.file_name().is_some_and(|n| n.to_string_lossy().starts_with(".tmp-"))
    }

    pub fn stats(&self) -> Stats {
        let mut s = Stats::default();
        for (path, meta) in self.files() {
            if Self::is_entry(&path) {
                s.entries += 1;
                s.bytes += meta.len();
            } else if Self::is_record(&path) {
                s.records += 1;
                s.bytes += meta.len();
            } else if Self::is_temporary(&path) {
                s.temporaries += 1;
            }
        }
        s
    }

    /// Evicts least recently used entries and records until they take at most `max_bytes`;
    /// removes temporary files older than a minute (left by interrupted writes).
    pub fn gc(&self, max_bytes: u64) -> GcReport {
        let mut entries = Vec::new();
        let now = SystemTime::now();
        for (path, meta) in self.files() {
            if Self::is_entry(&path) || Self::is_record(&path) {
                entries.push((meta.modified().unwrap_or(SystemTime::UNIX_EPOCH), meta.len(), path));
            } else if Self::is_temporary(&path) {
                let age = meta.modified().ok().and_then(|m| now.duration_since(m).ok()).unwrap_or_default();
                if age.as_secs() >= 60 {
                    let _ = fs::remove_file(&path);
                }
            }
        }
        entries.sort();
        let mut total: u64 = entries.iter().map(|e| e.1).sum();
        let mut report = GcReport::default();
        for (_, len, path) in &entries {
            if total <= max_bytes {
                break;
            }
            if fs::remove_file(path).is_ok() {
                total -= len;
                if Self::is_entry(path) {
                    report.removed += 1;
                } else {
                    report.removed_records += 1;
                }
                report.freed += len;
            }
        }
        let total_entries = entries.iter().filter(|e| Self::is_entry(&e.2)).count() as u64;
        report.kept = total_entries - report.removed;
        report.kept_bytes = total;
        report
    }

    /// Removes every entry, record, archive stamp and temporary file; returns how many
    /// entries were removed.
    pub fn clear(&self) -> Result<u64, Error> {
        let mut n = 0;
        for (path, _) in self.files() {
            let stamp = path.extension().is_some_and(|e| e == "stamp");
            if Self::is_entry(&path) || Self::is_record(&path) || Self::is_temporary(&path) || stamp {
                fs::remove_file(&path).map_err(|source| Error { path: path.clone(), source })?;
                n += u64::from(Self::is_entry(&path));
            }
        }
        Ok(n)
    }
}

/// Length, modification time and header checksum of an archive file.
fn archive_identity(path: &Path) -> io::Result<String> {
    use std::io::Read;
    let mut f = fs::File::open(path)?;
    let meta = f.metadata()?;
    let mtime = meta.modified()?.duration_since(SystemTime::UNIX_EPOCH).unwrap_or_default();
    let mut header = [0u8; 64];
    f.read_exact(&mut header)?;
    Ok(format!(
        "{} {}.{:09} {}",
        meta.len(),
        mtime.as_secs(),
        mtime.subsec_nanos(),
        blake3::Hash::from_bytes(header[32..64].try_into().unwrap()).to_hex()
    ))
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
/// The pieces of an entry, in file order (artifacts are borrowed, not copied).
fn encode_pieces<'a>(key: &'a Key, c: &'a Compiled, scratch: &'a mut Vec<Vec<u8>>) -> Vec<&'a [u8]> {
    // Small framing pieces live in `scratch`; artifacts are referenced in place.
    scratch.clear();
    scratch.push((c.artifacts.len() as u32).to_le_bytes().to_vec());
    for (t, bytes) in &c.artifacts {
        let mut frame = vec![t.name().len() as u8];
        frame.extend_from_slice(t.name().as_bytes());
        frame.extend_from_slice(&(bytes.len() as u64).to_le_bytes());
        scratch.push(frame);
    }
    let json = serde_json::to_vec(&c.reflection).expect("reflection serializes");
    scratch.push((json.len() as u64).to_le_bytes().to_vec());
    scratch.push(json);
    let scratch: &'a Vec<Vec<u8>> = scratch;
    let mut body: Vec<&'a [u8]> = vec![&key.0, &scratch[0]];
    for (i, (_, bytes)) in c.artifacts.iter().enumerate() {
        body.push(&scratch[1 + i]);
        body.push(bytes);
    }
    let n = scratch.len();
    body.push(&scratch[n - 2]);
    body.push(&scratch[n - 1]);
    body
}

/// An entry as one buffer (tests).
#[cfg(test)]
fn encode(key: &Key, c: &Compiled) -> Vec<u8> {
    let mut scratch = Vec::new();
    let body = encode_pieces(key, c, &mut scratch);
    let mut h = blake3::Hasher::new();
    body.iter().for_each(|p| {
        h.update(p);
    });
    let mut out = Vec::new();
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(h.finalize().as_bytes());
    body.iter().for_each(|p| out.extend_from_slice(p));
    out
}

fn decode(key: &Key, bytes: &[u8]) -> Result<Compiled, String> {
    if bytes.len() < 40 || &bytes[..8] != MAGIC {
        return Err("not a cache entry of this kiln".into());
    }
    let body = &bytes[40..];
    if blake3::hash(body).as_bytes() != &bytes[8..40] {
        return Err("checksum mismatch".into());
    }
    let mut r = Reader { bytes: body, at: 0 };
    if r.take(32)? != key.0 {
        return Err("the entry belongs to another key".into());
    }
    let count = u32::from_le_bytes(r.take(4)?.try_into().unwrap());
    let mut artifacts = Vec::new();
    for _ in 0..count {
        let n = r.take(1)?[0] as usize;
        let name = std::str::from_utf8(r.take(n)?).map_err(|_| "bad target name")?;
        let target = Target::from_name(name).ok_or_else(|| format!("unknown target `{name}`"))?;
        let len = r.u64()? as usize;
        artifacts.push((target, r.take(len)?.to_vec()));
    }
    let len = r.u64()? as usize;
    let reflection: Reflection = serde_json::from_slice(r.take(len)?).map_err(|e| format!("bad reflection: {e}"))?;
    if r.at != body.len() {
        return Err("trailing bytes".into());
    }
    Ok(Compiled { artifacts, reflection })
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
