//! Enumeration: an odometer over each shader's dimension indices, skip rules and derived
//! defines evaluated per permutation by the preprocessor's `#if` evaluator.

use super::{Config, ConfigError, Dimension, Level, Shader};
use crate::preprocess::{self, expr};

/// Where a define in effect comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum DefineOrigin {
    /// The feature level's `defines`.
    Level(String),
    /// The shader's constant `defines` (`overrides`: the level's value it replaces).
    Shader {
        /// The level's value it replaces, if any.
        overrides: Option<i64>,
    },
    /// A dimension's value.
    Dimension,
    /// `DIM_NAME` of an enum dimension: the index of `NAME`.
    EnumValue {
        /// The enum dimension.
        dimension: String,
    },
    /// A derived define and its expression.
    Derived {
        /// The `#if` expression it is defined by.
        expr: String,
    },
}

impl std::fmt::Display for DefineOrigin {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            DefineOrigin::Level(l) => write!(f, "level {l}"),
            DefineOrigin::Shader { overrides: None } => f.write_str("shader"),
            DefineOrigin::Shader { overrides: Some(v) } => write!(f, "shader (overrides the level's {v})"),
            DefineOrigin::Dimension => f.write_str("dimension"),
            DefineOrigin::EnumValue { dimension } => write!(f, "enum value of {dimension}"),
            DefineOrigin::Derived { expr } => write!(f, "derived: {expr}"),
        }
    }
}

/// One define in effect in a permutation.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Define {
    /// The define's name.
    pub name: String,
    /// Its value.
    pub value: i64,
    /// Where the value comes from.
    pub origin: DefineOrigin,
}

/// Whether one skip rule matched a permutation.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RuleResult {
    /// Index into `shader.skip`.
    pub index: usize,
    /// `Ok(matched)`, or the evaluation error (such as a division by zero).
    pub matched: Result<bool, String>,
}

/// One (shader, level, dimension values).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Permutation<'c> {
    /// Its shader.
    pub shader: &'c Shader,
    /// Its level.
    pub level: &'c Level,
    /// One value per dimension of `shader`, in declared order (an enum's index).
    pub values: Vec<i64>,
    /// The first skip rule that matched (index into `shader.skip`), if any.
    pub skipped_by: Option<usize>,
    /// The value of each derived define of `shader`, in order.
    pub derived: Vec<i64>,
    /// An expression that could not be evaluated for these values (a division by zero): the
    /// rule or define and the message. Such a permutation is kept (a rule that cannot be
    /// evaluated skips nothing) and the build should report it as a configuration error.
    pub error: Option<String>,
    /// Where in the toml text the expression of `error` is.
    pub error_span: Option<std::ops::Range<usize>>,
}

/// The names every expression of a shader at a level sees before dimensions: the level's
/// defines, the shader's (overriding), an enum's `DIM_NAME`s.
fn base_defines(shader: &Shader, level: &Level) -> Vec<Define> {
    let mut out: Vec<Define> = level
        .defines
        .iter()
        .map(|(n, v)| Define { name: n.clone(), value: *v, origin: DefineOrigin::Level(level.name.clone()) })
        .collect();
    for (n, v) in &shader.defines {
        let overrides = out.iter().position(|d| &d.name == n).map(|i| out.remove(i).value);
        out.push(Define { name: n.clone(), value: *v, origin: DefineOrigin::Shader { overrides } });
    }
    for d in &shader.dimensions {
        for (i, label) in d.labels.iter().enumerate() {
            out.push(Define {
                name: format!("{}_{label}", d.name),
                value: i as i64,
                origin: DefineOrigin::EnumValue { dimension: d.name.clone() },
            });
        }
    }
    out
}

/// Evaluation scope: (name, value) pairs, later ones win.
struct Scope<'a> {
    names: Vec<(&'a str, i64)>,
}

impl<'a> Scope<'a> {
    fn lookup(&self, name: &str) -> Option<i64> {
        self.names.iter().rev().find(|(n, _)| *n == name).map(|(_, v)| *v)
    }

