//! `kiln list`.

use std::io::{self, IsTerminal, Write};
use std::path::PathBuf;

use serde_json::json;

use super::{escape, CliResult, Failure};
use kiln::permute::{self, Analysis, Config, Permutation};
use kiln::preprocess::{self, SourceCache};

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
    /// The most permutations, of one shader at one level or of all together (default: `[compiler]
    /// max_permutations`, else 16777216 = 2^24); with `--all`, skipped ones count too.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u64).range(1..))]
    pub max_permutations: Option<u64>,
    /// Check the set against its budgets (`[budget]`, each shader's `budget`) without
    /// compiling: kept permutations, and distinct sources unless --no-analysis. Prints one
    /// line per budget; exit code 3 when one is exceeded.
    #[arg(long)]
    pub check_budget: bool,
}

/// The most kept permutations the analysis preprocesses; above it the listing streams
/// alone (in bounded memory) and says so.
const ANALYSIS_LIMIT: usize = 100_000;

/// Loads a permutation set, rendering a bad one as exit code 2.
/// Its warnings go to `err`.
pub(super) fn load_config(path: &std::path::Path, color: bool, err: &mut dyn Write) -> Result<Config, Failure> {
    let config = permute::load(path).map_err(|e| Failure::usage(e.render_with(color)))?;
    for w in &config.warnings {
        let _ = write!(err, "{w}");
    }
    Ok(config)
}

/// A write error: a closed pipe (`kiln list | head`) is success.
pub(super) fn write_result(r: io::Result<()>) -> CliResult {
    match r {
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
    /// Up to 2^128: 64 bool dimensions skipped whole are 2^64.
    skipped: u128,
}

pub fn exec(args: Args) -> CliResult {
    let stdout = io::stdout();
    let mut out = io::BufWriter::new(stdout.lock());
    let color = io::stderr().is_terminal();
    let r = run(&args, &mut out, &mut io::stderr(), color);
    write_result(out.flush())?;
    r
}

/// `kiln list` writing to `out` (the listing) and `err` (warnings).
pub(super) fn run(args: &Args, out: &mut dyn Write, err: &mut dyn Write, color: bool) -> CliResult {
    let config = load_config(&args.config, color, err)?;
    check_names(&config, args)?;
    let shader = args.shader.clone();
    let level = args.level.clone();
    let filter = move |s: &permute::Shader, l: &permute::Level| {
        shader.as_deref().is_none_or(|n| n == s.name) && level.as_deref().is_none_or(|n| n == l.name)
    };

    let max = config.max_permutations(args.max_permutations);
    config.check_space(&filter, max, args.all).map_err(|e| Failure::usage(e.render_with(color)))?;

    if args.check_budget {
        return check_budget(&config, &filter, args, out, err, color);
    }

    // The names stream out first; the analysis (which preprocesses) comes after.
    let cache = SourceCache::new(config.dir.clone());
    let mut listing = Listing {
        config: &config,
        filter: &filter,
        args,
        cache: &cache,
        counts: Vec::new(),
        errors: Vec::new(),
        analysis: None,
    };
    let result = write_result(if args.json { listing.json(out, err) } else { listing.text(out, err) });
    let _ = write_warnings(err, &listing.errors, listing.analysis.as_ref(), &cache, color);
    result
}

/// A usage error when `--shader` or `--level` names none of the set's.
fn check_names(config: &Config, args: &Args) -> CliResult {
    if let Some(s) = &args.shader {
        if config.shader(s).is_none() {
            let names: Vec<&str> = config.shaders.iter().map(|s| s.name.as_str()).collect();
            return Err(Failure::usage(format!(
                "error: no shader named `{s}` in {} (shaders: {})",
                args.config.display(),
                names.join(", ")
            )));
        }
    }
    if let Some(l) = &args.level {
        if config.level(l).is_none() {
            let names: Vec<&str> = config.levels.iter().map(|l| l.name.as_str()).collect();
            return Err(Failure::usage(format!(
                "error: no level named `{l}` in {} (levels: {})",
                args.config.display(),
                names.join(", ")
            )));
        }
    }
    Ok(())
}

/// One listing: what it lists, and what it counted and analysed on the way.
struct Listing<'a> {
    config: &'a Config,
    filter: &'a (dyn Fn(&permute::Shader, &permute::Level) -> bool + Sync),
    args: &'a Args,
    cache: &'a SourceCache,
    counts: Vec<Count>,
    errors: Vec<String>,
    analysis: Option<Analysis>,
}

