//! What changed between two permutation sets, each an archive or a `permutations.toml`:
//! per shader, the permutations added and removed (by canonical name), the distinct sources,
//! and for archives the artifact bytes per target. `kiln diff` prints it as text, a Markdown
//! table for a pull request comment, or JSON.
//!
//! Distinct sources: of an archive, the distinct sets of artifacts among a shader's
//! permutations (what its compiles produced); of a configuration, the distinct preprocessed
//! token streams (what a build would compile), found by preprocessing every kept
//! permutation. Bytes: each blob as stored in the archive (compressed), counted once, for
//! the first shader in the archive's order that uses it.

use std::collections::{BTreeMap, BTreeSet, HashSet};
use std::fmt::Write as _;
use std::path::Path;

use serde_json::json;

use crate::archive::Archive;
use crate::permute;
use crate::preprocess::SourceCache;

/// One shader of a [`Summary`].
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ShaderSummary {
    /// Canonical names of its permutations (kept ones, for a configuration).
    pub permutations: BTreeSet<String>,
    /// Distinct sources; `None` where unknown (a configuration not analysed).
    pub distinct: Option<u64>,
    /// Stored bytes of its artifacts, by target name (archives only).
    pub bytes: BTreeMap<String, u64>,
}

/// A permutation set as `kiln diff` compares it.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Summary {
    /// Each shader's permutations, by shader name.
    pub shaders: BTreeMap<String, ShaderSummary>,
    /// Stored artifact bytes by target name, with each target's dictionary (archives only).
    pub bytes: BTreeMap<String, u64>,
    /// The archive file's bytes (archives only).
    pub file_bytes: Option<u64>,
}

impl Summary {
    /// An archive's permutations, distinct artifact sets and bytes.
    pub fn from_archive(path: &Path) -> Result<Summary, String> {
        let archive = Archive::open(path).map_err(|e| format!("cannot read archive {}: {e}", path.display()))?;
        let mut summary = Summary { file_bytes: std::fs::metadata(path).ok().map(|m| m.len()), ..Summary::default() };
        let mut seen = HashSet::new();
        let mut sets: BTreeMap<String, HashSet<Vec<u32>>> = BTreeMap::new();
        let permutations =
            archive.permutations().map_err(|e| format!("cannot read archive {}: {e}", path.display()))?;
        for p in permutations {
            let shader = p.shader().name.clone();
            let entry = summary.shaders.entry(shader.clone()).or_default();
            entry.permutations.insert(p.name().to_string());
            let mut set = Vec::new();
            for target in p.targets() {
                let Some(id) = p.blob_id(target) else { continue };
                set.push(id.0);
                if seen.insert(id) {
                    let stored = archive.blob_info(id).map(|b| b.stored_len).unwrap_or(0);
                    *entry.bytes.entry(target.name().to_string()).or_default() += stored;
                    *summary.bytes.entry(target.name().to_string()).or_default() += stored;
                }
            }
            sets.entry(shader).or_default().insert(set);
        }
        // A target's dictionary is shared by all its blobs: counted in the total only.
        for (target, len) in archive.dictionaries() {
            *summary.bytes.entry(target.name().to_string()).or_default() += len;
        }
        for (shader, set) in sets {
            if let Some(s) = summary.shaders.get_mut(&shader) {
                s.distinct = Some(set.len() as u64);
            }
        }
        Ok(summary)
    }

    /// A configuration's kept permutations and, with `analyze`, its distinct sources
    /// (preprocessing every kept permutation; none where one fails to preprocess).
    pub fn from_config(path: &Path, analyze: bool) -> Result<Summary, String> {
        let config = permute::load(path).map_err(|e| e.render())?;
        let mut summary = Summary::default();
        for p in config.kept_where(|_, _| true) {
            summary.shaders.entry(p.shader.name.clone()).or_default().permutations.insert(p.name());
        }
        if analyze {
            let cache = SourceCache::new(config.dir.clone());
            let analysis = permute::analyze(&config, &cache, |_, _| true);
            for level in &analysis.levels {
                if let Some(s) = summary.shaders.get_mut(&level.shader) {
                    s.distinct = Some(0);
                }
            }
            for level in &analysis.levels {
                let ok = level.permutations.iter().all(|p| p.hash.is_some());
                if let Some(s) = summary.shaders.get_mut(&level.shader) {
                    s.distinct = s.distinct.filter(|_| ok).map(|d| d + level.distinct as u64);
                }
            }
        }
        Ok(summary)
    }

