//! The dialect's C preprocessor: takes a `.usf`/`.ush` file, include roots, virtual roots and
//! predefined macros; gives WGSL text, the files it read, warnings, and a [`SourceMap`] from
//! every output byte back to (file, line, column), macro-made text to its invocation with the
//! definition as a note.
//!
//! Guarantees: the output has the same token stream as GNU
//! `cpp -x c -P -undef -nostdinc -std=c11` with the same `-D`/`-I` (rescanning, painted
//! macros, `#`/`##`, `__VA_ARGS__`, `defined`, 64-bit `#if` arithmetic, `__LINE__`/`__FILE__`);
//! WGSL punctuation passes through untouched; an include never leaves its root; each file is
//! read once per [`SourceCache`]; every error is one located codespan diagnostic with its
//! include chain; expansion depth and output size are bounded, and no input panics. A source
//! must be UTF-8 (its first other byte is a located error, never replaced); a lone CR ends a
//! line as in cpp. Time and memory are linear in the input: no per-token work rescans a
//! line, an argument list or a definition, and a definition too long to keep as tokens is
//! read again from its text when first used.

mod engine;
pub mod expr;
mod lexer;
mod map;
pub(crate) mod source;
#[cfg(test)]
mod tests;

use std::fmt;
use std::path::{Path, PathBuf};

use codespan_reporting::diagnostic::Diagnostic;

/// The diagnostic types of this module's API, re-exported for callers.
pub use codespan_reporting::diagnostic::{Diagnostic as CodespanDiagnostic, Label, Severity};
pub use engine::{big_stack_thread, STACK_BYTES};
pub use map::{Origin, SourceMap};
pub use source::{FileId, SourceCache, SourceText};

/// How to preprocess.
#[derive(Clone, Debug)]
pub struct Options {
    /// Folders searched in order for `#include "..."` (after the including file's folder) and
    /// `#include <...>`.
    pub include_roots: Vec<PathBuf>,
    /// Path prefixes mapped to folders: `("/Engine", <abs path of shader_src>)`.
    pub virtual_roots: Vec<(String, PathBuf)>,
    /// Predefined macros, `NAME` → replacement text (like `-D NAME=text`; `NAME` may carry a
    /// parameter list, `F(x)`). `__STDC__`, `__STDC_VERSION__` (201112L) and the other macros
    /// `cpp -undef -std=c11` keeps are always defined.
    pub defines: Vec<(String, String)>,
    /// Most macro expansions nested inside each other (`#include` nesting stops at 200, as
    /// in cpp).
    pub max_expansion_depth: usize,
    /// Largest output, in bytes. Macro expansion may make at most a quarter as many tokens,
    /// and at most a million plus eight per byte of input read, so a macro bomb fails within
    /// milliseconds, in bounded memory; text made by `#` and `##` counts against it too.
    pub max_output_bytes: usize,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            include_roots: Vec::new(),
            virtual_roots: Vec::new(),
            defines: Vec::new(),
            max_expansion_depth: 256,
            max_output_bytes: 16 << 20,
        }
    }
}

/// A preprocessing error: one diagnostic, located, with the include chain as secondary labels.
#[derive(Clone, Debug)]
pub struct Error {
    /// The diagnostic, with its labels.
    pub diagnostic: Diagnostic<FileId>,
}

impl Error {
    pub(crate) fn new(message: impl Into<String>, labels: Vec<Label<FileId>>) -> Error {
        Error { diagnostic: Diagnostic::error().with_message(message.into()).with_labels(labels) }
    }
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.diagnostic.message)
    }
}

impl std::error::Error for Error {}

/// A preprocessed file.
#[derive(Clone, Debug)]
pub struct Output {
    /// The preprocessed WGSL.
    pub text: String,
    /// Where each output byte comes from.
    pub map: SourceMap,
    /// Every file read (main file first), deduplicated.
    pub files: Vec<FileId>,
    /// Include candidates tried and found missing (sorted): a file created at one of them
    /// could change the output, so a cached result is only reused while they stay missing.
    pub absent: Vec<PathBuf>,
    /// Warnings (`#warning`, redefinitions), located.
    pub warnings: Vec<Diagnostic<FileId>>,
    /// Lines a false `#if`/`#ifdef`/`#elif`/`#else` group excluded: (file, 1-based lines,
    /// end exclusive), in the order met. The conditional directives' own lines are not in it.
    pub skipped: Vec<(FileId, std::ops::Range<u32>)>,
}

