//! Budgets: `[budget]` in `permutations.toml` and a shader's `budget = { max_permutations = N }`.
//!
//! Takes the counts a build (or `kiln list --check-budget`) found: kept permutations per
//! shader, distinct keys, archive bytes, an estimate of compile time; gives a
//! [`BudgetExceeded`] with one diagnostic per limit gone over, located at that limit in the
//! toml file, naming the shader that weighs most, the dimension that multiplied it and by
//! how much. Exit code 3 (DESIGN.md's codes are 1 for a shader, 2 for usage).
//!
//! A dimension's multiplier is the shader's kept permutations divided by the distinct value
//! tuples of its other dimensions (and levels): exactly its number of values for a full
//! product, less where skip rules drop part of it.

use std::collections::HashSet;
use std::fmt::Write as _;
use std::ops::Range;

use codespan_reporting::diagnostic::{Diagnostic, Label};

use super::{Config, ConfigError, Level, Shader};

/// One limit and where it is written.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BudgetLimit {
    /// The most the measure may reach.
    pub value: u64,
    /// Its value in the toml text.
    pub span: Range<usize>,
}

/// `[budget]`: what a build may grow to. Every limit is optional.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Budget {
    /// Kept permutations of every shader and level built.
    pub max_permutations: Option<BudgetLimit>,
    /// Distinct keys (compiles) among them.
    pub max_distinct: Option<BudgetLimit>,
    /// Bytes of the archive file.
    pub max_archive_bytes: Option<BudgetLimit>,
    /// The estimated single-core compile time of every distinct key, in milliseconds
    /// ([`estimate_compile_ms`]), whether the cache holds it or not.
    pub max_compile_ms: Option<BudgetLimit>,
}

/// A shader's `budget = { max_permutations = N }`: its kept permutations over its levels.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ShaderBudget {
    /// Kept permutations of the shader, over its levels.
    pub max_permutations: Option<BudgetLimit>,
}

impl Config {
    /// Whether any budget is set, in `[budget]` or on a shader.
    pub fn has_budget(&self) -> bool {
        let b = &self.budget;
        b.max_permutations.is_some()
            || b.max_distinct.is_some()
            || b.max_archive_bytes.is_some()
            || b.max_compile_ms.is_some()
            || self.shaders.iter().any(|s| s.budget.max_permutations.is_some())
    }
}

/// Over budget: one diagnostic per limit gone over, against the toml file. Exit code 3.
#[derive(Debug, Clone, thiserror::Error)]
#[error("{0}")]
pub struct BudgetExceeded(pub ConfigError);

impl BudgetExceeded {
    /// Every diagnostic, rendered (ANSI colours when `color`).
    pub fn render_with(&self, color: bool) -> String {
        self.0.render_with(color)
    }
}

/// The estimated single-core milliseconds to compile a key whose preprocessed text is
/// `text_len` bytes, for `targets` targets: the cost the build balances shards by (text
/// length times targets), at a fixed rate of WGSL per target (naga parse and validation plus
/// one writer, as measured on the development machines). A constant,
/// so that a budget passes or fails alike whatever the machine, `-j` or the cache holds.
pub fn estimate_compile_ms(text_len: u64, targets: usize) -> f64 {
    text_len as f64 * targets.max(1) as f64 / 15_000.0
}

/// What is counted against a `[budget]` limit, with its unit for messages.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Measure {
    /// Distinct keys, the compiles (`max_distinct`).
    Distinct,
    /// Bytes of the archive file (`max_archive_bytes`).
    ArchiveBytes,
    /// Estimated single-core compile milliseconds (`max_compile_ms`).
    CompileMs,
}

impl Measure {
    fn limit(self, b: &Budget) -> Option<&BudgetLimit> {
        match self {
            Measure::Distinct => b.max_distinct.as_ref(),
            Measure::ArchiveBytes => b.max_archive_bytes.as_ref(),
            Measure::CompileMs => b.max_compile_ms.as_ref(),
        }
    }
    fn key(self) -> &'static str {
        match self {
            Measure::Distinct => "max_distinct",
            Measure::ArchiveBytes => "max_archive_bytes",
            Measure::CompileMs => "max_compile_ms",
        }
    }
    fn what(self) -> &'static str {
        match self {
            Measure::Distinct => "distinct sources (compiles)",
            Measure::ArchiveBytes => "archive bytes",
            Measure::CompileMs => "estimated compile ms",
        }
    }
}