    /// An archive (`.kpak` or anything not `.toml`) or a configuration (`.toml`).
    pub fn load(path: &Path, analyze: bool) -> Result<Summary, String> {
        match path.extension().and_then(|e| e.to_str()) {
            Some("toml") => Summary::from_config(path, analyze),
            _ => Summary::from_archive(path),
        }
    }
}

/// Old and new of one number.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Change<T> {
    /// In the old set.
    pub old: T,
    /// In the new set.
    pub new: T,
}

/// One shader's changes.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ShaderDiff {
    /// Canonical names in the new set only, sorted.
    pub added: Vec<String>,
    /// Canonical names in the old set only, sorted.
    pub removed: Vec<String>,
    /// Its permutations.
    pub permutations: Change<u64>,
    /// Its distinct sources (`None` where a side was not analysed).
    pub distinct: Change<Option<u64>>,
    /// Stored bytes by target, where either side has some.
    pub bytes: BTreeMap<String, Change<u64>>,
}

impl ShaderDiff {
    /// Whether nothing of the shader changed: no permutation added or removed, the same
    /// distinct sources and bytes.
    pub fn is_unchanged(&self) -> bool {
        self.added.is_empty()
            && self.removed.is_empty()
            && self.distinct.old == self.distinct.new
            && self.bytes.values().all(|c| c.old == c.new)
    }
}

/// What changed from one [`Summary`] to another.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Diff {
    /// Per shader of either set, by name.
    pub shaders: BTreeMap<String, ShaderDiff>,
    /// Stored bytes by target, with its dictionary (archives only).
    pub bytes: BTreeMap<String, Change<u64>>,
    /// The archive files' bytes (archives only).
    pub file_bytes: Change<Option<u64>>,
}

impl Diff {
    /// What changed from `old` to `new`, per shader.
    pub fn new(old: &Summary, new: &Summary) -> Diff {
        let empty = ShaderSummary::default();
        let names: BTreeSet<&String> = old.shaders.keys().chain(new.shaders.keys()).collect();
        let mut shaders = BTreeMap::new();
        for name in names {
            let (o, n) = (old.shaders.get(name).unwrap_or(&empty), new.shaders.get(name).unwrap_or(&empty));
            let distinct = Change {
                old: if old.shaders.contains_key(name) { o.distinct } else { Some(0) },
                new: if new.shaders.contains_key(name) { n.distinct } else { Some(0) },
            };
            shaders.insert(
                name.clone(),
                ShaderDiff {
                    added: n.permutations.difference(&o.permutations).cloned().collect(),
                    removed: o.permutations.difference(&n.permutations).cloned().collect(),
                    permutations: Change { old: o.permutations.len() as u64, new: n.permutations.len() as u64 },
                    distinct,
                    bytes: changes(&o.bytes, &n.bytes),
                },
            );
        }
        Diff {
            shaders,
            bytes: changes(&old.bytes, &new.bytes),
            file_bytes: Change { old: old.file_bytes, new: new.file_bytes },
        }
    }

    /// Permutations added, over every shader.
    pub fn added(&self) -> usize {
        self.shaders.values().map(|s| s.added.len()).sum()
    }

    /// Permutations removed, over every shader.
    pub fn removed(&self) -> usize {
        self.shaders.values().map(|s| s.removed.len()).sum()
    }

    fn permutations(&self) -> Change<u64> {
        let sum = |f: fn(&ShaderDiff) -> u64| self.shaders.values().map(f).sum();
        Change { old: sum(|s| s.permutations.old), new: sum(|s| s.permutations.new) }
    }

    fn distinct(&self) -> Change<Option<u64>> {
        let sum = |f: fn(&ShaderDiff) -> Option<u64>| self.shaders.values().map(f).sum::<Option<u64>>();
        Change { old: sum(|s| s.distinct.old), new: sum(|s| s.distinct.new) }
    }

    /// One line per changed shader, then the totals.
    pub fn to_text(&self) -> String {
        let mut out = String::new();
        let mut unchanged = 0;
        for (name, s) in &self.shaders {
            if s.is_unchanged() {
                unchanged += 1;
                continue;
            }
            let _ =
                write!(out, "{name}: {}", line(s.permutations, s.added.len(), s.removed.len(), s.distinct, &s.bytes));
            out.push('\n');
        }
        if unchanged > 0 {
            let _ = writeln!(out, "({unchanged} shaders unchanged)");
        }
        let _ = writeln!(
            out,
            "total: {}",
            line(self.permutations(), self.added(), self.removed(), self.distinct(), &self.bytes)
        );
        if let Change { old: Some(o), new: Some(n) } = self.file_bytes {
            let _ = writeln!(out, "archive: {o} -> {n} bytes ({})", signed(n as i128 - o as i128));
        }
        out
    }

