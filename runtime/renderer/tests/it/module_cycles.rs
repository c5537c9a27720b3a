//! No import cycles between modules, in the `src/` trees of the renderer, the runtime, the
//! compiler and the archive crate.
//!
//! Reads every `.rs` file (binaries aside), names its module by its path (`desktop/mod.rs` is
//! `desktop`, `desktop/taa.rs` is `desktop::taa`), and adds an edge for every `crate::...` and
//! `super::...` path outside comments, `use` trees included: to the deepest module of the
//! tree that the path names (an item's path ends at the module defining it). A parent's
//! `mod child;` and bare `child::` paths are not edges. Any strongly connected set of two or
//! more modules is a cycle, named in the failure.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// Module path (`a::b`, "" for the root) by file.
fn modules(src: &Path) -> BTreeMap<PathBuf, Vec<String>> {
    fn walk(dir: &Path, src: &Path, out: &mut BTreeMap<PathBuf, Vec<String>>) {
        let mut entries: Vec<_> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().path()).collect();
        entries.sort();
        for path in entries {
            let rel = path.strip_prefix(src).unwrap();
            if rel.starts_with("bin") {
                continue;
            }
            if path.is_dir() {
                walk(&path, src, out);
            } else if path.extension().is_some_and(|e| e == "rs") {
                let mut segments: Vec<String> =
                    rel.with_extension("").iter().map(|s| s.to_string_lossy().into_owned()).collect();
                if matches!(segments.last().map(String::as_str), Some("mod" | "lib" | "main")) {
                    segments.pop();
                }
                out.insert(path, segments);
            }
        }
    }
    let mut out = BTreeMap::new();
    walk(src, src, &mut out);
    out
}

/// The text without `//` comments (doc comments and their intra-doc links included) and
/// without string literals' contents.
fn code(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for line in text.lines() {
        let mut in_string = false;
        let mut prev = ' ';
        let mut chars = line.chars().peekable();
        while let Some(c) = chars.next() {
            if in_string {
                if c == '"' && prev != '\\' {
                    in_string = false;
                    out.push('"');
                }
                prev = if prev == '\\' && c == '\\' { ' ' } else { c };
                continue;
            }
            if c == '/' && chars.peek() == Some(&'/') {
                break;
            }
            if c == '"' && prev != '\'' {
                in_string = true;
            }
            out.push(c);
            prev = c;
        }
        out.push('\n');
    }
    out
}

/// Every path of a `use` tree (`a::{b, c::{d, e}}` gives `a::b`, `a::c::d`, `a::c::e`).
fn expand_use(tree: &str) -> Vec<String> {
    let tree: String = tree.split_whitespace().collect();
    fn go(prefix: &str, tree: &str, out: &mut Vec<String>) {
        match tree.find('{') {
            None => out.push(format!("{prefix}{tree}")),
            Some(open) => {
                let head = &tree[..open];
                let inner = &tree[open + 1..tree.rfind('}').unwrap_or(tree.len())];
                let mut depth = 0;
                let mut start = 0;
                for (i, c) in inner.char_indices() {
                    match c {
                        '{' => depth += 1,
                        '}' => depth -= 1,
                        ',' if depth == 0 => {
                            go(&format!("{prefix}{head}"), &inner[start..i], out);
                            start = i + 1;
                        }
                        _ => {}
                    }
                }
                go(&format!("{prefix}{head}"), &inner[start..], out);
            }
        }
    }
    let mut out = Vec::new();
    go("", &tree, &mut out);
    out.into_iter().filter(|p| !p.is_empty() && !p.ends_with("::")).collect()
}

/// The `crate::`/`super::` paths of a file's code.
fn paths(code: &str) -> Vec<String> {
    let mut out = Vec::new();
    // `use` trees first (they may hold braces), then the paths written inline.
    let mut rest = code;
    while let Some(i) = rest.find("use ") {
        let before = rest[..i].chars().last();
        let after = &rest[i + 4..];
        rest = after;
        if before.is_some_and(|c| c.is_alphanumeric() || c == '_') {
            continue;
        }
        let end = after.find(';').unwrap_or(after.len());
        out.extend(expand_use(&after[..end]));
    }
    let bytes = code.as_bytes();
    for start in ["crate::", "super::"] {
        let mut from = 0;
        while let Some(i) = code[from..].find(start) {
            let at = from + i;
            from = at + start.len();
            if at > 0 && (bytes[at - 1].is_ascii_alphanumeric() || bytes[at - 1] == b'_' || bytes[at - 1] == b':') {
                continue;
            }
            let len =
                code[at..].find(|c: char| !(c.is_alphanumeric() || c == '_' || c == ':')).unwrap_or(code.len() - at);
            out.push(code[at..at + len].trim_end_matches(':').to_string());
        }
    }
    out
}

/// The module a path names from `module` (the deepest module of `known` it reaches), or None
/// for a path that leaves the crate's own modules at once.
fn target(module: &[String], path: &str, known: &BTreeSet<Vec<String>>) -> Option<Vec<String>> {
    let mut segments = path.split("::").filter(|s| !s.is_empty()).peekable();
    let mut base: Vec<String> = match segments.peek().copied() {
        Some("crate") => {
            segments.next();
            Vec::new()
        }
        // Each `super` (the first included) goes up one module from this file's.
        Some("super") => module.to_vec(),
        _ => return None,
    };
    while segments.peek() == Some(&"super") {
        segments.next();
        base.pop()?;
    }
    let mut deepest = base.clone();
    for s in segments {
        if s == "self" || s == "*" {
            break;
        }
        base.push(s.to_string());
        if known.contains(&base) {
            deepest = base.clone();
        } else {
            break;
        }
    }
    Some(deepest)
}