    fn eval(&self, e: &str) -> Result<i64, String> {
        expr::eval(e, &|n| self.lookup(n)).map_err(|e| e.message)
    }
}

/// Applies skip rules and derived defines to `values`.
fn evaluate<'c>(shader: &'c Shader, level: &'c Level, base: &[Define], values: Vec<i64>) -> Permutation<'c> {
    let mut scope = Scope { names: Vec::with_capacity(base.len() + values.len() + shader.derived.len()) };
    scope.names.extend(base.iter().map(|d| (d.name.as_str(), d.value)));
    for (d, v) in shader.dimensions.iter().zip(&values) {
        scope.names.push((d.name.as_str(), *v));
    }
    let mut skipped_by = None;
    let mut error = None;
    let mut error_span = None;
    for (i, rule) in shader.skip.iter().enumerate() {
        match scope.eval(&rule.when) {
            Ok(0) => {}
            Ok(_) => {
                skipped_by = Some(i);
                break;
            }
            Err(e) => {
                if error.is_none() {
                    error = Some(format!("skip rule {} (`{}`): {e}", i + 1, rule.when));
                    error_span = Some(rule.span.clone());
                }
            }
        }
    }
    let mut derived = Vec::with_capacity(shader.derived.len());
    for (i, (name, e)) in shader.derived.iter().enumerate() {
        let v = match scope.eval(e) {
            Ok(v) => v,
            Err(msg) => {
                if error.is_none() {
                    error = Some(format!("derived define {name} (`{e}`): {msg}"));
                    error_span = shader.spans.derived.get(i).cloned();
                }
                0
            }
        };
        derived.push(v);
        scope.names.push((name.as_str(), v));
    }
    Permutation { shader, level, values, skipped_by, derived, error, error_span }
}

impl<'c> Permutation<'c> {
    /// Builds the permutation of `shader` at `level` with these values (one per dimension,
    /// each in its domain), evaluating skip rules and derived defines.
    pub fn new(shader: &'c Shader, level: &'c Level, values: Vec<i64>) -> Self {
        evaluate(shader, level, &base_defines(shader, level), values)
    }

    /// `Shader@level{DIM=value,...}` (`Shader@level{}` without dimensions).
    pub fn name(&self) -> String {
        canonical_name(self.shader, self.level, &self.values)
    }

    /// Whether no skip rule matched (errors count as not matched).
    pub fn is_kept(&self) -> bool {
        self.skipped_by.is_none()
    }

    /// (dimension, value as it appears in the name), in declared order.
    pub fn values_display(&self) -> Vec<(&'c str, String)> {
        self.shader.dimensions.iter().zip(&self.values).map(|(d, v)| (d.name.as_str(), d.display(*v))).collect()
    }

    /// Every skip rule, and whether it matched (all of them are evaluated, not only up to the first match).
    pub fn skip_results(&self) -> Vec<RuleResult> {
        let base = base_defines(self.shader, self.level);
        let mut scope = Scope { names: base.iter().map(|d| (d.name.as_str(), d.value)).collect() };
        for (d, v) in self.shader.dimensions.iter().zip(&self.values) {
            scope.names.push((d.name.as_str(), *v));
        }
        self.shader
            .skip
            .iter()
            .enumerate()
            .map(|(index, r)| RuleResult { index, matched: scope.eval(&r.when).map(|v| v != 0) })
            .collect()
    }

