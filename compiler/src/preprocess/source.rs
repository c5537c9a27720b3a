//! The source cache: every file read once per process, translation phases 1 and 2
//! (trigraphs, line splices) done once, and a table to map the spliced text back to the
//! original bytes for diagnostics.

use std::collections::HashMap;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::{Arc, RwLock};

use codespan_reporting::diagnostic::Label;
use codespan_reporting::files::{self, Files};

use super::lexer::{self, Kind};

/// Largest source file (offsets are 32-bit, with room for splicing).
pub(crate) const MAX_FILE_BYTES: u64 = (u32::MAX / 2) as u64;

/// Files larger than this get no token table (it takes four bytes per byte of text): they
/// are lexed as they are read, so a huge input costs little more memory than its text.
const MAX_TABLE_TEXT: usize = 16 << 20;

/// Lengths up to this fit in a token table entry; longer tokens are lexed each time.
const MAX_PACKED_LEN: usize = (1 << 27) - 1;

/// One entry of a token table: kind code (low 5 bits, 0 = no entry) and length.
fn pack(kind: Kind, len: usize) -> u32 {
    let code = match kind {
        Kind::Space => 1,
        Kind::Newline => 2,
        Kind::LineComment => 3,
        Kind::BlockComment { terminated: true } => 4,
        Kind::BlockComment { terminated: false } => 5,
        Kind::Ident => 6,
        Kind::Number => 7,
        Kind::Str { terminated: true } => 8,
        Kind::Str { terminated: false } => 9,
        Kind::Char { terminated: true } => 10,
        Kind::Char { terminated: false } => 11,
        Kind::Punct => 12,
        Kind::Other => 13,
        Kind::Eof => return 0,
    };
    if len > MAX_PACKED_LEN {
        return 0;
    }
    code | (len as u32) << 5
}

fn unpack(entry: u32) -> Option<(Kind, usize)> {
    let kind = match entry & 31 {
        1 => Kind::Space,
        2 => Kind::Newline,
        3 => Kind::LineComment,
        4 => Kind::BlockComment { terminated: true },
        5 => Kind::BlockComment { terminated: false },
        6 => Kind::Ident,
        7 => Kind::Number,
        8 => Kind::Str { terminated: true },
        9 => Kind::Str { terminated: false },
        10 => Kind::Char { terminated: true },
        11 => Kind::Char { terminated: false },
        12 => Kind::Punct,
        13 => Kind::Other,
        _ => return None,
    };
    Some((kind, (entry >> 5) as usize))
}

/// The packed token at each token start of one lexing pass over `text`.
fn token_table(text: &[u8]) -> Box<[u32]> {
    let mut table = vec![0u32; text.len()];
    let mut pos = 0;
    while pos < text.len() {
        let (kind, len) = lexer::next(text, pos);
        table[pos] = pack(kind, len);
        pos += len.max(1);
    }
    table.into_boxed_slice()
}

/// A file known to a [`SourceCache`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct FileId(pub(crate) u32);

/// One file: its original text and the text the lexer sees.
#[derive(Debug)]
pub struct SourceFile {
    /// The canonical path (for in-memory files, the name).
    pub path: PathBuf,
    /// The name used in diagnostics.
    pub name: String,
    /// The text as read.
    pub original: String,
    /// The text after trigraph replacement and line splicing (`None`: same as `original`).
    spliced: Option<String>,
    /// `(spliced offset, original offset)` at each point where the two stop moving together.
    splices: Vec<(u32, u32)>,
    line_starts: Vec<usize>,
    /// The first byte that is not UTF-8 (its offset and value); `original` then holds the
    /// text with U+FFFD in its place (at the same offset), for showing the error.
    pub(crate) bad_utf8: Option<(usize, u8)>,
    /// The lexer's answer at each token start of one pass over [`SourceFile::text`],
    /// packed (see [`SourceFile::lex`]); 0 elsewhere. Made on first use: every
    /// permutation then reads its tokens instead of lexing the file again.
    tokens: std::sync::OnceLock<Box<[u32]>>,
}

impl SourceFile {
    /// `lexer::next(self.text(), pos)`, from the file's token table where `pos` is a
    /// token start of the pass from the file's beginning (the preprocessor's positions
    /// almost always are), else lexed now.
    #[inline]
    pub(crate) fn lex(&self, pos: usize) -> (Kind, usize) {
        if self.text().len() > MAX_TABLE_TEXT {
            return lexer::next(self.text().as_bytes(), pos);
        }
        let table = self.tokens.get_or_init(|| token_table(self.text().as_bytes()));
        match table.get(pos).and_then(|&t| unpack(t)) {
            Some(token) => token,
            None => lexer::next(self.text().as_bytes(), pos),
        }
    }