fn name(m: &[String]) -> String {
    if m.is_empty() {
        "crate".to_string()
    } else {
        m.join("::")
    }
}

/// The cycles (strongly connected sets of two or more modules) of the tree at `src`, each as
/// `a -> b -> ... -> a` through files.
fn cycles(src: &Path) -> Vec<String> {
    let files = modules(src);
    let known: BTreeSet<Vec<String>> = files.values().cloned().collect();
    let mut edges: BTreeMap<Vec<String>, BTreeMap<Vec<String>, String>> = BTreeMap::new();
    for (file, module) in &files {
        let text = std::fs::read_to_string(file).unwrap();
        for path in paths(&code(&text)) {
            if let Some(to) = target(module, &path, &known) {
                if &to != module {
                    edges.entry(module.clone()).or_default().entry(to).or_insert(path);
                }
            }
        }
    }
    // Tarjan's strongly connected components.
    struct State<'a> {
        edges: &'a BTreeMap<Vec<String>, BTreeMap<Vec<String>, String>>,
        index: BTreeMap<Vec<String>, usize>,
        low: BTreeMap<Vec<String>, usize>,
        stack: Vec<Vec<String>>,
        on_stack: BTreeSet<Vec<String>>,
        components: Vec<Vec<Vec<String>>>,
    }
    fn visit(s: &mut State<'_>, v: &Vec<String>) {
        let i = s.index.len();
        s.index.insert(v.clone(), i);
        s.low.insert(v.clone(), i);
        s.stack.push(v.clone());
        s.on_stack.insert(v.clone());
        let next: Vec<Vec<String>> = s.edges.get(v).map(|e| e.keys().cloned().collect()).unwrap_or_default();
        for w in next {
            if !s.index.contains_key(&w) {
                visit(s, &w);
                let l = s.low[&w].min(s.low[v]);
                s.low.insert(v.clone(), l);
            } else if s.on_stack.contains(&w) {
                let l = s.index[&w].min(s.low[v]);
                s.low.insert(v.clone(), l);
            }
        }
        if s.low[v] == s.index[v] {
            let mut component = Vec::new();
            loop {
                let w = s.stack.pop().unwrap();
                s.on_stack.remove(&w);
                let done = &w == v;
                component.push(w);
                if done {
                    break;
                }
            }
            if component.len() > 1 {
                component.sort();
                s.components.push(component);
            }
        }
    }
    let mut state = State {
        edges: &edges,
        index: BTreeMap::new(),
        low: BTreeMap::new(),
        stack: Vec::new(),
        on_stack: BTreeSet::new(),
        components: Vec::new(),
    };
    for m in &known {
        if !state.index.contains_key(m) {
            visit(&mut state, m);
        }
    }
    state
        .components
        .iter()
        .map(|component| {
            let members: BTreeSet<&Vec<String>> = component.iter().collect();
            let by: Vec<String> = component
                .iter()
                .flat_map(|from| {
                    edges[from]
                        .iter()
                        .filter(|(to, _)| members.contains(to))
                        .map(move |(to, path)| format!("{} -> {} (`{path}`)", name(from), name(to)))
                })
                .collect();
            by.join(", ")
        })
        .collect()
}

fn assert_no_cycles(src: &Path) {
    let found = cycles(src);
    assert!(found.is_empty(), "import cycles in {}:\n  {}", src.display(), found.join("\n  "));
}

#[test]
fn the_renderer_has_no_import_cycles() {
    assert_no_cycles(&Path::new(env!("CARGO_MANIFEST_DIR")).join("src"));
}

#[test]
fn the_runtime_has_no_import_cycles() {
    assert_no_cycles(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../src"));
}

#[test]
fn the_compiler_has_no_import_cycles() {
    assert_no_cycles(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../../compiler/src"));
}

#[test]
fn the_archive_crate_has_no_import_cycles() {
    assert_no_cycles(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../../archive/src"));
}

#[test]
fn a_planted_cycle_is_found_and_named() {
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path();
    std::fs::create_dir_all(src.join("frame")).unwrap();
    std::fs::write(src.join("lib.rs"), "//! `crate::b` in a comment is no edge\npub mod a;\npub mod frame;\n").unwrap();
    std::fs::write(src.join("a.rs"), "use crate::frame::{x::{Y, Z}, W};\n").unwrap();
    std::fs::write(src.join("frame/mod.rs"), "pub mod x;\npub struct W;\n").unwrap();
    std::fs::write(src.join("frame/x.rs"), "pub fn f() { let s = \"crate::a\"; super::super::a::g(s) }\n").unwrap();
    let found = cycles(src);
    assert_eq!(found, ["a -> frame::x (`crate::frame::x::Y`), frame::x -> a (`super::super::a::g`)"], "{found:?}");
    // Without the back edge there is none.
    std::fs::write(src.join("frame/x.rs"), "pub fn f() { let s = \"crate::a\"; }\n").unwrap();
    assert_eq!(cycles(src), Vec::<String>::new());
}
