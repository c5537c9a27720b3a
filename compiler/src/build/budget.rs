//! Budgets in a build: `[budget]` and each shader's `budget`, checked as soon as what they
//! count is known: kept permutations after the plan, distinct keys and the estimated compile
//! time after grouping (before anything compiles), archive bytes once the archive is written
//! (it stays, so that `kiln diff` can show what grew). Each check is one
//! [`crate::permute::BudgetExceeded`], exit code 3.

use super::group::Keys;
use super::plan::{level_targets, Plan};
use super::preprocess::Preprocessed;
use super::{Error, Options};
use crate::permute::budget::{estimate_compile_ms, Measure};
use crate::permute::{BudgetExceeded, Config, Level, Shader};

fn exceeded(e: BudgetExceeded, options: &Options) -> Error {
    Error::Budget(e.render_with(options.color))
}

fn filter(options: &Options) -> impl Fn(&Shader, &Level) -> bool + '_ {
    |_: &Shader, l: &Level| options.levels.is_empty() || options.levels.contains(&l.name)
}

/// The index of `shader` in the configuration.
fn index(config: &Config, shader: &Shader) -> usize {
    config.shaders.iter().position(|s| std::ptr::eq(s, shader)).unwrap_or(0)
}

/// Adds `n` to shader `i`'s count.
fn add(counts: &mut Vec<(usize, u64)>, i: usize, n: u64) {
    match counts.iter_mut().find(|(s, _)| *s == i) {
        Some((_, c)) => *c += n,
        None => counts.push((i, n)),
    }
}

/// Kept permutations against the shaders' budgets and `[budget] max_permutations`.
pub(super) fn permutations(config: &Config, plan: &Plan<'_>, options: &Options) -> Result<(), Error> {
    let mut counts = Vec::new();
    for (shader, _, range) in plan.runs() {
        add(&mut counts, index(config, shader), range.len() as u64);
    }
    config.check_permutation_budget(&counts, &filter(options)).map_err(|e| exceeded(e, options))
}

/// Distinct keys against `max_distinct` and their estimated compile time against
/// `max_compile_ms`; the estimate, when one is asked for.
pub(super) fn keys(
    config: &Config,
    plan: &Plan<'_>,
    pre: &Preprocessed,
    keys: &Keys<'_>,
    options: &Options,
) -> Result<Option<f64>, Error> {
    let budget = &config.budget;
    if budget.max_distinct.is_none() && budget.max_compile_ms.is_none() {
        return Ok(None);
    }
    let mut distinct = Vec::new();
    let mut ms = Vec::new();
    let mut text_lens = Vec::with_capacity(pre.row_count());
    pre.each_row(|r| text_lens.push(r.text_len)).map_err(super::preprocess::read_back)?;
    let mut total_ms = 0.0;
    for k in 0..keys.len() {
        let members = keys.members(k);
        let (shader, level) = plan.shader_level(members[0] as usize);
        let i = index(config, shader);
        add(&mut distinct, i, 1);
        let len = members.iter().filter_map(|&m| pre.row_number(m as usize)).map(|r| u64::from(text_lens[r])).max();
        let key_ms = estimate_compile_ms(len.unwrap_or(0), level_targets(level, &options.targets).len());
        total_ms += key_ms;
        match ms.iter_mut().find(|(s, _): &&mut (usize, f64)| *s == i) {
            Some((_, m)) => *m += key_ms,
            None => ms.push((i, key_ms)),
        }
    }
    let filter = filter(options);
    config
        .check_budget(Measure::Distinct, keys.len() as u64, &distinct, &filter, Vec::new())
        .map_err(|e| exceeded(e, options))?;
    let ms: Vec<(usize, u64)> = ms.into_iter().map(|(i, m)| (i, m.round() as u64)).collect();
    let note = format!(
        "the estimate counts every distinct key once, on one core, whether the cache holds it or not ({} keys)",
        keys.len()
    );
    config
        .check_budget(Measure::CompileMs, total_ms.round() as u64, &ms, &filter, vec![note])
        .map_err(|e| exceeded(e, options))?;
    Ok(Some(total_ms))
}

/// The archive's bytes against `max_archive_bytes`, with its bytes per target and per
/// shader (each blob counted for the first shader that uses it).
pub(super) fn archive(config: &Config, path: &std::path::Path, options: &Options) -> Result<(), Error> {
    let Some(limit) = &config.budget.max_archive_bytes else { return Ok(()) };
    let bytes = std::fs::metadata(path).map(|m| m.len()).unwrap_or(0);
    if bytes <= limit.value {
        return Ok(());
    }
    let sizes = crate::diff::Summary::from_archive(path).map_err(|e| Error::Io(format!("error: {e}")))?;
    let per_shader: Vec<(usize, u64)> = config
        .shaders
        .iter()
        .enumerate()
        .filter_map(|(i, s)| sizes.shaders.get(&s.name).map(|sh| (i, sh.bytes.values().sum())))
        .collect();
    let targets: Vec<String> = sizes.bytes.iter().map(|(t, b)| format!("{t} {b}")).collect();
    let notes =
        vec![format!("artifact and dictionary bytes by target: {}; the rest is the manifest", targets.join(", "))];
    config
        .check_budget(Measure::ArchiveBytes, bytes, &per_shader, &filter(options), notes)
        .map_err(|e| exceeded(e, options))
}