    fn new(path: PathBuf, name: String, original: String) -> SourceFile {
        let (spliced, splices) = splice(&original);
        let line_starts = line_starts(original.as_bytes());
        SourceFile {
            path,
            name,
            original,
            spliced,
            splices,
            line_starts,
            bad_utf8: None,
            tokens: std::sync::OnceLock::new(),
        }
    }

    /// The text the lexer works on.
    pub fn text(&self) -> &str {
        self.spliced.as_deref().unwrap_or(&self.original)
    }

    /// Original byte offset of spliced offset `at`.
    pub fn original_offset(&self, at: usize) -> usize {
        if self.splices.is_empty() {
            return at;
        }
        let i = self.splices.partition_point(|&(s, _)| s as usize <= at);
        if i == 0 {
            return at;
        }
        let (s, o) = self.splices[i - 1];
        (o as usize + (at - s as usize)).min(self.original.len())
    }

    /// Original byte range of a spliced range, widened to character boundaries.
    pub fn original_range(&self, r: Range<usize>) -> Range<usize> {
        let text = &self.original;
        let mut start = self.original_offset(r.start).min(text.len());
        while !text.is_char_boundary(start) {
            start -= 1;
        }
        if r.end <= r.start {
            return start..start;
        }
        // The end is just after the last byte: map the last byte and step past its character.
        let mut end = (self.original_offset(r.end - 1) + 1).min(text.len()).max(start);
        while !text.is_char_boundary(end) {
            end += 1;
        }
        start..end
    }

    /// 1-based line of an original byte offset: a binary search, never a scan of the line
    /// (`__LINE__` asks for it once per use).
    pub fn line(&self, at: usize) -> usize {
        self.line_starts.partition_point(|&s| s <= at).max(1)
    }

    /// 1-based line and column (in characters) of an original byte offset.
    pub fn line_col(&self, at: usize) -> (usize, usize) {
        let line = self.line_starts.partition_point(|&s| s <= at).saturating_sub(1);
        let start = self.line_starts[line];
        let at = at.min(self.original.len());
        let col = self.original.get(start..at).map_or(at - start, |s| s.chars().count());
        (line + 1, col + 1)
    }
}

/// Offsets where lines start: after each `\n`, and after each `\r` not followed by `\n` (a
/// lone CR ends a line, as in cpp).
fn line_starts(text: &[u8]) -> Vec<usize> {
    let mut starts = vec![0];
    for (i, &c) in text.iter().enumerate() {
        if c == b'\n' || (c == b'\r' && text.get(i + 1) != Some(&b'\n')) {
            starts.push(i + 1);
        }
    }
    starts
}

/// A lone `\r` (old Mac line ending): a newline to cpp, a `\n` here. The replacement keeps
/// every offset, so no map entry is needed. `\r\n` stays (the `\r` lexes as a space).
fn lone_cr_to_lf(text: &[u8]) -> Option<Vec<u8>> {
    let lone = |i: usize| text[i] == b'\r' && text.get(i + 1) != Some(&b'\n');
    let first = (0..text.len()).find(|&i| lone(i))?;
    let mut out = text.to_vec();
    for (i, c) in out.iter_mut().enumerate().skip(first) {
        if lone(i) {
            *c = b'\n';
        }
    }
    Some(out)
}

