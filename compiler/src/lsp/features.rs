//! Hover, go to definition, completion, document symbols and semantic tokens, each answered
//! from the active permutation of the shader a file follows.

use std::path::{Path, PathBuf};

use lsp_types::{Position, Range};
use serde_json::{json, Value};

use super::text::{include_spelling, is_ident, line_around, offset_of, path_uri, position_of, range_of, word_at};
use super::workspace::{cache_with, Active, Overlays};
use crate::permute::{Config, DefineOrigin, Permutation};
use crate::preprocess;

/// What a feature sees: the set, the file and the active permutation it follows.
pub struct Ctx<'a> {
    pub config: &'a Config,
    pub shader: Option<usize>,
    pub active: Option<&'a Active>,
    pub path: &'a Path,
    pub text: &'a str,
}

impl Ctx<'_> {
    fn permutation(&self) -> Option<Permutation<'_>> {
        let a = self.active?;
        let s = self.config.shaders.get(self.shader?)?;
        Some(Permutation::new(s, self.config.levels.get(a.level)?, a.values.clone()))
    }

    /// The byte offset of the request's position.
    fn offset(&self, p: &Value) -> Option<usize> {
        let pos: Position = serde_json::from_value(p["position"].clone()).ok()?;
        Some(offset_of(self.text, pos))
    }

    /// Whether 1-based `line` of `path` is excluded in the active permutation.
    fn inactive(&self, path: &Path, line: u32) -> bool {
        self.active.is_some_and(|a| a.skipped.iter().any(|(p, r)| p == path && r.contains(&line)))
    }
}

/// A `#define NAME` in the files the active permutation read, outside excluded lines:
/// (file, 0-based line, byte range of the name in the line, the line).
fn find_define(ctx: &Ctx<'_>, name: &str) -> Option<(PathBuf, u32, std::ops::Range<usize>, String)> {
    let a = ctx.active?;
    for file in &a.files {
        let text = if file == ctx.path { ctx.text.to_string() } else { std::fs::read_to_string(file).ok()? };
        for (n, line) in text.lines().enumerate() {
            let t = line.trim_start();
            let Some(rest) = t.strip_prefix('#') else { continue };
            let rest = rest.trim_start();
            let Some(after) = rest.strip_prefix("define") else { continue };
            let after_trim = after.trim_start();
            if after_trim.starts_with(name)
                && !after_trim.as_bytes().get(name.len()).is_some_and(|&b| is_ident(b))
                && !ctx.inactive(file, n as u32 + 1)
            {
                let start = line.len() - after_trim.len();
                return Some((file.clone(), n as u32, start..start + name.len(), line.to_string()));
            }
        }
    }
    None
}

/// The toml location of a permutation define: (0-based line, byte range in that line).
fn toml_location(ctx: &Ctx<'_>, name: &str, origin: &DefineOrigin) -> Option<(u32, std::ops::Range<usize>)> {
    let text = &ctx.config.source.1;
    let shader = ctx.config.shaders.get(ctx.shader?)?;
    let from = match origin {
        DefineOrigin::Dimension | DefineOrigin::EnumValue { .. } => shader.spans.dimensions.start,
        DefineOrigin::Level(l) => text.find(&format!("[levels.{l}]")).unwrap_or(0),
        _ => shader.spans.name.start,
    };
    let mut at = from.min(text.len());
    while let Some(i) = text[at..].find(name).map(|i| i + at) {
        let b = text.as_bytes();
        let edge_ok = (i == 0 || !is_ident(b[i - 1])) && !b.get(i + name.len()).is_some_and(|&c| is_ident(c));
        if edge_ok {
            let p = position_of(text, i);
            return Some((p.line, p.character as usize..p.character as usize + name.len()));
        }
        at = i + name.len();
    }
    None
}

fn markdown(text: String) -> Value {
    json!({ "contents": { "kind": "markdown", "value": text } })
}

