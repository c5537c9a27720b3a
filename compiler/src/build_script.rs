//! The build-script API: compile a permutation set from a crate's `build.rs`.
//!
//! ```no_run
//! // build.rs, in `fn main()`:
//! kiln::Build::new("../permutations.toml")
//!     .out_dir_from_env() // OUT_DIR/shaders.kpak
//!     .run()
//!     .unwrap_or_else(|e| e.exit_for_cargo());
//! ```
//!
//! [`Build::run`] calls the same [`crate::build::run`] as `kiln build`. It prints
//! `cargo:rerun-if-changed` for the config and every file any permutation read, turns
//! warnings into `cargo:warning=` lines, keeps its cache under cargo's target folder (found
//! from `OUT_DIR`), uses the remote cache of `KILN_REMOTE_CACHE` (or
//! [`Build::remote_cache`]) under it, and on failure renders every failure with its mapped
//! location.

use std::path::{Path, PathBuf};

use crate::build::{self, CacheDir, RemoteCache, RemoteMode, Report};
use crate::Target;

/// A build of a permutation set, configured like `cc::Build`.
#[derive(Clone, Debug)]
pub struct Build {
    config: PathBuf,
    out_dir: Option<PathBuf>,
    archive_name: String,
    levels: Vec<String>,
    targets: Vec<Target>,
    cache: Option<CacheDir>,
    remote_cache: RemoteCache,
    remote_cache_mode: Option<RemoteMode>,
    jobs: Option<usize>,
    cargo_output: bool,
    rust_bindings: Option<String>,
}

/// A failed [`Build::run`]: the rendered failures, or what else went wrong.
#[derive(Debug)]
pub struct BuildError {
    /// Rendered text, ready to print.
    pub message: String,
    /// 1 when shaders failed, 2 for configuration and I/O errors.
    pub code: u8,
    /// The build's report when it got as far as compiling.
    pub report: Option<Box<Report>>,
}

impl std::fmt::Display for BuildError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.message.trim_end())
    }
}

impl std::error::Error for BuildError {}

impl BuildError {
    /// Prints the failures on stderr (cargo shows it when a build script fails) and exits
    /// the build script with a failing status.
    pub fn exit_for_cargo(self) -> ! {
        eprintln!("{}", self.message.trim_end());
        std::process::exit(i32::from(self.code.max(1)))
    }
}

impl Build {
    /// A build of the `permutations.toml` at `config`; a relative path starts at the
    /// crate's folder (`CARGO_MANIFEST_DIR`) when cargo runs the build script.
    pub fn new(config: impl AsRef<Path>) -> Build {
        let config = config.as_ref();
        let config = match std::env::var_os("CARGO_MANIFEST_DIR") {
            Some(dir) if config.is_relative() => PathBuf::from(dir).join(config),
            _ => config.to_path_buf(),
        };
        Build {
            config,
            out_dir: None,
            archive_name: "shaders.kpak".into(),
            levels: Vec::new(),
            targets: Vec::new(),
            cache: None,
            remote_cache: RemoteCache::Auto,
            remote_cache_mode: None,
            jobs: None,
            cargo_output: true,
            rust_bindings: None,
        }
    }

    /// Writes into `OUT_DIR` (set by cargo for build scripts).
    pub fn out_dir_from_env(mut self) -> Build {
        self.out_dir = std::env::var_os("OUT_DIR").map(PathBuf::from);
        self
    }

    /// Writes into `dir`.
    pub fn out_dir(mut self, dir: impl Into<PathBuf>) -> Build {
        self.out_dir = Some(dir.into());
        self
    }

    /// The archive's file name inside the output folder (`shaders.kpak` by default).
    pub fn archive_name(mut self, name: impl Into<String>) -> Build {
        self.archive_name = name.into();
        self
    }

    /// Builds only this level (may be called several times; all levels by default).
    pub fn level(mut self, level: impl Into<String>) -> Build {
        self.levels.push(level.into());
        self
    }

