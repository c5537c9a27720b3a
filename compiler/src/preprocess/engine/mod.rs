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

mod directive;
mod expand;

use std::collections::{HashMap, HashSet};
use std::hash::{BuildHasherDefault, Hasher};
use std::ops::Range;
use std::path::{Component, Path, PathBuf};
use std::sync::Arc;

use codespan_reporting::diagnostic::{Diagnostic, Label};

use super::expr;
use super::lexer::{self, Kind};
use super::map::{Entry, IncludeCtx, SourceMap, NONE};
use super::source::{FileId, LoadError, PathKind, SourceCache, SourceFile};
use super::{Error, Options, Output};
use directive::DefReader;

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

/// The symbol of a word that was never interned (see [`Pp::line_token`]).
const NO_SYM: Sym = Sym::MAX;

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
    /// A long body not kept as tokens: it is read again from its source on first use.
    lazy: Option<LazyBody>,
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

/// Where to read a long replacement list again (see [`Pp::body_of`]): the include context
/// and spliced offset of its first token, and how many tokens it has.
#[derive(Clone, Copy, Debug)]
struct LazyBody {
    ctx: u32,
    start: u32,
    len: usize,
}

/// Warnings kept per run; the rest are counted in one last warning.
const MAX_WARNINGS: usize = 1000;

/// Replacement lists longer than this many tokens are not kept as tokens until the macro is
/// first expanded: a huge `#define` that is never used costs no more than its text.
const LAZY_BODY_TOKENS: usize = 4096;

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
    /// Warnings past [`MAX_WARNINGS`], counted only.
    warnings_dropped: usize,
    files: Vec<FileId>,
    once: HashSet<FileId>,
    guards: HashMap<FileId, Sym, FxBuild>,
    /// Tokens macro expansion may still make.
    /// Tokens macro expansion made so far (see [`Pp::spend`]).
    made: usize,
    /// Bytes of text `#` and `##` made so far (see [`Pp::spend_bytes`]).
    made_bytes: usize,
    /// Bytes of source read so far.
    input_bytes: usize,
    counter: i64,
    /// Output range of the last token written (for paste avoidance).
    last_tok: Range<usize>,
    /// A padding token (a macro expansion's edge) came since the last token written: the
    /// next one is kept apart by cpp's rule too ([`lexer::cpp_avoid_paste`]).
    after_padding: bool,
    /// The top-level macro invocation being expanded: context, spliced range.
    inv: Option<(u32, u32, u32)>,
    /// Line `__LINE__` gives inside a directive.
    directive_line: Option<i64>,
    /// Allowed roots for includes (canonical).
    roots: Vec<PathBuf>,
    base_name: String,
    /// Include candidates found missing (see [`super::Output::absent`]).
    absent: std::cell::RefCell<Vec<PathBuf>>,
    /// Lines excluded by a false conditional (see [`super::Output::skipped`]).
    skipped: Vec<(FileId, Range<u32>)>,
}

// ---------------------------------------------------------------------------------------------
// Entry points

pub(crate) fn run(file: FileId, opts: &Options, cache: &SourceCache) -> Result<Output, Error> {
    run_named(file, None, opts, cache)
}

/// Stack for one preprocessing run: nested macro arguments recurse (one level per
/// `max_expansion_depth`), and a caller's thread (a test's, a rayon worker's) may be small.
pub const STACK_BYTES: usize = 256 << 20;

thread_local! {
    /// Set on threads started with [`STACK_BYTES`] of stack (see [`big_stack_thread`]).
    static BIG_STACK: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Declares that the calling thread was started with at least [`STACK_BYTES`] of stack
/// (rayon's `start_handler` of a pool built with that stack size): preprocessing then runs
/// on it, without starting a thread per file.
pub fn big_stack_thread() {
    BIG_STACK.with(|b| b.set(true));
}

pub(crate) fn run_named(
    file: FileId,
    name: Option<String>,
    opts: &Options,
    cache: &SourceCache,
) -> Result<Output, Error> {
    let panicked = || Err(Error::new("internal error: the preprocessor panicked", Vec::new()));
    if BIG_STACK.with(|b| b.get()) {
        return std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| run_here(file, name.clone(), opts, cache)))
            .unwrap_or_else(|_| panicked());
    }
    // The stack is only reserved address space; pages are touched as deep as the input goes.
    std::thread::scope(|s| {
        let worker = std::thread::Builder::new()
            .name("kiln-preprocess".into())
            .stack_size(STACK_BYTES)
            .spawn_scoped(s, || run_here(file, name.clone(), opts, cache));
        match worker {
            Ok(handle) => handle.join().unwrap_or_else(|_| panicked()),
            Err(_) => run_here(file, name.clone(), opts, cache),
        }
    })
}

