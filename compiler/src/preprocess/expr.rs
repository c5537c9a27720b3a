//! `#if` expressions: C's integer constant expressions as GNU cpp evaluates them, in 64-bit
//! arithmetic (signed, or unsigned where an operand is unsigned, as cpp does), with
//! short-circuit `&&`, `||` and `?:` (no division-by-zero error in an unevaluated operand).
//!
//! [`eval`] is the stand-alone form used by `permutations.toml` (`skip`, `derived`): no macro
//! expansion, identifiers are looked up directly. The preprocessor uses [`eval_tokens`] on the
//! macro-expanded tokens of a directive.

use std::fmt;

use super::lexer::{self, Kind};

/// An expression that does not evaluate, with the bytes it is about.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ExprError {
    /// Byte offset into the expression text.
    pub offset: usize,
    /// Length in bytes of the offending text (0 at the end of the expression).
    pub len: usize,
    /// What is wrong.
    pub message: String,
}

impl fmt::Display for ExprError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.message)
    }
}

impl std::error::Error for ExprError {}

/// Evaluates an `#if`-style expression. `defined X` and `defined(X)` are 1 when `lookup`
/// knows `X`; other identifiers are `lookup`'s value, or 0.
pub fn eval(expr: &str, lookup: &dyn Fn(&str) -> Option<i64>) -> Result<i64, ExprError> {
    let lexed = lex(expr);
    let mut toks = Vec::with_capacity(lexed.len());
    let mut i = 0;
    while i < lexed.len() {
        let (kind, range) = &lexed[i];
        let text = &expr[range.clone()];
        if *kind == Kind::Ident && text == "defined" {
            let (name, used) = parse_defined(&lexed, i, expr).map_err(|(at, message)| {
                let r = lexed.get(at).map(|t| t.1.clone()).unwrap_or(expr.len()..expr.len());
                ExprError { offset: r.start, len: r.len(), message }
            })?;
            let v = lookup(name).is_some() as i64;
            toks.push(Token { kind: TokKind::Num(Value::signed(v)), text: "defined" });
            i += used;
            continue;
        }
        toks.push(Token::from_lexed(*kind, text, &|n| lookup(n)));
        i += 1;
    }
    eval_tokens(&toks).map(|v| v.v).map_err(|e| {
        let r = match lexed.get(e.at) {
            Some((_, r)) => r.clone(),
            None => expr.len()..expr.len(),
        };
        ExprError { offset: r.start, len: r.len(), message: e.message }
    })
}

/// Identifiers the expression references, in order of first appearance (the operand of
/// `defined` included, the keyword itself not).
pub fn identifiers(expr: &str) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    for (kind, r) in lex(expr) {
        let text = &expr[r];
        if kind == Kind::Ident && text != "defined" && !out.iter().any(|s| s == text) {
            out.push(text.to_string());
        }
    }
    out
}

fn lex(expr: &str) -> Vec<(Kind, std::ops::Range<usize>)> {
    let src = expr.as_bytes();
    let mut out = Vec::new();
    let mut pos = 0;
    loop {
        let (kind, len) = lexer::next(src, pos);
        match kind {
            Kind::Eof => return out,
            Kind::Space | Kind::Newline | Kind::LineComment | Kind::BlockComment { .. } => {}
            _ => out.push((kind, pos..pos + len)),
        }
        pos += len.max(1);
    }
}

/// `defined X` / `defined ( X )` starting at `i`: the name and how many tokens it took.
fn parse_defined<'a>(
    lexed: &[(Kind, std::ops::Range<usize>)],
    i: usize,
    src: &'a str,
) -> Result<(&'a str, usize), (usize, String)> {
    let tok = |j: usize| lexed.get(j).map(|(k, r)| (*k, &src[r.clone()]));
    match tok(i + 1) {
        Some((Kind::Ident, name)) => Ok((name, 2)),
        Some((Kind::Punct, "(")) => match tok(i + 2) {
            Some((Kind::Ident, name)) => match tok(i + 3) {
                Some((Kind::Punct, ")")) => Ok((name, 4)),
                _ => Err((i + 3, "missing ')' after \"defined\"".into())),
            },
            _ => Err((i + 2, "operator \"defined\" requires an identifier".into())),
        },
        _ => Err((i + 1, "operator \"defined\" requires an identifier".into())),
    }
}

