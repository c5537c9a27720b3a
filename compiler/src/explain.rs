//! `kiln explain`: everything Kiln knows about one permutation.

use std::fmt::Write;

use codespan_reporting::diagnostic::Diagnostic;

use crate::permute::{analyze, Config, Define, NotFound, Permutation, RuleResult, Shader};
use crate::preprocess::{self, FileId, SourceCache};

/// One permutation explained.
#[derive(Debug, Clone)]
pub struct Explanation {
    /// Its canonical name.
    pub name: String,
    /// Whether the skip rules keep it.
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
    /// The kept permutations of the same shader and level whose compacted module is this
    /// one's (the build runs the writers once for all of them), in enumeration order, itself
    /// included; `Err` with the reason when its module could not be made.
    pub module_group: Result<Vec<String>, String>,
    /// The preprocessing error, if it failed.
    pub error: Option<Diagnostic<FileId>>,
    /// All of the above as the text `kiln explain` prints.
    pub text: String,
}

/// The widest a column is padded to.
const MAX_COLUMN: usize = 64;

/// The most kept permutations of a shader at a level whose dedup group is computed.
const GROUP_LIMIT: u128 = 100_000;

/// Explains the permutation `name`: its defines and their origins, the skip rules, the files it
/// reads, its token hash and its deduplication group. Preprocesses every kept permutation of
/// its shader and level (for the group).
pub fn explain(config: &Config, cache: &SourceCache, name: &str) -> Result<Explanation, NotFound> {
    let p = config.find(name)?;
    let (files, hash, error) =
        match preprocess::preprocess_file(&p.shader.source_path, &p.preprocess_options(config), cache) {
            Ok(out) => (out.files.iter().map(|f| cache.name(*f)).collect(), Some(out.token_hash()), None),
            Err(e) => (Vec::new(), None, Some(e.diagnostic)),
        };
    let mut group = Vec::new();
    // The group preprocesses every kept permutation of the shader at the level: only when
    // there are few enough (counted over the dimensions the skip rules name).
    let kept = crate::permute::enumerate::count_kept(p.shader, p.level, 1 << 16);
    let grouped = kept.is_some_and(|k| k <= GROUP_LIMIT);
    if let (Some(hash), true) = (hash, grouped) {
        let analysis = analyze(config, cache, |s, l| std::ptr::eq(s, p.shader) && std::ptr::eq(l, p.level));
        if let Some(level) = analysis.levels.first() {
            group = level
                .group(hash)
                .map(|q| crate::permute::enumerate::canonical_name(p.shader, p.level, &q.values))
                .collect();
        }
    }

    let module_group = match hash {
        // Like the dedup group, it preprocesses every kept permutation of the shader.
        Some(_) if !grouped => Err(format!("not computed: over {GROUP_LIMIT} kept permutations")),
        Some(_) if p.is_kept() && p.error.is_none() => module_group(config, cache, &p),
        Some(_) => Err("not built".to_string()),
        None => Err("preprocessing failed".to_string()),
    };

    let mut e = Explanation {
        name: p.name(),
        kept: p.skipped_by.is_none(),
        defines: p.defines(),
        rules: p.skip_results(),
        files,
        hash,
        group,
        module_group,
        error,
        text: String::new(),
    };
    let mut t = String::new();
    write_header(&mut t, &e, &p, cache);
    write_defines(&mut t, &e.defines);
    write_rules(&mut t, &e.rules, p.shader);
    write_files(&mut t, &e.files);
    write_dedup_group(&mut t, &e, &p, grouped);
    write_module_group(&mut t, &e, &p);
    e.text = t;
    Ok(e)
}

/// The permutation's name, shader, source, level, status and error.
fn write_header(t: &mut String, e: &Explanation, p: &Permutation<'_>, cache: &SourceCache) {
    let s = p.shader;
    let l = p.level;
    let _ = writeln!(t, "{}", e.name);
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
}

/// The defines in effect, aligned in columns, with their origins.
fn write_defines(t: &mut String, defines: &[Define]) {
    let _ = writeln!(t, "\ndefines:");
    // Columns are aligned up to a width; a longer name runs past its column (a format width
    // must fit in a u16).
    let wn = defines.iter().map(|d| d.name.len()).max().unwrap_or(0).min(MAX_COLUMN);
    let wv = defines.iter().map(|d| d.value.to_string().len()).max().unwrap_or(0).min(MAX_COLUMN);
    if defines.is_empty() {
        let _ = writeln!(t, "  (none)");
    }
    for d in defines {
        let _ = writeln!(t, "  {:<wn$} = {:>wv$}  {}", d.name, d.value, d.origin);
    }
}

/// Each skip rule of the shader `s` and its verdict.
fn write_rules(t: &mut String, rules: &[RuleResult], s: &Shader) {
    let _ = writeln!(t, "\nskip rules:");
    if rules.is_empty() {
        let _ = writeln!(t, "  (none)");
    }
    for r in rules {
        let rule = &s.skip[r.index];
        let verdict = match &r.matched {
            Ok(true) => "matches".to_string(),
            Ok(false) => "does not match".to_string(),
            Err(e) => format!("cannot be evaluated: {e}"),
        };
        let _ = writeln!(t, "  {}. {}: {verdict} ({})", r.index + 1, rule.when, rule.why);
    }
}