impl Output {
    /// blake3 of the token stream with whitespace and comments normalized: identical tokens
    /// give identical hashes, whatever the spacing and line structure.
    pub fn token_hash(&self) -> blake3::Hash {
        token_hash(&self.text)
    }
}

/// [`Output::token_hash`] of any text.
pub fn token_hash(text: &str) -> blake3::Hash {
    // The hashed bytes are each token's length (u32, little-endian) then its bytes. They are
    // gathered in a fixed buffer and fed to the hasher a chunk at a time: the same hash as
    // hashing them all at once, without a buffer the size of the text (and its reallocations,
    // whose fresh pages each fault in).
    const CHUNK: usize = 16 << 10;
    let src = text.as_bytes();
    let end = src.len();
    let mut hasher = blake3::Hasher::new();
    let mut buf = [0u8; CHUNK + 32];
    let mut n = 0;
    let mut pos = 0;
    while pos < end {
        let b = src[pos];
        // Fast paths for what preprocessed WGSL is mostly made of: runs of blanks (indents),
        // identifiers, numbers and punctuators that never begin a longer one. The rest (and
        // the string and character prefixes `L` `U` `u` `u8` before a quote) goes the long way.
        let len = match HASH_CLASS[b as usize] {
            BLANK => {
                pos += 1;
                while pos < end && HASH_CLASS[src[pos] as usize] == BLANK {
                    pos += 1;
                }
                continue;
            }
            IDENT => {
                let mut i = pos + 1;
                while i < end && lexer::IDENT_CONTINUE[src[i] as usize] {
                    i += 1;
                }
                i - pos
            }
            PREFIX if !matches!(src.get(pos + 1), Some(b'"' | b'\'' | b'8')) => lexer::ident_len(src, pos),
            DIGIT => lexer::number_len(src, pos),
            SINGLE => 1,
            _ => match lexer::next(src, pos) {
                (lexer::Kind::Eof, _) => break,
                (
                    lexer::Kind::Space
                    | lexer::Kind::Newline
                    | lexer::Kind::LineComment
                    | lexer::Kind::BlockComment { .. },
                    len,
                ) => {
                    pos += len.max(1);
                    continue;
                }
                (_, len) => len.max(1),
            },
        };
        if n > CHUNK {
            hasher.update(&buf[..n]);
            n = 0;
        }
        buf[n..n + 4].copy_from_slice(&(len as u32).to_le_bytes());
        n += 4;
        if len <= 16 && pos + 16 <= end {
            // Most tokens are short: copy a fixed 16 bytes (one move) and count only `len`.
            buf[n..n + 16].copy_from_slice(&src[pos..pos + 16]);
            n += len;
        } else {
            for piece in src[pos..pos + len].chunks(16) {
                if n > CHUNK {
                    hasher.update(&buf[..n]);
                    n = 0;
                }
                buf[n..n + piece.len()].copy_from_slice(piece);
                n += piece.len();
            }
        }
        pos += len;
    }
    hasher.update(&buf[..n]);
    hasher.finalize()
}

/// [`token_hash`]'s classes of a token's first byte: what the lexer would make of it.
const OTHER: u8 = 0;
/// ` `, `\n`, `\t`: dropped.
const BLANK: u8 = 1;
/// Starts an identifier, and cannot start a string or character literal.
const IDENT: u8 = 2;
/// `L`, `U`, `u`: an identifier unless a quote (or `8"`) follows.
const PREFIX: u8 = 3;
const DIGIT: u8 = 4;
/// A punctuator that never begins a longer one.
const SINGLE: u8 = 5;

static HASH_CLASS: [u8; 256] = {
    let mut t = [OTHER; 256];
    let mut i = 0;
    while i < 256 {
        let b = i as u8;
        t[i] = match b {
            b' ' | b'\n' | b'\t' => BLANK,
            b'L' | b'U' | b'u' => PREFIX,
            b'a'..=b'z' | b'A'..=b'Z' | b'_' => IDENT,
            b'0'..=b'9' => DIGIT,
            b'(' | b')' | b'{' | b'}' | b'[' | b']' | b';' | b',' | b'?' | b'~' => SINGLE,
            _ => OTHER,
        };
        i += 1;
    }
    t
};

