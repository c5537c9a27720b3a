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
use std::fs::File;
use std::hash::Hash;
use std::io::Write;
use std::os::unix::ffi::OsStrExt;
use std::os::unix::fs::FileExt;
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

/// Each permutation's row by its direct key (see `preprocess::direct_key`), sorted by it:
/// the rows as the records file holds them. From the local cache they stay in the file,
/// read in place, with only each direct key's prefix in memory for the search (a warm
/// build's largest table was the rows read whole); from the remote cache (rare) they are in
/// memory, their list numbers made the interner's.
#[derive(Debug, Default)]
pub(super) struct Records {
    rows: Rows,
}

#[derive(Debug)]
enum Rows {
    Memory(Vec<u8>),
    File(InPlace),
}

impl Default for Rows {
    fn default() -> Self {
        Rows::Memory(Vec::new())
    }
}

/// Rows left in their file.
#[derive(Debug)]
struct InPlace {
    file: File,
    /// Where the rows start in the file.
    at: u64,
    /// Each row's direct key's first 8 bytes, big-endian so that they sort as the rows do:
    /// what a lookup searches before it reads the row.
    prefixes: Vec<u64>,
    /// The interner's number of each of the file's lists, by kind (files, absent, warnings).
    numbers: [Vec<u32>; 3],
}

/// Rows read at a time from a records file while it is checked or iterated.
const READ_ROWS: usize = 4096;

fn prefix_of(direct: &Direct) -> u64 {
    u64::from_be_bytes(direct[..8].try_into().expect("8 bytes"))
}

impl InPlace {
    /// A row read from the file, its lists numbered in the interner; `None` where the file
    /// no longer reads as it did when it was checked.
    fn row(&self, b: &[u8; ROW_BYTES]) -> Option<(Direct, Row)> {
        let (direct, row) = get_row(b);
        let number = |t: usize, id: u32| self.numbers[t].get(id as usize).copied();
        let row = Row {
            files: number(0, row.files)?,
            absent: number(1, row.absent)?,
            warnings: number(2, row.warnings)?,
            ..row
        };
        Some((direct, row))
    }

    /// Up to `n` rows from row `start` on.
    fn read(&self, start: usize, n: usize) -> Option<Vec<(Direct, Row)>> {
        let n = n.min(self.prefixes.len().saturating_sub(start));
        let mut buffer = vec![[0u8; ROW_BYTES]; n];
        self.file.read_exact_at(buffer.as_flattened_mut(), self.at + (start * ROW_BYTES) as u64).ok()?;
        buffer.iter().map(|b| self.row(b)).collect()
    }

    /// The row of `direct`: the rows that share its prefix are read, one at a time (two
    /// share one with odds near 2^-64 a pair).
    fn get(&self, direct: &Direct) -> Option<Row> {
        let prefix = prefix_of(direct);
        let first = self.prefixes.partition_point(|&p| p < prefix);
        let same = self.prefixes[first..].iter().take_while(|&&p| p == prefix).count();
        (first..first + same).find_map(|i| {
            let mut b = [0u8; ROW_BYTES];
            self.file.read_exact_at(&mut b, self.at + (i * ROW_BYTES) as u64).ok()?;
            self.row(&b).filter(|(d, _)| d == direct).map(|(_, row)| row)
        })
    }
}

impl PartialEq for Records {
    fn eq(&self, other: &Records) -> bool {
        self.len() == other.len() && self.iter().eq(other.iter())
    }
}

impl Records {
    /// The records of `rows` (one per direct key; of two, the first is kept).
    #[cfg(test)]
    pub fn new(mut rows: Vec<(Direct, Row)>) -> Records {
        rows.sort_by_key(|r| r.0);
        rows.dedup_by(|a, b| a.0 == b.0);
        let mut bytes = vec![0u8; rows.len() * ROW_BYTES];
        for (out, (direct, row)) in bytes.as_chunks_mut::<ROW_BYTES>().0.iter_mut().zip(&rows) {
            put_row(out, direct, row);
        }
        Records { rows: Rows::Memory(bytes) }
    }