/// `textDocument/hover`.
pub fn hover(ctx: &Ctx<'_>, p: &Value) -> Value {
    let Some(at) = ctx.offset(p) else { return Value::Null };
    if let Some(target) = include_target(ctx, at) {
        let shown = target.display();
        return markdown(format!("`#include` resolves to `{shown}`{}", active_note(ctx)));
    }
    let Some((word, _)) = word_at(ctx.text, at) else { return Value::Null };
    let perm = ctx.permutation();
    let active = active_note(ctx);
    if let Some(perm) = &perm {
        if let Some(d) = perm.shader.dimensions.iter().position(|d| d.name == word) {
            return markdown(dimension_hover(ctx, perm, d, &active));
        }
        if let Some(def) = perm.defines().into_iter().find(|d| d.name == word) {
            let toml = ctx.config.path.file_name().map(|f| f.to_string_lossy().into_owned()).unwrap_or_default();
            let line = toml_location(ctx, word, &def.origin).map_or(String::new(), |(l, _)| format!(":{}", l + 1));
            return markdown(format!(
                "`{word}` = `{}`{active}\n\ndefined by {} in `{toml}{line}`",
                def.value, def.origin
            ));
        }
    }
    if let Some((file, n, _, text)) = find_define(ctx, word) {
        let name = file.strip_prefix(&ctx.config.dir).unwrap_or(&file).display().to_string();
        return markdown(format!("```c\n{}\n```\n`#define` at `{name}:{}`{active}", text.trim(), n + 1));
    }
    Value::Null
}

/// ` in `NAME`` of the active permutation, for hovers.
fn active_note(ctx: &Ctx<'_>) -> String {
    ctx.active.map_or(String::new(), |a| format!(" in `{}`", a.name))
}

/// A dimension: its value in the active permutation, its values, and how many kept
/// permutations of the active level each value has.
fn dimension_hover(ctx: &Ctx<'_>, perm: &Permutation<'_>, d: usize, active: &str) -> String {
    let dim = &perm.shader.dimensions[d];
    let mut counts = vec![0u64; dim.values.len()];
    let (shader, level) = (perm.shader, perm.level);
    for k in ctx.config.kept_where(|s, l| std::ptr::eq(s, shader) && std::ptr::eq(l, level)) {
        if let Some(i) = dim.values.iter().position(|v| *v == k.values[d]) {
            counts[i] += 1;
        }
    }
    let mut s = format!(
        "`{}` = `{}`{active}\n\ndimension of `{}`: {}\n\n",
        dim.name,
        dim.display(perm.values[d]),
        shader.name,
        dim.describe()
    );
    for (v, n) in dim.values.iter().zip(counts) {
        s.push_str(&format!("- `{}`: {} kept permutations at {}\n", dim.display(*v), n, level.name));
    }
    s
}

/// The file an `#include` on the line at `at` brings in: the active permutation's own
/// inclusion where it made one, else the directive resolved as the preprocessor would.
fn include_target(ctx: &Ctx<'_>, at: usize) -> Option<PathBuf> {
    let line_range = line_around(ctx.text, at);
    let (spelling, angle, _) = include_spelling(&ctx.text[line_range.clone()])?;
    if let Some((out, cache)) = ctx.active.and_then(|a| a.output.as_ref()) {
        for (parent, site, child) in out.map.includes() {
            if cache.path(parent) == ctx.path && site.start <= line_range.end && site.end >= line_range.start {
                return Some(cache.path(child));
            }
        }
    }
    // Not included in this permutation (an inactive line, or a file no shader reads).
    let mut candidates: Vec<PathBuf> = Vec::new();
    if !angle {
        if let Some(dir) = ctx.path.parent() {
            candidates.push(dir.join(spelling));
        }
    }
    for (prefix, dir) in &ctx.config.virtual_roots {
        if let Some(rest) = spelling.strip_prefix(prefix.as_str()) {
            candidates.push(dir.join(rest.trim_start_matches('/')));
        }
    }
    candidates.extend(ctx.config.include_roots.iter().map(|r| r.join(spelling)));
    candidates.into_iter().find(|c| c.is_file()).map(|c| c.canonicalize().unwrap_or(c))
}

