//! The preprocessor proper: directives, includes and macro expansion.
//!
//! Macro expansion follows GNU cpp's own algorithm (cpplib `macro.c`) so the token streams
//! agree in the corner cases: a stack of token contexts, one per macro being rescanned, with
//! the macro disabled while its context is on the stack; a name met while its macro is
//! disabled is painted (`NO_EXPAND`) for good; arguments are collected unexpanded (painting
//! disabled names), pre-expanded in isolation (a barrier context) and substituted; `##` is
//! applied when the replacement list is built, with placemarkers for empty operands.
//!
//! Text outside macro invocations is not tokenized into tokens at all: the scanner lexes it
//! in place and copies whole runs to the output, which keeps the WGSL formatting and makes
//! the common case a `memcpy` plus one source map entry per run.

use std::collections::{HashMap, HashSet};
use std::hash::{BuildHasherDefault, Hasher};
use std::ops::Range;
use std::path::{Component, Path, PathBuf};
use std::sync::Arc;

use codespan_reporting::diagnostic::{Diagnostic, Label};

use super::expr;
use super::lexer::{self, Kind};
use super::map::{Entry, IncludeCtx, SourceMap, NONE};
use super::source::{FileId, SourceCache, SourceFile};
use super::{Error, Options, Output};

// ---------------------------------------------------------------------------------------------
// Interning

#[derive(Default, Clone, Copy)]
struct FxHasher(u64);

impl Hasher for FxHasher {
    #[inline]
    fn write(&mut self, bytes: &[u8]) {
        const K: u64 = 0x51_7c_c1_b7_27_22_0a_95;
        let mut h = self.0;
        let mut chunks = bytes.chunks_exact(8);
        for c in &mut chunks {
            let w = u64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]);
            h = (h.rotate_left(5) ^ w).wrapping_mul(K);
        }
        for &b in chunks.remainder() {
            h = (h.rotate_left(5) ^ b as u64).wrapping_mul(K);
        }
        self.0 = h;
    }
    #[inline]
    fn write_u8(&mut self, i: u8) {
        self.0 = (self.0.rotate_left(5) ^ i as u64).wrapping_mul(0x51_7c_c1_b7_27_22_0a_95);
    }
    #[inline]
    fn finish(&self) -> u64 {
        self.0
    }
}

type FxBuild = BuildHasherDefault<FxHasher>;

type Sym = u32;

#[derive(Default)]
struct Interner {
    map: HashMap<Arc<str>, Sym, FxBuild>,
    strs: Vec<Arc<str>>,
}

impl Interner {
    fn intern(&mut self, s: &str) -> Sym {
        if let Some(&sym) = self.map.get(s) {
            return sym;
        }
        let sym = self.strs.len() as Sym;
        let a: Arc<str> = Arc::from(s);
        self.strs.push(a.clone());
        self.map.insert(a, sym);
        sym
    }
    #[inline]
    fn get(&self, s: &str) -> Option<Sym> {
        self.map.get(s).copied()
    }
    #[inline]
    fn str(&self, sym: Sym) -> &str {
        self.strs.get(sym as usize).map_or("", |s| s)
    }
}

// ---------------------------------------------------------------------------------------------
// Tokens and macros

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum TK {
    Ident,
    Number,
    Str,
    Char,
    Punct,
    Other,
    /// An empty `##` operand.
    Placemarker,
    /// cpp's padding token: no text, only spacing for the printer and for `#`. `WHITE` is its
    /// source token's leading whitespace; `NULL_SOURCE` marks one with no source.
    Padding,
    /// The end of a barrier context or of the current file.
    Eof,
}

const WHITE: u8 = 1;
const NO_EXPAND: u8 = 2;
/// The location is in a macro definition (or nowhere), not text of the file being output.
const FROM_DEF: u8 = 4;
const PASTE_LEFT: u8 = 8;
const STRINGIFY: u8 = 16;
/// A `,` before `__VA_ARGS__` joined by GNU `, ##`.
const VA_COMMA: u8 = 32;
/// A padding token with no source (cpp's `avoid_paste`).
const NULL_SOURCE: u8 = 64;

const NO_PARAM: u16 = u16::MAX;

#[derive(Clone, Copy, Debug)]
struct Tok {
    sym: Sym,
    /// Include context and spliced offset of the spelling (`ctx == NONE`: no location).
    ctx: u32,
    src: u32,
    len: u32,
    param: u16,
    kind: TK,
    flags: u8,
}

impl Tok {
    fn eof() -> Tok {
        Tok { sym: 0, ctx: NONE, src: 0, len: 0, param: NO_PARAM, kind: TK::Eof, flags: 0 }
    }
}

fn tk_of(kind: Kind) -> TK {
    match kind {
        Kind::Ident => TK::Ident,
        Kind::Number => TK::Number,
        Kind::Str { .. } => TK::Str,
        Kind::Char { .. } => TK::Char,
        Kind::Punct => TK::Punct,
        _ => TK::Other,
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Builtin {
    None,
    Line,
    File,
    Counter,
    IncludeLevel,
    BaseFile,
    Pragma,
    /// `__has_include` / `__has_include_next`, only meaningful in `#if`.
    HasInclude,
    Date,
    Time,
}

#[derive(Clone, Debug)]
struct Macro {
    func: bool,
    variadic: bool,
    params: Vec<Sym>,
    body: Arc<[Tok]>,
    /// The body has `##` (else expansion is a plain copy).
    pastes: bool,
    /// The body has `__VA_OPT__`.
    va_opt: bool,
    builtin: Builtin,
    /// Where the name was defined (`ctx == NONE`: predefined).
    ctx: u32,
    site: Range<u32>,
    disabled: bool,
}

struct Context {
    toks: Vec<Tok>,
    pos: usize,
    /// The macro this context rescans (disabled while the context is on the stack).
    mac: u32,
    /// Reading stops here (argument pre-expansion, directive lines).
    barrier: bool,
}

#[derive(Clone, Debug)]
struct Cond {
    /// Offset of the `#` of the opening directive, and its name for messages.
    site: Range<u32>,
    name: &'static str,
    /// Some group of this conditional was taken (later `#elif`/`#else` are skipped).
    taken: bool,
    else_seen: bool,
}

struct Frame {
    source: Arc<SourceFile>,
    file: FileId,
    ctx: u32,
    pos: usize,
    /// Only whitespace since the last newline.
    bol: bool,
    conds: Vec<Cond>,
    /// The name `__FILE__` gives, spelled as cpp would.
    name: String,
    /// `#line` adjustment: added to physical line numbers.
    line_delta: i64,
    /// Include guard detection: the macro of an `#ifndef X` opening the file, while still
    /// possible that it guards the whole file.
    guard: GuardState,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum GuardState {
    /// Nothing but whitespace and comments seen yet.
    Start,
    /// `#ifndef X` is the first thing; still inside it.
    Inside(Sym),
    /// The `#endif` closing it was seen; only whitespace may follow.
    Closed(Sym),
    No,
}

/// An internal error before it is made a diagnostic.
type PResult<T> = Result<T, Error>;

/// Well-known symbols.
struct Syms {
    defined: Sym,
    va_args: Sym,
    va_opt: Sym,
    has_include: Sym,
    has_include_next: Sym,
    lparen: Sym,
    rparen: Sym,
    comma: Sym,
    one: Sym,
    zero: Sym,
}

pub(crate) struct Pp<'a> {
    opts: &'a Options,
    cache: &'a SourceCache,
    it: Interner,
    syms: Syms,
    /// Current definition of each symbol (index into `defs`) or `NONE`.
    macro_of: Vec<u32>,
    defs: Vec<Macro>,
    pushed: HashMap<Sym, Vec<u32>, FxBuild>,
    /// Spare token vectors.
    pool: Vec<Vec<Tok>>,
    /// Filter of macro names: bit `len & 63` of `first byte`'s word is set when some macro
    /// with that first byte and length was ever defined.
    name_filter: [u64; 256],
    frames: Vec<Frame>,
    stack: Vec<Context>,
    out: String,
    map: SourceMap,
    warnings: Vec<Diagnostic<FileId>>,
    files: Vec<FileId>,
    once: HashSet<FileId>,
    guards: HashMap<FileId, Sym, FxBuild>,
    /// Tokens macro expansion may still make.
    budget: usize,
    counter: i64,
    /// Output range of the last token written (for paste avoidance).
    last_tok: Range<usize>,
    /// The top-level macro invocation being expanded: context, spliced range.
    inv: Option<(u32, u32, u32)>,
    /// Line `__LINE__` gives inside a directive.
    directive_line: Option<i64>,
    /// Allowed roots for includes (canonical).
    roots: Vec<PathBuf>,
    base_name: String,
}

// ---------------------------------------------------------------------------------------------
// Entry points

pub(crate) fn run(file: FileId, opts: &Options, cache: &SourceCache) -> Result<Output, Error> {
    run_named(file, None, opts, cache)
}

pub(crate) fn run_named(file: FileId, name: Option<String>, opts: &Options, cache: &SourceCache) -> Result<Output, Error> {
    let Some(source) = cache.get(file) else {
        return Err(Error::new("unknown file id", Vec::new()));
    };
    if source.text().len() >= (u32::MAX / 2) as usize {
        return Err(Error::new(format!("`{}` is too large to preprocess", source.name), Vec::new()));
    }
    let mut pp = Pp::new(opts, cache, &source)?;
    let name = name.unwrap_or_else(|| source.name.clone());
    pp.base_name = name.clone();
    pp.push_file(file, source, name, NONE, 0..0);
    pp.run_main()?;
    pp.map.entries.shrink_to_fit();
    Ok(Output { text: pp.out, map: pp.map, files: pp.files, warnings: pp.warnings })
}

/// Resolves `<spelling>` through the virtual roots, then the include roots.
pub(crate) fn resolve_angle(spelling: &str, opts: &Options) -> Result<PathBuf, String> {
    match resolve_in_roots(spelling, opts) {
        Resolved::Found(p, _) => Ok(p),
        Resolved::Escapes(p) => Err(format!("`{spelling}` resolves to `{}`, outside its root", p.display())),
        Resolved::NotFound => Err(format!("cannot find `{spelling}` in the include roots")),
    }
}

enum Resolved {
    /// Canonical path, and the name cpp would give it.
    Found(PathBuf, String),
    Escapes(PathBuf),
    NotFound,
}

/// `candidate` if it exists inside `root` (both canonicalized).
fn contained(candidate: &Path, root: &Path) -> Resolved {
    let Ok(c) = candidate.canonicalize() else { return Resolved::NotFound };
    if !c.is_file() {
        return Resolved::NotFound;
    }
    let root = root.canonicalize().unwrap_or_else(|_| root.to_path_buf());
    if c.starts_with(&root) {
        Resolved::Found(c, String::new())
    } else {
        Resolved::Escapes(c)
    }
}

fn virtual_match<'s>(spelling: &'s str, prefix: &str) -> Option<&'s str> {
    let prefix = prefix.trim_end_matches('/');
    let rest = spelling.strip_prefix(prefix)?;
    if rest.is_empty() || rest.starts_with('/') {
        Some(rest.trim_start_matches('/'))
    } else {
        None
    }
}

fn relative_ok(rel: &str) -> bool {
    !Path::new(rel).components().any(|c| matches!(c, Component::Prefix(_) | Component::RootDir))
}

fn resolve_in_roots(spelling: &str, opts: &Options) -> Resolved {
    for (prefix, dir) in &opts.virtual_roots {
        if let Some(rest) = virtual_match(spelling, prefix) {
            return match contained(&dir.join(rest), dir) {
                Resolved::Found(p, _) => Resolved::Found(p, format!("{}/{rest}", prefix.trim_end_matches('/'))),
                other => other,
            };
        }
    }
    if !relative_ok(spelling) {
        return Resolved::NotFound;
    }
    let mut escaped = None;
    for root in &opts.include_roots {
        match contained(&root.join(spelling), root) {
            Resolved::Found(p, _) => {
                let name = format!("{}/{spelling}", root.display());
                return Resolved::Found(p, name);
            }
            Resolved::Escapes(p) => escaped = escaped.or(Some(p)),
            Resolved::NotFound => {}
        }
    }
    match escaped {
        Some(p) => Resolved::Escapes(p),
        None => Resolved::NotFound,
    }
}

// ---------------------------------------------------------------------------------------------

