//! Preprocessing records, compact: what preprocessing one permutation gave ([`Row`]), and
//! the binary encoding of a configuration's set of them (stored by the cache under one key).
//!
//! A [`Row`] is fixed-size: its lists of files, missing include candidates and warnings are
//! numbers in the build's [`Interner`] (many permutations read the same files). A set of
//! records is one table sorted by direct key, looked up by binary search: no allocation
//! per permutation, in memory or on disk.
//!
//! ```text
//! magic "KILNREC\x03"
//! u32 count, then each file list:    u32 n, n x (u32 len, path bytes, 32-byte blake3 of its text)
//! u32 count, then each absent list:  u32 n, n x (u32 len, path bytes)
//! u32 count, then each warning list: u32 n, n x (u32 len, UTF-8 text)
//! u64 count, then each row (sorted by direct key): direct key (16), key (32),
//!     text length (u32, saturating), file list, absent list, warning list (u32 indices)
//! ```
//!
//! Paths under the configuration's folder are written relative to it, so that the records
//! hold in any checkout of the same sources (another machine, another folder).

use std::collections::HashMap;
use std::ffi::OsStr;
use std::hash::Hash;
use std::os::unix::ffi::OsStrExt;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use crate::cache::Key;

const MAGIC: &[u8; 8] = b"KILNREC\x03";

/// A permutation's direct key (see `preprocess::direct_key`): a prefix of a
/// blake3, as long as the cache's pack names (a collision among 2^32 permutations has odds
/// near 2^-64), so that a record is smaller than with the whole hash, on disk and in the buffer a build encodes them
/// in (where the build peaks).
pub(super) type Direct = [u8; 16];

/// A file read, with the blake3 of the text the preprocessor read.
pub(super) type FileEntry = (PathBuf, [u8; 32]);

/// What preprocessing one permutation gave.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct Row {
    pub key: Key,
    /// Length of the preprocessed text (the key's estimated compile cost), saturating: 48
    /// bytes a row rather than 56.
    pub text_len: u32,
    /// Files read ([`Interner::files`]).
    pub files: u32,
    /// Include candidates that were missing ([`Interner::absent`]): the record holds only
    /// while they still are.
    pub absent: u32,
    /// Preprocessor warnings, rendered without colour ([`Interner::warnings`]).
    pub warnings: u32,
}

/// Each permutation's row by its direct key (see `preprocess::direct_key`), sorted by it.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub(super) struct Records {
    rows: Vec<(Direct, Row)>,
}

impl Records {
    /// The records of `rows` (one per direct key; of two, the first is kept).
    pub fn new(mut rows: Vec<(Direct, Row)>) -> Records {
        rows.sort_by_key(|r| r.0);
        rows.dedup_by(|a, b| a.0 == b.0);
        rows.shrink_to_fit();
        Records { rows }
    }

    pub fn get(&self, direct: &Direct) -> Option<&Row> {
        self.rows.binary_search_by(|r| r.0.cmp(direct)).ok().map(|i| &self.rows[i].1)
    }

    /// Each direct key with its row, in order.
    pub fn iter(&self) -> impl Iterator<Item = (&Direct, &Row)> + Clone {
        self.rows.iter().map(|(k, r)| (k, r))
    }

    pub fn len(&self) -> usize {
        self.rows.len()
    }
}

/// Distinct lists, each numbered by first appearance.
pub(super) struct Lists<T> {
    lists: Vec<Arc<[T]>>,
    index: HashMap<Arc<[T]>, u32>,
}

impl<T> Default for Lists<T> {
    fn default() -> Self {
        Lists { lists: Vec::new(), index: HashMap::new() }
    }
}

impl<T: Eq + Hash> Lists<T> {
    /// The number of `v`, equal lists sharing one.
    pub fn intern(&mut self, v: Vec<T>) -> u32 {
        if let Some(&i) = self.index.get(&v[..]) {
            return i;
        }
        let i = self.lists.len() as u32;
        let a: Arc<[T]> = v.into();
        self.lists.push(a.clone());
        self.index.insert(a, i);
        i
    }
}

