//! Enumeration: an odometer over each shader's dimension indices, skip rules and derived
//! defines evaluated per permutation by the preprocessor's `#if` evaluator.

use super::{Config, Dimension, Level, Shader};
use crate::preprocess::{self, expr};

/// Where a define in effect comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum DefineOrigin {
    /// The feature level's `defines`.
    Level(String),
    /// The shader's constant `defines` (`overrides`: the level's value it replaces).
    Shader { overrides: Option<i64> },
    /// A dimension's value.
    Dimension,
    /// `DIM_NAME` of an enum dimension: the index of `NAME`.
    EnumValue { dimension: String },
    /// A derived define and its expression.
    Derived { expr: String },
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
    pub name: String,
    pub value: i64,
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
    pub shader: &'c Shader,
    pub level: &'c Level,
    /// One value per dimension of `shader`, in declared order (an enum's index).
    pub values: Vec<i64>,
    /// The first skip rule that matched (index into `shader.skip`), if any.
    pub skipped_by: Option<usize>,
    /// The value of each derived define of `shader`, in order.
    pub derived: Vec<i64>,
    /// An expression that could not be evaluated for these values (a division by zero): the
    /// rule or define and the message. Such a permutation is kept (a rule that cannot be
    /// evaluated skips nothing) and the build should report it as failed.
    pub error: Option<String>,
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
    for (i, rule) in shader.skip.iter().enumerate() {
        match scope.eval(&rule.when) {
            Ok(0) => {}
            Ok(_) => {
                skipped_by = Some(i);
                break;
            }
            Err(e) => {
                error.get_or_insert_with(|| format!("skip rule {} (`{}`): {e}", i + 1, rule.when));
            }
        }
    }
    let mut derived = Vec::with_capacity(shader.derived.len());
    for (name, e) in &shader.derived {
        let v = match scope.eval(e) {
            Ok(v) => v,
            Err(msg) => {
                error.get_or_insert_with(|| format!("derived define {name} (`{e}`): {msg}"));
                0
            }
        };
        derived.push(v);
        scope.names.push((name.as_str(), v));
    }
    Permutation { shader, level, values, skipped_by, derived, error }
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
pub(super) fn canonical_name(shader: &Shader, level: &Level, values: &[i64]) -> String {
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
