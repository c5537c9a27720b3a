//! Errors of the permute stage: a bad configuration, and a permutation name that does not exist.

use std::fmt;

use codespan_reporting::diagnostic::Diagnostic;
use codespan_reporting::files::SimpleFile;
use codespan_reporting::term;

/// `permutations.toml` could not be read or is not a valid permutation set. Every problem
/// found is kept, each with the line and column in the toml file. Exit code 2.
#[derive(Debug, Clone)]
pub struct ConfigError {
    /// How the file is named in messages.
    pub file_name: String,
    text: String,
    /// One diagnostic per problem, labels as byte ranges into the toml text.
    pub diagnostics: Vec<Diagnostic<()>>,
}

impl ConfigError {
    pub(crate) fn new(file_name: String, text: String, diagnostics: Vec<Diagnostic<()>>) -> Self {
        ConfigError { file_name, text, diagnostics }
    }

    /// Renders every diagnostic as text (rustc-like, no colour).
    pub fn render(&self) -> String {
        self.render_with(false)
    }

    /// Renders every diagnostic, with ANSI colours when `color` is set.
    pub fn render_with(&self, color: bool) -> String {
        let file = SimpleFile::new(self.file_name.as_str(), self.text.as_str());
        let config = term::Config::default();
        let mut out = String::new();
        // Names from the file are shown escaped (a control character as `\u{..}`); lines
        // stay lines.
        let text = |s: &str| s.split('\n').map(|l| crate::archive::escape(l)).collect::<Vec<_>>().join("\n");
        for d in &self.diagnostics {
            let mut d = d.clone();
            d.message = text(&d.message);
            d.notes = d.notes.iter().map(|n| text(n)).collect();
            d.labels.iter_mut().for_each(|l| l.message = text(&l.message));
            let d = &d;
            let rendered = if color {
                let mut buf = term::termcolor::Buffer::ansi();
                term::emit_to_write_style(&mut buf, &config, &file, d)
                    .map(|_| String::from_utf8_lossy(buf.as_slice()).into_owned())
            } else {
                term::emit_into_string(&config, &file, d)
            };
            match rendered {
                Ok(s) => out.push_str(&s),
                Err(_) => {
                    out.push_str(&format!("error: {}\n", d.message));
                }
            }
        }
        out
    }
}

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.diagnostics.first() {
            Some(d) if self.diagnostics.len() > 1 => {
                write!(f, "{}: {} (and {} more problems)", self.file_name, d.message, self.diagnostics.len() - 1)
            }
            Some(d) => write!(f, "{}: {}", self.file_name, d.message),
            None => write!(f, "{}: invalid configuration", self.file_name),
        }
    }
}

impl std::error::Error for ConfigError {}

/// A permutation name that names no permutation of the configuration, with the closest
/// permutations that do exist.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NotFound {
    /// The name asked for.
    pub name: String,
    /// Why it names nothing (unknown shader, level, dimension or value; bad syntax).
    pub reason: String,
    /// The closest existing permutations, best first.
    pub nearest: Vec<Near>,
}

/// One existing permutation close to a missing name.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Near {
    /// Its canonical name.
    pub name: String,
    /// What differs, as `DIM: asked -> this one` (also `shader:` and `level:`).
    pub differences: Vec<String>,
}

impl NotFound {
    /// The message the command line prints.
    pub fn render(&self) -> String {
        let mut s = format!("error: no permutation named `{}`\n  = {}\n", self.name, self.reason);
        if !self.nearest.is_empty() {
            s.push_str("closest permutations:\n");
            for n in &self.nearest {
                if n.differences.is_empty() {
                    s.push_str(&format!("  {}\n", n.name));
                } else {
                    s.push_str(&format!("  {}  ({})\n", n.name, n.differences.join(", ")));
                }
            }
        }
        s
    }
}

impl fmt::Display for NotFound {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "no permutation named `{}`: {}", self.name, self.reason)
    }
}

impl std::error::Error for NotFound {}
