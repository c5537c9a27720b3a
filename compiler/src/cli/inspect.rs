//! `kiln inspect`: an archive's summary, its permutation list, one artifact's bytes or one
//! permutation's reflection.

use std::collections::{BTreeMap, HashSet};
use std::fmt::Write as _;
use std::io::Write as _;
use std::path::{Path, PathBuf};

use super::{escape, print_stdout, CliResult, Failure};
use kiln::archive::{
    Archive, ArchiveError, BindingKind, Lookup, NumericType, PermutationRef, Reflection, ScalarKind, Target,
};
use kiln::cache::format_size;

/// Arguments of `kiln inspect`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The archive (`shaders.kpak`).
    pub archive: PathBuf,
    /// A permutation's canonical name (`Shader@level{DIM=value,...}`; an enum's value by name
    /// or index): print its artifact (`--target`) or its reflection (`--reflection`).
    pub permutation: Option<String>,
    /// Print as JSON (the summary, or with `--reflection` the reflection).
    #[arg(long, conflicts_with_all = ["list", "target"])]
    pub json: bool,
    /// Print every permutation's canonical name, one per line.
    #[arg(long, conflicts_with_all = ["permutation", "json"])]
    pub list: bool,
    /// Print the pipeline manifest (`kiln build --usage`): one pipeline a line, in the order
    /// a renderer creates them (with `--json`, a JSON object).
    #[arg(long, conflicts_with_all = ["permutation", "list"])]
    pub pipelines: bool,
    /// The target whose artifact to print: wgsl, spirv, msl, glsl or hlsl.
    #[arg(long, short = 't', requires = "permutation", conflicts_with = "reflection")]
    pub target: Option<String>,
    /// Write the artifact to FILE instead of stdout.
    #[arg(long, short = 'o', requires = "target")]
    pub output: Option<PathBuf>,
    /// Print the permutation's bind groups, vertex inputs, outputs and workgroup size.
    #[arg(long, requires = "permutation")]
    pub reflection: bool,
}

/// Opens the archive; a missing, truncated, corrupted or foreign file, an unknown name or
/// target and a corrupted blob are exit code 2.
pub fn exec(args: Args) -> CliResult {
    let damaged = |e: kiln::archive::ArchiveError| match e {
        kiln::archive::ArchiveError::Io { .. } | kiln::archive::ArchiveError::NotAFile { .. } => {
            Failure::usage(format!("error: {e}"))
        }
        _ => Failure::usage(format!("error: {}: {e}", args.archive.display())),
    };
    let archive = Archive::open(&args.archive).map_err(damaged)?;
    if args.pipelines {
        return print_stdout(&pipelines(archive.pipeline_manifest(), args.json));
    }
    if args.list {
        // Every record is checked before the first name is printed; then the names are
        // streamed (the list grows with the set).
        let permutations = archive.permutations().map_err(damaged)?;
        return stream_stdout(|out| {
            for (i, p) in permutations.enumerate() {
                out.write_all(escape(p.name()).as_bytes())?;
                out.write_all(b"\n")?;
                release_now(&archive, i);
            }
            Ok(())
        });
    }
    let Some(name) = &args.permutation else {
        if args.json {
            // Every record and blob is checked (by the targets' sizes) before the first byte
            // is printed; then the permutations are streamed.
            let targets = target_sizes(&archive).map_err(damaged)?;
            return stream_stdout(|out| json(&archive, targets, out));
        }
        return print_stdout(&text(&archive, &args.archive).map_err(damaged)?);
    };
    let p = find(&archive, name).map_err(|e| e.unwrap_or_else(damaged))?;
    if let Some(t) = &args.target {
        return artifact(&p, t, args.output.as_deref());
    }
    if args.reflection {
        let text = if args.json {
            let mut s = serde_json::to_string_pretty(p.reflection()).expect("json");
            s.push('\n');
            s
        } else {
            reflection_text(&p)
        };
        return print_stdout(&text);
    }
    Err(Failure::usage(format!(
        "error: say what to show of `{}`: --target T (its artifact) or --reflection",
        escape(p.name())
    )))
}