fn location(path: &Path, range: Range) -> Value {
    match path_uri(path) {
        Some(uri) => json!({ "uri": uri, "range": range }),
        None => Value::Null,
    }
}

fn line_range(line: u32, cols: std::ops::Range<usize>) -> Range {
    Range { start: Position { line, character: cols.start as u32 }, end: Position { line, character: cols.end as u32 } }
}

/// `textDocument/definition`.
pub fn definition(ctx: &Ctx<'_>, p: &Value) -> Value {
    let Some(at) = ctx.offset(p) else { return Value::Null };
    if let Some(target) = include_target(ctx, at) {
        return location(&target, line_range(0, 0..0));
    }
    let Some((word, _)) = word_at(ctx.text, at) else { return Value::Null };
    if let Some(perm) = ctx.permutation() {
        if let Some(def) = perm.defines().into_iter().find(|d| d.name == word) {
            if let Some((l, cols)) = toml_location(ctx, word, &def.origin) {
                return location(&ctx.config.path, line_range(l, cols));
            }
        }
    }
    if let Some((file, n, cols, _)) = find_define(ctx, word) {
        return location(&file, line_range(n, cols));
    }
    wgsl_declaration(ctx, word).or_else(|| written_declaration(ctx, word)).unwrap_or(Value::Null)
}

/// A declaration of `name` as written in this file or the files the active permutation
/// read (when the permutation's text does not have it: an inactive line, or a text that
/// does not preprocess).
fn written_declaration(ctx: &Ctx<'_>, name: &str) -> Option<Value> {
    let mut files = vec![ctx.path.to_path_buf()];
    files.extend(ctx.active.map_or_else(Vec::new, |a| a.files.clone()));
    for file in files {
        let text = if file == ctx.path { ctx.text.to_string() } else { std::fs::read_to_string(&file).ok()? };
        if let Some((_, _, r)) = declarations(&text).into_iter().find(|(_, n, _)| *n == name) {
            return Some(location(&file, range_of(&text, r)));
        }
    }
    None
}

/// A WGSL `fn`, `struct`, `const`, `override`, `alias` or module-scope `var` named `name` in
/// the active permutation's preprocessed text, mapped back to its file, line and column.
fn wgsl_declaration(ctx: &Ctx<'_>, name: &str) -> Option<Value> {
    let (out, cache) = ctx.active?.output.as_ref()?;
    let at = find_declaration(&out.text, name)?;
    let o = out.map.origin(at)?;
    let path = cache.path(o.file);
    let text = cache.text(o.file)?;
    Some(location(&path, range_of(&text, o.span.start..o.span.start + name.len())))
}

/// The offset of `name` where a declaration introduces it.
fn find_declaration(text: &str, name: &str) -> Option<usize> {
    let b = text.as_bytes();
    let mut from = 0;
    while let Some(i) = text[from..].find(name).map(|i| i + from) {
        from = i + name.len();
        if (i > 0 && is_ident(b[i - 1])) || b.get(i + name.len()).is_some_and(|&c| is_ident(c)) {
            continue;
        }
        let before = text[..i].trim_end();
        let keyword_start = before.rfind(|c: char| !(c.is_ascii_alphanumeric() || c == '_')).map_or(0, |k| k + 1);
        let keyword = &before[keyword_start..];
        let is_var = before.ends_with('>') && before.rfind("var").is_some_and(|k| !before[k..].contains(';'));
        if matches!(keyword, "fn" | "struct" | "const" | "override" | "alias" | "var") || is_var {
            return Some(i);
        }
    }
    None
}

