//! A byte cursor lexer for preprocessing tokens (C11 translation phase 3), in the manner of
//! `rustc_lexer`: it gives a `Copy` kind and a length, positions live with the caller.
//!
//! The input has already been through phases 1 and 2 (trigraphs, line splices: see
//! [`super::source`]). Comments are tokens here; the preprocessor turns them into spaces.

/// What a token is. Lengths are returned beside it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// Spaces, tabs, `\r`, form feeds, vertical tabs (never `\n`).
    Space,
    Newline,
    LineComment,
    /// `/* ... */`; `terminated` is false when the text ends first.
    BlockComment {
        terminated: bool,
    },
    Ident,
    Number,
    /// A string literal, with its prefix; `terminated` is false at an unescaped line end.
    Str {
        terminated: bool,
    },
    /// A character constant; an unterminated one spans the rest of the line (as in cpp).
    Char {
        terminated: bool,
    },
    Punct,
    /// Any other single character (`@`, `` ` ``, a stray `\`).
    Other,
    Eof,
}

#[inline]
pub fn is_ident_start(b: u8) -> bool {
    b.is_ascii_alphabetic() || b == b'_' || b == b'$' || b >= 0x80
}

#[inline]
pub fn is_ident_continue(b: u8) -> bool {
    b.is_ascii_alphanumeric() || b == b'_' || b == b'$' || b >= 0x80
}

/// [`is_ident_continue`] of every byte, for the hot loops.
pub(crate) static IDENT_CONTINUE: [bool; 256] = {
    let mut t = [false; 256];
    let mut i = 0;
    while i < 256 {
        let b = i as u8;
        t[i] = b.is_ascii_alphanumeric() || b == b'_' || b == b'$' || b >= 0x80;
        i += 1;
    }
    t
};

#[inline]
fn is_space(b: u8) -> bool {
    matches!(b, b' ' | b'\t' | b'\r' | b'\x0b' | b'\x0c')
}

/// Lexes one token of `src` starting at `pos` (which must be `< src.len()` unless at the end).
#[inline]
pub fn next(src: &[u8], pos: usize) -> (Kind, usize) {
    let Some(&b) = src.get(pos) else {
        return (Kind::Eof, 0);
    };
    let at = |i: usize| -> u8 { src.get(pos + i).copied().unwrap_or(0) };
    match b {
        b'\n' => (Kind::Newline, 1),
        b' ' | b'\t' | b'\r' | b'\x0b' | b'\x0c' => {
            let mut i = 1;
            while pos + i < src.len() && is_space(src[pos + i]) {
                i += 1;
            }
            (Kind::Space, i)
        }
        b'/' if at(1) == b'/' => {
            let end = memchr_nl(src, pos + 2);
            (Kind::LineComment, end - pos)
        }
        b'/' if at(1) == b'*' => {
            let mut i = pos + 2;
            loop {
                match memchr_star(src, i) {
                    None => return (Kind::BlockComment { terminated: false }, src.len() - pos),
                    Some(j) => {
                        if src.get(j + 1) == Some(&b'/') {
                            return (Kind::BlockComment { terminated: true }, j + 2 - pos);
                        }
                        i = j + 1;
                    }
                }
            }
        }
        b'0'..=b'9' => (Kind::Number, number_len(src, pos)),
        b'.' if at(1).is_ascii_digit() => (Kind::Number, number_len(src, pos)),
        b'"' => quoted(src, pos, 0, b'"'),
        b'\'' => quoted(src, pos, 0, b'\''),
        b'L' | b'U' | b'u' => {
            // String and character prefixes (C11: L, u, U, u8 strings; L, u, U chars).
            if at(1) == b'"' || at(1) == b'\'' {
                return quoted(src, pos, 1, at(1));
            }
            if b == b'u' && at(1) == b'8' && at(2) == b'"' {
                return quoted(src, pos, 2, b'"');
            }
            (Kind::Ident, ident_len(src, pos))
        }
        _ if is_ident_start(b) => (Kind::Ident, ident_len(src, pos)),
        _ => match punct_len(src, pos) {
            0 => (Kind::Other, 1),
            n => (Kind::Punct, n),
        },
    }
}

#[inline]
pub(crate) fn ident_len(src: &[u8], pos: usize) -> usize {
    let mut i = pos + 1;
    while i < src.len() && is_ident_continue(src[i]) {
        i += 1;
    }
    i - pos
}

#[inline]
pub(crate) fn number_len(src: &[u8], pos: usize) -> usize {
    let mut i = pos + 1;
    while i < src.len() {
        let c = src[i];
        let signed_exponent = matches!(c, b'+' | b'-') && matches!(src[i - 1], b'e' | b'E' | b'p' | b'P');
        if !(signed_exponent || is_ident_continue(c) || c == b'.') {
            break;
        }
        i += 1;
    }
    i - pos
}