/// A value of an `#if` expression: 64 bits, signed unless cpp's rules make it unsigned.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Value {
    /// The value's bits.
    pub v: i64,
    /// Whether cpp treats it as unsigned.
    pub unsigned: bool,
}

impl Value {
    /// A signed value.
    pub fn signed(v: i64) -> Value {
        Value { v, unsigned: false }
    }
    fn truth(self) -> bool {
        self.v != 0
    }
}

/// A token of an expression after macro expansion.
#[derive(Clone, Debug)]
pub struct Token<'a> {
    /// What it is.
    pub kind: TokKind,
    /// The spelling, for messages.
    pub text: &'a str,
}

/// What an expression token is.
#[derive(Clone, Debug)]
pub enum TokKind {
    /// A number or character constant.
    Num(Value),
    /// An operator or parenthesis.
    Punct,
    /// An identifier left after expansion (0), or a token that is not valid in an expression.
    Ident(i64),
    /// Not allowed in an expression; the message says why.
    Invalid(String),
}

impl<'a> Token<'a> {
    /// Classifies a lexed token; `lookup` gives identifiers their values.
    pub fn from_lexed(kind: Kind, text: &'a str, lookup: &dyn Fn(&str) -> Option<i64>) -> Token<'a> {
        let kind = match kind {
            Kind::Number => match parse_number(text) {
                Ok(v) => TokKind::Num(v),
                Err(m) => TokKind::Invalid(m),
            },
            Kind::Char { terminated: true } => match parse_char(text) {
                Ok(v) => TokKind::Num(v),
                Err(m) => TokKind::Invalid(m),
            },
            Kind::Ident => TokKind::Ident(lookup(text).unwrap_or(0)),
            Kind::Punct => TokKind::Punct,
            _ => TokKind::Invalid(format!("token \"{text}\" is not valid in preprocessor expressions")),
        };
        Token { kind, text }
    }
}

/// An error at token index `at` (== tokens.len() for the end).
#[derive(Debug, Clone)]
pub struct TokError {
    /// The token index.
    pub at: usize,
    /// What is wrong.
    pub message: String,
}

/// Parses a C integer constant the way cpp does (decimal, octal, hex, GNU binary; u/l suffixes).
pub fn parse_number(text: &str) -> Result<Value, String> {
    let b = text.as_bytes();
    let (radix, digits_start) = if b.len() > 1 && b[0] == b'0' && (b[1] == b'x' || b[1] == b'X') {
        (16, 2)
    } else if b.len() > 1 && b[0] == b'0' && (b[1] == b'b' || b[1] == b'B') {
        (2, 2)
    } else if b[0] == b'0' {
        (8, 0)
    } else {
        (10, 0)
    };
    let mut end = digits_start;
    while end < b.len() && (b[end] as char).is_digit(if radix == 8 { 10 } else { radix }) {
        end += 1;
    }
    let is_float = |rest: &[u8]| {
        rest.first() == Some(&b'.')
            || (radix == 10 || radix == 8) && matches!(rest.first(), Some(b'e' | b'E'))
            || radix == 16 && matches!(rest.first(), Some(b'p' | b'P'))
            || radix != 16
                && rest.last().is_some_and(|c| matches!(c, b'f' | b'F'))
                && rest.iter().all(|c| matches!(c, b'f' | b'F' | b'l' | b'L'))
    };
    if b[0] == b'.' || is_float(&b[end..]) {
        return Err("floating constant in preprocessor expression".into());
    }
    let suffix = &text[end..];
    let unsigned_suffix = match suffix.to_ascii_lowercase().as_str() {
        "" | "l" | "ll" => false,
        "u" | "ul" | "lu" | "ull" | "llu" => true,
        _ => {
            if suffix.eq_ignore_ascii_case("ll") || matches!(suffix, "lL" | "Ll") {
                false
            } else {
                return Err(format!("invalid suffix \"{suffix}\" on integer constant"));
            }
        }
    };
    if matches!(suffix, "lL" | "Ll" | "uLl" | "ulL" | "ULl" | "UlL" | "lLu" | "Llu" | "lLU" | "LlU") {
        return Err(format!("invalid suffix \"{suffix}\" on integer constant"));
    }
    let digits = &text[digits_start..end];
    if digits.is_empty() && radix != 8 {
        return Err(format!("invalid suffix \"{}\" on integer constant", &text[1..]));
    }
    if radix == 8 && digits.bytes().any(|c| c >= b'8') {
        return Err(format!(
            "invalid digit \"{}\" in octal constant",
            digits.bytes().find(|&c| c >= b'8').unwrap_or(b'8') as char
        ));
    }
    let mut v: u64 = 0;
    let mut overflow = false;
    for c in digits.bytes() {
        let d = (c as char).to_digit(radix).unwrap_or(0) as u64;
        match v.checked_mul(radix as u64).and_then(|x| x.checked_add(d)) {
            Some(x) => v = x,
            None => {
                overflow = true;
                v = v.wrapping_mul(radix as u64).wrapping_add(d);
            }
        }
    }
    let _ = overflow; // cpp pedwarns "integer constant is too large for its type" and wraps.
                      // A constant too big for a signed 64-bit value is unsigned (cpp warns, C says so for
                      // hex/octal; cpp treats decimal the same way).
    let unsigned = unsigned_suffix || v > i64::MAX as u64;
    Ok(Value { v: v as i64, unsigned })
}

/// Value of a character constant as cpp computes it (plain `char` is signed on the host).
pub fn parse_char(text: &str) -> Result<Value, String> {
    let b = text.as_bytes();
    let (prefix, q) = match b.iter().position(|&c| c == b'\'') {
        Some(q) => (&text[..q], q),
        None => return Err(format!("token \"{text}\" is not valid in preprocessor expressions")),
    };
    if b.len() < q + 2 || b[b.len() - 1] != b'\'' {
        return Err("missing terminating ' character".into());
    }
    let chars = char_values(&b[q + 1..b.len() - 1], prefix.is_empty());
    if chars.is_empty() {
        return Err("empty character constant".into());
    }
    let v = if prefix.is_empty() {
        if chars.len() == 1 {
            (chars[0] as u8) as i8 as i64
        } else {
            // Multi-character constant: an int, 8 bits per char, last 4 chars.
            let mut v: u32 = 0;
            for c in &chars {
                v = (v << 8) | (*c & 0xff);
            }
            v as i32 as i64
        }
    } else {
        let last = *chars.last().unwrap_or(&0);
        match prefix {
            "L" => last as i32 as i64,
            "u" => (last & 0xffff) as i64,
            _ => last as i64,
        }
    };
    let unsigned = matches!(prefix, "u" | "U");
    Ok(Value { v, unsigned })
}

/// The values of the characters between a character constant's quotes, escapes decoded; a
/// UTF-8 sequence is one character with a prefix and its bytes without (`plain`).
fn char_values(body: &[u8], plain: bool) -> Vec<u32> {
    let mut chars: Vec<u32> = Vec::new();
    let mut i = 0;
    while i < body.len() {
        if body[i] == b'\\' && i + 1 < body.len() {
            let (v, next) = escape_value(body, i + 1);
            chars.push(v);
            i = next;
            continue;
        }
        // A UTF-8 sequence counts as its bytes for a plain char constant.
        let s = std::str::from_utf8(&body[i..]).ok().and_then(|s| s.chars().next());
        match (plain, s) {
            (false, Some(ch)) => {
                chars.push(ch as u32);
                i += ch.len_utf8();
            }
            _ => {
                chars.push(body[i] as u32);
                i += 1;
            }
        }
    }
    chars
}

/// The value of the escape whose letter is at `body[i]` (just after its backslash), and the
/// offset after it: simple escapes, up to three octal digits, or any number of hex digits.
fn escape_value(body: &[u8], mut i: usize) -> (u32, usize) {
    let c = body[i];
    i += 1;
    let v = match c {
        b'n' => 10,
        b't' => 9,
        b'r' => 13,
        b'a' => 7,
        b'b' => 8,
        b'f' => 12,
        b'v' => 11,
        b'e' | b'E' => 27,
        b'0'..=b'7' => {
            let mut v = (c - b'0') as u32;
            let mut n = 1;
            while n < 3 && i < body.len() && (b'0'..=b'7').contains(&body[i]) {
                v = v * 8 + (body[i] - b'0') as u32;
                i += 1;
                n += 1;
            }
            v
        }
        b'x' => {
            let mut v: u32 = 0;
            while i < body.len() && body[i].is_ascii_hexdigit() {
                v = v.wrapping_mul(16).wrapping_add((body[i] as char).to_digit(16).unwrap_or(0));
                i += 1;
            }
            v
        }
        other => other as u32,
    };
    (v, i)
}

/// How [`eval`] reads one token of a stand-alone expression: for code that translates
/// expressions rather than evaluating them (the typed keys of [`crate::keys`]).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum TokenClass {
    /// A number or character constant, with its type.
    Number(Value),
    /// An identifier.
    Ident,
    /// An operator or parenthesis.
    Punct,
    /// Not valid in an expression; the message says why.
    Invalid(String),
}