fn run_here(file: FileId, name: Option<String>, opts: &Options, cache: &SourceCache) -> Result<Output, Error> {
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
    if pp.warnings_dropped > 0 {
        let n = pp.warnings_dropped;
        pp.warnings.push(Diagnostic::warning().with_message(format!("{n} more warnings not shown")));
    }
    let mut absent = pp.absent.into_inner();
    absent.sort();
    absent.dedup();
    Ok(Output { text: pp.out, map: pp.map, files: pp.files, absent, warnings: pp.warnings, skipped: pp.skipped })
}

/// Tokens macro expansion may make in one run: a quarter of the output limit (a token
/// prints as at least one byte plus, often, a space), so a macro bomb stops early and small.
fn token_budget(opts: &Options) -> usize {
    (opts.max_output_bytes / 4).max(1024)
}

/// Resolves `<spelling>` through the virtual roots, then the include roots.
pub(crate) fn resolve_angle(spelling: &str, opts: &Options) -> Result<PathBuf, String> {
    match resolve_in_roots(spelling, opts, &mut Vec::new(), None) {
        Resolved::Found(p, _) => Ok(p),
        Resolved::Escapes(p) => Err(format!("`{spelling}` resolves to `{}`, outside its root", p.display())),
        Resolved::NotFound => match non_file_in(spelling, opts, &[]) {
            Some((p, what)) => Err(format!("`{spelling}` names `{}`, which is {what}, not a file", p.display())),
            None => Err(format!("cannot find `{spelling}` in the include roots")),
        },
    }
}

/// The first candidate for `spelling` (in `dirs`, then through the virtual roots or in the
/// include roots, as [`resolve_in_roots`] looks) that exists but is not a regular file, and
/// what it is.
fn non_file_in(spelling: &str, opts: &Options, dirs: &[PathBuf]) -> Option<(PathBuf, &'static str)> {
    if !relative_ok(spelling) && !opts.virtual_roots.iter().any(|(p, _)| virtual_match(spelling, p).is_some()) {
        return None;
    }
    let mut candidates: Vec<PathBuf> = dirs.iter().map(|d| d.join(spelling)).collect();
    match opts.virtual_roots.iter().find_map(|(p, d)| virtual_match(spelling, p).map(|rest| d.join(rest))) {
        Some(c) => candidates.push(c),
        None => candidates.extend(opts.include_roots.iter().map(|r| r.join(spelling))),
    }
    candidates.into_iter().find_map(|c| {
        let meta = std::fs::metadata(&c).ok()?;
        let what = if meta.is_dir() {
            "a directory"
        } else if meta.is_file() {
            return None;
        } else {
            "a device, FIFO or socket"
        };
        Some((c.canonicalize().unwrap_or(c), what))
    })
}

enum Resolved {
    /// Canonical path, and the name cpp would give it.
    Found(PathBuf, String),
    Escapes(PathBuf),
    NotFound,
}

/// What `path` is: from the build's source cache where there is one.
fn path_kind(cache: Option<&SourceCache>, path: &Path) -> PathKind {
    match cache {
        Some(c) => c.kind(path),
        None => match std::fs::metadata(path) {
            Ok(m) if m.is_file() => PathKind::File,
            Ok(m) if m.is_dir() => PathKind::Dir,
            Ok(_) => PathKind::Other,
            Err(_) => PathKind::Missing,
        },
    }
}

/// `path.canonicalize()`: from the build's source cache where there is one.
fn canonical(cache: Option<&SourceCache>, path: &Path) -> Option<PathBuf> {
    match cache {
        Some(c) => c.canonical(path),
        None => path.canonicalize().ok(),
    }
}

