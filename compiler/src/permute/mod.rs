//! The permutation model: `permutations.toml` in, a lazy stream of permutations out.
//!
//! Takes a `permutations.toml` (include and virtual roots, feature levels, shaders with their
//! constant defines, dimensions, derived defines and skip rules) and gives a checked
//! [`Config`]; [`Config::permutations`] enumerates every (shader, level, dimension values)
//! in a stable order, marks the ones a skip rule drops, and hands each permutation's defines
//! (with where each came from) and preprocessing options to the next stage. [`analyze`]
//! preprocesses them to find deduplication groups and dead dimensions.
//!
//! Guarantees: a bad configuration is one [`ConfigError`] that points at the toml line and
//! column of every problem, never a panic; `skip` and `derived` are evaluated by the
//! preprocessor's own `#if` evaluator ([`crate::preprocess::expr`]); enumeration streams (an
//! odometer over dimension indices: memory does not grow with the number of permutations);
//! canonical names are `Shader@level{DIM=value,...}` with dimensions in declared order, enum
//! values by name, and `Shader@level{}` for a shader without dimensions, exactly as
//! [`crate::archive::Archive::canonical_name`] builds them.

mod analysis;
pub mod budget;
pub(crate) mod enumerate;
mod error;
mod names;
mod schema;

use std::path::{Path, PathBuf};

pub use analysis::{
    analyze, dead_dimensions, dead_dimensions_in, Analysis, DeadDimension, Failed, LevelAnalysis, Preprocessed,
};
pub use budget::{Budget, BudgetExceeded, BudgetLimit, ShaderBudget};
pub use enumerate::{
    canonical_name, nominal, Define, DefineOrigin, Kept, Permutation, Permutations, RuleResult,
    DEFAULT_MAX_PERMUTATIONS,
};
pub use error::{ConfigError, Near, NotFound};
pub use schema::MAX_DIMENSION_VALUES;

use crate::preprocess;
use crate::{Stage, Target};

/// A checked permutation set.
#[derive(Debug, Clone)]
pub struct Config {
    /// The toml file (absolute).
    pub path: PathBuf,
    /// Its folder: relative paths in the file, and file names in diagnostics, start here.
    pub dir: PathBuf,
    /// `[compiler] include`, absolute, in order.
    pub include_roots: Vec<PathBuf>,
    /// `[compiler] virtual`: (`"/Engine"`, absolute folder), in order.
    pub virtual_roots: Vec<(String, PathBuf)>,
    /// `[levels.*]` in file order.
    pub levels: Vec<Level>,
    /// `[[shader]]` in file order.
    pub shaders: Vec<Shader>,
    /// Rendered warnings about the file (an expression using an identifier nothing defines).
    pub warnings: Vec<String>,
    /// `[compiler] max_permutations`: the most permutations of one shader at one level, or of
    /// all together (see [`DEFAULT_MAX_PERMUTATIONS`]).
    pub max_permutations: Option<u64>,
    /// `[budget]`: what a CI build may grow to (see [`budget`]).
    pub budget: Budget,
    /// `[usage] keep`: patterns of canonical names (`*`, `?`) a `kiln build --usage-only`
    /// keeps whether recorded or not.
    pub usage_keep: Vec<String>,
    /// (name in messages, text) of the file, for errors found after loading.
    pub source: std::sync::Arc<(String, String)>,
}

/// A feature level: the defines it sets, the targets it compiles to, the limits it validates against.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Level {
    /// The level's name (the `@level` of permutation names).
    pub name: String,
    /// The defines every permutation at the level gets.
    pub defines: Vec<(String, i64)>,
    /// The targets written for this level; all of them when the file names none.
    pub targets: Vec<Target>,
    /// The base limits (`limits = "..."`, or the table's `base`).
    pub limits: Limits,
    /// The table form's single limits, as (wgpu `Limits` field, value), in the file's order.
    pub limit_overrides: Vec<(String, u64)>,
}