impl Listing<'_> {
    /// One name a line (a skipped one with its rule), then the summary table.
    fn text(&mut self, out: &mut dyn Write, err: &mut dyn Write) -> io::Result<()> {
        for_each_listed(self.config, self.filter, self.args.all, &mut self.counts, &mut self.errors, &mut |p| match p
            .skipped_by
        {
            None => writeln!(out, "{}", escape(&p.name())),
            Some(i) => {
                let rule = &p.shader.skip[i];
                writeln!(
                    out,
                    "{}  skipped by rule {}: {} (when {})",
                    escape(&p.name()),
                    i + 1,
                    escape(&rule.why),
                    escape(&rule.when)
                )
            }
        })?;
        out.flush()?;
        self.run_analysis(err);
        write_summary(out, &self.counts, self.analysis.as_ref())
    }

    /// `--json`: the permutations, then the counts, totals, dead dimensions and failures.
    fn json(&mut self, out: &mut dyn Write, err: &mut dyn Write) -> io::Result<()> {
        writeln!(out, "{{")?;
        writeln!(out, "  \"config\": {},", json!(self.config.path.display().to_string()))?;
        write!(out, "  \"permutations\": [")?;
        let mut first = true;
        for_each_listed(self.config, self.filter, self.args.all, &mut self.counts, &mut self.errors, &mut |p| {
            write!(out, "{}\n    {}", if first { "" } else { "," }, permutation_json(p))?;
            first = false;
            Ok(())
        })?;
        writeln!(out, "\n  ],")?;
        self.run_analysis(err);
        self.json_counts(out)?;
        writeln!(out, "}}")
    }

    /// Runs the analysis when it is wanted and the set is small enough.
    fn run_analysis(&mut self, err: &mut dyn Write) {
        if analyze(self.args, &self.counts, err) {
            self.analysis = Some(permute::analyze(self.config, self.cache, self.filter));
        }
    }

    /// The JSON listing's `counts`, `totals`, `dead_dimensions` and `failed` members.
    fn json_counts(&self, out: &mut dyn Write) -> io::Result<()> {
        let analysis = &self.analysis;
        let count_json: Vec<serde_json::Value> = self
            .counts
            .iter()
            .map(|c| {
                let distinct = analysis
                    .as_ref()
                    .and_then(|a| a.find(&c.shader, &c.level))
                    .filter(|l| l.permutations.iter().all(|p| p.hash.is_some()))
                    .map(|l| l.distinct);
                json!({ "shader": c.shader, "level": c.level, "kept": c.kept, "skipped": json_count(c.skipped), "distinct": distinct })
            })
            .collect();
        let kept: usize = self.counts.iter().map(|c| c.kept).sum();
        let skipped: u128 = self.counts.iter().map(|c| c.skipped).fold(0, u128::saturating_add);
        let distinct = analysis
            .as_ref()
            .filter(|a| a.failed.is_empty())
            .map(|a| a.levels.iter().map(|l| l.distinct).sum::<usize>());
        let dead: Vec<serde_json::Value> = analysis
            .iter()
            .flat_map(|a| a.dead())
            .map(|d| json!({ "shader": d.shader, "level": d.level, "dimension": d.dimension, "multiplier": d.multiplier }))
            .collect();
        let failed: Vec<&str> = analysis.iter().flat_map(|a| a.failed.iter().map(|f| f.name.as_str())).collect();
        writeln!(out, "  \"counts\": {},", serde_json::to_string(&count_json).map_err(io::Error::other)?)?;
        writeln!(
            out,
            "  \"totals\": {},",
            json!({ "kept": kept, "skipped": json_count(skipped), "distinct": distinct })
        )?;
        writeln!(out, "  \"dead_dimensions\": {},", json!(dead))?;
        writeln!(out, "  \"failed\": {}", json!(failed))
    }
}