/// Phases 1 and 2: line endings (a lone CR is a newline), trigraphs (cpp -std=c11 replaces
/// them) and backslash-newline splices (GNU: whitespace between the backslash and the newline
/// is allowed).
fn splice(text: &str) -> (Option<String>, Vec<(u32, u32)>) {
    let normalized = lone_cr_to_lf(text.as_bytes());
    let b = normalized.as_deref().unwrap_or(text.as_bytes());
    let has_work = b.windows(2).any(|w| w == b"??") || b.contains(&b'\\');
    if !has_work {
        // Only lone CRs were replaced (an ASCII byte for an ASCII byte: still UTF-8).
        return match normalized {
            Some(n) => (
                Some(String::from_utf8(n).unwrap_or_else(|e| String::from_utf8_lossy(e.as_bytes()).into_owned())),
                Vec::new(),
            ),
            None => (None, Vec::new()),
        };
    }
    let mut out: Vec<u8> = Vec::with_capacity(b.len());
    let mut map = Vec::new();
    let mut i = 0;
    let mut changed = normalized.is_some();
    while i < b.len() {
        let c = b[i];
        if c == b'?' && i + 2 < b.len() && b[i + 1] == b'?' {
            let r = match b[i + 2] {
                b'=' => Some(b'#'),
                b'(' => Some(b'['),
                b'/' => Some(b'\\'),
                b')' => Some(b']'),
                b'\'' => Some(b'^'),
                b'<' => Some(b'{'),
                b'!' => Some(b'|'),
                b'>' => Some(b'}'),
                b'-' => Some(b'~'),
                _ => None,
            };
            if let Some(r) = r {
                // `??/` is a backslash and may itself splice.
                if r == b'\\' {
                    if let Some(end) = splice_end(b, i + 3) {
                        i = end;
                        map.push((out.len() as u32, i as u32));
                        changed = true;
                        continue;
                    }
                }
                out.push(r);
                i += 3;
                map.push((out.len() as u32, i as u32));
                changed = true;
                continue;
            }
        }
        if c == b'\\' {
            if let Some(end) = splice_end(b, i + 1) {
                i = end;
                map.push((out.len() as u32, i as u32));
                changed = true;
                continue;
            }
        }
        out.push(c);
        i += 1;
    }
    if !changed {
        return (None, Vec::new());
    }
    // Only whole sequences were removed or replaced, so the result stays UTF-8.
    let s = String::from_utf8(out).unwrap_or_else(|e| String::from_utf8_lossy(e.as_bytes()).into_owned());
    (Some(s), map)
}

/// If a backslash ending at `from` starts a line splice, where the next line begins.
fn splice_end(b: &[u8], from: usize) -> Option<usize> {
    let mut j = from;
    while j < b.len() && matches!(b[j], b' ' | b'\t' | b'\r' | b'\x0c' | b'\x0b') {
        j += 1;
    }
    (j < b.len() && b[j] == b'\n').then_some(j + 1)
}

/// Why [`SourceCache::load`] gave no text.
#[derive(Debug)]
pub(crate) enum LoadError {
    Io(std::io::Error),
    /// The file is in the cache (for showing the error), with U+FFFD at `offset`.
    NotUtf8 {
        file: FileId,
        offset: usize,
        byte: u8,
    },
}

impl LoadError {
    /// The located error, with `labels` (an include chain) after the primary label.
    pub(crate) fn into_error(self, shown: &str, mut labels: Vec<Label<FileId>>) -> super::Error {
        match self {
            LoadError::Io(e) => super::Error::new(format!("cannot read `{shown}`: {e}"), labels),
            LoadError::NotUtf8 { file, offset, byte } => {
                // U+FFFD stands for the byte: three bytes of the shown text.
                labels.insert(0, Label::primary(file, offset..offset + 3).with_message(format!("byte 0x{byte:02x}")));
                super::Error::new(format!("`{shown}` is not UTF-8 text"), labels)
            }
        }
    }
}

#[derive(Default)]
struct Inner {
    files: Vec<Arc<SourceFile>>,
    by_path: HashMap<PathBuf, FileId>,
}

/// What a path is, as `std::fs::metadata` (symlinks followed) says.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum PathKind {
    File,
    Dir,
    /// A FIFO, device or socket.
    Other,
    /// Missing, or not readable.
    Missing,
}

/// The file system's answers about include paths, asked once per cache (see
/// [`SourceCache::kind`]).
#[derive(Default)]
struct Lookups {
    kinds: HashMap<PathBuf, PathKind>,
    canonical: HashMap<PathBuf, Option<PathBuf>>,
}

/// Thread-safe store of source files shared by every permutation of a build: reads each file
/// once (keyed by canonical path), hands out [`FileId`]s, and names files for diagnostics
/// relative to `display_base`. The include paths the permutations look up are asked of the
/// file system once too (`SourceCache::kind`, `SourceCache::canonical`): every
/// permutation of a build sees the files as they were when first asked for, as it sees
/// their contents (a build of 625 permutations otherwise made 35,000 `readlink` and `stat`
/// calls resolving the same few includes).
pub struct SourceCache {
    display_base: PathBuf,
    inner: RwLock<Inner>,
    lookups: RwLock<Lookups>,
}

impl std::fmt::Debug for SourceCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SourceCache").field("display_base", &self.display_base).finish_non_exhaustive()
    }
}

