//! What the permutations preprocess to: deduplication groups (permutations of one shader and
//! level whose token streams are identical share one compile) and dead dimensions.

use std::collections::{HashMap, HashSet};

use rayon::prelude::*;

use super::{Config, Level, Permutation, Shader};
use crate::preprocess::{self, SourceCache};

/// A kept permutation and the hash of its preprocessed token stream.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Preprocessed {
    /// Its dimension values, as in [`Permutation::values`].
    pub values: Vec<i64>,
    /// [`preprocess::Output::token_hash`]; `None` when it failed to preprocess.
    pub hash: Option<blake3::Hash>,
}

/// A permutation that failed to preprocess.
#[derive(Debug)]
pub struct Failed {
    /// The permutation's canonical name.
    pub name: String,
    /// Its preprocessing error.
    pub error: preprocess::Error,
}

/// A dimension whose value never changes a shader's preprocessed token stream at a level:
/// every group of kept permutations that differ only in it preprocesses to one stream.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DeadDimension {
    /// The shader.
    pub shader: String,
    /// The level.
    pub level: String,
    /// The dimension.
    pub dimension: String,
    /// Its number of values: the factor it multiplies the permutations to preprocess by.
    pub multiplier: usize,
}

impl std::fmt::Display for DeadDimension {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "dimension `{}` of `{}@{}` never changes the preprocessed text: it multiplies the permutations by {} for nothing",
            self.dimension, self.shader, self.level, self.multiplier
        )
    }
}

/// One shader at one level, preprocessed.
#[derive(Debug, Clone)]
pub struct LevelAnalysis {
    /// The shader.
    pub shader: String,
    /// The level.
    pub level: String,
    /// Every kept permutation, in enumeration order.
    pub permutations: Vec<Preprocessed>,
    /// The number of distinct token streams among those that preprocessed.
    pub distinct: usize,
    /// Its dead dimensions.
    pub dead: Vec<DeadDimension>,
}

impl LevelAnalysis {
    /// The kept permutations whose token stream is `hash`, in enumeration order.
    pub fn group(&self, hash: blake3::Hash) -> impl Iterator<Item = &Preprocessed> {
        self.permutations.iter().filter(move |p| p.hash == Some(hash))
    }
}

/// Every (shader, level) `filter` accepts, preprocessed.
#[derive(Debug)]
pub struct Analysis {
    /// Each (shader, level), in configuration order.
    pub levels: Vec<LevelAnalysis>,
    /// Permutations that failed to preprocess, in enumeration order.
    pub failed: Vec<Failed>,
}

impl Analysis {
    /// Every dead dimension of every (shader, level).
    pub fn dead(&self) -> impl Iterator<Item = &DeadDimension> {
        self.levels.iter().flat_map(|l| l.dead.iter())
    }

    /// The analysis of `shader` at `level`, if it was analysed.
    pub fn find(&self, shader: &str, level: &str) -> Option<&LevelAnalysis> {
        self.levels.iter().find(|l| l.shader == shader && l.level == level)
    }
}

/// Preprocesses every kept permutation of the shaders and levels `filter` accepts (in
/// parallel, every file read once through `cache`), then groups them by token stream and
/// finds dead dimensions.
pub fn analyze(config: &Config, cache: &SourceCache, filter: impl Fn(&Shader, &Level) -> bool + Sync) -> Analysis {
    // Every (shader, level) the filter accepts, and all their kept permutations in one list,
    // so that many small shaders preprocess in parallel as well as one big one.
    let mut pairs: Vec<(&Shader, &Level)> = Vec::new();
    let mut kept: Vec<(usize, Permutation<'_>)> = Vec::new();
    for (shader, level) in config.groups_where(&filter) {
        pairs.push((shader, level));
        let same = |s: &Shader, l: &Level| std::ptr::eq(s, shader) && std::ptr::eq(l, level);
        kept.extend(config.kept_where(same).map(|p| (pairs.len() - 1, p)));
    }
    let results: Vec<Result<blake3::Hash, preprocess::Error>> = kept
        .par_iter()
        .map(|(_, p)| {
            preprocess::preprocess_file(&p.shader.source_path, &p.preprocess_options(config), cache)
                .map(|o| o.token_hash())
        })
        .collect();

    let mut per_pair: Vec<Vec<Preprocessed>> = vec![Vec::new(); pairs.len()];
    let mut failed = Vec::new();
    for ((pair, p), r) in kept.into_iter().zip(results) {
        let hash = match r {
            Ok(h) => Some(h),
            Err(error) => {
                failed.push(Failed { name: p.name(), error });
                None
            }
        };
        per_pair[pair].push(Preprocessed { values: p.values, hash });
    }
    let levels = pairs
        .into_iter()
        .zip(per_pair)
        .map(|((shader, level), permutations)| {
            let distinct = permutations.iter().filter_map(|p| p.hash).collect::<HashSet<_>>().len();
            let dead = dead_dimensions_in(shader, level, &permutations);
            LevelAnalysis { shader: shader.name.clone(), level: level.name.clone(), permutations, distinct, dead }
        })
        .collect();
    Analysis { levels, failed }
}

/// The dead dimensions of every shader at every level (the build warns about them).
/// Permutations that fail to preprocess count as distinct, so they never make a dimension dead.
pub fn dead_dimensions(config: &Config, cache: &SourceCache) -> Vec<DeadDimension> {
    analyze(config, cache, |_, _| true).dead().cloned().collect()
}

/// The dead dimensions of `shader` at `level`, from the token hashes of its kept permutations
/// (for a caller that already preprocessed them, such as the build).
///
/// Dimension `d` is dead when every group of kept permutations that differ only in `d` has one
/// token stream, and at least one such group has two or more members (otherwise skip rules
/// already fix its value and it costs nothing). A permutation without a hash (it failed) is
/// distinct from every other, so it never makes a dimension dead.
pub fn dead_dimensions_in(shader: &Shader, level: &Level, permutations: &[Preprocessed]) -> Vec<DeadDimension> {
    let mut dead = Vec::new();
    for (d, dim) in shader.dimensions.iter().enumerate() {
        if dim.values.len() < 2 {
            continue;
        }
        // Others' values -> (the group's hash if all agree so far, members).
        let mut groups: HashMap<Vec<i64>, (Option<blake3::Hash>, usize)> = HashMap::new();
        let mut live = false;
        for p in permutations {
            let key: Vec<i64> = p.values.iter().enumerate().filter(|(i, _)| *i != d).map(|(_, v)| *v).collect();
            let entry = groups.entry(key).or_insert((p.hash, 0));
            if entry.1 > 0 && (entry.0 != p.hash || p.hash.is_none()) {
                live = true;
                break;
            }
            entry.1 += 1;
        }
        if !live && groups.values().any(|(_, n)| *n >= 2) {
            dead.push(DeadDimension {
                shader: shader.name.clone(),
                level: level.name.clone(),
                dimension: dim.name.clone(),
                multiplier: dim.values.len(),
            });
        }
    }
    dead
}