/// Which wgpu limits a level is validated against.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Limits {
    /// `wgpu::Limits::default()`.
    #[default]
    Default,
    /// `wgpu::Limits::downlevel_defaults()` and no storage buffers or textures in vertex shaders.
    Downlevel,
}

impl Limits {
    /// The name `permutations.toml` gives it.
    pub fn name(self) -> &'static str {
        match self {
            Limits::Default => "default",
            Limits::Downlevel => "downlevel",
        }
    }
}

/// One `[[shader]]`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Shader {
    /// The shader's name (the start of its permutation names).
    pub name: String,
    /// `source` as written.
    pub source: String,
    /// `source` resolved like `#include <...>` (absolute).
    pub source_path: PathBuf,
    /// The entry point (`main` when the file names none).
    pub entry: String,
    /// The entry point's stage.
    pub stage: Stage,
    /// The levels it is built for, in its order (every level, in file order, when the file names none).
    pub levels: Vec<String>,
    /// Constant defines; one with the name of a level define overrides it.
    pub defines: Vec<(String, i64)>,
    /// Its dimensions, in declared order.
    pub dimensions: Vec<Dimension>,
    /// (name, `#if` expression), in order: each sees the ones before it.
    pub derived: Vec<(String, String)>,
    /// Its skip rules, in order.
    pub skip: Vec<SkipRule>,
    /// `budget = { max_permutations = N }`.
    pub budget: ShaderBudget,
    /// `always = true`: every kept permutation of it is built by `kiln build --usage-only`.
    pub always: bool,
    /// Where its parts are in the toml file.
    pub spans: ShaderSpans,
}

/// Byte ranges of a shader's parts in the toml text, for errors found after loading.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct ShaderSpans {
    /// The shader's name.
    pub name: std::ops::Range<usize>,
    /// Each dimension's name, in order.
    pub each_dimension: Vec<std::ops::Range<usize>>,
    /// From the first dimension's name to the last one's domain (the name without dimensions).
    pub dimensions: std::ops::Range<usize>,
    /// Each derived define's expression.
    pub derived: Vec<std::ops::Range<usize>>,
}

/// A dimension and its domain.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Dimension {
    /// The dimension's name: the define it sets.
    pub name: String,
    /// The values it takes, in enumeration order (an enum's indices).
    pub values: Vec<i64>,
    /// An enum's names (`values[i]` is `i`), else empty.
    pub labels: Vec<String>,
    /// Written `"bool"` (values 0 and 1), rather than as a list or range.
    pub is_bool: bool,
}

impl Dimension {
    /// How `value` appears in a canonical name: an enum's name, or the integer.
    pub fn display(&self, value: i64) -> String {
        usize::try_from(value).ok().and_then(|i| self.labels.get(i)).cloned().unwrap_or_else(|| value.to_string())
    }

    /// The index in `values` of a value written in a name (an enum's name or index, or an integer).
    pub fn parse(&self, text: &str) -> Option<usize> {
        if let Some(i) = self.labels.iter().position(|l| l == text) {
            return Some(i);
        }
        let v: i64 = text.trim().parse().ok()?;
        self.values.iter().position(|x| *x == v)
    }

    /// A short description of the domain for messages: `bool`, `[0, 1, 2, 4]`, `enum [A, B]`.
    pub fn describe(&self) -> String {
        if !self.labels.is_empty() {
            format!("enum [{}]", self.labels.join(", "))
        } else if self.values == [0, 1] {
            "bool".to_string()
        } else if self.values.len() > 2 && self.values.windows(2).all(|w| w[1] == w[0] + 1) {
            format!("range [{}, {}]", self.values[0], self.values[self.values.len() - 1])
        } else {
            let v: Vec<String> = self.values.iter().map(i64::to_string).collect();
            format!("[{}]", v.join(", "))
        }
    }
}