impl<T> Lists<T> {
    pub fn get(&self, i: u32) -> &Arc<[T]> {
        &self.lists[i as usize]
    }

    pub fn len(&self) -> usize {
        self.lists.len()
    }
}

/// Interns lists so that equal lists share one number.
#[derive(Default)]
pub(super) struct Interner {
    pub files: Lists<FileEntry>,
    pub absent: Lists<PathBuf>,
    pub warnings: Lists<String>,
}

/// The lists of one kind that rows refer to, renumbered in order of first reference.
struct Table {
    number: HashMap<u32, u32>,
    order: Vec<u32>,
}

impl Table {
    fn new() -> Self {
        Table { number: HashMap::new(), order: Vec::new() }
    }
    fn add(&mut self, id: u32) -> u32 {
        let n = self.order.len() as u32;
        *self.number.entry(id).or_insert_with(|| {
            self.order.push(id);
            n
        })
    }
}

fn put_bytes(out: &mut Vec<u8>, b: &[u8]) {
    out.extend_from_slice(&(b.len() as u32).to_le_bytes());
    out.extend_from_slice(b);
}

fn put_lists<T>(out: &mut Vec<u8>, table: &Table, lists: &Lists<T>, item: impl Fn(&mut Vec<u8>, &T)) {
    out.extend_from_slice(&(table.order.len() as u32).to_le_bytes());
    for &id in &table.order {
        let list = lists.get(id);
        out.extend_from_slice(&(list.len() as u32).to_le_bytes());
        for x in list.iter() {
            item(out, x);
        }
    }
}

/// The records of `count` permutations as bytes, or `None` when they are `old`'s.
/// `row(i)` gives permutation `i`'s direct key and row (`None` where it failed), one of
/// `all`; the records are sorted by direct key, one per direct key, and every path under
/// `root` is written relative to it (paths elsewhere stay absolute).
///
/// The rows are encoded straight into the buffer that is returned (in parallel), sorted
/// and renumbered there, and the lists written in front of them: nothing per row is held
/// besides those bytes (a table of (direct key, row) to sort took more per permutation).
pub(super) fn encode(
    count: usize,
    row: impl Fn(usize) -> Option<(Direct, Row)> + Sync,
    all: impl Iterator<Item = Row>,
    interner: &Interner,
    root: &Path,
    old: Records,
) -> Option<Vec<u8>> {
    use rayon::prelude::*;
    let relative = |p: &Path| -> PathBuf {
        p.strip_prefix(root).ok().filter(|r| !r.as_os_str().is_empty()).map_or_else(|| p.to_path_buf(), PathBuf::from)
    };
    let lists = |out: &mut Vec<u8>, tables: &[Table; 3]| {
        put_lists(out, &tables[0], &interner.files, |o, (p, h)| {
            put_bytes(o, relative(p).as_os_str().as_bytes());
            o.extend_from_slice(h);
        });
        put_lists(out, &tables[1], &interner.absent, |o, p| put_bytes(o, relative(p).as_os_str().as_bytes()));
        put_lists(out, &tables[2], &interner.warnings, |o, w| put_bytes(o, w.as_bytes()));
    };
    // Room in front for the lists of every row (those of the rows kept are as long or
    // shorter: a list's bytes do not depend on its number).
    let mut every = [Table::new(), Table::new(), Table::new()];
    for r in all {
        every[0].add(r.files);
        every[1].add(r.absent);
        every[2].add(r.warnings);
    }
    let mut head = MAGIC.to_vec();
    lists(&mut head, &every);
    let room = head.len() + 8;
    drop((head, every));
    let mut out = vec![0u8; room + count * ROW_BYTES];
    let (rows, _) = out[room..].as_chunks_mut::<ROW_BYTES>();
    rows.par_iter_mut().enumerate().for_each(|(i, r)| match row(i) {
        Some((direct, row)) => put_row(r, &direct, &row),
        // Failed: sorted last and cut off.
        None => r[..16].fill(0xFF),
    });
    let failed = rows.par_iter().filter(|r| r[..16] == [0xFF; 16]).count();
    rows.par_sort_unstable_by(|a, b| a[..16].cmp(&b[..16]));
    // One record per direct key (each permutation has its own): of two, the first.
    let mut n = 0;
    for i in 0..count - failed {
        if n == 0 || rows[n - 1][..16] != rows[i][..16] {
            rows[n] = rows[i];
            n += 1;
        }
    }
    let rows = &mut rows[..n];
    if rows.iter().map(get_row).eq(old.iter().map(|(k, r)| (*k, *r))) {
        return None;
    }
    drop(old);
    // The lists numbered by first reference, in the rows' order.
    let mut tables = [Table::new(), Table::new(), Table::new()];
    for r in rows.iter_mut() {
        for (t, table) in tables.iter_mut().enumerate() {
            let at = LISTS_AT + 4 * t;
            let id = u32::from_le_bytes(r[at..at + 4].try_into().expect("4 bytes"));
            r[at..at + 4].copy_from_slice(&table.add(id).to_le_bytes());
        }
    }
    let mut head = MAGIC.to_vec();
    lists(&mut head, &tables);
    head.extend_from_slice(&(n as u64).to_le_bytes());
    // The rows kept and the lists just before them; the unused room in front goes (the
    // bytes move down in place).
    out.truncate(room + n * ROW_BYTES);
    let skip = room - head.len();
    out[skip..room].copy_from_slice(&head);
    out.drain(..skip);
    Some(out)
}