    /// A Markdown table (changed shaders, then the total) for a pull request comment.
    pub fn to_markdown(&self) -> String {
        let targets: Vec<&String> = self.bytes.keys().collect();
        let mut out = String::from("| Shader | Permutations | Added | Removed | Distinct |");
        for t in &targets {
            let _ = write!(out, " {t} bytes |");
        }
        out.push_str("\n|---|---:|---:|---:|---:|");
        out.push_str(&"---:|".repeat(targets.len()));
        out.push('\n');
        let row = |out: &mut String,
                   name: &str,
                   p: Change<u64>,
                   a: usize,
                   r: usize,
                   d: Change<Option<u64>>,
                   b: &BTreeMap<String, Change<u64>>| {
            let _ = write!(out, "| {name} | {} → {} | +{a} | −{r} | {} |", p.old, p.new, opt_change(d));
            for t in &targets {
                let c = b.get(*t).copied().unwrap_or_default();
                let _ = write!(out, " {} → {} ({}) |", c.old, c.new, signed(c.new as i128 - c.old as i128));
            }
            out.push('\n');
        };
        for (name, s) in self.shaders.iter().filter(|(_, s)| !s.is_unchanged()) {
            row(&mut out, &format!("`{name}`"), s.permutations, s.added.len(), s.removed.len(), s.distinct, &s.bytes);
        }
        row(&mut out, "**total**", self.permutations(), self.added(), self.removed(), self.distinct(), &self.bytes);
        out
    }

    /// `{"added": N, "removed": N, "permutations": [old, new], "distinct": [old, new],
    /// "bytes": {target: [old, new]}, "archive_bytes": [old, new], "shaders": {NAME: {...}}}`;
    /// each shader with the same fields and its `added_names` / `removed_names`.
    pub fn to_json(&self) -> serde_json::Value {
        let pair = |c: Change<u64>| json!([c.old, c.new]);
        let bytes = |b: &BTreeMap<String, Change<u64>>| -> serde_json::Map<String, serde_json::Value> {
            b.iter().map(|(t, c)| (t.clone(), pair(*c))).collect()
        };
        let shaders: serde_json::Map<String, serde_json::Value> = self
            .shaders
            .iter()
            .map(|(name, s)| {
                let v = json!({
                    "added": s.added.len(), "removed": s.removed.len(),
                    "permutations": pair(s.permutations), "distinct": [s.distinct.old, s.distinct.new],
                    "bytes": bytes(&s.bytes), "added_names": s.added, "removed_names": s.removed,
                });
                (name.clone(), v)
            })
            .collect();
        let d = self.distinct();
        json!({
            "added": self.added(), "removed": self.removed(),
            "permutations": pair(self.permutations()), "distinct": [d.old, d.new],
            "bytes": bytes(&self.bytes), "archive_bytes": [self.file_bytes.old, self.file_bytes.new],
            "shaders": shaders,
        })
    }
}

fn changes(old: &BTreeMap<String, u64>, new: &BTreeMap<String, u64>) -> BTreeMap<String, Change<u64>> {
    let keys: BTreeSet<&String> = old.keys().chain(new.keys()).collect();
    keys.into_iter()
        .map(|k| (k.clone(), Change { old: old.get(k).copied().unwrap_or(0), new: new.get(k).copied().unwrap_or(0) }))
        .collect()
}

fn signed(n: i128) -> String {
    if n >= 0 {
        format!("+{n}")
    } else {
        n.to_string()
    }
}

fn opt_change(c: Change<Option<u64>>) -> String {
    let s = |v: Option<u64>| v.map_or("?".to_string(), |v| v.to_string());
    format!("{} → {}", s(c.old), s(c.new))
}

fn line(
    p: Change<u64>,
    added: usize,
    removed: usize,
    d: Change<Option<u64>>,
    b: &BTreeMap<String, Change<u64>>,
) -> String {
    let mut out = format!(
        "permutations {} -> {} (+{added} -{removed}), distinct {}",
        p.old,
        p.new,
        opt_change(d).replace('→', "->")
    );
    for (t, c) in b {
        let _ = write!(out, ", {t} {} -> {} bytes ({})", c.old, c.new, signed(c.new as i128 - c.old as i128));
    }
    out
}
