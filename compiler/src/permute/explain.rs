//! `kiln explain`: everything Kiln knows about one permutation.

use std::fmt::Write;

use codespan_reporting::diagnostic::Diagnostic;

use super::{analyze, Config, Define, NotFound, RuleResult};
use crate::preprocess::{self, FileId, SourceCache};

/// One permutation explained.
#[derive(Debug, Clone)]
pub struct Explanation {
    /// Its canonical name.
    pub name: String,
    pub kept: bool,
    /// Every define in effect, with its origin.
    pub defines: Vec<Define>,
    /// Every skip rule and whether it matched.
    pub rules: Vec<RuleResult>,
    /// The files preprocessing read (main file first), named relative to the config's folder.
    pub files: Vec<String>,
    /// The hash of its preprocessed token stream (`None` when preprocessing failed).
    pub hash: Option<blake3::Hash>,
    /// The kept permutations of the same shader and level with the same token stream, in
    /// enumeration order (itself included when kept).
    pub group: Vec<String>,
    /// The preprocessing error, if it failed.
    pub error: Option<Diagnostic<FileId>>,
    /// All of the above as the text `kiln explain` prints.
    pub text: String,
}

/// Explains the permutation `name`: its defines and their origins, the skip rules, the files it
/// reads, its token hash and its deduplication group. Preprocesses every kept permutation of
/// its shader and level (for the group).
pub fn explain(config: &Config, cache: &SourceCache, name: &str) -> Result<Explanation, NotFound> {
    let p = config.find(name)?;
    let name = p.name();
    let defines = p.defines();
    let rules = p.skip_results();
    let (files, hash, error) =
        match preprocess::preprocess_file(&p.shader.source_path, &p.preprocess_options(config), cache) {
            Ok(out) => (out.files.iter().map(|f| cache.name(*f)).collect(), Some(out.token_hash()), None),
            Err(e) => (Vec::new(), None, Some(e.diagnostic)),
        };
    let mut group = Vec::new();
    if let Some(hash) = hash {
        let analysis = analyze(config, cache, |s, l| std::ptr::eq(s, p.shader) && std::ptr::eq(l, p.level));
        if let Some(level) = analysis.levels.first() {
            group = level.group(hash).map(|q| super::enumerate::canonical_name(p.shader, p.level, &q.values)).collect();
        }
    }

    let mut t = String::new();
    let s = p.shader;
    let l = p.level;
    let _ = writeln!(t, "{name}");
    let _ = writeln!(t, "  shader:  {} ({}, entry {})", s.name, s.stage, s.entry);
    let _ = writeln!(t, "  source:  {} ({})", s.source, cache.display_name(&s.source_path));
    let targets: Vec<&str> = l.targets.iter().map(|t| t.name()).collect();
    let mut limits = l.limits.name().to_string();
    for (field, value) in &l.limit_overrides {
        limits.push_str(&format!(", {field} = {value}"));
    }
    let _ = writeln!(t, "  level:   {} (targets: {}; limits: {limits})", l.name, targets.join(", "));
    match p.skipped_by {
        None => {
            let _ = writeln!(t, "  status:  kept");
        }
        Some(i) => {
            let _ = writeln!(t, "  status:  skipped by rule {} ({}): not built", i + 1, s.skip[i].why);
        }
    }
    if let Some(e) = &p.error {
        let _ = writeln!(t, "  error:   {e}");
    }

    let _ = writeln!(t, "\ndefines:");
    let wn = defines.iter().map(|d| d.name.len()).max().unwrap_or(0);
    let wv = defines.iter().map(|d| d.value.to_string().len()).max().unwrap_or(0);
    if defines.is_empty() {
        let _ = writeln!(t, "  (none)");
    }
    for d in &defines {
        let _ = writeln!(t, "  {:<wn$} = {:>wv$}  {}", d.name, d.value, d.origin);
    }

    let _ = writeln!(t, "\nskip rules:");
    if rules.is_empty() {
        let _ = writeln!(t, "  (none)");
    }
    for r in &rules {
        let rule = &s.skip[r.index];
        let verdict = match &r.matched {
            Ok(true) => "matches".to_string(),
            Ok(false) => "does not match".to_string(),
            Err(e) => format!("cannot be evaluated: {e}"),
        };
        let _ = writeln!(t, "  {}. {}: {verdict} ({})", r.index + 1, rule.when, rule.why);
    }

    let _ = writeln!(t, "\nfiles read:");
    if files.is_empty() {
        let _ = writeln!(t, "  (none: preprocessing failed)");
    }
    for f in &files {
        let _ = writeln!(t, "  {f}");
    }

    match hash {
        Some(h) => {
            let _ = writeln!(t, "\ntoken hash: {}", h.to_hex());
            let others = group.iter().filter(|g| **g != name).count();
            if others == 0 {
                let _ = writeln!(
                    t,
                    "dedup group: no other kept permutation of {}@{} has this token stream",
                    s.name, l.name
                );
            } else {
                let _ = writeln!(
                    t,
                    "dedup group: {} kept permutation(s) of {}@{} have this token stream and compile once:",
                    group.len(),
                    s.name,
                    l.name
                );
                for g in &group {
                    let _ = writeln!(t, "  {g}{}", if *g == name { "  (this one)" } else { "" });
                }
            }
        }
        None => {
            let _ = writeln!(t, "\ntoken hash: (none: preprocessing failed)");
        }
    }

    Ok(Explanation { name, kept: p.skipped_by.is_none(), defines, rules, files, hash, group, error, text: t })
}