impl<'a> Pp<'a> {
    fn new(opts: &'a Options, cache: &'a SourceCache, main: &SourceFile) -> PResult<Pp<'a>> {
        let mut it = Interner::default();
        let syms = Syms {
            defined: it.intern("defined"),
            va_args: it.intern("__VA_ARGS__"),
            va_opt: it.intern("__VA_OPT__"),
            has_include: it.intern("__has_include"),
            has_include_next: it.intern("__has_include_next"),
            lparen: it.intern("("),
            rparen: it.intern(")"),
            comma: it.intern(","),
            one: it.intern("1"),
            zero: it.intern("0"),
        };
        let mut roots: Vec<PathBuf> = Vec::new();
        let main_dir = main.path.parent().filter(|p| p.is_dir()).map(|p| p.to_path_buf());
        if let Some(d) = &main_dir {
            roots.push(d.clone());
        }
        for r in &opts.include_roots {
            roots.push(r.canonicalize().unwrap_or_else(|_| r.clone()));
        }
        for (_, r) in &opts.virtual_roots {
            roots.push(r.canonicalize().unwrap_or_else(|_| r.clone()));
        }
        let mut pp = Pp {
            opts,
            cache,
            it,
            syms,
            macro_of: Vec::new(),
            defs: Vec::new(),
            pushed: HashMap::default(),
            pool: Vec::new(),
            name_filter: [0; 256],
            frames: Vec::new(),
            stack: Vec::new(),
            out: String::with_capacity(main.text().len() + main.text().len() / 4),
            map: SourceMap::default(),
            warnings: Vec::new(),
            files: Vec::new(),
            once: HashSet::new(),
            guards: HashMap::default(),
            budget: opts.max_output_bytes.max(1024),
            counter: 0,
            last_tok: 0..0,
            inv: None,
            directive_line: None,
            roots,
            base_name: String::new(),
        };
        for (name, b) in [
            ("__LINE__", Builtin::Line),
            ("__FILE__", Builtin::File),
            ("__COUNTER__", Builtin::Counter),
            ("__INCLUDE_LEVEL__", Builtin::IncludeLevel),
            ("__BASE_FILE__", Builtin::BaseFile),
            ("_Pragma", Builtin::Pragma),
            ("__has_include", Builtin::HasInclude),
            ("__has_include_next", Builtin::HasInclude),
            ("__DATE__", Builtin::Date),
            ("__TIME__", Builtin::Time),
        ] {
            let sym = pp.it.intern(name);
            pp.set_macro(sym, Macro { func: false, variadic: false, params: Vec::new(), body: Arc::from(Vec::new()), pastes: false, va_opt: false, builtin: b, ctx: NONE, site: 0..0, disabled: false });
        }
        let predefined = [
            ("__STDC__", "1"),
            ("__STDC_VERSION__", "201112L"),
            ("__STDC_HOSTED__", "1"),
            ("__STDC_UTF_16__", "1"),
            ("__STDC_UTF_32__", "1"),
        ];
        for (name, value) in predefined {
            pp.define_text(name, value)?;
        }
        for (name, value) in &opts.defines {
            pp.define_text(name, value)?;
        }
        Ok(pp)
    }

    fn set_macro(&mut self, sym: Sym, m: Macro) -> u32 {
        let idx = self.defs.len() as u32;
        let name = self.it.str(sym).as_bytes();
        if let Some(&b) = name.first() {
            self.name_filter[b as usize] |= 1u64 << (name.len() & 63);
        }
        self.defs.push(m);
        if self.macro_of.len() <= sym as usize {
            self.macro_of.resize(sym as usize + 1, NONE);
        }
        self.macro_of[sym as usize] = idx;
        idx
    }

    #[inline]
    fn macro_idx(&self, sym: Sym) -> u32 {
        self.macro_of.get(sym as usize).copied().unwrap_or(NONE)
    }

    /// A `-D NAME=VALUE` definition (NAME may carry a parameter list: `F(x)`).
    fn define_text(&mut self, name: &str, value: &str) -> PResult<()> {
        let line = format!("{name} {value}");
        let toks = self.lex_string(&line);
        let toks = match toks {
            Some(t) => t,
            None => return Err(Error::new(format!("invalid definition `{name}={value}`"), Vec::new())),
        };
        // `NAME(x)` must keep `(` attached to the name.
        self.parse_define(toks, true)
    }

    /// Tokens of a string with no location (predefined macros).
    fn lex_string(&mut self, s: &str) -> Option<Vec<Tok>> {
        let b = s.as_bytes();
        let mut pos = 0;
        let mut white = false;
        let mut out = Vec::new();
        loop {
            let (kind, len) = lexer::next(b, pos);
            match kind {
                Kind::Eof => return Some(out),
                Kind::Space | Kind::Newline | Kind::LineComment | Kind::BlockComment { terminated: true } => white = true,
                Kind::BlockComment { terminated: false } | Kind::Str { terminated: false } => return None,
                _ => {
                    let sym = self.it.intern(&s[pos..pos + len]);
                    let flags = if white { WHITE } else { 0 } | FROM_DEF;
                    out.push(Tok { sym, ctx: NONE, src: 0, len: len as u32, param: NO_PARAM, kind: tk_of(kind), flags });
                    white = false;
                }
            }
            pos += len.max(1);
        }
    }

    // -----------------------------------------------------------------------------------------
    // Diagnostics

    fn labels_at(&self, ctx: u32, range: Range<u32>, message: &str) -> Vec<Label<FileId>> {
        let Some(c) = self.map.ctxs.get(ctx as usize) else { return Vec::new() };
        let r = c.source.original_range(range.start as usize..range.end as usize);
        let mut labels = vec![Label::primary(c.file, r).with_message(message)];
        for (f, r) in self.map.chain(ctx) {
            labels.push(Label::secondary(f, r).with_message("included from here"));
        }
        labels
    }

    /// Labels for a token: its own text, or for macro-made tokens the invocation being
    /// expanded with the token's place in the definition.
    fn tok_labels(&self, t: &Tok, message: &str) -> Vec<Label<FileId>> {
        if t.flags & FROM_DEF == 0 && t.ctx != NONE {
            return self.labels_at(t.ctx, t.src..t.src + t.len, message);
        }
        let mut labels = match self.inv {
            Some((ctx, s, e)) => self.labels_at(ctx, s..e, message),
            None => self.frame_labels(message),
        };
        if let Some(c) = self.map.ctxs.get(t.ctx as usize) {
            let r = c.source.original_range(t.src as usize..(t.src + t.len) as usize);
            labels.insert(1.min(labels.len()), Label::secondary(c.file, r).with_message("in this macro's definition"));
        }
        labels
    }

    /// Labels for a whole invocation whose name is `name`: from the name to the last token
    /// read from the file when the name is text of the file.
    fn invocation_labels(&self, name: &Tok, message: &str) -> Vec<Label<FileId>> {
        match self.inv {
            Some((ctx, _, end)) if name.flags & FROM_DEF == 0 && name.ctx == ctx && end > name.src => {
                self.labels_at(ctx, name.src..end, message)
            }
            _ => self.tok_labels(name, message),
        }
    }

    /// Labels at the current position of the current file.
    fn frame_labels(&self, message: &str) -> Vec<Label<FileId>> {
        match self.frames.last() {
            Some(f) => {
                let p = f.pos.min(f.source.text().len()) as u32;
                self.labels_at(f.ctx, p..p, message)
            }
            None => Vec::new(),
        }
    }

    fn err_tok<T>(&self, t: &Tok, message: impl Into<String>, label: &str) -> PResult<T> {
        Err(Error::new(message, self.tok_labels(t, label)))
    }

    fn err_at<T>(&self, ctx: u32, range: Range<u32>, message: impl Into<String>, label: &str) -> PResult<T> {
        Err(Error::new(message, self.labels_at(ctx, range, label)))
    }

    fn warn(&mut self, message: impl Into<String>, labels: Vec<Label<FileId>>) {
        self.warnings.push(Diagnostic::warning().with_message(message.into()).with_labels(labels));
    }

    // -----------------------------------------------------------------------------------------
    // Files

    fn push_file(&mut self, file: FileId, source: Arc<SourceFile>, name: String, parent: u32, site: Range<u32>) {
        let ctx = self.map.ctxs.len() as u32;
        self.map.ctxs.push(IncludeCtx { file, source: source.clone(), parent, site });
        if !self.files.contains(&file) {
            self.files.push(file);
        }
        self.frames.push(Frame {
            source,
            file,
            ctx,
            pos: 0,
            bol: true,
            conds: Vec::new(),
            name,
            line_delta: 0,
            guard: GuardState::Start,
        });
    }

    fn run_main(&mut self) -> PResult<()> {
        while !self.frames.is_empty() {
            self.scan_text()?;
        }
        Ok(())
    }

    /// End of the current file: checks conditionals, records guards, pops it.
    fn end_of_file(&mut self) -> PResult<()> {
        let Some(frame) = self.frames.last() else { return Ok(()) };
        if let Some(c) = frame.conds.last() {
            let (ctx, site, name) = (frame.ctx, c.site.clone(), c.name);
            return self.err_at(ctx, site, format!("unterminated #{name}"), "this conditional is never closed");
        }
        if let GuardState::Closed(sym) = frame.guard {
            self.guards.insert(frame.file, sym);
        }
        self.frames.pop();
        if !self.frames.is_empty() && !self.out.is_empty() && !self.out.ends_with('\n') {
            self.out.push('\n');
        }
        Ok(())
    }

    // -----------------------------------------------------------------------------------------
    // Output

    fn check_output(&self) -> PResult<()> {
        if self.out.len() > self.opts.max_output_bytes {
            return Err(Error::new(
                format!("output exceeds the limit of {} bytes", self.opts.max_output_bytes),
                self.inv.map_or_else(|| self.frame_labels("while preprocessing this"), |(c, s, e)| self.labels_at(c, s..e, "while expanding this")),
            ));
        }
        Ok(())
    }

    /// Copies `text[start..end]` of the current frame to the output.
    fn copy_run(&mut self, ctx: u32, text: &str, start: usize, end: usize, last_tok: Option<Range<usize>>) -> PResult<()> {
        if end <= start {
            return Ok(());
        }
        let bytes = text.as_bytes();
        // After macro output, the run's first token may paste onto the last token written.
        if self.last_tok.end == self.out.len() && !self.last_tok.is_empty() {
            let first = bytes[start];
            if !matches!(first, b' ' | b'\t' | b'\n' | b'\r') {
                let (_, len) = lexer::next(bytes, start);
                let len = len.min(end - start).max(1);
                if lexer::would_paste(self.out[self.last_tok.clone()].as_bytes(), &bytes[start..start + len]) {
                    self.out.push(' ');
                }
            }
        }
        let out_at = self.out.len();
        self.push_copy_entry(ctx, start as u32, end as u32, out_at as u32);
        self.out.push_str(&text[start..end]);
        self.last_tok = match last_tok {
            Some(r) if r.end == end => (out_at + r.start - start)..(out_at + r.end - start),
            _ => 0..0,
        };
        self.check_output()
    }

    fn push_copy_entry(&mut self, ctx: u32, src: u32, end: u32, out: u32) {
        if let Some(last) = self.map.entries.last_mut() {
            if !last.is_macro && last.ctx == ctx && last.end == src && last.out + (last.end - last.src) == out {
                last.end = end;
                return;
            }
        }
        self.map.entries.push(Entry { out, ctx, src, end, def_ctx: NONE, def_src: 0, def_len: 0, is_macro: false });
    }

    fn emit_space(&mut self) {
        if !self.out.is_empty() && !self.out.ends_with([' ', '\n', '\t']) {
            self.out.push(' ');
        }
    }

    /// Writes a token made by macro expansion at top level.
    fn emit(&mut self, t: Tok) -> PResult<()> {
        if t.kind == TK::Padding {
            if t.flags & (WHITE | NULL_SOURCE) == WHITE {
                self.emit_space();
            }
            return Ok(());
        }
        if t.kind == TK::Placemarker || t.kind == TK::Eof {
            return Ok(());
        }
        let text: &str = self.it.strs.get(t.sym as usize).map_or("", |s| s);
        let adjacent = self.last_tok.end == self.out.len() && !self.last_tok.is_empty();
        if (t.flags & WHITE != 0) || (adjacent && lexer::would_paste(self.out[self.last_tok.clone()].as_bytes(), text.as_bytes())) {
            if !self.out.is_empty() && !self.out.ends_with([' ', '\n', '\t']) {
                self.out.push(' ');
            }
        }
        let out_at = self.out.len() as u32;
        if t.flags & FROM_DEF == 0 && t.ctx != NONE {
            self.push_copy_entry(t.ctx, t.src, t.src + t.len, out_at);
        } else {
            let (ctx, src, end) = self.inv.unwrap_or((NONE, 0, 0));
            self.map.entries.push(Entry { out: out_at, ctx, src, end, def_ctx: t.ctx, def_src: t.src, def_len: t.len, is_macro: true });
        }
        let text: &str = self.it.strs.get(t.sym as usize).map_or("", |s| s);
        self.out.push_str(text);
        self.last_tok = out_at as usize..self.out.len();
        self.check_output()
    }

    // -----------------------------------------------------------------------------------------
    // The scanner: text outside macro invocations

    fn scan_text(&mut self) -> PResult<()> {
        let Some(frame) = self.frames.last_mut() else { return Ok(()) };
        let source = frame.source.clone();
        let ctx = frame.ctx;
        let text = source.text();
        let bytes = text.as_bytes();
        let mut pos = frame.pos;
        let mut bol = frame.bol;
        let mut run_start = pos;
        let mut last_tok: Option<Range<usize>> = None;
        let mut guard_check = matches!(frame.guard, GuardState::Start | GuardState::Closed(_));
        loop {
            let (kind, len) = lexer::next(bytes, pos);
            match kind {
                Kind::Eof => {
                    self.copy_run(ctx, text, run_start, pos, last_tok)?;
                    if let Some(f) = self.frames.last_mut() {
                        f.pos = pos;
                    }
                    return self.end_of_file();
                }
                Kind::Newline => {
                    pos += 1;
                    bol = true;
                }
                Kind::Space => pos += len,
                Kind::LineComment | Kind::BlockComment { terminated: true } => {
                    self.copy_run(ctx, text, run_start, pos, last_tok.clone())?;
                    self.emit_space();
                    self.last_tok = 0..0;
                    pos += len;
                    run_start = pos;
                }
                Kind::BlockComment { terminated: false } => {
                    return self.err_at(ctx, pos as u32..pos as u32 + 2, "unterminated comment", "this comment is never closed");
                }
                Kind::Punct if bol && (bytes[pos] == b'#' || (len == 2 && &bytes[pos..pos + 2] == b"%:")) => {
                    self.copy_run(ctx, text, run_start, pos, last_tok)?;
                    if let Some(f) = self.frames.last_mut() {
                        f.pos = pos + len;
                        f.bol = false;
                    }
                    return self.directive(pos);
                }
                _ => {
                    if guard_check {
                        guard_check = false;
                        if let Some(f) = self.frames.last_mut() {
                            f.guard = GuardState::No;
                        }
                    }
                    bol = false;
                    match kind {
                        Kind::Ident if self.name_filter[bytes[pos] as usize] & (1u64 << (len & 63)) != 0 => {
                            let name = &text[pos..pos + len];
                            if let Some(sym) = self.it.get(name) {
                                let m = self.macro_idx(sym);
                                if m != NONE {
                                    let func = self.defs[m as usize].func;
                                    if !func || self.peek_file_lparen(bytes, pos + len) {
                                        self.copy_run(ctx, text, run_start, pos, last_tok)?;
                                        if let Some(f) = self.frames.last_mut() {
                                            f.pos = pos + len;
                                            f.bol = false;
                                        }
                                        let name_tok = Tok { sym, ctx, src: pos as u32, len: len as u32, param: NO_PARAM, kind: TK::Ident, flags: 0 };
                                        return self.expand_top(name_tok, m);
                                    }
                                }
                            }
                        }
                        Kind::Str { terminated: false } => {
                            return self.err_at(ctx, pos as u32..pos as u32 + 1, "missing terminating \" character", "this string is never closed");
                        }
                        Kind::Char { terminated: false } => {
                            let labels = self.labels_at(ctx, pos as u32..pos as u32 + 1, "this character constant is never closed");
                            self.warn("missing terminating ' character", labels);
                        }
                        _ => {}
                    }
                    last_tok = Some(pos..pos + len);
                    pos += len;
                }
            }
        }
    }

    /// Is the next token in the file text from `pos` a `(` (no directive line in between)?
    fn peek_file_lparen(&self, bytes: &[u8], mut pos: usize) -> bool {
        let mut bol = false;
        loop {
            let (kind, len) = lexer::next(bytes, pos);
            match kind {
                Kind::Space | Kind::LineComment | Kind::BlockComment { terminated: true } => {}
                Kind::Newline => bol = true,
                Kind::Punct => return !(bol && bytes[pos] == b'#') && bytes[pos] == b'(',
                _ => return false,
            }
            pos += len;
        }
    }

    /// Expands the macro invocation whose name was just read from the file, writing the
    /// result, and leaves the frame after the invocation.
    fn expand_top(&mut self, name: Tok, m: u32) -> PResult<()> {
        self.inv = Some((name.ctx, name.src, name.src + name.len));
        let entered = self.enter_macro(name, m)?;
        if !entered {
            // A function-like macro without arguments after all: the name is plain text.
            let frame = self.frames.last().map(|f| (f.ctx, f.source.clone()));
            if let Some((ctx, source)) = frame {
                let (s, e) = (name.src as usize, (name.src + name.len) as usize);
                self.copy_run(ctx, source.text(), s, e, Some(s..e))?;
            }
        } else {
            while let Some(t) = self.get_token(false)? {
                self.emit(t)?;
            }
        }
        self.inv = None;
        Ok(())
    }

    // -----------------------------------------------------------------------------------------
    // Token sources

    /// The next token of the current file, for argument collection: skips whitespace and
    /// comments (setting `WHITE`), runs directives at line starts. `Eof` at the file's end.
    fn lex_file_token(&mut self) -> PResult<Tok> {
        let mut white = false;
        loop {
            let Some(frame) = self.frames.last_mut() else { return Ok(Tok::eof()) };
            let source = frame.source.clone();
            let bytes = source.text().as_bytes();
            let pos = frame.pos;
            let (kind, len) = lexer::next(bytes, pos);
            match kind {
                Kind::Eof => return Ok(Tok::eof()),
                Kind::Newline => {
                    frame.pos += 1;
                    frame.bol = true;
                    white = true;
                }
                Kind::Space | Kind::LineComment | Kind::BlockComment { terminated: true } => {
                    frame.pos += len;
                    white = true;
                }
                Kind::BlockComment { terminated: false } => {
                    let ctx = frame.ctx;
                    return self.err_at(ctx, pos as u32..pos as u32 + 2, "unterminated comment", "this comment is never closed");
                }
                Kind::Punct if frame.bol && (bytes[pos] == b'#' || &bytes[pos..pos + len] == b"%:") => {
                    frame.pos += len;
                    frame.bol = false;
                    self.directive_in_args(pos)?;
                    white = true;
                }
                _ => {
                    frame.bol = false;
                    if matches!(frame.guard, GuardState::Start | GuardState::Closed(_)) {
                        frame.guard = GuardState::No;
                    }
                    frame.pos += len;
                    let ctx = frame.ctx;
                    if kind == (Kind::Str { terminated: false }) {
                        return self.err_at(ctx, pos as u32..pos as u32 + 1, "missing terminating \" character", "this string is never closed");
                    }
                    let sym = self.it.intern(&source.text()[pos..pos + len]);
                    if let Some((c, _, e)) = self.inv.as_mut() {
                        if *c == ctx {
                            *e = (*e).max((pos + len) as u32);
                        }
                    }
                    let flags = if white { WHITE } else { 0 };
                    return Ok(Tok { sym, ctx, src: pos as u32, len: len as u32, param: NO_PARAM, kind: tk_of(kind), flags });
                }
            }
        }
    }

    /// The next token from the contexts (popping finished ones and re-enabling their
    /// macros), else from the file when `file_ok`. `None`: no context and not `file_ok`.
    fn next_raw(&mut self, file_ok: bool) -> PResult<Option<Tok>> {
        loop {
            if let Some(c) = self.stack.last_mut() {
                if let Some(&t) = c.toks.get(c.pos) {
                    c.pos += 1;
                    return Ok(Some(t));
                }
                if c.barrier {
                    return Ok(Some(Tok::eof()));
                }
                let mac = c.mac;
                if let Some(c) = self.stack.pop() {
                    self.give_vec(c.toks);
                }
                if let Some(m) = self.defs.get_mut(mac as usize) {
                    m.disabled = false;
                }
                if self.directive_line.is_none() {
                    // cpp's `avoid_paste` padding at the end of every expansion.
                    return Ok(Some(Tok { kind: TK::Padding, flags: NULL_SOURCE, ..Tok::eof() }));
                }
                continue;
            }
            if !file_ok {
                return Ok(None);
            }
            return self.lex_file_token().map(Some);
        }
    }

    /// Is the next token (without consuming anything) a `(`?
    fn peek_lparen(&self) -> bool {
        for c in self.stack.iter().rev() {
            let rest = c.toks.get(c.pos..).unwrap_or(&[]);
            if let Some(t) = rest.iter().find(|t| !matches!(t.kind, TK::Padding | TK::Placemarker)) {
                return t.kind == TK::Punct && t.sym == self.syms.lparen;
            }
            if c.barrier {
                return false;
            }
        }
        match self.frames.last() {
            Some(f) => self.peek_file_lparen(f.source.text().as_bytes(), f.pos),
            None => false,
        }
    }

    /// The next fully macro-expanded token (`None` when the contexts run out and not
    /// `file_ok`; `Eof` at a barrier or the file's end).
    fn get_token(&mut self, file_ok: bool) -> PResult<Option<Tok>> {
        loop {
            let Some(mut t) = self.next_raw(file_ok)? else { return Ok(None) };
            if t.kind != TK::Ident || t.flags & NO_EXPAND != 0 {
                return Ok(Some(t));
            }
            let m = self.macro_idx(t.sym);
            if m == NONE {
                return Ok(Some(t));
            }
            if self.defs[m as usize].disabled {
                t.flags |= NO_EXPAND;
                return Ok(Some(t));
            }
            if !self.enter_macro(t, m)? {
                return Ok(Some(t));
            }
            if self.directive_line.is_none() {
                // cpp's padding whose source is the macro name.
                return Ok(Some(Tok { kind: TK::Padding, flags: t.flags & WHITE, param: NO_PARAM, ..t }));
            }
        }
    }

    /// The next expanded token that is not a placemarker (`Eof` where `get_token` gives none).
    fn get_real_token(&mut self, file_ok: bool) -> PResult<Tok> {
        loop {
            match self.get_token(file_ok)? {
                Some(t) if matches!(t.kind, TK::Placemarker | TK::Padding) => continue,
                Some(t) => return Ok(t),
                None => return Ok(Tok::eof()),
            }
        }
    }

    // -----------------------------------------------------------------------------------------
    // Macro expansion

    /// An empty token vector, reusing the storage of finished contexts.
    fn take_vec(&mut self) -> Vec<Tok> {
        self.pool.pop().unwrap_or_default()
    }

    fn give_vec(&mut self, mut v: Vec<Tok>) {
        if self.pool.len() < 64 && v.capacity() <= 4096 {
            v.clear();
            self.pool.push(v);
        }
    }

    fn push_context(&mut self, toks: Vec<Tok>, mac: u32, barrier: bool, at: &Tok) -> PResult<()> {
        if self.stack.len() >= self.opts.max_expansion_depth {
            return self.err_tok(
                at,
                format!("macro expansion nested deeper than {} levels", self.opts.max_expansion_depth),
                "while expanding this",
            );
        }
        if toks.len() > self.budget {
            return self.err_tok(
                at,
                format!("macro expansion makes more than {} tokens", self.opts.max_output_bytes.max(1024)),
                "while expanding this",
            );
        }
        self.budget -= toks.len();
        if let Some(m) = self.defs.get_mut(mac as usize) {
            m.disabled = true;
        }
        self.stack.push(Context { toks, pos: 0, mac, barrier });
        Ok(())
    }

    /// Starts expanding macro `m` named by `name`. False if it is function-like and no `(`
    /// follows (nothing consumed).
    fn enter_macro(&mut self, name: Tok, m: u32) -> PResult<bool> {
        let mac = &self.defs[m as usize];
        if mac.builtin != Builtin::None {
            return self.builtin(name, mac.builtin);
        }
        if !mac.func {
            let body = mac.body.clone();
            let toks = if mac.pastes {
                self.substitute(m, &name, &body, &[], &mut [])?
            } else {
                let mut toks = self.take_vec();
                toks.extend_from_slice(&body);
                toks
            };
            self.push_context(toks, m, false, &name)?;
            return Ok(true);
        }
        if !self.peek_lparen() {
            return Ok(false);
        }
        // Up to the `(` the peek saw, past paddings and finished contexts.
        while let Some(t) = self.next_raw(true)? {
            if !matches!(t.kind, TK::Padding | TK::Placemarker) {
                break;
            }
        }
        let args = self.collect_args(&name, m)?;
        let mac = &self.defs[m as usize];
        let nparams = mac.params.len();
        let variadic = mac.variadic;
        let name_str = self.it.str(name.sym).to_string();
        let mut args = args;
        if args.len() < nparams {
            if variadic && args.len() + 1 == nparams {
                // The variable arguments are absent (not merely empty).
            } else if !(nparams == 1 && args.is_empty()) {
                let labels = self.invocation_labels(&name, "this invocation");
                return Err(Error::new(format!("macro \"{name_str}\" requires {nparams} arguments, but only {} given", args.len()), labels));
            }
        } else if args.len() > nparams && !(nparams == 0 && args.len() == 1 && args[0].is_empty()) {
            let labels = self.invocation_labels(&name, "this invocation");
            return Err(Error::new(format!("macro \"{name_str}\" passed {} arguments, but takes just {nparams}", args.len()), labels));
        }
        if nparams == 0 {
            args.clear();
        }
        let absent_va = variadic && args.len() < nparams;
        let mut body = self.defs[m as usize].body.clone();
        let mut expanded: Vec<Option<Vec<Tok>>> = vec![None; args.len()];
        if self.defs[m as usize].va_opt {
            body = self.resolve_va_opt(&body, nparams - 1, &args, &mut expanded, &name)?.into();
        }
        let mut toks = self.substitute_args(m, &name, &body, &args, &mut expanded, absent_va)?;
        if toks.iter().all(|t| t.kind == TK::Placemarker) {
            toks.clear();
        }
        self.push_context(toks, m, false, &name)?;
        Ok(true)
    }

    /// Collects the arguments after the `(` (already read), unexpanded, up to the matching `)`.
    fn collect_args(&mut self, name: &Tok, m: u32) -> PResult<Vec<Vec<Tok>>> {
        let nparams = self.defs[m as usize].params.len();
        let variadic = self.defs[m as usize].variadic;
        let mut args: Vec<Vec<Tok>> = vec![Vec::new()];
        let mut depth = 0usize;
        loop {
            let Some(mut t) = self.next_raw(true)? else { return self.unterminated(name) };
            match t.kind {
                TK::Eof => return self.unterminated(name),
                TK::Punct if t.sym == self.syms.lparen => depth += 1,
                TK::Punct if t.sym == self.syms.rparen => {
                    if depth == 0 {
                        break;
                    }
                    depth -= 1;
                }
                TK::Punct if t.sym == self.syms.comma && depth == 0 && !(variadic && args.len() >= nparams) => {
                    args.push(Vec::new());
                    continue;
                }
                TK::Ident => {
                    let mi = self.macro_idx(t.sym);
                    if mi != NONE && self.defs[mi as usize].disabled {
                        t.flags |= NO_EXPAND;
                    }
                }
                _ => {}
            }
            if let Some(a) = args.last_mut() {
                a.push(t);
            }
            if args.iter().map(Vec::len).sum::<usize>() > self.budget {
                return self.err_tok(name, "macro arguments exceed the expansion budget", "while collecting these arguments");
            }
        }
        // Like cpp's padding, placemarkers at either end of an argument do not count.
        for a in &mut args {
            while a.last().is_some_and(|t| matches!(t.kind, TK::Placemarker | TK::Padding)) {
                a.pop();
            }
            let lead = a.iter().take_while(|t| matches!(t.kind, TK::Placemarker | TK::Padding)).count();
            if lead > 0 {
                a.drain(..lead);
            }
        }
        if args.len() == 1 && args[0].is_empty() && nparams == 0 {
            return Ok(Vec::new());
        }
        Ok(args)
    }

    fn unterminated<T>(&self, name: &Tok) -> PResult<T> {
        let n = self.it.str(name.sym).to_string();
        self.err_tok(name, format!("unterminated argument list invoking macro \"{n}\""), "this invocation is never closed")
    }

    /// Fully macro-expands an argument in isolation.
    fn expand_arg(&mut self, arg: &[Tok], at: &Tok) -> PResult<Vec<Tok>> {
        // Nothing to expand: no identifiers (the common case of numbers and punctuation).
        if !arg.iter().any(|t| t.kind == TK::Ident && t.flags & NO_EXPAND == 0 && self.macro_idx(t.sym) != NONE) {
            if arg.len() > self.budget {
                return self.err_tok(at, format!("macro expansion makes more than {} tokens", self.opts.max_output_bytes.max(1024)), "while expanding this");
            }
            self.budget -= arg.len();
            return Ok(arg.to_vec());
        }
        let mut v = self.take_vec();
        v.extend_from_slice(arg);
        self.push_context(v, NONE, true, at)?;
        let mut out = Vec::with_capacity(arg.len());
        loop {
            match self.get_token(false)? {
                Some(t) if t.kind == TK::Eof => break,
                Some(t) => out.push(t),
                None => break,
            }
        }
        if let Some(c) = self.stack.pop() {
            self.give_vec(c.toks);
        }
        Ok(out)
    }

    /// Object-like replacement: pastes only.
    fn substitute(&mut self, m: u32, name: &Tok, body: &[Tok], args: &[Vec<Tok>], expanded: &mut [Option<Vec<Tok>>]) -> PResult<Vec<Tok>> {
        let mut toks = self.substitute_args(m, name, body, args, expanded, false)?;
        if toks.iter().all(|t| t.kind == TK::Placemarker) {
            toks.clear();
        }
        Ok(toks)
    }

    /// Builds a replacement list: parameters replaced (stringified, raw next to `##`, else
    /// expanded), then `##` applied left to right.
    fn substitute_args(
        &mut self,
        _m: u32,
        name: &Tok,
        body: &[Tok],
        args: &[Vec<Tok>],
        expanded: &mut [Option<Vec<Tok>>],
        absent_va: bool,
    ) -> PResult<Vec<Tok>> {
        let mut out: Vec<Tok> = self.take_vec();
        out.reserve(body.len() + args.iter().map(Vec::len).sum::<usize>());
        let mut i = 0;
        while i < body.len() {
            let b = body[i];
            let prev_pastes = i > 0 && body[i - 1].flags & PASTE_LEFT != 0;
            if b.flags & VA_COMMA != 0 {
                // GNU `, ## __VA_ARGS__`: absent variable arguments drop the comma; empty ones
                // leave it (pasted with a placemarker); otherwise the comma stays unpasted and
                // the arguments go in unexpanded, as `##` operands do.
                let p = body[i + 1];
                let arg = args.get(p.param as usize).cloned().unwrap_or_default();
                let va_paste = p.flags & PASTE_LEFT;
                if absent_va && va_paste == 0 {
                    // Dropped with its comma.
                } else if arg.is_empty() {
                    out.push(Tok { flags: (b.flags & !(PASTE_LEFT | VA_COMMA)) | va_paste, ..b });
                } else {
                    out.push(Tok { flags: b.flags & !(PASTE_LEFT | VA_COMMA), ..b });
                    out.extend(arg);
                    if let Some(t) = out.last_mut() {
                        t.flags |= va_paste;
                    }
                    if va_paste == 0 && self.directive_line.is_none() {
                        out.push(Tok { kind: TK::Padding, flags: NULL_SOURCE, ..Tok::eof() });
                    }
                }
                i += 2;
                continue;
            }
            if b.param == NO_PARAM {
                out.push(b);
                i += 1;
                continue;
            }
            let pi = b.param as usize;
            if b.flags & STRINGIFY != 0 {
                let s = self.stringify(args.get(pi).map_or(&[][..], |a| &a[..]));
                let sym = self.it.intern(&s);
                out.push(Tok { sym, kind: TK::Str, param: NO_PARAM, flags: (b.flags & (WHITE | PASTE_LEFT)) | FROM_DEF, ..b });
                i += 1;
                continue;
            }
            let raw = b.flags & PASTE_LEFT != 0 || prev_pastes;
            if !raw {
                self.expanded_arg(pi, args, expanded, name)?;
            }
            let toks: &[Tok] = if raw {
                args.get(pi).map_or(&[][..], |a| &a[..])
            } else {
                expanded.get(pi).and_then(|e| e.as_deref()).unwrap_or(&[])
            };
            // cpp's paddings around an argument: on the left (its source the parameter) unless
            // it is the first token or the right operand of `##`, on the right unless `##`
            // follows.
            let pad = self.directive_line.is_none();
            if pad && i > 0 && !prev_pastes {
                out.push(Tok { kind: TK::Padding, flags: b.flags & WHITE, param: NO_PARAM, ..b });
            }
            if toks.is_empty() {
                if raw {
                    out.push(Tok { kind: TK::Placemarker, param: NO_PARAM, flags: b.flags & (PASTE_LEFT | WHITE), ..b });
                }
            } else {
                out.extend_from_slice(toks);
                if b.flags & PASTE_LEFT != 0 {
                    if let Some(t) = out.last_mut() {
                        t.flags |= PASTE_LEFT;
                    }
                }
            }
            if pad && b.flags & PASTE_LEFT == 0 {
                out.push(Tok { kind: TK::Padding, flags: NULL_SOURCE, ..Tok::eof() });
            }
            i += 1;
        }
        if out.iter().any(|t| t.flags & PASTE_LEFT != 0) {
            out = self.paste_all(out, name)?;
        }
        if out.iter().any(|t| t.kind == TK::Placemarker) && out.len() > 1 {
            let white = out.first().map_or(0, |t| t.flags & WHITE);
            out.retain(|t| t.kind != TK::Placemarker);
            if let Some(t) = out.first_mut() {
                t.flags |= white;
            }
        }
        Ok(out)
    }

    /// Replaces each `__VA_OPT__(...)` of a body by its contents when the variable arguments
    /// expand to some tokens, else by a placemarker (C2x, as GCC 12 does in every mode).
    fn resolve_va_opt(&mut self, body: &[Tok], va: usize, args: &[Vec<Tok>], expanded: &mut [Option<Vec<Tok>>], name: &Tok) -> PResult<Vec<Tok>> {
        self.expanded_arg(va, args, expanded, name)?;
        let present = expanded.get(va).and_then(|e| e.as_ref()).is_some_and(|e| e.iter().any(|t| !matches!(t.kind, TK::Placemarker | TK::Padding)));
        let mut out = Vec::with_capacity(body.len());
        let mut i = 0;
        while i < body.len() {
            let t = body[i];
            let opens = body.get(i + 1).is_some_and(|n| n.kind == TK::Punct && n.sym == self.syms.lparen);
            if !(t.kind == TK::Ident && t.sym == self.syms.va_opt && t.param == NO_PARAM && opens) {
                out.push(t);
                i += 1;
                continue;
            }
            // Find the matching `)`.
            let mut depth = 0usize;
            let mut j = i + 1;
            while j < body.len() {
                if body[j].kind == TK::Punct && body[j].sym == self.syms.lparen {
                    depth += 1;
                } else if body[j].kind == TK::Punct && body[j].sym == self.syms.rparen {
                    depth -= 1;
                    if depth == 0 {
                        break;
                    }
                }
                j += 1;
            }
            if j >= body.len() {
                return self.err_tok(&t, "unterminated __VA_OPT__", "this __VA_OPT__ is never closed");
            }
            let close_paste = body[j].flags & PASTE_LEFT;
            let inner = &body[i + 2..j];
            if t.flags & STRINGIFY != 0 {
                let toks = if present { self.substitute_args(NONE, name, inner, args, expanded, false)? } else { Vec::new() };
                let text = self.stringify(&toks);
                let sym = self.it.intern(&text);
                out.push(Tok { sym, kind: TK::Str, param: NO_PARAM, flags: (t.flags & WHITE) | close_paste | FROM_DEF, ..t });
            } else if present && !inner.is_empty() {
                let start = out.len();
                out.extend_from_slice(inner);
                out[start].flags = (out[start].flags & !WHITE) | (t.flags & WHITE);
                if let Some(last) = out.last_mut() {
                    last.flags |= close_paste;
                }
            } else {
                out.push(Tok { kind: TK::Placemarker, param: NO_PARAM, flags: (t.flags & WHITE) | close_paste, ..t });
            }
            i = j + 1;
        }
        Ok(out)
    }

    /// Makes sure `expanded[pi]` holds the macro-expanded argument `pi`.
    fn expanded_arg(&mut self, pi: usize, args: &[Vec<Tok>], expanded: &mut [Option<Vec<Tok>>], name: &Tok) -> PResult<()> {
        if matches!(expanded.get(pi), Some(Some(_)) | None) {
            return Ok(());
        }
        let raw = args.get(pi).map_or(&[][..], |a| &a[..]);
        let e = self.expand_arg(raw, name)?;
        if let Some(slot) = expanded.get_mut(pi) {
            *slot = Some(e);
        }
        Ok(())
    }

    /// Applies every `##` (tokens flagged `PASTE_LEFT` join the next one).
    fn paste_all(&mut self, toks: Vec<Tok>, name: &Tok) -> PResult<Vec<Tok>> {
        let mut out: Vec<Tok> = Vec::with_capacity(toks.len());
        let mut iter = toks.into_iter();
        while let Some(mut lhs) = iter.next() {
            while lhs.flags & PASTE_LEFT != 0 {
                let Some(rhs) = iter.next() else {
                    lhs.flags &= !PASTE_LEFT;
                    break;
                };
                lhs = self.paste(lhs, rhs, name)?;
            }
            out.push(lhs);
        }
        Ok(out)
    }

    fn paste(&mut self, lhs: Tok, rhs: Tok, name: &Tok) -> PResult<Tok> {
        let keep = (lhs.flags & WHITE) | (rhs.flags & PASTE_LEFT);
        if rhs.kind == TK::Placemarker {
            return Ok(Tok { flags: (lhs.flags & !PASTE_LEFT) | keep, ..lhs });
        }
        if lhs.kind == TK::Placemarker {
            return Ok(Tok { flags: (rhs.flags & !(PASTE_LEFT | WHITE)) | keep, ..rhs });
        }
        let joined = format!("{}{}", self.it.str(lhs.sym), self.it.str(rhs.sym));
        let (kind, len) = lexer::next(joined.as_bytes(), 0);
        let valid = len == joined.len()
            && !matches!(kind, Kind::Space | Kind::Newline | Kind::LineComment | Kind::BlockComment { .. } | Kind::Eof)
            && !matches!(kind, Kind::Str { terminated: false } | Kind::Char { terminated: false });
        if !valid {
            let msg = format!(
                "pasting \"{}\" and \"{}\" does not give a valid preprocessing token",
                self.it.str(lhs.sym),
                self.it.str(rhs.sym)
            );
            return self.err_tok(&lhs, msg, "in this expansion");
        }
        let sym = self.it.intern(&joined);
        let mut flags = keep | FROM_DEF;
        if lhs.flags & FROM_DEF == 0 && rhs.flags & FROM_DEF == 0 && lhs.ctx == rhs.ctx && lhs.src + lhs.len == rhs.src {
            flags &= !FROM_DEF;
        }
        let _ = name;
        Ok(Tok { sym, kind: tk_of(kind), flags, len: if flags & FROM_DEF == 0 { joined.len() as u32 } else { lhs.len }, param: NO_PARAM, ..lhs })
    }

    /// `#x`: the spelling of the argument, spaces normalized, `"` and `\` escaped in literals.
    fn stringify(&self, arg: &[Tok]) -> String {
        let mut s = String::from("\"");
        // cpp's rule: the whitespace before a token is that of the source of the padding
        // before it, if any (a padding with no source resets it), else its own.
        // `source`: None is cpp's NULL, Some(w) a source token with leading whitespace `w`.
        let mut source: Option<bool> = None;
        for t in arg {
            if t.kind == TK::Padding {
                let tsrc = if t.flags & NULL_SOURCE != 0 { None } else { Some(t.flags & WHITE != 0) };
                if source.is_none() || (source == Some(false) && tsrc.is_none()) {
                    source = tsrc;
                }
                continue;
            }
            if t.kind == TK::Placemarker {
                continue;
            }
            if s.len() > 1 {
                let white = source.unwrap_or(t.flags & WHITE != 0);
                if white {
                    s.push(' ');
                }
            }
            source = None;
            let text = self.it.str(t.sym);
            if matches!(t.kind, TK::Str | TK::Char) {
                for c in text.chars() {
                    if c == '"' || c == '\\' {
                        s.push('\\');
                    }
                    s.push(c);
                }
            } else {
                s.push_str(text);
            }
        }
        s.push('"');
        s
    }

    fn current_line(&self, t: &Tok) -> i64 {
        if let Some(l) = self.directive_line {
            return l;
        }
        // Text of the file (an argument, say) has its own line; macro-made text the line of
        // the outermost invocation.
        let (ctx, src) = match self.inv {
            Some((c, s, _)) if t.flags & FROM_DEF != 0 || t.ctx == NONE => (c, s),
            _ => (t.ctx, t.src),
        };
        let delta = self.frames.last().map_or(0, |f| f.line_delta);
        match self.map.ctxs.get(ctx as usize) {
            Some(c) => c.source.line_col(c.source.original_offset(src as usize)).0 as i64 + delta,
            None => 0,
        }
    }

    fn builtin(&mut self, name: Tok, b: Builtin) -> PResult<bool> {
        let text = match b {
            Builtin::Line => self.current_line(&name).to_string(),
            Builtin::File => quote(&self.frames.last().map_or(String::new(), |f| f.name.clone())),
            Builtin::BaseFile => quote(&self.base_name),
            Builtin::Counter => {
                self.counter += 1;
                (self.counter - 1).to_string()
            }
            Builtin::IncludeLevel => (self.frames.len().saturating_sub(1)).to_string(),
            Builtin::Pragma => return self.pragma_operator(name),
            // Left for the `#if` evaluation to read.
            Builtin::HasInclude if self.directive_line.is_some() => return Ok(false),
            Builtin::HasInclude => {
                let n = self.it.str(name.sym).to_string();
                return self.err_tok(&name, format!("\"{n}\" used outside of preprocessing directive"), "only in #if and #elif");
            }
            Builtin::Date | Builtin::Time => {
                let (date, time) = date_time();
                quote(if b == Builtin::Date { &date } else { &time })
            }
            Builtin::None => return Ok(false),
        };
        let kind = if matches!(b, Builtin::File | Builtin::BaseFile | Builtin::Date | Builtin::Time) { TK::Str } else { TK::Number };
        let sym = self.it.intern(&text);
        let t = Tok { sym, kind, flags: (name.flags & WHITE) | FROM_DEF, param: NO_PARAM, ..name };
        self.push_context(vec![t], NONE, false, &name)?;
        Ok(true)
    }

    /// `_Pragma("...")`: written out as a `#pragma` line, like cpp does.
    fn pragma_operator(&mut self, name: Tok) -> PResult<bool> {
        if !self.peek_lparen() {
            return Ok(false);
        }
        while let Some(t) = self.next_raw(true)? {
            if !matches!(t.kind, TK::Padding | TK::Placemarker) {
                break;
            }
        }
        let s = self.get_real_token(true)?;
        let close = self.get_real_token(true)?;
        if s.kind != TK::Str || !(close.kind == TK::Punct && close.sym == self.syms.rparen) {
            return self.err_tok(&name, "_Pragma takes a parenthesized string literal", "here");
        }
        let lit = self.it.str(s.sym).to_string();
        let start = lit.find('"').map_or(0, |i| i + 1);
        let body = lit.get(start..lit.len().saturating_sub(1)).unwrap_or("");
        let body = body.replace("\\\"", "\"").replace("\\\\", "\\");
        if body.trim() == "once" {
            if let Some(f) = self.frames.last() {
                let id = f.file;
                self.once.insert(id);
            }
            return self.push_context(vec![Tok { kind: TK::Placemarker, ..name }], NONE, false, &name).map(|_| true);
        }
        let line = format!("\n#pragma {body}\n");
        let sym = self.it.intern(&line);
        let t = Tok { sym, kind: TK::Other, flags: FROM_DEF, param: NO_PARAM, ..name };
        self.push_context(vec![t], NONE, false, &name)?;
        Ok(true)
    }

    // -----------------------------------------------------------------------------------------
    // Directives

    /// Reads the rest of the directive line as tokens (comments are spaces; a block comment
    /// may carry the line on). Leaves the frame at the start of the next line.
    fn directive_tokens(&mut self) -> PResult<(Vec<Tok>, u32)> {
        let Some(frame) = self.frames.last_mut() else { return Ok((Vec::new(), 0)) };
        let source = frame.source.clone();
        let ctx = frame.ctx;
        let bytes = source.text().as_bytes();
        let mut pos = frame.pos;
        let mut white = false;
        let mut toks = Vec::new();
        let end;
        loop {
            let (kind, len) = lexer::next(bytes, pos);
            match kind {
                Kind::Eof => {
                    end = pos;
                    break;
                }
                Kind::Newline => {
                    end = pos;
                    pos += 1;
                    break;
                }
                Kind::Space | Kind::LineComment | Kind::BlockComment { terminated: true } => white = true,
                Kind::BlockComment { terminated: false } => {
                    return self.err_at(ctx, pos as u32..pos as u32 + 2, "unterminated comment", "this comment is never closed");
                }
                _ => {
                    let sym = self.it.intern(&source.text()[pos..pos + len]);
                    let flags = if white { WHITE } else { 0 };
                    toks.push(Tok { sym, ctx, src: pos as u32, len: len as u32, param: NO_PARAM, kind: tk_of(kind), flags });
                    white = false;
                }
            }
            pos += len;
        }
        if let Some(f) = self.frames.last_mut() {
            f.pos = pos;
            f.bol = true;
        }
        Ok((toks, end as u32))
    }

    /// A directive met while collecting macro arguments: allowed except `#include`.
    fn directive_in_args(&mut self, hash: usize) -> PResult<()> {
        let saved = self.inv;
        let r = self.directive(hash);
        self.inv = saved;
        r
    }

    /// Runs the directive whose `#` is at `hash` (the frame is just after the `#`).
    fn directive(&mut self, hash: usize) -> PResult<()> {
        let Some(frame) = self.frames.last() else { return Ok(()) };
        let ctx = frame.ctx;
        let source = frame.source.clone();
        let text = source.text();
        let bytes = text.as_bytes();
        // The directive name, read in place (include needs the raw text after it).
        let mut p = frame.pos;
        loop {
            let (kind, len) = lexer::next(bytes, p);
            match kind {
                Kind::Space | Kind::BlockComment { terminated: true } => p += len,
                _ => break,
            }
        }
        let (kind, len) = lexer::next(bytes, p);
        let name = if kind == Kind::Ident { &text[p..p + len] } else { "" };
        let name_range = p as u32..(p + len) as u32;
        let hash_range = hash as u32..(hash + 1) as u32;
        let in_args = !self.stack.is_empty() || self.inv.is_some();
        let first_directive = frame.guard == GuardState::Start;
        if let Some(f) = self.frames.last_mut() {
            if kind == Kind::Ident {
                f.pos = p + len;
            }
            let closed = matches!(f.guard, GuardState::Closed(_));
            if closed || (first_directive && name != "ifndef") {
                f.guard = GuardState::No;
            }
            if matches!(name, "else" | "elif") && f.conds.len() == 1 && matches!(f.guard, GuardState::Inside(_)) {
                f.guard = GuardState::No;
            }
        }
        match name {
            "define" => {
                let (toks, _) = self.directive_tokens()?;
                if toks.is_empty() {
                    return self.err_at(ctx, name_range, "no macro name given in #define directive", "expected a macro name");
                }
                self.parse_define(toks, false)
            }
            "undef" => {
                let (toks, _) = self.directive_tokens()?;
                let sym = self.directive_name(&toks, "undef", ctx, name_range)?;
                if toks.len() > 1 {
                    let l = self.tok_labels(&toks[1], "unexpected");
                    self.warn("extra tokens at end of #undef directive", l);
                }
                if (sym as usize) < self.macro_of.len() {
                    self.macro_of[sym as usize] = NONE;
                }
                Ok(())
            }
            "include" | "include_next" | "import" => {
                if in_args {
                    return self.err_at(ctx, name_range, "#include inside macro arguments is not supported", "inside this invocation's arguments");
                }
                self.include(hash_range.start, p + len)
            }
            "if" | "ifdef" | "ifndef" => {
                let (toks, _) = self.directive_tokens()?;
                let taken = match name {
                    "if" => self.eval_if(toks, ctx, name_range.clone())?,
                    _ => {
                        let sym = self.directive_name(&toks, name, ctx, name_range.clone())?;
                        if toks.len() > 1 {
                            let l = self.tok_labels(&toks[1], "unexpected");
                            self.warn(format!("extra tokens at end of #{name} directive"), l);
                        }
                        let defined = self.macro_idx(sym) != NONE;
                        if name == "ifndef" && first_directive {
                            if let Some(f) = self.frames.last_mut() {
                                f.guard = if f.conds.is_empty() && toks.len() == 1 { GuardState::Inside(sym) } else { GuardState::No };
                            }
                        }
                        if name == "ifdef" { defined } else { !defined }
                    }
                };
                let nm: &'static str = match name {
                    "if" => "if",
                    "ifdef" => "ifdef",
                    _ => "ifndef",
                };
                if let Some(f) = self.frames.last_mut() {
                    f.conds.push(Cond { site: hash_range.start..name_range.end, name: nm, taken, else_seen: false });
                }
                if !taken {
                    self.skip_group()?;
                }
                Ok(())
            }
            "elif" | "else" => {
                let (toks, _) = self.directive_tokens()?;
                let Some(f) = self.frames.last_mut() else { return Ok(()) };
                let Some(c) = f.conds.last_mut() else {
                    return self.err_at(ctx, hash_range.start..name_range.end, format!("#{name} without #if"), "no open conditional");
                };
                if c.else_seen {
                    return self.err_at(ctx, hash_range.start..name_range.end, format!("#{name} after #else"), "after the #else of this conditional");
                }
                if name == "else" {
                    c.else_seen = true;
                    if !toks.is_empty() {
                        let l = self.tok_labels(&toks[0], "unexpected");
                        self.warn("extra tokens at end of #else directive", l);
                    }
                }
                // We were in a taken group: everything up to #endif is skipped.
                self.skip_group()
            }
            "endif" => {
                let (toks, _) = self.directive_tokens()?;
                let Some(f) = self.frames.last_mut() else { return Ok(()) };
                if f.conds.pop().is_none() {
                    return self.err_at(ctx, hash_range.start..name_range.end, "#endif without #if", "no open conditional");
                }
                if f.conds.is_empty() {
                    if let GuardState::Inside(sym) = f.guard {
                        f.guard = GuardState::Closed(sym);
                    }
                }
                if !toks.is_empty() {
                    let l = self.tok_labels(&toks[0], "unexpected");
                    self.warn("extra tokens at end of #endif directive", l);
                }
                Ok(())
            }
            "error" | "warning" => {
                let start = p + len;
                let (_, end) = self.directive_tokens()?;
                let msg = text.get(start..end as usize).unwrap_or("").trim();
                let msg = collapse_comments(msg);
                let message = if msg.is_empty() { format!("#{name}") } else { format!("#{name} {msg}") };
                let labels = self.labels_at(ctx, hash_range.start..end, "");
                if name == "error" {
                    return Err(Error::new(message, labels));
                }
                self.warn(message, labels);
                Ok(())
            }
            "pragma" => self.pragma(p + len, ctx),
            "line" => {
                let (toks, _) = self.directive_tokens()?;
                self.line_directive(toks, ctx, name_range)
            }
            "ident" | "sccs" => {
                let start = p + len;
                let (_, end) = self.directive_tokens()?;
                let rest = collapse_comments(text.get(start..end as usize).unwrap_or("").trim());
                self.emit_line(ctx, hash, &format!("#ident {rest}"))
            }
            "assert" | "unassert" => {
                self.directive_tokens()?;
                Ok(())
            }
            "" => {
                let (toks, _) = self.directive_tokens()?;
                match toks.first() {
                    None => Ok(()),
                    // GNU line marker: `# 33 "file"`.
                    Some(t) if t.kind == TK::Number => self.line_directive(toks, ctx, name_range),
                    Some(t) => {
                        let s = self.it.str(t.sym).to_string();
                        self.err_tok(t, format!("invalid preprocessing directive #{s}"), "not a directive")
                    }
                }
            }
            other => {
                let other = other.to_string();
                self.err_at(ctx, name_range, format!("invalid preprocessing directive #{other}"), "unknown directive")
            }
        }
    }

    /// The macro name of `#undef`/`#ifdef`/`#ifndef`.
    fn directive_name(&self, toks: &[Tok], dir: &str, ctx: u32, at: Range<u32>) -> PResult<Sym> {
        match toks.first() {
            None => self.err_at(ctx, at, format!("no macro name given in #{dir} directive"), "expected a macro name"),
            Some(t) if t.kind == TK::Ident => {
                if t.sym == self.syms.defined && dir == "undef" {
                    return self.err_tok(t, "\"defined\" cannot be used as a macro name", "here");
                }
                Ok(t.sym)
            }
            Some(t) => self.err_tok(t, "macro names must be identifiers", "not an identifier"),
        }
    }

    /// Writes a line of its own (`#pragma`, `#ident` pass-through).
    fn emit_line(&mut self, ctx: u32, at: usize, line: &str) -> PResult<()> {
        if !self.out.is_empty() && !self.out.ends_with('\n') {
            self.out.push('\n');
        }
        let out_at = self.out.len() as u32;
        self.map.entries.push(Entry { out: out_at, ctx, src: at as u32, end: at as u32 + 1, def_ctx: NONE, def_src: 0, def_len: 0, is_macro: true });
        self.out.push_str(line);
        self.out.push('\n');
        self.last_tok = 0..0;
        self.check_output()
    }

    fn pragma(&mut self, start: usize, ctx: u32) -> PResult<()> {
        let (toks, end) = self.directive_tokens()?;
        let Some(frame) = self.frames.last() else { return Ok(()) };
        let source = frame.source.clone();
        let file = frame.file;
        let first = toks.first().map(|t| self.it.str(t.sym).to_string()).unwrap_or_default();
        match first.as_str() {
            "once" => {
                self.once.insert(file);
                Ok(())
            }
            "push_macro" | "pop_macro" => {
                // push_macro("NAME")
                let name = toks.get(2).filter(|t| t.kind == TK::Str).map(|t| {
                    let s = self.it.str(t.sym);
                    s.trim_matches('"').to_string()
                });
                if let Some(name) = name {
                    let sym = self.it.intern(&name);
                    if first == "push_macro" {
                        let m = self.macro_idx(sym);
                        self.pushed.entry(sym).or_default().push(m);
                    } else if let Some(m) = self.pushed.get_mut(&sym).and_then(|v| v.pop()) {
                        if self.macro_of.len() <= sym as usize {
                            self.macro_of.resize(sym as usize + 1, NONE);
                        }
                        self.macro_of[sym as usize] = m;
                    }
                }
                Ok(())
            }
            "GCC" => {
                let second = toks.get(1).map(|t| self.it.str(t.sym).to_string()).unwrap_or_default();
                match second.as_str() {
                    "error" | "warning" => {
                        let msg = toks.get(2).map(|t| self.it.str(t.sym).to_string()).unwrap_or_default();
                        let labels = self.labels_at(ctx, start as u32..end, "");
                        if second == "error" {
                            return Err(Error::new(msg.trim_matches('"').to_string(), labels));
                        }
                        self.warn(msg.trim_matches('"').to_string(), labels);
                        Ok(())
                    }
                    "system_header" | "poison" | "dependency" | "push_options" | "pop_options" | "diagnostic" => Ok(()),
                    _ => {
                        let rest = collapse_comments(source.text().get(start..end as usize).unwrap_or("").trim());
                        self.emit_line(ctx, start, &format!("#pragma {rest}"))
                    }
                }
            }
            _ => {
                let rest = collapse_comments(source.text().get(start..end as usize).unwrap_or("").trim());
                self.emit_line(ctx, start, &format!("#pragma {rest}"))
            }
        }
    }

    fn line_directive(&mut self, toks: Vec<Tok>, ctx: u32, at: Range<u32>) -> PResult<()> {
        let line_here = match self.frames.last() {
            Some(f) => f.source.line_col(f.source.original_offset(at.start as usize)).0 as i64,
            None => return Ok(()),
        };
        let toks = self.expand_line(toks, Some(line_here))?;
        let Some(n) = toks.first().filter(|t| t.kind == TK::Number) else {
            return self.err_at(ctx, at, "#line directive requires a simple digit sequence", "here");
        };
        let Ok(value) = self.it.str(n.sym).parse::<i64>() else {
            return self.err_tok(n, "line number out of range", "here");
        };
        let name = toks.get(1).filter(|t| t.kind == TK::Str).map(|t| self.it.str(t.sym).to_string());
        if let Some(f) = self.frames.last_mut() {
            // The line after the directive gets `value`.
            f.line_delta = value - (line_here + 1);
            if let Some(n) = name {
                f.name = unquote(&n);
            }
        }
        Ok(())
    }

    /// Macro-expands directive tokens in isolation.
    fn expand_line(&mut self, toks: Vec<Tok>, line: Option<i64>) -> PResult<Vec<Tok>> {
        let Some(first) = toks.first().copied() else { return Ok(Vec::new()) };
        let saved_line = self.directive_line;
        self.directive_line = line;
        let saved_inv = self.inv.take();
        let depth = self.stack.len();
        self.push_context(toks, NONE, true, &first)?;
        let mut out = Vec::new();
        let r = loop {
            match self.get_token(false) {
                Ok(Some(t)) if t.kind == TK::Eof => break Ok(()),
                Ok(Some(t)) if matches!(t.kind, TK::Placemarker | TK::Padding) => {}
                Ok(Some(t)) => out.push(t),
                Ok(None) => break Ok(()),
                Err(e) => break Err(e),
            }
        };
        self.unwind(depth);
        self.directive_line = saved_line;
        self.inv = saved_inv;
        r.map(|_| out)
    }

    /// Pops contexts down to `depth`, re-enabling their macros.
    fn unwind(&mut self, depth: usize) {
        while self.stack.len() > depth {
            if let Some(c) = self.stack.pop() {
                if let Some(m) = self.defs.get_mut(c.mac as usize) {
                    m.disabled = false;
                }
            }
        }
    }

    /// Evaluates an `#if`/`#elif` line.
    fn eval_if(&mut self, toks: Vec<Tok>, ctx: u32, at: Range<u32>) -> PResult<bool> {
        let line = match self.frames.last() {
            Some(f) => f.source.line_col(f.source.original_offset(at.start as usize)).0 as i64 + f.line_delta,
            None => 0,
        };
        let Some(first) = toks.first().copied() else {
            return self.err_at(ctx, at, "#if with no expression", "expected an expression");
        };
        let saved_line = self.directive_line;
        self.directive_line = Some(line);
        let saved_inv = self.inv.take();
        let depth = self.stack.len();
        let r = self.expand_if_tokens(toks, &first);
        self.unwind(depth);
        self.directive_line = saved_line;
        self.inv = saved_inv;
        let expanded = r?;
        let mut etoks = Vec::with_capacity(expanded.len());
        for t in &expanded {
            let s = self.it.str(t.sym);
            let kind = match t.kind {
                TK::Ident => Kind::Ident,
                TK::Number => Kind::Number,
                TK::Str => Kind::Str { terminated: true },
                TK::Char => Kind::Char { terminated: true },
                TK::Punct => Kind::Punct,
                _ => Kind::Other,
            };
            etoks.push(expr::Token::from_lexed(kind, s, &|_| None));
        }
        let result = expr::eval_tokens(&etoks);
        drop(etoks);
        match result {
            Ok(v) => Ok(v.v != 0),
            Err(e) => {
                let label = if e.message.contains("division by zero") { "this divisor is zero" } else { "here" };
                match expanded.get(e.at).or(expanded.last()) {
                    Some(t) => self.err_tok(t, e.message, label),
                    None => self.err_at(ctx, at, e.message, label),
                }
            }
        }
    }

    /// Expands `#if` tokens, replacing `defined X` / `defined(X)` before expansion.
    fn expand_if_tokens(&mut self, toks: Vec<Tok>, first: &Tok) -> PResult<Vec<Tok>> {
        self.push_context(toks, NONE, true, first)?;
        let mut out = Vec::new();
        loop {
            let Some(t) = self.get_token(false)? else { break };
            if t.kind == TK::Eof {
                break;
            }
            if matches!(t.kind, TK::Placemarker | TK::Padding) {
                continue;
            }
            if t.kind == TK::Ident && (t.sym == self.syms.has_include || t.sym == self.syms.has_include_next) && t.flags & NO_EXPAND == 0 {
                let found = self.has_include(&t)?;
                let sym = if found { self.syms.one } else { self.syms.zero };
                out.push(Tok { sym, kind: TK::Number, ..t });
                continue;
            }
            if t.kind == TK::Ident && t.sym == self.syms.defined {
                let Some(mut n) = self.next_raw(false)? else { break };
                let paren = n.kind == TK::Punct && n.sym == self.syms.lparen;
                if paren {
                    n = self.next_raw(false)?.unwrap_or(Tok::eof());
                }
                if n.kind != TK::Ident {
                    return self.err_tok(if n.kind == TK::Eof { &t } else { &n }, "operator \"defined\" requires an identifier", "expected an identifier");
                }
                if paren {
                    let close = self.next_raw(false)?.unwrap_or(Tok::eof());
                    if !(close.kind == TK::Punct && close.sym == self.syms.rparen) {
                        return self.err_tok(&n, "missing ')' after \"defined\"", "expected ')' after this");
                    }
                }
                let is = self.macro_idx(n.sym) != NONE;
                let sym = if is { self.syms.one } else { self.syms.zero };
                out.push(Tok { sym, kind: TK::Number, ..t });
                continue;
            }
            out.push(t);
        }
        Ok(out)
    }

    /// `__has_include ( "file" )` / `( <file> )` in `#if`: whether the include resolves.
    fn has_include(&mut self, at: &Tok) -> PResult<bool> {
        let name = self.it.str(at.sym).to_string();
        let open = self.next_raw(false)?.unwrap_or(Tok::eof());
        if !(open.kind == TK::Punct && open.sym == self.syms.lparen) {
            return self.err_tok(at, format!("missing '(' after \"{name}\""), "expected '(' after this");
        }
        let first = self.get_real_token(false)?;
        let (spelling, angle) = if first.kind == TK::Str {
            let s = self.it.str(first.sym);
            (s.get(1..s.len().saturating_sub(1)).unwrap_or("").to_string(), false)
        } else if first.kind == TK::Punct && self.it.str(first.sym) == "<" {
            let mut s = String::new();
            loop {
                let t = self.get_real_token(false)?;
                if t.kind == TK::Eof {
                    return self.err_tok(at, format!("missing terminating > character in \"{name}\""), "here");
                }
                if t.kind == TK::Punct && self.it.str(t.sym) == ">" {
                    break;
                }
                if !s.is_empty() && t.flags & WHITE != 0 {
                    s.push(' ');
                }
                s.push_str(self.it.str(t.sym));
            }
            (s, true)
        } else {
            return self.err_tok(at, format!("operator \"{name}\" requires a header-name"), "expected \"FILE\" or <FILE> after this");
        };
        let close = self.next_raw(false)?.unwrap_or(Tok::eof());
        if !(close.kind == TK::Punct && close.sym == self.syms.rparen) {
            return self.err_tok(at, format!("missing ')' after \"{name}\" operand"), "expected ')'");
        }
        Ok(matches!(self.resolve_include(&spelling, angle), Resolved::Found(..)))
    }

    /// Skips a group whose condition is false, up to the `#elif`/`#else`/`#endif` that ends
    /// it, taking an `#elif`/`#else` branch when no earlier branch was taken.
    fn skip_group(&mut self) -> PResult<()> {
        let Some(frame) = self.frames.last() else { return Ok(()) };
        let source = frame.source.clone();
        let ctx = frame.ctx;
        let text = source.text();
        let bytes = text.as_bytes();
        let mut pos = frame.pos;
        let mut depth = 0usize;
        loop {
            // At a line start: whitespace and comments, then maybe a directive.
            let mut p = pos;
            loop {
                let (kind, len) = lexer::next(bytes, p);
                match kind {
                    Kind::Space | Kind::BlockComment { terminated: true } => p += len,
                    _ => break,
                }
            }
            if p >= bytes.len() {
                if let Some(f) = self.frames.last_mut() {
                    f.pos = bytes.len();
                }
                return Ok(()); // end_of_file reports the open conditional
            }
            let (kind, len) = lexer::next(bytes, p);
            let is_hash = kind == Kind::Punct && (bytes[p] == b'#' || &bytes[p..p + len] == b"%:");
            if is_hash {
                let hash = p;
                let mut q = p + len;
                loop {
                    let (k, l) = lexer::next(bytes, q);
                    match k {
                        Kind::Space | Kind::BlockComment { terminated: true } => q += l,
                        _ => break,
                    }
                }
                let (k, l) = lexer::next(bytes, q);
                let name = if k == Kind::Ident { &text[q..q + l] } else { "" };
                let name_range = q as u32..(q + l) as u32;
                match name {
                    "if" | "ifdef" | "ifndef" => depth += 1,
                    "endif" if depth > 0 => depth -= 1,
                    "endif" | "else" | "elif" if depth == 0 => {
                        if let Some(f) = self.frames.last_mut() {
                            f.pos = q + l;
                        }
                        let (toks, _) = self.directive_tokens()?;
                        let Some(f) = self.frames.last_mut() else { return Ok(()) };
                        if name != "endif" && f.conds.len() == 1 && matches!(f.guard, GuardState::Inside(_)) {
                            f.guard = GuardState::No;
                        }
                        let Some(c) = f.conds.last_mut() else { return Ok(()) };
                        match name {
                            "endif" => {
                                f.conds.pop();
                                if f.conds.is_empty() {
                                    if let GuardState::Inside(sym) = f.guard {
                                        f.guard = GuardState::Closed(sym);
                                    }
                                }
                                return Ok(());
                            }
                            _ if c.else_seen => {
                                return self.err_at(ctx, hash as u32..name_range.end, format!("#{name} after #else"), "after the #else of this conditional");
                            }
                            "else" => {
                                c.else_seen = true;
                                if !c.taken {
                                    c.taken = true;
                                    return Ok(());
                                }
                            }
                            _ => {
                                // #elif
                                if !c.taken {
                                    let v = self.eval_if(toks, ctx, name_range.clone())?;
                                    if v {
                                        if let Some(c) = self.frames.last_mut().and_then(|f| f.conds.last_mut()) {
                                            c.taken = true;
                                        }
                                        return Ok(());
                                    }
                                }
                            }
                        }
                        pos = self.frames.last().map_or(bytes.len(), |f| f.pos);
                        continue;
                    }
                    _ => {}
                }
            }
            // Skip to the end of this line, honouring comments and literals.
            pos = skip_line(bytes, p);
        }
    }

    fn include(&mut self, hash: u32, after_name: usize) -> PResult<()> {
        let Some(frame) = self.frames.last() else { return Ok(()) };
        let ctx = frame.ctx;
        let source = frame.source.clone();
        let text = source.text();
        let bytes = text.as_bytes();
        let mut p = after_name;
        while p < bytes.len() && matches!(bytes[p], b' ' | b'\t' | b'\r' | b'\x0b' | b'\x0c') {
            p += 1;
        }
        // Header names are lexed from the raw text; anything else is macro-expanded.
        let line_end = lexer::memchr_nl(bytes, p);
        let (spelling, angle, spell_range, rest_at) = match bytes.get(p) {
            Some(b'<') => match text[p + 1..line_end].find('>') {
                Some(i) => (text[p + 1..p + 1 + i].to_string(), true, p as u32..(p + i + 2) as u32, p + i + 2),
                None => return self.err_at(ctx, p as u32..line_end as u32, "missing terminating > character", "this header name is never closed"),
            },
            Some(b'"') => match text[p + 1..line_end].find('"') {
                Some(i) => (text[p + 1..p + 1 + i].to_string(), false, p as u32..(p + i + 2) as u32, p + i + 2),
                None => return self.err_at(ctx, p as u32..line_end as u32, "missing terminating \" character", "this file name is never closed"),
            },
            _ => {
                if let Some(f) = self.frames.last_mut() {
                    f.pos = p;
                }
                let (toks, end) = self.directive_tokens()?;
                if toks.is_empty() {
                    return self.err_at(ctx, hash..end, "#include expects \"FILENAME\" or <FILENAME>", "no file name");
                }
                let range = toks[0].src..end;
                let line = source.line_col(source.original_offset(hash as usize)).0 as i64;
                let exp = self.expand_line(toks, Some(line))?;
                let (s, angle) = self.computed_header(&exp).ok_or(()).or_else(|_| {
                    self.err_at(ctx, range.clone(), "#include expects \"FILENAME\" or <FILENAME>", "this does not expand to a file name")
                })?;
                return self.do_include(&s, angle, ctx, hash, range);
            }
        };
        if let Some(f) = self.frames.last_mut() {
            f.pos = rest_at;
        }
        let (extra, _) = self.directive_tokens()?;
        if let Some(t) = extra.first() {
            let l = self.tok_labels(t, "unexpected");
            self.warn("extra tokens at end of #include directive", l);
        }
        self.do_include(&spelling, angle, ctx, hash, spell_range)
    }

    /// The file name of a macro-expanded `#include` line.
    fn computed_header(&self, toks: &[Tok]) -> Option<(String, bool)> {
        let first = toks.first()?;
        if first.kind == TK::Str {
            let s = self.it.str(first.sym);
            if s.starts_with('"') && s.len() >= 2 {
                return Some((s[1..s.len() - 1].to_string(), false));
            }
            return None;
        }
        if first.kind == TK::Punct && self.it.str(first.sym) == "<" {
            let mut s = String::new();
            for (i, t) in toks.iter().enumerate().skip(1) {
                if t.kind == TK::Punct && self.it.str(t.sym) == ">" {
                    return Some((s, true));
                }
                if i > 1 && t.flags & WHITE != 0 {
                    s.push(' ');
                }
                s.push_str(self.it.str(t.sym));
            }
        }
        None
    }

    /// Where an include of `spelling` leads from the current file.
    fn resolve_include(&self, spelling: &str, angle: bool) -> Resolved {
        let includer_name = self.frames.last().map(|f| f.name.clone()).unwrap_or_default();
        let mut found = Resolved::NotFound;
        let is_virtual = self.opts.virtual_roots.iter().any(|(p, _)| virtual_match(spelling, p).is_some());
        if !angle && !is_virtual && relative_ok(spelling) {
            if let Some(dir) = self.frames.last().and_then(|f| f.source.path.parent()).filter(|d| d.is_dir()) {
                let cand = dir.join(spelling);
                if cand.is_file() {
                    found = Resolved::NotFound;
                    if let Ok(c) = cand.canonicalize() {
                        found = if self.roots.iter().any(|r| c.starts_with(r)) { Resolved::Found(c, String::new()) } else { Resolved::Escapes(c) };
                    }
                    if let Resolved::Found(_, name) = &mut found {
                        *name = match includer_name.rfind('/') {
                            Some(i) => format!("{}/{spelling}", &includer_name[..i]),
                            None => spelling.to_string(),
                        };
                    }
                }
            }
        }
        if matches!(found, Resolved::NotFound) {
            found = resolve_in_roots(spelling, self.opts);
        }
        found
    }

    fn do_include(&mut self, spelling: &str, angle: bool, ctx: u32, hash: u32, range: Range<u32>) -> PResult<()> {
        if spelling.is_empty() {
            return self.err_at(ctx, range, "empty filename in #include", "no file name");
        }
        if self.frames.len() >= 200 {
            return self.err_at(ctx, range, "#include nested depth 200 exceeds maximum of 200", "this include");
        }
        let found = self.resolve_include(spelling, angle);
        let (path, cpp_name) = match found {
            Resolved::Found(p, n) => (p, n),
            Resolved::Escapes(p) => {
                let shown = self.cache.display_name(&p);
                return self.err_at(ctx, range, format!("#include \"{spelling}\" resolves to `{shown}`, outside the include roots"), "this include escapes its root");
            }
            Resolved::NotFound => {
                let mut e = Error::new(format!("cannot find include file `{spelling}`"), self.labels_at(ctx, range, "not found"));
                let mut searched: Vec<String> = Vec::new();
                if !angle {
                    searched.push("the including file's folder".to_string());
                }
                for r in &self.opts.include_roots {
                    searched.push(self.cache.display_name(&r.canonicalize().unwrap_or_else(|_| r.clone())));
                }
                e.diagnostic = e.diagnostic.with_notes(vec![if searched.is_empty() {
                    "no include roots are configured".to_string()
                } else {
                    format!("searched: {}", searched.join(", "))
                }]);
                return Err(e);
            }
        };
        let (id, source) = self.cache.load(&path).map_err(|e| Error::new(format!("cannot read `{}`: {e}", self.cache.display_name(&path)), self.labels_at(ctx, range.clone(), "included here")))?;
        if source.text().len() >= (u32::MAX / 2) as usize {
            return self.err_at(ctx, range, "included file is too large", "this include");
        }
        if self.once.contains(&id) {
            if !self.files.contains(&id) {
                self.files.push(id);
            }
            return Ok(());
        }
        if let Some(&g) = self.guards.get(&id) {
            if self.macro_idx(g) != NONE {
                return Ok(());
            }
        }
        let name = if cpp_name.is_empty() { source.name.clone() } else { cpp_name };
        let site_end = range.end.max(hash);
        if !self.out.is_empty() && !self.out.ends_with('\n') {
            self.out.push('\n');
        }
        self.push_file(id, source, name, ctx, hash..site_end);
        Ok(())
    }

    // -----------------------------------------------------------------------------------------
    // Definitions

    fn parse_define(&mut self, toks: Vec<Tok>, predefined: bool) -> PResult<()> {
        let name = toks[0];
        if name.kind != TK::Ident {
            return self.err_tok(&name, "macro names must be identifiers", "not an identifier");
        }
        if name.sym == self.syms.defined {
            return self.err_tok(&name, "\"defined\" cannot be used as a macro name", "here");
        }
        let mut i = 1;
        let mut func = false;
        let mut variadic = false;
        let mut params: Vec<Sym> = Vec::new();
        if toks.get(1).is_some_and(|t| t.kind == TK::Punct && t.sym == self.syms.lparen && t.flags & WHITE == 0) {
            func = true;
            i = 2;
            let mut expect_param = true;
            loop {
                let Some(t) = toks.get(i).copied() else {
                    return self.err_tok(&toks[i - 1], "missing ')' in macro parameter list", "expected ')' after this");
                };
                i += 1;
                let s = self.it.str(t.sym).to_string();
                if expect_param {
                    if t.kind == TK::Ident {
                        if params.contains(&t.sym) {
                            return self.err_tok(&t, format!("duplicate macro parameter \"{s}\""), "already a parameter");
                        }
                        if t.sym == self.syms.va_args {
                            return self.err_tok(&t, "__VA_ARGS__ can not be used as a parameter name", "here");
                        }
                        params.push(t.sym);
                        expect_param = false;
                        continue;
                    }
                    if s == "..." {
                        variadic = true;
                        params.push(self.syms.va_args);
                        let Some(c) = toks.get(i).copied() else {
                            return self.err_tok(&t, "missing ')' in macro parameter list", "expected ')' after this");
                        };
                        i += 1;
                        if !(c.kind == TK::Punct && c.sym == self.syms.rparen) {
                            return self.err_tok(&c, "expected ')' after \"...\"", "expected ')'");
                        }
                        break;
                    }
                    if s == ")" && params.is_empty() {
                        break;
                    }
                    return self.err_tok(&t, format!("expected parameter name, found \"{s}\""), "expected a parameter name");
                }
                match s.as_str() {
                    "," => expect_param = true,
                    ")" => break,
                    "..." => {
                        // GNU named variadic parameter: `args...`.
                        variadic = true;
                        let Some(c) = toks.get(i).copied() else {
                            return self.err_tok(&t, "missing ')' in macro parameter list", "expected ')' after this");
                        };
                        i += 1;
                        if !(c.kind == TK::Punct && c.sym == self.syms.rparen) {
                            return self.err_tok(&c, "expected ')' after \"...\"", "expected ')'");
                        }
                        break;
                    }
                    _ => return self.err_tok(&t, format!("expected ',' or ')', found \"{s}\""), "expected ',' or ')'"),
                }
            }
        } else if let Some(t) = toks.get(1) {
            if t.flags & WHITE == 0 && !predefined {
                let l = self.tok_labels(&name, "here");
                self.warn("missing whitespace after the macro name", l);
            }
        }
        let named_variadic = variadic && params.last() != Some(&self.syms.va_args);
        let mut body: Vec<Tok> = Vec::with_capacity(toks.len() - i);
        let mut j = i;
        while j < toks.len() {
            let mut t = toks[j];
            t.flags |= FROM_DEF;
            if body.is_empty() {
                t.flags &= !WHITE;
            }
            let s = self.it.str(t.sym);
            if t.kind == TK::Punct && (s == "##" || s == "%:%:") {
                if body.is_empty() || j + 1 == toks.len() {
                    return self.err_tok(&toks[j], "'##' cannot appear at either end of a macro expansion", "here");
                }
                if let Some(last) = body.last_mut() {
                    last.flags |= PASTE_LEFT;
                }
                j += 1;
                continue;
            }
            if func && t.kind == TK::Punct && (s == "#" || s == "%:") {
                let next = toks.get(j + 1).copied();
                if let Some(n) = next.filter(|n| variadic && n.kind == TK::Ident && n.sym == self.syms.va_opt) {
                    // `#__VA_OPT__(...)`: stringified when the __VA_OPT__ is resolved.
                    body.push(Tok { flags: (t.flags & WHITE) | STRINGIFY | FROM_DEF, ..n });
                    j += 2;
                    continue;
                }
                match next.filter(|n| n.kind == TK::Ident).and_then(|n| params.iter().position(|&p| p == n.sym)) {
                    Some(pi) => {
                        let n = toks[j + 1];
                        body.push(Tok { param: pi as u16, flags: (t.flags & WHITE) | STRINGIFY | FROM_DEF, ..n });
                        j += 2;
                        continue;
                    }
                    None => return self.err_tok(&toks[j], "'#' is not followed by a macro parameter", "here"),
                }
            }
            if t.kind == TK::Ident {
                if func {
                    if let Some(pi) = params.iter().position(|&p| p == t.sym) {
                        t.param = pi as u16;
                    }
                }
                if t.sym == self.syms.va_args && (!variadic || named_variadic) && t.param == NO_PARAM {
                    let l = self.tok_labels(&toks[j], "here");
                    self.warn("__VA_ARGS__ can only appear in the expansion of a C99 variadic macro", l);
                }
            }
            body.push(t);
            j += 1;
        }
        // GNU `, ## __VA_ARGS__`.
        if variadic {
            let va = (params.len() - 1) as u16;
            for k in 0..body.len().saturating_sub(1) {
                if body[k].kind == TK::Punct
                    && body[k].sym == self.syms.comma
                    && body[k].flags & PASTE_LEFT != 0
                    && body[k + 1].param == va
                    && body[k + 1].flags & STRINGIFY == 0
                {
                    body[k].flags |= VA_COMMA;
                }
            }
        }
        if params.len() >= NO_PARAM as usize {
            return self.err_tok(&name, "too many macro parameters", "here");
        }
        let pastes = body.iter().any(|t| t.flags & (PASTE_LEFT | VA_COMMA) != 0);
        let va_opt = variadic && body.iter().any(|t| t.kind == TK::Ident && t.sym == self.syms.va_opt);
        let m = Macro {
            func,
            variadic,
            params,
            body: body.into(),
            pastes,
            va_opt,
            builtin: Builtin::None,
            ctx: name.ctx,
            site: name.src..name.src + name.len,
            disabled: false,
        };
        let old = self.macro_idx(name.sym);
        if old != NONE {
            let prev = &self.defs[old as usize];
            if !self.same_definition(prev, &m) {
                let n = self.it.str(name.sym).to_string();
                let mut labels = self.tok_labels(&name, "redefined here");
                if prev.ctx != NONE {
                    if let Some(c) = self.map.ctxs.get(prev.ctx as usize) {
                        let r = c.source.original_range(prev.site.start as usize..prev.site.end as usize);
                        labels.push(Label::secondary(c.file, r).with_message("previous definition"));
                    }
                }
                self.warn(format!("\"{n}\" redefined"), labels);
            }
        }
        self.set_macro(name.sym, m);
        Ok(())
    }

    fn same_definition(&self, a: &Macro, b: &Macro) -> bool {
        const CMP: u8 = WHITE | PASTE_LEFT | STRINGIFY;
        a.builtin == b.builtin
            && a.func == b.func
            && a.variadic == b.variadic
            && a.params == b.params
            && a.body.len() == b.body.len()
            && a.body.iter().zip(b.body.iter()).enumerate().all(|(i, (x, y))| {
                x.sym == y.sym && x.param == y.param && (i == 0 || (x.flags & CMP) == (y.flags & CMP))
            })
    }
}

