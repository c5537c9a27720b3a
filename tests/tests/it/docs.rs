//! The documentation's own checks (issue 29), std only:
//!
//! - every relative link and every `#anchor` in `README.md` and `docs/**/*.md` resolves to a
//!   file (or folder) inside the repository and, for an anchor, to a heading of that page
//!   (GitHub's anchor rules);
//! - every command in a fenced `sh` block of `docs/guide/getting-started.md` runs, in page
//!   order, in an empty temporary folder with the checkout's `kiln` first on `PATH`, and
//!   succeeds (`bash -euo pipefail`);
//! - the README opens with the two commands (main job, tests) and stays within 200 lines;
//! - `docs/reference/cli.md` names every command, subcommand and flag that `kiln --help`,
//!   each subcommand's `--help` and `kiln-view --help` list, and documents no flag that
//!   they do not.
//!
//! The `kiln` and `kiln-view` binaries: see [`binary`].

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

/// A binary of this workspace that a docs test runs.
struct Bin {
    package: &'static str,
    name: &'static str,
    /// What a build newer than the binary could change (files or folders, from the root).
    sources: &'static [&'static str],
}

/// The compiler's command line, from everything it is built from.
const KILN: Bin = Bin {
    package: "kiln",
    name: "kiln",
    sources: &[
        "Cargo.lock",
        "compiler/Cargo.toml",
        "compiler/src",
        "compiler/build.rs",
        "archive/Cargo.toml",
        "archive/src",
    ],
};

/// The viewer, for its `--help` only: its flags are defined in its own file (the libraries
/// under it change more often and do not change them).
const KILN_VIEW: Bin = Bin {
    package: "kiln-renderer",
    name: "kiln-view",
    sources: &["Cargo.lock", "runtime/renderer/Cargo.toml", "runtime/renderer/src/bin"],
};

/// The newest modification time of the files under `sources`.
fn newest_source(root: &Path, sources: &[&str]) -> SystemTime {
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
    for p in sources {
        walk(&root.join(p), &mut newest);
    }
    newest
}

/// The `kiln` binary of this checkout (see [`binary`]).
fn kiln_binary(root: &Path) -> PathBuf {
    binary(root, &KILN)
}