/// The pipeline manifest as text (`render VERTEX FRAGMENT|- STATE FIRST_FRAME`, `compute
/// PERMUTATION FIRST_FRAME`, names escaped) or as JSON (`{"pipelines": [...]}`, `null` for
/// an archive without one).
fn pipelines(manifest: Option<&[kiln::archive::PipelineRecord]>, json: bool) -> String {
    use kiln::archive::usage::UsageKey;
    if json {
        let mut s = serde_json::to_string_pretty(&serde_json::json!({ "pipelines": manifest })).expect("json");
        s.push('\n');
        return s;
    }
    let Some(manifest) = manifest else {
        return "no pipeline manifest (the archive was built without `--usage`)\n".to_string();
    };
    let mut s = format!("{} pipelines, in first-use order:\n", manifest.len());
    for r in manifest {
        let _ = match &r.key {
            UsageKey::Compute { compute } => writeln!(s, "compute {} {}", escape(compute), r.first_frame),
            UsageKey::Render { vertex, fragment, state } => writeln!(
                s,
                "render {} {} {} {}",
                escape(vertex),
                escape(fragment.as_deref().unwrap_or("-")),
                escape(state),
                r.first_frame
            ),
        };
    }
    s
}

/// The permutation `name` names: its canonical name, or the same with enum values given by
/// index. An unknown name lists the nearest (`Err(Ok(failure))`); a damaged archive is
/// `Err(Err(error))`.
fn find<'a>(archive: &'a Archive, name: &str) -> Result<PermutationRef<'a>, Result<Failure, ArchiveError>> {
    if let Some(p) = archive.get(name).map_err(Err)? {
        return Ok(p);
    }
    if let Some(canonical) = canonical_form(archive, name) {
        if let Some(p) = archive.get(&canonical).map_err(Err)? {
            return Ok(p);
        }
    }
    let near = match archive.lookup(name).map_err(Err)? {
        Lookup::Found(p) => return Ok(p),
        Lookup::Missing(near) => near,
    };
    let mut msg = format!("error: permutation `{}` is not in the archive", escape(name));
    if near.is_empty() {
        msg.push_str(" (the archive holds no permutations)");
    } else {
        msg.push_str("; nearest:");
        for n in near {
            let _ = write!(msg, "\n  {}", escape(&n.name));
            if !n.differences.is_empty() {
                let _ = write!(msg, "  (differs in {})", escape(&n.differences.join(", ")));
            }
        }
    }
    Err(Ok(Failure::usage(msg)))
}

/// `Shader@level{A=1,B=0}` rewritten through the archive's dimension records (enum indices
/// to labels, any order of dimensions); `None` when it does not parse that far.
fn canonical_form(archive: &Archive, name: &str) -> Option<String> {
    let (head, rest) = name.split_once('{')?;
    let (shader, level) = head.split_once('@')?;
    let body = rest.strip_suffix('}')?;
    let values: Vec<(&str, &str)> = body
        .split(',')
        .filter(|kv| !kv.trim().is_empty())
        .map(|kv| kv.split_once('=').map(|(k, v)| (k.trim(), v.trim())))
        .collect::<Option<_>>()?;
    archive.canonical_name(shader.trim(), level.trim(), &values).ok()
}

/// Writes one artifact's bytes to stdout or `output`.
fn artifact(p: &PermutationRef<'_>, target: &str, output: Option<&Path>) -> CliResult {
    let targets = || p.targets().map(|t| t.name()).collect::<Vec<_>>().join(", ");
    let t = Target::from_name(target).ok_or_else(|| {
        Failure::usage(format!("error: unknown target `{target}` (targets: wgsl, spirv, msl, glsl, hlsl)"))
    })?;
    let bytes = p.artifact(t).map_err(|e| Failure::usage(format!("error: {e}")))?.ok_or_else(|| {
        Failure::usage(format!("error: `{}` has no {t} artifact (it has: {})", escape(p.name()), targets()))
    })?;
    match output {
        None => {
            let mut out = std::io::stdout().lock();
            match out.write_all(&bytes).and_then(|_| out.flush()) {
                Ok(()) => Ok(()),
                Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
                Err(e) => Err(Failure::usage(format!("error: cannot write to stdout: {e}"))),
            }
        }
        Some(path) => write_output(path, &bytes)
            .map_err(|e| Failure::usage(format!("error: cannot write {}: {e}", path.display()))),
    }
}

