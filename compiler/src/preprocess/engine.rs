//! Macro expansion, directives and includes (being written).

use std::path::PathBuf;

use super::{Error, FileId, Options, Output, SourceCache};

pub(crate) fn resolve_angle(spelling: &str, opts: &Options) -> Result<PathBuf, String> {
    let _ = opts;
    Err(format!("cannot resolve `{spelling}` yet"))
}

pub(crate) fn run(file: FileId, opts: &Options, cache: &SourceCache) -> Result<Output, Error> {
    let _ = (file, opts, cache);
    Err(Error::new("the preprocessor is not finished", Vec::new()))
}
