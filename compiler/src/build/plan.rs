//! Plan: the configuration, the kept permutations, their targets and limits, the distinct
//! keys once preprocessing gave them, and a shard's share of those keys.

use std::collections::HashMap;

use super::preprocess::Preprocessed;
use super::{Error, Options};
use crate::archive::Target;
use crate::cache::Key;
use crate::compile::Limits;
use crate::permute::{self, Config, Permutation};

/// `--shard I/N`: this process compiles share `index` (0-based) of `count`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shard {
    pub index: usize,
    pub count: usize,
}

impl Shard {
    /// `I/N` with `0 <= I < N`.
    pub fn parse(text: &str) -> Result<Shard, String> {
        let bad = || format!("invalid shard `{text}`: expected I/N with 0 <= I < N (0-based), e.g. 0/4");
        let (i, n) = text.trim().split_once('/').ok_or_else(bad)?;
        let index: usize = i.trim().parse().map_err(|_| bad())?;
        let count: usize = n.trim().parse().map_err(|_| bad())?;
        if count == 0 || index >= count {
            return Err(bad());
        }
        Ok(Shard { index, count })
    }

    /// `--shards N` with the index from `JOB_COMPLETION_INDEX` (Kubernetes Indexed Jobs).
    pub fn from_completion_index(count: usize, index: Option<&str>) -> Result<Shard, String> {
        let index = index
            .ok_or("--shards N needs JOB_COMPLETION_INDEX (set by a Kubernetes Indexed Job), or use --shard I/N")?;
        let i: usize = index
            .trim()
            .parse()
            .map_err(|_| format!("invalid JOB_COMPLETION_INDEX `{index}`: expected a number below {count}"))?;
        if count == 0 || i >= count {
            return Err(format!("invalid shard: JOB_COMPLETION_INDEX {i} with --shards {count} (0 <= index < N)"));
        }
        Ok(Shard { index: i, count })
    }
}

impl std::fmt::Display for Shard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

/// Loads the configuration and checks the levels asked for.
pub(super) fn load(options: &Options) -> Result<Config, Error> {
    let config = permute::load(&options.config).map_err(|e| Error::Config(e.render()))?;
    for l in &options.levels {
        if config.level(l).is_none() {
            let names: Vec<&str> = config.levels.iter().map(|l| l.name.as_str()).collect();
            return Err(Error::Config(format!(
                "error: no level named `{l}` in {} (its levels: {})",
                options.config.display(),
                names.join(", ")
            )));
        }
    }
    super::outputs::check_outputs(options, &config)?;
    let max = config.max_permutations(options.max_permutations);
    config.check_space(|_, level| selected(options, level), max, false).map_err(|e| Error::Config(e.render()))?;
    Ok(config)
}

/// Whether `level` is one the build is asked for.
fn selected(options: &Options, level: &permute::Level) -> bool {
    options.levels.is_empty() || options.levels.contains(&level.name)
}

/// The permutations to build.
pub(super) struct Plan<'c> {
    pub config: &'c Config,
    pub options: &'c Options,
    /// Kept permutations, in enumeration order (the archive's order).
    pub kept: Vec<Permutation<'c>>,
    /// Permutations dropped by skip rules (saturating).
    pub skipped: u128,
}

impl<'c> Plan<'c> {
    /// Enumerates, pruned: a skip rule decided on the first dimensions skips their subtree.
    /// A skip rule or derived define that cannot be evaluated is a configuration error.
    pub fn new(config: &'c Config, options: &'c Options) -> Result<Plan<'c>, Error> {
        let mut kept = Vec::new();
        let mut stream = config.kept_where(|_, level| selected(options, level));
        for p in &mut stream {
            if let Some(e) = config.evaluation_error(&p) {
                return Err(Error::Config(e.render()));
            }
            kept.push(p);
        }
        Ok(Plan { config, options, kept, skipped: stream.skipped() })
    }

    /// The targets written for `p`: its level's, filtered by `--target`.
    pub fn targets(&self, p: &Permutation<'_>) -> Vec<Target> {
        level_targets(p.level, &self.options.targets)
    }

    /// Whether the build writes anything from the artifacts (an archive or loose files).
    pub fn assembles(&self) -> bool {
        self.options.output.is_some() || self.options.emit_dir.is_some()
    }

    /// The distinct keys in order of first appearance, each with its permutations, and the
    /// keys this process must produce.
    pub fn group(&self, pre: &Preprocessed) -> Keys {
        let mut groups: Vec<(Key, Vec<usize>)> = Vec::new();
        let mut group_of: HashMap<Key, usize> = HashMap::new();
        for (i, r) in pre.iter().enumerate() {
            if let Ok(p) = r {
                let g = *group_of.entry(p.key).or_insert_with(|| {
                    groups.push((p.key, Vec::new()));
                    groups.len() - 1
                });
                groups[g].1.push(i);
            }
        }
        let share = match self.options.shard {
            None => vec![true; groups.len()],
            Some(shard) => {
                let costs: Vec<u64> = groups
                    .iter()
                    .map(|(_, members)| {
                        let p = &self.kept[members[0]];
                        let len = members.iter().filter_map(|&m| pre[m].as_ref().ok()).map(|r| r.text_len).max();
                        len.unwrap_or(0).max(1) * self.targets(p).len().max(1) as u64
                    })
                    .collect();
                let keys: Vec<Key> = groups.iter().map(|g| g.0).collect();
                assign(&keys, &costs, shard.count).into_iter().map(|s| s == shard.index).collect()
            }
        };
        Keys { groups, share }
    }
}

