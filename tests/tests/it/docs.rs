//! The documentation's own checks (issue 29), std only:
//!
//! - every relative link and every `#anchor` in `README.md` and `docs/**/*.md` resolves to a
//!   file (or folder) inside the repository and, for an anchor, to a heading of that page
//!   (GitHub's anchor rules);
//! - every command in a fenced `sh` block of `docs/guide/getting-started.md` runs, in page
//!   order, in an empty temporary folder with the checkout's `kiln` first on `PATH`, and
//!   succeeds (`bash -euo pipefail`);
//! - the README opens with the two commands (main job, tests) and stays within 200 lines.
//!
//! The `kiln` binary: see [`kiln_binary`].

use std::collections::{BTreeSet, HashMap};
use std::path::{Component, Path, PathBuf};
use std::process::Command;
use std::time::SystemTime;

/// The repository's root: the parent of this package's folder (`tests/`).
fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("tests/ has a parent").to_path_buf()
}

/// README.md and every `.md` under docs/, sorted.
fn pages(root: &Path) -> Vec<PathBuf> {
    fn walk(dir: &Path, out: &mut Vec<PathBuf>) {
        let Ok(entries) = std::fs::read_dir(dir) else { return };
        for e in entries.flatten() {
            let p = e.path();
            if p.is_dir() {
                walk(&p, out);
            } else if p.extension().is_some_and(|x| x == "md") {
                out.push(p);
            }
        }
    }
    let mut out = vec![root.join("README.md")];
    walk(&root.join("docs"), &mut out);
    out.sort();
    out
}

/// A fenced code block's opening: its fence character, length and info string.
fn fence_open(line: &str) -> Option<(char, usize, &str)> {
    let t = line.trim_start_matches(' ');
    if line.len() - t.len() > 3 {
        return None;
    }
    let c = t.chars().next().filter(|c| *c == '`' || *c == '~')?;
    let n = t.chars().take_while(|x| *x == c).count();
    (n >= 3).then(|| (c, n, t[n..].trim()))
}

/// The page's lines outside fenced code blocks, with their line numbers (from 1).
fn prose_lines(text: &str) -> Vec<(usize, &str)> {
    let mut out = Vec::new();
    let mut open: Option<(char, usize)> = None;
    for (i, line) in text.lines().enumerate() {
        match (open, fence_open(line)) {
            (None, Some((c, n, _))) => open = Some((c, n)),
            (Some((c, n)), Some((c2, n2, info))) if c2 == c && n2 >= n && info.is_empty() => open = None,
            (None, None) => out.push((i + 1, line)),
            _ => {}
        }
    }
    out
}

/// `line` without its code spans (`` `a](b)` `` is not a link).
fn strip_code_spans(line: &str) -> String {
    let mut out = String::new();
    let mut rest = line;
    while let Some(start) = rest.find('`') {
        out.push_str(&rest[..start]);
        let ticks = rest[start..].chars().take_while(|c| *c == '`').count();
        let after = &rest[start + ticks..];
        let fence = "`".repeat(ticks);
        match after.find(&fence) {
            Some(end) => {
                out.push(' ');
                rest = &after[end + ticks..];
            }
            None => {
                out.push_str(&rest[start..start + ticks]);
                rest = after;
            }
        }
    }
    out.push_str(rest);
    out
}

/// The link targets of one prose line: inline links and images `[text](target "title")`,
/// and reference definitions `[label]: target`.
fn link_targets(line: &str) -> Vec<String> {
    let line = strip_code_spans(line);
    let mut out = Vec::new();
    let trimmed = line.trim_start();
    if trimmed.starts_with('[') {
        if let Some(close) = trimmed.find("]:") {
            if !trimmed[..close].contains("](") {
                if let Some(t) = trimmed[close + 2..].split_whitespace().next() {
                    out.push(t.trim_matches(|c| c == '<' || c == '>').to_string());
                }
                return out;
            }
        }
    }
    let bytes = line.as_bytes();
    let mut i = 0;
    while let Some(at) = line[i..].find("](") {
        let start = i + at + 2;
        let mut depth = 0usize;
        let mut end = start;
        while end < bytes.len() {
            match bytes[end] {
                b'(' => depth += 1,
                b')' if depth == 0 => break,
                b')' => depth -= 1,
                _ => {}
            }
            end += 1;
        }
        let inner = line[start..end].trim();
        let target = if let Some(rest) = inner.strip_prefix('<') {
            rest.split('>').next().unwrap_or("").to_string()
        } else {
            inner.split_whitespace().next().unwrap_or("").to_string()
        };
        if !target.is_empty() {
            out.push(target);
        }
        i = end.max(start);
    }
    out
}