/// The tokens of `expr` as [`eval`] classifies them, with their spelling.
pub fn tokens(expr: &str) -> Vec<(TokenClass, &str)> {
    lex(expr)
        .into_iter()
        .map(|(kind, r)| {
            let text = &expr[r];
            let class = match Token::from_lexed(kind, text, &|_| None).kind {
                TokKind::Num(v) => TokenClass::Number(v),
                TokKind::Ident(_) => TokenClass::Ident,
                TokKind::Punct => TokenClass::Punct,
                TokKind::Invalid(m) => TokenClass::Invalid(m),
            };
            (class, text)
        })
        .collect()
}

/// Evaluates tokens that are already macro-expanded, with `defined` already replaced.
pub fn eval_tokens(toks: &[Token<'_>]) -> Result<Value, TokError> {
    if toks.is_empty() {
        return Err(TokError { at: 0, message: "#if with no expression".into() });
    }
    let mut p = Parser { toks, pos: 0, depth: 0 };
    let v = p.comma(true)?;
    if p.pos < toks.len() {
        let t = &toks[p.pos];
        let message = match (&t.kind, t.text) {
            (TokKind::Punct, ")") => "missing '(' in expression".to_string(),
            (TokKind::Punct, ":") => "':' without preceding '?'".to_string(),
            (TokKind::Invalid(m), _) => m.clone(),
            (TokKind::Punct, op) if !is_expr_punct(op) => {
                format!("token \"{op}\" is not valid in preprocessor expressions")
            }
            _ => format!("missing binary operator before token \"{}\"", t.text),
        };
        return Err(TokError { at: p.pos, message });
    }
    Ok(v)
}

struct Parser<'t, 'a> {
    toks: &'t [Token<'a>],
    pos: usize,
    /// Nesting of parentheses, unary operators and `?:`, bounded so that no input overflows
    /// the stack.
    depth: usize,
}