fn quoted(src: &[u8], pos: usize, prefix: usize, q: u8) -> (Kind, usize) {
    let mut i = pos + prefix + 1;
    while i < src.len() {
        match src[i] {
            b'\\' if i + 1 < src.len() && src[i + 1] != b'\n' => i += 2,
            b'\n' => break,
            c if c == q => {
                let len = i + 1 - pos;
                return if q == b'"' {
                    (Kind::Str { terminated: true }, len)
                } else {
                    (Kind::Char { terminated: true }, len)
                };
            }
            _ => i += 1,
        }
    }
    if q == b'"' {
        // cpp keeps the lone quote as its own token and goes on lexing (after an error).
        (Kind::Str { terminated: false }, prefix + 1)
    } else {
        // cpp makes the rest of the line a single token (after a warning).
        (Kind::Char { terminated: false }, memchr_nl(src, pos) - pos)
    }
}

/// Length of the punctuator at `pos`, 0 if none (longest match, C11 with digraphs).
pub fn punct_len(src: &[u8], pos: usize) -> usize {
    let at = |i: usize| -> u8 { src.get(pos + i).copied().unwrap_or(0) };
    let (a, b, c) = (at(0), at(1), at(2));
    match a {
        b'%' if b == b':' && c == b'%' && at(3) == b':' => 4,
        b'.' if b == b'.' && c == b'.' => 3,
        b'<' if b == b'<' && c == b'=' => 3,
        b'>' if b == b'>' && c == b'=' => 3,
        b'-' if matches!(b, b'>' | b'-' | b'=') => 2,
        b'+' if matches!(b, b'+' | b'=') => 2,
        b'<' if matches!(b, b'<' | b'=' | b':' | b'%') => 2,
        b'>' if matches!(b, b'>' | b'=') => 2,
        b'=' | b'!' | b'*' | b'/' | b'^' if b == b'=' => 2,
        b'&' if matches!(b, b'&' | b'=') => 2,
        b'|' if matches!(b, b'|' | b'=') => 2,
        b'#' if b == b'#' => 2,
        b'%' if matches!(b, b'=' | b'>' | b':') => 2,
        b':' if b == b'>' => 2,
        b'[' | b']' | b'(' | b')' | b'{' | b'}' | b'.' | b'&' | b'*' | b'+' | b'-' | b'~' | b'!' | b'/' | b'%'
        | b'<' | b'>' | b'^' | b'|' | b'?' | b':' | b';' | b'=' | b',' | b'#' => 1,
        _ => 0,
    }
}

/// Whether a punctuator's text opens a directive at a line start: `#` or `%:`, never `##` or
/// `%:%:` (cpp passes a line starting with `##` through as text).
#[inline]
pub fn is_directive_hash(punct: &[u8]) -> bool {
    punct == b"#" || punct == b"%:"
}

/// Index of the next `\n` at or after `from`, or `src.len()`.
#[inline]
pub fn memchr_nl(src: &[u8], from: usize) -> usize {
    match src.get(from..).and_then(|s| s.iter().position(|&c| c == b'\n')) {
        Some(i) => from + i,
        None => src.len(),
    }
}

#[inline]
fn memchr_star(src: &[u8], from: usize) -> Option<usize> {
    src.get(from..)?.iter().position(|&c| c == b'*').map(|i| from + i)
}

/// True if printing `a` immediately followed by `b` would lex differently from the two
/// tokens apart (so the printer must put a space between them).
pub fn would_paste(a: &[u8], b: &[u8]) -> bool {
    if a.is_empty() || b.is_empty() {
        return false;
    }
    let mut buf = [0u8; 64];
    let (head, tail) =
        if a.len() > 32 { (&a[a.len() - 32..], &b[..b.len().min(32)]) } else { (a, &b[..b.len().min(32)]) };
    // A long token whose tail we cut: only identifiers, numbers and strings get that long,
    // and for them the last 32 bytes decide (except a string's prefix, which is at the head).
    buf[..head.len()].copy_from_slice(head);
    buf[head.len()..head.len() + tail.len()].copy_from_slice(tail);
    let joined = &buf[..head.len() + tail.len()];
    if a.len() > 32 {
        // Only word-like tails can merge with what follows.
        let last = a[a.len() - 1];
        let first = b[0];
        if matches!(a[0], b'"' | b'\'') || a.ends_with(b"\"") || a.ends_with(b"'") {
            return false;
        }
        return (is_ident_continue(last) || last == b'.')
            && (is_ident_continue(first)
                || first == b'.'
                || first == b'+'
                || first == b'-'
                || first == b'"'
                || first == b'\'');
    }
    let (kind, len) = next(joined, 0);
    if len != head.len() {
        return true;
    }
    // `u8` + `"x"` is fine for the lexer above only because we lexed `u8` first; check the
    // string prefixes explicitly the way cpp does (a name followed by a literal).
    matches!(kind, Kind::Ident) && matches!(b[0], b'"' | b'\'')
}