/// GitHub's anchor of a heading's text: markdown markup dropped, lower case, every
/// character but letters, digits, `-`, `_` and spaces removed, spaces as `-`.
fn slug(heading: &str) -> String {
    let mut text = String::new();
    // Links keep their text: `[text](url)` -> `text`.
    let mut rest = heading;
    while let Some(open) = rest.find('[') {
        let Some(mid) = rest[open..].find("](").map(|m| open + m) else { break };
        let Some(close) = rest[mid..].find(')').map(|c| mid + c) else { break };
        text.push_str(&rest[..open]);
        text.push_str(&rest[open + 1..mid]);
        rest = &rest[close + 1..];
    }
    text.push_str(rest);
    text.to_lowercase()
        .chars()
        .filter(|c| c.is_alphanumeric() || *c == '-' || *c == '_' || *c == ' ')
        .map(|c| if c == ' ' { '-' } else { c })
        .collect()
}

/// The anchors of a page: its headings' slugs (a repeated slug gets `-1`, `-2`, ... as on
/// GitHub) and explicit `id="..."` / `name="..."` attributes.
fn anchors(text: &str) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    let mut seen: HashMap<String, usize> = HashMap::new();
    for (_, line) in prose_lines(text) {
        let t = line.trim_start_matches(' ');
        if line.len() - t.len() <= 3 && t.starts_with('#') {
            let level = t.chars().take_while(|c| *c == '#').count();
            let after = &t[level..];
            if level <= 6 && (after.is_empty() || after.starts_with(' ')) {
                let title = after.trim().trim_end_matches('#').trim();
                let base = slug(title);
                let n = seen.entry(base.clone()).or_insert(0);
                out.insert(if *n == 0 { base.clone() } else { format!("{base}-{n}") });
                *n += 1;
            }
        }
        for attr in ["id=\"", "name=\""] {
            let mut rest = line;
            while let Some(at) = rest.find(attr) {
                let value = &rest[at + attr.len()..];
                if let Some(end) = value.find('"') {
                    out.insert(value[..end].to_string());
                }
                rest = &rest[at + attr.len()..];
            }
        }
    }
    out
}

/// `path` with `.` and `..` resolved lexically.
fn normalize(path: &Path) -> PathBuf {
    let mut out = PathBuf::new();
    for c in path.components() {
        match c {
            Component::ParentDir => {
                out.pop();
            }
            Component::CurDir => {}
            c => out.push(c),
        }
    }
    out
}

/// `%20` and the like, for link targets with spaces.
fn percent_decode(s: &str) -> String {
    let bytes = s.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i] == b'%' && i + 2 < bytes.len() {
            if let Ok(b) = u8::from_str_radix(&s[i + 1..i + 3], 16) {
                out.push(b);
                i += 3;
                continue;
            }
        }
        out.push(bytes[i]);
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

