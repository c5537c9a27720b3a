//! Second-level deduplication: the writers run once per distinct compacted module.
//!
//! Two permutations whose token streams differ (so whose cache keys differ) can still
//! compact to the same module for their entry point: a dimension that only changes a helper
//! the entry point never calls, as Unreal's shared headers are full of. [`module_hash`] is a
//! structural hash of the compacted, validated module (naga's IR as it serializes: every
//! field but the source spans, which no writer without debug info reads) together
//! with the entry point, the stage, the targets and the level's limits (which decide the
//! validator's capabilities, and so the [`naga::valid::ModuleInfo`] the writers read).
//! [`SharedWriters`] maps that hash to the writers' outputs for one build, shared by every
//! thread. The first key with a module runs the writers and keeps nothing but a prefix of the
//! hash: most modules of a build belong to one key (616 of 621 on the bundled set), and keeping
//! a copy of every key's artifacts in case another key shares them cost more (a copy, and
//! memory the size of the build's output, faulted in page by page) than the sharing saved. The
//! second key with a module runs the writers again and keeps their outputs; every later one
//! takes a copy. naga's writers are deterministic functions of the module, its info and their
//! options, so the artifacts are byte-identical to those the key would have written itself,
//! whatever the order the keys are compiled in.
//!
//! The cache key stays the token hash: this map lives for one build and changes no key.

use std::collections::{HashMap, VecDeque};
use std::hash::{BuildHasherDefault, Hasher};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, OnceLock};

use super::prefixes::Seen;
use super::{Compiled, Error, Options, Validated};
use crate::archive::Target;

/// The artifacts of one compacted module, or the writer's error.
type Written = Result<Vec<(Target, Vec<u8>)>, Error>;

/// A module's identity: a prefix of its [`module_hash`] (a collision among 2^32
/// modules has odds of 2^-64), half the whole hash a module.
type Ident = u128;

fn ident(hash: &blake3::Hash) -> Ident {
    let mut first = [0; 16];
    first.copy_from_slice(&hash.as_bytes()[..16]);
    Ident::from_le_bytes(first)
}

/// Hashes an [`Ident`] by its low half, or a `u64` or `u32` by itself (each is a uniform
/// hash already: the build's reuse maps are keyed by part of a signature too).
#[derive(Default)]
pub(crate) struct IdentHasher(u64);

impl Hasher for IdentHasher {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0 << 8 | u64::from(b)) ^ (self.0 >> 56);
        }
    }

    fn write_u32(&mut self, n: u32) {
        // Spread over the 64 bits: a table takes its tags from the top ones.
        self.0 = u64::from(n).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    }

    fn write_u64(&mut self, n: u64) {
        self.0 = n;
    }

    fn write_u128(&mut self, n: u128) {
        self.0 = n as u64;
    }
}

type ByIdent = BuildHasherDefault<IdentHasher>;

/// What a build knows of its compacted modules. Most modules belong to one key, so those
/// are a set that may answer "seen" for a module it has not seen ([`Seen`]: far less than
/// the whole identity or a map to an enum of whole hashes), and the few whose outputs are
/// kept are a map beside it, by whole identity.
///
/// The set only decides whether a module's outputs are worth keeping: a false "seen" (a
/// few in a thousand) makes that module's key keep its own outputs, never take another's.
/// Sharing goes only through `kept`.
#[derive(Default)]
struct Modules {
    /// The modules a key had (those kept are found in `kept` first).
    seen: Seen,
    /// The writers' outputs, kept once a second key had the module (or being written by that
    /// key).
    kept: HashMap<Ident, Arc<OnceLock<Written>>, ByIdent>,
    /// The modules of `kept` whose outputs are written, oldest first, with their bytes: the
    /// first let go when the budget is reached (keys of a module come close together in the
    /// plan's order, so a module kept long ago is the least likely to be asked for again).
    order: VecDeque<(Ident, usize)>,
}

/// The writers' outputs by compacted module, for one build. Memory stays bounded: past
/// [`SharedWriters::BUDGET`] bytes of artifacts kept, the oldest module's are let go (a later
/// key with that module keeps them again, to the same bytes).
pub struct SharedWriters {
    map: Mutex<Modules>,
    shared: AtomicUsize,
    /// Bytes of artifacts held in `map`.
    kept: AtomicUsize,
    /// Every compile runs its own writers (to check that sharing changes no byte).
    disabled: bool,
}

impl Default for SharedWriters {
    fn default() -> Self {
        SharedWriters { map: Mutex::default(), shared: AtomicUsize::new(0), kept: AtomicUsize::new(0), disabled: false }
    }
}

impl SharedWriters {
    /// The most bytes of artifacts kept for sharing. The build streams (issue 12: memory
    /// bounded by the work in flight), so this is small: the keys of a module come close
    /// together in the plan's order, so the newest modules' outputs serve nearly every key
    /// that can share, and a larger budget only holds older modules' longer. Past it, the
    /// oldest module's outputs go.
    pub const BUDGET: usize = 1 << 20;

    /// An empty set.
    pub fn new() -> Self {
        SharedWriters::default()
    }

    /// [`SharedWriters::new`] with room for `modules` modules' prefixes (a build knows a
    /// bound: its permutations): no copies of a table that grows by doubling, whose old and
    /// new tables are both held while it grows.
    pub fn with_capacity(modules: usize) -> Self {
        let writers = SharedWriters::default();
        writers.map.lock().expect("a new lock").seen = Seen::with_bound(modules);
        writers
    }

