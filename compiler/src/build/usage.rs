//! Builds from usage: `--usage FILE...` (usage files as a renderer's pipeline cache records
//! them, `kiln_archive::usage`) preprocesses, and so compiles, the recorded permutations
//! first (after the first permutation of each shader and level); `--usage-only` which keeps of the configuration's kept
//! permutations only those a file recorded, those a `[usage] keep` pattern matches and those
//! of shaders with `always = true`. The others are left out: counted per shader, named in
//! the archive (which says it is partial, so that a lookup of one is an error naming it) and
//! in the build's fingerprint. What is kept depends only on the configuration and the files'
//! contents, never on `-j`, the cache or shards.
//!
//! `--usage` also gives the archive its pipeline manifest: the merged files' pipelines whose
//! permutations the archive holds, in first-use order (first frame, then key); the others
//! are counted in the build's note.

use std::collections::{BTreeMap, HashSet};

use super::{Error, Options};
use crate::archive::usage::{Usage, UsageKey};
use crate::archive::PipelineRecord;
use crate::permute::{Config, Permutation};

/// What the usage files and the configuration keep.
pub(super) struct Filter {
    recorded: HashSet<String>,
    keep: Vec<String>,
    /// Only the recorded and kept ones are built (`--usage-only`).
    only: bool,
    /// The merged files' pipelines, in first-use order.
    pipelines: Vec<PipelineRecord>,
}

/// Per shader: (permutations built that the filter kept, permutations left out).
#[derive(Clone, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct ShaderUsage {
    /// Permutations built.
    pub used: usize,
    /// Permutations left out.
    pub left_out: usize,
}

/// What a build from usage kept and left out.
#[derive(Clone, Debug, Default)]
pub(super) struct Outcome {
    /// Canonical names left out, in enumeration order.
    pub left_out: Vec<String>,
    pub shaders: BTreeMap<String, ShaderUsage>,
    /// Permutations built because a file recorded them (the rest: patterns and `always`).
    pub recorded: usize,
    /// Recorded names that are no kept permutation of the configuration.
    pub unknown: usize,
    /// Recorded names the build keeps (and so the archive holds).
    pub built_recorded: HashSet<String>,
    /// The archive's pipeline manifest: the recorded pipelines whose permutations it holds.
    pub pipelines: Vec<PipelineRecord>,
    /// Recorded pipelines left out of the manifest: a permutation of theirs is not built.
    pub pipelines_left_out: usize,
}

impl Filter {
    /// The filter of `options`; `None` without `--usage`.
    pub fn load(config: &Config, options: &Options) -> Result<Option<Filter>, Error> {
        if options.usage.is_empty() {
            if options.usage_only {
                return Err(Error::Config("error: --usage-only needs at least one --usage FILE".into()));
            }
            return Ok(None);
        }
        let mut merged: Option<Usage> = None;
        for path in &options.usage {
            let text = std::fs::read_to_string(path)
                .map_err(|e| Error::Config(format!("error: cannot read usage file {}: {e}", path.display())))?;
            let u = Usage::parse(&text).map_err(|e| Error::Config(format!("error: {}: {e}", path.display())))?;
            match &mut merged {
                None => merged = Some(u),
                Some(m) => m.merge(&u).map_err(|e| Error::Config(format!("error: {}: {e}", path.display())))?,
            }
        }
        let merged = merged.unwrap_or_default();
        let recorded = merged.permutations().into_iter().map(str::to_string).collect();
        let mut pipelines: Vec<PipelineRecord> = merged
            .records
            .iter()
            .map(|(key, count)| PipelineRecord { key: key.clone(), first_frame: count.first_frame })
            .collect();
        pipelines.sort_by(|a, b| (a.first_frame, &a.key).cmp(&(b.first_frame, &b.key)));
        Ok(Some(Filter { recorded, keep: config.usage_keep.clone(), only: options.usage_only, pipelines }))
    }