/// Every broken relative link or anchor of the pages under `root`, one line each.
fn broken_links(root: &Path) -> Vec<String> {
    let root = normalize(root);
    let mut anchor_cache: HashMap<PathBuf, BTreeSet<String>> = HashMap::new();
    let mut problems = Vec::new();
    for page in pages(&root) {
        let text = std::fs::read_to_string(&page).unwrap_or_else(|e| panic!("{}: {e}", page.display()));
        let shown = page.strip_prefix(&root).unwrap_or(&page).display().to_string();
        for (n, line) in prose_lines(&text) {
            for target in link_targets(line) {
                let scheme = target.split(['/', '#', '?']).next().unwrap_or("");
                if scheme.contains(':') {
                    continue; // https:, mailto:, ...: not checked offline
                }
                let (path_part, anchor) = match target.split_once('#') {
                    Some((p, a)) => (p, Some(a)),
                    None => (target.as_str(), None),
                };
                let path_part = percent_decode(path_part.split('?').next().unwrap_or(""));
                let resolved = if path_part.is_empty() {
                    page.clone()
                } else if path_part.starts_with('/') {
                    problems.push(format!("{shown}:{n}: `{target}`: an absolute path does not render on every forge"));
                    continue;
                } else {
                    normalize(&page.parent().expect("a page has a folder").join(&path_part))
                };
                if !resolved.starts_with(&root) {
                    problems.push(format!("{shown}:{n}: `{target}` leaves the repository"));
                    continue;
                }
                let relative = resolved.strip_prefix(&root).expect("checked").to_string_lossy().replace('\\', "/");
                if !resolved.exists() {
                    problems.push(format!("{shown}:{n}: `{target}`: {relative} does not exist"));
                    continue;
                }
                let Some(anchor) = anchor.filter(|a| !a.is_empty()) else { continue };
                if resolved.extension().is_none_or(|x| x != "md") {
                    problems.push(format!("{shown}:{n}: `{target}`: an anchor into a file that is not markdown"));
                    continue;
                }
                let known = anchor_cache
                    .entry(resolved.clone())
                    .or_insert_with(|| anchors(&std::fs::read_to_string(&resolved).unwrap_or_default()));
                if !known.contains(&percent_decode(anchor)) {
                    problems.push(format!(
                        "{shown}:{n}: `{target}`: {relative} has no heading with anchor #{anchor} (it has: {})",
                        known.iter().cloned().collect::<Vec<_>>().join(", ")
                    ));
                }
            }
        }
    }
    problems
}

#[test]
fn every_relative_link_and_anchor_resolves() {
    let root = repo();
    let pages = pages(&root);
    assert!(pages.len() > 10, "expected README.md and the docs/ pages, found {pages:?}");
    let problems = broken_links(&root);
    assert!(problems.is_empty(), "{} broken links:\n{}", problems.len(), problems.join("\n"));
}

#[test]
fn the_link_checker_finds_what_it_should() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    std::fs::create_dir_all(root.join("docs/guide")).unwrap();
    std::fs::write(
        root.join("README.md"),
        "# Kiln\n\n## A tour: `kiln build`\n\n[ok](docs/guide/a.md#the-b_c-part) [self](#a-tour-kiln-build)\n\
         [dup](docs/guide/a.md#same-1) `[not](a link)`\n\
         [web](https://example.com/x.md) ![img](docs/missing.png)\n\n```sh\n[code](not/checked.md)\n```\n\
         [bad anchor](docs/guide/a.md#nope) [out](../outside.md)\n[def]: docs/guide/gone.md\n",
    )
    .unwrap();
    std::fs::write(
        root.join("docs/guide/a.md"),
        "# A\n\n## The B_C part!\n\n## Same\n\n## Same\n\n[up](../../README.md)\n",
    )
    .unwrap();
    let problems = broken_links(root);
    let found: Vec<&str> = problems.iter().map(|p| p.split('`').nth(1).unwrap_or("")).collect();
    assert_eq!(
        found,
        ["docs/missing.png", "docs/guide/a.md#nope", "../outside.md", "docs/guide/gone.md"],
        "{problems:#?}"
    );
}

#[test]
fn readme_opens_with_the_two_commands_and_stays_short() {
    let text = std::fs::read_to_string(repo().join("README.md")).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert!(lines.len() <= 200, "README.md has {} lines; the issue allows 200", lines.len());
    let first_block: Vec<&str> = lines
        .iter()
        .skip_while(|l| !l.starts_with("```"))
        .skip(1)
        .take_while(|l| !l.starts_with("```"))
        .copied()
        .collect();
    assert!(first_block.first().is_some_and(|l| l.starts_with("cargo run --release -- build ")), "{first_block:?}");
    assert!(first_block.get(1).is_some_and(|l| l.starts_with("bash .ci/run ")), "{first_block:?}");
}

/// The newest modification time of the files a `kiln` binary is built from.
fn newest_source(root: &Path) -> SystemTime {
    fn walk(p: &Path, newest: &mut SystemTime) {
        if p.is_dir() {
            for e in std::fs::read_dir(p).into_iter().flatten().flatten() {
                walk(&e.path(), newest);
            }
        } else if let Ok(t) = p.metadata().and_then(|m| m.modified()) {
            *newest = (*newest).max(t);
        }
    }
    let mut newest = SystemTime::UNIX_EPOCH;
    for p in
        ["Cargo.lock", "compiler/Cargo.toml", "compiler/src", "compiler/build.rs", "archive/Cargo.toml", "archive/src"]
    {
        walk(&root.join(p), &mut newest);
    }
    newest
}