/// A binary of this checkout, in this order:
/// 1. for `kiln`, `KILN_BIN`, when set (CI may point it at a binary it built);
/// 2. the binary in this test binary's profile folder (`target/<profile>/`, where
///    `cargo test --workspace` builds it for its package's own tests), or in the other
///    profile's, when it is newer than every source it is built from;
/// 3. otherwise `cargo build -p PACKAGE --bin NAME` into `<target>/docs-kiln`, a target folder
///    of its own so that it never waits on the lock of the `cargo test` running it (the
///    first time, a whole build of the package).
fn binary(root: &Path, bin: &Bin) -> PathBuf {
    if bin.name == "kiln" {
        if let Some(path) = std::env::var_os("KILN_BIN").filter(|b| !b.is_empty()) {
            return PathBuf::from(path);
        }
    }
    let exe = std::env::current_exe().expect("the test binary's path");
    // target/<profile>/deps/<test binary>
    let profile_dir = exe.parent().and_then(Path::parent).expect("target/<profile>/deps").to_path_buf();
    let target = profile_dir.parent().expect("target/").to_path_buf();
    let name = format!("{}{}", bin.name, std::env::consts::EXE_SUFFIX);
    let newest = newest_source(root, bin.sources);
    for dir in [profile_dir.clone(), target.join("release"), target.join("debug")] {
        let path = dir.join(&name);
        if path.metadata().and_then(|m| m.modified()).is_ok_and(|t| t >= newest) {
            return path;
        }
    }
    let own = target.join("docs-kiln");
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    let status = Command::new(cargo)
        .args(["build", "--locked", "-p", bin.package, "--bin", bin.name, "--target-dir"])
        .arg(&own)
        .current_dir(root)
        .status()
        .expect("cargo runs");
    assert!(status.success(), "cargo build -p {} --bin {} failed", bin.package, bin.name);
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

/// What one command's `--help` lists: its flags and its subcommands.
#[derive(Debug, Default, PartialEq)]
struct Help {
    /// Long flags (`--out`), and short flags that have no long form (`-D`).
    named: BTreeSet<String>,
    /// Every flag, long and short (`-o` too).
    all: BTreeSet<String>,
    subcommands: Vec<String>,
}

/// The flag names at the start of `spec` (`-o, --output <FILE>`): each `-x` and `--name`.
fn flag_names(spec: &str) -> Vec<String> {
    spec.split([',', ' '])
        .filter(|t| t.starts_with('-'))
        .map(|t| {
            let dashes = if t.starts_with("--") { 2 } else { 1 };
            let name: String =
                t[dashes..].chars().take_while(|c| c.is_ascii_alphanumeric() || *c == '-' || *c == '_').collect();
            format!("{}{name}", &t[..dashes])
        })
        .filter(|t| t.len() > 1 && !t.ends_with('-'))
        .collect()
}

/// Parses clap's help text: under `Commands:`, each entry's name (but `help`); under any
/// other heading (`Options:`, custom headings), each entry's flags, without `--help` and
/// `--version` (clap's own). Commands sit two spaces in, flags two to six (a long flag
/// alone is aligned with those after a short one); wrapped help text sits deeper.
fn parse_help(text: &str) -> Help {
    let mut help = Help::default();
    let mut section = "";
    for line in text.lines() {
        if !line.starts_with(' ') && line.trim_end().ends_with(':') {
            section = line.trim_end();
            continue;
        }
        let entry = line.trim_start_matches(' ');
        let indent = line.len() - entry.len();
        if section == "Commands:" && indent == 2 {
            let name = entry.split_whitespace().next().unwrap_or("");
            if name != "help" {
                help.subcommands.push(name.to_string());
            }
        } else if section != "Commands:" && (2..=6).contains(&indent) && entry.starts_with('-') {
            // The entry's flags end where its help text starts (two spaces or more).
            let spec = entry.split("  ").next().unwrap_or("");
            let names = flag_names(spec);
            let has_long = names.iter().any(|n| n.starts_with("--"));
            for n in names {
                if ["--help", "-h", "--version", "-V"].contains(&n.as_str()) {
                    continue;
                }
                if n.starts_with("--") || !has_long {
                    help.named.insert(n.clone());
                }
                help.all.insert(n);
            }
        }
    }
    help
}

/// Each command of a binary (its path of subcommands, empty for the binary itself) and its
/// help.
type HelpTree = Vec<(Vec<String>, Help)>;

/// `bin ARGS... --help`, parsed, for `path` and every subcommand under it, depth first:
/// `(["cache", "gc"], help)`.
fn help_tree(bin: &Path, path: Vec<String>, out: &mut HelpTree) {
    let output = Command::new(bin).args(&path).arg("--help").env("NO_COLOR", "1").output().expect("the binary runs");
    assert!(output.status.success(), "{} {} --help: {}", bin.display(), path.join(" "), output.status);
    let help = parse_help(&String::from_utf8_lossy(&output.stdout));
    let subcommands = help.subcommands.clone();
    out.push((path.clone(), help));
    for sub in subcommands {
        let mut next = path.clone();
        next.push(sub);
        help_tree(bin, next, out);
    }
}

/// The reference split at its `## ` headings: `(heading, body)`, the text before the first
/// heading under `""`.
fn reference_sections(text: &str) -> Vec<(String, String)> {
    let mut out = vec![(String::new(), String::new())];
    let prose: BTreeSet<usize> = prose_lines(text).into_iter().map(|(n, _)| n).collect();
    for (i, line) in text.lines().enumerate() {
        match line.strip_prefix("## ").filter(|_| prose.contains(&(i + 1))) {
            Some(heading) => out.push((heading.trim().to_string(), String::new())),
            None => {
                let body = &mut out.last_mut().expect("one at least").1;
                body.push_str(line);
                body.push('\n');
            }
        }
    }
    out
}

/// Whether `text` holds `flag` as a whole word (`--level` is not in `--levels`).
fn mentions(text: &str, flag: &str) -> bool {
    text.match_indices(flag).any(|(at, _)| {
        let before = text[..at].chars().next_back();
        let after = text[at + flag.len()..].chars().next();
        !before.is_some_and(|c| c.is_ascii_alphanumeric() || c == '-')
            && !after.is_some_and(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
    })
}

/// The flags written in `text` (`--name` and `-x`, each starting a word).
fn flags_in(text: &str) -> Vec<String> {
    let mut out = Vec::new();
    for (at, _) in text.match_indices('-') {
        let before = text[..at].chars().next_back();
        if before.is_some_and(|c| !matches!(c, ' ' | '[' | '(' | '|' | '`' | ',')) {
            continue;
        }
        let rest = &text[at..];
        let dashes = if rest.starts_with("--") { 2 } else { 1 };
        let name: String =
            rest[dashes..].chars().take_while(|c| c.is_ascii_alphanumeric() || *c == '-' || *c == '_').collect();
        let short_ok = dashes == 2 || name.chars().count() == 1;
        if !name.is_empty() && name.chars().next().is_some_and(|c| c.is_ascii_alphabetic()) && short_ok {
            out.push(format!("{}{name}", &rest[..dashes]));
        }
    }
    out
}

/// The reference's section for a command (`kiln build`, `kiln-view`; subcommands of a group
/// live in the group's section; `kiln` alone in the page's opening).
fn section_of(binary: &str, path: &[String]) -> String {
    match path.first() {
        Some(top) => format!("{binary} {top}"),
        None if binary == "kiln" => String::new(),
        None => binary.to_string(),
    }
}

/// Every gap between `docs/reference/cli.md` (`text`) and the commands' help (`trees`, per
/// binary): a flag or subcommand the page does not name in its section, a command without
/// a section, and a flag the page documents (in a table's first column or the synopsis) that
/// the command does not have. A flag whose row says `hidden` is documented on purpose.
fn reference_gaps(text: &str, trees: &[(&str, HelpTree)]) -> Vec<String> {
    let sections = reference_sections(text);
    let section = |name: &str| sections.iter().find(|(h, _)| h == name).map(|(_, body)| body.as_str());
    let mut problems = Vec::new();
    // Per section: the flags its commands have (a group's and its subcommands').
    let mut known: HashMap<String, BTreeSet<String>> = HashMap::new();
    for (binary, tree) in trees {
        for (path, help) in tree {
            let shown = [*binary].into_iter().chain(path.iter().map(String::as_str)).collect::<Vec<_>>().join(" ");
            let name = section_of(binary, path);
            known.entry(name.clone()).or_default().extend(help.all.iter().cloned());
            let Some(body) = section(&name) else {
                problems.push(format!("`{shown}` has no section `## {name}`"));
                continue;
            };
            for flag in &help.named {
                if !mentions(body, flag) {
                    problems.push(format!("`{shown} {flag}` is not in the section `## {name}`"));
                }
            }
            if !path.is_empty() {
                let spans = code_spans(body);
                for sub in &help.subcommands {
                    if !spans.iter().any(|s| s.split_whitespace().any(|w| w == sub)) {
                        problems.push(format!("`{shown} {sub}` is not in the section `## {name}`"));
                    }
                }
            }
        }
    }
    // Documented flags and commands that do not exist.
    for (heading, body) in &sections {
        let Some(flags) = known.get(heading) else {
            if heading.starts_with("kiln") {
                problems.push(format!("`## {heading}`: no such command"));
            }
            continue;
        };
        for line in body.lines().filter(|l| l.starts_with("| `") && !l.contains("hidden")) {
            let first = line.split('|').nth(1).unwrap_or("");
            for flag in flags_in(&strip_fences(first)) {
                if !flags.contains(&flag) {
                    problems.push(format!("`## {heading}` documents `{flag}`, which `{heading}` does not have"));
                }
            }
        }
    }
    for (line, command) in synopsis(section("").unwrap_or("")) {
        let name = command.split_whitespace().take(2).collect::<Vec<_>>().join(" ");
        let Some(flags) = known.get(&name) else {
            problems.push(format!("the synopsis's line {line} shows `{name}`: no such command"));
            continue;
        };
        for flag in flags_in(&command) {
            if !flags.contains(&flag) {
                problems.push(format!("the synopsis shows `{name} {flag}`, which does not exist"));
            }
        }
    }
    problems
}

/// `text` with its backticks dropped.
fn strip_fences(text: &str) -> String {
    text.replace('`', " ")
}

/// The contents of the code spans of `text` (between backticks, one line at a time).
fn code_spans(text: &str) -> Vec<String> {
    text.lines().flat_map(|l| l.split('`').skip(1).step_by(2).map(str::to_string).collect::<Vec<_>>()).collect()
}

/// The synopsis block (the opening's ```text block): each command with its continuation
/// lines, and the line it starts on within the opening.
fn synopsis(opening: &str) -> Vec<(usize, String)> {
    let mut out: Vec<(usize, String)> = Vec::new();
    let mut inside = false;
    for (i, line) in opening.lines().enumerate() {
        if line.starts_with("```") {
            inside = !inside && line.trim() == "```text";
            continue;
        }
        if !inside {
            continue;
        }
        if line.starts_with(' ') {
            if let Some(last) = out.last_mut() {
                last.1.push(' ');
                last.1.push_str(line.trim());
            }
        } else if !line.trim().is_empty() {
            out.push((i + 1, line.trim().to_string()));
        }
    }
    out
}

/// Issue 29: every command, subcommand and flag of `kiln` and `kiln-view` (from their
/// `--help`, so from the clap definitions) is in `docs/reference/cli.md`, and every flag the
/// page documents exists.
#[test]
fn the_cli_reference_matches_every_help() {
    let root = repo();
    let mut trees = Vec::new();
    for bin in [&KILN, &KILN_VIEW] {
        let mut tree = Vec::new();
        help_tree(&binary(&root, bin), Vec::new(), &mut tree);
        trees.push((bin.name, tree));
    }
    let kiln = &trees[0].1;
    assert!(
        kiln.len() > 10 && kiln.iter().any(|(p, h)| p == &["build"] && h.named.contains("--remote-cache")),
        "{kiln:#?}"
    );
    let text = std::fs::read_to_string(root.join("docs/reference/cli.md")).unwrap();
    let problems = reference_gaps(&text, &trees);
    assert!(problems.is_empty(), "docs/reference/cli.md is out of date:\n{}", problems.join("\n"));
}

#[test]
fn the_cli_reference_check_finds_what_it_should() {
    let top = "Usage: kiln <COMMAND>\n\nCommands:\n  build  Build\n          wrapped --not-a-flag\n  cache  Cache\n  help   Print this\n\nOptions:\n  -h, --help  Print help\n  -V, --version  Print version\n";
    assert_eq!(parse_help(top).subcommands, ["build", "cache"]);
    let build = parse_help(
        "Options:\n      --config <FILE>  The set\n  -o, --output <OUT>  The archive, see\n                      --level\n  -D <NAME>  Define\n      --no-cache\n          --wrapped-help-text\n  -h, --help  Print help\n",
    );
    assert_eq!(build.named.iter().collect::<Vec<_>>(), ["--config", "--no-cache", "--output", "-D"]);
    assert!(build.all.contains("-o") && !build.all.contains("--level"));
    let cache = parse_help("Commands:\n  stats  Stats\n  gc  GC\n\nOptions:\n      --cache-dir <DIR>  Dir\n");
    let gc = parse_help("Options:\n      --cache-dir <DIR>  Dir\n      --max-size <SIZE>\n");
    let trees = vec![(
        "kiln",
        vec![
            (vec![], parse_help(top)),
            (vec!["build".to_string()], build),
            (vec!["cache".to_string()], cache),
            (vec!["cache".to_string(), "gc".to_string()], gc),
        ],
    )];
    let page = "# CLI\n\n```text\nkiln build [--config FILE] [--gone]\n           [-o FILE]\nkiln old X\n```\n\n\
        ## kiln build\n\n| flag | meaning |\n| --- | --- |\n| `--config` | the set (`--levels` is elsewhere) |\n\
        | `--output`, `-o` | out |\n| `-D` | define |\n| `--stale` | gone |\n| `--secret` | hidden, for tests |\n\n\
        ## kiln cache\n\n`kiln cache --cache-dir DIR stats`\n\n## kiln removed\n";
    let problems = reference_gaps(page, &trees);
    assert_eq!(
        problems.iter().map(String::as_str).collect::<Vec<_>>(),
        [
            "`kiln build --no-cache` is not in the section `## kiln build`",
            "`kiln cache gc` is not in the section `## kiln cache`",
            "`kiln cache gc --max-size` is not in the section `## kiln cache`",
            "`## kiln build` documents `--stale`, which `kiln build` does not have",
            "`## kiln removed`: no such command",
            "the synopsis shows `kiln build --gone`, which does not exist",
            "the synopsis's line 6 shows `kiln old`: no such command",
        ],
        "{problems:#?}"
    );
}
