//! Preprocessing records, compact: what preprocessing one permutation gave ([`Row`]), and
//! the binary encoding of a configuration's set of them (stored by the cache under one key).
//!
//! A build keeps one [`Row`] per distinct preprocessing result, shared (`Arc`) by the
//! permutations that reuse it, with its lists of files, missing include candidates and
//! warnings interned: a few hundred bytes per permutation, so that a 100k-permutation set's
//! records fit in tens of megabytes, in memory and on disk.
//!
//! ```text
//! magic "KILNREC\x01"
//! u32 count, then each file list:    u32 n, n x (u32 len, path bytes, 32-byte blake3 of its text)
//! u32 count, then each absent list:  u32 n, n x (u32 len, path bytes)
//! u32 count, then each warning list: u32 n, n x (u32 len, utf-8 bytes)
//! u64 count, then each row: direct key (32), key (32), token hash (32), text hash (32),
//!     text length (u64), file list, absent list, warning list (u32 indices)
//! ```

use std::collections::HashMap;
use std::ffi::OsStr;
use std::os::unix::ffi::OsStrExt;
use std::path::PathBuf;
use std::sync::Arc;

use crate::cache::Key;

const MAGIC: &[u8; 8] = b"KILNREC\x01";

/// Files read, each with the blake3 of the text the preprocessor read.
pub(super) type FileList = Arc<[(PathBuf, [u8; 32])]>;

/// What preprocessing one permutation gave.
#[derive(Debug, PartialEq, Eq)]
pub(super) struct Row {
    pub key: Key,
    pub token_hash: blake3::Hash,
    pub text_hash: blake3::Hash,
    /// Length of the preprocessed text (the key's estimated compile cost).
    pub text_len: u64,
    pub files: FileList,
    /// Include candidates that were missing: the record holds only while they still are.
    pub absent: Arc<[PathBuf]>,
    /// Preprocessor warnings, rendered without colour.
    pub warnings: Arc<[String]>,
}

/// Each permutation's row by its direct key (see `preprocess::direct_key`).
pub(super) type Records = HashMap<Key, Arc<Row>>;

/// Interns lists so that equal lists share one allocation.
#[derive(Default)]
pub(super) struct Interner {
    files: std::collections::HashSet<FileList>,
    absent: std::collections::HashSet<Arc<[PathBuf]>>,
    warnings: std::collections::HashSet<Arc<[String]>>,
}

fn intern<T: Eq + std::hash::Hash + Clone>(set: &mut std::collections::HashSet<Arc<[T]>>, v: Vec<T>) -> Arc<[T]> {
    if let Some(a) = set.get(&v[..]) {
        return a.clone();
    }
    let a: Arc<[T]> = v.into();
    set.insert(a.clone());
    a
}

impl Interner {
    pub fn files(&mut self, v: Vec<(PathBuf, [u8; 32])>) -> FileList {
        intern(&mut self.files, v)
    }
    pub fn absent(&mut self, v: Vec<PathBuf>) -> Arc<[PathBuf]> {
        intern(&mut self.absent, v)
    }
    pub fn warnings(&mut self, v: Vec<String>) -> Arc<[String]> {
        intern(&mut self.warnings, v)
    }
}

/// Index of each distinct list (by allocation) in encoding order.
struct Table<'a, T> {
    index: HashMap<*const T, u32>,
    lists: Vec<&'a [T]>,
}

impl<'a, T> Table<'a, T> {
    fn new() -> Self {
        Table { index: HashMap::new(), lists: Vec::new() }
    }
    fn add(&mut self, list: &'a Arc<[T]>) -> u32 {
        let n = self.lists.len() as u32;
        *self.index.entry(Arc::as_ptr(list) as *const T).or_insert_with(|| {
            self.lists.push(&**list);
            n
        })
    }
}

fn put_bytes(out: &mut Vec<u8>, b: &[u8]) {
    out.extend_from_slice(&(b.len() as u32).to_le_bytes());
    out.extend_from_slice(b);
}

fn put_lists<T>(out: &mut Vec<u8>, table: &Table<'_, T>, item: impl Fn(&mut Vec<u8>, &T)) {
    out.extend_from_slice(&(table.lists.len() as u32).to_le_bytes());
    for list in &table.lists {
        out.extend_from_slice(&(list.len() as u32).to_le_bytes());
        for x in list.iter() {
            item(out, x);
        }
    }
}

