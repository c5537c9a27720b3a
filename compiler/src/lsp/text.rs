//! Text helpers: LSP positions (UTF-16 columns) against byte offsets, words, URIs, numbers.

use std::path::{Path, PathBuf};

use lsp_types::{Position, Range, Url};

/// The byte offset of an LSP position in `text` (clamped to the line and the text).
pub fn offset_of(text: &str, pos: Position) -> usize {
    let mut start = 0;
    for _ in 0..pos.line {
        match text[start..].find('\n') {
            Some(i) => start += i + 1,
            None => return text.len(),
        }
    }
    let line_end = text[start..].find('\n').map_or(text.len(), |i| start + i);
    let mut units = 0u32;
    for (i, c) in text[start..line_end].char_indices() {
        if units >= pos.character {
            return start + i;
        }
        units += c.len_utf16() as u32;
    }
    line_end
}

/// The LSP position of a byte offset in `text`.
pub fn position_of(text: &str, offset: usize) -> Position {
    let mut offset = offset.min(text.len());
    while !text.is_char_boundary(offset) {
        offset -= 1;
    }
    let before = &text[..offset];
    let line = before.matches('\n').count() as u32;
    let line_start = before.rfind('\n').map_or(0, |i| i + 1);
    let character = text[line_start..offset].encode_utf16().count() as u32;
    Position { line, character }
}

/// The LSP range of a byte range in `text`.
pub fn range_of(text: &str, r: std::ops::Range<usize>) -> Range {
    Range { start: position_of(text, r.start), end: position_of(text, r.end.max(r.start)) }
}

/// A line's start (0-based line) as a range of zero length.
pub fn line_start(line: u32) -> Range {
    let p = Position { line, character: 0 };
    Range { start: p, end: p }
}

pub fn is_ident(b: u8) -> bool {
    b.is_ascii_alphanumeric() || b == b'_'
}

/// The identifier around byte `at` (touching it from either side) and its byte range.
pub fn word_at(text: &str, at: usize) -> Option<(&str, std::ops::Range<usize>)> {
    let b = text.as_bytes();
    let at = at.min(b.len());
    let mut s = at;
    while s > 0 && is_ident(b[s - 1]) {
        s -= 1;
    }
    let mut e = at;
    while e < b.len() && is_ident(b[e]) {
        e += 1;
    }
    (e > s && !b[s].is_ascii_digit()).then(|| (&text[s..e], s..e))
}

/// The line holding byte `at`: its byte range, without the newline.
pub fn line_around(text: &str, at: usize) -> std::ops::Range<usize> {
    let at = at.min(text.len());
    let s = text[..at].rfind('\n').map_or(0, |i| i + 1);
    let e = text[at..].find('\n').map_or(text.len(), |i| at + i);
    s..e
}

/// The path of a `file:` URI, canonical where the file exists.
pub fn uri_path(uri: &Url) -> Option<PathBuf> {
    let p = uri.to_file_path().ok()?;
    Some(p.canonicalize().unwrap_or(p))
}

/// The `file:` URI of a path.
pub fn path_uri(path: &Path) -> Option<Url> {
    Url::from_file_path(path).ok()
}

/// `4096` as `4,096`.
pub fn thousands(n: u64) -> String {
    let s = n.to_string();
    let mut out = String::new();
    for (i, c) in s.chars().enumerate() {
        if i > 0 && (s.len() - i).is_multiple_of(3) {
            out.push(',');
        }
        out.push(c);
    }
    out
}

/// The path spelled by an `#include` directive on this line: (spelling, angle brackets,
/// byte range of the spelling within the line).
pub fn include_spelling(line: &str) -> Option<(&str, bool, std::ops::Range<usize>)> {
    let t = line.trim_start();
    let lead = line.len() - t.len();
    let rest = t.strip_prefix('#')?;
    let r = rest.trim_start();
    let r = r.strip_prefix("include")?;
    let r2 = r.trim_start();
    let (close, angle) = match r2.chars().next()? {
        '"' => ('"', false),
        '<' => ('>', true),
        _ => return None,
    };
    let start = line.len() - r2.len() + 1;
    let len = r2[1..].find(close)?;
    let _ = lead;
    Some((&line[start..start + len], angle, start..start + len))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn positions_round_trip() {
        let t = "ab\nçd€f\n";
        let p = Position { line: 1, character: 2 };
        let o = offset_of(t, p);
        assert_eq!(&t[o..o + 3], "€");
        assert_eq!(position_of(t, o), p);
        assert_eq!(offset_of(t, Position { line: 9, character: 0 }), t.len());
    }

    #[test]
    fn words_and_includes() {
        assert_eq!(word_at("a FOO_1+", 4).map(|w| w.0), Some("FOO_1"));
        assert_eq!(word_at(" 12 ", 2), None);
        assert_eq!(include_spelling("  # include \"a/b.ush\" // x").map(|i| (i.0, i.1)), Some(("a/b.ush", false)));
        assert_eq!(include_spelling("#include <c.ush>").map(|i| (i.0, i.1)), Some(("c.ush", true)));
        assert_eq!(thousands(4096), "4,096");
        assert_eq!(thousands(12), "12");
        assert_eq!(thousands(100000), "100,000");
    }
}
