//! `kiln usage`: usage files as `kiln-view --record-usage` (or any renderer's
//! `PipelineCache::usage`) writes them (format: `kiln_archive::usage`).

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use super::{print_stdout, CliResult, Failure};
use kiln::archive::usage::Usage;

/// Arguments of `kiln usage`.
#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(subcommand)]
    pub action: Action,
}

#[derive(Debug, clap::Subcommand)]
pub enum Action {
    /// Merge usage files of one archive into one: frames add up, the first frame is the
    /// earliest. The same files in any order give the same bytes.
    Merge {
        /// The files to merge.
        #[arg(required = true, value_name = "FILE")]
        files: Vec<PathBuf>,
        /// Where to write the merged file.
        #[arg(short, long, value_name = "FILE")]
        output: PathBuf,
    },
    /// Coverage per shader: permutations used (of those kept, with --config) and pipelines
    /// per used permutation.
    Stats {
        /// The usage file.
        file: PathBuf,
        /// The permutation set, for the kept permutations of each shader.
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
    },
}

/// Reads a usage file; a bad one is exit code 2 naming the file.
pub(super) fn read(path: &Path) -> Result<Usage, Failure> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| Failure::usage(format!("error: cannot read {}: {e}", path.display())))?;
    Usage::parse(&text).map_err(|e| Failure::usage(format!("error: {}: {e}", path.display())))
}

pub fn exec(args: Args) -> CliResult {
    match args.action {
        Action::Merge { files, output } => {
            let mut merged: Option<Usage> = None;
            for f in &files {
                let u = read(f)?;
                match &mut merged {
                    None => merged = Some(u),
                    Some(m) => m.merge(&u).map_err(|e| Failure::usage(format!("error: {}: {e}", f.display())))?,
                }
            }
            let merged = merged.expect("clap requires a file");
            kiln::archive::write_atomic(&output, merged.to_text().as_bytes())
                .map_err(|e| Failure::usage(format!("error: cannot write {}: {e}", output.display())))
        }
        Action::Stats { file, config } => {
            let usage = read(&file)?;
            let kept = match config {
                Some(c) => {
                    let config = kiln::permute::load(&c).map_err(|e| Failure::usage(e.render()))?;
                    let counts = config.kept_counts(&|_, _| true);
                    Some(counts.into_iter().map(|(i, n)| (config.shaders[i].name.clone(), n)).collect())
                }
                None => None,
            };
            print_stdout(&stats(&usage, kept.as_ref()))
        }
    }
}

/// The shader of a canonical name (`Shader@level{...}`).
pub(crate) fn shader_of(name: &str) -> &str {
    name.split('@').next().unwrap_or(name)
}

/// One line per shader (used, kept, pipelines per used permutation), then the totals.
fn stats(usage: &Usage, kept: Option<&BTreeMap<String, u64>>) -> String {
    // Pipelines per permutation.
    let mut per_permutation: BTreeMap<&str, u64> = BTreeMap::new();
    for k in usage.records.keys() {
        for p in k.permutations() {
            *per_permutation.entry(p).or_default() += 1;
        }
    }
    // Per shader: (used permutations, pipelines over them, most pipelines of one).
    let mut shaders: BTreeMap<&str, (u64, u64, u64)> = BTreeMap::new();
    for (p, n) in &per_permutation {
        let s = shaders.entry(shader_of(p)).or_default();
        s.0 += 1;
        s.1 += n;
        s.2 = s.2.max(*n);
    }
    if let Some(kept) = kept {
        for name in kept.keys() {
            shaders.entry(name.as_str()).or_default();
        }
    }
    let mut out = format!(
        "usage of archive {} ({} runs): {} pipelines, {} permutations\n",
        &usage.archive[..16.min(usage.archive.len())],
        usage.runs,
        usage.records.len(),
        per_permutation.len()
    );
    let _ = writeln!(out, "{:<40} {:>13} {:>9} {:>22}", "shader", "used/kept", "coverage", "pipelines/permutation");
    let (mut used_total, mut kept_total) = (0, 0);
    for (name, (used, pipelines, most)) in &shaders {
        let k = kept.and_then(|k| k.get(*name)).copied();
        used_total += used;
        kept_total += k.unwrap_or(0);
        let (of, coverage) = match k {
            Some(k) => (format!("{used}/{k}"), format!("{:.0}%", *used as f64 * 100.0 / k.max(1) as f64)),
            None => (format!("{used}/?"), "-".to_string()),
        };
        let per = match used {
            0 => "-".to_string(),
            _ => format!("{:.2} (max {most})", *pipelines as f64 / *used as f64),
        };
        let _ = writeln!(out, "{name:<40} {of:>13} {coverage:>9} {per:>22}");
    }
    match kept {
        Some(_) => {
            let _ = writeln!(
                out,
                "total: {used_total} of {kept_total} kept permutations used ({:.0}%)",
                used_total as f64 * 100.0 / kept_total.max(1) as f64
            );
        }
        None => {
            let _ = writeln!(out, "total: {used_total} permutations used (--config gives the kept ones)");
        }
    }
    out
}
