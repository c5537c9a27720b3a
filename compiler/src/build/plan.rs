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

/// The permutations to build, compact: each kept permutation is the number of its values
/// in its shader's domain (4 bytes, decoded by [`Plan::values`]), or where a domain has more
/// than 2^32 points its values in one flat table; its shader and level are those of its run.
/// A [`Permutation`] is made again where one is needed ([`Plan::permutation`]).
pub(super) struct Plan<'c> {
    pub config: &'c Config,
    pub options: &'c Options,
    /// Each run of kept permutations of one (shader, level), in enumeration order (the
    /// archive's order).
    runs: Vec<Run<'c>>,
    /// Each kept permutation's point in its domain, mixed radix (the first dimension the
    /// most significant); unused (0) in the runs of a larger domain.
    points: Vec<u32>,
    /// The values of the kept permutations of larger domains, one after another.
    values: Vec<i64>,
    /// Kept permutations.
    len: usize,
    /// Permutations dropped by skip rules (saturating).
    pub skipped: u128,
    /// What `--usage` kept and `--usage-only` left out (`None` without `--usage`).
    pub usage: Option<super::usage::Outcome>,
    /// The kept permutations the usage files record, ascending: preprocessed (and so
    /// compiled) first.
    pub recorded: Vec<usize>,
}

/// The values of point `point` of `shader`'s domain ([`Domain::point`] undone).
fn decode(shader: &Shader, mut point: u32) -> Vec<i64> {
    let mut values = vec![0; shader.dimensions.len()];
    for (v, d) in values.iter_mut().zip(&shader.dimensions).rev() {
        let n = d.values.len() as u32;
        *v = d.values[(point % n) as usize];
        point /= n;
    }
    values
}

/// Kept permutations `first..` (until the next run) of one shader at one level; with
/// `flat`, their values start at `first_value`, `shader.dimensions.len()` each.
struct Run<'c> {
    shader: &'c Shader,
    level: &'c Level,
    first: usize,
    first_value: usize,
    flat: bool,
}

/// Numbers the points of a shader's domain: each dimension's value by its place in the
/// dimension's list.
struct Domain {
    places: Vec<HashMap<i64, u32>>,
}

impl Domain {
    /// `None` where the domain has more than 2^32 points.
    fn new(shader: &Shader) -> Option<Domain> {
        let size = shader.dimensions.iter().try_fold(1u64, |n, d| n.checked_mul(d.values.len() as u64))?;
        if size > 1 << 32 {
            return None;
        }
        let places = shader
            .dimensions
            .iter()
            .map(|d| {
                let mut places = HashMap::with_capacity(d.values.len());
                for (k, v) in d.values.iter().enumerate() {
                    places.entry(*v).or_insert(k as u32);
                }
                places
            })
            .collect();
        Some(Domain { places })
    }

    /// The point of `values`; `None` for a value not in its dimension's list.
    fn point(&self, shader: &Shader, values: &[i64]) -> Option<u32> {
        let mut point = 0u64;
        for ((d, places), v) in shader.dimensions.iter().zip(&self.places).zip(values) {
            point = point * d.values.len() as u64 + u64::from(*places.get(v)?);
        }
        u32::try_from(point).ok()
    }
}