    /// Every define in effect: the level's, the shader's, the dimensions (with an enum's
    /// `DIM_NAME`s), the derived ones; each with its origin, in that order.
    pub fn defines(&self) -> Vec<Define> {
        let mut out = base_defines(self.shader, self.level);
        // Enum names come after their dimension in the listing.
        let enum_names: Vec<Define> =
            out.iter().filter(|d| matches!(d.origin, DefineOrigin::EnumValue { .. })).cloned().collect();
        out.retain(|d| !matches!(d.origin, DefineOrigin::EnumValue { .. }));
        for (d, v) in self.shader.dimensions.iter().zip(&self.values) {
            out.push(Define { name: d.name.clone(), value: *v, origin: DefineOrigin::Dimension });
            out.extend(
                enum_names
                    .iter()
                    .filter(|e| matches!(&e.origin, DefineOrigin::EnumValue { dimension } if *dimension == d.name))
                    .cloned(),
            );
        }
        for ((name, e), v) in self.shader.derived.iter().zip(&self.derived) {
            out.push(Define { name: name.clone(), value: *v, origin: DefineOrigin::Derived { expr: e.clone() } });
        }
        out
    }

    /// [`Config::preprocess_options`] plus this permutation's defines.
    pub fn preprocess_options(&self, config: &Config) -> preprocess::Options {
        let mut o = config.preprocess_options();
        o.defines = self.defines().into_iter().map(|d| (d.name, d.value.to_string())).collect();
        o
    }
}

/// The canonical name of `shader` at `level` with `values`.
pub fn canonical_name(shader: &Shader, level: &Level, values: &[i64]) -> String {
    let mut s = String::with_capacity(shader.name.len() + level.name.len() + 2 + 16 * values.len());
    s.push_str(&shader.name);
    s.push('@');
    s.push_str(&level.name);
    s.push('{');
    for (i, (d, v)) in shader.dimensions.iter().zip(values).enumerate() {
        if i > 0 {
            s.push(',');
        }
        s.push_str(&d.name);
        s.push('=');
        s.push_str(&d.display(*v));
    }
    s.push('}');
    s
}

/// Which (shader, level) pairs a stream enumerates.
type Filter<'c> = Box<dyn Fn(&Shader, &Level) -> bool + 'c>;

/// The lazy stream of [`Config::permutations`].
pub struct Permutations<'c> {
    config: &'c Config,
    filter: Filter<'c>,
    shader: usize,
    level: usize,
    /// The current (shader, level) and the defines its expressions see before dimensions.
    current: Option<(&'c Shader, &'c Level, Vec<Define>)>,
    /// Index into each dimension's values; `None` before the first permutation of a (shader, level).
    odometer: Option<Vec<usize>>,
}

impl<'c> Permutations<'c> {
    pub(super) fn new(config: &'c Config, filter: impl Fn(&Shader, &Level) -> bool + 'c) -> Self {
        Permutations { config, filter: Box::new(filter), shader: 0, level: 0, current: None, odometer: None }
    }

    /// Moves to the next (shader, level) the filter accepts, from (`self.shader`, `self.level`).
    fn enter(&mut self) -> bool {
        while let Some(shader) = self.config.shaders.get(self.shader) {
            while let Some(level_name) = shader.levels.get(self.level) {
                let Some(level) = self.config.level(level_name) else {
                    self.level += 1;
                    continue;
                };
                if (self.filter)(shader, level) {
                    let base = base_defines(shader, level);
                    self.current = Some((shader, level, base));
                    self.odometer = None;
                    return true;
                }
                self.level += 1;
            }
            self.shader += 1;
            self.level = 0;
        }
        self.current = None;
        false
    }
}

impl<'c> Iterator for Permutations<'c> {
    type Item = Permutation<'c>;

    fn next(&mut self) -> Option<Permutation<'c>> {
        loop {
            if self.current.is_none() && !self.enter() {
                return None;
            }
            let (shader, level, _) = self.current.as_ref().expect("entered");
            let (shader, level): (&'c Shader, &'c Level) = (shader, level);
            let dims: &'c [Dimension] = &shader.dimensions;
            let advanced = match &mut self.odometer {
                None => {
                    self.odometer = Some(vec![0; dims.len()]);
                    true
                }
                Some(od) => {
                    // Last dimension fastest.
                    let mut i = od.len();
                    loop {
                        if i == 0 {
                            break false;
                        }
                        i -= 1;
                        od[i] += 1;
                        if od[i] < dims[i].values.len() {
                            break true;
                        }
                        od[i] = 0;
                    }
                }
            };
            if !advanced {
                self.current = None;
                self.level += 1;
                continue;
            }
            let od = self.odometer.as_ref().expect("set above");
            let values: Vec<i64> = od.iter().zip(dims).map(|(i, d)| d.values[*i]).collect();
            let base = &self.current.as_ref().expect("entered").2;
            return Some(evaluate(shader, level, base, values));
        }
    }
}

