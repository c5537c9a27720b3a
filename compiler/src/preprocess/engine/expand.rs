//! Macro expansion: the token sources (contexts over the file), argument collection and
//! pre-expansion, substitution with `#` and `##`, cpp's padding tokens, builtins.

use super::*;

impl Pp<'_> {
    // -----------------------------------------------------------------------------------------
    // Token sources

    /// The next token of the current file, for argument collection: skips whitespace and
    /// comments (setting `WHITE`), runs directives at line starts. `Eof` at the file's end.
    pub(super) fn lex_file_token(&mut self) -> PResult<Tok> {
        let mut white = false;
        loop {
            let Some(frame) = self.frames.last_mut() else {
                return Ok(Tok::eof());
            };
            let source = frame.source.clone();
            let bytes = source.text().as_bytes();
            let pos = frame.pos;
            let (kind, len) = source.lex(pos);
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
                    return self.err_at(
                        ctx,
                        pos as u32..pos as u32 + 2,
                        "unterminated comment",
                        "this comment is never closed",
                    );
                }
                Kind::Punct if frame.bol && lexer::is_directive_hash(&bytes[pos..pos + len]) => {
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
                        return self.err_at(
                            ctx,
                            pos as u32..pos as u32 + 1,
                            "missing terminating \" character",
                            "this string is never closed",
                        );
                    }
                    let sym = self.it.intern(&source.text()[pos..pos + len]);
                    if let Some((c, _, e)) = self.inv.as_mut() {
                        if *c == ctx {
                            *e = (*e).max((pos + len) as u32);
                        }
                    }
                    let flags = if white { WHITE } else { 0 };
                    return Ok(Tok {
                        sym,
                        ctx,
                        src: pos as u32,
                        len: len as u32,
                        param: NO_PARAM,
                        kind: tk_of(kind),
                        flags,
                    });
                }
            }
        }
    }

    /// The next token from the contexts (popping finished ones and re-enabling their
    /// macros), else from the file when `file_ok`. `None`: no context and not `file_ok`.
    pub(super) fn next_raw(&mut self, file_ok: bool) -> PResult<Option<Tok>> {
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
    pub(super) fn peek_lparen(&self) -> bool {
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
    pub(super) fn get_token(&mut self, file_ok: bool) -> PResult<Option<Tok>> {
        loop {
            let Some(mut t) = self.next_raw(file_ok)? else {
                return Ok(None);
            };
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
    pub(super) fn get_real_token(&mut self, file_ok: bool) -> PResult<Tok> {
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

    /// Most tokens expansion may make: a million plus a few per byte of input read, and never
    /// more than the output limit allows. A macro bomb in a small file stops within
    /// milliseconds; a large real input is never cut short.
    pub(super) fn token_limit(&self) -> usize {
        (1usize << 20).saturating_add(self.input_bytes.saturating_mul(8)).min(token_budget(self.opts))
    }

    /// Counts `n` tokens made by expansion against [`Pp::token_limit`].
    pub(super) fn spend(&mut self, n: usize, at: &Tok) -> PResult<()> {
        self.made += n;
        if self.made > self.token_limit() {
            let limit = self.token_limit();
            return self.err_tok(at, format!("macro expansion makes more than {limit} tokens"), "while expanding this");
        }
        Ok(())
    }

    /// Counts `n` bytes of text made by `#` and `##` against the output limit: a body that
    /// stringifies or pastes long arguments many times stops there, not after the work.
    pub(super) fn spend_bytes(&mut self, n: usize, at: &Tok) -> PResult<()> {
        self.made_bytes = self.made_bytes.saturating_add(n);
        if self.made_bytes > self.opts.max_output_bytes {
            let limit = self.opts.max_output_bytes;
            return self.err_tok(
                at,
                format!("macro expansion makes more than {limit} bytes of stringified or pasted text"),
                "while expanding this",
            );
        }
        Ok(())
    }

    /// An empty token vector, reusing the storage of finished contexts.
    pub(super) fn take_vec(&mut self) -> Vec<Tok> {
        self.pool.pop().unwrap_or_default()
    }

    pub(super) fn give_vec(&mut self, mut v: Vec<Tok>) {
        if self.pool.len() < 64 && v.capacity() <= 4096 {
            v.clear();
            self.pool.push(v);
        }
    }

    pub(super) fn push_context(&mut self, toks: Vec<Tok>, mac: u32, barrier: bool, at: &Tok) -> PResult<()> {
        if self.stack.len() >= self.opts.max_expansion_depth {
            return self.err_tok(
                at,
                format!("macro expansion nested deeper than {} levels", self.opts.max_expansion_depth),
                "while expanding this",
            );
        }
        self.spend(toks.len(), at)?;
        if let Some(m) = self.defs.get_mut(mac as usize) {
            m.disabled = true;
        }
        self.stack.push(Context { toks, pos: 0, mac, barrier });
        Ok(())
    }

    /// Starts expanding macro `m` named by `name`. False if it is function-like and no `(`
    /// follows (nothing consumed).
    pub(super) fn enter_macro(&mut self, name: Tok, m: u32) -> PResult<bool> {
        let mac = &self.defs[m as usize];
        if mac.builtin != Builtin::None {
            return self.builtin(name, mac.builtin);
        }
        if !mac.func {
            let body = self.body_of(m, &name)?;
            let mac = &self.defs[m as usize];
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
                return Err(Error::new(
                    format!("macro \"{name_str}\" requires {nparams} arguments, but only {} given", args.len()),
                    labels,
                ));
            }
        } else if args.len() > nparams && !(nparams == 0 && args.len() == 1 && args[0].is_empty()) {
            let labels = self.invocation_labels(&name, "this invocation");
            return Err(Error::new(
                format!("macro \"{name_str}\" passed {} arguments, but takes just {nparams}", args.len()),
                labels,
            ));
        }
        if nparams == 0 {
            args.clear();
        }
        let absent_va = variadic && args.len() < nparams;
        let mut body = self.body_of(m, &name)?;
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
    pub(super) fn collect_args(&mut self, name: &Tok, m: u32) -> PResult<Vec<Vec<Tok>>> {
        let nparams = self.defs[m as usize].params.len();
        let variadic = self.defs[m as usize].variadic;
        let mut args: Vec<Vec<Tok>> = vec![Vec::new()];
        // Tokens collected so far, kept as a running count: summing the arguments at each
        // token made a call with many arguments quadratic.
        let mut collected = 0usize;
        let mut depth = 0usize;
        loop {
            let Some(mut t) = self.next_raw(true)? else {
                return self.unterminated(name);
            };
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
            collected += 1;
            if self.made + collected > self.token_limit() {
                return self.err_tok(
                    name,
                    "macro arguments exceed the expansion budget",
                    "while collecting these arguments",
                );
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

    pub(super) fn unterminated<T>(&self, name: &Tok) -> PResult<T> {
        let n = self.it.str(name.sym).to_string();
        self.err_tok(
            name,
            format!("unterminated argument list invoking macro \"{n}\""),
            "this invocation is never closed",
        )
    }

    /// Fully macro-expands an argument in isolation.
    pub(super) fn expand_arg(&mut self, arg: &[Tok], at: &Tok) -> PResult<Vec<Tok>> {
        // Nothing to expand: no identifiers (the common case of numbers and punctuation).
        if !arg.iter().any(|t| t.kind == TK::Ident && t.flags & NO_EXPAND == 0 && self.macro_idx(t.sym) != NONE) {
            self.spend(arg.len(), at)?;
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
    pub(super) fn substitute(
        &mut self,
        m: u32,
        name: &Tok,
        body: &[Tok],
        args: &[Vec<Tok>],
        expanded: &mut [Option<Vec<Tok>>],
    ) -> PResult<Vec<Tok>> {
        let mut toks = self.substitute_args(m, name, body, args, expanded, false)?;
        if toks.iter().all(|t| t.kind == TK::Placemarker) {
            toks.clear();
        }
        Ok(toks)
    }

    /// Builds a replacement list: parameters replaced (stringified, raw next to `##`, else
    /// expanded), then `##` applied left to right.
    pub(super) fn substitute_args(
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
        // `#x` of each parameter, made once however often the body names it.
        let mut strung: Vec<Option<Sym>> = Vec::new();
        let mut i = 0;
        while i < body.len() {
            // A body naming a long argument many times could make a huge list before the
            // budget sees it (checked here, as it grows).
            if self.made + out.len() > self.token_limit() {
                let limit = self.token_limit();
                return self.err_tok(
                    name,
                    format!("macro expansion makes more than {limit} tokens"),
                    "while expanding this",
                );
            }
            let b = body[i];
            if b.flags & VA_COMMA != 0 {
                self.push_va_comma(&mut out, b, body[i + 1], args, absent_va);
                i += 2;
                continue;
            }
            if b.param == NO_PARAM {
                out.push(b);
            } else if b.flags & STRINGIFY != 0 {
                self.push_stringified(&mut out, b, args, &mut strung, name)?;
            } else {
                let prev = i.checked_sub(1).map(|k| body[k]);
                self.push_arg(&mut out, b, prev, args, expanded, name)?;
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

    /// GNU `, ## __VA_ARGS__` (the comma `b`, the parameter `p`): absent variable arguments
    /// drop the comma; empty ones leave it (pasted with a placemarker); otherwise the comma
    /// stays unpasted and the arguments go in unexpanded, as `##` operands do.
    #[inline]
    fn push_va_comma(&self, out: &mut Vec<Tok>, b: Tok, p: Tok, args: &[Vec<Tok>], absent_va: bool) {
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
    }

    /// `#x` (the body token `b`): the argument as one string literal, made once per
    /// parameter and kept in `strung`.
    #[inline]
    fn push_stringified(
        &mut self,
        out: &mut Vec<Tok>,
        b: Tok,
        args: &[Vec<Tok>],
        strung: &mut Vec<Option<Sym>>,
        name: &Tok,
    ) -> PResult<()> {
        let pi = b.param as usize;
        if strung.len() <= pi {
            strung.resize(pi + 1, None);
        }
        let sym = match strung[pi] {
            Some(sym) => sym,
            None => {
                let s = self.stringify(args.get(pi).map_or(&[][..], |a| &a[..]));
                self.spend_bytes(s.len(), name)?;
                let sym = self.it.intern(&s);
                strung[pi] = Some(sym);
                sym
            }
        };
        out.push(Tok { sym, kind: TK::Str, param: NO_PARAM, flags: (b.flags & (WHITE | PASTE_LEFT)) | FROM_DEF, ..b });
        Ok(())
    }

    /// A parameter (the body token `b`, after `prev`) replaced by its argument: raw next to
    /// `##` (a placemarker when empty), else fully expanded, between cpp's paddings.
    #[inline]
    fn push_arg(
        &mut self,
        out: &mut Vec<Tok>,
        b: Tok,
        prev: Option<Tok>,
        args: &[Vec<Tok>],
        expanded: &mut [Option<Vec<Tok>>],
        name: &Tok,
    ) -> PResult<()> {
        let pi = b.param as usize;
        let prev_pastes = prev.is_some_and(|p| p.flags & PASTE_LEFT != 0);
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
        if pad && prev.is_some() && !prev_pastes {
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
        Ok(())
    }

    /// Replaces each `__VA_OPT__(...)` of a body by its contents when the variable arguments
    /// expand to some tokens, else by a placemarker (C2x, as GCC 12 does in every mode).
    pub(super) fn resolve_va_opt(
        &mut self,
        body: &[Tok],
        va: usize,
        args: &[Vec<Tok>],
        expanded: &mut [Option<Vec<Tok>>],
        name: &Tok,
    ) -> PResult<Vec<Tok>> {
        self.expanded_arg(va, args, expanded, name)?;
        let present = expanded
            .get(va)
            .and_then(|e| e.as_ref())
            .is_some_and(|e| e.iter().any(|t| !matches!(t.kind, TK::Placemarker | TK::Padding)));
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
                let toks =
                    if present { self.substitute_args(NONE, name, inner, args, expanded, false)? } else { Vec::new() };
                let text = self.stringify(&toks);
                self.spend_bytes(text.len(), name)?;
                let sym = self.it.intern(&text);
                out.push(Tok {
                    sym,
                    kind: TK::Str,
                    param: NO_PARAM,
                    flags: (t.flags & WHITE) | close_paste | FROM_DEF,
                    ..t
                });
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
    pub(super) fn expanded_arg(
        &mut self,
        pi: usize,
        args: &[Vec<Tok>],
        expanded: &mut [Option<Vec<Tok>>],
        name: &Tok,
    ) -> PResult<()> {
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
    ///
    /// A chain `a ## b ## c ...` grows one spelling in place and interns only its result,
    /// and each step checks only the text it appends where it can (an identifier or number
    /// taking more identifier characters), so a chain of n pastes costs O(its length), not
    /// O(n²) time and memory.
    pub(super) fn paste_all(&mut self, toks: Vec<Tok>, name: &Tok) -> PResult<Vec<Tok>> {
        let mut out: Vec<Tok> = Vec::with_capacity(toks.len());
        let mut iter = toks.into_iter();
        let mut acc = String::new();
        while let Some(mut lhs) = iter.next() {
            if lhs.flags & PASTE_LEFT == 0 {
                out.push(lhs);
                continue;
            }
            acc.clear();
            acc.push_str(self.it.str(lhs.sym));
            let mut changed = false;
            while lhs.flags & PASTE_LEFT != 0 {
                let Some(rhs) = iter.next() else {
                    lhs.flags &= !PASTE_LEFT;
                    break;
                };
                changed |= self.paste(&mut lhs, &mut acc, rhs, name)?;
            }
            if changed {
                lhs.sym = self.it.intern(&acc);
            }
            out.push(lhs);
        }
        Ok(out)
    }

    /// One `##` step: `lhs` (spelled `acc`) joins `rhs`. True when the spelling changed
    /// (the caller interns it at the end of the chain).
    pub(super) fn paste(&mut self, lhs: &mut Tok, acc: &mut String, rhs: Tok, name: &Tok) -> PResult<bool> {
        let keep = (lhs.flags & WHITE) | (rhs.flags & PASTE_LEFT);
        if rhs.kind == TK::Placemarker {
            lhs.flags = (lhs.flags & !PASTE_LEFT) | keep;
            return Ok(false);
        }
        if lhs.kind == TK::Placemarker {
            *lhs = Tok { flags: (rhs.flags & !(PASTE_LEFT | WHITE)) | keep, ..rhs };
            acc.clear();
            acc.push_str(self.it.str(rhs.sym));
            return Ok(false);
        }
        self.spend_bytes(self.it.str(rhs.sym).len(), name)?;
        let right = self.it.str(rhs.sym);
        let kind = match continues(lhs.kind, acc.as_bytes(), right.as_bytes()) {
            Some(kind) => kind,
            None => {
                let joined = format!("{acc}{right}");
                let (kind, len) = lexer::next(joined.as_bytes(), 0);
                let valid = len == joined.len()
                    && !matches!(
                        kind,
                        Kind::Space | Kind::Newline | Kind::LineComment | Kind::BlockComment { .. } | Kind::Eof
                    )
                    && !matches!(kind, Kind::Str { terminated: false } | Kind::Char { terminated: false });
                if !valid {
                    let msg = format!("pasting \"{acc}\" and \"{right}\" does not give a valid preprocessing token");
                    let at = *lhs;
                    return self.err_tok(&at, msg, "in this expansion");
                }
                tk_of(kind)
            }
        };
        acc.push_str(right);
        let mut flags = keep | FROM_DEF;
        if lhs.flags & FROM_DEF == 0 && rhs.flags & FROM_DEF == 0 && lhs.ctx == rhs.ctx && lhs.src + lhs.len == rhs.src
        {
            flags &= !FROM_DEF;
        }
        lhs.kind = kind;
        lhs.flags = flags;
        lhs.param = NO_PARAM;
        if flags & FROM_DEF == 0 {
            lhs.len = acc.len() as u32;
        }
        Ok(true)
    }

    /// `#x`: the spelling of the argument, spaces normalized, `"` and `\` escaped in literals.
    pub(super) fn stringify(&self, arg: &[Tok]) -> String {
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
        // cpp: "invalid string literal, ignoring final '\\'".
        let trailing = s.len() - s.trim_end_matches('\\').len();
        if trailing % 2 == 1 {
            s.pop();
        }
        s.push('"');
        s
    }

    pub(super) fn current_line(&self, t: &Tok) -> i64 {
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
            Some(c) => c.source.line(c.source.original_offset(src as usize)) as i64 + delta,
            None => 0,
        }
    }

    pub(super) fn builtin(&mut self, name: Tok, b: Builtin) -> PResult<bool> {
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
                return self.err_tok(
                    &name,
                    format!("\"{n}\" used outside of preprocessing directive"),
                    "only in #if and #elif",
                );
            }
            Builtin::Date | Builtin::Time => {
                let (date, time) = date_time();
                quote(if b == Builtin::Date { &date } else { &time })
            }
            Builtin::None => return Ok(false),
        };
        let kind = if matches!(b, Builtin::File | Builtin::BaseFile | Builtin::Date | Builtin::Time) {
            TK::Str
        } else {
            TK::Number
        };
        let sym = self.it.intern(&text);
        let t = Tok { sym, kind, flags: (name.flags & WHITE) | FROM_DEF, param: NO_PARAM, ..name };
        self.push_context(vec![t], NONE, false, &name)?;
        Ok(true)
    }

    /// `_Pragma("...")`: written out as a `#pragma` line, like cpp does.
    pub(super) fn pragma_operator(&mut self, name: Tok) -> PResult<bool> {
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
}

/// The kind of `left` followed by `right` when that is plainly one token of `left`'s kind
/// (an identifier or pp-number taking more of its characters), checked on `right` alone;
/// `None`: lex the whole.
fn continues(kind: TK, left: &[u8], right: &[u8]) -> Option<TK> {
    match kind {
        TK::Ident if !right.is_empty() && right.iter().all(|&c| lexer::is_ident_continue(c)) => Some(TK::Ident),
        TK::Number if !right.is_empty() => {
            let mut prev = *left.last()?;
            for &c in right {
                let sign = matches!(c, b'+' | b'-') && matches!(prev, b'e' | b'E' | b'p' | b'P');
                if !(sign || lexer::is_ident_continue(c) || c == b'.') {
                    return None;
                }
                prev = c;
            }
            Some(TK::Number)
        }
        _ => None,
    }
}

/// `__DATE__` and `__TIME__` of now (UTC, or `SOURCE_DATE_EPOCH` like GCC).
fn date_time() -> (String, String) {
    let secs = std::env::var("SOURCE_DATE_EPOCH").ok().and_then(|v| v.parse::<i64>().ok()).unwrap_or_else(|| {
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
