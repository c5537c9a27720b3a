//! Plan: the configuration, the kept permutations, their targets and limits, the distinct
//! keys once preprocessing gave them, and a shard's share of those keys.

use std::collections::HashMap;

use super::preprocess::Preprocessed;
use super::{Error, Options};
use crate::archive::Target;
use crate::cache::Key;
use crate::compile::Limits;
use crate::permute::{self, Config, Level, Permutation, Shader};

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

/// The permutations to build, compact: each kept permutation is its values in one flat
/// table (a few bytes per dimension), its shader and level those of its run; a
/// [`Permutation`] is made again where one is needed ([`Plan::permutation`]).
pub(super) struct Plan<'c> {
    pub config: &'c Config,
    pub options: &'c Options,
    /// Each run of kept permutations of one (shader, level), in enumeration order (the
    /// archive's order).
    runs: Vec<Run<'c>>,
    /// Every kept permutation's values, one after another.
    values: Vec<i64>,
    /// Kept permutations.
    len: usize,
    /// Permutations dropped by skip rules (saturating).
    pub skipped: u128,
}

/// Kept permutations `first..` (until the next run) of one shader at one level; their
/// values start at `first_value`, `shader.dimensions.len()` each.
struct Run<'c> {
    shader: &'c Shader,
    level: &'c Level,
    first: usize,
    first_value: usize,
}

impl<'c> Plan<'c> {
    /// Enumerates, pruned: a skip rule decided on the first dimensions skips their subtree.
    /// A skip rule or derived define that cannot be evaluated is a configuration error.
    pub fn new(config: &'c Config, options: &'c Options) -> Result<Plan<'c>, Error> {
        let (mut runs, mut values, mut len) = (Vec::<Run<'c>>::new(), Vec::new(), 0);
        let mut stream = config.kept_where(|_, level| selected(options, level));
        for p in &mut stream {
            if let Some(e) = config.evaluation_error(&p) {
                return Err(Error::Config(e.render()));
            }
            let same = runs.last().is_some_and(|r| std::ptr::eq(r.shader, p.shader) && std::ptr::eq(r.level, p.level));
            if !same {
                runs.push(Run { shader: p.shader, level: p.level, first: len, first_value: values.len() });
            }
            values.extend_from_slice(&p.values);
            len += 1;
        }
        runs.shrink_to_fit();
        values.shrink_to_fit();
        Ok(Plan { config, options, runs, values, len, skipped: stream.skipped() })
    }

    /// Kept permutations.
    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    fn run(&self, i: usize) -> &Run<'c> {
        &self.runs[self.runs.partition_point(|r| r.first <= i) - 1]
    }

    /// The shader and level of kept permutation `i`.
    pub fn shader_level(&self, i: usize) -> (&'c Shader, &'c Level) {
        let r = self.run(i);
        (r.shader, r.level)
    }

    /// The values of kept permutation `i`, one per dimension.
    pub fn values(&self, i: usize) -> &[i64] {
        let r = self.run(i);
        let n = r.shader.dimensions.len();
        let at = r.first_value + (i - r.first) * n;
        &self.values[at..at + n]
    }

    /// Kept permutation `i`, evaluated again (its derived defines).
    pub fn permutation(&self, i: usize) -> Permutation<'c> {
        let (shader, level) = self.shader_level(i);
        Permutation::new(shader, level, self.values(i).to_vec())
    }

    /// The canonical name of kept permutation `i`.
    pub fn name(&self, i: usize) -> String {
        let (shader, level) = self.shader_level(i);
        permute::canonical_name(shader, level, self.values(i))
    }

    /// The kept permutations of each (shader, level), as index ranges, in order.
    pub fn runs(&self) -> impl Iterator<Item = (&'c Shader, &'c Level, std::ops::Range<usize>)> + '_ {
        self.runs.iter().enumerate().map(|(k, r)| {
            let end = self.runs.get(k + 1).map_or(self.len, |n| n.first);
            (r.shader, r.level, r.first..end)
        })
    }

    /// The targets written for `p`: its level's, filtered by `--target`.
    pub fn targets(&self, p: &Permutation<'_>) -> Vec<Target> {
        level_targets(p.level, &self.options.targets)
    }

    /// The most artifacts of one permutation (the most targets of a level built): with
    /// [`Plan::len`], a bound on what the per-key tables hold. They are allocated at that
    /// bound once rather than grown by doubling: a doubling copies the whole table and
    /// holds both copies for a moment (1.5x the memory it needs at best, 3x at worst),
    /// while the untouched part of a large allocation costs no resident memory.
    pub fn max_targets(&self) -> usize {
        self.runs.iter().map(|r| level_targets(r.level, &self.options.targets).len()).max().unwrap_or(0)
    }

    /// Whether the build writes anything from the artifacts (an archive or loose files).
    pub fn assembles(&self) -> bool {
        self.options.output.is_some() || self.options.emit_dir.is_some()
    }

    /// The distinct keys in order of first appearance, each with its permutations, and the
    /// keys this process must produce.
    pub fn group(&self, pre: &Preprocessed) -> Keys {
        // Each permutation's key number, by first appearance; then the members of each key,
        // one after another (counting sort).
        let mut keys: Vec<Key> = Vec::with_capacity(self.len);
        let mut number: HashMap<Key, u32> = HashMap::with_capacity(self.len);
        let of: Vec<u32> = (0..self.len)
            .map(|i| match pre.key(i) {
                Some(key) => *number.entry(*key).or_insert_with(|| {
                    keys.push(*key);
                    keys.len() as u32 - 1
                }),
                None => u32::MAX,
            })
            .collect();
        drop(number);
        let mut starts = vec![0usize; keys.len() + 1];
        for &k in of.iter().filter(|&&k| k != u32::MAX) {
            starts[k as usize + 1] += 1;
        }
        for k in 0..keys.len() {
            starts[k + 1] += starts[k];
        }
        let mut next = starts.clone();
        let mut members = vec![0usize; starts[keys.len()]];
        for (i, &k) in of.iter().enumerate().filter(|(_, &k)| k != u32::MAX) {
            members[next[k as usize]] = i;
            next[k as usize] += 1;
        }
        drop((of, next));
        let mut keys = Keys { keys, starts, members, share: Vec::new() };
        keys.share = match self.options.shard {
            None => vec![true; keys.len()],
            Some(shard) => {
                let costs: Vec<u64> = (0..keys.len())
                    .map(|k| {
                        let members = keys.members(k);
                        let (_, level) = self.shader_level(members[0]);
                        let len = members.iter().filter_map(|&m| pre.row(m)).map(|r| r.text_len).max();
                        len.unwrap_or(0).max(1) * level_targets(level, &self.options.targets).len().max(1) as u64
                    })
                    .collect();
                assign(&keys.keys, &costs, shard.count).into_iter().map(|s| s == shard.index).collect()
            }
        };
        keys
    }
}