/// cpp's words for signed arithmetic that overflows.
const OVERFLOW: &str = "integer overflow in preprocessor expression";

/// Deepest nesting an expression may have.
const MAX_DEPTH: usize = 1000;

fn is_expr_punct(op: &str) -> bool {
    binary_prec(op).is_some() || matches!(op, "(" | ")" | "?" | ":" | "," | "~" | "!")
}

fn binary_prec(op: &str) -> Option<u8> {
    Some(match op {
        "*" | "/" | "%" => 10,
        "+" | "-" => 9,
        "<<" | ">>" => 8,
        "<" | ">" | "<=" | ">=" => 7,
        "==" | "!=" => 6,
        "&" => 5,
        "^" => 4,
        "|" => 3,
        "&&" => 2,
        "||" => 1,
        _ => return None,
    })
}

impl Parser<'_, '_> {
    fn peek_punct(&self) -> Option<&str> {
        match self.toks.get(self.pos) {
            Some(Token { kind: TokKind::Punct, text }) => Some(text),
            _ => None,
        }
    }

    fn err<T>(&self, at: usize, message: impl Into<String>) -> Result<T, TokError> {
        Err(TokError { at, message: message.into() })
    }

    fn comma(&mut self, eval: bool) -> Result<Value, TokError> {
        let mut v = self.ternary(eval)?;
        while self.peek_punct() == Some(",") {
            self.pos += 1;
            v = self.ternary(eval)?;
        }
        Ok(v)
    }

    fn ternary(&mut self, eval: bool) -> Result<Value, TokError> {
        self.depth += 1;
        if self.depth > MAX_DEPTH {
            return self
                .err(self.pos.min(self.toks.len()), format!("expression nested more than {MAX_DEPTH} levels deep"));
        }
        let r = self.ternary_inner(eval);
        self.depth -= 1;
        r
    }