/// The preprocessing tokens of a text, comments and whitespace dropped (for comparisons).
pub fn tokens(text: &str) -> Vec<&str> {
    let src = text.as_bytes();
    let mut out = Vec::new();
    let mut pos = 0;
    loop {
        let (kind, len) = lexer::next(src, pos);
        match kind {
            lexer::Kind::Eof => return out,
            lexer::Kind::Space | lexer::Kind::Newline | lexer::Kind::LineComment | lexer::Kind::BlockComment { .. } => {
            }
            _ => out.push(&text[pos..pos + len]),
        }
        pos += len.max(1);
    }
}

/// Resolves a `source = "..."` of `permutations.toml` like `#include <...>`: through a virtual
/// root, else against the include roots in order. The result is canonical.
pub fn resolve_source(spelling: &str, opts: &Options) -> Result<PathBuf, Error> {
    engine::resolve_angle(spelling, opts).map_err(|message| Error::new(message, Vec::new()))
}

/// Preprocesses the file at `path` (read through `cache`).
pub fn preprocess_file(path: &Path, opts: &Options, cache: &SourceCache) -> Result<Output, Error> {
    let canonical = match cache.canonical(path) {
        Some(c) => c,
        // Asked again for the error's words (an error stops only this permutation).
        None => {
            let e =
                path.canonicalize().err().map_or_else(|| "it changed during the build".to_string(), |e| e.to_string());
            return Err(Error::new(format!("cannot read `{}`: {e}", path.display()), Vec::new()));
        }
    };
    let (id, _) = cache.load(&canonical).map_err(|e| {
        let shown = match e {
            source::LoadError::NotUtf8 { .. } => cache.display_name(&canonical),
            source::LoadError::Io(_) => path.display().to_string(),
        };
        e.into_error(&shown, Vec::new())
    })?;
    // `__FILE__` spells the main file as it was given, like cpp does.
    let name = if path.is_relative() { Some(path.to_string_lossy().into_owned()) } else { None };
    engine::run_named(id, name, opts, cache)
}

/// Preprocesses a file already in `cache` (for example one added with
/// [`SourceCache::add_virtual`]).
pub fn preprocess_file_id(file: FileId, opts: &Options, cache: &SourceCache) -> Result<Output, Error> {
    engine::run(file, opts, cache)
}

/// Renders diagnostics as text the way rustc does (codespan), optionally with ANSI colour.
///
/// A source line longer than [`MAX_SHOWN_LINE`] bytes is shown cut to the parts around its
/// labels (`…` for the rest): a diagnostic on a line of megabytes is a few lines, not the
/// whole line.
pub fn render(diagnostics: &[Diagnostic<FileId>], cache: &SourceCache, color: bool) -> String {
    use codespan_reporting::term;
    let config = term::Config::default();
    let mut out = String::new();
    for d in diagnostics {
        if let Some((files, clipped)) = clip_long_lines(d, cache) {
            match term::emit_into_string(&config, &files, &clipped) {
                Ok(s) => out.push_str(&s),
                Err(e) => {
                    out.push_str(&format!("{}: {}\n(cannot show the source: {e})\n", severity_name(d), d.message))
                }
            }
            continue;
        }
        if color {
            let mut buf = term::termcolor::Ansi::new(Vec::new());
            let _ = term::emit_to_write_style(&mut buf, &config, cache, d);
            out.push_str(&String::from_utf8_lossy(&buf.into_inner()));
        } else {
            match term::emit_into_string(&config, cache, d) {
                Ok(s) => out.push_str(&s),
                Err(e) => {
                    out.push_str(&format!("{}: {}\n", severity_name(d), d.message));
                    out.push_str(&format!("(cannot show the source: {e})\n"));
                }
            }
        }
    }
    out
}

/// Source lines longer than this are shown cut around their labels.
pub const MAX_SHOWN_LINE: usize = 512;