/// `textDocument/completion`: macro and dimension names after `#if`, `#ifdef`, `#ifndef`,
/// `#elif`, `defined(`; header paths after `#include "` or `#include <`.
pub fn completion(ctx: &Ctx<'_>, p: &Value) -> Value {
    let Some(at) = ctx.offset(p) else { return Value::Null };
    let line_start = line_around(ctx.text, at).start;
    let before = &ctx.text[line_start..at];
    let t = before.trim_start();
    let directive = t.strip_prefix('#').map(str::trim_start);
    if let Some(d) = directive.and_then(|d| d.strip_prefix("include")) {
        let d = d.trim_start();
        if d.starts_with('"') || d.starts_with('<') {
            return json!(header_items(ctx));
        }
    }
    let conditional = directive.is_some_and(|d| ["if", "ifdef", "ifndef", "elif"].iter().any(|k| d.starts_with(k)));
    if !(conditional || before.contains("defined(") || before.contains("defined ")) {
        return json!([]);
    }
    let mut items: Vec<Value> = Vec::new();
    let mut seen = std::collections::HashSet::new();
    if let Some(perm) = ctx.permutation() {
        for d in perm.defines() {
            if seen.insert(d.name.clone()) {
                items.push(json!({ "label": d.name, "kind": 21, "detail": format!("{} = {}", d.origin, d.value) }));
            }
        }
    }
    for name in define_names(ctx) {
        if seen.insert(name.clone()) {
            items.push(json!({ "label": name, "kind": 21, "detail": "#define" }));
        }
    }
    json!(items)
}

/// The names `#define`d in the files the active permutation read.
fn define_names(ctx: &Ctx<'_>) -> Vec<String> {
    let mut out = Vec::new();
    let mut files: Vec<PathBuf> = ctx.active.map_or_else(|| vec![ctx.path.to_path_buf()], |a| a.files.clone());
    // While the text does not preprocess, its own includes still name the headers it reads.
    let mut at = 0;
    for line in ctx.text.split_inclusive('\n') {
        if include_spelling(line).is_some() {
            files.extend(include_target(ctx, at));
        }
        at += line.len();
    }
    files.dedup();
    for file in files {
        let text =
            if file == ctx.path { ctx.text.to_string() } else { std::fs::read_to_string(&file).unwrap_or_default() };
        for line in text.lines() {
            let t = line.trim_start();
            if let Some(rest) = t.strip_prefix('#').map(str::trim_start).and_then(|r| r.strip_prefix("define")) {
                let name: String =
                    rest.trim_start().chars().take_while(|c| c.is_ascii_alphanumeric() || *c == '_').collect();
                if !name.is_empty() {
                    out.push(name);
                }
            }
        }
    }
    out
}

/// Every `.ush`/`.usf` under the include roots, spelled relative to a root and through each
/// virtual root.
fn header_items(ctx: &Ctx<'_>) -> Vec<Value> {
    let mut items = Vec::new();
    for root in &ctx.config.include_roots {
        for entry in walkdir::WalkDir::new(root).max_depth(8).into_iter().filter_map(Result::ok).take(5000) {
            let path = entry.path();
            if !matches!(path.extension().and_then(|e| e.to_str()), Some("ush" | "usf")) {
                continue;
            }
            let Ok(rel) = path.strip_prefix(root) else { continue };
            let rel = rel.to_string_lossy().into_owned();
            items.push(json!({ "label": rel, "kind": 17 }));
            for (prefix, dir) in &ctx.config.virtual_roots {
                if let Ok(v) = path.strip_prefix(dir) {
                    items.push(json!({ "label": format!("{prefix}/{}", v.to_string_lossy()), "kind": 17 }));
                }
            }
        }
    }
    items
}

/// Module-scope declarations of a WGSL text: (kind keyword, name, byte range of the name,
/// byte range of the line).
fn declarations(text: &str) -> Vec<(&'static str, &str, std::ops::Range<usize>)> {
    let mut out = Vec::new();
    let mut offset = 0;
    for line in text.split_inclusive('\n') {
        let t = line.trim_start();
        let lead = line.len() - t.len();
        let mut rest = t;
        // Attributes (`@group(0) @binding(1) var<uniform> x`, `@fragment fn f`).
        while let Some(r) = rest.strip_prefix('@') {
            let end = r.find(|c: char| c.is_whitespace()).unwrap_or(r.len());
            rest = r[end..].trim_start();
        }
        for kw in ["fn", "struct", "const", "override", "alias", "var"] {
            let Some(r) = rest.strip_prefix(kw) else { continue };
            let r = if kw == "var" && r.starts_with('<') { r.find('>').map_or(r, |e| &r[e + 1..]) } else { r };
            if !(r.starts_with(|c: char| c.is_whitespace()) || kw == "var" && rest.starts_with("var<")) {
                continue;
            }
            let r = r.trim_start();
            let len = r.bytes().take_while(|&b| is_ident(b)).count();
            if len > 0 && line.len() - lead > 0 {
                let start = offset + (line.len() - r.len());
                let kind = if kw == "var" { "binding" } else { kw };
                out.push((kind, &text[start..start + len], start..start + len));
            }
            break;
        }
        offset += line.len();
    }
    out
}