/// One permutation of the JSON listing: its name, shader, level, values and skip rule.
fn permutation_json(p: &Permutation<'_>) -> serde_json::Value {
    let values: serde_json::Map<String, serde_json::Value> = p
        .shader
        .dimensions
        .iter()
        .zip(&p.values)
        .map(|(d, v)| (d.name.clone(), if d.labels.is_empty() { json!(v) } else { json!(d.display(*v)) }))
        .collect();
    let skip =
        p.skipped_by.map(|i| json!({ "rule": i + 1, "when": p.shader.skip[i].when, "why": p.shader.skip[i].why }));
    json!({
        "name": p.name(), "shader": p.shader.name, "level": p.level.name, "values": values,
        "kept": p.is_kept(), "skip": skip,
    })
}

/// `--check-budget`: the kept permutations per shader against the shaders' budgets and
/// `[budget] max_permutations`, then (preprocessing, not compiling) the distinct sources
/// against `max_distinct`. One line per checked budget on `out`; exit code 3 with the
/// located diagnostics when one is exceeded.
fn check_budget(
    config: &Config,
    filter: &(dyn Fn(&permute::Shader, &permute::Level) -> bool + Sync),
    args: &Args,
    out: &mut dyn Write,
    err: &mut dyn Write,
    color: bool,
) -> CliResult {
    let counts = config.kept_counts(filter);
    let total: u64 = counts.iter().map(|c| c.1).sum();
    let mut lines = String::new();
    for &(i, n) in &counts {
        if let Some(l) = &config.shaders[i].budget.max_permutations {
            lines.push_str(&format!(
                "budget: shader {} keeps {n} of {} permutations\n",
                config.shaders[i].name, l.value
            ));
        }
    }
    let budget = &config.budget;
    match &budget.max_permutations {
        Some(l) => lines.push_str(&format!("budget: {total} of {} permutations\n", l.value)),
        None => lines.push_str(&format!("budget: {total} permutations (no max_permutations)\n")),
    }
    let mut result = config.check_permutation_budget(&counts, filter).map_err(|e| e.render_with(color));
    if let (Some(l), Ok(())) = (&budget.max_distinct, &result) {
        if args.no_analysis || total as usize > ANALYSIS_LIMIT {
            lines.push_str("budget: max_distinct not checked (no analysis)\n");
        } else {
            let cache = SourceCache::new(config.dir.clone());
            let analysis = permute::analyze(config, &cache, filter);
            let _ = write_warnings(err, &[], Some(&analysis), &cache, color);
            let mut per_shader: Vec<(usize, u64)> = Vec::new();
            for level in &analysis.levels {
                let i = config.shaders.iter().position(|s| s.name == level.shader).unwrap_or(0);
                match per_shader.iter_mut().find(|(s, _)| *s == i) {
                    Some((_, n)) => *n += level.distinct as u64,
                    None => per_shader.push((i, level.distinct as u64)),
                }
            }
            let distinct: u64 = per_shader.iter().map(|c| c.1).sum();
            lines.push_str(&format!("budget: {distinct} of {} distinct sources\n", l.value));
            result = config
                .check_budget(permute::budget::Measure::Distinct, distinct, &per_shader, filter, Vec::new())
                .map_err(|e| e.render_with(color));
        }
    }
    if budget.max_archive_bytes.is_some() || budget.max_compile_ms.is_some() {
        lines.push_str("budget: max_archive_bytes and max_compile_ms are checked by `kiln build`\n");
    }
    write_result(out.write_all(lines.as_bytes()))?;
    result.map_err(Failure::budget)
}

/// A count as a JSON number: exact up to 2^64 - 1, a float above (64 bool dimensions
/// skipped whole are 2^64 permutations).
fn json_count(n: u128) -> serde_json::Value {
    u64::try_from(n).map_or_else(|_| json!(n as f64), |n| json!(n))
}

