//! `kiln preprocess`.

use std::path::PathBuf;

use super::{print_stdout, CliResult, Failure};
use kiln::preprocess::{self, Options, SourceCache};

/// Arguments of `kiln preprocess`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The file to preprocess.
    pub file: PathBuf,
    /// Define a macro: `NAME` (as 1) or `NAME=VALUE`.
    #[arg(short = 'D', value_name = "NAME[=VALUE]")]
    pub define: Vec<String>,
    /// Add an include root (searched in order after the including file's folder).
    #[arg(short = 'I', value_name = "DIR")]
    pub include: Vec<PathBuf>,
    /// Take include roots, virtual roots and a level's defines from a permutation set
    /// (requires `--level`). `-D` and `-I` still apply, after the configuration's.
    #[arg(long, value_name = "FILE", requires = "level")]
    pub config: Option<PathBuf>,
    /// The feature level of `--config` whose defines are predefined (`sm5`, `es3_1`, ...).
    #[arg(long, value_name = "L", requires = "config")]
    pub level: Option<String>,
    /// Show warnings and errors with ANSI colours.
    #[arg(long)]
    pub color: bool,
}

/// `-D NAME[=VALUE]` as a (name, replacement text) pair; `-D NAME` defines it as 1.
pub fn parse_define(d: &str) -> (String, String) {
    match d.split_once('=') {
        Some((n, v)) => (n.to_string(), v.to_string()),
        None => (d.to_string(), "1".to_string()),
    }
}

pub fn exec(args: Args) -> CliResult {
    match std::fs::metadata(&args.file) {
        Ok(m) if m.is_file() => {}
        Ok(m) => {
            use std::os::unix::fs::FileTypeExt;
            let t = m.file_type();
            let what = if t.is_dir() {
                "a directory"
            } else if t.is_fifo() {
                "a FIFO"
            } else if t.is_char_device() || t.is_block_device() {
                "a device"
            } else {
                "a socket"
            };
            let name = args.file.display();
            return Err(Failure::usage(format!("error: cannot read `{name}`: it is {what}, not a regular file")));
        }
        Err(e) => return Err(Failure::usage(format!("error: cannot read `{}`: {e}", args.file.display()))),
    }
    for dir in &args.include {
        if !dir.is_dir() {
            return Err(Failure::usage(format!("error: include folder `{}` does not exist", dir.display())));
        }
    }
    // DESIGN.md: for `kiln preprocess` the roots are the input file's folder and each `-I`
    // folder; with `--config`, the configuration's roots and virtual roots come first.
    let mut opts = Options::default();
    let mut display_base = std::env::current_dir().unwrap_or_else(|_| PathBuf::from("."));
    if let (Some(config_path), Some(level_name)) = (&args.config, &args.level) {
        let config = super::list::load_config(config_path, args.color, &mut std::io::stderr())?;
        let level = config.level(level_name).ok_or_else(|| {
            let names: Vec<&str> = config.levels.iter().map(|l| l.name.as_str()).collect();
            Failure::usage(format!(
                "error: `{}` has no level `{level_name}` (its levels: {})",
                config_path.display(),
                names.join(", ")
            ))
        })?;
        opts = config.preprocess_options();
        opts.defines.extend(level.defines.iter().map(|(n, v)| (n.clone(), v.to_string())));
        display_base = config.dir.clone();
    }
    opts.include_roots.extend(args.include.iter().cloned());
    let file_dir = match args.file.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    opts.include_roots.push(file_dir);
    opts.defines.extend(args.define.iter().map(|d| parse_define(d)));
    let cache = SourceCache::new(display_base);
    match preprocess::preprocess_file(&args.file, &opts, &cache) {
        Ok(out) => {
            if !out.warnings.is_empty() {
                eprint!("{}", preprocess::render(&out.warnings, &cache, args.color));
            }
            print_stdout(&out.text)
        }
        Err(e) => Err(Failure::shader(preprocess::render(std::slice::from_ref(&e.diagnostic), &cache, args.color))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defines() {
        assert_eq!(parse_define("A"), ("A".into(), "1".into()));
        assert_eq!(parse_define("A=2"), ("A".into(), "2".into()));
        assert_eq!(parse_define("A="), ("A".into(), "".into()));
        assert_eq!(parse_define("F(x)=x+1"), ("F(x)".into(), "x+1".into()));
    }

    fn args(file: PathBuf) -> Args {
        Args { file, define: vec!["N=4".into()], include: Vec::new(), config: None, level: None, color: false }
    }

    #[test]
    fn exit_codes() {
        let dir = tempfile::tempdir().expect("temp dir");
        let ok = dir.path().join("ok.usf");
        std::fs::write(
            &ok,
            "#if N == 4
fn f() {}
#endif
",
        )
        .expect("write");
        assert!(exec(args(ok)).is_ok());

        let bad = dir.path().join("bad.usf");
        std::fs::write(
            &bad,
            "#if N == 4
#error four
#endif
",
        )
        .expect("write");
        let f = exec(args(bad)).expect_err("#error fails");
        assert_eq!(f.code, 1);
        assert!(f.message.starts_with("error: #error four\n"), "{}", f.message);
        assert!(f.message.contains("bad.usf:2:1"), "{}", f.message);

        let f = exec(args(dir.path().join("missing.usf"))).expect_err("no file");
        assert_eq!(f.code, 2);
        let mut a = args(dir.path().join("bad.usf"));
        a.include.push(dir.path().join("no-such-dir"));
        assert_eq!(exec(a).expect_err("bad -I").code, 2);
    }

    #[test]
    fn args_definition_is_consistent() {
        use clap::CommandFactory;
        #[derive(clap::Parser)]
        struct Wrapper {
            #[command(flatten)]
            args: Args,
        }
        Wrapper::command().debug_assert();
    }
}