/// Bytes of context kept on each side of a label on a cut line.
const SHOWN_CONTEXT: usize = 60;

/// When a label of `d` sits on a line longer than [`MAX_SHOWN_LINE`]: the files of its labels
/// with such lines cut to windows around the labels, and `d` with its labels moved to match.
fn clip_long_lines<'c>(
    d: &Diagnostic<FileId>,
    cache: &'c SourceCache,
) -> Option<(ClippedFiles<'c>, Diagnostic<usize>)> {
    let long =
        d.labels.iter().any(|l| line_of(cache, l.file_id, l.range.start).is_some_and(|r| r.len() > MAX_SHOWN_LINE));
    if !long {
        return None;
    }
    let mut files = ClippedFiles { cache, files: Vec::new() };
    // Each file of the labels and its index in `files`.
    let mut ids: Vec<(FileId, usize)> = Vec::new();
    let mut labels = Vec::new();
    for l in &d.labels {
        if !ids.iter().any(|(f, ..)| *f == l.file_id) {
            let text = cache.get(l.file_id)?.original.clone();
            let keep = keep_windows(d, l.file_id, &text, cache)?;
            let (new, moves) = cut_text(&text, keep);
            let id = files.files.len();
            let starts = line_starts_of(&new);
            files.files.push(ClippedFile { file: l.file_id, text: new, line_starts: starts, moves });
            ids.push((l.file_id, id));
        }
        let &(_, id) = ids.iter().find(|(f, _)| *f == l.file_id)?;
        let moves = &files.files[id].moves;
        let map = |o: usize| moves.iter().find(|(a, b, _)| (*a..=*b).contains(&o)).map_or(0, |(a, _, n)| n + (o - a));
        let start = map(l.range.start);
        let end = map(l.range.end.min(l.range.start + MAX_SHOWN_LINE)).max(start);
        labels.push(Label { style: l.style, file_id: id, range: start..end, message: l.message.clone() });
    }
    let clipped = Diagnostic {
        severity: d.severity,
        code: d.code.clone(),
        message: d.message.clone(),
        labels,
        notes: d.notes.clone(),
    };
    Some((files, clipped))
}

/// The byte range of the line of `file` holding offset `at`.
fn line_of(cache: &SourceCache, file: FileId, at: usize) -> Option<std::ops::Range<usize>> {
    use codespan_reporting::files::Files;
    let i = cache.line_index(file, at).ok()?;
    cache.line_range(file, i).ok()
}

/// The windows of `text` (the original of `file`) to keep on each long line that has a label
/// of `d`, with each such line's ends as empty windows, sorted.
fn keep_windows(d: &Diagnostic<FileId>, file: FileId, text: &str, cache: &SourceCache) -> Option<Vec<(usize, usize)>> {
    let mut keep: Vec<(usize, usize)> = Vec::new();
    for m in d.labels.iter().filter(|m| m.file_id == file) {
        let line = line_of(cache, m.file_id, m.range.start)?;
        if line.len() > MAX_SHOWN_LINE {
            let start = m.range.start.saturating_sub(SHOWN_CONTEXT).max(line.start);
            let end = (m.range.end.min(m.range.start + MAX_SHOWN_LINE) + SHOWN_CONTEXT).min(line.end);
            keep.push((floor_boundary(text, start), ceil_boundary(text, end)));
            keep.push((line.start, line.start));
            keep.push((line.end, line.end));
        }
    }
    keep.sort_unstable();
    Some(keep)
}

/// Cuts `text` to the sorted windows `keep`: the text between windows of one long line
/// becomes `…`. Also gives the moves that map an old offset to a new one: (old start, old
/// end, new start) of each kept piece.
fn cut_text(text: &str, keep: Vec<(usize, usize)>) -> (String, Vec<(usize, usize, usize)>) {
    let mut new = String::new();
    let mut moves = Vec::new();
    let mut at = 0;
    let mut merged: Vec<(usize, usize)> = Vec::new();
    for (a, b) in keep {
        match merged.last_mut() {
            Some(last) if a <= last.1 => last.1 = last.1.max(b),
            _ => merged.push((a, b)),
        }
    }
    for (a, b) in merged {
        if a > at {
            // A gap within one line (up to its line ending) is cut.
            let gap = &text[at..a];
            let body = gap.trim_end_matches(['\r', '\n']);
            if !body.is_empty() && !body.contains(['\n', '\r']) {
                new.push('…');
                new.push_str(&gap[body.len()..]);
            } else {
                moves.push((at, a, new.len()));
                new.push_str(gap);
            }
        }
        moves.push((a, b, new.len()));
        new.push_str(&text[a..b]);
        at = b;
    }
    moves.push((at, text.len(), new.len()));
    new.push_str(&text[at..]);
    (new, moves)
}