    pub fn get(&self, direct: &Direct) -> Option<Row> {
        match &self.rows {
            Rows::Memory(bytes) => {
                let rows = bytes.as_chunks::<ROW_BYTES>().0;
                rows.binary_search_by(|r| r[..16].cmp(direct)).ok().map(|i| get_row(&rows[i]).1)
            }
            Rows::File(f) => f.get(direct),
        }
    }

    /// Each direct key with its row, in order (from a file, a few at a time: one that no
    /// longer reads ends there).
    pub fn iter(&self) -> Box<dyn Iterator<Item = (Direct, Row)> + '_> {
        match &self.rows {
            Rows::Memory(bytes) => Box::new(bytes.as_chunks::<ROW_BYTES>().0.iter().map(get_row)),
            Rows::File(f) => {
                Box::new((0..f.prefixes.len()).step_by(READ_ROWS).map_while(|start| f.read(start, READ_ROWS)).flatten())
            }
        }
    }

    pub fn len(&self) -> usize {
        match &self.rows {
            Rows::Memory(bytes) => bytes.len() / ROW_BYTES,
            Rows::File(f) => f.prefixes.len(),
        }
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

/// The records of `count` permutations, or `None` when they are `old`'s (or a temporary
/// file could not be used: failing to only costs preprocessing next time).
/// `row(i)` gives permutation `i`'s direct key and row (`None` where it failed); the records
/// are sorted by direct key, one per direct key, and every path under `root` is written
/// relative to it (paths elsewhere stay absolute).
///
/// An external sort, so that nothing per permutation is held in memory: the rows are
/// encoded (in parallel) a run at a time, each run sorted and written to a temporary file,
/// then the runs are merged, the lists renumbered by first reference, into a second
/// temporary file that [`Encoded`] streams from.
pub(super) fn encode(
    count: usize,
    row: impl Fn(usize) -> Option<(Direct, Row)> + Sync,
    interner: &Interner,
    root: &Path,
    old: Records,
) -> Option<Encoded> {
    let runs = sorted_runs(count, &row).ok()?;
    drop(row);
    let merged = merge_runs(&runs, &old).ok()??;
    drop((runs, old));
    let Merged { tables, rows, count } = merged;
    let head = head(&tables, interner, root, count);
    Some(Encoded { head, rows, rows_len: count as u64 * ROW_BYTES as u64 })
}

/// What comes before the rows: the magic, the lists the rows refer to (in `tables`' order,
/// paths under `root` relative to it) and the number of rows.
fn head(tables: &[Table; 3], interner: &Interner, root: &Path, count: usize) -> Vec<u8> {
    let relative = |p: &Path| -> PathBuf {
        p.strip_prefix(root).ok().filter(|r| !r.as_os_str().is_empty()).map_or_else(|| p.to_path_buf(), PathBuf::from)
    };
    let mut head = MAGIC.to_vec();
    put_lists(&mut head, &tables[0], &interner.files, |o, (p, h)| {
        put_bytes(o, relative(p).as_os_str().as_bytes());
        o.extend_from_slice(h);
    });
    put_lists(&mut head, &tables[1], &interner.absent, |o, p| put_bytes(o, relative(p).as_os_str().as_bytes()));
    put_lists(&mut head, &tables[2], &interner.warnings, |o, w| put_bytes(o, w.as_bytes()));
    head.extend_from_slice(&(count as u64).to_le_bytes());
    head
}

/// The encoding of a few records, whole in memory and on the calling thread (no temporary
/// file, no parallel sort: it is made while the caller holds the interner): a piece of a
/// shard's records. One row per direct key, the first of `rows` kept; [`decode`] reads it.
pub(super) fn encode_small(mut rows: Vec<(Direct, Row)>, interner: &Interner, root: &Path) -> Vec<u8> {
    rows.sort_by_key(|r| r.0);
    rows.dedup_by(|a, b| a.0 == b.0);
    let mut tables = [Table::new(), Table::new(), Table::new()];
    let mut bytes = vec![0u8; rows.len() * ROW_BYTES];
    for (out, (direct, row)) in bytes.as_chunks_mut::<ROW_BYTES>().0.iter_mut().zip(&rows) {
        let numbered = Row {
            files: tables[0].add(row.files),
            absent: tables[1].add(row.absent),
            warnings: tables[2].add(row.warnings),
            ..*row
        };
        put_row(out, direct, &numbered);
    }
    let mut out = head(&tables, interner, root, rows.len());
    out.extend_from_slice(&bytes);
    out
}

/// Encoded records: the lists and the count in memory, the rows in a temporary file.
pub(super) struct Encoded {
    head: Vec<u8>,
    rows: File,
    rows_len: u64,
}

impl Encoded {
    /// The length of the encoding.
    pub fn len(&self) -> u64 {
        self.head.len() as u64 + self.rows_len
    }

    /// Calls `f` on consecutive pieces of the encoding, the rows read again from their file
    /// through a small buffer.
    pub fn each_piece(&self, f: &mut dyn FnMut(&[u8]) -> std::io::Result<()>) -> std::io::Result<()> {
        f(&self.head)?;
        let mut buffer = vec![0u8; MERGE_ROWS * ROW_BYTES];
        let mut at = 0u64;
        while at < self.rows_len {
            let n = (self.rows_len - at).min(buffer.len() as u64) as usize;
            self.rows.read_exact_at(&mut buffer[..n], at)?;
            f(&buffer[..n])?;
            at += n as u64;
        }
        Ok(())
    }

    /// The whole encoding in memory.
    #[cfg(test)]
    pub fn to_vec(&self) -> std::io::Result<Vec<u8>> {
        let mut out = Vec::with_capacity(usize::try_from(self.len()).unwrap_or(0));
        self.each_piece(&mut |b| {
            out.extend_from_slice(b);
            Ok(())
        })?;
        Ok(out)
    }
}

/// Rows encoded, sorted and written at a time: a run's buffer is the encoding's largest
/// allocation.
const RUN_ROWS: usize = 1 << 14;

/// Rows read at a time from each run while they are merged.
const MERGE_ROWS: usize = 256;

/// The sorted runs of rows in one temporary file: the file and each run's (first row, rows).
struct Runs {
    file: File,
    runs: Vec<(u64, usize)>,
}

/// Encodes every permutation's row, a run at a time, each run sorted by direct key (the
/// failed ones left out) and appended to a temporary file.
fn sorted_runs(count: usize, row: &(impl Fn(usize) -> Option<(Direct, Row)> + Sync)) -> std::io::Result<Runs> {
    use rayon::prelude::*;
    let mut file = tempfile::tempfile()?;
    let mut runs = Vec::new();
    let mut buffer = vec![0u8; RUN_ROWS.min(count) * ROW_BYTES];
    let mut first = 0u64;
    for start in (0..count).step_by(RUN_ROWS) {
        let len = RUN_ROWS.min(count - start);
        let (rows, _) = buffer[..len * ROW_BYTES].as_chunks_mut::<ROW_BYTES>();
        rows.par_iter_mut().enumerate().for_each(|(i, r)| match row(start + i) {
            Some((direct, row)) => put_row(r, &direct, &row),
            // Failed: sorted last and cut off.
            None => r[..16].fill(0xFF),
        });
        let failed = rows.par_iter().filter(|r| r[..16] == [0xFF; 16]).count();
        // Stable: of two rows with one direct key, the earlier permutation's stays first.
        rows.par_sort_by(|a, b| a[..16].cmp(&b[..16]));
        let kept = len - failed;
        file.write_all(&buffer[..kept * ROW_BYTES])?;
        runs.push((first, kept));
        first += kept as u64;
    }
    Ok(Runs { file, runs })
}

/// The rows merged from their runs: the lists' tables, the rows in a temporary file with
/// their lists renumbered, and how many.
struct Merged {
    tables: [Table; 3],
    rows: File,
    count: usize,
}

/// One run being merged: its rows not read yet, and a buffer of those read.
struct RunReader {
    next: u64,
    left: usize,
    buffer: Vec<[u8; ROW_BYTES]>,
    at: usize,
}

impl RunReader {
    /// The run's current row, reading the next rows when the buffer is used up; `None` at
    /// its end.
    fn peek(&mut self, file: &File) -> std::io::Result<Option<&[u8; ROW_BYTES]>> {
        if self.at == self.buffer.len() {
            let n = self.left.min(MERGE_ROWS);
            if n == 0 {
                return Ok(None);
            }
            self.buffer.resize(n, [0; ROW_BYTES]);
            file.read_exact_at(self.buffer.as_flattened_mut(), self.next * ROW_BYTES as u64)?;
            (self.next, self.left, self.at) = (self.next + n as u64, self.left - n, 0);
        }
        Ok(Some(&self.buffer[self.at]))
    }
}

fn direct_of(row: &[u8; ROW_BYTES]) -> Direct {
    row[..16].try_into().expect("16 bytes")
}

/// Merges the runs in direct key order, one row per direct key (of two, the earlier
/// permutation's), renumbering the lists by first reference; `None` when the rows are
/// `old`'s.
fn merge_runs(runs: &Runs, old: &Records) -> std::io::Result<Option<Merged>> {
    use std::cmp::Reverse;
    use std::collections::BinaryHeap;
    let file = &runs.file;
    let mut readers: Vec<RunReader> =
        runs.runs.iter().map(|&(next, left)| RunReader { next, left, buffer: Vec::new(), at: 0 }).collect();
    // By direct key, then by run (runs are in permutation order): not by the rest of the
    // row, so that of two rows with one direct key the earlier permutation's is kept.
    let mut heap = BinaryHeap::new();
    for (i, r) in readers.iter_mut().enumerate() {
        if let Some(row) = r.peek(file)? {
            heap.push(Reverse((direct_of(row), i)));
        }
    }
    let mut out = std::io::BufWriter::with_capacity(MERGE_ROWS * ROW_BYTES, tempfile::tempfile()?);
    let mut tables = [Table::new(), Table::new(), Table::new()];
    let (mut old_rows, mut same, mut count) = (old.iter(), true, 0usize);
    let mut last: Option<Direct> = None;
    while let Some(Reverse((direct, i))) = heap.pop() {
        let mut row = readers[i].buffer[readers[i].at];
        readers[i].at += 1;
        if let Some(next) = readers[i].peek(file)? {
            heap.push(Reverse((direct_of(next), i)));
        }
        if last == Some(direct) {
            continue;
        }
        last = Some(direct);
        same = same && old_rows.next().is_some_and(|old| old == get_row(&row));
        for (t, table) in tables.iter_mut().enumerate() {
            let at = LISTS_AT + 4 * t;
            let id = u32::from_le_bytes(row[at..at + 4].try_into().expect("4 bytes"));
            row[at..at + 4].copy_from_slice(&table.add(id).to_le_bytes());
        }
        out.write_all(&row)?;
        count += 1;
    }
    if same && old_rows.next().is_none() {
        return Ok(None);
    }
    let rows = out.into_inner().map_err(|e| e.into_error())?;
    Ok(Some(Merged { tables, rows, count }))
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
/// `root`; `None` if they are not records of this encoding, or not sorted (the build then
/// preprocesses everything, as with no records). The rows stay in `bytes`: the lists in
/// front of them are cut off.
pub(super) fn decode(mut bytes: Vec<u8>, interner: &mut Interner, root: &Path) -> Option<Records> {
    let (numbers, n, at) = decode_head(&bytes, interner, root)?;
    if n.checked_mul(ROW_BYTES as u64)? != (bytes.len() - at) as u64 {
        return None;
    }
    let mut last: Option<Direct> = None;
    for row in bytes[at..].as_chunks_mut::<ROW_BYTES>().0 {
        let direct = direct_of(row);
        // Strictly ascending, as written: lookups search them.
        if last.is_some_and(|l| l >= direct) {
            return None;
        }
        last = Some(direct);
        for (t, numbers) in numbers.iter().enumerate() {
            let at = LISTS_AT + 4 * t;
            let id = u32::from_le_bytes(row[at..at + 4].try_into().expect("4 bytes"));
            row[at..at + 4].copy_from_slice(&numbers.get(id as usize)?.to_le_bytes());
        }
    }
    bytes.drain(..at);
    Some(Records { rows: Rows::Memory(bytes) })
}

/// Records as the cache holds them: the local file, to be read in place (its body's start
/// and length; its checksum was checked), or a body in memory (the remote cache's).
pub(super) enum Stored {
    File { file: File, at: u64, len: u64 },
    Bytes(Vec<u8>),
}

/// [`decode`] for records as the cache holds them: a file's rows stay in it, checked
/// through a small buffer.
pub(super) fn decode_stored(stored: Stored, interner: &mut Interner, root: &Path) -> Option<Records> {
    match stored {
        Stored::Bytes(bytes) => decode(bytes, interner, root),
        Stored::File { file, at, len } => decode_file(file, at, len, interner, root),
    }
}

/// Bytes read first for the lists in front of a file's rows (doubled until they fit).
const HEAD_READ: u64 = 1 << 20;

/// [`decode`] for the body of `len` bytes at `at` in `file`: the lists are read whole (few
/// beside the rows), the rows checked a few at a time and left in the file, only their
/// direct keys' prefixes kept.
fn decode_file(file: File, at: u64, len: u64, interner: &mut Interner, root: &Path) -> Option<Records> {
    let mut magic = [0u8; 8];
    file.read_exact_at(&mut magic, at).ok()?;
    // Another encoding is not read further (nor read whole to find its lists).
    if &magic != MAGIC {
        return None;
    }
    let mut want = HEAD_READ.min(len);
    let (numbers, n, head) = loop {
        let mut bytes = vec![0u8; usize::try_from(want).ok()?];
        file.read_exact_at(&mut bytes, at).ok()?;
        match decode_head(&bytes, interner, root) {
            Some(h) => break h,
            None if want < len => want = want.saturating_mul(2).min(len),
            None => return None,
        }
    };
    let count = usize::try_from(n).ok()?;
    if n.checked_mul(ROW_BYTES as u64)? != len - head as u64 {
        return None;
    }
    let rows_at = at + head as u64;
    let mut prefixes = Vec::with_capacity(count);
    let mut buffer = vec![[0u8; ROW_BYTES]; READ_ROWS.min(count)];
    let mut last: Option<Direct> = None;
    for start in (0..count).step_by(READ_ROWS) {
        let chunk = &mut buffer[..READ_ROWS.min(count - start)];
        file.read_exact_at(chunk.as_flattened_mut(), rows_at + (start * ROW_BYTES) as u64).ok()?;
        for row in chunk.iter() {
            let direct = direct_of(row);
            // Strictly ascending, as written: lookups search them.
            if last.is_some_and(|l| l >= direct) {
                return None;
            }
            last = Some(direct);
            for (t, numbers) in numbers.iter().enumerate() {
                let id = u32::from_le_bytes(row[LISTS_AT + 4 * t..LISTS_AT + 4 + 4 * t].try_into().expect("4 bytes"));
                numbers.get(id as usize)?;
            }
            prefixes.push(prefix_of(&direct));
        }
    }
    Some(Records { rows: Rows::File(InPlace { file, at: rows_at, prefixes, numbers }) })
}

/// The lists in front of the rows, interned into `interner` (each list's number there, by
/// kind), the number of rows and where they start; `None` if `bytes` does not hold them
/// whole or they are not of this encoding.
fn decode_head(bytes: &[u8], interner: &mut Interner, root: &Path) -> Option<([Vec<u32>; 3], u64, usize)> {
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
    Some(([files, absent, warnings], n, r.at))
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
        encode(rows.len(), |n| Some(rows[n]), i, root, Records::default()).unwrap().to_vec().unwrap()
    }

    #[test]
    fn round_trip_and_damage() {
        let mut i = Interner::default();
        let files = vec![(PathBuf::from("/a/b.ush"), [7; 32]), (PathBuf::from("/usr/x.ush"), [1; 32])];
        let rows: Vec<(Direct, Row)> = (0..5u8).rev().map(|k| ([k + 100; 16], row(&mut i, k, files.clone()))).collect();
        let records = Records::new(rows.clone());
        assert_eq!(records.len(), 5);
        assert_eq!(records.get(&[102; 16]), Some(rows[2].1));
        assert_eq!(records.get(&[1; 16]), None);
        let bytes = encode_all(&rows, &i, Path::new("/a"));
        // Shared lists are written once; no path under the root is absolute.
        assert_eq!(bytes.windows(10).filter(|w| w == b"/usr/x.ush").count(), 1);
        assert_eq!(bytes.windows(3).filter(|w| w == b"/a/").count(), 0);

        // Decoded at the same root into the same interner: the same records.
        assert_eq!(decode(bytes.clone(), &mut i, Path::new("/a")), Some(Records::new(rows.clone())));
        // Elsewhere: the paths under the root move with it, the others stay.
        let mut j = Interner::default();
        let elsewhere = decode(bytes.clone(), &mut j, Path::new("/b/c")).unwrap();
        let moved = elsewhere.get(&[100; 16]).unwrap();
        assert_eq!(
            j.files.get(moved.files)[..],
            [(PathBuf::from("/b/c/b.ush"), [7; 32]), (PathBuf::from("/usr/x.ush"), [1; 32])]
        );
        assert_eq!(j.absent.get(moved.absent)[..], [PathBuf::from("/b/c/missing.ush")]);
        assert_eq!(j.warnings.get(moved.warnings)[..], ["warning: w".to_string()]);
        assert_eq!(moved.text_len, 100);

        for cut in [0, 7, 9, bytes.len() / 2, bytes.len() - 1] {
            assert_eq!(decode(bytes[..cut].to_vec(), &mut Interner::default(), Path::new("/a")), None, "cut at {cut}");
        }
        let mut long = bytes.clone();
        long.push(0);
        assert_eq!(decode(long, &mut Interner::default(), Path::new("/a")), None);
        // Rows out of order are not searched.
        let mut swapped = bytes.clone();
        let end = swapped.len();
        let last: Vec<u8> = swapped[end - ROW_BYTES..].to_vec();
        swapped.copy_within(end - 2 * ROW_BYTES..end - ROW_BYTES, end - ROW_BYTES);
        swapped[end - 2 * ROW_BYTES..end - ROW_BYTES].copy_from_slice(&last);
        assert_eq!(decode(swapped, &mut Interner::default(), Path::new("/a")), None);
        assert_eq!(decode(b"not records".to_vec(), &mut Interner::default(), Path::new("/a")), None);
        // Records of the last encoding are not read.
        let mut old = bytes.clone();
        old[7] = 2;
        assert_eq!(decode(old, &mut Interner::default(), Path::new("/a")), None);
    }

    #[test]
    fn small_encoding_reads_like_the_large_one() {
        let mut i = Interner::default();
        let files = vec![(PathBuf::from("/a/b.ush"), [7; 32])];
        let mut rows: Vec<(Direct, Row)> =
            (0..9u8).rev().map(|k| ([k % 5; 16], row(&mut i, k, files.clone()))).collect();
        rows.push(([200; 16], row(&mut i, 9, vec![(PathBuf::from("/usr/x.ush"), [1; 32])])));
        let small = encode_small(rows.clone(), &i, Path::new("/a"));
        assert_eq!(small, encode_all(&rows, &i, Path::new("/a")), "the same bytes as the external sort's");
        let decoded = decode(small, &mut Interner::default(), Path::new("/a")).unwrap();
        assert_eq!(decoded.len(), 6, "one row per direct key");
    }

    /// `body` in a file behind 40 bytes (where the cache's magic and checksum go).
    fn stored(body: &[u8]) -> Stored {
        let mut file = tempfile::tempfile().unwrap();
        file.write_all(&[0u8; 40]).unwrap();
        file.write_all(body).unwrap();
        Stored::File { file, at: 40, len: body.len() as u64 }
    }

    #[test]
    fn records_read_in_place_read_like_those_in_memory() {
        let mut i = Interner::default();
        let n = READ_ROWS + 100;
        let lists: Vec<Row> =
            (0..3u8).map(|k| row(&mut i, k, vec![(PathBuf::from(format!("/a/{k}.ush")), [k; 32])])).collect();
        let direct = |n: usize| -> Direct { *blake3::hash(&n.to_le_bytes()).as_bytes().first_chunk().unwrap() };
        let rows: Vec<(Direct, Row)> =
            (0..n).map(|n| (direct(n), Row { key: Key([n as u8; 32]), ..lists[n % 3] })).collect();
        let bytes = encode_all(&rows, &i, Path::new("/a"));
        let mut j = Interner::default();
        let in_place = decode_stored(stored(&bytes), &mut j, Path::new("/b")).unwrap();
        let mut k = Interner::default();
        let memory = decode(bytes.clone(), &mut k, Path::new("/b")).unwrap();
        assert!(matches!(in_place.rows, Rows::File(_)));
        assert_eq!(in_place.len(), n);
        assert!(in_place == memory, "the same rows, in order");
        for (n, (d, _)) in rows.iter().enumerate().step_by(97) {
            let found = in_place.get(d).unwrap();
            assert_eq!(found, memory.get(d).unwrap());
            let k = n % 3;
            assert_eq!(j.files.get(found.files)[..], [(PathBuf::from(format!("/b/{k}.ush")), [k as u8; 32])]);
        }
        assert_eq!(in_place.get(&[7; 16]), None);

        // Damaged or another encoding: not read.
        let mut old = bytes.clone();
        old[7] = 2;
        assert!(decode_stored(stored(&old), &mut Interner::default(), Path::new("/b")).is_none());
        let mut swapped = bytes.clone();
        let end = swapped.len();
        swapped[end - ROW_BYTES..end - ROW_BYTES + 16].copy_from_slice(&[0; 16]);
        assert!(decode_stored(stored(&swapped), &mut Interner::default(), Path::new("/b")).is_none());
        assert!(decode_stored(stored(&bytes[..bytes.len() - 1]), &mut Interner::default(), Path::new("/b")).is_none());
        assert!(decode_stored(stored(b"KILNREC"), &mut Interner::default(), Path::new("/b")).is_none());
    }

    #[test]
    fn runs_merge_like_one_sort() {
        // More rows than a run, some failed, one direct key twice (the first is kept).
        let mut i = Interner::default();
        let n = RUN_ROWS * 2 + 1000;
        let lists: Vec<Row> =
            (0..3u8).map(|k| row(&mut i, k, vec![(PathBuf::from(format!("/a/{k}.ush")), [k; 32])])).collect();
        let direct = |n: usize| -> Direct {
            *blake3::hash(&(n % (RUN_ROWS * 2)).to_le_bytes()).as_bytes().first_chunk().unwrap()
        };
        let at = |n: usize| (n % 7 != 3).then(|| (direct(n), Row { key: Key([n as u8; 32]), ..lists[n % 3] }));
        let bytes = encode(n, at, &i, Path::new("/a"), Records::default()).unwrap().to_vec().unwrap();
        let mut expected: Vec<(Direct, Row)> = (0..n).filter_map(at).collect();
        expected.sort_by_key(|r| r.0);
        expected.dedup_by(|a, b| a.0 == b.0);
        let decoded = decode(bytes.clone(), &mut i, Path::new("/a")).unwrap();
        assert_eq!(decoded.len(), expected.len());
        assert!(decoded.iter().zip(&expected).all(|(a, b)| a == *b));
        // The same rows as the last build's: nothing to write.
        assert!(encode(n, at, &i, Path::new("/a"), decoded).is_none());
    }
}