/// `candidate` if it exists inside `root` (both canonicalized).
fn contained(candidate: &Path, root: &Path, cache: Option<&SourceCache>) -> Resolved {
    let Some(c) = canonical(cache, candidate) else {
        return Resolved::NotFound;
    };
    if path_kind(cache, &c) != PathKind::File {
        return Resolved::NotFound;
    }
    let root = canonical(cache, root).unwrap_or_else(|| root.to_path_buf());
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

/// Resolves `spelling` in the virtual roots, then the include roots in order; every
/// candidate tried and found missing is pushed on `absent` (a file appearing there later
/// would change the result).
fn resolve_in_roots(
    spelling: &str,
    opts: &Options,
    absent: &mut Vec<PathBuf>,
    cache: Option<&SourceCache>,
) -> Resolved {
    for (prefix, dir) in &opts.virtual_roots {
        if let Some(rest) = virtual_match(spelling, prefix) {
            return match contained(&dir.join(rest), dir, cache) {
                Resolved::Found(p, _) => Resolved::Found(p, format!("{}/{rest}", prefix.trim_end_matches('/'))),
                Resolved::NotFound => {
                    absent.push(dir.join(rest));
                    Resolved::NotFound
                }
                other => other,
            };
        }
    }
    if !relative_ok(spelling) {
        return Resolved::NotFound;
    }
    let mut escaped = None;
    for root in &opts.include_roots {
        match contained(&root.join(spelling), root, cache) {
            Resolved::Found(p, _) => {
                let name = format!("{}/{spelling}", root.display());
                return Resolved::Found(p, name);
            }
            Resolved::Escapes(p) => escaped = escaped.or(Some(p)),
            Resolved::NotFound => absent.push(root.join(spelling)),
        }
    }
    match escaped {
        Some(p) => Resolved::Escapes(p),
        None => Resolved::NotFound,
    }
}

/// Where includes are searched, in order: the main file's folder, then the include roots and
/// the virtual roots, canonical where they exist.
fn search_roots(opts: &Options, cache: &SourceCache, main: &SourceFile) -> Vec<PathBuf> {
    let mut roots: Vec<PathBuf> = Vec::new();
    let main_dir = main.path.parent().filter(|p| cache.kind(p) == PathKind::Dir).map(|p| p.to_path_buf());
    if let Some(d) = &main_dir {
        roots.push(d.clone());
    }
    for r in &opts.include_roots {
        roots.push(cache.canonical(r).unwrap_or_else(|| r.clone()));
    }
    for (_, r) in &opts.virtual_roots {
        roots.push(cache.canonical(r).unwrap_or_else(|| r.clone()));
    }
    roots
}

impl Syms {
    /// Interns the names the engine compares against.
    fn new(it: &mut Interner) -> Syms {
        Syms {
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
        }
    }
}

// ---------------------------------------------------------------------------------------------

impl<'a> Pp<'a> {
    fn new(opts: &'a Options, cache: &'a SourceCache, main: &SourceFile) -> PResult<Pp<'a>> {
        let mut it = Interner::default();
        let syms = Syms::new(&mut it);
        let roots = search_roots(opts, cache, main);
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
            warnings_dropped: 0,
            files: Vec::new(),
            once: HashSet::new(),
            guards: HashMap::default(),
            made: 0,
            made_bytes: 0,
            input_bytes: 0,
            counter: 0,
            last_tok: 0..0,
            after_padding: false,
            inv: None,
            directive_line: None,
            roots,
            base_name: String::new(),
            absent: std::cell::RefCell::new(Vec::new()),
            skipped: Vec::new(),
        };
        pp.define_builtins();
        pp.define_predefined()?;
        Ok(pp)
    }

    /// The macros the engine computes: `__LINE__`, `__FILE__`, `_Pragma`, `__has_include`...
    fn define_builtins(&mut self) {
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
            let sym = self.it.intern(name);
            self.set_macro(
                sym,
                Macro {
                    func: false,
                    variadic: false,
                    params: Vec::new(),
                    body: Arc::from(Vec::new()),
                    lazy: None,
                    pastes: false,
                    va_opt: false,
                    builtin: b,
                    ctx: NONE,
                    site: 0..0,
                    disabled: false,
                },
            );
        }
    }

    /// cpp's predefined `__STDC__` macros, then the options' `-D` definitions.
    fn define_predefined(&mut self) -> PResult<()> {
        let predefined = [
            ("__STDC__", "1"),
            ("__STDC_VERSION__", "201112L"),
            ("__STDC_HOSTED__", "1"),
            ("__STDC_UTF_16__", "1"),
            ("__STDC_UTF_32__", "1"),
        ];
        for (name, value) in predefined {
            self.define_text(name, value)?;
        }
        let opts = self.opts;
        for (name, value) in &opts.defines {
            self.define_text(name, value)?;
        }
        Ok(())
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
        self.parse_define(&mut DefReader::list(toks), true)
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
                Kind::Space | Kind::Newline | Kind::LineComment | Kind::BlockComment { terminated: true } => {
                    white = true
                }
                Kind::BlockComment { terminated: false } | Kind::Str { terminated: false } => return None,
                _ => {
                    let sym = self.it.intern(&s[pos..pos + len]);
                    let flags = if white { WHITE } else { 0 } | FROM_DEF;
                    out.push(Tok {
                        sym,
                        ctx: NONE,
                        src: 0,
                        len: len as u32,
                        param: NO_PARAM,
                        kind: tk_of(kind),
                        flags,
                    });
                    white = false;
                }
            }
            pos += len.max(1);
        }
    }

    // -----------------------------------------------------------------------------------------
    // Diagnostics

    fn labels_at(&self, ctx: u32, range: Range<u32>, message: &str) -> Vec<Label<FileId>> {
        let Some(c) = self.map.ctxs.get(ctx as usize) else {
            return Vec::new();
        };
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
        if self.warnings.len() >= MAX_WARNINGS {
            // A million bad lines would otherwise keep a million diagnostics.
            self.warnings_dropped += 1;
            return;
        }
        self.warnings.push(Diagnostic::warning().with_message(message.into()).with_labels(labels));
    }

    // -----------------------------------------------------------------------------------------
    // Files

    fn push_file(&mut self, file: FileId, source: Arc<SourceFile>, name: String, parent: u32, site: Range<u32>) {
        let ctx = self.map.ctxs.len() as u32;
        self.input_bytes += source.text().len();
        self.map.ctxs.push(IncludeCtx { file, source: source.clone(), parent, site });
        if !self.files.contains(&file) {
            self.files.push(file);
        }
        // A UTF-8 byte order mark is not text (cpp skips it too).
        let pos = if source.text().starts_with('\u{feff}') { 3 } else { 0 };
        self.frames.push(Frame {
            source,
            file,
            ctx,
            pos,
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
        let Some(frame) = self.frames.last() else {
            return Ok(());
        };
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
                self.inv.map_or_else(
                    || self.frame_labels("while preprocessing this"),
                    |(c, s, e)| self.labels_at(c, s..e, "while expanding this"),
                ),
            ));
        }
        Ok(())
    }

    /// Copies `text[start..end]` of the current frame to the output.
    fn copy_run(
        &mut self,
        ctx: u32,
        text: &str,
        start: usize,
        end: usize,
        last_tok: Option<Range<usize>>,
    ) -> PResult<()> {
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
                // Text after an expansion: cpp has a padding here, so its rule applies.
                let (last, first) = (self.out[self.last_tok.clone()].as_bytes(), &bytes[start..start + len]);
                if lexer::would_paste(last, first) || lexer::cpp_avoid_paste(last, first) {
                    self.out.push(' ');
                }
            }
        }
        let out_at = self.out.len();
        self.push_copy_entry(ctx, start as u32, end as u32, out_at as u32);
        self.out.push_str(&text[start..end]);
        self.after_padding = false;
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
            self.after_padding = true;
            return Ok(());
        }
        if t.kind == TK::Placemarker || t.kind == TK::Eof {
            return Ok(());
        }
        let text: &str = self.it.strs.get(t.sym as usize).map_or("", |s| s);
        let adjacent = self.last_tok.end == self.out.len() && !self.last_tok.is_empty();
        let space = (t.flags & WHITE != 0)
            || (adjacent && {
                let last = self.out[self.last_tok.clone()].as_bytes();
                lexer::would_paste(last, text.as_bytes())
                    || (self.after_padding && lexer::cpp_avoid_paste(last, text.as_bytes()))
            });
        self.after_padding = false;
        if space && !self.out.is_empty() && !self.out.ends_with([' ', '\n', '\t']) {
            self.out.push(' ');
        }
        let out_at = self.out.len() as u32;
        if t.flags & FROM_DEF == 0 && t.ctx != NONE {
            self.push_copy_entry(t.ctx, t.src, t.src + t.len, out_at);
        } else {
            let (ctx, src, end) = self.inv.unwrap_or((NONE, 0, 0));
            let e =
                Entry { out: out_at, ctx, src, end, def_ctx: t.ctx, def_src: t.src, def_len: t.len, is_macro: true };
            // Runs of tokens with one origin (a repeated expansion) share an entry.
            let key = |e: &Entry| (e.ctx, e.src, e.end, e.def_ctx, e.def_src, e.def_len);
            if !self.map.entries.last().is_some_and(|l| l.is_macro && key(l) == key(&e)) {
                self.map.entries.push(e);
            }
        }
        let text: &str = self.it.strs.get(t.sym as usize).map_or("", |s| s);
        self.out.push_str(text);
        self.last_tok = out_at as usize..self.out.len();
        self.check_output()
    }

    // -----------------------------------------------------------------------------------------
    // The scanner: text outside macro invocations

    fn scan_text(&mut self) -> PResult<()> {
        let Some(frame) = self.frames.last_mut() else {
            return Ok(());
        };
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
            let (kind, len) = source.lex(pos);
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
                    return self.err_at(
                        ctx,
                        pos as u32..pos as u32 + 2,
                        "unterminated comment",
                        "this comment is never closed",
                    );
                }
                Kind::Punct if bol && lexer::is_directive_hash(&bytes[pos..pos + len]) => {
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
                            if let Some((sym, m)) = self.macro_here(text, pos, len) {
                                self.copy_run(ctx, text, run_start, pos, last_tok)?;
                                return self.expand_here(sym, m, ctx, pos, len);
                            }
                        }
                        Kind::Str { terminated: false } | Kind::Char { terminated: false } => {
                            self.unterminated_literal(kind, ctx, pos)?;
                        }
                        _ => {}
                    }
                    last_tok = Some(pos..pos + len);
                    pos += len;
                }
            }
        }
    }

    /// The macro that the identifier at `pos..pos + len` of the file text invokes: an
    /// object-like macro, or a function-like one followed by `(`.
    #[inline]
    fn macro_here(&self, text: &str, pos: usize, len: usize) -> Option<(Sym, u32)> {
        let sym = self.it.get(&text[pos..pos + len])?;
        let m = self.macro_idx(sym);
        if m == NONE {
            return None;
        }
        let func = self.defs[m as usize].func;
        (!func || self.peek_file_lparen(text.as_bytes(), pos + len)).then_some((sym, m))
    }

    /// Expands macro `m` named by the identifier `sym` at `pos..pos + len` of the file text,
    /// the frame left after the name.
    fn expand_here(&mut self, sym: Sym, m: u32, ctx: u32, pos: usize, len: usize) -> PResult<()> {
        if let Some(f) = self.frames.last_mut() {
            f.pos = pos + len;
            f.bol = false;
        }
        let name_tok = Tok { sym, ctx, src: pos as u32, len: len as u32, param: NO_PARAM, kind: TK::Ident, flags: 0 };
        self.expand_top(name_tok, m)
    }

    /// A string literal (an error) or character constant (a warning) with no closing quote
    /// at `pos` of the file text.
    #[cold]
    fn unterminated_literal(&mut self, kind: Kind, ctx: u32, pos: usize) -> PResult<()> {
        if matches!(kind, Kind::Str { .. }) {
            return self.err_at(
                ctx,
                pos as u32..pos as u32 + 1,
                "missing terminating \" character",
                "this string is never closed",
            );
        }
        let labels = self.labels_at(ctx, pos as u32..pos as u32 + 1, "this character constant is never closed");
        self.warn("missing terminating ' character", labels);
        Ok(())
    }

    /// Is the next token in the file text from `pos` a `(` (no directive line in between)?
    fn peek_file_lparen(&self, bytes: &[u8], mut pos: usize) -> bool {
        let mut bol = false;
        loop {
            let (kind, len) = lexer::next(bytes, pos);
            match kind {
                Kind::Space | Kind::LineComment | Kind::BlockComment { terminated: true } => {}
                Kind::Newline => bol = true,
                Kind::Punct => return !(bol && lexer::is_directive_hash(&bytes[pos..pos + len])) && bytes[pos] == b'(',
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

#[allow(dead_code)]
fn _assert_send_sync() {
    fn is<T: Send + Sync>() {}
    is::<SourceCache>();
    is::<Output>();
}