/// The distinct keys of a build.
pub(super) struct Keys {
    /// Each key with its permutations (indices into [`Plan::kept`]), by first appearance.
    pub groups: Vec<(Key, Vec<usize>)>,
    /// Whether each key is in this process's share (every key without `--shard`).
    pub share: Vec<bool>,
}

impl Keys {
    pub fn len(&self) -> usize {
        self.groups.len()
    }
}

/// Greedy longest-processing-time assignment of keys to `shards` by estimated cost: keys
/// sorted by cost (descending), then by key bytes, each to the least loaded shard (the
/// lowest index among equals). Depends only on the keys and their costs, so every shard
/// process computes the same assignment.
pub(super) fn assign(keys: &[Key], costs: &[u64], shards: usize) -> Vec<usize> {
    let mut order: Vec<usize> = (0..keys.len()).collect();
    order.sort_by(|&a, &b| costs[b].cmp(&costs[a]).then(keys[a].cmp(&keys[b])));
    let mut load: std::collections::BinaryHeap<std::cmp::Reverse<(u64, usize)>> =
        (0..shards).map(|s| std::cmp::Reverse((0u64, s))).collect();
    let mut out = vec![0; keys.len()];
    for k in order {
        let std::cmp::Reverse((l, s)) = load.pop().expect("at least one shard");
        out[k] = s;
        load.push(std::cmp::Reverse((l + costs[k], s)));
    }
    out
}

pub(super) fn level_targets(level: &permute::Level, filter: &[Target]) -> Vec<Target> {
    level.targets.iter().copied().filter(|t| filter.is_empty() || filter.contains(t)).collect()
}

pub(super) fn level_limits(level: &permute::Level) -> Limits {
    Limits::for_level(level)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shard_specs() {
        assert_eq!(Shard::parse("0/4"), Ok(Shard { index: 0, count: 4 }));
        assert_eq!(Shard::parse(" 3/4 "), Ok(Shard { index: 3, count: 4 }));
        for bad in ["4/4", "1/0", "0", "a/2", "-1/2", "1/2/3", ""] {
            assert!(Shard::parse(bad).is_err(), "{bad}");
        }
        assert_eq!(Shard::from_completion_index(3, Some("2")), Ok(Shard { index: 2, count: 3 }));
        assert!(Shard::from_completion_index(3, Some("3")).is_err());
        assert!(Shard::from_completion_index(3, None).is_err());
        assert!(Shard::from_completion_index(0, Some("0")).is_err());
    }

    #[test]
    fn assignment_balances_cost_and_ignores_order() {
        let keys: Vec<Key> = (0..40u8).map(|i| Key([i; 32])).collect();
        let costs: Vec<u64> = (0..40u64).map(|i| 1 + (i * 37) % 101).collect();
        let a = assign(&keys, &costs, 4);
        let mut load = [0u64; 4];
        for (k, s) in a.iter().enumerate() {
            load[*s] += costs[k];
        }
        let (min, max) = (*load.iter().min().unwrap(), *load.iter().max().unwrap());
        assert!(max - min <= *costs.iter().max().unwrap(), "{load:?}");
        // The same keys in another order get the same shards.
        let mut rev_keys = keys.clone();
        let mut rev_costs = costs.clone();
        rev_keys.reverse();
        rev_costs.reverse();
        let mut b = assign(&rev_keys, &rev_costs, 4);
        b.reverse();
        assert_eq!(a, b);
    }
}