/// The default of `[compiler] max_permutations` and `--max-permutations`: 2^24 permutations
/// of one shader at one level, or of all together.
pub const DEFAULT_MAX_PERMUTATIONS: u64 = 1 << 24;

/// Rule evaluations [`Config::check_space`] may spend counting what a space over the limit
/// keeps before it gives up (a few seconds at most).
const COUNT_BUDGET: u64 = 1 << 20;

/// Rule evaluations [`Kept`] spends, on entering a (shader, level), looking for a space its
/// rules skip entirely.
const ENTRY_BUDGET: u64 = 1 << 16;

/// The skip rules of one (shader, level), each placed at the depth of a walk over the
/// dimensions (in a given order) where every dimension it names is bound: there its value
/// is decided for the whole subtree below.
struct Pruner<'c> {
    shader: &'c Shader,
    base: Vec<Define>,
    /// The dimension bound at each depth.
    order: Vec<usize>,
    /// The conditions decided once `depth` dimensions are bound, for depth 0..=order.len():
    /// each a rule, or one operand of a rule's top-level `||` (which skips alone).
    rules_at: Vec<Vec<String>>,
}

/// The operands of the top-level `||` of an `#if` expression (the expression itself when it
/// has none, or has a top-level `?:`, which binds looser than `||`). Each operand that is
/// nonzero makes the whole expression 1.
fn disjuncts(expr: &str) -> Vec<String> {
    let tokens = crate::preprocess::tokens(expr);
    let mut depth = 0i32;
    let mut parts: Vec<Vec<&str>> = vec![Vec::new()];
    for t in &tokens {
        match *t {
            "(" => depth += 1,
            ")" => depth -= 1,
            "?" | ":" if depth == 0 => return vec![expr.to_string()],
            "||" if depth == 0 => {
                parts.push(Vec::new());
                continue;
            }
            _ => {}
        }
        parts.last_mut().expect("one part at least").push(t);
    }
    if parts.len() < 2 || parts.iter().any(Vec::is_empty) {
        return vec![expr.to_string()];
    }
    parts.into_iter().map(|p| p.join(" ")).collect()
}

impl<'c> Pruner<'c> {
    fn new(shader: &'c Shader, level: &'c Level, order: Vec<usize>) -> Self {
        let mut rules_at = vec![Vec::new(); order.len() + 1];
        for rule in &shader.skip {
            for condition in disjuncts(&rule.when) {
                let depth = expr::identifiers(&condition)
                    .iter()
                    .filter_map(|id| shader.dimensions.iter().position(|d| &d.name == id))
                    .map(|dim| order.iter().position(|&o| o == dim).map_or(order.len(), |at| at + 1))
                    .max()
                    .unwrap_or(0);
                rules_at[depth].push(condition);
            }
        }
        Pruner { shader, base: base_defines(shader, level), order, rules_at }
    }

    /// Whether a rule decided at `depth` (with `od[k]` the value index of the dimension bound
    /// at depth k) skips everything below. A rule that cannot be evaluated skips nothing.
    fn skips(&self, depth: usize, od: &[usize]) -> bool {
        let rules = &self.rules_at[depth];
        if rules.is_empty() {
            return false;
        }
        let mut scope = Scope { names: Vec::with_capacity(self.base.len() + depth) };
        scope.names.extend(self.base.iter().map(|d| (d.name.as_str(), d.value)));
        for (k, &dim) in self.order.iter().enumerate().take(depth) {
            let d = &self.shader.dimensions[dim];
            scope.names.push((d.name.as_str(), d.values[od[k]]));
        }
        rules.iter().any(|c| matches!(scope.eval(c), Ok(v) if v != 0))
    }
}