    fn ternary_inner(&mut self, eval: bool) -> Result<Value, TokError> {
        let cond = self.binary(0, eval)?;
        if self.peek_punct() != Some("?") {
            return Ok(cond);
        }
        let q = self.pos;
        self.pos += 1;
        let a = self.comma(eval && cond.truth())?;
        if self.peek_punct() != Some(":") {
            return self.err(q, "'?' without following ':'");
        }
        self.pos += 1;
        let b = self.ternary(eval && !cond.truth())?;
        let unsigned = a.unsigned || b.unsigned;
        let v = if cond.truth() { a.v } else { b.v };
        Ok(Value { v, unsigned })
    }

    fn binary(&mut self, min_prec: u8, eval: bool) -> Result<Value, TokError> {
        let mut lhs = self.unary(eval)?;
        loop {
            let Some(op) = self.peek_punct() else {
                return Ok(lhs);
            };
            let Some(prec) = binary_prec(op) else {
                return Ok(lhs);
            };
            if prec < min_prec {
                return Ok(lhs);
            }
            let op_at = self.pos;
            let op = self.toks[op_at].text;
            self.pos += 1;
            let rhs_eval = match op {
                "&&" => eval && lhs.truth(),
                "||" => eval && !lhs.truth(),
                _ => eval,
            };
            if self.pos >= self.toks.len() {
                return self.err(op_at, format!("operator '{op}' has no right operand"));
            }
            let rhs = self.binary(prec + 1, rhs_eval)?;
            lhs = self.apply(op, op_at, lhs, rhs, eval)?;
        }
    }

    fn apply(&self, op: &str, at: usize, a: Value, b: Value, eval: bool) -> Result<Value, TokError> {
        let u = a.unsigned || b.unsigned;
        let bool_v = |x: bool| Value::signed(x as i64);
        // Signed arithmetic that overflows is an error where it is evaluated (cpp reports
        // "integer overflow in preprocessor expression"); unsigned arithmetic wraps, as in C.
        let signed = |checked: Option<i64>, wrapped: i64| match checked {
            None if !u && eval => self.err(at, OVERFLOW),
            _ => Ok(Value { v: if u { wrapped } else { checked.unwrap_or(wrapped) }, unsigned: u }),
        };
        Ok(match op {
            "*" => signed(a.v.checked_mul(b.v), a.v.wrapping_mul(b.v))?,
            "/" | "%" => {
                if b.v == 0 {
                    if !eval {
                        return Ok(Value { v: 0, unsigned: u });
                    }
                    return self.err(at, "division by zero in #if");
                }
                let v = if u {
                    let (x, y) = (a.v as u64, b.v as u64);
                    (if op == "/" { x / y } else { x % y }) as i64
                } else if op == "/" {
                    return signed(a.v.checked_div(b.v), a.v.wrapping_div(b.v));
                } else {
                    a.v.wrapping_rem(b.v)
                };
                Value { v, unsigned: u }
            }
            "+" => signed(a.v.checked_add(b.v), a.v.wrapping_add(b.v))?,
            "-" => signed(a.v.checked_sub(b.v), a.v.wrapping_sub(b.v))?,
            "<<" | ">>" => {
                // cpp: a negative count shifts the other way; the result has the left type.
                let left = op == "<<";
                let (left, n) = if !b.unsigned && b.v < 0 { (!left, b.v.unsigned_abs()) } else { (left, b.v as u64) };
                let v = if left {
                    let v = if n >= 64 { 0 } else { ((a.v as u64) << n) as i64 };
                    // A signed shift overflows when shifting back does not give the operand
                    // (libcpp's `num_lshift`).
                    let back = if n >= 64 { 0 } else { v >> n };
                    if !a.unsigned && eval && back != a.v {
                        return self.err(at, OVERFLOW);
                    }
                    v
                } else if a.unsigned {
                    if n >= 64 {
                        0
                    } else {
                        ((a.v as u64) >> n) as i64
                    }
                } else if n >= 64 {
                    if a.v < 0 {
                        -1
                    } else {
                        0
                    }
                } else {
                    a.v >> n
                };
                Value { v, unsigned: a.unsigned }
            }
            "<" | ">" | "<=" | ">=" => {
                let ord = if u { (a.v as u64).cmp(&(b.v as u64)) } else { a.v.cmp(&b.v) };
                use std::cmp::Ordering::*;
                bool_v(match op {
                    "<" => ord == Less,
                    ">" => ord == Greater,
                    "<=" => ord != Greater,
                    _ => ord != Less,
                })
            }
            "==" => bool_v(a.v == b.v),
            "!=" => bool_v(a.v != b.v),
            "&" => Value { v: a.v & b.v, unsigned: u },
            "^" => Value { v: a.v ^ b.v, unsigned: u },
            "|" => Value { v: a.v | b.v, unsigned: u },
            "&&" => bool_v(a.truth() && b.truth()),
            "||" => bool_v(a.truth() || b.truth()),
            _ => return self.err(at, format!("token \"{op}\" is not valid in preprocessor expressions")),
        })
    }