    /// Writes only this target (may be called several times; each level's own by default).
    pub fn target(mut self, target: Target) -> Build {
        self.targets.push(target);
        self
    }

    /// Uses this cache folder instead of the one under cargo's target folder.
    pub fn cache_dir(mut self, dir: impl Into<PathBuf>) -> Build {
        self.cache = Some(CacheDir::Dir(dir.into()));
        self
    }

    /// Compiles everything, caching nothing.
    pub fn no_cache(mut self) -> Build {
        self.cache = Some(CacheDir::Disabled);
        self
    }

    /// Layers this shared cache (`redis://host:port[/db]` or `http(s)://host[:port]/prefix`)
    /// under the local one, instead of `KILN_REMOTE_CACHE`'s. Credentials come from
    /// `KILN_REMOTE_CACHE_TOKEN`.
    pub fn remote_cache(mut self, url: impl Into<String>) -> Build {
        self.remote_cache = RemoteCache::Url(url.into());
        self
    }

    /// Only reads the remote cache (a developer's machine, when CI fills it); by default
    /// `KILN_REMOTE_CACHE_MODE`, else read-write.
    pub fn remote_cache_mode(mut self, mode: RemoteMode) -> Build {
        self.remote_cache_mode = Some(mode);
        self
    }

    /// Worker threads (one per core by default).
    pub fn jobs(mut self, jobs: usize) -> Build {
        self.jobs = Some(jobs);
        self
    }

    /// Also writes typed permutation keys to this file in the output folder
    /// (`OUT_DIR/kiln_shaders.rs`), for `include!(concat!(env!("OUT_DIR"), "/kiln_shaders.rs"))`.
    /// The names follow fixed rules: see [`crate::keys`]. The file is rewritten only when
    /// its text changes.
    pub fn rust_bindings(mut self, file_name: impl Into<String>) -> Build {
        self.rust_bindings = Some(file_name.into());
        self
    }

    /// Whether to print `cargo:` lines (on by default; off for use outside build scripts).
    pub fn cargo_output(mut self, on: bool) -> Build {
        self.cargo_output = on;
        self
    }

    /// Runs the build; returns the archive's path. `cargo:` lines go to stdout.
    pub fn run(self) -> Result<PathBuf, BuildError> {
        let stdout = std::io::stdout();
        let mut lock = stdout.lock();
        self.run_with_output(&mut lock)
    }

    /// [`Build::run`], writing the `cargo:` lines to `out`.
    pub fn run_with_output(self, out: &mut dyn std::io::Write) -> Result<PathBuf, BuildError> {
        let out_dir = self.out_dir.clone().ok_or_else(|| BuildError {
            message: "error: kiln::Build has no output folder: call .out_dir_from_env() in a build script (OUT_DIR is not set) or .out_dir(DIR)".into(),
            code: 2,
            report: None,
        })?;
        let archive = out_dir.join(&self.archive_name);
        let cache = match &self.cache {
            Some(c) => c.clone(),
            None => CacheDir::Dir(cache_dir_for(&out_dir, &self.config)),
        };
        let options = build::Options {
            config: self.config.clone(),
            output: Some(archive.clone()),
            emit_dir: None,
            levels: self.levels.clone(),
            targets: self.targets.clone(),
            jobs: self.jobs,
            cache,
            remote_cache: self.remote_cache.clone(),
            remote_cache_mode: self.remote_cache_mode,
            stats_json: None,
            progress: false,
            color: false,
            ..build::Options::default()
        };
        if self.cargo_output {
            let _ = writeln!(out, "cargo:rerun-if-changed={}", self.config.display());
            let _ = writeln!(out, "cargo:rerun-if-env-changed=KILN_CACHE_DIR");
        }
        if let Some(name) = &self.rust_bindings {
            self.write_bindings(&out_dir.join(name))?;
        }
        let result = build::run(&options);
        let report = match &result {
            Ok(r) => Some(r),
            Err(build::Error::Failed(r)) => Some(&**r),
            Err(_) => None,
        };
        if let (true, Some(report)) = (self.cargo_output, report) {
            for f in &report.files_read {
                if f != &self.config {
                    let _ = writeln!(out, "cargo:rerun-if-changed={}", f.display());
                }
            }
            for w in &report.warnings {
                for line in w.trim_end().lines() {
                    let _ = writeln!(out, "cargo:warning={line}");
                }
            }
        }
        match result {
            Ok(_) => Ok(archive),
            Err(build::Error::Failed(report)) => {
                let mut message = String::new();
                for f in &report.failures {
                    message.push_str(f.trim_end());
                    message.push_str("\n\n");
                }
                message.push_str(&format!(
                    "error: {} of {} shader permutations failed ({})",
                    report.stats.failed,
                    report.stats.permutations,
                    self.config.display()
                ));
                Err(BuildError { message, code: 1, report: Some(report) })
            }
            Err(e) => {
                let code = e.exit_code();
                Err(BuildError { message: e.to_string(), code, report: None })
            }
        }
    }
}