/// Writes a row with its lists' numbers in the interner (renumbered by [`encode`]).
fn put_row(out: &mut [u8; ROW_BYTES], direct: &Direct, r: &Row) {
    out[..16].copy_from_slice(direct);
    out[16..48].copy_from_slice(&r.key.0);
    out[48..52].copy_from_slice(&r.text_len.to_le_bytes());
    for (t, id) in [r.files, r.absent, r.warnings].into_iter().enumerate() {
        out[LISTS_AT + 4 * t..LISTS_AT + 4 + 4 * t].copy_from_slice(&id.to_le_bytes());
    }
}

/// A row [`put_row`] wrote.
fn get_row(b: &[u8; ROW_BYTES]) -> (Direct, Row) {
    let u32_at = |at: usize| u32::from_le_bytes(b[at..at + 4].try_into().expect("4 bytes"));
    let row = Row {
        key: Key(b[16..48].try_into().expect("32 bytes")),
        text_len: u32_at(48),
        files: u32_at(LISTS_AT),
        absent: u32_at(LISTS_AT + 4),
        warnings: u32_at(LISTS_AT + 8),
    };
    (b[..16].try_into().expect("16 bytes"), row)
}

/// An encoded row: direct key, key, text length, three list numbers.
const ROW_BYTES: usize = 16 + 32 + 4 + 3 * 4;

/// Where a row's list numbers start.
const LISTS_AT: usize = 52;

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
    /// Each list read, interned: the numbers in `lists`.
    fn lists<T: Eq + Hash>(
        &mut self,
        lists: &mut Lists<T>,
        mut item: impl FnMut(&mut Self) -> Option<T>,
    ) -> Option<Vec<u32>> {
        let n = self.u32()? as usize;
        let mut out = Vec::with_capacity(n.min(1 << 16));
        for _ in 0..n {
            let len = self.u32()? as usize;
            let mut list = Vec::with_capacity(len.min(1 << 12));
            for _ in 0..len {
                list.push(item(self)?);
            }
            out.push(lists.intern(list));
        }
        Some(out)
    }
}