type Filter<'f> = &'f dyn Fn(&Shader, &Level) -> bool;

impl Config {
    /// Kept permutations of each shader `filter` accepts, over its levels, by shader index
    /// (file order; shaders with none left out).
    pub fn kept_counts(&self, filter: Filter<'_>) -> Vec<(usize, u64)> {
        let mut counts: Vec<(usize, u64)> = Vec::new();
        for p in self.kept_where(filter) {
            let i = self.shaders.iter().position(|s| std::ptr::eq(s, p.shader)).unwrap_or(0);
            match counts.last_mut() {
                Some((s, n)) if *s == i => *n += 1,
                _ => counts.push((i, 1)),
            }
        }
        counts
    }

    /// Checks every shader's `budget.max_permutations` and `[budget] max_permutations`
    /// against `counts` ([`Config::kept_counts`]).
    pub fn check_permutation_budget(&self, counts: &[(usize, u64)], filter: Filter<'_>) -> Result<(), BudgetExceeded> {
        let mut diagnostics = Vec::new();
        for &(i, n) in counts {
            let shader = &self.shaders[i];
            let Some(limit) = shader.budget.max_permutations.as_ref().filter(|l| n > l.value) else { continue };
            let mut d = Diagnostic::error()
                .with_message(format!(
                    "shader `{}` keeps {n} permutations, over its budget of {} by {}",
                    shader.name,
                    limit.value,
                    n - limit.value
                ))
                .with_labels(vec![
                    Label::primary((), limit.span.clone()).with_message(format!("budget: {}", limit.value))
                ]);
            self.explain_growth(&mut d, shader, n, filter);
            d.notes.push(format!(
                "raise `budget = {{ max_permutations = N }}` of shader `{}`, skip more, or drop a dimension",
                shader.name
            ));
            diagnostics.push(d);
        }
        let total: u64 = counts.iter().map(|c| c.1).sum();
        if let Some(limit) = self.budget.max_permutations.as_ref().filter(|l| total > l.value) {
            diagnostics.push(self.over_total("permutations", "max_permutations", limit, total, counts, filter));
        }
        self.exceeded(diagnostics)
    }

    /// Checks a `[budget]` limit other than `max_permutations`: `total` against it, with
    /// `per_shader` (by shader index) saying which shaders weigh most; `notes` are added.
    pub fn check_budget(
        &self,
        measure: Measure,
        total: u64,
        per_shader: &[(usize, u64)],
        filter: Filter<'_>,
        notes: Vec<String>,
    ) -> Result<(), BudgetExceeded> {
        let Some(limit) = measure.limit(&self.budget).filter(|l| total > l.value) else { return Ok(()) };
        let mut d = self.over_total(measure.what(), measure.key(), limit, total, per_shader, filter);
        d.notes.splice(0..0, notes);
        self.exceeded(vec![d])
    }

    fn exceeded(&self, diagnostics: Vec<Diagnostic<()>>) -> Result<(), BudgetExceeded> {
        match diagnostics.is_empty() {
            true => Ok(()),
            false => Err(BudgetExceeded(self.error(diagnostics))),
        }
    }