impl Build {
    /// Writes the typed keys of the permutation set to `path` (atomically, and only when the
    /// text differs, so that cargo does not rebuild the including crate for nothing).
    fn write_bindings(&self, path: &Path) -> Result<(), BuildError> {
        let usage = |message: String| BuildError { message, code: 2, report: None };
        let config = crate::permute::load(&self.config).map_err(|e| usage(e.render_with(false)))?;
        let text = crate::keys::generate(&config).map_err(|e| usage(format!("error: {e}")))?;
        if crate::archive::input::read_regular(path, text.len() as u64).ok().as_deref() == Some(text.as_bytes()) {
            return Ok(());
        }
        crate::archive::write_atomic(path, text.as_bytes())
            .map_err(|e| usage(format!("error: cannot write {}: {e}", path.display())))
    }
}

/// `KILN_CACHE_DIR`, else `kiln-cache` in cargo's target folder: the ancestor of `OUT_DIR`
/// holding cargo's `CACHEDIR.TAG`, else the folder above `OUT_DIR`'s `build/`, else the
/// default of [`build::default_cache_dir`].
fn cache_dir_for(out_dir: &Path, config: &Path) -> PathBuf {
    if let Some(d) = std::env::var_os("KILN_CACHE_DIR").filter(|d| !d.is_empty()) {
        return PathBuf::from(d);
    }
    if let Some(target) = out_dir.ancestors().find(|a| a.join("CACHEDIR.TAG").is_file()) {
        return target.join("kiln-cache");
    }
    if let Some(build) = out_dir.ancestors().find(|a| a.file_name().is_some_and(|n| n == "build")) {
        if let Some(profile) = build.parent() {
            return profile.join("kiln-cache");
        }
    }
    build::default_cache_dir(config.parent().unwrap_or(Path::new(".")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cache_lives_in_cargos_target_folder() {
        let tmp = tempfile::tempdir().unwrap();
        let target = tmp.path().join("target");
        let out_dir = target.join("debug/build/kiln-runtime-0123abcd/out");
        std::fs::create_dir_all(&out_dir).unwrap();
        let config = tmp.path().join("permutations.toml");
        let expected = |fallback: PathBuf| match std::env::var_os("KILN_CACHE_DIR").filter(|d| !d.is_empty()) {
            Some(d) => PathBuf::from(d),
            None => fallback,
        };
        // Without cargo's tag: the folder above `build/`.
        assert_eq!(cache_dir_for(&out_dir, &config), expected(target.join("debug/kiln-cache")));
        // With it: the target folder itself, shared by every profile.
        std::fs::write(target.join("CACHEDIR.TAG"), "Signature: 8a477f597d28d172789f06886806bc55").unwrap();
        assert_eq!(cache_dir_for(&out_dir, &config), expected(target.join("kiln-cache")));
    }
}
