//! `kiln explain`.

use std::io::IsTerminal;
use std::path::PathBuf;

use super::list::load_config;
use super::{print_stdout, CliResult, Failure};
use kiln::preprocess::SourceCache;

/// Arguments of `kiln explain`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// A canonical name, `Shader@level{DIM=value,...}` (enum values by name or index, dimensions in any order).
    #[arg(value_name = "PERMUTATION_NAME")]
    pub name: String,
    /// The permutation set.
    #[arg(long, value_name = "FILE", default_value = "permutations.toml")]
    pub config: PathBuf,
}

pub fn exec(args: Args) -> CliResult {
    let (text, failure) = run(&args, std::io::stderr().is_terminal())?;
    print_stdout(&text)?;
    match failure {
        Some(f) if f.code == 0 => {
            eprint!("{}", f.message);
            Ok(())
        }
        Some(f) => Err(f),
        None => Ok(()),
    }
}

/// The text `kiln explain` prints, and how it fails after printing it. A name that does not
/// exist is exit code 2 (with the nearest names); a permutation that fails to preprocess is
/// explained, then fails with exit code 1 and the rendered error (code 0 when the permutation
/// is skipped: the error is only shown).
pub(super) fn run(args: &Args, color: bool) -> Result<(String, Option<Failure>), Failure> {
    let config = load_config(&args.config, color, &mut std::io::stderr())?;
    let cache = SourceCache::new(config.dir.clone());
    let report = kiln::explain::explain(&config, &cache, &args.name).map_err(|e| Failure::usage(e.render()))?;
    let failure = report.error.map(|d| {
        let rendered = kiln::preprocess::render(std::slice::from_ref(&d), &cache, color);
        if report.kept {
            Failure::shader(rendered)
        } else {
            // A skipped permutation is never built: its failure is worth showing, not failing for.
            Failure { code: 0, message: rendered }
        }
    });
    Ok((report.text, failure))
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

    fn explain(args: &[&str]) -> Result<(String, Option<Failure>), Failure> {
        let cli = Cli::try_parse_from(std::iter::once("explain").chain(args.iter().copied())).unwrap();
        run(&cli.args, false)
    }

    #[test]
    fn unknown_name_is_exit_2_with_the_closest() {
        let config = format!("{}/../tests/in/permute/mobile/permutations.toml", env!("CARGO_MANIFEST_DIR"));
        let f = explain(&["Tonemap@sm5{BLEND_MODE=MASKED,DEBUG_VIEW=0}", "--config", &config]).unwrap_err();
        assert_eq!(f.code, 2);
        assert_eq!(
            f.message,
            "error: no permutation named `Tonemap@sm5{BLEND_MODE=MASKED,DEBUG_VIEW=0}`
  = no value for dimension `GRAIN`
closest permutations:
  Tonemap@sm5{BLEND_MODE=MASKED,DEBUG_VIEW=0,GRAIN=0}  (GRAIN: (missing) -> 0)
  Tonemap@sm5{BLEND_MODE=MASKED,DEBUG_VIEW=0,GRAIN=1}  (GRAIN: (missing) -> 1)
  Tonemap@sm5{BLEND_MODE=MASKED,DEBUG_VIEW=0,GRAIN=2}  (GRAIN: (missing) -> 2)
  Tonemap@sm5{BLEND_MODE=OPAQUE,DEBUG_VIEW=0,GRAIN=0}  (BLEND_MODE: MASKED -> OPAQUE, GRAIN: (missing) -> 0)
  Tonemap@sm5{BLEND_MODE=OPAQUE,DEBUG_VIEW=0,GRAIN=1}  (BLEND_MODE: MASKED -> OPAQUE, GRAIN: (missing) -> 1)
"
        );
    }

    #[test]
    fn bad_config_is_exit_2() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("permutations.toml");
        std::fs::write(&path, "[levels.sm5]\ndefines = { X = [1] }\n").unwrap();
        let f = explain(&["S@sm5", "--config", path.to_str().unwrap()]).unwrap_err();
        assert_eq!(f.code, 2);
        assert!(
            f.message.starts_with("error: invalid type: sequence, expected an integer or a boolean\n"),
            "{}",
            f.message
        );
        assert!(f.message.contains("permutations.toml:2:17"), "{}", f.message);
    }

    #[test]
    fn preprocessing_failure_is_exit_1_when_kept_and_shown_when_skipped() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(
            dir.path().join("S.usf"),
            "#if MODE == 2\n#error mode 2 is not written yet\n#endif\nfn f() {}\n",
        )
        .unwrap();
        std::fs::write(
            dir.path().join("permutations.toml"),
            "[compiler]\ninclude = [\".\"]\n[levels.sm5]\n[[shader]]\nname = \"S\"\nsource = \"S.usf\"\nstage = \"compute\"\ndimensions = { MODE = [1, 2], OFF = \"bool\" }\nskip = [{ when = \"OFF\", why = \"off\" }]\n",
        )
        .unwrap();
        let config = dir.path().join("permutations.toml");
        let (text, failure) = explain(&["S@sm5{MODE=2,OFF=0}", "--config", config.to_str().unwrap()]).unwrap();
        assert!(
            text.contains(
                "\nfiles read:\n  (none: preprocessing failed)\n\ntoken hash: (none: preprocessing failed)\n"
            ),
            "{text}"
        );
        let f = failure.unwrap();
        assert_eq!(f.code, 1);
        assert!(f.message.starts_with("error: #error mode 2 is not written yet\n  ┌─ S.usf:2:1\n"), "{}", f.message);
        let (_, failure) = explain(&["S@sm5{MODE=2,OFF=1}", "--config", config.to_str().unwrap()]).unwrap();
        assert_eq!(failure.unwrap().code, 0);
        let (text, failure) = explain(&["S@sm5{MODE=1,OFF=0}", "--config", config.to_str().unwrap()]).unwrap();
        assert!(failure.is_none());
        assert!(text.contains("\nfiles read:\n  S.usf\n"), "{text}");
    }
}