/// The records as bytes, rows sorted by direct key.
pub(super) fn encode(records: &Records) -> Vec<u8> {
    let mut rows: Vec<(&Key, &Arc<Row>)> = records.iter().collect();
    rows.sort_by_key(|r| r.0);
    let (mut files, mut absent, mut warnings) = (Table::new(), Table::new(), Table::new());
    let indices: Vec<[u32; 3]> =
        rows.iter().map(|(_, r)| [files.add(&r.files), absent.add(&r.absent), warnings.add(&r.warnings)]).collect();
    let mut out = MAGIC.to_vec();
    put_lists(&mut out, &files, |o, (p, h)| {
        put_bytes(o, p.as_os_str().as_bytes());
        o.extend_from_slice(h);
    });
    put_lists(&mut out, &absent, |o, p| put_bytes(o, p.as_os_str().as_bytes()));
    put_lists(&mut out, &warnings, |o, w| put_bytes(o, w.as_bytes()));
    out.extend_from_slice(&(rows.len() as u64).to_le_bytes());
    for ((direct, r), idx) in rows.iter().zip(indices) {
        out.extend_from_slice(&direct.0);
        out.extend_from_slice(&r.key.0);
        out.extend_from_slice(r.token_hash.as_bytes());
        out.extend_from_slice(r.text_hash.as_bytes());
        out.extend_from_slice(&r.text_len.to_le_bytes());
        for i in idx {
            out.extend_from_slice(&i.to_le_bytes());
        }
    }
    out
}

/// [`encode`] with every path under `root` written relative to it, so that the records
/// hold in any checkout of the same sources (another machine, another folder); paths
/// elsewhere stay absolute.
pub(super) fn encode_relative(records: &Records, root: &std::path::Path) -> Vec<u8> {
    encode(&relocate(records, |p| p.strip_prefix(root).ok().filter(|r| !r.as_os_str().is_empty()).map(PathBuf::from)))
}

/// [`decode`] of [`encode_relative`]'s bytes: relative paths are joined to `root`.
pub(super) fn decode_relative(bytes: &[u8], root: &std::path::Path) -> Option<Records> {
    Some(relocate(&decode(bytes)?, |p| p.is_relative().then(|| root.join(p))))
}

/// `records` with each path that `map` gives a new one for replaced; lists stay shared.
fn relocate(records: &Records, map: impl Fn(&std::path::Path) -> Option<PathBuf>) -> Records {
    let path = |p: &PathBuf| map(p).unwrap_or_else(|| p.clone());
    let mut files: HashMap<*const (PathBuf, [u8; 32]), FileList> = HashMap::new();
    let mut absent: HashMap<*const PathBuf, Arc<[PathBuf]>> = HashMap::new();
    let mut out = Records::with_capacity(records.len());
    for (direct, row) in records {
        let f = files
            .entry(Arc::as_ptr(&row.files) as *const _)
            .or_insert_with(|| row.files.iter().map(|(p, h)| (path(p), *h)).collect())
            .clone();
        let a = absent
            .entry(Arc::as_ptr(&row.absent) as *const _)
            .or_insert_with(|| row.absent.iter().map(path).collect())
            .clone();
        let moved = Row { files: f, absent: a, warnings: row.warnings.clone(), ..**row };
        out.insert(*direct, Arc::new(moved));
    }
    out
}

struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Option<&'a [u8]> {
        let end = self.at.checked_add(n).filter(|&e| e <= self.bytes.len())?;
        let s = &self.bytes[self.at..end];
        self.at = end;
        Some(s)
    }
    fn u32(&mut self) -> Option<u32> {
        Some(u32::from_le_bytes(self.take(4)?.try_into().ok()?))
    }
    fn u64(&mut self) -> Option<u64> {
        Some(u64::from_le_bytes(self.take(8)?.try_into().ok()?))
    }
    fn bytes(&mut self) -> Option<&'a [u8]> {
        let n = self.u32()? as usize;
        self.take(n)
    }
    fn hash(&mut self) -> Option<[u8; 32]> {
        self.take(32)?.try_into().ok()
    }
    fn lists<T>(&mut self, mut item: impl FnMut(&mut Self) -> Option<T>) -> Option<Vec<Arc<[T]>>> {
        let n = self.u32()? as usize;
        let mut out = Vec::with_capacity(n.min(1 << 16));
        for _ in 0..n {
            let len = self.u32()? as usize;
            let mut list = Vec::with_capacity(len.min(1 << 12));
            for _ in 0..len {
                list.push(item(self)?);
            }
            out.push(list.into());
        }
        Some(out)
    }
}