/// The records in `bytes`, their lists interned into `interner`, relative paths joined to
/// `root`; `None` if they are not records of this encoding (the build then preprocesses
/// everything, as with no records).
pub(super) fn decode(bytes: &[u8], interner: &mut Interner, root: &Path) -> Option<Records> {
    let mut r = Reader { bytes, at: 0 };
    if r.take(8)? != MAGIC {
        return None;
    }
    let path = |b: &[u8]| {
        let p = Path::new(OsStr::from_bytes(b));
        if p.is_relative() {
            root.join(p)
        } else {
            p.to_path_buf()
        }
    };
    let files = r.lists(&mut interner.files, |r| Some((path(r.bytes()?), r.hash()?)))?;
    let absent = r.lists(&mut interner.absent, |r| Some(path(r.bytes()?)))?;
    let warnings = r.lists(&mut interner.warnings, |r| String::from_utf8(r.bytes()?.to_vec()).ok())?;
    let n = r.u64()?;
    // A count beyond the bytes left is damage, not an allocation.
    if n > ((bytes.len() - r.at) / ROW_BYTES) as u64 {
        return None;
    }
    let mut rows = Vec::with_capacity(n as usize);
    for _ in 0..n {
        let direct: Direct = r.take(16)?.try_into().ok()?;
        let row = Row {
            key: Key(r.hash()?),
            text_len: r.u32()?,
            files: *files.get(r.u32()? as usize)?,
            absent: *absent.get(r.u32()? as usize)?,
            warnings: *warnings.get(r.u32()? as usize)?,
        };
        rows.push((direct, row));
    }
    (r.at == bytes.len()).then(|| Records::new(rows))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(i: &mut Interner, k: u8, files: Vec<FileEntry>) -> Row {
        Row {
            key: Key([k; 32]),
            text_len: 100 + k as u32,
            files: i.files.intern(files),
            absent: i.absent.intern(vec![PathBuf::from("/a/missing.ush")]),
            warnings: i.warnings.intern(vec!["warning: w".to_string()]),
        }
    }

    fn encode_all(rows: &[(Direct, Row)], i: &Interner, root: &Path) -> Vec<u8> {
        let all: Vec<Row> = rows.iter().map(|r| r.1).collect();
        encode(rows.len(), |n| Some(rows[n]), all.iter().copied(), i, root, Records::default()).unwrap()
    }

    #[test]
    fn round_trip_and_damage() {
        let mut i = Interner::default();
        let files = vec![(PathBuf::from("/a/b.ush"), [7; 32]), (PathBuf::from("/usr/x.ush"), [1; 32])];
        let rows: Vec<(Direct, Row)> = (0..5u8).rev().map(|k| ([k + 100; 16], row(&mut i, k, files.clone()))).collect();
        let records = Records::new(rows.clone());
        assert_eq!(records.len(), 5);
        assert_eq!(records.get(&[102; 16]), Some(&rows[2].1));
        assert_eq!(records.get(&[1; 16]), None);
        let bytes = encode_all(&rows, &i, Path::new("/a"));
        // Shared lists are written once; no path under the root is absolute.
        assert_eq!(bytes.windows(10).filter(|w| w == b"/usr/x.ush").count(), 1);
        assert_eq!(bytes.windows(3).filter(|w| w == b"/a/").count(), 0);

        // Decoded at the same root into the same interner: the same records.
        assert_eq!(decode(&bytes, &mut i, Path::new("/a")), Some(records.clone()));
        // Elsewhere: the paths under the root move with it, the others stay.
        let mut j = Interner::default();
        let elsewhere = decode(&bytes, &mut j, Path::new("/b/c")).unwrap();
        let moved = elsewhere.get(&[100; 16]).unwrap();
        assert_eq!(
            j.files.get(moved.files)[..],
            [(PathBuf::from("/b/c/b.ush"), [7; 32]), (PathBuf::from("/usr/x.ush"), [1; 32])]
        );
        assert_eq!(j.absent.get(moved.absent)[..], [PathBuf::from("/b/c/missing.ush")]);
        assert_eq!(j.warnings.get(moved.warnings)[..], ["warning: w".to_string()]);
        assert_eq!(moved.text_len, 100);

        for cut in [0, 7, 9, bytes.len() / 2, bytes.len() - 1] {
            assert_eq!(decode(&bytes[..cut], &mut Interner::default(), Path::new("/a")), None, "cut at {cut}");
        }
        let mut long = bytes.clone();
        long.push(0);
        assert_eq!(decode(&long, &mut Interner::default(), Path::new("/a")), None);
        assert_eq!(decode(b"not records", &mut Interner::default(), Path::new("/a")), None);
        // Records of the last encoding are not read.
        let mut old = bytes.clone();
        old[7] = 2;
        assert_eq!(decode(&old, &mut Interner::default(), Path::new("/a")), None);
    }
}