impl SourceCache {
    /// An empty cache; file names are shown relative to `display_base`.
    pub fn new(display_base: PathBuf) -> Self {
        let display_base = display_base.canonicalize().unwrap_or(display_base);
        SourceCache { display_base, inner: RwLock::new(Inner::default()), lookups: RwLock::default() }
    }

    /// What `path` is (`std::fs::metadata`), asked of the file system the first time only.
    pub(crate) fn kind(&self, path: &Path) -> PathKind {
        if let Some(&k) = self.lookups.read().unwrap_or_else(|e| e.into_inner()).kinds.get(path) {
            return k;
        }
        let k = match std::fs::metadata(path) {
            Ok(m) if m.is_file() => PathKind::File,
            Ok(m) if m.is_dir() => PathKind::Dir,
            Ok(_) => PathKind::Other,
            Err(_) => PathKind::Missing,
        };
        self.lookups.write().unwrap_or_else(|e| e.into_inner()).kinds.insert(path.to_path_buf(), k);
        k
    }

    /// `path.canonicalize()` (`None` where it fails), asked of the file system the first time only.
    pub(crate) fn canonical(&self, path: &Path) -> Option<PathBuf> {
        if let Some(c) = self.lookups.read().unwrap_or_else(|e| e.into_inner()).canonical.get(path) {
            return c.clone();
        }
        let c = path.canonicalize().ok();
        self.lookups.write().unwrap_or_else(|e| e.into_inner()).canonical.insert(path.to_path_buf(), c.clone());
        c
    }

    /// The canonical path of a file (an in-memory file: its name).
    pub fn path(&self, id: FileId) -> PathBuf {
        self.get(id).map(|f| f.path.clone()).unwrap_or_default()
    }

    /// The diagnostic name of a file: its path relative to the display base.
    pub fn name(&self, id: FileId) -> String {
        self.get(id).map(|f| f.name.clone()).unwrap_or_default()
    }

    /// 1-based (line, column) of a byte offset in a file's original text.
    pub fn location(&self, id: FileId, offset: usize) -> (usize, usize) {
        self.get(id).map_or((0, 0), |f| f.line_col(offset.min(f.original.len())))
    }

    /// Adds an in-memory file (tests, generated sources). Each call makes a new file.
    pub fn add_virtual(&self, name: &str, text: &str) -> FileId {
        let file = SourceFile::new(PathBuf::from(name), name.to_string(), text.to_string());
        let mut inner = self.inner.write().unwrap_or_else(|e| e.into_inner());
        let id = FileId(inner.files.len() as u32);
        inner.files.push(Arc::new(file));
        id
    }

    /// Gives the file at canonical path `canonical` this text, as if read from disk (an
    /// editor's unsaved buffer): every later load of that path sees it. A path already
    /// loaded keeps its first text (each cache sees each file once).
    pub fn set_text(&self, canonical: &Path, text: &str) -> FileId {
        let mut inner = self.inner.write().unwrap_or_else(|e| e.into_inner());
        if let Some(&id) = inner.by_path.get(canonical) {
            return id;
        }
        let file = SourceFile::new(canonical.to_path_buf(), self.display_name(canonical), text.to_string());
        let id = FileId(inner.files.len() as u32);
        inner.files.push(Arc::new(file));
        inner.by_path.insert(canonical.to_path_buf(), id);
        id
    }

    /// The original text of a file (`None` for an unknown id).
    pub fn text(&self, id: FileId) -> Option<String> {
        self.get(id).map(|f| f.original.clone())
    }

    pub(crate) fn get(&self, id: FileId) -> Option<Arc<SourceFile>> {
        let inner = self.inner.read().unwrap_or_else(|e| e.into_inner());
        inner.files.get(id.0 as usize).cloned()
    }

    /// The display name of a path: relative to the display base when inside it.
    pub fn display_name(&self, path: &Path) -> String {
        match path.strip_prefix(&self.display_base) {
            Ok(rel) if !rel.as_os_str().is_empty() => rel.to_string_lossy().into_owned(),
            _ => path.to_string_lossy().into_owned(),
        }
    }

