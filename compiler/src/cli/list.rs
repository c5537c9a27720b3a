//! `kiln list`.

use std::io::{self, IsTerminal, Write};
use std::path::PathBuf;

use serde_json::json;

use super::{CliResult, Failure};
use crate::permute::{self, Analysis, Config, Permutation};
use crate::preprocess::{self, SourceCache};

/// Arguments of `kiln list`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The permutation set.
    #[arg(long, value_name = "FILE", default_value = "permutations.toml")]
    pub config: PathBuf,
    /// Only this shader.
    #[arg(long, value_name = "NAME")]
    pub shader: Option<String>,
    /// Only this feature level.
    #[arg(long, value_name = "L")]
    pub level: Option<String>,
    /// Also list the skipped permutations, with the rule and reason that skipped each.
    #[arg(long)]
    pub all: bool,
    /// Print JSON: the permutations, the counts and the dead dimensions.
    #[arg(long)]
    pub json: bool,
    /// Do not preprocess: no distinct counts and no dead dimensions, but much faster.
    #[arg(long)]
    pub no_analysis: bool,
}

/// Loads a permutation set, rendering a bad one as exit code 2.
pub(super) fn load_config(path: &std::path::Path) -> Result<Config, Failure> {
    permute::load(path).map_err(|e| Failure::usage(e.render_with(io::stderr().is_terminal())))
}

/// Runs `body` on a buffered stdout; a closed pipe (`kiln list | head`) is success.
pub(super) fn with_stdout(body: impl FnOnce(&mut dyn Write) -> io::Result<()>) -> CliResult {
    let stdout = io::stdout();
    let mut out = io::BufWriter::new(stdout.lock());
    match body(&mut out).and_then(|_| out.flush()) {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == io::ErrorKind::BrokenPipe => Ok(()),
        Err(e) => Err(Failure::usage(format!("error: cannot write to stdout: {e}"))),
    }
}

#[derive(Default)]
struct Count {
    shader: String,
    level: String,
    kept: usize,
    skipped: usize,
}

pub fn exec(args: Args) -> CliResult {
    let config = load_config(&args.config)?;
    if let Some(s) = &args.shader {
        if config.shader(s).is_none() {
            let names: Vec<&str> = config.shaders.iter().map(|s| s.name.as_str()).collect();
            return Err(Failure::usage(format!("error: no shader named `{s}` in {} (shaders: {})", args.config.display(), names.join(", "))));
        }
    }
    if let Some(l) = &args.level {
        if config.level(l).is_none() {
            let names: Vec<&str> = config.levels.iter().map(|l| l.name.as_str()).collect();
            return Err(Failure::usage(format!("error: no level named `{l}` in {} (levels: {})", args.config.display(), names.join(", "))));
        }
    }
    let shader = args.shader.clone();
    let level = args.level.clone();
    let filter = move |s: &permute::Shader, l: &permute::Level| {
        shader.as_deref().is_none_or(|n| n == s.name) && level.as_deref().is_none_or(|n| n == l.name)
    };

    let mut counts: Vec<Count> = Vec::new();
    let mut errors: Vec<String> = Vec::new();
    let mut tally = |p: &Permutation<'_>, counts: &mut Vec<Count>| {
        if !matches!(counts.last(), Some(c) if c.shader == p.shader.name && c.level == p.level.name) {
            counts.push(Count { shader: p.shader.name.clone(), level: p.level.name.clone(), ..Count::default() });
        }
        let c = counts.last_mut().expect("pushed above");
        if p.is_kept() {
            c.kept += 1;
        } else {
            c.skipped += 1;
        }
        if let Some(e) = &p.error {
            errors.push(format!("warning: {}: {e}", p.name()));
        }
    };

    // The names stream out first; the analysis (which preprocesses) comes after.
    let cache = SourceCache::new(config.dir.clone());
    let mut analysis: Option<Analysis> = None;
    let result = with_stdout(|out| {
        if args.json {
            writeln!(out, "{{")?;
            writeln!(out, "  \"config\": {},", json!(config.path.display().to_string()))?;
            write!(out, "  \"permutations\": [")?;
            let mut first = true;
            for p in config.permutations_where(&filter) {
                tally(&p, &mut counts);
                if !(args.all || p.is_kept()) {
                    continue;
                }
                let values: serde_json::Map<String, serde_json::Value> = p
                    .shader
                    .dimensions
                    .iter()
                    .zip(&p.values)
                    .map(|(d, v)| (d.name.clone(), if d.labels.is_empty() { json!(v) } else { json!(d.display(*v)) }))
                    .collect();
                let skip = p.skipped_by.map(|i| json!({ "rule": i + 1, "when": p.shader.skip[i].when, "why": p.shader.skip[i].why }));
                let obj = json!({
                    "name": p.name(), "shader": p.shader.name, "level": p.level.name, "values": values,
                    "kept": p.is_kept(), "skip": skip,
                });
                write!(out, "{}\n    {obj}", if first { "" } else { "," })?;
                first = false;
            }
            writeln!(out, "\n  ],")?;
            if !args.no_analysis {
                analysis = Some(permute::analyze(&config, &cache, &filter));
            }
            let count_json: Vec<serde_json::Value> = counts
                .iter()
                .map(|c| {
                    let distinct = analysis.as_ref().and_then(|a| a.find(&c.shader, &c.level)).map(|l| l.distinct);
                    json!({ "shader": c.shader, "level": c.level, "kept": c.kept, "skipped": c.skipped, "distinct": distinct })
                })
                .collect();
            let kept: usize = counts.iter().map(|c| c.kept).sum();
            let skipped: usize = counts.iter().map(|c| c.skipped).sum();
            let distinct = analysis.as_ref().map(|a| a.levels.iter().map(|l| l.distinct).sum::<usize>());
            let dead: Vec<serde_json::Value> = analysis
                .iter()
                .flat_map(|a| a.dead())
                .map(|d| json!({ "shader": d.shader, "level": d.level, "dimension": d.dimension, "multiplier": d.multiplier }))
                .collect();
            let failed: Vec<&str> = analysis.iter().flat_map(|a| a.failed.iter().map(|f| f.name.as_str())).collect();
            writeln!(out, "  \"counts\": {},", serde_json::to_string(&count_json).map_err(io::Error::other)?)?;
            writeln!(out, "  \"totals\": {},", json!({ "kept": kept, "skipped": skipped, "distinct": distinct }))?;
            writeln!(out, "  \"dead_dimensions\": {},", json!(dead))?;
            writeln!(out, "  \"failed\": {}", json!(failed))?;
            writeln!(out, "}}")?;
            return Ok(());
        }

        for p in config.permutations_where(&filter) {
            tally(&p, &mut counts);
            match p.skipped_by {
                None => writeln!(out, "{}", p.name())?,
                Some(i) if args.all => {
                    let rule = &p.shader.skip[i];
                    writeln!(out, "{}  skipped by rule {}: {} (when {})", p.name(), i + 1, rule.why, rule.when)?
                }
                Some(_) => {}
            }
        }
        out.flush()?;
        if !args.no_analysis {
            analysis = Some(permute::analyze(&config, &cache, &filter));
        }
        write_summary(out, &counts, analysis.as_ref())
    });
    for e in errors.iter().take(20) {
        eprintln!("{e}");
    }
    if let Some(a) = &analysis {
        if let Some(first) = a.failed.first() {
            eprintln!(
                "warning: {} permutation(s) failed to preprocess; distinct counts and dead dimensions leave them out. The first, {}:",
                a.failed.len(),
                first.name
            );
            eprint!("{}", preprocess::render(std::slice::from_ref(&first.error.diagnostic), &cache, io::stderr().is_terminal()));
        }
    }
    result
}