impl<'c> Plan<'c> {
    /// Enumerates, pruned: a skip rule decided on the first dimensions skips their subtree.
    /// A skip rule or derived define that cannot be evaluated is a configuration error.
    pub fn new(config: &'c Config, options: &'c Options) -> Result<Plan<'c>, Error> {
        let (mut runs, mut points, mut values, mut len) = (Vec::<Run<'c>>::new(), Vec::new(), Vec::new(), 0);
        let mut domain: Option<Domain> = None;
        let mut stream = config.kept_where(|_, level| selected(options, level));
        let filter = super::usage::Filter::load(config, options)?;
        let mut usage = super::usage::Outcome::default();
        let mut recorded = Vec::new();
        for p in &mut stream {
            if let Some(e) = config.evaluation_error(&p) {
                return Err(Error::Config(e.render()));
            }
            if let Some(f) = &filter {
                let name = p.name();
                if !f.keeps(&p, &name, &mut usage) {
                    continue;
                }
                if f.records(&name) {
                    recorded.push(len);
                }
            }
            let same = runs.last().is_some_and(|r| std::ptr::eq(r.shader, p.shader) && std::ptr::eq(r.level, p.level));
            if !same {
                if runs.last().is_none_or(|r| !std::ptr::eq(r.shader, p.shader)) {
                    domain = Domain::new(p.shader);
                }
                runs.push(Run {
                    shader: p.shader,
                    level: p.level,
                    first: len,
                    first_value: values.len(),
                    flat: domain.is_none(),
                });
            }
            if len >= u32::MAX as usize {
                // Permutations are numbered in 4 bytes through the build.
                return Err(Error::Config(format!(
                    "error: {} keeps more than {} permutations: build it in parts (`--level`)",
                    options.config.display(),
                    u32::MAX - 1
                )));
            }
            let run = runs.last_mut().expect("pushed above");
            match domain.as_ref().filter(|_| !run.flat).and_then(|d| d.point(p.shader, &p.values)) {
                Some(point) => points.push(point),
                None if run.flat => {
                    points.push(0);
                    values.extend_from_slice(&p.values);
                }
                None => {
                    // A value outside its list (the enumeration makes none): this run keeps
                    // its values flat, from its first permutation.
                    run.flat = true;
                    for &point in &points[run.first..len] {
                        values.extend_from_slice(&decode(run.shader, point));
                    }
                    points.push(0);
                    values.extend_from_slice(&p.values);
                }
            }
            len += 1;
        }
        runs.shrink_to_fit();
        points.shrink_to_fit();
        values.shrink_to_fit();
        let usage = filter.map(|f| {
            usage.unknown = f.unknown(&usage);
            usage
        });
        Ok(Plan { config, options, runs, points, values, len, skipped: stream.skipped(), usage, recorded })
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
    pub fn values(&self, i: usize) -> Vec<i64> {
        let r = self.run(i);
        if r.flat {
            let n = r.shader.dimensions.len();
            let at = r.first_value + (i - r.first) * n;
            return self.values[at..at + n].to_vec();
        }
        decode(r.shader, self.points[i])
    }

    /// Kept permutation `i`, evaluated again (its derived defines).
    pub fn permutation(&self, i: usize) -> Permutation<'c> {
        let (shader, level) = self.shader_level(i);
        Permutation::new(shader, level, self.values(i))
    }

    /// The canonical name of kept permutation `i`.
    pub fn name(&self, i: usize) -> String {
        let (shader, level) = self.shader_level(i);
        permute::canonical_name(shader, level, &self.values(i))
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
    pub fn group<'p>(&self, pre: &'p Preprocessed) -> Result<Keys<'p>, Error> {
        // Each permutation's key number, by first appearance; then the members of each key,
        // one after another (counting sort). Keys are found equal by sorting the rows (the
        // distinct results, about one per key) by key: 12 bytes a row, where a map from key to
        // number took about 50 a permutation.
        let rows = pre.row_count();
        let key = |r: u32| pre.row_key(r as usize);
        let mut order: Vec<u32> = (0..rows as u32).collect();
        order.sort_unstable_by(|&a, &b| key(a).cmp(key(b)));
        // Each row's representative: the first row of its key in `order`.
        let mut same = vec![0u32; rows];
        let mut distinct = 0;
        for (k, &r) in order.iter().enumerate() {
            let first = match k {
                0 => r,
                _ if key(order[k - 1]) != key(r) => r,
                _ => same[order[k - 1] as usize],
            };
            distinct += usize::from(first == r);
            same[r as usize] = first;
        }
        drop(order);
        let mut number = vec![u32::MAX; rows];
        let mut count = 0;
        let of: Vec<u32> = (0..self.len)
            .map(|i| match pre.row_number(i) {
                Some(r) => {
                    let first = same[r] as usize;
                    if number[first] == u32::MAX {
                        number[first] = count;
                        count += 1;
                    }
                    number[first]
                }
                None => u32::MAX,
            })
            .collect();
        debug_assert_eq!(count as usize, distinct);
        drop((same, number));
        // Numbers of permutations, so below 2^32 ([`Plan::new`]): 4 bytes each, not 8.
        let count = count as usize;
        let mut starts = vec![0u32; count + 1];
        for &k in of.iter().filter(|&&k| k != u32::MAX) {
            starts[k as usize + 1] += 1;
        }
        for k in 0..count {
            starts[k + 1] += starts[k];
        }
        let mut members = vec![0u32; starts[count] as usize];
        // Each key's next free place: its start, moved one on per member (no second table).
        for (i, &k) in of.iter().enumerate().filter(|(_, &k)| k != u32::MAX) {
            members[starts[k as usize] as usize] = i as u32;
            starts[k as usize] += 1;
        }
        drop(of);
        // Each start was moved to the next key's: shift them back.
        starts.copy_within(0..count, 1);
        starts[0] = 0;
        let mut keys = Keys { pre, starts, members, share: Vec::new() };
        keys.share = match self.options.shard {
            None => vec![true; keys.len()],
            Some(shard) => {
                // Each row's text length, read again (the rows' keys alone are held).
                let mut text_lens = Vec::with_capacity(rows);
                pre.each_row(|r| text_lens.push(r.text_len)).map_err(super::preprocess::read_back)?;
                let costs: Vec<u64> = (0..keys.len())
                    .map(|k| {
                        let members = keys.members(k);
                        let (_, level) = self.shader_level(members[0] as usize);
                        let len = members
                            .iter()
                            .filter_map(|&m| pre.row_number(m as usize))
                            .map(|r| u64::from(text_lens[r]))
                            .max();
                        len.unwrap_or(0).max(1) * level_targets(level, &self.options.targets).len().max(1) as u64
                    })
                    .collect();
                assign(&keys.to_vec(), &costs, shard.count).into_iter().map(|s| s == shard.index).collect()
            }
        };
        Ok(keys)
    }
}