/// The files preprocessing read.
fn write_files(t: &mut String, files: &[String]) {
    let _ = writeln!(t, "\nfiles read:");
    if files.is_empty() {
        let _ = writeln!(t, "  (none: preprocessing failed)");
    }
    for f in files {
        let _ = writeln!(t, "  {f}");
    }
}

/// The token hash and the permutations that share it (`grouped`: the group was computed).
fn write_dedup_group(t: &mut String, e: &Explanation, p: &Permutation<'_>, grouped: bool) {
    let Some(h) = e.hash else {
        let _ = writeln!(t, "\ntoken hash: (none: preprocessing failed)");
        return;
    };
    let (s, l) = (p.shader, p.level);
    let _ = writeln!(t, "\ntoken hash: {}", h.to_hex());
    let others = e.group.iter().filter(|g| **g != e.name).count();
    if !grouped {
        let _ =
            writeln!(t, "dedup group: not computed ({}@{} keeps more than {GROUP_LIMIT} permutations)", s.name, l.name);
    } else if others == 0 {
        let _ = writeln!(t, "dedup group: no other kept permutation of {}@{} has this token stream", s.name, l.name);
    } else {
        let _ = writeln!(
            t,
            "dedup group: {} kept permutation(s) of {}@{} have this token stream and compile once:",
            e.group.len(),
            s.name,
            l.name
        );
        for g in &e.group {
            let _ = writeln!(t, "  {g}{}", if *g == e.name { "  (this one)" } else { "" });
        }
    }
}

/// The permutations whose token streams differ but whose compacted module is this one's.
fn write_module_group(t: &mut String, e: &Explanation, p: &Permutation<'_>) {
    match &e.module_group {
        Ok(members) if members.len() > e.group.len() => {
            let _ = writeln!(
                t,
                "compacted module: {} kept permutation(s) of {}@{} compact to this one's module (their token streams differ \
                 only in code the entry point never reaches); the writers run once for all of them:",
                members.len(),
                p.shader.name,
                p.level.name
            );
            for g in members {
                let _ = writeln!(t, "  {g}{}", if *g == e.name { "  (this one)" } else { "" });
            }
        }
        Ok(_) => {
            let _ = writeln!(t, "compacted module: shared with no permutation of another token stream");
        }
        Err(why) => {
            let _ = writeln!(t, "compacted module: (none: {why})");
        }
    }
}

/// The kept permutations of `p`'s shader and level whose compacted module equals `p`'s
/// ([`crate::compile::module_hash`]): each distinct token stream is parsed and validated once.
fn module_group(
    config: &Config,
    cache: &SourceCache,
    p: &crate::permute::Permutation<'_>,
) -> Result<Vec<String>, String> {
    use rayon::prelude::*;
    use std::collections::HashMap;

    let options = crate::compile::Options::for_level(p.level, &[]);
    let same = |q: &crate::permute::Permutation<'_>| std::ptr::eq(q.shader, p.shader) && std::ptr::eq(q.level, p.level);
    let kept: Vec<crate::permute::Permutation<'_>> = config
        .permutations_where(|s, l| std::ptr::eq(s, p.shader) && std::ptr::eq(l, p.level))
        .filter(|q| same(q) && q.is_kept() && q.error.is_none())
        .collect();
    // Each permutation's compacted module, its text dropped once hashed (every kept text at
    // once would grow with the set); each distinct token stream is validated
    // once (two threads may both validate one: the same answer).
    let modules: std::sync::Mutex<HashMap<blake3::Hash, Result<blake3::Hash, String>>> = Default::default();
    let of: Vec<Option<Result<blake3::Hash, String>>> = kept
        .par_iter()
        .map(|q| {
            let o = preprocess::preprocess_file(&q.shader.source_path, &q.preprocess_options(config), cache).ok()?;
            let h = o.token_hash();
            if let Some(m) = modules.lock().expect("no panics while locked").get(&h) {
                return Some(m.clone());
            }
            let module = crate::compile::validate(&o.text, &p.shader.entry, p.shader.stage, &options.limits)
                .map(|v| crate::compile::module_hash(&v, &options))
                .map_err(|e| format!("it does not compile: {e}"));
            modules.lock().expect("no panics while locked").insert(h, module.clone());
            Some(module)
        })
        .collect();
    drop(modules);
    let name = p.name();
    let index = kept.iter().position(|q| q.name() == name).ok_or("not built")?;
    let own = of[index].clone().ok_or("preprocessing failed")??;
    Ok(kept.iter().zip(&of).filter(|(_, m)| matches!(m, Some(Ok(m)) if *m == own)).map(|(q, _)| q.name()).collect())
}