/// Skips to the start of the next line from `p`, treating comments and literals as cpp does
/// in a skipped group (a block comment may run over several lines).
fn skip_line(bytes: &[u8], mut p: usize) -> usize {
    while p < bytes.len() {
        match bytes[p] {
            b'\n' => return p + 1,
            b'/' | b'"' | b'\'' | b'L' | b'u' | b'U' => {
                let (kind, len) = lexer::next(bytes, p);
                match kind {
                    Kind::LineComment => return lexer::memchr_nl(bytes, p) + 1,
                    _ => p += len.max(1),
                }
            }
            _ => p += 1,
        }
    }
    bytes.len()
}

/// A string literal for a file name.
fn quote(s: &str) -> String {
    let mut out = String::with_capacity(s.len() + 2);
    out.push('"');
    for c in s.chars() {
        if c == '"' || c == '\\' {
            out.push('\\');
        }
        out.push(c);
    }
    out.push('"');
    out
}

fn unquote(s: &str) -> String {
    let inner = s.strip_prefix('"').and_then(|s| s.strip_suffix('"')).unwrap_or(s);
    inner.replace("\\\"", "\"").replace("\\\\", "\\")
}

/// Directive text with comments replaced by single spaces.
fn collapse_comments(s: &str) -> String {
    if !s.contains("/*") && !s.contains("//") {
        return s.to_string();
    }
    let b = s.as_bytes();
    let mut out = String::with_capacity(s.len());
    let mut p = 0;
    while p < b.len() {
        let (kind, len) = lexer::next(b, p);
        let len = len.max(1).min(b.len() - p);
        match kind {
            Kind::LineComment | Kind::BlockComment { .. } => out.push(' '),
            _ => out.push_str(s.get(p..p + len).unwrap_or("")),
        }
        p += len;
    }
    out.trim().to_string()
}

#[allow(dead_code)]
fn _assert_send_sync() {
    fn is<T: Send + Sync>() {}
    is::<SourceCache>();
    is::<Output>();
}

/// `__DATE__` and `__TIME__` of now (UTC, or `SOURCE_DATE_EPOCH` like GCC).
fn date_time() -> (String, String) {
    let secs = std::env::var("SOURCE_DATE_EPOCH")
        .ok()
        .and_then(|v| v.parse::<i64>().ok())
        .unwrap_or_else(|| {
            std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_secs() as i64)
        });
    let days = secs.div_euclid(86_400);
    let rem = secs.rem_euclid(86_400);
    // Civil date from days since 1970-01-01 (Howard Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    const MONTHS: [&str; 12] = ["Jan", "Feb", "Mar", "Apr", "May", "Jun", "Jul", "Aug", "Sep", "Oct", "Nov", "Dec"];
    let date = format!("{} {day:2} {year}", MONTHS[(month - 1) as usize]);
    let time = format!("{:02}:{:02}:{:02}", rem / 3600, rem % 3600 / 60, rem % 60);
    (date, time)
}
