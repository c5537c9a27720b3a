//! Directives: conditionals (and skipping), `#include`, `#define`/`#undef`, `#pragma`,
//! `#line`, `#error`/`#warning`.

use super::*;

impl Pp<'_> {
    // -----------------------------------------------------------------------------------------
    // Directives

    /// Reads the rest of the directive line as tokens (comments are spaces; a block comment
    /// may carry the line on). Leaves the frame at the start of the next line.
    pub(super) fn directive_tokens(&mut self) -> PResult<(Vec<Tok>, u32)> {
        self.directive_rest(usize::MAX)
    }

    /// [`Pp::directive_tokens`] keeping only the first `keep` tokens: the rest of the line is
    /// lexed (an unterminated comment is still an error) but neither interned nor stored, so
    /// a huge `#error` or `#pragma` line costs no memory. A kept line over the token budget
    /// is an error.
    pub(super) fn directive_rest(&mut self, keep: usize) -> PResult<(Vec<Tok>, u32)> {
        let Some(frame) = self.frames.last_mut() else {
            return Ok((Vec::new(), 0));
        };
        let source = frame.source.clone();
        let ctx = frame.ctx;
        let mut pos = frame.pos;
        let mut toks = Vec::new();
        let limit = self.token_limit();
        while let Some(t) = self.line_token(&source, ctx, &mut pos, toks.len() < keep)? {
            if toks.len() < keep {
                if toks.len() >= limit {
                    return self.err_tok(
                        &t,
                        format!("directive line has more than {limit} tokens"),
                        "this directive is too long",
                    );
                }
                toks.push(t);
            }
        }
        let end = pos;
        if source.text().as_bytes().get(pos) == Some(&b'\n') {
            pos += 1;
        }
        if let Some(f) = self.frames.last_mut() {
            f.pos = pos;
            f.bol = true;
        }
        Ok((toks, end as u32))
    }

    /// The next token of a directive line from `*pos` (whitespace and comments skipped; a
    /// block comment may carry the line on). `None` at the line's `\n` or the end of the
    /// text, with `*pos` left there. Identifiers and other words are interned only when
    /// `intern` (else looked up: a word never interned is no parameter or macro name);
    /// punctuators always are (there are few).
    pub(super) fn line_token(
        &mut self,
        source: &SourceFile,
        ctx: u32,
        pos: &mut usize,
        intern: bool,
    ) -> PResult<Option<Tok>> {
        let mut white = false;
        loop {
            let at = *pos;
            let (kind, len) = source.lex(at);
            match kind {
                Kind::Eof | Kind::Newline => return Ok(None),
                Kind::Space | Kind::LineComment | Kind::BlockComment { terminated: true } => white = true,
                Kind::BlockComment { terminated: false } => {
                    return self.err_at(
                        ctx,
                        at as u32..at as u32 + 2,
                        "unterminated comment",
                        "this comment is never closed",
                    );
                }
                _ => {
                    let text = &source.text()[at..at + len];
                    let sym = if intern || kind == Kind::Punct {
                        self.it.intern(text)
                    } else {
                        self.it.get(text).unwrap_or(NO_SYM)
                    };
                    *pos = at + len;
                    let flags = if white { WHITE } else { 0 };
                    return Ok(Some(Tok {
                        sym,
                        ctx,
                        src: at as u32,
                        len: len as u32,
                        param: NO_PARAM,
                        kind: tk_of(kind),
                        flags,
                    }));
                }
            }
            *pos = at + len;
        }
    }

    /// A directive met while collecting macro arguments: allowed except `#include`.
    pub(super) fn directive_in_args(&mut self, hash: usize) -> PResult<()> {
        let saved = self.inv;
        let r = self.directive(hash);
        self.inv = saved;
        r
    }

    /// Runs the directive whose `#` is at `hash` (the frame is just after the `#`).
    pub(super) fn directive(&mut self, hash: usize) -> PResult<()> {
        let Some(frame) = self.frames.last() else {
            return Ok(());
        };
        let ctx = frame.ctx;
        let source = frame.source.clone();
        let text = source.text();
        // The directive name, read in place (include needs the raw text after it).
        let (name, p, len) = directive_name(text, frame.pos);
        let after = p + len;
        let name_range = p as u32..after as u32;
        let hash_range = hash as u32..(hash + 1) as u32;
        let site = hash_range.start..name_range.end;
        let in_args = !self.stack.is_empty() || self.inv.is_some();
        let first_directive = frame.guard == GuardState::Start;
        self.update_guard(name, after, first_directive);
        match name {
            "define" => self.define_checked(&source, ctx, name_range),
            "undef" => self.undef_directive(ctx, name_range),
            "include" | "include_next" | "import" => {
                if in_args {
                    return self.err_at(
                        ctx,
                        name_range,
                        "#include inside macro arguments is not supported",
                        "inside this invocation's arguments",
                    );
                }
                self.include(hash_range.start, after)
            }
            "if" | "ifdef" | "ifndef" => self.if_directive(name, ctx, site, name_range, first_directive),
            "elif" | "else" => self.else_directive(name, ctx, site),
            "endif" => self.endif_directive(ctx, site),
            "error" | "warning" => self.message_directive(name, text, after, ctx, hash),
            "pragma" => self.pragma(after, ctx),
            "line" => {
                let (toks, _) = self.directive_tokens()?;
                self.line_directive(toks, ctx, name_range)
            }
            "ident" | "sccs" => {
                let (_, end) = self.directive_rest(0)?;
                let rest = collapse_comments(text.get(after..end as usize).unwrap_or("").trim());
                self.emit_line(ctx, hash, &format!("#ident {rest}"))
            }
            "assert" | "unassert" => {
                self.directive_rest(0)?;
                Ok(())
            }
            "" => self.null_directive(ctx, name_range),
            other => {
                let other = other.to_string();
                self.err_at(ctx, name_range, format!("invalid preprocessing directive #{other}"), "unknown directive")
            }
        }
    }

    /// Moves the frame past the directive's name (when it has one) and updates its include
    /// guard state: only an `#ifndef` that is the file's first directive opens a guard, and
    /// any directive after the guard's `#endif`, or an `#else`/`#elif` of the guard, ends it.
    fn update_guard(&mut self, name: &str, after: usize, first_directive: bool) {
        let Some(f) = self.frames.last_mut() else {
            return;
        };
        if !name.is_empty() {
            f.pos = after;
        }
        let closed = matches!(f.guard, GuardState::Closed(_));
        if closed || (first_directive && name != "ifndef") {
            f.guard = GuardState::No;
        }
        if matches!(name, "else" | "elif") && f.conds.len() == 1 && matches!(f.guard, GuardState::Inside(_)) {
            f.guard = GuardState::No;
        }
    }

    /// `#define`, after checking that a macro name follows.
    fn define_checked(&mut self, source: &SourceFile, ctx: u32, name_range: Range<u32>) -> PResult<()> {
        let Some(f) = self.frames.last() else {
            return Ok(());
        };
        let mut p = f.pos;
        if self.line_token(source, ctx, &mut p, false)?.is_none() {
            return self.err_at(ctx, name_range, "no macro name given in #define directive", "expected a macro name");
        }
        self.define_directive()
    }

    /// `#undef NAME`.
    fn undef_directive(&mut self, ctx: u32, name_range: Range<u32>) -> PResult<()> {
        let (toks, _) = self.directive_rest(2)?;
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

    /// `#if`, `#ifdef` and `#ifndef`: opens a conditional and skips its group when false.
    fn if_directive(
        &mut self,
        name: &str,
        ctx: u32,
        site: Range<u32>,
        name_range: Range<u32>,
        first_directive: bool,
    ) -> PResult<()> {
        let taken = if name == "if" {
            let (toks, _) = self.directive_tokens()?;
            self.eval_if(toks, ctx, name_range)?
        } else {
            self.ifdef_taken(name, ctx, name_range, first_directive)?
        };
        let nm: &'static str = match name {
            "if" => "if",
            "ifdef" => "ifdef",
            _ => "ifndef",
        };
        if let Some(f) = self.frames.last_mut() {
            f.conds.push(Cond { site, name: nm, taken, else_seen: false });
        }
        if !taken {
            self.skip_group()?;
        }
        Ok(())
    }

    /// Whether the group of an `#ifdef`/`#ifndef` is taken; an `#ifndef NAME` that is the
    /// file's first directive may open an include guard.
    fn ifdef_taken(&mut self, name: &str, ctx: u32, name_range: Range<u32>, first_directive: bool) -> PResult<bool> {
        let (toks, _) = self.directive_rest(2)?;
        let sym = self.directive_name(&toks, name, ctx, name_range)?;
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
        Ok(if name == "ifdef" { defined } else { !defined })
    }

    /// `#elif`/`#else` met in a taken group: everything up to `#endif` is skipped.
    fn else_directive(&mut self, name: &str, ctx: u32, site: Range<u32>) -> PResult<()> {
        let (toks, _) = self.directive_rest(1)?;
        let Some(f) = self.frames.last_mut() else {
            return Ok(());
        };
        let Some(c) = f.conds.last_mut() else {
            return self.err_at(ctx, site, format!("#{name} without #if"), "no open conditional");
        };
        if c.else_seen {
            return self.err_at(ctx, site, format!("#{name} after #else"), "after the #else of this conditional");
        }
        if name == "else" {
            c.else_seen = true;
            if !toks.is_empty() {
                let l = self.tok_labels(&toks[0], "unexpected");
                self.warn("extra tokens at end of #else directive", l);
            }
        }
        self.skip_group()
    }

    /// `#endif`: closes the conditional, and the include guard when it was the guard's.
    fn endif_directive(&mut self, ctx: u32, site: Range<u32>) -> PResult<()> {
        let (toks, _) = self.directive_rest(1)?;
        let Some(f) = self.frames.last_mut() else {
            return Ok(());
        };
        if f.conds.pop().is_none() {
            return self.err_at(ctx, site, "#endif without #if", "no open conditional");
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

    /// `#error` (an error) and `#warning` (a warning), with the rest of the line as message.
    fn message_directive(&mut self, name: &str, text: &str, start: usize, ctx: u32, hash: usize) -> PResult<()> {
        let (_, end) = self.directive_rest(0)?;
        let msg = text.get(start..end as usize).unwrap_or("").trim();
        let msg = collapse_comments(msg);
        let message = if msg.is_empty() { format!("#{name}") } else { format!("#{name} {msg}") };
        let labels = self.labels_at(ctx, hash as u32..end, "");
        if name == "error" {
            return Err(Error::new(message, labels));
        }
        self.warn(message, labels);
        Ok(())
    }

    /// A `#` with no name: empty, or a GNU line marker (`# 33 "file"`).
    fn null_directive(&mut self, ctx: u32, name_range: Range<u32>) -> PResult<()> {
        let (toks, _) = self.directive_tokens()?;
        match toks.first() {
            None => Ok(()),
            Some(t) if t.kind == TK::Number => self.line_directive(toks, ctx, name_range),
            Some(t) => {
                let s = self.it.str(t.sym).to_string();
                self.err_tok(t, format!("invalid preprocessing directive #{s}"), "not a directive")
            }
        }
    }

    /// The macro name of `#undef`/`#ifdef`/`#ifndef`.
    pub(super) fn directive_name(&self, toks: &[Tok], dir: &str, ctx: u32, at: Range<u32>) -> PResult<Sym> {
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
    pub(super) fn emit_line(&mut self, ctx: u32, at: usize, line: &str) -> PResult<()> {
        if !self.out.is_empty() && !self.out.ends_with('\n') {
            self.out.push('\n');
        }
        let out_at = self.out.len() as u32;
        self.map.entries.push(Entry {
            out: out_at,
            ctx,
            src: at as u32,
            end: at as u32 + 1,
            def_ctx: NONE,
            def_src: 0,
            def_len: 0,
            is_macro: true,
        });
        self.out.push_str(line);
        self.out.push('\n');
        self.last_tok = 0..0;
        self.check_output()
    }

    pub(super) fn pragma(&mut self, start: usize, ctx: u32) -> PResult<()> {
        let (toks, end) = self.directive_rest(3)?;
        let Some(frame) = self.frames.last() else {
            return Ok(());
        };
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

    pub(super) fn line_directive(&mut self, toks: Vec<Tok>, ctx: u32, at: Range<u32>) -> PResult<()> {
        let line_here = match self.frames.last() {
            Some(f) => f.source.line(f.source.original_offset(at.start as usize)) as i64,
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
    pub(super) fn expand_line(&mut self, toks: Vec<Tok>, line: Option<i64>) -> PResult<Vec<Tok>> {
        let Some(first) = toks.first().copied() else {
            return Ok(Vec::new());
        };
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
    pub(super) fn unwind(&mut self, depth: usize) {
        while self.stack.len() > depth {
            if let Some(c) = self.stack.pop() {
                if let Some(m) = self.defs.get_mut(c.mac as usize) {
                    m.disabled = false;
                }
            }
        }
    }

    /// Evaluates an `#if`/`#elif` line.
    pub(super) fn eval_if(&mut self, toks: Vec<Tok>, ctx: u32, at: Range<u32>) -> PResult<bool> {
        let line = match self.frames.last() {
            Some(f) => f.source.line(f.source.original_offset(at.start as usize)) as i64 + f.line_delta,
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
    pub(super) fn expand_if_tokens(&mut self, toks: Vec<Tok>, first: &Tok) -> PResult<Vec<Tok>> {
        self.push_context(toks, NONE, true, first)?;
        let mut out = Vec::new();
        while let Some(t) = self.get_token(false)? {
            if t.kind == TK::Eof {
                break;
            }
            if matches!(t.kind, TK::Placemarker | TK::Padding) {
                continue;
            }
            if t.kind == TK::Ident
                && (t.sym == self.syms.has_include || t.sym == self.syms.has_include_next)
                && t.flags & NO_EXPAND == 0
            {
                let found = self.has_include(&t)?;
                let sym = if found { self.syms.one } else { self.syms.zero };
                out.push(Tok { sym, kind: TK::Number, ..t });
                continue;
            }
            if t.kind == TK::Ident && t.sym == self.syms.defined {
                let Some(mut n) = self.next_raw(false)? else {
                    break;
                };
                let paren = n.kind == TK::Punct && n.sym == self.syms.lparen;
                if paren {
                    n = self.next_raw(false)?.unwrap_or(Tok::eof());
                }
                if n.kind != TK::Ident {
                    return self.err_tok(
                        if n.kind == TK::Eof { &t } else { &n },
                        "operator \"defined\" requires an identifier",
                        "expected an identifier",
                    );
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
    pub(super) fn has_include(&mut self, at: &Tok) -> PResult<bool> {
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
            return self.err_tok(
                at,
                format!("operator \"{name}\" requires a header-name"),
                "expected \"FILE\" or <FILE> after this",
            );
        };
        let close = self.next_raw(false)?.unwrap_or(Tok::eof());
        if !(close.kind == TK::Punct && close.sym == self.syms.rparen) {
            return self.err_tok(at, format!("missing ')' after \"{name}\" operand"), "expected ')'");
        }
        Ok(matches!(self.resolve_include(&spelling, angle), Resolved::Found(..)))
    }

    /// Skips a group whose condition is false, up to the `#elif`/`#else`/`#endif` that ends
    /// it, taking an `#elif`/`#else` branch when no earlier branch was taken.
    pub(super) fn skip_group(&mut self) -> PResult<()> {
        let Some(frame) = self.frames.last() else {
            return Ok(());
        };
        let source = frame.source.clone();
        let ctx = frame.ctx;
        let file = frame.file;
        let text = source.text();
        let bytes = text.as_bytes();
        let mut pos = frame.pos;
        // Where the group being skipped began (after the directive that opened it).
        let mut group = pos;
        let mut depth = 0usize;
        loop {
            // At a line start: whitespace and comments, then maybe a directive.
            let p = skip_blank(&source, pos);
            if p >= bytes.len() {
                if let Some(f) = self.frames.last_mut() {
                    f.pos = bytes.len();
                }
                return Ok(()); // end_of_file reports the open conditional
            }
            let (kind, len) = source.lex(p);
            if kind == Kind::Punct && lexer::is_directive_hash(&bytes[p..p + len]) {
                let (name, q, l) = directive_name(text, p + len);
                match name {
                    "if" | "ifdef" | "ifndef" => depth += 1,
                    "endif" if depth > 0 => depth -= 1,
                    "endif" | "else" | "elif" if depth == 0 => {
                        self.mark_skipped(&source, file, group, p);
                        if let Some(f) = self.frames.last_mut() {
                            f.pos = q + l;
                        }
                        if self.end_of_skip(name, ctx, p as u32, q as u32..(q + l) as u32)? {
                            return Ok(());
                        }
                        pos = self.frames.last().map_or(bytes.len(), |f| f.pos);
                        group = pos;
                        continue;
                    }
                    _ => {}
                }
            }
            // Skip to the end of this line, honouring comments and literals.
            pos = match skip_line(bytes, p) {
                Ok(next) => next,
                // cpp reports it too (and then the open conditional).
                Err(at) => {
                    return self.err_at(
                        ctx,
                        at as u32..at as u32 + 2,
                        "unterminated comment",
                        "this comment is never closed",
                    )
                }
            };
        }
    }

    /// The `#endif`, `#else` or `#elif` (`name`, `#` at `hash`) that ends a skipped group, the
    /// frame just past its name: `true` when skipping ends (the conditional is closed or this
    /// branch is taken), `false` when the next group is skipped too.
    fn end_of_skip(&mut self, name: &str, ctx: u32, hash: u32, name_range: Range<u32>) -> PResult<bool> {
        let (toks, _) = self.directive_tokens()?;
        let Some(f) = self.frames.last_mut() else {
            return Ok(true);
        };
        if name != "endif" && f.conds.len() == 1 && matches!(f.guard, GuardState::Inside(_)) {
            f.guard = GuardState::No;
        }
        let Some(c) = f.conds.last_mut() else {
            return Ok(true);
        };
        match name {
            "endif" => {
                f.conds.pop();
                if f.conds.is_empty() {
                    if let GuardState::Inside(sym) = f.guard {
                        f.guard = GuardState::Closed(sym);
                    }
                }
                Ok(true)
            }
            _ if c.else_seen => self.err_at(
                ctx,
                hash..name_range.end,
                format!("#{name} after #else"),
                "after the #else of this conditional",
            ),
            "else" => {
                c.else_seen = true;
                let take = !c.taken;
                c.taken = true;
                Ok(take)
            }
            // #elif
            _ if c.taken => Ok(false),
            _ => {
                let v = self.eval_if(toks, ctx, name_range)?;
                if v {
                    if let Some(c) = self.frames.last_mut().and_then(|f| f.conds.last_mut()) {
                        c.taken = true;
                    }
                }
                Ok(v)
            }
        }
    }

    /// Records the whole lines from spliced offset `from` (a partial first line is the
    /// directive's own) up to the line holding spliced offset `hash` (excluded).
    fn mark_skipped(&mut self, source: &SourceFile, file: FileId, from: usize, hash: usize) {
        let (line, column) = source.line_col(source.original_offset(from));
        let first = if column == 1 { line } else { line + 1 };
        let end = source.line(source.original_offset(hash));
        if end > first {
            self.skipped.push((file, first as u32..end as u32));
        }
    }

    pub(super) fn include(&mut self, hash: u32, after_name: usize) -> PResult<()> {
        let Some(frame) = self.frames.last() else {
            return Ok(());
        };
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
                None => {
                    return self.err_at(
                        ctx,
                        p as u32..line_end as u32,
                        "missing terminating > character",
                        "this header name is never closed",
                    )
                }
            },
            Some(b'"') => match text[p + 1..line_end].find('"') {
                Some(i) => (text[p + 1..p + 1 + i].to_string(), false, p as u32..(p + i + 2) as u32, p + i + 2),
                None => {
                    return self.err_at(
                        ctx,
                        p as u32..line_end as u32,
                        "missing terminating \" character",
                        "this file name is never closed",
                    )
                }
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
                let line = source.line(source.original_offset(hash as usize)) as i64;
                let exp = self.expand_line(toks, Some(line))?;
                let (s, angle) = self.computed_header(&exp).ok_or(()).or_else(|_| {
                    self.err_at(
                        ctx,
                        range.clone(),
                        "#include expects \"FILENAME\" or <FILENAME>",
                        "this does not expand to a file name",
                    )
                })?;
                return self.do_include(&s, angle, ctx, hash, range);
            }
        };
        if let Some(f) = self.frames.last_mut() {
            f.pos = rest_at;
        }
        let (extra, _) = self.directive_rest(1)?;
        if let Some(t) = extra.first() {
            let l = self.tok_labels(t, "unexpected");
            self.warn("extra tokens at end of #include directive", l);
        }
        self.do_include(&spelling, angle, ctx, hash, spell_range)
    }

    /// The file name of a macro-expanded `#include` line.
    pub(super) fn computed_header(&self, toks: &[Tok]) -> Option<(String, bool)> {
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

    /// The first place an include of `spelling` looked that holds something other than a
    /// regular file (a directory, a FIFO...), and what it is: said instead of "cannot find".
    pub(super) fn non_file_candidate(&self, spelling: &str, angle: bool) -> Option<(PathBuf, &'static str)> {
        let mut dirs: Vec<PathBuf> = Vec::new();
        let is_virtual = self.opts.virtual_roots.iter().any(|(p, _)| virtual_match(spelling, p).is_some());
        if !angle && !is_virtual {
            if let Some(dir) = self.frames.last().and_then(|f| f.source.path.parent()) {
                dirs.push(dir.to_path_buf());
            }
        }
        non_file_in(spelling, self.opts, &dirs)
    }

    /// Where an include of `spelling` leads from the current file.
    pub(super) fn resolve_include(&self, spelling: &str, angle: bool) -> Resolved {
        let includer_name = self.frames.last().map(|f| f.name.clone()).unwrap_or_default();
        let mut found = Resolved::NotFound;
        let is_virtual = self.opts.virtual_roots.iter().any(|(p, _)| virtual_match(spelling, p).is_some());
        if !angle && !is_virtual && relative_ok(spelling) {
            let dir = self.frames.last().and_then(|f| f.source.path.parent());
            if let Some(dir) = dir.filter(|d| self.cache.kind(d) == PathKind::Dir) {
                let cand = dir.join(spelling);
                let is_file = self.cache.kind(&cand) == PathKind::File;
                if !is_file {
                    self.absent.borrow_mut().push(cand.clone());
                }
                if is_file {
                    found = Resolved::NotFound;
                    if let Some(c) = self.cache.canonical(&cand) {
                        found = if self.roots.iter().any(|r| c.starts_with(r)) {
                            Resolved::Found(c, String::new())
                        } else {
                            Resolved::Escapes(c)
                        };
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
            found = resolve_in_roots(spelling, self.opts, &mut self.absent.borrow_mut(), Some(self.cache));
        }
        found
    }

    pub(super) fn do_include(
        &mut self,
        spelling: &str,
        angle: bool,
        ctx: u32,
        hash: u32,
        range: Range<u32>,
    ) -> PResult<()> {
        if spelling.is_empty() {
            return self.err_at(ctx, range, "empty filename in #include", "no file name");
        }
        if self.frames.len() >= 200 {
            return self.err_at(ctx, range, "#include nested depth 200 exceeds maximum of 200", "this include");
        }
        let (path, cpp_name) = self.include_target(spelling, angle, ctx, &range)?;
        let (id, source) = self.cache.load(&path).map_err(|e| {
            let mut labels = self.labels_at(ctx, range.clone(), "included here");
            if matches!(e, LoadError::NotUtf8 { .. }) {
                // The bad byte is the primary label; the include line is where it came from.
                if let Some(first) = labels.first_mut() {
                    first.style = codespan_reporting::diagnostic::LabelStyle::Secondary;
                }
            }
            e.into_error(&self.cache.display_name(&path), labels)
        })?;
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

    /// The file an `#include` names and the name cpp gives it, or the error saying why there
    /// is none: it escapes the include roots, is not a file, or is nowhere to be found.
    fn include_target(&self, spelling: &str, angle: bool, ctx: u32, range: &Range<u32>) -> PResult<(PathBuf, String)> {
        match self.resolve_include(spelling, angle) {
            Resolved::Found(p, n) => Ok((p, n)),
            Resolved::Escapes(p) => {
                let shown = self.cache.display_name(&p);
                self.err_at(
                    ctx,
                    range.clone(),
                    format!("#include \"{spelling}\" resolves to `{shown}`, outside the include roots"),
                    "this include escapes its root",
                )
            }
            Resolved::NotFound => {
                if let Some((path, what)) = self.non_file_candidate(spelling, angle) {
                    let shown = self.cache.display_name(&path);
                    return self.err_at(
                        ctx,
                        range.clone(),
                        format!("#include \"{spelling}\" names `{shown}`, which is {what}, not a file"),
                        "not a file",
                    );
                }
                Err(self.include_not_found(spelling, angle, ctx, range))
            }
        }
    }

    /// "cannot find include file", with a note naming the folders searched.
    fn include_not_found(&self, spelling: &str, angle: bool, ctx: u32, range: &Range<u32>) -> Error {
        let mut e = Error::new(
            format!("cannot find include file `{spelling}`"),
            self.labels_at(ctx, range.clone(), "not found"),
        );
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
        e
    }

    // -----------------------------------------------------------------------------------------
    // Definitions

    /// The next token of a definition.
    fn def_next(&mut self, r: &mut DefReader) -> PResult<Option<Tok>> {
        if let Some(t) = r.peeked.take() {
            return Ok(t);
        }
        match &mut r.src {
            DefSource::List { toks, at } => {
                let t = toks.get(*at).copied();
                *at += 1;
                Ok(t)
            }
            DefSource::Line { source, ctx, pos, intern } => self.line_token(source, *ctx, pos, *intern),
        }
    }

    /// The token [`Pp::def_next`] gives next, left in place.
    fn def_peek(&mut self, r: &mut DefReader) -> PResult<Option<Tok>> {
        if r.peeked.is_none() {
            let t = self.def_next(r)?;
            r.peeked = Some(t);
        }
        Ok(r.peeked.flatten())
    }

    /// `#define` with its tokens read from the current directive line; the frame is left at
    /// the next line.
    pub(super) fn define_directive(&mut self) -> PResult<()> {
        let Some(frame) = self.frames.last() else {
            return Ok(());
        };
        let mut r = DefReader {
            src: DefSource::Line { source: frame.source.clone(), ctx: frame.ctx, pos: frame.pos, intern: true },
            peeked: None,
        };
        self.parse_define(&mut r, false)?;
        // Past the replacement list (read to its end) and the newline.
        if let DefSource::Line { pos, .. } = r.src {
            if let Some(f) = self.frames.last_mut() {
                f.pos = pos;
            }
        }
        self.directive_rest(0)?;
        Ok(())
    }

    pub(super) fn parse_define(&mut self, r: &mut DefReader, predefined: bool) -> PResult<()> {
        let Some(name) = self.def_next(r)? else {
            return match self.frames.last() {
                Some(f) if !predefined => {
                    let p = f.pos as u32;
                    let ctx = f.ctx;
                    self.err_at(ctx, p..p, "no macro name given in #define directive", "expected a macro name")
                }
                _ => Err(Error::new("no macro name given in #define directive", Vec::new())),
            };
        };
        if name.kind != TK::Ident {
            return self.err_tok(&name, "macro names must be identifiers", "not an identifier");
        }
        if name.sym == self.syms.defined {
            return self.err_tok(&name, "\"defined\" cannot be used as a macro name", "here");
        }
        let mut func = false;
        let mut variadic = false;
        let mut params: Vec<Sym> = Vec::new();
        // Parameter numbers by name, for duplicate checks and the body: a linear search per
        // token made a macro with many parameters quadratic.
        let mut index: HashMap<Sym, u16, FxBuild> = HashMap::default();
        let first = self.def_peek(r)?;
        if let Some(open) = first.filter(|t| t.kind == TK::Punct && t.sym == self.syms.lparen && t.flags & WHITE == 0) {
            self.def_next(r)?;
            func = true;
            variadic = self.define_params(r, open, &mut params, &mut index)?;
        } else if let Some(t) = first {
            if t.flags & WHITE == 0 && !predefined {
                let l = self.tok_labels(&name, "here");
                self.warn("missing whitespace after the macro name", l);
            }
        }
        let shape = Shape { func, variadic, params: &params, index: &index };
        let keep = if predefined { usize::MAX } else { LAZY_BODY_TOKENS };
        let body = self.read_body(r, &shape, keep, true)?;
        let lazy = match (&body.toks, body.start) {
            (None, Some(start)) => Some(LazyBody { ctx: name.ctx, start, len: body.len }),
            _ => None,
        };
        let m = Macro {
            func,
            variadic,
            params,
            body: body.toks.unwrap_or_default().into(),
            lazy,
            pastes: body.pastes,
            va_opt: body.va_opt,
            builtin: Builtin::None,
            ctx: name.ctx,
            site: name.src..name.src + name.len,
            disabled: false,
        };
        let old = self.macro_idx(name.sym);
        let new = self.set_macro(name.sym, m);
        if old != NONE && !self.same_definition(old, new)? {
            self.warn_redefined(&name, old);
        }
        Ok(())
    }

    /// Reads a function-like macro's parameter list after its `(` (the token `open`) into
    /// `params` and `index`; whether the macro is variadic.
    fn define_params(
        &mut self,
        r: &mut DefReader,
        open: Tok,
        params: &mut Vec<Sym>,
        index: &mut HashMap<Sym, u16, FxBuild>,
    ) -> PResult<bool> {
        let mut prev = open;
        let mut expect_param = true;
        loop {
            let Some(t) = self.def_next(r)? else {
                return self.err_tok(&prev, "missing ')' in macro parameter list", "expected ')' after this");
            };
            prev = t;
            let s = self.it.str(t.sym).to_string();
            if expect_param {
                if t.kind == TK::Ident {
                    if index.contains_key(&t.sym) {
                        return self.err_tok(&t, format!("duplicate macro parameter \"{s}\""), "already a parameter");
                    }
                    if t.sym == self.syms.va_args {
                        return self.err_tok(&t, "__VA_ARGS__ can not be used as a parameter name", "here");
                    }
                    if params.len() + 1 >= NO_PARAM as usize {
                        return self.err_tok(&t, "too many macro parameters", "here");
                    }
                    index.insert(t.sym, params.len() as u16);
                    params.push(t.sym);
                    expect_param = false;
                    continue;
                }
                if s == "..." {
                    index.insert(self.syms.va_args, params.len() as u16);
                    params.push(self.syms.va_args);
                    self.close_variadic(r, &t)?;
                    return Ok(true);
                }
                if s == ")" && params.is_empty() {
                    return Ok(false);
                }
                return self.err_tok(
                    &t,
                    format!("expected parameter name, found \"{s}\""),
                    "expected a parameter name",
                );
            }
            match s.as_str() {
                "," => expect_param = true,
                ")" => return Ok(false),
                "..." => {
                    // GNU named variadic parameter: `args...`.
                    self.close_variadic(r, &t)?;
                    return Ok(true);
                }
                _ => return self.err_tok(&t, format!("expected ',' or ')', found \"{s}\""), "expected ',' or ')'"),
            }
        }
    }

    /// The `)` that must follow a parameter list's `...` (the token `dots`).
    fn close_variadic(&mut self, r: &mut DefReader, dots: &Tok) -> PResult<()> {
        let Some(c) = self.def_next(r)? else {
            return self.err_tok(dots, "missing ')' in macro parameter list", "expected ')' after this");
        };
        if !(c.kind == TK::Punct && c.sym == self.syms.rparen) {
            return self.err_tok(&c, "expected ')' after \"...\"", "expected ')'");
        }
        Ok(())
    }

    /// Warns that macro `name` is redefined, pointing at definition `old` too.
    fn warn_redefined(&mut self, name: &Tok, old: u32) {
        let prev = &self.defs[old as usize];
        let n = self.it.str(name.sym).to_string();
        let mut labels = self.tok_labels(name, "redefined here");
        if prev.ctx != NONE {
            if let Some(c) = self.map.ctxs.get(prev.ctx as usize) {
                let r = c.source.original_range(prev.site.start as usize..prev.site.end as usize);
                labels.push(Label::secondary(c.file, r).with_message("previous definition"));
            }
        }
        self.warn(format!("\"{n}\" redefined"), labels);
    }

    /// Reads a replacement list from `r`: `#` and `##` made flags, parameters numbered,
    /// `__VA_OPT__` checked (cpp's errors: nested, without `(`, unterminated). Keeps at most
    /// `keep` tokens; past that it only checks and counts, and the list is read again from
    /// its source when first expanded ([`Pp::body_of`]). `warn`: report warnings (the first
    /// reading does, a re-reading does not).
    fn read_body(&mut self, r: &mut DefReader, shape: &Shape, keep: usize, warn: bool) -> PResult<Body> {
        let mut body: Option<Vec<Tok>> = Some(Vec::new());
        let mut len = 0usize;
        let mut start = None;
        let (mut pastes, mut va_opt) = (false, false);
        // The `__VA_OPT__` being read and the depth of parentheses inside it.
        let mut open_va_opt: Option<(Tok, usize)> = None;
        while let Some(mut t) = self.def_next(r)? {
            if start.is_none() {
                start = Some(t.src);
            }
            // Where errors point: the token as it is in the file.
            let mut site = t;
            t.flags |= FROM_DEF;
            if len == 0 {
                t.flags &= !WHITE;
            }
            let s = self.it.str(t.sym);
            let is_paste = t.kind == TK::Punct && (s == "##" || s == "%:%:");
            let is_hash = t.kind == TK::Punct && (s == "#" || s == "%:");
            if is_paste {
                if len == 0 || self.def_peek(r)?.is_none() {
                    return self.err_tok(&site, "'##' cannot appear at either end of a macro expansion", "here");
                }
                if let Some(last) = body.as_mut().and_then(|b| b.last_mut()) {
                    last.flags |= PASTE_LEFT;
                }
                pastes = true;
                continue;
            }
            let mut va_opt_name = shape.variadic && t.kind == TK::Ident && t.sym == self.syms.va_opt;
            if shape.func && is_hash {
                va_opt_name = self.body_stringify(r, shape, &mut t, &mut site)?;
            } else if t.kind == TK::Ident {
                self.body_ident(shape, &mut t, &site, warn);
            }
            if va_opt_name {
                if open_va_opt.is_some() {
                    return self.err_tok(&site, "__VA_OPT__ may not appear in a __VA_OPT__", "nested here");
                }
                let opens = self.def_peek(r)?.is_some_and(|n| n.kind == TK::Punct && n.sym == self.syms.lparen);
                if !opens {
                    return self.err_tok(&site, "__VA_OPT__ must be followed by an open parenthesis", "here");
                }
                open_va_opt = Some((site, 0));
                va_opt = true;
            } else if let Some((_, depth)) = open_va_opt.as_mut() {
                if t.kind == TK::Punct && t.sym == self.syms.lparen {
                    *depth += 1;
                } else if t.kind == TK::Punct && t.sym == self.syms.rparen {
                    *depth -= 1;
                    if *depth == 0 {
                        open_va_opt = None;
                    }
                }
            }
            len += 1;
            keep_body_token(&mut body, r, t, keep);
        }
        if let Some((t, _)) = open_va_opt {
            return self.err_tok(&t, "unterminated __VA_OPT__", "this __VA_OPT__ is never closed");
        }
        // GNU `, ## __VA_ARGS__`.
        if let (true, Some(b)) = (shape.variadic, body.as_mut()) {
            mark_va_commas(b, (shape.params.len() - 1) as u16, self.syms.comma);
        }
        Ok(Body { toks: body, len, start, pastes, va_opt })
    }

    /// A `#` in a function-like macro's body (`t`, errors at `site`): with the parameter or
    /// `__VA_OPT__` after it, it becomes one stringifying token. Whether that is a
    /// `__VA_OPT__`.
    #[inline]
    fn body_stringify(&mut self, r: &mut DefReader, shape: &Shape, t: &mut Tok, site: &mut Tok) -> PResult<bool> {
        let next = self.def_peek(r)?;
        if let Some(n) = next.filter(|n| shape.variadic && n.kind == TK::Ident && n.sym == self.syms.va_opt) {
            // `#__VA_OPT__(...)`: stringified when the __VA_OPT__ is resolved.
            self.def_next(r)?;
            *site = n;
            *t = Tok { flags: (t.flags & WHITE) | STRINGIFY | FROM_DEF, ..n };
            return Ok(true);
        }
        match next.filter(|n| n.kind == TK::Ident).and_then(|n| shape.index.get(&n.sym).copied()) {
            Some(pi) => {
                let Some(n) = self.def_next(r)? else {
                    return self.err_tok(site, "'#' is not followed by a macro parameter", "here");
                };
                *t = Tok { param: pi, flags: (t.flags & WHITE) | STRINGIFY | FROM_DEF, ..n };
                Ok(false)
            }
            None => self.err_tok(site, "'#' is not followed by a macro parameter", "here"),
        }
    }

    /// An identifier in a body: numbered when it names a parameter; cpp's warnings for
    /// `__VA_ARGS__` and `__VA_OPT__` outside a variadic macro when `warn`.
    #[inline]
    fn body_ident(&mut self, shape: &Shape, t: &mut Tok, site: &Tok, warn: bool) {
        if shape.func {
            if let Some(pi) = shape.index.get(&t.sym).copied() {
                t.param = pi;
            }
        }
        if !warn || t.param != NO_PARAM {
            return;
        }
        let named_variadic = shape.variadic && shape.params.last() != Some(&self.syms.va_args);
        if t.sym == self.syms.va_args && (!shape.variadic || named_variadic) {
            let l = self.tok_labels(site, "here");
            self.warn("__VA_ARGS__ can only appear in the expansion of a C99 variadic macro", l);
        }
        if t.sym == self.syms.va_opt && !shape.variadic {
            // cpp's warning; the name stays a plain identifier.
            let l = self.tok_labels(site, "here");
            self.warn("__VA_OPT__ can only appear in the expansion of a C++20 variadic macro", l);
        }
    }

    /// The replacement list of macro `m`, read again from its source first if it was too long
    /// to keep ([`LazyBody`]). A list that would exceed the expansion budget is an error
    /// before it is read.
    pub(super) fn body_of(&mut self, m: u32, at: &Tok) -> PResult<Arc<[Tok]>> {
        let mac = &self.defs[m as usize];
        let Some(lazy) = mac.lazy else {
            return Ok(mac.body.clone());
        };
        if self.made.saturating_add(lazy.len) > self.token_limit() {
            let limit = self.token_limit();
            return self.err_tok(at, format!("macro expansion makes more than {limit} tokens"), "while expanding this");
        }
        self.read_lazy(m)
    }

    /// The replacement list of macro `m`, read again from its source if it was not kept.
    fn read_lazy(&mut self, m: u32) -> PResult<Arc<[Tok]>> {
        let mac = &self.defs[m as usize];
        let Some(lazy) = mac.lazy else {
            return Ok(mac.body.clone());
        };
        let Some(source) = self.map.ctxs.get(lazy.ctx as usize).map(|c| c.source.clone()) else {
            return Ok(mac.body.clone());
        };
        let params = mac.params.clone();
        let (func, variadic) = (mac.func, mac.variadic);
        let index: HashMap<Sym, u16, FxBuild> = params.iter().enumerate().map(|(i, &p)| (p, i as u16)).collect();
        let mut r = DefReader {
            src: DefSource::Line { source, ctx: lazy.ctx, pos: lazy.start as usize, intern: true },
            peeked: None,
        };
        let shape = Shape { func, variadic, params: &params, index: &index };
        let body = self.read_body(&mut r, &shape, usize::MAX, false)?;
        let toks: Arc<[Tok]> = body.toks.unwrap_or_default().into();
        let mac = &mut self.defs[m as usize];
        mac.body = toks.clone();
        mac.lazy = None;
        Ok(toks)
    }

    /// Whether two long replacement lists have the same tokens with the same whitespace
    /// between them, read from their text side by side.
    fn same_text_tokens(&mut self, p: LazyBody, q: LazyBody) -> PResult<bool> {
        let source = |c: u32| self.map.ctxs.get(c as usize).map(|c| c.source.clone());
        let (Some(sp), Some(sq)) = (source(p.ctx), source(q.ctx)) else {
            return Ok(false);
        };
        let (mut i, mut j) = (p.start as usize, q.start as usize);
        let mut first = true;
        loop {
            let x = self.line_token(&sp, p.ctx, &mut i, false)?;
            let y = self.line_token(&sq, q.ctx, &mut j, false)?;
            match (x, y) {
                (None, None) => return Ok(true),
                (Some(x), Some(y)) => {
                    let (a, b) = (&sp.text().as_bytes()[x.src as usize..], &sq.text().as_bytes()[y.src as usize..]);
                    let same = x.len == y.len && a[..x.len as usize] == b[..y.len as usize];
                    if !same || (!first && (x.flags & WHITE) != (y.flags & WHITE)) {
                        return Ok(false);
                    }
                    first = false;
                }
                _ => return Ok(false),
            }
        }
    }

    /// Whether definitions `a` and `b` are the same (cpp's rule: same parameters, same
    /// tokens with the same whitespace between them). Long bodies are read for it.
    pub(super) fn same_definition(&mut self, a: u32, b: u32) -> PResult<bool> {
        const CMP: u8 = WHITE | PASTE_LEFT | STRINGIFY;
        let (x, y) = (&self.defs[a as usize], &self.defs[b as usize]);
        let len = |m: &Macro| m.lazy.map_or(m.body.len(), |l| l.len);
        if x.builtin != y.builtin
            || x.func != y.func
            || x.variadic != y.variadic
            || x.params != y.params
            || len(x) != len(y)
        {
            return Ok(false);
        }
        if let (Some(p), Some(q)) = (x.lazy, y.lazy) {
            // Two long bodies (a header read twice): compared as text, never made tokens.
            return self.same_text_tokens(p, q);
        }
        let (x, y) = (self.read_lazy(a)?, self.read_lazy(b)?);
        Ok(x.iter()
            .zip(y.iter())
            .enumerate()
            .all(|(i, (x, y))| x.sym == y.sym && x.param == y.param && (i == 0 || (x.flags & CMP) == (y.flags & CMP))))
    }
}

/// Past the whitespace and whole block comments from `p` at a line's start.
#[inline]
fn skip_blank(source: &SourceFile, mut p: usize) -> usize {
    loop {
        let (kind, len) = source.lex(p);
        match kind {
            Kind::Space | Kind::BlockComment { terminated: true } => p += len,
            _ => return p,
        }
    }
}

/// Skips to the start of the next line from `p`, treating comments and literals as cpp does
/// in a skipped group (a block comment may run over several lines). `Err(at)`: a block
/// comment at `at` is never closed.
fn skip_line(bytes: &[u8], mut p: usize) -> Result<usize, usize> {
    while p < bytes.len() {
        match bytes[p] {
            b'\n' => return Ok(p + 1),
            b'/' | b'"' | b'\'' | b'L' | b'u' | b'U' => {
                let (kind, len) = lexer::next(bytes, p);
                match kind {
                    Kind::LineComment => return Ok(lexer::memchr_nl(bytes, p) + 1),
                    Kind::BlockComment { terminated: false } => return Err(p),
                    _ => p += len.max(1),
                }
            }
            _ => p += 1,
        }
    }
    Ok(bytes.len())
}

/// Appends body token `t` while fewer than `keep` are kept; past that the body is only
/// checked, so it is dropped and the rest of its words need not be interned.
#[inline]
fn keep_body_token(body: &mut Option<Vec<Tok>>, r: &mut DefReader, t: Tok, keep: usize) {
    let Some(b) = body.as_mut() else {
        return;
    };
    if b.len() < keep {
        b.push(t);
        return;
    }
    *body = None;
    if let DefSource::Line { intern, .. } = &mut r.src {
        *intern = false;
    }
}

/// Marks GNU `, ## __VA_ARGS__` commas (`va` is the variadic parameter's number): the comma
/// goes when the variable arguments are empty.
fn mark_va_commas(b: &mut [Tok], va: u16, comma: Sym) {
    for k in 0..b.len().saturating_sub(1) {
        if b[k].kind == TK::Punct
            && b[k].sym == comma
            && b[k].flags & PASTE_LEFT != 0
            && b[k + 1].param == va
            && b[k + 1].flags & (STRINGIFY | PASTE_LEFT) == 0
        {
            b[k].flags |= VA_COMMA;
        }
    }
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

/// The name of a directive whose `#` ends before `pos`: skips spaces and closed block
/// comments, then returns (the identifier or "" when there is none, its offset, its length).
fn directive_name(text: &str, mut pos: usize) -> (&str, usize, usize) {
    let bytes = text.as_bytes();
    loop {
        let (kind, len) = lexer::next(bytes, pos);
        match kind {
            Kind::Space | Kind::BlockComment { terminated: true } => pos += len,
            _ => break,
        }
    }
    let (kind, len) = lexer::next(bytes, pos);
    let name = if kind == Kind::Ident { &text[pos..pos + len] } else { "" };
    (name, pos, len)
}

/// Where [`Pp::parse_define`] reads tokens, with one token of lookahead.
pub(super) struct DefReader {
    src: DefSource,
    /// `Some(t)`: the next token (`Some(None)`: the end) was already read.
    peeked: Option<Option<Tok>>,
}

impl DefReader {
    pub(super) fn list(toks: Vec<Tok>) -> DefReader {
        DefReader { src: DefSource::List { toks, at: 0 }, peeked: None }
    }
}

enum DefSource {
    /// Tokens already lexed (predefined macros, `-D`).
    List { toks: Vec<Tok>, at: usize },
    /// A directive line, lexed as it is read.
    Line { source: Arc<SourceFile>, ctx: u32, pos: usize, intern: bool },
}

/// A macro's parameters, as [`Pp::read_body`] needs them.
#[derive(Clone, Copy)]
struct Shape<'p> {
    func: bool,
    variadic: bool,
    params: &'p [Sym],
    index: &'p HashMap<Sym, u16, FxBuild>,
}

/// What [`Pp::read_body`] read.
struct Body {
    /// The tokens, `None` when there were more than it keeps.
    toks: Option<Vec<Tok>>,
    len: usize,
    /// Spliced offset of the first token.
    start: Option<u32>,
    pastes: bool,
    va_opt: bool,
}
