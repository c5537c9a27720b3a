//! The build's progress bar.

use std::io::IsTerminal;

/// A progress bar on a terminal; nothing in CI or when stderr is redirected.
pub(super) struct Progress {
    bar: Option<indicatif::ProgressBar>,
}

impl Progress {
    pub fn new(wanted: bool) -> Progress {
        let show = wanted && std::io::stderr().is_terminal() && std::env::var_os("CI").is_none();
        let bar = show.then(|| {
            let bar = indicatif::ProgressBar::new(0);
            bar.set_style(
                indicatif::ProgressStyle::with_template("{prefix:>13} [{bar:30}] {pos}/{len} {elapsed}")
                    .expect("valid template")
                    .progress_chars("=> "),
            );
            bar
        });
        Progress { bar }
    }
    pub fn stage(&self, name: &'static str, len: usize) {
        if let Some(b) = &self.bar {
            b.set_length(len as u64);
            b.set_position(0);
            b.set_prefix(name);
        }
    }
    pub fn inc(&self) {
        if let Some(b) = &self.bar {
            b.inc(1);
        }
    }
    pub fn finish(&self) {
        if let Some(b) = &self.bar {
            b.finish_and_clear();
        }
    }
}