    /// A `[budget]` limit gone over: located at the limit, the heaviest shader and its
    /// heaviest dimension labelled, the shaders listed by weight.
    fn over_total(
        &self,
        what: &str,
        key: &str,
        limit: &BudgetLimit,
        total: u64,
        per_shader: &[(usize, u64)],
        filter: Filter<'_>,
    ) -> Diagnostic<()> {
        let mut d = Diagnostic::error()
            .with_message(format!(
                "the set has {total} {what}, over its `[budget] {key}` of {} by {}",
                limit.value,
                total - limit.value
            ))
            .with_labels(vec![Label::primary((), limit.span.clone()).with_message(format!("budget: {}", limit.value))]);
        let mut heaviest: Vec<(usize, u64)> = per_shader.to_vec();
        heaviest.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
        if let Some(&(i, n)) = heaviest.first() {
            let shader = &self.shaders[i];
            d.labels.push(Label::secondary((), shader.spans.name.clone()).with_message(format!(
                "`{}` has {n} of them ({:.0}%)",
                shader.name,
                n as f64 * 100.0 / total.max(1) as f64
            )));
            let kept = self.kept_counts(&|s: &Shader, l: &Level| std::ptr::eq(s, shader) && filter(s, l));
            self.explain_growth(&mut d, shader, kept.first().map_or(0, |c| c.1), filter);
        }
        let mut list = String::from("by shader: ");
        for (k, (i, n)) in heaviest.iter().take(8).enumerate() {
            let _ = write!(list, "{}{} {n}", if k > 0 { ", " } else { "" }, self.shaders[*i].name);
        }
        if heaviest.len() > 8 {
            let _ = write!(list, " and {} more", heaviest.len() - 8);
        }
        d.notes.push(list);
        d
    }

    /// Labels the dimension that multiplies `shader`'s `kept` permutations most, and notes
    /// what each dimension (and its levels) multiplies them by.
    fn explain_growth(&self, d: &mut Diagnostic<()>, shader: &Shader, kept: u64, filter: Filter<'_>) {
        let factors = self.multipliers(shader, filter);
        let heaviest = factors
            .iter()
            .enumerate()
            .take(shader.dimensions.len())
            .max_by(|a, b| a.1 .1.partial_cmp(&b.1 .1).unwrap_or(std::cmp::Ordering::Equal).then(b.0.cmp(&a.0)));
        if let Some((k, (name, f))) = heaviest.filter(|(_, (_, f))| *f > 1.0) {
            let without = (kept as f64 / f).round();
            if let Some(span) = shader.spans.each_dimension.get(k) {
                d.labels.push(Label::secondary((), span.clone()).with_message(format!(
                    "`{name}` multiplies `{}` by {}: {without} permutations without it",
                    shader.name,
                    factor(*f).trim_start_matches('×')
                )));
            }
        }
        if !factors.is_empty() {
            let each: Vec<String> = factors.iter().map(|(n, f)| format!("{n} {}", factor(*f))).collect();
            d.notes.push(format!("`{}` keeps {kept}: {}", shader.name, each.join(", ")));
        }
    }

    /// How much each dimension of `shader` (then its levels, as `levels`) multiplies its kept
    /// permutations at the levels `filter` accepts: kept permutations over the distinct
    /// value tuples of the other dimensions.
    pub fn multipliers(&self, shader: &Shader, filter: Filter<'_>) -> Vec<(String, f64)> {
        let n = shader.dimensions.len();
        let mut without: Vec<HashSet<(usize, Vec<i64>)>> = vec![HashSet::new(); n + 1];
        let mut kept = 0u64;
        for p in self.kept_where(|s, l| std::ptr::eq(s, shader) && filter(s, l)) {
            kept += 1;
            let level = shader.levels.iter().position(|l| *l == p.level.name).unwrap_or(0);
            for (d, set) in without.iter_mut().enumerate().take(n) {
                let mut v = p.values.clone();
                v.remove(d);
                set.insert((level, v));
            }
            without[n].insert((0, p.values.clone()));
        }
        let ratio = |set: &HashSet<(usize, Vec<i64>)>| kept as f64 / set.len().max(1) as f64;
        let mut out: Vec<(String, f64)> =
            shader.dimensions.iter().zip(&without).map(|(d, set)| (d.name.clone(), ratio(set))).collect();
        if without[n].len() as u64 != kept {
            out.push(("levels".to_string(), ratio(&without[n])));
        }
        out
    }
}

/// `×4`, or `×2.5` for a multiplier skip rules made fractional.
fn factor(f: f64) -> String {
    if (f - f.round()).abs() < 0.005 {
        format!("×{}", f.round())
    } else {
        format!("×{f:.2}")
    }
}