/// A depth-first walk over value indices, pruned by a predicate on prefixes.
struct Walker {
    sizes: Vec<usize>,
    od: Vec<usize>,
    /// How many leading entries of `od` are bound.
    depth: usize,
    started: bool,
}

impl Walker {
    fn new(sizes: Vec<usize>) -> Self {
        Walker { od: vec![0; sizes.len()], sizes, depth: 0, started: false }
    }

    /// The number of leaves below a node at `depth`.
    fn leaves_below(&self, depth: usize) -> u128 {
        self.sizes[depth..].iter().fold(1u128, |n, &s| n.saturating_mul(s as u128))
    }

    /// Moves to the next leaf (`od` complete) no pruned prefix covers; `pruned(depth, od)` is
    /// asked about each new prefix of length 1 or more, and the leaves of every pruned
    /// subtree are added to `skipped`. False when the walk is over.
    fn next_leaf(&mut self, pruned: &mut dyn FnMut(usize, &[usize]) -> bool, skipped: &mut u128) -> bool {
        let mut new_prefix = if self.started {
            if !self.advance() {
                return false;
            }
            true
        } else {
            self.started = true;
            if self.sizes.contains(&0) {
                return false;
            }
            false
        };
        loop {
            if new_prefix && pruned(self.depth, &self.od) {
                *skipped = skipped.saturating_add(self.leaves_below(self.depth));
                if !self.advance() {
                    return false;
                }
                continue;
            }
            if self.depth == self.sizes.len() {
                return true;
            }
            self.od[self.depth] = 0;
            self.depth += 1;
            new_prefix = true;
        }
    }

    /// The next sibling of the deepest bound prefix, going up as needed.
    fn advance(&mut self) -> bool {
        while self.depth > 0 {
            let i = self.depth - 1;
            self.od[i] += 1;
            if self.od[i] < self.sizes[i] {
                return true;
            }
            self.depth -= 1;
        }
        false
    }
}

/// The (shader, level) pairs of a configuration `filter` accepts, in enumeration order.
fn groups<'c>(
    config: &'c Config,
    filter: impl Fn(&Shader, &Level) -> bool + 'c,
) -> impl Iterator<Item = (&'c Shader, &'c Level)> + 'c {
    config
        .shaders
        .iter()
        .flat_map(move |s| s.levels.iter().filter_map(move |l| config.level(l)).map(move |l| (s, l)))
        .filter(move |(s, l)| filter(s, l))
}

/// The number of permutations of `shader` before skip rules (saturating).
pub fn nominal(shader: &Shader) -> u128 {
    shader.dimensions.iter().fold(1u128, |n, d| n.saturating_mul(d.values.len() as u128))
}

/// The lazy stream of [`Config::kept_where`]: the kept permutations in the order of
/// [`Config::permutations`], skipping whole subtrees a rule decides on the dimensions bound
/// so far (a rule naming only the first dimensions prunes early), counting what it skips.
pub struct Kept<'c> {
    groups: Box<dyn Iterator<Item = (&'c Shader, &'c Level)> + 'c>,
    current: Option<(&'c Shader, &'c Level, Pruner<'c>, Walker)>,
    skipped: u128,
}

impl<'c> Kept<'c> {
    pub(super) fn new(config: &'c Config, filter: impl Fn(&Shader, &Level) -> bool + 'c) -> Self {
        Kept { groups: Box::new(groups(config, filter)), current: None, skipped: 0 }
    }

    /// The permutations skipped so far (saturating).
    pub fn skipped(&self) -> u128 {
        self.skipped
    }
}

impl<'c> Iterator for Kept<'c> {
    type Item = Permutation<'c>;