/// A regular file (or a new one) is replaced atomically; a device or FIFO (`-o /dev/null`)
/// is written through, never renamed over; a directory is refused.
fn write_output(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    match std::fs::metadata(path) {
        Ok(m) if m.is_dir() => Err(std::io::Error::other("it is a directory")),
        Ok(m) if !m.is_file() => std::fs::OpenOptions::new().write(true).open(path)?.write_all(bytes),
        _ => kiln::archive::write_atomic_unsynced(path, bytes),
    }
}

/// Per target: (permutations, distinct blobs, raw bytes, stored bytes, dictionary bytes).
#[derive(Default)]
struct TargetSizes {
    permutations: usize,
    blobs: usize,
    raw: u64,
    stored: u64,
    dictionary: u64,
}

/// Releases the archive's touched pages every [`kiln::archive::RELEASE_EVERY`] steps of a
/// walk: a tool's peak then stays flat however large the archive.
fn release_now(archive: &Archive, step: usize) {
    if (step + 1).is_multiple_of(kiln::archive::RELEASE_EVERY) {
        archive.release_pages();
    }
}

/// Writes to stdout through a buffer; a closed pipe ends the output quietly.
fn stream_stdout(write: impl FnOnce(&mut dyn std::io::Write) -> std::io::Result<()>) -> CliResult {
    let mut out = std::io::BufWriter::with_capacity(64 << 10, std::io::stdout().lock());
    match write(&mut out).and_then(|_| out.flush()) {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
        Err(e) => Err(Failure::usage(format!("error: cannot write to stdout: {e}"))),
    }
}

fn target_sizes(a: &Archive) -> Result<BTreeMap<Target, TargetSizes>, ArchiveError> {
    // One bit per blob (a set of blob ids grew large with the set).
    let mut seen = vec![0u64; a.blob_count().div_ceil(64)];
    let mut out: BTreeMap<Target, TargetSizes> = BTreeMap::new();
    for (i, p) in a.permutations()?.enumerate() {
        release_now(a, i);
        for t in p.targets() {
            let e = out.entry(t).or_default();
            e.permutations += 1;
            let Some(id) = p.blob_id(t) else { continue };
            let (word, bit) = (id.0 as usize / 64, 1u64 << (id.0 % 64));
            let first = seen.get(word).is_none_or(|w| w & bit == 0);
            if let Some(w) = seen.get_mut(word) {
                *w |= bit;
            }
            if first {
                let Some(info) = p.blob_info(t)? else { continue };
                e.blobs += 1;
                e.raw += info.raw_len;
                e.stored += info.stored_len;
            }
        }
    }
    for (t, len) in a.dictionaries() {
        out.entry(t).or_default().dictionary += len;
    }
    Ok(out)
}

fn kind_name(k: &BindingKind) -> String {
    match k {
        BindingKind::UniformBuffer { min_size } => format!("uniform({min_size} B)"),
        BindingKind::StorageBuffer { read_only, min_size } => {
            format!("storage{}({min_size} B)", if *read_only { ", read" } else { ", read_write" })
        }
        BindingKind::Sampler { comparison } => {
            if *comparison {
                "sampler_comparison".into()
            } else {
                "sampler".into()
            }
        }
        BindingKind::Texture { dim, sample, multisampled } => {
            format!("texture({dim:?}, {sample:?}{})", if *multisampled { ", multisampled" } else { "" })
        }
        BindingKind::StorageTexture { dim, format, access } => {
            format!("storage_texture({dim:?}, {format}, {access:?})")
        }
    }
}

/// `f32`, `vec3<u32>`: a numeric type as WGSL spells it.
fn numeric(t: &NumericType) -> String {
    let bits = u32::from(t.width) * 8;
    let scalar = match t.scalar {
        ScalarKind::Float => format!("f{bits}"),
        ScalarKind::Sint => format!("i{bits}"),
        ScalarKind::Uint => format!("u{bits}"),
        ScalarKind::Bool => "bool".to_string(),
    };
    if t.components <= 1 {
        scalar
    } else {
        format!("vec{}<{scalar}>", t.components)
    }
}