/// `textDocument/documentSymbol`: functions, structs, constants and bindings.
pub fn symbols(ctx: &Ctx<'_>, _p: &Value) -> Value {
    let items: Vec<Value> = declarations(ctx.text)
        .into_iter()
        .filter(|(kind, ..)| *kind != "alias")
        .map(|(kind, name, r)| {
            let range = range_of(ctx.text, r);
            let sym = match kind {
                "fn" => 12,
                "struct" => 23,
                "const" | "override" => 14,
                _ => 13,
            };
            json!({ "name": name, "detail": kind, "kind": sym, "range": range, "selectionRange": range })
        })
        .collect();
    json!(items)
}

/// `textDocument/semanticTokens/full`: each excluded line as one `comment` token.
pub fn semantic_tokens(ctx: &Ctx<'_>, _p: &Value) -> Value {
    let mut lines: Vec<u32> = ctx
        .active
        .map(|a| a.skipped.iter().filter(|(p, _)| p == ctx.path).flat_map(|(_, r)| r.clone()).collect())
        .unwrap_or_default();
    lines.sort_unstable();
    lines.dedup();
    let text_lines: Vec<&str> = ctx.text.split('\n').collect();
    let mut data = Vec::new();
    let mut prev = 0u32;
    for l in lines {
        let Some(t) = text_lines.get(l as usize - 1) else { continue };
        let len = t.trim_end_matches('\r').encode_utf16().count() as u32;
        if len == 0 {
            continue;
        }
        data.extend([l - 1 - prev, 0, len, 0, 0]);
        prev = l - 1;
    }
    json!({ "data": data })
}

/// The canonical names of the kept permutations of shader `i` that read `path`: all of them
/// for the shader's own source; for a header, those whose preprocessing reads it (checked
/// one by one up to a bound, beyond which every kept permutation of the shader is listed).
pub fn reading_permutations(config: &Config, i: usize, path: &Path, overlays: &Overlays, names: &mut Vec<String>) {
    const CHECKED: usize = 4096;
    let Some(shader) = config.shaders.get(i) else { return };
    let kept = || config.kept_where(|s, _| std::ptr::eq(s, shader));
    if shader.source_path == path || kept().take(CHECKED + 1).count() > CHECKED {
        names.extend(kept().map(|p| p.name()));
        return;
    }
    let cache = cache_with(overlays, &config.dir);
    for p in kept() {
        let reads = preprocess::preprocess_file(&shader.source_path, &p.preprocess_options(config), &cache)
            .map(|o| o.files.iter().any(|f| cache.path(*f) == path))
            .unwrap_or(true);
        if reads {
            names.push(p.name());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_declarations() {
        let t = "struct Light { a: f32 }\n@group(0) @binding(1) var<uniform> view: View;\nfn shade(x: f32) -> f32 { return x; }\nconst PI = 3.14;\n";
        let names: Vec<(&str, &str)> = declarations(t).into_iter().map(|(k, n, _)| (k, n)).collect();
        assert_eq!(names, [("struct", "Light"), ("binding", "view"), ("fn", "shade"), ("const", "PI")]);
        assert_eq!(find_declaration(t, "shade"), t.find("shade"));
        assert_eq!(find_declaration(t, "view"), t.find("view"));
        assert_eq!(find_declaration("let y = shade(1.0);", "shade"), None);
    }
}