    fn next(&mut self) -> Option<Permutation<'c>> {
        loop {
            if self.current.is_none() {
                let (shader, level) = self.groups.next()?;
                let pruner = Pruner::new(shader, level, (0..shader.dimensions.len()).collect());
                // Rules may name only late dimensions: counting over the named ones first
                // (cheaply, when it can) finds a space that keeps nothing without walking it.
                if pruner.skips(0, &[]) || count_kept(shader, level, ENTRY_BUDGET) == Some(0) {
                    self.skipped = self.skipped.saturating_add(nominal(shader));
                    continue;
                }
                let walker = Walker::new(shader.dimensions.iter().map(|d| d.values.len()).collect());
                self.current = Some((shader, level, pruner, walker));
            }
            let (shader, level, pruner, walker) = self.current.as_mut().expect("set above");
            let mut skipped = 0;
            let found = walker.next_leaf(&mut |depth, od| pruner.skips(depth, od), &mut skipped);
            self.skipped = self.skipped.saturating_add(skipped);
            if !found {
                self.current = None;
                continue;
            }
            let values = walker.od.iter().zip(&shader.dimensions).map(|(i, d)| d.values[*i]).collect();
            let p = evaluate(shader, level, &pruner.base, values);
            if p.is_kept() {
                return Some(p);
            }
            self.skipped += 1;
        }
    }
}

/// How many permutations of `shader` at `level` its skip rules keep, counted over only the
/// dimensions the rules name (the others multiply the count); `None` when that takes more
/// than `budget` rule evaluations.
pub(crate) fn count_kept(shader: &Shader, level: &Level, budget: u64) -> Option<u128> {
    let named: Vec<usize> = (0..shader.dimensions.len())
        .filter(|&i| {
            let name = &shader.dimensions[i].name;
            shader.skip.iter().any(|r| expr::identifiers(&r.when).iter().any(|id| id == name))
        })
        .collect();
    let free: u128 = (0..shader.dimensions.len())
        .filter(|i| !named.contains(i))
        .fold(1u128, |n, i| n.saturating_mul(shader.dimensions[i].values.len() as u128));
    let pruner = Pruner::new(shader, level, named.clone());
    if pruner.skips(0, &[]) {
        return Some(0);
    }
    let mut walker = Walker::new(named.iter().map(|&i| shader.dimensions[i].values.len()).collect());
    let mut spent = 0u64;
    let mut kept = 0u128;
    let mut skipped = 0u128;
    loop {
        let mut over = false;
        let found = walker.next_leaf(
            &mut |depth, od| {
                spent += 1;
                if spent > budget {
                    over = true;
                    return true; // stop descending; the answer is dropped below
                }
                pruner.skips(depth, od)
            },
            &mut skipped,
        );
        if over {
            return None;
        }
        if !found {
            return Some(kept);
        }
        kept = kept.saturating_add(free);
    }
}

/// `2^k (n)` for a power of two, else `n`.
fn describe_count(n: u128) -> String {
    if n == u128::MAX {
        "more than 2^128".to_string()
    } else if n.is_power_of_two() && n >= 1024 {
        format!("2^{} ({n})", n.trailing_zeros())
    } else {
        n.to_string()
    }
}