fn bindings_text(s: &mut String, r: &Reflection, indent: &str) {
    for b in &r.bindings {
        let _ = writeln!(
            s,
            "{indent}@group({}) @binding({}) {}: {}",
            b.group,
            b.binding,
            escape(b.name.as_deref().unwrap_or("_")),
            kind_name(&b.kind)
        );
    }
}

/// The reflection of one permutation, every field of it.
fn reflection_text(p: &PermutationRef<'_>) -> String {
    let r = p.reflection();
    let sh = p.shader();
    let mut s = String::new();
    let _ = writeln!(s, "permutation: {}", escape(p.name()));
    let _ = writeln!(s, "entry: {} `{}`", sh.stage, r.entry);
    if r.bindings.is_empty() {
        let _ = writeln!(s, "bind groups: none");
    } else {
        let _ = writeln!(s, "bind groups:");
        bindings_text(&mut s, r, "  ");
    }
    if !r.vertex_inputs.is_empty() {
        let _ = writeln!(s, "vertex inputs:");
        for v in &r.vertex_inputs {
            let _ = writeln!(
                s,
                "  @location({}) {}: {}",
                v.location,
                escape(v.name.as_deref().unwrap_or("_")),
                numeric(&v.ty)
            );
        }
    }
    if !r.color_outputs.is_empty() {
        let _ = writeln!(s, "color outputs:");
        for o in &r.color_outputs {
            let _ = writeln!(s, "  @location({}): {}", o.location, numeric(&o.ty));
        }
    }
    if let Some([x, y, z]) = r.workgroup_size {
        let _ = writeln!(s, "workgroup size: ({x}, {y}, {z})");
    }
    s
}

