//! `kiln inspect`.

use std::collections::BTreeMap;
use std::fmt::Write;
use std::path::PathBuf;

use super::{print_stdout, CliResult, Failure};
use crate::archive::{Archive, BindingKind, Target};
use crate::cache::format_size;

/// Arguments of `kiln inspect`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The archive (`shaders.kpak`).
    pub archive: PathBuf,
    /// Print the summary as JSON.
    #[arg(long)]
    pub json: bool,
}

/// Opens the archive; a missing, truncated, corrupted or foreign file is exit code 2.
pub fn exec(args: Args) -> CliResult {
    let archive = Archive::open(&args.archive).map_err(|e| match e {
        crate::archive::ArchiveError::Io { .. } => Failure::usage(format!("error: {e}")),
        _ => Failure::usage(format!("error: {}: {e}", args.archive.display())),
    })?;
    let text = if args.json { json(&archive) } else { text(&archive, &args.archive) };
    print_stdout(&text)
}

fn target_sizes(a: &Archive) -> BTreeMap<Target, (usize, u64)> {
    // (permutations with the target, bytes of the distinct blobs of the target)
    let mut seen = std::collections::HashSet::new();
    let mut out: BTreeMap<Target, (usize, u64)> = BTreeMap::new();
    for p in a.permutations() {
        for t in p.targets() {
            let e = out.entry(t).or_default();
            e.0 += 1;
            let id = p.blob_id(t).expect("listed target");
            if seen.insert(id) {
                e.1 += a.blob(id).len() as u64;
            }
        }
    }
    out
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

fn text(a: &Archive, path: &std::path::Path) -> String {
    let mut s = String::new();
    let perms = a.permutations().count();
    let _ = writeln!(s, "archive: {} ({})", path.display(), format_size(a.len() as u64));
    let _ = writeln!(s, "format version: {}", crate::archive::FORMAT_VERSION);
    let _ = writeln!(s, "kiln: {}  naga: {}", a.kiln_version(), a.naga_version());
    let _ = writeln!(s, "permutations: {perms}  blobs: {}  reflections: {}", a.blob_count(), a.reflections().len());
    let _ = writeln!(s, "targets:");
    for (t, (n, bytes)) in target_sizes(a) {
        let _ = writeln!(s, "  {:<6} {n} permutations, {} distinct", t.name(), format_size(bytes));
    }
    let _ = writeln!(s, "shaders:");
    for (i, sh) in a.shaders().iter().enumerate() {
        let ps: Vec<_> = a.permutations().filter(|p| p.record().shader as usize == i).collect();
        let dims: Vec<&str> = sh.dimensions.iter().map(|d| d.name.as_str()).collect();
        let _ = writeln!(
            s,
            "  {}@{}  {} `{}`  {} permutations  dimensions: [{}]",
            sh.name,
            sh.level,
            sh.stage,
            sh.entry,
            ps.len(),
            dims.join(", ")
        );
        if let Some(p) = ps.first() {
            let r = p.reflection();
            for b in &r.bindings {
                let _ = writeln!(
                    s,
                    "      @group({}) @binding({}) {}: {}",
                    b.group,
                    b.binding,
                    b.name.as_deref().unwrap_or("_"),
                    kind_name(&b.kind)
                );
            }
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
            if ps.len() > 1 {
                let _ = writeln!(s, "      (reflection of {}; {} distinct among its permutations)", p.name(), {
                    let mut rs: Vec<_> = ps.iter().map(|p| p.record().reflection).collect();
                    rs.sort_unstable();
                    rs.dedup();
                    rs.len()
                });
            }
        }
    }
    s
}

fn json(a: &Archive) -> String {
    let targets: serde_json::Map<String, serde_json::Value> = target_sizes(a)
        .into_iter()
        .map(|(t, (n, bytes))| (t.name().to_string(), serde_json::json!({ "permutations": n, "bytes": bytes })))
        .collect();
    let permutations: Vec<serde_json::Value> = a
        .permutations()
        .map(|p| {
            let sizes: serde_json::Map<String, serde_json::Value> = p
                .targets()
                .map(|t| (t.name().to_string(), serde_json::json!(p.artifact(t).map_or(0, |b| b.len()))))
                .collect();
            serde_json::json!({
                "name": p.name(),
                "shader": p.shader().name,
                "level": p.shader().level,
                "values": p.values(),
                "artifacts": sizes,
                "reflection": p.reflection(),
            })
        })
        .collect();
    let v = serde_json::json!({
        "format_version": crate::archive::FORMAT_VERSION,
        "kiln_version": a.kiln_version(),
        "naga_version": a.naga_version(),
        "bytes": a.len(),
        "blobs": a.blob_count(),
        "shaders": a.shaders(),
        "targets": targets,
        "permutations": permutations,
    });
    let mut s = serde_json::to_string_pretty(&v).expect("json");
    s.push('\n');
    s
}