    /// Whether `p` (named `name`) is built, counting it in `outcome`.
    pub fn keeps(&self, p: &Permutation<'_>, name: &str, outcome: &mut Outcome) -> bool {
        let recorded = self.recorded.contains(name);
        let kept = recorded || p.shader.always || self.keep.iter().any(|pattern| matches(pattern, name));
        let s = outcome.shaders.entry(p.shader.name.clone()).or_default();
        outcome.recorded += usize::from(recorded);
        if kept || !self.only {
            s.used += usize::from(kept);
            if recorded {
                outcome.built_recorded.insert(name.to_string());
            }
            true
        } else {
            s.left_out += 1;
            outcome.left_out.push(name.to_string());
            false
        }
    }

    /// Whether a usage file records `name`.
    pub fn records(&self, name: &str) -> bool {
        self.recorded.contains(name)
    }

    /// Recorded permutations that no kept permutation matched (renamed or skipped since).
    pub fn unknown(&self, outcome: &Outcome) -> usize {
        self.recorded.len().saturating_sub(outcome.recorded)
    }

    /// Fills `outcome`'s pipeline manifest: the recorded pipelines whose every permutation
    /// the build keeps, in first-use order, and counts the others.
    pub fn manifest(&self, outcome: &mut Outcome) {
        let built = |key: &UsageKey| key.permutations().iter().all(|n| outcome.built_recorded.contains(*n));
        let (kept, left): (Vec<&PipelineRecord>, Vec<&PipelineRecord>) =
            self.pipelines.iter().partition(|r| built(&r.key));
        outcome.pipelines = kept.into_iter().cloned().collect();
        outcome.pipelines_left_out = left.len();
    }
}

impl Outcome {
    /// The line the build prints: what was left out, per shader.
    pub fn summary(&self, only: bool) -> String {
        let used: usize = self.shaders.values().map(|s| s.used).sum();
        let mut s = match only {
            true => format!("note: --usage-only built {used} permutations and left out {}", self.left_out.len()),
            false => format!("note: the usage files record {} of the permutations built", self.recorded),
        };
        let out: Vec<String> = self
            .shaders
            .iter()
            .filter(|(_, u)| u.left_out > 0)
            .map(|(n, u)| format!("{n} {} of {}", u.left_out, u.left_out + u.used))
            .collect();
        if only && !out.is_empty() {
            s.push_str(&format!(": {}", out.join(", ")));
        }
        s.push_str(&format!("\nnote: the archive's pipeline manifest holds {} pipelines", self.pipelines.len()));
        if self.pipelines_left_out > 0 {
            s.push_str(&format!(
                "; {} recorded pipelines are left out of it (a permutation of theirs is not in the archive)",
                self.pipelines_left_out
            ));
        }
        if self.unknown > 0 {
            s.push_str(&format!(
                "\nwarning: {} recorded permutations are not kept permutations of the set (renamed or skipped since \
                 the recording)",
                self.unknown
            ));
        }
        s
    }
}

/// Whether `name` matches `pattern`: `*` any run of characters, `?` any one, the rest itself.
pub fn matches(pattern: &str, name: &str) -> bool {
    let (p, n): (Vec<char>, Vec<char>) = (pattern.chars().collect(), name.chars().collect());
    // The classic two-pointer glob: on a mismatch, go back to the last `*` and let it take
    // one more character.
    let (mut i, mut j, mut star, mut mark) = (0, 0, None, 0);
    while j < n.len() {
        if i < p.len() && (p[i] == '?' || p[i] == n[j]) {
            i += 1;
            j += 1;
        } else if i < p.len() && p[i] == '*' {
            star = Some(i);
            mark = j;
            i += 1;
        } else if let Some(s) = star {
            i = s + 1;
            mark += 1;
            j = mark;
        } else {
            return false;
        }
    }
    p[i..].iter().all(|&c| c == '*')
}

#[cfg(test)]
mod tests {
    use super::matches;

    #[test]
    fn patterns() {
        assert!(matches("ScreenVS@*", "ScreenVS@sm5{}"));
        assert!(matches("*@es3_1{*FULLY_ROUGH=1*}", "MobileBasePassPS@es3_1{FULLY_ROUGH=1,X=2}"));
        assert!(!matches("*@es3_1{*FULLY_ROUGH=1*}", "MobileBasePassPS@es3_1{FULLY_ROUGH=0,X=2}"));
        assert!(matches("A?C", "ABC") && !matches("A?C", "AC"));
        assert!(matches("*", "") && !matches("A", "AB"));
    }
}