fn write_summary(out: &mut dyn Write, counts: &[Count], analysis: Option<&Analysis>) -> io::Result<()> {
    let distinct = |c: &Count| -> String {
        match analysis.and_then(|a| a.find(&c.shader, &c.level)) {
            Some(l) => l.distinct.to_string(),
            None => "-".to_string(),
        }
    };
    let total_kept: usize = counts.iter().map(|c| c.kept).sum();
    let total_skipped: usize = counts.iter().map(|c| c.skipped).sum();
    let total_distinct = match analysis {
        Some(a) => a.levels.iter().map(|l| l.distinct).sum::<usize>().to_string(),
        None => "-".to_string(),
    };
    let ws = counts.iter().map(|c| c.shader.len()).chain([6]).max().unwrap_or(6);
    let wl = counts.iter().map(|c| c.level.len()).chain([5]).max().unwrap_or(5);
    writeln!(out)?;
    writeln!(out, "{:<ws$}  {:<wl$}  {:>8}  {:>8}  {:>8}", "shader", "level", "kept", "skipped", "distinct")?;
    for c in counts {
        writeln!(out, "{:<ws$}  {:<wl$}  {:>8}  {:>8}  {:>8}", c.shader, c.level, c.kept, c.skipped, distinct(c))?;
    }
    writeln!(out, "{:<ws$}  {:<wl$}  {:>8}  {:>8}  {:>8}", "total", "", total_kept, total_skipped, total_distinct)?;
    if let Some(a) = analysis {
        let dead: Vec<_> = a.dead().collect();
        if !dead.is_empty() {
            writeln!(out)?;
            writeln!(out, "dead dimensions (they never change the preprocessed text):")?;
            for d in dead {
                writeln!(out, "  {}@{}: {} (x{} permutations for nothing)", d.shader, d.level, d.dimension, d.multiplier)?;
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Debug, Parser)]
    struct Cli {
        #[command(flatten)]
        args: Args,
    }

    #[test]
    fn defaults() {
        let cli = Cli::try_parse_from(["list"]).unwrap();
        assert_eq!(cli.args.config, PathBuf::from("permutations.toml"));
        assert!(!cli.args.all && !cli.args.json && cli.args.shader.is_none());
        let cli = Cli::try_parse_from(["list", "--config", "x.toml", "--shader", "S", "--level", "sm5", "--all", "--json"]).unwrap();
        assert_eq!(cli.args.shader.as_deref(), Some("S"));
        assert!(cli.args.all && cli.args.json);
    }
}