/// The distinct keys of a build, by first appearance, with their permutations. A key is
/// its first member's (in `pre`): not a copy of each (about 2.4 MB at 100k permutations).
pub(super) struct Keys<'p> {
    pre: &'p Preprocessed,
    /// The members of key `k` are `members[starts[k]..starts[k + 1]]`.
    starts: Vec<u32>,
    /// Indices into the plan's kept permutations, ascending within each key.
    members: Vec<u32>,
    /// Whether each key is in this process's share (every key without `--shard`).
    pub share: Vec<bool>,
}

impl Keys<'_> {
    pub fn len(&self) -> usize {
        self.starts.len() - 1
    }

    /// Key `k`.
    pub fn key(&self, k: usize) -> &Key {
        self.pre.key(self.members(k)[0] as usize).expect("a key's members were preprocessed")
    }

    /// Every key, in order, copied.
    pub fn to_vec(&self) -> Vec<Key> {
        (0..self.len()).map(|k| *self.key(k)).collect()
    }

    /// The permutations of key `k`, ascending.
    pub fn members(&self, k: usize) -> &[u32] {
        &self.members[self.starts[k] as usize..self.starts[k + 1] as usize]
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
            assert_eq!(plan.values(i), p.values);
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
    fn a_domain_past_2_32_points_keeps_its_values_flat() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("A.usf"), "fn a() {}\n").unwrap();
        let text = r#"
[compiler]
include = ["."]
[levels.sm5]
defines = { FL = 5 }
targets = ["wgsl"]
[[shader]]
name = "A"
source = "A.usf"
entry = "main"
stage = "fragment"
dimensions = { X = [-3, 7, 5], Y = { range = [0, 65535] }, Z = { range = [0, 65535] }, W = [2, 1] }
skip = [ { when = "Y > 1", why = "t" }, { when = "Z > 2", why = "t" } ]
[[shader]]
name = "B"
source = "A.usf"
entry = "main"
stage = "fragment"
dimensions = { X = [-3, 7, 5], Y = { range = [0, 99] } }
"#;
        // 3 x 65536 x 65536 x 2 points
        let config = permute::load_str(text, &dir.path().join("permutations.toml")).unwrap();
        let options = Options::default();
        let plan = Plan::new(&config, &options).unwrap();
        let kept: Vec<Permutation<'_>> = config.kept_where(|_, _| true).collect();
        assert_eq!(plan.len(), kept.len());
        assert_eq!(kept.len(), 3 * 2 * 3 * 2 + 3 * 100);
        assert_eq!(plan.runs.iter().map(|r| r.flat).collect::<Vec<_>>(), [true, false]);
        for (i, p) in kept.iter().enumerate() {
            assert_eq!(plan.values(i), p.values, "{}", p.name());
            assert_eq!(plan.name(i), p.name());
        }
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