/// GNU cpp's `cpp_avoid_paste`: whether cpp prints a space between `a` and `b` where they meet
/// across a macro expansion's edge. Its rule is by pairs and errs towards a space, so it also
/// keeps apart tokens that only a third one would merge (`.` `.` `.` is not `...`).
pub fn cpp_avoid_paste(a: &[u8], b: &[u8]) -> bool {
    if a.is_empty() || b.is_empty() {
        return false;
    }
    let (ka, la) = next(a, 0);
    let (kb, _) = next(b, 0);
    // The first character of `b` when it is a punctuator (cpp's `c`).
    let c = if kb == Kind::Punct { b[0] } else { 0 };
    if ka == Kind::Punct && la == a.len() {
        if c == b'='
            && matches!(
                a,
                b"=" | b"!" | b">" | b"<" | b"+" | b"-" | b"*" | b"/" | b"%" | b"&" | b"|" | b"^" | b">>" | b"<<"
            )
        {
            return true;
        }
        return match a {
            b">" => c == b'>',
            b"<" => matches!(c, b'<' | b'%' | b':'),
            b"+" => c == b'+',
            b"-" => matches!(c, b'-' | b'>'),
            b"/" => matches!(c, b'/' | b'*'),
            b"%" => matches!(c, b':' | b'%'),
            b"&" => c == b'&',
            b"|" => c == b'|',
            b":" => matches!(c, b':' | b'>'),
            b"->" => c == b'*',
            b"." => matches!(c, b'.' | b'%') || kb == Kind::Number,
            b"#" | b"%:" => matches!(c, b'#' | b'%'),
            _ => false,
        };
    }
    match ka {
        Kind::Ident => matches!(kb, Kind::Ident | Kind::Char { .. } | Kind::Str { .. }),
        Kind::Number => matches!(kb, Kind::Number | Kind::Ident | Kind::Char { .. }) || matches!(c, b'.' | b'+' | b'-'),
        Kind::Other => a[0] == b'\\' && kb == Kind::Ident,
        _ => false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kinds(s: &str) -> Vec<(Kind, &str)> {
        let mut out = Vec::new();
        let mut pos = 0;
        loop {
            let (k, n) = next(s.as_bytes(), pos);
            if k == Kind::Eof {
                return out;
            }
            out.push((k, &s[pos..pos + n]));
            pos += n;
        }
    }

    #[test]
    fn tokens() {
        use Kind::*;
        assert_eq!(
            kinds("a1 0x1p-3 .5e+1 \"s\\\"\" 'c' <<= -> @x"),
            vec![
                (Ident, "a1"),
                (Space, " "),
                (Number, "0x1p-3"),
                (Space, " "),
                (Number, ".5e+1"),
                (Space, " "),
                (Str { terminated: true }, "\"s\\\"\""),
                (Space, " "),
                (Char { terminated: true }, "'c'"),
                (Space, " "),
                (Punct, "<<="),
                (Space, " "),
                (Punct, "->"),
                (Space, " "),
                (Other, "@"),
                (Ident, "x"),
            ]
        );
        assert_eq!(
            kinds("u8\"a\"L'b'"),
            vec![(Str { terminated: true }, "u8\"a\""), (Char { terminated: true }, "L'b'")]
        );
        assert_eq!(
            kinds("/* a */b//c\nd"),
            vec![
                (BlockComment { terminated: true }, "/* a */"),
                (Ident, "b"),
                (LineComment, "//c"),
                (Newline, "\n"),
                (Ident, "d"),
            ]
        );
        assert_eq!(
            kinds("don't x\ny"),
            vec![(Ident, "don"), (Char { terminated: false }, "'t x"), (Newline, "\n"), (Ident, "y")]
        );
        assert_eq!(kinds("/* open"), vec![(BlockComment { terminated: false }, "/* open")]);
        assert_eq!(kinds("%:%:..."), vec![(Punct, "%:%:"), (Punct, "...")]);
    }

    #[test]
    fn pasting() {
        assert!(would_paste(b"-", b"-"));
        assert!(would_paste(b"a", b"b"));
        assert!(would_paste(b"1", b"e"));
        assert!(would_paste(b"/", b"/"));
        assert!(would_paste(b"/", b"*"));
        assert!(would_paste(b"L", b"\"x\""));
        assert!(would_paste(b".", b"5"));
        assert!(!would_paste(b"(", b"a"));
        assert!(!would_paste(b"a", b"("));
        assert!(!would_paste(b"+", b"-"));
    }

    #[test]
    fn avoid_paste_like_cpp() {
        assert!(cpp_avoid_paste(b".", b"."));
        assert!(cpp_avoid_paste(b".", b"5"));
        assert!(cpp_avoid_paste(b"%:", b"%:"));
        assert!(cpp_avoid_paste(b"<<", b"="));
        assert!(cpp_avoid_paste(b"1", b"+"));
        assert!(cpp_avoid_paste(b"x", b"'c'"));
        assert!(!cpp_avoid_paste(b"(", b"("));
        assert!(!cpp_avoid_paste(b"+", b"-"));
        assert!(!cpp_avoid_paste(b"==", b"="));
        assert!(!cpp_avoid_paste(b"x", b"("));
    }
}
