//! Cross-compilation: one preprocessed WGSL source in, every target of a level out.
//!
//! Takes the preprocessed text of one permutation, its entry point and stage, and the
//! level's [`Options`] (targets, [`Limits`]); gives the artifacts, one per target, and the
//! [`Reflection`] of the entry point. Guarantees: the module is parsed and validated once;
//! only the requested entry point is kept, so every writer and the reflection see exactly
//! that entry point; the level's capabilities and resource limits are checked before any
//! writer runs; a writer that panics (naga's writers do on some input) is caught and turned
//! into an [`Error`] like any other. Errors carry byte spans into the preprocessed text;
//! the build maps them back onto the original files through the preprocessor's source map.
//! [`SharedWriters`] runs the writers once per distinct compacted module of a build (keys
//! whose texts differ only in code the entry point never reaches), by [`module_hash`].

mod limits;
pub(crate) mod prefixes;
mod reflect;
mod shared;
mod structural;
mod writers;

use std::ops::Range;

pub use limits::{Limits, WGPU_LIMITS};
pub use reflect::reflect;
pub(crate) use shared::IdentHasher;
pub use shared::{module_hash, SharedWriters};

use crate::archive::{Reflection, Stage, Target};

/// The version of naga Kiln compiles with; part of every cache key and of every archive.
/// A test checks it against `Cargo.lock`.
pub const NAGA_VERSION: &str = "30.0.1";

/// How one level compiles.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct Options {
    /// Outputs to write, in this order.
    pub targets: Vec<Target>,
    /// Resource limits the entry point must fit in.
    pub limits: Limits,
}

impl Options {
    /// How `level` compiles: its targets (those of `filter` only, unless it is empty) and limits.
    pub fn for_level(level: &crate::permute::Level, filter: &[Target]) -> Options {
        Options {
            targets: level.targets.iter().copied().filter(|t| filter.is_empty() || filter.contains(t)).collect(),
            limits: Limits::for_level(level),
        }
    }
}

impl Default for Options {
    /// Every target under wgpu's default (desktop) limits.
    fn default() -> Self {
        Options { targets: Target::ALL.to_vec(), limits: Limits::desktop() }
    }
}

/// The result of compiling one distinct source.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Compiled {
    /// One artifact per requested target, in the order of [`Options::targets`].
    pub artifacts: Vec<(Target, Vec<u8>)>,
    /// The entry point's reflection.
    pub reflection: Reflection,
}

/// What went wrong, with spans into the preprocessed text.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{message}")]
pub struct Error {
    /// Which step failed.
    pub kind: ErrorKind,
    /// One line, lowercase, as naga writes its messages.
    pub message: String,
    /// Byte ranges of the preprocessed text with what to say there; the first is primary.
    pub labels: Vec<(Range<usize>, String)>,
    /// Further explanation (naga's error chain, the limit that was exceeded).
    pub notes: Vec<String>,
}

/// Which step of a compile failed.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ErrorKind {
    /// The WGSL did not parse.
    Parse,
    /// naga's validator rejected the module (types, uniformity, capabilities of the level).
    Validation,
    /// The entry point is missing or has another stage.
    EntryPoint,
    /// A resource limit of the level is exceeded.
    Limit,
    /// A writer failed or panicked.
    Writer(Target),
}

impl Error {
    fn new(kind: ErrorKind, message: impl Into<String>) -> Self {
        Error { kind, message: message.into(), labels: Vec::new(), notes: Vec::new() }
    }
}

fn naga_stage(stage: Stage) -> naga::ShaderStage {
    match stage {
        Stage::Vertex => naga::ShaderStage::Vertex,
        Stage::Fragment => naga::ShaderStage::Fragment,
        Stage::Compute => naga::ShaderStage::Compute,
    }
}

fn stage_name(stage: naga::ShaderStage) -> &'static str {
    match stage {
        naga::ShaderStage::Vertex => "vertex",
        naga::ShaderStage::Fragment => "fragment",
        naga::ShaderStage::Compute => "compute",
        naga::ShaderStage::Task => "task",
        naga::ShaderStage::Mesh => "mesh",
        _ => "ray tracing",
    }
}

/// A parsed and validated module holding only the requested entry point.
pub struct Validated {
    /// The module, compacted to the entry point.
    pub module: naga::Module,
    /// naga's validation info for it.
    pub info: naga::valid::ModuleInfo,
    /// The entry point's name.
    pub entry: String,
    /// The entry point's stage.
    pub stage: Stage,
}

