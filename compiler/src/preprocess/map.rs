//! The source map: output byte ranges back to the text they came from.
//!
//! Kept as runs: one entry per run of copied text (any number of lines) and one per token a
//! macro made, never one per byte.

use std::ops::Range;
use std::sync::Arc;

use codespan_reporting::diagnostic::Label;

use super::source::{FileId, SourceFile};

/// No include context / no location.
pub(crate) const NONE: u32 = u32::MAX;

/// One file inclusion: which file, and the `#include` directive that brought it in.
#[derive(Clone, Debug)]
pub(crate) struct IncludeCtx {
    pub file: FileId,
    pub source: Arc<SourceFile>,
    /// The including context (`NONE` for the main file).
    pub parent: u32,
    /// The directive's span (spliced offsets) in the parent's file.
    pub site: Range<u32>,
}

#[derive(Clone, Copy, Debug)]
pub(crate) struct Entry {
    /// First output byte of the run.
    pub out: u32,
    /// Include context of the text (`NONE`: no source location).
    pub ctx: u32,
    /// Copied text: spliced offsets `src..end` of the run. Macro-made text: the invocation.
    pub src: u32,
    pub end: u32,
    /// Macro-made text: the context and spliced offset of the token in the macro's
    /// definition (`def_ctx == NONE` for a definition given in [`super::Options::defines`]).
    pub def_ctx: u32,
    pub def_src: u32,
    pub def_len: u32,
    pub is_macro: bool,
}

/// Where each byte of a preprocessed output came from.
#[derive(Clone, Debug, Default)]
pub struct SourceMap {
    pub(crate) entries: Vec<Entry>,
    pub(crate) ctxs: Vec<IncludeCtx>,
}

/// The source of one output byte.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Origin {
    /// The file it comes from.
    pub file: FileId,
    /// Bytes in that file: the copied text, or the whole macro invocation for macro-made text.
    pub span: Range<usize>,
    /// 1-based line and column (in characters) of `span.start`.
    pub line: usize,
    /// (See `line`.)
    pub column: usize,
    /// For macro-made text: the token in the macro's definition it was made from.
    pub macro_definition: Option<(FileId, Range<usize>)>,
    /// The `#include` directives that led to `file`, innermost first.
    pub include_chain: Vec<(FileId, Range<usize>)>,
}

impl SourceMap {
    fn entry_at(&self, offset: usize) -> Option<&Entry> {
        let i = self.entries.partition_point(|e| e.out as usize <= offset);
        self.entries.get(i.checked_sub(1)?)
    }

    /// Where output byte `offset` came from (`None` past the end of the output or for text
    /// with no source, like a predefined macro's expansion outside any file).
    pub fn origin(&self, offset: usize) -> Option<Origin> {
        let e = self.entry_at(offset)?;
        let ctx = self.ctxs.get(e.ctx as usize)?;
        let f = &ctx.source;
        let spliced = if e.is_macro {
            e.src as usize..e.end as usize
        } else {
            let at = (e.src as usize + (offset - e.out as usize)).min(e.end.max(e.src) as usize);
            let end = (at + 1).min(e.end as usize).max(at);
            at..end
        };
        let span = f.original_range(spliced);
        let (line, column) = f.line_col(span.start);
        let macro_definition = if e.is_macro {
            self.ctxs.get(e.def_ctx as usize).map(|d| {
                let r = d.source.original_range(e.def_src as usize..(e.def_src + e.def_len) as usize);
                (d.file, r)
            })
        } else {
            None
        };
        Some(Origin { file: ctx.file, span, line, column, macro_definition, include_chain: self.chain(e.ctx) })
    }

    /// The include chain of a context, innermost first.
    pub(crate) fn chain(&self, ctx: u32) -> Vec<(FileId, Range<usize>)> {
        let mut out = Vec::new();
        let mut c = self.ctxs.get(ctx as usize);
        while let Some(x) = c {
            let Some(p) = self.ctxs.get(x.parent as usize) else {
                break;
            };
            out.push((p.file, p.source.original_range(x.site.start as usize..x.site.end as usize)));
            c = Some(p);
        }
        out
    }

    /// codespan labels for an output byte range: a primary label on the original text (the
    /// invocation for macro-made text), a secondary "in this macro's definition" where
    /// macro-made, and "included from here" for each `#include` that led there.
    pub fn labels(&self, range: Range<usize>, message: &str) -> Vec<Label<FileId>> {
        let Some(first) = self.origin(range.start) else {
            return Vec::new();
        };
        let mut span = first.span.clone();
        if range.end > range.start + 1 {
            if let Some(last) = self.origin(range.end - 1) {
                if last.file == first.file && last.include_chain == first.include_chain && last.span.end > span.start {
                    span = span.start.min(last.span.start)..span.end.max(last.span.end);
                }
            }
        }
        let mut labels = vec![Label::primary(first.file, span).with_message(message)];
        if let Some((f, r)) = first.macro_definition {
            labels.push(Label::secondary(f, r).with_message("in this macro's definition"));
        }
        for (f, r) in first.include_chain {
            labels.push(Label::secondary(f, r).with_message("included from here"));
        }
        labels
    }

    /// Every inclusion: (including file, the `#include` directive's original byte range in
    /// it, included file), in the order the files were entered.
    pub fn includes(&self) -> Vec<(FileId, Range<usize>, FileId)> {
        self.ctxs
            .iter()
            .filter_map(|c| {
                let p = self.ctxs.get(c.parent as usize)?;
                Some((p.file, p.source.original_range(c.site.start as usize..c.site.end as usize), c.file))
            })
            .collect()
    }

    /// Number of runs (a measure of compactness).
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Whether the map maps no byte.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }
}