/// Calls `f` on every permutation to list (the kept ones, pruned; with `all`, every one) of
/// each (shader, level) `filter` accepts, counting them per (shader, level) into `counts`.
fn for_each_listed(
    config: &Config,
    filter: &dyn Fn(&permute::Shader, &permute::Level) -> bool,
    all: bool,
    counts: &mut Vec<Count>,
    errors: &mut Vec<String>,
    f: &mut dyn FnMut(&Permutation<'_>) -> io::Result<()>,
) -> io::Result<()> {
    for (shader, level) in config.groups_where(filter) {
        let same = |s: &permute::Shader, l: &permute::Level| std::ptr::eq(s, shader) && std::ptr::eq(l, level);
        let mut c = Count { shader: shader.name.clone(), level: level.name.clone(), ..Count::default() };
        let mut each = |p: &Permutation<'_>, c: &mut Count| {
            if let Some(e) = &p.error {
                if p.is_kept() {
                    errors.push(format!("warning: {}: {e}", escape(&p.name())));
                }
            }
            if p.is_kept() {
                c.kept += 1;
            } else {
                c.skipped += 1;
            }
            f(p)
        };
        if all {
            for p in config.permutations_where(same) {
                each(&p, &mut c)?;
            }
        } else {
            let mut kept = config.kept_where(same);
            for p in &mut kept {
                each(&p, &mut c)?;
            }
            c.skipped = kept.skipped();
        }
        counts.push(c);
    }
    Ok(())
}

/// Whether to run the analysis (which preprocesses every kept permutation); a note on `err`
/// when there are too many.
fn analyze(args: &Args, counts: &[Count], err: &mut dyn Write) -> bool {
    let kept: usize = counts.iter().map(|c| c.kept).sum();
    if args.no_analysis {
        return false;
    }
    if kept > ANALYSIS_LIMIT {
        let _ = writeln!(
            err,
            "note: {kept} kept permutations: the analysis (distinct sources, dead dimensions) runs up to {ANALYSIS_LIMIT}; \
             use --shader or --level to analyse part of the set"
        );
        return false;
    }
    true
}

fn write_warnings(
    err: &mut dyn Write,
    errors: &[String],
    analysis: Option<&Analysis>,
    cache: &SourceCache,
    color: bool,
) -> io::Result<()> {
    for e in errors.iter().take(20) {
        writeln!(err, "{e}")?;
    }
    if let Some(first) = analysis.and_then(|a| a.failed.first()) {
        writeln!(
            err,
            "warning: {} permutation(s) failed to preprocess (their levels show no distinct count). The first, {}:",
            analysis.map_or(0, |a| a.failed.len()),
            first.name
        )?;
        write!(err, "{}", preprocess::render(std::slice::from_ref(&first.error.diagnostic), cache, color))?;
    }
    Ok(())
}

