//! Plan: the configuration, the kept permutations, their targets and limits, the distinct
//! keys once preprocessing gave them, and a shard's share of those keys.

use std::collections::HashMap;

use super::{Error, Options};
use crate::archive::Target;
use crate::compile::Limits;
use crate::permute::{self, Config, Level, Permutation, Shader};

/// `--shard I/N`: this process compiles share `index` (0-based) of `count`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shard {
    /// This process's share, from 0.
    pub index: usize,
    /// How many shares there are.
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

impl Shard {
    /// Whether `key` falls to this shard by its hash ([`Plan::hashed_shares`]): a share
    /// every shard works out from the key alone, as soon as it has it.
    pub(super) fn hashes_to(&self, key: &crate::cache::Key) -> bool {
        let h = u64::from_le_bytes(key.0[8..16].try_into().expect("8 of 32 bytes"));
        h % self.count as u64 == self.index as u64
    }
}

/// From this many kept permutations, `--shard` shares keys by their hash rather than by
/// cost. A share balanced by cost needs every key's cost, so a shard knows its share only
/// once it has preprocessed everything, and must keep every key's text until then; by hash
/// it compiles its keys as it finds them, as a plain build does. With this many keys, the
/// shares' costs even out without being balanced.
pub(super) const HASHED_SHARES_FROM: usize = 65_536;

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
/// in its shader's domain (a `u32`, decoded by [`Plan::values`]), or where a domain has more
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
                // Permutations are numbered by a `u32` through the build.
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
            f.manifest(&mut usage);
            usage.built_recorded = Default::default();
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
    /// holds both copies for a moment (from half as much again as it needs to three times),
    /// while the untouched part of a large allocation costs no resident memory.
    pub fn max_targets(&self) -> usize {
        self.runs.iter().map(|r| level_targets(r.level, &self.options.targets).len()).max().unwrap_or(0)
    }

    /// Whether the build writes anything from the artifacts (an archive or loose files).
    pub fn assembles(&self) -> bool {
        self.options.output.is_some() || self.options.emit_dir.is_some()
    }

    /// Whether `--shard` shares keys by hash ([`HASHED_SHARES_FROM`]): decided by the set
    /// alone, so every shard decides alike.
    pub fn hashed_shares(&self) -> bool {
        self.len >= HASHED_SHARES_FROM
    }
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
    fn hashed_shares_give_each_key_to_one_shard_evenly() {
        let mut counts = [0usize; 8];
        for i in 0..16_000u32 {
            let key = crate::cache::Key(*blake3::hash(&i.to_le_bytes()).as_bytes());
            let owners: Vec<usize> = (0..8).filter(|&s| Shard { index: s, count: 8 }.hashes_to(&key)).collect();
            assert_eq!(owners.len(), 1, "one shard per key");
            counts[owners[0]] += 1;
        }
        assert!(counts.iter().all(|&c| (1_800..2_200).contains(&c)), "{counts:?}");
    }

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
}