    fn unary(&mut self, eval: bool) -> Result<Value, TokError> {
        self.depth += 1;
        if self.depth > MAX_DEPTH {
            return self
                .err(self.pos.min(self.toks.len()), format!("expression nested more than {MAX_DEPTH} levels deep"));
        }
        let r = self.unary_inner(eval);
        self.depth -= 1;
        r
    }

    fn unary_inner(&mut self, eval: bool) -> Result<Value, TokError> {
        let at = self.pos;
        let Some(t) = self.toks.get(at) else {
            return self.err(at, "#if with no expression");
        };
        self.pos += 1;
        match &t.kind {
            TokKind::Num(v) => Ok(*v),
            TokKind::Ident(v) => Ok(Value::signed(*v)),
            TokKind::Invalid(m) => self.err(at, m.clone()),
            TokKind::Punct => match t.text {
                "(" => {
                    if self.peek_punct() == Some(")") {
                        return self.err(self.pos, "missing expression between '(' and ')'");
                    }
                    let v = self.comma(eval)?;
                    if self.peek_punct() != Some(")") {
                        return self.err(at, "missing ')' in expression");
                    }
                    self.pos += 1;
                    Ok(v)
                }
                "+" | "-" | "~" | "!" => {
                    if self.pos >= self.toks.len() {
                        return self.err(at, format!("operator '{}' has no right operand", t.text));
                    }
                    let v = self.unary(eval)?;
                    if t.text == "-" && eval && !v.unsigned && v.v == i64::MIN {
                        return self.err(at, OVERFLOW);
                    }
                    Ok(match t.text {
                        "+" => v,
                        "-" => Value { v: v.v.wrapping_neg(), unsigned: v.unsigned },
                        "~" => Value { v: !v.v, unsigned: v.unsigned },
                        _ => Value::signed((!v.truth()) as i64),
                    })
                }
                op if binary_prec(op).is_some() || op == "?" || op == ":" || op == "," => {
                    if op == ":" {
                        self.err(at, "':' without preceding '?'")
                    } else {
                        self.err(at, format!("operator '{op}' has no left operand"))
                    }
                }
                ")" => self.err(at, "missing expression between '(' and ')'"),
                other => self.err(at, format!("token \"{other}\" is not valid in preprocessor expressions")),
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ev(s: &str) -> Result<i64, String> {
        eval(s, &|n| match n {
            "A" => Some(3),
            "B" => Some(0),
            _ => None,
        })
        .map_err(|e| format!("{}@{}+{}", e.message, e.offset, e.len))
    }

    #[test]
    fn arithmetic() {
        let cases: &[(&str, i64)] = &[
            ("1 + 2 * 3", 7),
            ("(1 + 2) * 3", 9),
            ("10 / 3", 3),
            ("-7 / 2", -3),
            ("-7 % 3", -1),
            ("1 << 62", 1 << 62),
            ("-1 << 63 >> 63", -1),
            ("-1 >> 70", -1),
            ("1 << -1", 0),
            ("8 >> -1", 16),
            ("~0", -1),
            ("!0 + !5", 1),
            ("0x10 + 010 + 0b11", 27),
            ("1 ? 2 : 3", 2),
            ("0 ? 2 : 0 ? 3 : 4", 4),
            ("1, 2", 2),
            ("3 > 2 > 1", 0),
            ("1 == 1 && 2 != 3", 1),
            ("0 || 0 || 5", 1),
            ("6 & 3 | 8 ^ 1", 11),
            ("-1 < 0u", 0),
            ("-1 > 0u", 1),
            ("0xffffffffffffffff == -1", 1),
            ("18446744073709551615 / 2", i64::MAX),
            ("(0 ? 1u : -1) > 0", 1),
            ("'a'", 97),
            ("'\\377'", -1),
            ("'\\n' + L'b'", 10 + 98),
            ("'ab'", 0x6162),
            ("10L + 2ull", 12),
        ];
        for (s, want) in cases {
            assert_eq!(ev(s), Ok(*want), "{s}");
        }
    }

    #[test]
    fn lookups_and_defined() {
        assert_eq!(ev("A * 2"), Ok(6));
        assert_eq!(ev("defined A + defined(B) + defined C"), Ok(2));
        assert_eq!(ev("UNKNOWN + 1"), Ok(1));
        assert_eq!(ev("defined(A) && A > 2"), Ok(1));
        assert_eq!(identifiers("defined(A) && B_1 > A || !defined C"), vec!["A", "B_1", "C"]);
    }

    #[test]
    fn short_circuit() {
        assert_eq!(ev("0 && 1 / 0"), Ok(0));
        assert_eq!(ev("1 || 1 % 0"), Ok(1));
        assert_eq!(ev("1 ? 2 : 1 / 0"), Ok(2));
        assert_eq!(ev("0 ? 1 / 0 : 7"), Ok(7));
        // Overflow where it is not evaluated, and unsigned arithmetic, are no errors.
        assert_eq!(ev("0 && 9223372036854775807 + 1"), Ok(0));
        assert_eq!(ev("18446744073709551615u + 1"), Ok(0));
        assert_eq!(ev("9223372036854775807u + 1 == 9223372036854775808u"), Ok(1));
    }

    #[test]
    fn errors() {
        let cases: &[(&str, &str)] = &[
            ("", "#if with no expression@0+0"),
            ("9223372036854775807 + 1", "integer overflow in preprocessor expression@20+1"),
            ("-9223372036854775807 - 2", "integer overflow in preprocessor expression@21+1"),
            ("4611686018427387904 * 2", "integer overflow in preprocessor expression@20+1"),
            ("-(-9223372036854775807 - 1)", "integer overflow in preprocessor expression@0+1"),
            ("(-9223372036854775807 - 1) / -1", "integer overflow in preprocessor expression@27+1"),
            ("1 << 63", "integer overflow in preprocessor expression@2+2"),
            ("2 << 62", "integer overflow in preprocessor expression@2+2"),
            ("1 << 64", "integer overflow in preprocessor expression@2+2"),
            ("5 >> -62", "integer overflow in preprocessor expression@2+2"),
            ("1 / 0", "division by zero in #if@2+1"),
            ("A % B", "division by zero in #if@2+1"),
            ("(1", "missing ')' in expression@0+1"),
            ("1)", "missing '(' in expression@1+1"),
            ("1 2", "missing binary operator before token \"2\"@2+1"),
            ("1 +", "operator '+' has no right operand@2+1"),
            ("* 1", "operator '*' has no left operand@0+1"),
            ("()", "missing expression between '(' and ')'@1+1"),
            ("1.0", "floating constant in preprocessor expression@0+3"),
            ("1 ? 2", "'?' without following ':'@2+1"),
            ("1 : 2", "':' without preceding '?'@2+1"),
            ("defined", "operator \"defined\" requires an identifier@7+0"),
            ("defined(A", "missing ')' after \"defined\"@9+0"),
            ("\"s\"", "token \"\"s\"\" is not valid in preprocessor expressions@0+3"),
            ("1 = 2", "token \"=\" is not valid in preprocessor expressions@2+1"),
            ("12abc", "invalid suffix \"abc\" on integer constant@0+5"),
            ("09", "invalid digit \"9\" in octal constant@0+2"),
        ];
        let deep = format!("{}1{}", "(".repeat(100_000), ")".repeat(100_000));
        assert!(ev(&deep).unwrap_err().starts_with("expression nested more than 1000 levels deep"));
        let deep = format!("{}1", "- ".repeat(100_000));
        assert!(ev(&deep).unwrap_err().starts_with("expression nested more than 1000 levels deep"));
        let deep = "1 ? ".repeat(100_000) + "1";
        assert!(ev(&deep).unwrap_err().starts_with("expression nested more than 1000 levels deep"));
        for (s, want) in cases {
            assert_eq!(ev(s).unwrap_err(), *want, "{s}");
        }
    }
}