    /// Loads a file by its canonical path, reading it only the first time. A file that is
    /// not UTF-8 is an error (every time it is asked for) that points at its first bad byte.
    pub(crate) fn load(&self, canonical: &Path) -> Result<(FileId, Arc<SourceFile>), LoadError> {
        let found = |id: FileId, file: &Arc<SourceFile>| match file.bad_utf8 {
            Some((offset, byte)) => Err(LoadError::NotUtf8 { file: id, offset, byte }),
            None => Ok((id, file.clone())),
        };
        {
            let inner = self.inner.read().unwrap_or_else(|e| e.into_inner());
            if let Some(&id) = inner.by_path.get(canonical) {
                return found(id, &inner.files[id.0 as usize]);
            }
        }
        // Read under the write lock: two threads wanting the same new file read it once.
        let mut inner = self.inner.write().unwrap_or_else(|e| e.into_inner());
        if let Some(&id) = inner.by_path.get(canonical) {
            return found(id, &inner.files[id.0 as usize]);
        }
        // Only regular files: a FIFO or a device would block or never end.
        let meta = std::fs::metadata(canonical).map_err(LoadError::Io)?;
        if !meta.is_file() {
            let what =
                if meta.is_dir() { "is a directory" } else { "is not a regular file (a device, FIFO or socket)" };
            return Err(LoadError::Io(std::io::Error::other(what)));
        }
        if meta.len() >= MAX_FILE_BYTES {
            return Err(LoadError::Io(std::io::Error::other(format!(
                "{} bytes is over the limit of {MAX_FILE_BYTES} bytes for a source file",
                meta.len()
            ))));
        }
        // Again as the file is opened (the path may have changed since).
        let bytes = crate::archive::input::read_regular(canonical, MAX_FILE_BYTES).map_err(LoadError::Io)?;
        let (text, bad) = match String::from_utf8(bytes) {
            Ok(text) => (text, None),
            Err(e) => {
                let offset = e.utf8_error().valid_up_to();
                let byte = e.as_bytes()[offset];
                (String::from_utf8_lossy(e.as_bytes()).into_owned(), Some((offset, byte)))
            }
        };
        let mut file = SourceFile::new(canonical.to_path_buf(), self.display_name(canonical), text);
        file.bad_utf8 = bad;
        let file = Arc::new(file);
        let id = FileId(inner.files.len() as u32);
        inner.files.push(file.clone());
        inner.by_path.insert(canonical.to_path_buf(), id);
        found(id, &file)
    }

    /// How many files were read from disk or added (tests check "read once").
    pub fn len(&self) -> usize {
        self.inner.read().unwrap_or_else(|e| e.into_inner()).files.len()
    }

    /// Whether no file is loaded.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// The text of a cached file, for codespan.
#[derive(Clone, Debug)]
pub struct SourceText(Arc<SourceFile>);

impl AsRef<str> for SourceText {
    fn as_ref(&self) -> &str {
        &self.0.original
    }
}

impl<'a> Files<'a> for SourceCache {
    type FileId = FileId;
    type Name = String;
    type Source = SourceText;

    fn name(&'a self, id: FileId) -> Result<String, files::Error> {
        self.get(id).map(|f| f.name.clone()).ok_or(files::Error::FileMissing)
    }

    fn source(&'a self, id: FileId) -> Result<SourceText, files::Error> {
        self.get(id).map(SourceText).ok_or(files::Error::FileMissing)
    }

    fn line_index(&'a self, id: FileId, byte_index: usize) -> Result<usize, files::Error> {
        let f = self.get(id).ok_or(files::Error::FileMissing)?;
        Ok(f.line_starts.partition_point(|&s| s <= byte_index).saturating_sub(1))
    }

    fn line_range(&'a self, id: FileId, line_index: usize) -> Result<Range<usize>, files::Error> {
        let f = self.get(id).ok_or(files::Error::FileMissing)?;
        let start = *f
            .line_starts
            .get(line_index)
            .ok_or(files::Error::LineTooLarge { given: line_index, max: f.line_starts.len() - 1 })?;
        let end = f.line_starts.get(line_index + 1).copied().unwrap_or(f.original.len());
        Ok(start..end)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn splices_and_trigraphs_map_back() {
        let f = SourceFile::new("t".into(), "t".into(), "ab\\\ncd??=e\\  \nf".into());
        assert_eq!(f.text(), "abcd#ef");
        assert_eq!(f.original_offset(2), 4); // c
        assert_eq!(f.original_offset(4), 6); // # from ??=
        assert_eq!(f.original_offset(5), 9); // e
        assert_eq!(f.original_offset(6), 14); // f
        assert_eq!(f.line_col(14), (3, 1));
        assert_eq!(f.original_range(0..4), 0..6);
    }

    #[test]
    fn plain_text_is_not_copied() {
        let f = SourceFile::new("t".into(), "t".into(), "a\\b ?x".into());
        assert!(f.spliced.is_none());
        assert_eq!(f.original_offset(3), 3);
    }
}