/// The distinct keys of a build, by first appearance, with their permutations.
pub(super) struct Keys {
    pub keys: Vec<Key>,
    /// The members of key `k` are `members[starts[k]..starts[k + 1]]`.
    starts: Vec<usize>,
    /// Indices into the plan's kept permutations, ascending within each key.
    members: Vec<usize>,
    /// Whether each key is in this process's share (every key without `--shard`).
    pub share: Vec<bool>,
}

impl Keys {
    pub fn len(&self) -> usize {
        self.keys.len()
    }

    /// The permutations of key `k`, ascending.
    pub fn members(&self, k: usize) -> &[usize] {
        &self.members[self.starts[k]..self.starts[k + 1]]
    }

    /// Each key with its permutations, in order.
    pub fn iter(&self) -> impl Iterator<Item = (&Key, &[usize])> + '_ {
        self.keys.iter().enumerate().map(|(k, key)| (key, self.members(k)))
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

    /// The compact plan gives back every kept permutation as the enumeration made it (values,
    /// derived defines, shader and level, name), runs included, with a level filter.
    #[test]
    fn the_compact_plan_gives_back_each_permutation() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("A.usf"), "fn a() {}\n").unwrap();
        std::fs::write(dir.path().join("B.usf"), "fn b() {}\n").unwrap();
        let text = r#"
[compiler]
include = ["."]
[levels.sm5]
targets = ["spirv"]
defines = { FL = 5 }
[levels.es3]
targets = ["glsl"]
limits = "downlevel"
defines = { FL = 3 }
[levels.es2]
targets = ["glsl"]
[[shader]]
name = "A"
source = "A.usf"
entry = "main"
stage = "fragment"
levels = ["sm5", "es3", "es2"]
dimensions = { X = { range = [0, 4] }, Y = "bool", Z = [1, 2, 8] }
derived = { XZ = "X * Z" }
skip = [ { when = "FL == 3 && Z == 8", why = "t" }, { when = "X == 2 && Y == 1", why = "t" } ]
[[shader]]
name = "B"
source = "B.usf"
entry = "main"
stage = "vertex"
levels = ["es3", "sm5"]
"#;
        let config = permute::load_str(text, &dir.path().join("permutations.toml")).unwrap();
        let options = Options { levels: vec!["sm5".into(), "es3".into()], ..Options::default() };
        let plan = Plan::new(&config, &options).unwrap();
        let kept: Vec<Permutation<'_>> = config.kept_where(|_, l| l.name == "sm5" || l.name == "es3").collect();
        assert_eq!(plan.len(), kept.len());
        assert!(kept.len() > 20, "{}", kept.len());
        for (i, p) in kept.iter().enumerate() {
            let q = plan.permutation(i);
            assert_eq!(
                (q.shader.name.as_str(), q.level.name.as_str()),
                (p.shader.name.as_str(), p.level.name.as_str())
            );
            assert_eq!((&q.values, &q.derived), (&p.values, &p.derived), "{}", p.name());
            assert_eq!(plan.values(i), &p.values[..]);
            assert_eq!(plan.name(i), p.name());
        }
        let runs: Vec<(String, String, usize)> =
            plan.runs().map(|(s, l, r)| (s.name.clone(), l.name.clone(), r.len())).collect();
        let names: Vec<(&str, &str)> = runs.iter().map(|r| (r.0.as_str(), r.1.as_str())).collect();
        assert_eq!(names, [("A", "sm5"), ("A", "es3"), ("B", "es3"), ("B", "sm5")]);
        assert_eq!(runs.iter().map(|r| r.2).sum::<usize>(), kept.len());
        // 5 x 2 x 3 values less the 5 of X == 2 && Y == 1 at sm5; es3 also skips Z == 8.
        assert_eq!(runs[0].2, 30 - 3);
        assert_eq!(runs[1].2, 20 - 2);
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
