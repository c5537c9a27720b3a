//! `kiln cache`.

use std::path::PathBuf;

use super::{print_stdout, CliResult, Failure};
use kiln::cache::{format_size, parse_size, Cache};

/// Arguments of `kiln cache`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The cache folder (default: as `kiln build` finds it from the config's folder).
    #[arg(long, value_name = "DIR", global = true)]
    pub cache_dir: Option<PathBuf>,
    /// The permutation set whose default cache to use.
    #[arg(long, default_value = "permutations.toml", global = true)]
    pub config: PathBuf,
    #[command(subcommand)]
    pub action: Action,
}

#[derive(Debug, clap::Subcommand)]
pub enum Action {
    /// Print the number of entries and their size.
    Stats,
    /// Evict least recently used entries until the cache fits in SIZE (10M, 1G, ...).
    Gc {
        /// The size to fit in: bytes, or a number with a binary unit (`500K`, `1.5G`).
        #[arg(long, value_name = "SIZE", value_parser = parse_size)]
        max_size: u64,
    },
    /// Remove every entry.
    Clear,
}

pub fn exec(args: Args) -> CliResult {
    let dir = args.cache_dir.unwrap_or_else(|| {
        let config_dir = std::path::absolute(&args.config)
            .ok()
            .and_then(|p| p.parent().map(|p| p.to_path_buf()))
            .unwrap_or_else(|| PathBuf::from("."));
        kiln::build::default_cache_dir(&config_dir)
    });
    // Read and remove only: a folder that is not there is not made.
    let shown = super::escape(&dir.display().to_string()).into_owned();
    let Some(cache) = Cache::open_existing(&dir).map_err(|e| Failure::usage(format!("error: {e}")))? else {
        return print_stdout(&format!("cache: {shown}: no cache there (nothing to do)\n"));
    };
    let text = match args.action {
        Action::Stats => {
            let s = cache.stats();
            let ratio = if s.stored > 0 { s.raw as f64 / s.stored as f64 } else { 1.0 };
            let mut t = format!(
                "cache: {}\nentries: {} in {} packs\nentries raw: {} ({} bytes)\nentries stored: {} ({} bytes, \
                 compressed {ratio:.1}x)\ndictionaries: {} ({})\npreprocessing records: {}\nsize: {} ({} bytes)\n",
                shown,
                s.entries,
                s.packs,
                format_size(s.raw),
                s.raw,
                format_size(s.stored),
                s.stored,
                s.dictionaries,
                format_size(s.dictionary_bytes),
                s.records,
                format_size(s.bytes),
                s.bytes
            );
            if s.temporaries > 0 {
                t += &format!(
                    "temporary files: {} (left by interrupted writes; `kiln cache gc` removes them)\n",
                    s.temporaries
                );
            }
            t
        }
        Action::Gc { max_size } => {
            let r = cache.gc(max_size);
            format!(
                "removed {} packs ({} entries) and {} preprocessing records ({}); kept {} entries ({})\n",
                r.removed_packs,
                r.removed,
                r.removed_records,
                format_size(r.freed),
                r.kept,
                format_size(r.kept_bytes)
            )
        }
        Action::Clear => {
            let n = cache.clear().map_err(|e| Failure::usage(format!("error: {e}")))?;
            format!("removed {n} entries from {shown}\n")
        }
    };
    print_stdout(&text)
}