/// The `kiln` binary of this checkout, in this order:
/// 1. `KILN_BIN`, when set (CI may point it at a binary it built);
/// 2. `kiln` in this test binary's profile folder (`target/<profile>/kiln`, which
///    `cargo test --workspace` builds for kiln's own tests), or in the other profile's,
///    when it is newer than every source it is built from;
/// 3. otherwise `cargo build -p kiln --bin kiln` into `<target>/docs-kiln`, a target folder
///    of its own so that it never waits on the lock of the `cargo test` running it (the
///    first time, a whole build of kiln).
fn kiln_binary(root: &Path) -> PathBuf {
    if let Some(bin) = std::env::var_os("KILN_BIN").filter(|b| !b.is_empty()) {
        return PathBuf::from(bin);
    }
    let exe = std::env::current_exe().expect("the test binary's path");
    // target/<profile>/deps/<test binary>
    let profile_dir = exe.parent().and_then(Path::parent).expect("target/<profile>/deps").to_path_buf();
    let target = profile_dir.parent().expect("target/").to_path_buf();
    let name = format!("kiln{}", std::env::consts::EXE_SUFFIX);
    let newest = newest_source(root);
    for dir in [profile_dir.clone(), target.join("release"), target.join("debug")] {
        let bin = dir.join(&name);
        if bin.metadata().and_then(|m| m.modified()).is_ok_and(|t| t >= newest) {
            return bin;
        }
    }
    let own = target.join("docs-kiln");
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    let status = Command::new(cargo)
        .args(["build", "--locked", "-p", "kiln", "--bin", "kiln", "--target-dir"])
        .arg(&own)
        .current_dir(root)
        .status()
        .expect("cargo runs");
    assert!(status.success(), "cargo build -p kiln failed");
    own.join("debug").join(name)
}

/// The `sh` blocks of a page, in order, with the line each starts on.
fn sh_blocks(text: &str) -> Vec<(usize, String)> {
    let mut out = Vec::new();
    let mut open: Option<(char, usize, bool, usize, String)> = None;
    for (i, line) in text.lines().enumerate() {
        match (&mut open, fence_open(line)) {
            (None, Some((c, n, info))) => open = Some((c, n, info == "sh", i + 1, String::new())),
            (Some((c, n, _, _, _)), Some((c2, n2, info))) if c2 == *c && n2 >= *n && info.is_empty() => {
                let (_, _, sh, at, body) = open.take().expect("open");
                if sh {
                    out.push((at, body));
                }
            }
            (Some((_, _, _, _, body)), _) => {
                body.push_str(line);
                body.push('\n');
            }
            (None, None) => {}
        }
    }
    out
}

#[test]
fn getting_started_commands_run() {
    let root = repo();
    let page = root.join("docs/guide/getting-started.md");
    let blocks = sh_blocks(&std::fs::read_to_string(&page).unwrap());
    assert!(blocks.len() >= 5, "expected the page's sh blocks, found {}", blocks.len());
    let kiln = kiln_binary(&root);
    let bin_dir = kiln.parent().expect("a folder").to_path_buf();
    let path = std::env::join_paths(
        std::iter::once(bin_dir).chain(std::env::split_paths(&std::env::var_os("PATH").unwrap_or_default())),
    )
    .unwrap();
    let work = tempfile::tempdir().unwrap();
    for (line, block) in &blocks {
        let mut cmd = Command::new("bash");
        cmd.args(["-euo", "pipefail", "-c", block]).current_dir(work.path()).env("PATH", &path);
        // The page's cache is `.kiln-cache/` in the folder, and nothing reaches out.
        for (k, _) in std::env::vars_os() {
            if k.to_string_lossy().starts_with("KILN_") || k == "CARGO_TARGET_DIR" {
                cmd.env_remove(k);
            }
        }
        cmd.env("CI", "1").env("NO_COLOR", "1");
        let out = cmd.output().expect("bash runs");
        assert!(
            out.status.success(),
            "docs/guide/getting-started.md, the sh block at line {line} failed ({}):\n{block}\n--- stdout\n{}\n--- stderr\n{}",
            out.status,
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
    }
}