/// Files with long lines cut (see [`clip_long_lines`]); columns are those of the original
/// text.
struct ClippedFiles<'c> {
    cache: &'c SourceCache,
    files: Vec<ClippedFile>,
}

struct ClippedFile {
    file: FileId,
    text: String,
    line_starts: Vec<usize>,
    /// (original start, original end, cut start) of each piece kept.
    moves: Vec<(usize, usize, usize)>,
}

/// Line starts as [`SourceCache`] counts them (a lone CR ends a line too).
fn line_starts_of(text: &str) -> Vec<usize> {
    let b = text.as_bytes();
    let mut starts = vec![0];
    for (i, &c) in b.iter().enumerate() {
        if c == b'\n' || (c == b'\r' && b.get(i + 1) != Some(&b'\n')) {
            starts.push(i + 1);
        }
    }
    starts
}

impl<'a> codespan_reporting::files::Files<'a> for ClippedFiles<'_> {
    type FileId = usize;
    type Name = String;
    type Source = &'a str;

    fn name(&'a self, id: usize) -> Result<String, codespan_reporting::files::Error> {
        let f = self.files.get(id).ok_or(codespan_reporting::files::Error::FileMissing)?;
        Ok(self.cache.name(f.file))
    }

    fn source(&'a self, id: usize) -> Result<&'a str, codespan_reporting::files::Error> {
        Ok(&self.files.get(id).ok_or(codespan_reporting::files::Error::FileMissing)?.text)
    }

    fn line_index(&'a self, id: usize, byte_index: usize) -> Result<usize, codespan_reporting::files::Error> {
        let f = self.files.get(id).ok_or(codespan_reporting::files::Error::FileMissing)?;
        Ok(f.line_starts.partition_point(|&s| s <= byte_index).saturating_sub(1))
    }

    fn line_range(
        &'a self,
        id: usize,
        line_index: usize,
    ) -> Result<std::ops::Range<usize>, codespan_reporting::files::Error> {
        let f = self.files.get(id).ok_or(codespan_reporting::files::Error::FileMissing)?;
        let start = *f.line_starts.get(line_index).ok_or(codespan_reporting::files::Error::LineTooLarge {
            given: line_index,
            max: f.line_starts.len() - 1,
        })?;
        let end = f.line_starts.get(line_index + 1).copied().unwrap_or(f.text.len());
        Ok(start..end)
    }

    /// The column in the original text (the cut text's would be wrong).
    fn column_number(
        &'a self,
        id: usize,
        _line_index: usize,
        byte_index: usize,
    ) -> Result<usize, codespan_reporting::files::Error> {
        let f = self.files.get(id).ok_or(codespan_reporting::files::Error::FileMissing)?;
        let original = f
            .moves
            .iter()
            .find(|&&(a, b, n)| (n..=n + (b - a)).contains(&byte_index))
            .map_or(byte_index, |&(a, _, n)| a + (byte_index - n));
        Ok(self.cache.location(f.file, original).1)
    }
}

fn floor_boundary(s: &str, mut i: usize) -> usize {
    while !s.is_char_boundary(i) {
        i -= 1;
    }
    i
}

fn ceil_boundary(s: &str, mut i: usize) -> usize {
    while !s.is_char_boundary(i) {
        i += 1;
    }
    i
}

fn severity_name(d: &Diagnostic<FileId>) -> &'static str {
    use codespan_reporting::diagnostic::Severity;
    match d.severity {
        Severity::Bug => "bug",
        Severity::Error => "error",
        Severity::Warning => "warning",
        Severity::Note => "note",
        Severity::Help => "help",
    }
}
