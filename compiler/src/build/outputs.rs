//! Outputs: what the build writes, checked before any work (a directory or a socket is
//! refused; an output naming the configuration, a shader's source or any file the build
//! reads is refused, naming both paths). Writing itself goes through [`crate::output`].

use std::path::{Path, PathBuf};

use super::{Error, Options};
use crate::permute::Config;

/// The files this build writes: (what, path).
pub(super) fn output_files(options: &Options) -> Vec<(&'static str, PathBuf)> {
    let mut out = Vec::new();
    if let Some(o) = &options.output {
        out.push(("the archive (-o)", o.clone()));
    }
    if let Some(s) = &options.stats_json {
        out.push(("--stats-json", s.clone()));
    }
    if let Some(d) = &options.emit_dir {
        out.push(("the --emit-dir index", d.join("index.json")));
    }
    out
}

/// Refuses, before any work, outputs that cannot be written (a directory, a socket) and
/// outputs that name the configuration or a shader's source: the build would overwrite its
/// own input.
pub(super) fn check_outputs(options: &Options, config: &Config) -> Result<(), Error> {
    if let Some(d) = &options.emit_dir {
        if d.exists() && !d.is_dir() {
            return Err(Error::Io(format!("error: --emit-dir {} is not a folder", d.display())));
        }
    }
    let outputs = output_files(options);
    for (_, path) in &outputs {
        crate::output::check_target(path)
            .map_err(|e| Error::Io(format!("error: cannot write {}: {e}", path.display())))?;
    }
    let mut inputs = vec![("the configuration", config.path.clone())];
    inputs.extend(config.shaders.iter().map(|s| ("a shader source", s.source_path.clone())));
    check_aliases(&outputs, inputs.iter().map(|(w, p)| (*w, p.as_path())))?;
    for (i, (what, a)) in outputs.iter().enumerate() {
        // Two outputs on one device are fine (`-o /dev/null --stats-json /dev/null`); on one
        // file, existing or not, the second would replace the first.
        let device = std::fs::metadata(a).is_ok_and(|m| !m.is_file());
        let same = |b: &Path| crate::output::same_file(a, b) || lexical(a) == lexical(b);
        if let Some((other, b)) = outputs[i + 1..].iter().find(|(_, b)| !device && same(b)) {
            return Err(Error::Config(format!(
                "error: {what} {} and {other} {} are the same file",
                a.display(),
                b.display()
            )));
        }
    }
    Ok(())
}

/// An error naming both paths when an output is one of `inputs` (the same file, through
/// links and relative paths).
pub(super) fn check_aliases<'a>(
    outputs: &[(&'static str, PathBuf)],
    inputs: impl IntoIterator<Item = (&'a str, &'a Path)>,
) -> Result<(), Error> {
    for (input_kind, input) in inputs {
        for (what, out) in outputs {
            if crate::output::same_file(out, input) {
                return Err(Error::Config(format!(
                    "error: {what} {} is {input_kind} {}: writing it would destroy the input",
                    out.display(),
                    input.display()
                )));
            }
        }
    }
    Ok(())
}

/// `path` made absolute with `.` and `..` resolved by name (links are not followed).
fn lexical(path: &Path) -> PathBuf {
    let abs = std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf());
    let mut out = PathBuf::new();
    for c in abs.components() {
        match c {
            std::path::Component::ParentDir => {
                out.pop();
            }
            std::path::Component::CurDir => {}
            c => out.push(c),
        }
    }
    out
}
