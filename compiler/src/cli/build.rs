//! `kiln build`.

use std::io::IsTerminal;
use std::path::PathBuf;

use super::{CliResult, Failure};
use kiln::build::{self, CacheDir, RemoteCache, RemoteMode, Shard};
use kiln::Target;

/// Arguments of `kiln build`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The permutation set.
    #[arg(long, default_value = "permutations.toml")]
    pub config: PathBuf,
    /// The archive to write [default: shaders.kpak; none for a shard unless given].
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    /// Also write each distinct artifact once as DIR/<hash>.<ext>, and DIR/index.json
    /// mapping every permutation and target to its file.
    #[arg(long, value_name = "DIR")]
    pub emit_dir: Option<PathBuf>,
    /// Build only this level (repeatable).
    #[arg(long = "level", value_name = "L")]
    pub levels: Vec<String>,
    /// Write only this target: wgsl, spirv, msl, glsl, hlsl (repeatable).
    #[arg(long = "target", value_name = "T", value_parser = parse_target)]
    pub targets: Vec<Target>,
    /// Worker threads (default: one per core).
    #[arg(short = 'j', long, value_name = "N")]
    pub jobs: Option<usize>,
    /// The cache folder (default: KILN_CACHE_DIR, else kiln-cache in cargo's target folder,
    /// else .kiln-cache next to the config).
    #[arg(long, value_name = "DIR")]
    pub cache_dir: Option<PathBuf>,
    /// Compile everything; neither read nor write the cache (local or remote).
    #[arg(long, conflicts_with_all = ["cache_dir", "remote_cache"])]
    pub no_cache: bool,
    /// Write the build's counts and timings as JSON.
    #[arg(long, value_name = "FILE")]
    pub stats_json: Option<PathBuf>,
    /// The most permutations, of one shader at one level or of all together (default: `[compiler]
    /// max_permutations`, else 16777216 = 2^24). Skip rules that bring the kept ones under it
    /// make a larger space acceptable.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u64).range(1..))]
    pub max_permutations: Option<u64>,
    /// Compile only shard I of N (0-based): a share of the distinct keys (balanced by cost;
    /// by key hash from 65,536 permutations), into the cache; no archive unless -o is given. A plain build afterwards assembles
    /// the archive from the cache. Also KILN_SHARD=I/N.
    #[arg(long, value_name = "I/N", conflicts_with = "shards")]
    pub shard: Option<String>,
    /// Compile shard JOB_COMPLETION_INDEX of N (a Kubernetes Indexed Job's index).
    #[arg(long, value_name = "N")]
    pub shards: Option<usize>,
    /// A shared cache under the local one: redis://host:port[/db] or
    /// http(s)://host[:port]/prefix (default: KILN_REMOTE_CACHE). Credentials come from
    /// KILN_REMOTE_CACHE_TOKEN (HTTP bearer, or basic auth as user:password; redis AUTH).
    #[arg(long, value_name = "URL")]
    pub remote_cache: Option<String>,
    /// read, or read-write to also store what this build compiles (default:
    /// KILN_REMOTE_CACHE_MODE, else read-write).
    #[arg(long, value_name = "M", value_parser = RemoteMode::parse)]
    pub remote_cache_mode: Option<RemoteMode>,
    /// A usage file recorded by a renderer (`kiln-view --record-usage`; repeatable, merged):
    /// the build says how many of its permutations the files record.
    #[arg(long, value_name = "FILE")]
    pub usage: Vec<PathBuf>,
    /// Build only the permutations the --usage files record, those `[usage] keep` matches and
    /// those of `always = true` shaders; print per shader what was left out. The archive
    /// records that it is partial: looking a left-out permutation up is an error naming it.
    #[arg(long, requires = "usage")]
    pub usage_only: bool,
    /// After the build, watch every file it read and rebuild on each change (one line per
    /// rebuild) until interrupted.
    #[arg(long)]
    pub watch: bool,
}

pub fn parse_target(s: &str) -> Result<Target, String> {
    Target::from_name(s).ok_or_else(|| {
        let names: Vec<&str> = Target::ALL.iter().map(|t| t.name()).collect();
        format!("unknown target `{s}` (expected one of: {})", names.join(", "))
    })
}

