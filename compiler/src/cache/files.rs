//! The cache folder's files: which are the cache's, and `kiln cache`'s stats, gc and
//! clear over them.

use super::*;

impl Cache {
    pub(super) fn files(&self) -> impl Iterator<Item = (PathBuf, fs::Metadata)> {
        walkdir::WalkDir::new(&self.dir)
            .min_depth(1)
            .max_depth(1)
            .into_iter()
            .filter_map(Result::ok)
            .filter(|e| e.file_type().is_file())
            .filter_map(|e| Some((e.path().to_path_buf(), e.metadata().ok()?)))
    }

    pub(super) fn is_pack(path: &Path) -> bool {
        path.extension().is_some_and(|e| e == PACK_EXTENSION)
    }

    pub(super) fn is_dictionary(path: &Path) -> bool {
        path.extension().is_some_and(|e| e == codec::DICT_EXTENSION)
    }

    pub(super) fn is_record(path: &Path) -> bool {
        path.extension().is_some_and(|e| e == RECORD_EXTENSION)
    }

    /// A temporary file of a write into the cache (named by [`crate::output`] after a cache
    /// file).
    pub(super) fn is_temporary(path: &Path) -> bool {
        path.file_name()
            .and_then(|n| n.to_str())
            .and_then(crate::output::temporary_parts)
            .is_some_and(|(name, _)| Self::is_cache_file_name(name))
    }

    /// `<32 or 64 hex digits>.kcp`, `.kpp` or `.stamp`: how the cache names its files.
    pub(super) fn is_cache_file_name(name: &str) -> bool {
        let Some((stem, ext)) = name.split_once('.') else { return false };
        (stem.len() == 32 || stem.len() == 64)
            && stem.bytes().all(|b| b.is_ascii_hexdigit())
            && [PACK_EXTENSION, RECORD_EXTENSION, codec::DICT_EXTENSION, "stamp"].contains(&ext)
    }

    /// Whether the file at `path` is one Kiln wrote into a cache: a pack or a record with its
    /// magic bytes, a stamp in its format, a temporary file named after one of those. Only
    /// these are ever counted, evicted or cleared; anything else in the folder is left alone.
    pub(super) fn is_own(path: &Path) -> bool {
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
    pub(super) fn pack_keys(path: &Path) -> Vec<Key> {
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
                    // The raw size from the entry's header (version 3 on), else its length.
                    let mut header = [0u8; codec::HEADER];
                    let header = &mut header[..len.min(codec::HEADER as u64) as usize];
                    let read = pack.file.read_exact_at(header, offset).is_ok();
                    s.raw += read.then(|| codec::raw_len(header)).flatten().unwrap_or(len);
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