/// `{ when = "...", why = "..." }`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SkipRule {
    /// An `#if` expression over dimensions and the level's and shader's defines.
    pub when: String,
    /// The reason, shown by `kiln list --all` and `kiln explain`.
    pub why: String,
    /// Where `when` is in the toml text.
    pub span: std::ops::Range<usize>,
}

/// Reads and checks a `permutations.toml`. File names in diagnostics are `path` as given.
pub fn load(path: &Path) -> Result<Config, ConfigError> {
    let display = path.display().to_string();
    let text = read_regular_file(path).map_err(|e| {
        ConfigError::new(
            display.clone(),
            String::new(),
            vec![codespan_reporting::diagnostic::Diagnostic::error()
                .with_message(format!("cannot read permutation set `{display}`: {e}"))],
        )
    })?;
    load_str(&text, path)
}

/// The largest `permutations.toml` read.
pub const MAX_CONFIG_BYTES: u64 = 64 << 20;

/// The text of the regular file at `path`, at most [`MAX_CONFIG_BYTES`]. Anything else (a
/// directory, a FIFO, a device) is an error, without blocking (see `kiln_archive::input`).
fn read_regular_file(path: &Path) -> std::io::Result<String> {
    crate::archive::input::read_regular_to_string(path, MAX_CONFIG_BYTES)
}

/// Checks the text of a `permutations.toml` located at `path` (which relative paths in it start
/// from; the file itself is not read).
pub fn load_str(text: &str, path: &Path) -> Result<Config, ConfigError> {
    schema::parse(text, path, &path.display().to_string())
}

impl Config {
    /// The level named `name`, if any.
    pub fn level(&self, name: &str) -> Option<&Level> {
        self.levels.iter().find(|l| l.name == name)
    }

    /// The shader named `name`, if any.
    pub fn shader(&self, name: &str) -> Option<&Shader> {
        self.shaders.iter().find(|s| s.name == name)
    }

    /// Options for preprocessing: the include and virtual roots, no permutation defines.
    pub fn preprocess_options(&self) -> preprocess::Options {
        preprocess::Options {
            include_roots: self.include_roots.clone(),
            virtual_roots: self.virtual_roots.clone(),
            ..preprocess::Options::default()
        }
    }

    /// Every permutation, kept and skipped: shaders in file order, each shader's levels in its
    /// order, then the product of its dimensions (first dimension slowest). Lazy: nothing is
    /// held but the current position.
    pub fn permutations(&self) -> Permutations<'_> {
        Permutations::new(self, |_, _| true)
    }

    /// The permutations of the shaders and levels `filter` accepts, in the same order.
    pub fn permutations_where<'c>(&'c self, filter: impl Fn(&Shader, &Level) -> bool + 'c) -> Permutations<'c> {
        Permutations::new(self, filter)
    }

    /// Looks a permutation name up (enum values by name or index, dimensions in any order).
    /// A skipped permutation is found too ([`Permutation::skipped_by`] says so).
    pub fn find(&self, name: &str) -> Result<Permutation<'_>, NotFound> {
        names::find(self, name)
    }

    /// The number of permutations of each shader at each level: (shader, level, kept, skipped).
    /// Pruned like [`Config::kept_where`]: only kept permutations are visited one by one.
    pub fn counts(&self) -> Vec<Count> {
        self.groups_where(|_, _| true)
            .map(|(shader, level)| {
                let mut kept = self.kept_where(|s, l| std::ptr::eq(s, shader) && std::ptr::eq(l, level));
                let n = kept.by_ref().count();
                Count {
                    shader: shader.name.clone(),
                    level: level.name.clone(),
                    kept: n,
                    skipped: usize::try_from(kept.skipped()).unwrap_or(usize::MAX),
                }
            })
            .collect()
    }
}

/// Permutation counts of one shader at one level.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Count {
    /// The shader.
    pub shader: String,
    /// The level.
    pub level: String,
    /// Permutations the skip rules keep.
    pub kept: usize,
    /// Permutations they skip.
    pub skipped: usize,
}

#[cfg(test)]
mod tests;