/// Parses `source`, keeps only `entry`, and validates it with the capabilities of `limits`.
pub fn validate(source: &str, entry: &str, stage: Stage, limits: &Limits) -> Result<Validated, Error> {
    let mut module = naga::front::wgsl::parse_str(source).map_err(|e| Error {
        kind: ErrorKind::Parse,
        message: e.message().to_string(),
        labels: e.labels().filter_map(|(span, msg)| Some((span.to_range()?, msg.to_string()))).collect(),
        notes: e.notes().map(str::to_string).collect(),
    })?;
    let want = naga_stage(stage);
    let Some(index) = module.entry_points.iter().position(|ep| ep.name == entry) else {
        let mut e = Error::new(ErrorKind::EntryPoint, format!("no entry point named `{entry}`"));
        let names: Vec<String> =
            module.entry_points.iter().map(|ep| format!("`{}` ({})", ep.name, stage_name(ep.stage))).collect();
        e.notes.push(if names.is_empty() {
            "the module has no entry points".to_string()
        } else {
            format!("the module's entry points: {}", names.join(", "))
        });
        return Err(e);
    };
    let found = module.entry_points[index].stage;
    if found != want {
        let mut e = Error::new(
            ErrorKind::EntryPoint,
            format!("entry point `{entry}` is a {} shader, not a {} shader", stage_name(found), stage.name()),
        );
        if let Some(range) = find_function(source, entry) {
            e.labels.push((range, format!("declared as a {} entry point here", stage_name(found))));
        }
        return Err(e);
    }
    let kept = module.entry_points.swap_remove(index);
    module.entry_points.clear();
    module.entry_points.push(kept);
    // Drop what the kept entry point does not use (other entry points' globals and helpers)
    // before validating: the module validated is the module compiled. Writers would
    // otherwise declare resources the pipeline's layout does not bind, which Mesa's lavapipe
    // does not survive at pipeline creation; and, as with a shader compiler's dead code, a
    // helper of a shared header that this permutation never calls cannot fail it (a desktop
    // helper using a capability the mobile level lacks, say). Compaction only follows
    // handles, which the front end made consistent; a panic is caught all the same.
    let compacted = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        naga::compact::compact(&mut module, naga::compact::KeepUnused::No);
    }));
    if compacted.is_err() {
        return Err(Error::new(ErrorKind::Validation, "internal error: naga panicked while compacting the module"));
    }

    let mut validator = naga::valid::Validator::new(naga::valid::ValidationFlags::all(), limits.capabilities());
    let info = validator.validate(&module).map_err(|e| {
        let mut notes = Vec::new();
        let mut source: Option<&dyn std::error::Error> = std::error::Error::source(e.as_inner());
        while let Some(next) = source {
            notes.push(next.to_string());
            source = next.source();
        }
        Error {
            kind: ErrorKind::Validation,
            message: e.as_inner().to_string(),
            labels: e.spans().filter_map(|(span, msg)| Some((span.to_range()?, msg.clone()))).collect(),
            notes,
        }
    })?;
    Ok(Validated { module, info, entry: entry.to_string(), stage })
}

/// The span of `fn NAME` in WGSL text (the first one outside comments is good enough for a
/// label: WGSL has no overloading).
pub(crate) fn find_function(source: &str, name: &str) -> Option<Range<usize>> {
    let bytes = source.as_bytes();
    let is_ident = |b: u8| b.is_ascii_alphanumeric() || b == b'_';
    let mut from = 0;
    while let Some(i) = source[from..].find(name).map(|i| i + from) {
        from = i + name.len();
        let end = i + name.len();
        if bytes.get(end).is_some_and(|&b| is_ident(b)) || (i > 0 && is_ident(bytes[i - 1])) {
            continue;
        }
        let before = source[..i].trim_end();
        if before.ends_with("fn")
            && !before[..before.len() - 2].ends_with(|c: char| c.is_ascii_alphanumeric() || c == '_')
        {
            return Some(i..end);
        }
    }
    None
}

/// Compiles one preprocessed source: parse, validate, check the limits, reflect, then one
/// writer per target. [`SharedWriters::compile`] does the same, running the writers once per
/// distinct compacted module of a build.
pub fn compile(source: &str, entry: &str, stage: Stage, options: &Options) -> Result<Compiled, Error> {
    let v = validate(source, entry, stage, &options.limits)?;
    let reflection = checked_reflection(&v, options)?;
    let artifacts = write_all(&v, options)?;
    Ok(Compiled { artifacts, reflection })
}

/// Everything [`compile`] checks before its writers run: parse, validation and the level's
/// limits (what an editor shows while the text is typed; writers rarely fail on valid input).
pub fn check(source: &str, entry: &str, stage: Stage, limits: &Limits) -> Result<(), Error> {
    let v = validate(source, entry, stage, limits)?;
    let reflection = reflect(&v.module, &v.info);
    limits.check(&v.module, &v.info, &reflection)
}

/// The entry point's reflection, once the module is checked against the level's limits.
fn checked_reflection(v: &Validated, options: &Options) -> Result<Reflection, Error> {
    let reflection = reflect(&v.module, &v.info);
    options.limits.check(&v.module, &v.info, &reflection)?;
    Ok(reflection)
}

/// Every target's writer on a validated module (overrides resolved to their defaults first).
fn write_all(v: &Validated, options: &Options) -> Result<Vec<(Target, Vec<u8>)>, Error> {
    let (module, info) = if v.module.overrides.is_empty() {
        (std::borrow::Cow::Borrowed(&v.module), std::borrow::Cow::Borrowed(&v.info))
    } else {
        naga::back::pipeline_constants::process_overrides(&v.module, &v.info, None, &Default::default()).map_err(
            |e| {
                let mut err = Error::new(ErrorKind::Validation, format!("cannot resolve overrides: {e}"));
                err.notes
                    .push("every `override` needs a default value: Kiln compiles ahead of pipeline creation".into());
                err
            },
        )?
    };
    let mut artifacts = Vec::with_capacity(options.targets.len());
    for &target in &options.targets {
        let bytes = writers::write(target, &module, &info, &v.entry, v.stage)?;
        artifacts.push((target, bytes));
    }
    Ok(artifacts)
}

#[cfg(test)]
mod tests;