    /// Shares nothing: [`SharedWriters::compile`] is [`super::compile`].
    pub fn disabled() -> Self {
        SharedWriters { disabled: true, ..SharedWriters::default() }
    }

    /// [`super::compile`], running the writers only for a module no earlier call had.
    pub fn compile(
        &self,
        source: &str,
        entry: &str,
        stage: crate::Stage,
        options: &Options,
    ) -> Result<Compiled, Error> {
        if self.disabled {
            return super::compile(source, entry, stage, options);
        }
        let v = super::validate(source, entry, stage, &options.limits)?;
        let reflection = super::checked_reflection(&v, options)?;
        let id = ident(&module_hash(&v, options));
        let cell = {
            let mut map = self.map.lock().expect("no panics while locked");
            if let Some(cell) = map.kept.get(&id) {
                Some(cell.clone())
            } else if map.seen.insert(id) {
                None
            } else {
                let cell = Arc::<OnceLock<Written>>::default();
                map.kept.insert(id, cell.clone());
                Some(cell)
            }
        };
        let Some(cell) = cell else {
            // The module's first key: its artifacts are handed on, not copied.
            return Ok(Compiled { artifacts: super::write_all(&v, options)?, reflection });
        };
        let mut ran = false;
        let written = cell.get_or_init(|| {
            ran = true;
            super::write_all(&v, options)
        });
        if !ran {
            self.shared.fetch_add(1, Ordering::Relaxed);
        } else if let Ok(artifacts) = written {
            self.kept_now(id, artifacts.iter().map(|(_, b)| b.len()).sum());
        } else {
            // A writer's error is kept like artifacts (no bytes to count), until let go
            // with the modules kept before it.
            self.kept_now(id, 0);
        }
        Ok(Compiled { artifacts: written.clone()?, reflection })
    }

    /// Counts module `id`'s `bytes` just kept, and lets go of the oldest modules' outputs
    /// past the budget (their identities stay seen; callers already holding one still get
    /// its outputs).
    fn kept_now(&self, id: Ident, bytes: usize) {
        let mut map = self.map.lock().expect("no panics while locked");
        map.order.push_back((id, bytes));
        let mut kept = self.kept.load(Ordering::Relaxed) + bytes;
        while kept > Self::BUDGET {
            let Some((old, old_bytes)) = map.order.pop_front() else { break };
            map.kept.remove(&old);
            map.seen.insert(old);
            kept -= old_bytes;
        }
        self.kept.store(kept, Ordering::Relaxed);
    }

    /// Lets go of every module's kept outputs and identity (a build's compile stage after
    /// preprocessing has few keys left; theirs run the writers themselves, to the same
    /// bytes), which would otherwise stay under the next stages.
    pub fn forget(&self) {
        *self.map.lock().expect("no panics while locked") = Modules::default();
        self.kept.store(0, Ordering::Relaxed);
    }

    /// How many compiles took their artifacts from an earlier one's module (a module of `n`
    /// keys shares `n - 2`: its first two keys run the writers).
    pub fn shared(&self) -> usize {
        self.shared.load(Ordering::Relaxed)
    }
}

/// The structural hash of a compacted, validated module and of what its writers are given.
/// Equal hashes mean equal artifacts for every target of `options`.
pub fn module_hash(v: &Validated, options: &Options) -> blake3::Hash {
    let mut prefix = Vec::new();
    let mut field = |bytes: &[u8]| {
        prefix.extend_from_slice(&(bytes.len() as u64).to_le_bytes());
        prefix.extend_from_slice(bytes);
    };
    field(b"kiln module v1");
    field(v.entry.as_bytes());
    field(v.stage.name().as_bytes());
    for t in &options.targets {
        field(t.name().as_bytes());
    }
    field(format!("{:?}", options.limits).as_bytes());
    field(super::NAGA_VERSION.as_bytes());
    super::structural::hash(&prefix, &v.module)
}

#[cfg(test)]
mod module_tests {
    use super::super::{validate, Options};
    use super::*;

    const SOURCE: &str = "
fn used(x: f32) -> f32 { return x * 2.0; }
fn unused(x: f32) -> f32 { return HELPER; }
@fragment fn main_ps(@location(0) v: f32) -> @location(0) vec4<f32> { return vec4<f32>(used(v) + ENTRY); }
@compute @workgroup_size(1) fn main_cs() {}
";

    fn hash(used: &str, unused: &str, spacing: &str) -> blake3::Hash {
        let text =
            SOURCE.replace("ENTRY", used).replace("HELPER", unused).replace("fn used", &format!("{spacing}fn used"));
        let options = Options::default();
        let v = validate(&text, "main_ps", crate::Stage::Fragment, &options.limits).unwrap();
        module_hash(&v, &options)
    }

    #[test]
    fn the_module_hash_sees_what_the_entry_point_reaches_and_nothing_else() {
        let base = hash("1.0", "x", "");
        assert_eq!(hash("1.0", "x + 1.0", ""), base, "an uncalled helper changed");
        assert_eq!(hash("1.0", "x", "\n\n   // moved\n"), base, "only the spans moved");
        assert_ne!(hash("2.0", "x", ""), base, "the entry point's code changed");
        let options = Options { targets: vec![crate::Target::Spirv], ..Options::default() };
        let text = SOURCE.replace("ENTRY", "1.0").replace("HELPER", "x");
        let v = validate(&text, "main_ps", crate::Stage::Fragment, &options.limits).unwrap();
        assert_ne!(module_hash(&v, &options), base, "other targets");
    }
}