fn write_summary(out: &mut dyn Write, counts: &[Count], analysis: Option<&Analysis>) -> io::Result<()> {
    let distinct = |c: &Count| -> String {
        match analysis.and_then(|a| a.find(&c.shader, &c.level)) {
            Some(l) if l.permutations.iter().all(|p| p.hash.is_some()) => l.distinct.to_string(),
            _ => "-".to_string(),
        }
    };
    let total_kept: usize = counts.iter().map(|c| c.kept).sum();
    let total_skipped: u128 = counts.iter().map(|c| c.skipped).fold(0, u128::saturating_add);
    let total_distinct = match analysis {
        Some(a) if a.failed.is_empty() => a.levels.iter().map(|l| l.distinct).sum::<usize>().to_string(),
        _ => "-".to_string(),
    };
    // Aligned up to 64 columns; a longer name runs past its column (a format width must fit
    // in a u16).
    let ws = counts.iter().map(|c| c.shader.len()).chain([6]).max().unwrap_or(6).min(64);
    let wl = counts.iter().map(|c| c.level.len()).chain([5]).max().unwrap_or(5).min(64);
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
                writeln!(
                    out,
                    "  {}@{}: {} (x{} permutations for nothing)",
                    d.shader, d.level, d.dimension, d.multiplier
                )?;
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

    fn fixture(name: &str) -> String {
        format!("{}/../tests/in/permute/{name}", env!("CARGO_MANIFEST_DIR"))
    }

    /// `kiln list ARGS...`: (exit code, stdout, stderr).
    fn list(args: &[&str]) -> (u8, String, String) {
        let cli = Cli::try_parse_from(std::iter::once("list").chain(args.iter().copied())).unwrap();
        let (mut out, mut err) = (Vec::new(), Vec::new());
        let code = match run(&cli.args, &mut out, &mut err, false) {
            Ok(()) => 0,
            Err(f) => {
                err.extend_from_slice(f.message.as_bytes());
                f.code
            }
        };
        (code, String::from_utf8(out).unwrap(), String::from_utf8(err).unwrap())
    }

    #[test]
    fn defaults() {
        let cli = Cli::try_parse_from(["list"]).unwrap();
        assert_eq!(cli.args.config, PathBuf::from("permutations.toml"));
        assert!(!cli.args.all && !cli.args.json && cli.args.shader.is_none());
        let cli =
            Cli::try_parse_from(["list", "--config", "x.toml", "--shader", "S", "--level", "sm5", "--all", "--json"])
                .unwrap();
        assert_eq!(cli.args.shader.as_deref(), Some("S"));
        assert!(cli.args.all && cli.args.json);
    }

    #[test]
    fn kept_names_then_counts() {
        let config = fixture("mobile/permutations.toml");
        let (code, out, err) = list(&["--config", &config, "--shader", "Tonemap", "--level", "es3_1", "--no-analysis"]);
        assert_eq!((code, err.as_str()), (0, ""));
        assert_eq!(
            out,
            "Tonemap@es3_1{BLEND_MODE=OPAQUE,DEBUG_VIEW=0,GRAIN=0}
Tonemap@es3_1{BLEND_MODE=OPAQUE,DEBUG_VIEW=0,GRAIN=1}
Tonemap@es3_1{BLEND_MODE=OPAQUE,DEBUG_VIEW=0,GRAIN=2}
Tonemap@es3_1{BLEND_MODE=OPAQUE,DEBUG_VIEW=1,GRAIN=0}
Tonemap@es3_1{BLEND_MODE=OPAQUE,DEBUG_VIEW=1,GRAIN=1}
Tonemap@es3_1{BLEND_MODE=OPAQUE,DEBUG_VIEW=1,GRAIN=2}
Tonemap@es3_1{BLEND_MODE=MASKED,DEBUG_VIEW=0,GRAIN=0}
Tonemap@es3_1{BLEND_MODE=MASKED,DEBUG_VIEW=0,GRAIN=1}
Tonemap@es3_1{BLEND_MODE=MASKED,DEBUG_VIEW=0,GRAIN=2}
Tonemap@es3_1{BLEND_MODE=MASKED,DEBUG_VIEW=1,GRAIN=0}
Tonemap@es3_1{BLEND_MODE=MASKED,DEBUG_VIEW=1,GRAIN=1}
Tonemap@es3_1{BLEND_MODE=MASKED,DEBUG_VIEW=1,GRAIN=2}
Tonemap@es3_1{BLEND_MODE=TRANSLUCENT,DEBUG_VIEW=0,GRAIN=0}
Tonemap@es3_1{BLEND_MODE=TRANSLUCENT,DEBUG_VIEW=1,GRAIN=0}

shader   level      kept   skipped  distinct
Tonemap  es3_1        14         4         -
total                 14         4         -
"
        );
    }

    #[test]
    fn all_adds_skipped_with_rule_and_reason() {
        let config = fixture("mobile/permutations.toml");
        let (code, out, _) = list(&["--config", &config, "--shader", "MobileBasePassPS", "--all", "--no-analysis"]);
        assert_eq!(code, 0);
        let lines: Vec<&str> = out.lines().collect();
        assert_eq!(lines.len(), 32 + 4);
        assert_eq!(
            lines[5],
            "MobileBasePassPS@es3_1{FULLY_ROUGH=0,MAX_DYNAMIC_POINT_LIGHTS=1,USE_VERTEX_FOG=0,DEFERRED_SHADING_PATH=1}  skipped by rule 1: deferred lights run in their own pass (when DEFERRED_SHADING_PATH && MAX_DYNAMIC_POINT_LIGHTS > 0)"
        );
        assert_eq!(lines.iter().filter(|l| l.contains("  skipped by rule 1: ")).count(), 12);
        assert_eq!(lines[34], "MobileBasePassPS  es3_1        20        12         -");
    }

    #[test]
    fn json_form() {
        let config = fixture("mobile/permutations.toml");
        let (code, out, _) = list(&["--config", &config, "--all", "--json", "--no-analysis"]);
        assert_eq!(code, 0);
        let v: serde_json::Value = serde_json::from_str(&out).unwrap();
        let perms = v["permutations"].as_array().unwrap();
        assert_eq!(perms.len(), 32 + 18 + 18);
        let skipped = perms.iter().find(|p| p["kept"] == false).unwrap();
        assert_eq!(skipped["skip"]["rule"], 1);
        assert_eq!(skipped["skip"]["why"], "deferred lights run in their own pass");
        let t = perms.iter().find(|p| p["shader"] == "Tonemap").unwrap();
        assert_eq!(t["values"], serde_json::json!({ "BLEND_MODE": "OPAQUE", "DEBUG_VIEW": 0, "GRAIN": 0 }));
        assert_eq!(t["level"], "sm5");
        assert_eq!(v["totals"], serde_json::json!({ "kept": 48, "skipped": 20, "distinct": null }));
        assert_eq!(
            v["counts"][1],
            serde_json::json!({ "shader": "Tonemap", "level": "sm5", "kept": 14, "skipped": 4, "distinct": null })
        );
    }

    #[test]
    fn counts_with_distinct_streams_and_dead_dimensions() {
        let config = fixture("mobile/permutations.toml");
        let (code, out, err) = list(&["--config", &config]);
        assert_eq!((code, err.as_str()), (0, ""));
        let tail: Vec<&str> = out.lines().skip(48).collect();
        assert_eq!(
            tail.join("\n"),
            "
shader            level      kept   skipped  distinct
MobileBasePassPS  es3_1        20        12        18
Tonemap           sm5          14         4         6
Tonemap           es3_1        14         4         6
total                          48        20        30

dead dimensions (they never change the preprocessed text):
  Tonemap@sm5: DEBUG_VIEW (x2 permutations for nothing)
  Tonemap@es3_1: DEBUG_VIEW (x2 permutations for nothing)"
        );
        let (_, out, _) = list(&["--config", &config, "--json", "--shader", "Tonemap"]);
        let v: serde_json::Value = serde_json::from_str(&out).unwrap();
        assert_eq!(v["totals"], serde_json::json!({ "kept": 28, "skipped": 8, "distinct": 12 }));
        assert_eq!(
            v["dead_dimensions"][1],
            serde_json::json!({ "shader": "Tonemap", "level": "es3_1", "dimension": "DEBUG_VIEW", "multiplier": 2 })
        );
        assert_eq!(v["failed"], serde_json::json!([]));
    }

    #[test]
    fn preprocessing_failures_warn_and_leave_distinct_out() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(
            dir.path().join("S.usf"),
            "#if MODE == 2\n#error mode 2 is not written yet\n#endif\nfn f() {}\n",
        )
        .unwrap();
        std::fs::write(
            dir.path().join("permutations.toml"),
            "[compiler]\ninclude = [\".\"]\n[levels.sm5]\n[[shader]]\nname = \"S\"\nsource = \"S.usf\"\nstage = \"compute\"\ndimensions = { MODE = [1, 2] }\n",
        )
        .unwrap();
        let config = dir.path().join("permutations.toml");
        let (code, out, err) = list(&["--config", config.to_str().unwrap()]);
        assert_eq!(code, 0);
        assert!(
            out.ends_with("S       sm5           2         0         -\ntotal                 2         0         -\n"),
            "{out}"
        );
        assert!(err.starts_with("warning: 1 permutation(s) failed to preprocess (their levels show no distinct count). The first, S@sm5{MODE=2}:\nerror: "), "{err}");
    }

    #[test]
    fn config_errors_and_unknown_filters_exit_2() {
        let (code, out, err) = list(&["--config", "/nonexistent/permutations.toml"]);
        assert_eq!((code, out.as_str()), (2, ""));
        assert!(err.starts_with("error: cannot read permutation set `/nonexistent/permutations.toml`: "), "{err}");
        let config = fixture("mobile/permutations.toml");
        let (code, _, err) = list(&["--config", &config, "--shader", "Nope"]);
        assert_eq!(code, 2);
        assert!(err.ends_with("(shaders: MobileBasePassPS, Tonemap)"), "{err}");
        let (code, _, err) = list(&["--config", &config, "--level", "sm6"]);
        assert_eq!(code, 2);
        assert!(err.ends_with("(levels: sm5, es3_1)"), "{err}");
    }
}