fn text(a: &Archive, path: &Path) -> Result<String, ArchiveError> {
    let mut s = String::new();
    let perms = a.permutation_count();
    let _ = writeln!(s, "archive: {} ({})", path.display(), format_size(a.len() as u64));
    let _ = writeln!(s, "format version: {}", a.format_version());
    let _ = writeln!(s, "kiln: {}  naga: {}", a.kiln_version(), a.naga_version());
    let _ = writeln!(s, "permutations: {perms}  blobs: {}  reflections: {}", a.blob_count(), a.reflections().len());
    let _ = writeln!(s, "targets:");
    for (t, z) in target_sizes(a)? {
        let dict =
            if z.dictionary > 0 { format!(" + {} dictionary", format_size(z.dictionary)) } else { String::new() };
        let ratio = if z.stored + z.dictionary > 0 { z.raw as f64 / (z.stored + z.dictionary) as f64 } else { 1.0 };
        let _ = writeln!(
            s,
            "  {:<6} {} permutations, {} distinct: {} raw, {} compressed{dict} ({ratio:.1}x)",
            t.name(),
            z.permutations,
            z.blobs,
            format_size(z.raw),
            format_size(z.stored),
        );
    }
    let _ = writeln!(s, "shaders:");
    // Per shader: its count, its first permutation and its distinct reflections (not every
    // permutation, which grows with the set).
    let mut by_shader: Vec<(usize, Option<PermutationRef<'_>>, HashSet<u32>)> =
        (0..a.shaders().len()).map(|_| (0, None, HashSet::new())).collect();
    for (i, p) in a.permutations()?.enumerate() {
        release_now(a, i);
        let (count, first, reflections) = &mut by_shader[p.shader_index() as usize];
        *count += 1;
        reflections.insert(p.reflection_index());
        first.get_or_insert(p);
    }
    for (sh, (count, first, reflections)) in a.shaders().iter().zip(&by_shader) {
        let dims: Vec<&str> = sh.dimensions.iter().map(|d| d.name.as_str()).collect();
        let _ = writeln!(
            s,
            "  {}@{}  {} `{}`  {} permutations  dimensions: [{}]",
            escape(&sh.name),
            escape(&sh.level),
            sh.stage,
            escape(&sh.entry),
            count,
            escape(&dims.join(", "))
        );
        if let Some(p) = first {
            let r = p.reflection();
            bindings_text(&mut s, r, "      ");
            if !r.vertex_inputs.is_empty() {
                let locs: Vec<String> = r.vertex_inputs.iter().map(|v| v.location.to_string()).collect();
                let _ = writeln!(s, "      vertex inputs at locations {}", locs.join(", "));
            }
            if !r.color_outputs.is_empty() {
                let locs: Vec<String> = r.color_outputs.iter().map(|v| v.location.to_string()).collect();
                let _ = writeln!(s, "      color outputs at locations {}", locs.join(", "));
            }
            if let Some([x, y, z]) = r.workgroup_size {
                let _ = writeln!(s, "      workgroup size ({x}, {y}, {z})");
            }
            if *count > 1 {
                let _ = writeln!(
                    s,
                    "      (reflection of {}; {} distinct among its permutations)",
                    escape(p.name()),
                    reflections.len()
                );
            }
        }
    }
    Ok(s)
}

/// `value` as `serde_json::to_string_pretty` writes it, its lines after the first indented
/// by `indent` spaces (its place in the enclosing pretty document).
fn pretty_at(value: &impl serde::Serialize, indent: usize) -> String {
    let text = serde_json::to_string_pretty(value).expect("json");
    text.replace('\n', &format!("\n{}", " ".repeat(indent)))
}

/// The summary as JSON, written as `serde_json::to_string_pretty` wrote the whole document
/// (keys sorted), one permutation at a time: the whole document as `serde_json::Value` grew
/// many times the archive's size.
fn json(a: &Archive, targets: BTreeMap<Target, TargetSizes>, out: &mut dyn std::io::Write) -> std::io::Result<()> {
    let targets: serde_json::Map<String, serde_json::Value> = targets
        .into_iter()
        .map(|(t, z)| {
            let v = serde_json::json!({
                "permutations": z.permutations,
                "blobs": z.blobs,
                "bytes": z.raw,
                "raw_bytes": z.raw,
                "compressed_bytes": z.stored,
                "dictionary_bytes": z.dictionary,
            });
            (t.name().to_string(), v)
        })
        .collect();
    writeln!(out, "{{")?;
    writeln!(out, "  \"blobs\": {},", a.blob_count())?;
    writeln!(out, "  \"bytes\": {},", a.len())?;
    writeln!(out, "  \"format_version\": {},", a.format_version())?;
    writeln!(out, "  \"kiln_version\": {},", serde_json::to_string(a.kiln_version()).expect("json"))?;
    writeln!(out, "  \"naga_version\": {},", serde_json::to_string(a.naga_version()).expect("json"))?;
    let permutations = a.permutations().map_err(std::io::Error::other)?;
    let mut first = true;
    for (i, p) in permutations.enumerate() {
        release_now(a, i);
        let (mut sizes, mut compressed) = (serde_json::Map::new(), serde_json::Map::new());
        for t in p.targets() {
            if let Some(info) = p.blob_info(t).map_err(std::io::Error::other)? {
                sizes.insert(t.name().to_string(), serde_json::json!(info.raw_len));
                compressed.insert(t.name().to_string(), serde_json::json!(info.stored_len));
            }
        }
        let v = serde_json::json!({
            "name": p.name(),
            "shader": p.shader().name,
            "level": p.shader().level,
            "values": p.decode_values().collect::<Vec<i64>>(),
            "artifacts": sizes,
            "compressed": compressed,
            "reflection": p.reflection(),
        });
        out.write_all(if first { b"  \"permutations\": [\n    " } else { b",\n    " })?;
        out.write_all(pretty_at(&v, 4).as_bytes())?;
        first = false;
    }
    out.write_all(if first { b"  \"permutations\": [],\n" } else { b"\n  ],\n" })?;
    // As a `Value`, as the whole document was: its keys sorted.
    let shaders = serde_json::to_value(a.shaders()).expect("json");
    writeln!(out, "  \"shaders\": {},", pretty_at(&shaders, 2))?;
    writeln!(out, "  \"targets\": {}", pretty_at(&targets, 2))?;
    writeln!(out, "}}")
}