/// The records in `bytes`; `None` if they are not records of this encoding (the build then
/// preprocesses everything, as with no records).
pub(super) fn decode(bytes: &[u8]) -> Option<Records> {
    let mut r = Reader { bytes, at: 0 };
    if r.take(8)? != MAGIC {
        return None;
    }
    let path = |b: &[u8]| PathBuf::from(OsStr::from_bytes(b));
    let files = r.lists(|r| Some((path(r.bytes()?), r.hash()?)))?;
    let absent = r.lists(|r| Some(path(r.bytes()?)))?;
    let warnings = r.lists(|r| String::from_utf8(r.bytes()?.to_vec()).ok())?;
    let n = r.u64()?;
    let mut out = Records::with_capacity((n as usize).min(1 << 20));
    for _ in 0..n {
        let direct = Key(r.hash()?);
        let row = Row {
            key: Key(r.hash()?),
            token_hash: blake3::Hash::from_bytes(r.hash()?),
            text_hash: blake3::Hash::from_bytes(r.hash()?),
            text_len: r.u64()?,
            files: files.get(r.u32()? as usize)?.clone(),
            absent: absent.get(r.u32()? as usize)?.clone(),
            warnings: warnings.get(r.u32()? as usize)?.clone(),
        };
        out.insert(direct, Arc::new(row));
    }
    (r.at == bytes.len()).then_some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    #[test]
    fn round_trip_and_damage() {
        let mut i = Interner::default();
        let files = i.files(vec![(PathBuf::from("/a/b.ush"), [7; 32]), (PathBuf::from("/a/c.usf"), [9; 32])]);
        let row = |k: u8| {
            Arc::new(Row {
                key: Key([k; 32]),
                token_hash: blake3::hash(&[k]),
                text_hash: blake3::hash(&[k, 1]),
                text_len: 100 + k as u64,
                files: files.clone(),
                absent: i.absent.iter().next().cloned().unwrap_or_else(|| Arc::from(vec![PathBuf::from("/x")])),
                warnings: Arc::from(vec!["warning: w".to_string()]),
            })
        };
        let records: Records = (0..5u8).map(|k| (Key([k + 100; 32]), row(k))).collect();
        let bytes = encode(&records);
        assert_eq!(decode(&bytes), Some(records.clone()));
        // Shared lists are written once.
        assert_eq!(bytes.windows(8).filter(|w| w == b"/a/b.ush").count(), 1);
        for cut in [0, 7, 9, bytes.len() / 2, bytes.len() - 1] {
            assert_eq!(decode(&bytes[..cut]), None, "cut at {cut}");
        }
        assert_eq!(decode(b"not records"), None);
        assert_eq!(decode(&[]), None);

        // Relative to a root: the paths under it move with it, the others stay.
        let outside = i.files(vec![(PathBuf::from("/a/b.ush"), [7; 32]), (PathBuf::from("/usr/x.ush"), [1; 32])]);
        let mut moved = records.clone();
        let first = *moved.keys().next().unwrap();
        let row = &moved[&first];
        let row = Row { files: outside, absent: row.absent.clone(), warnings: row.warnings.clone(), ..**row };
        moved.insert(first, Arc::new(row));
        let bytes = encode_relative(&moved, Path::new("/a"));
        assert_eq!(bytes.windows(3).filter(|w| w == b"/a/").count(), 0, "no path under the root is absolute");
        let elsewhere = decode_relative(&bytes, Path::new("/b/c")).unwrap();
        assert_eq!(
            elsewhere[&first].files[..],
            [(PathBuf::from("/b/c/b.ush"), [7; 32]), (PathBuf::from("/usr/x.ush"), [1; 32])]
        );
        let other = *moved.keys().nth(1).unwrap();
        assert_eq!(elsewhere[&other].files[1].0, PathBuf::from("/b/c/c.usf"));
        assert_eq!(decode_relative(&bytes, Path::new("/a")), Some(moved));
    }
}