impl Config {
    /// The (shader, level) pairs `filter` accepts, in enumeration order.
    pub fn groups_where<'c>(
        &'c self,
        filter: impl Fn(&Shader, &Level) -> bool + 'c,
    ) -> impl Iterator<Item = (&'c Shader, &'c Level)> + 'c {
        groups(self, filter)
    }

    /// The kept permutations of the shaders and levels `filter` accepts, in the order of
    /// [`Config::permutations`], pruned (see [`Kept`]); [`Kept::skipped`] counts the others.
    pub fn kept_where<'c>(&'c self, filter: impl Fn(&Shader, &Level) -> bool + 'c) -> Kept<'c> {
        Kept::new(self, filter)
    }

    /// The limit on the permutations built or listed: `cli` (`--max-permutations`), else
    /// `[compiler] max_permutations`, else [`DEFAULT_MAX_PERMUTATIONS`].
    pub fn max_permutations(&self, cli: Option<u64>) -> u64 {
        cli.or(self.max_permutations).unwrap_or(DEFAULT_MAX_PERMUTATIONS)
    }

    /// Checks that no (shader, level) `filter` accepts has more than `max` permutations (kept
    /// ones only, unless `all`: then every one, kept or skipped), nor all of them together. A
    /// space over `max` is accepted when its skip rules are shown (in bounded time) to keep at
    /// most `max`. The error is located at the dimensions of the shader that goes over.
    pub fn check_space(
        &self,
        filter: impl Fn(&Shader, &Level) -> bool,
        max: u64,
        all: bool,
    ) -> Result<(), ConfigError> {
        let max = max as u128;
        let mut total = 0u128;
        for (shader, level) in groups(self, filter) {
            let nominal = nominal(shader);
            // Counted only when the nominal size would go over (per shader or in all).
            let over = nominal > max || total.saturating_add(nominal) > max;
            let kept = match (over, all) {
                (false, _) => Some(nominal),
                (true, true) => None,
                (true, false) => count_kept(shader, level, COUNT_BUDGET),
            };
            let (message, note) = match kept {
                Some(k) if k <= max && total.saturating_add(k) <= max => {
                    total += k;
                    continue;
                }
                Some(k) if k <= max => (
                    format!(
                        "the permutation set has more than {max} permutations: shader `{}` at level `{}` adds {}                          to the {total} before it",
                        shader.name,
                        level.name,
                        describe_count(k)
                    ),
                    "the limit counts every shader at every level built".to_string(),
                ),
                _ => (
                    format!(
                        "shader `{}` has {} permutations at level `{}`, over the limit of {max}",
                        shader.name,
                        describe_count(nominal),
                        level.name
                    ),
                    match kept {
                        Some(k) => format!("its skip rules keep {} of them", describe_count(k)),
                        None if all => "`--all` lists every one of them, skipped or not".to_string(),
                        None => "its skip rules could not be shown to keep fewer (a rule prunes as soon as the \
                                 dimensions it names are chosen)"
                            .to_string(),
                    },
                ),
            };
            let d = codespan_reporting::diagnostic::Diagnostic::error()
                .with_message(format!("{message}: {note}"))
                .with_labels(vec![codespan_reporting::diagnostic::Label::primary((), shader.spans.dimensions.clone())
                    .with_message(format!("{} dimensions", shader.dimensions.len()))])
                .with_notes(vec![
                    "raise the limit with `--max-permutations N` or `[compiler] max_permutations = N`, or skip more"
                        .to_string(),
                ]);
            return Err(self.error(vec![d]));
        }
        Ok(())
    }

    /// A configuration error about this file (spans into its text).
    pub fn error(&self, diagnostics: Vec<codespan_reporting::diagnostic::Diagnostic<()>>) -> ConfigError {
        ConfigError::new(self.source.0.clone(), self.source.1.clone(), diagnostics)
    }

    /// The error of a permutation whose skip rule or derived define cannot be evaluated (a
    /// division by zero), located at that expression.
    pub fn evaluation_error(&self, p: &Permutation<'_>) -> Option<ConfigError> {
        let message = p.error.as_ref()?;
        let mut d = codespan_reporting::diagnostic::Diagnostic::error()
            .with_message(format!("{message} in permutation {}", p.name()));
        if let Some(span) = &p.error_span {
            d = d
                .with_labels(vec![codespan_reporting::diagnostic::Label::primary((), span.clone())
                    .with_message("cannot be evaluated")]);
        }
        Some(self.error(vec![d]))
    }
}

#[cfg(test)]
mod tests {
    use super::disjuncts;

    #[test]
    fn top_level_or_splits_into_conditions() {
        assert_eq!(disjuncts("A || B && (C || D)"), ["A", "B && ( C || D )"]);
        assert_eq!(disjuncts("A && B"), ["A && B"]);
        assert_eq!(disjuncts("A || B ? 1 : 0"), ["A || B ? 1 : 0"]);
        assert_eq!(disjuncts("(A || B)"), ["(A || B)"]);
        assert_eq!(disjuncts("A || "), ["A || "]);
    }
}