/// The shard of `--shard`, `--shards` with `JOB_COMPLETION_INDEX`, or `KILN_SHARD`.
fn shard(args: &Args) -> Result<Option<Shard>, String> {
    if let Some(s) = &args.shard {
        return Shard::parse(s).map(Some);
    }
    if let Some(n) = args.shards {
        let index = std::env::var("JOB_COMPLETION_INDEX").ok();
        return Shard::from_completion_index(n, index.as_deref()).map(Some);
    }
    match std::env::var("KILN_SHARD") {
        Ok(s) if !s.trim().is_empty() => Shard::parse(&s).map(Some).map_err(|e| format!("KILN_SHARD: {e}")),
        _ => Ok(None),
    }
}

pub fn exec(args: Args) -> CliResult {
    let color = std::io::stderr().is_terminal() && std::env::var_os("NO_COLOR").is_none();
    let shard = shard(&args).map_err(|e| Failure::usage(format!("error: {e}")))?;
    let output = match (&args.output, shard) {
        (Some(o), _) => Some(o.clone()),
        (None, None) => Some(PathBuf::from("shaders.kpak")),
        (None, Some(_)) => None,
    };
    if shard.is_some() && args.no_cache {
        return Err(Failure::usage("error: --shard needs a cache (it stores its share there): drop --no-cache"));
    }
    let options = build::Options {
        config: args.config,
        output,
        emit_dir: args.emit_dir,
        levels: args.levels,
        targets: args.targets,
        jobs: args.jobs,
        cache: match (args.no_cache, args.cache_dir) {
            (true, _) => CacheDir::Disabled,
            (false, Some(d)) => CacheDir::Dir(d),
            (false, None) => CacheDir::Auto,
        },
        remote_cache: match args.remote_cache {
            Some(url) => RemoteCache::Url(url),
            None => RemoteCache::Auto,
        },
        remote_cache_mode: args.remote_cache_mode,
        stats_json: args.stats_json,
        progress: !args.watch,
        color,
        max_permutations: args.max_permutations,
        shard,
        release_freed: Some(crate::release_freed),
        usage: args.usage,
        usage_only: args.usage_only,
    };
    if args.watch {
        return watch(options);
    }
    match build::run(&options) {
        Ok(report) => {
            for w in &report.warnings {
                eprintln!("{}", w.trim_end());
            }
            eprintln!("kiln: {}", report.summary());
            Ok(())
        }
        Err(build::Error::Failed(report)) => {
            for w in &report.warnings {
                eprintln!("{}", w.trim_end());
            }
            for f in &report.failures {
                eprintln!("{}\n", f.trim_end());
            }
            Err(Failure::shader(format!(
                "kiln: {}\nerror: {} of {} permutations failed; no archive written",
                report.summary(),
                report.stats.failed,
                report.stats.permutations
            )))
        }
        Err(e @ build::Error::Budget(_)) => Err(Failure::budget(e.to_string())),
        Err(e) => Err(Failure::usage(e.to_string())),
    }
}

/// `--watch`: builds, then rebuilds on every change to a file the last build read. Failures
/// are printed and the watch goes on (the last good archive stays in place).
fn watch(options: build::Options) -> CliResult {
    let (mut watch, first) = kiln::watch::Watch::start(options).map_err(|e| Failure::usage(format!("error: {e}")))?;
    report_rebuild(&first, watch.files().count(), true);
    loop {
        match watch.wait(std::time::Duration::from_secs(3600)) {
            Ok(Some(outcome)) => report_rebuild(&outcome, watch.files().count(), false),
            Ok(None) => {}
            Err(e) => return Err(Failure::usage(format!("error: {e}"))),
        }
    }
}

/// Prints a build's warnings and failures, then its one line.
fn report_rebuild(o: &kiln::watch::Outcome, watched: usize, first: bool) {
    let what = if first {
        "built".to_string()
    } else {
        let names: Vec<String> = o
            .changed
            .iter()
            .map(|p| p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default())
            .collect();
        format!("rebuilt after {} changed", names.join(", "))
    };
    let ms = o.build_time.as_secs_f64() * 1000.0;
    match &o.result {
        Ok(report) => {
            for w in &report.warnings {
                eprintln!("{}", w.trim_end());
            }
            eprintln!("kiln: {what} in {ms:.0} ms: {}; watching {watched} files", report.summary());
        }
        Err(build::Error::Failed(report)) => {
            for f in &report.failures {
                eprintln!("{}\n", f.trim_end());
            }
            eprintln!(
                "kiln: {what} in {ms:.0} ms: {} of {} permutations failed, archive kept; watching {watched} files",
                report.stats.failed, report.stats.permutations
            );
        }
        Err(e) => {
            eprintln!("{}", e.to_string().trim_end());
            eprintln!("kiln: {what} in {ms:.0} ms: the build did not run, archive kept; watching {watched} files");
        }
    }
}
