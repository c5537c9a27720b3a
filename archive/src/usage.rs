//! Usage files: which pipelines a renderer asked its pipeline cache for, with the
//! permutations each runs and its whole key, how many frames asked for it and the first frame
//! that did. The runtime writes them (`PipelineCache::usage`), `kiln usage merge` merges them,
//! `kiln usage stats` reads them.
//!
//! The text format, one record a line, sorted, so that two files diff line by line:
//!
//! ```text
//! kiln-usage 1
//! archive <64 hex digits: the archive's content hash, Archive::content_hash>
//! runs <how many recordings were merged into this file>
//! compute <permutation> <frames> <first frame>
//! render <vertex permutation> <fragment permutation, or -> <state> <frames> <first frame>
//! ```
//!
//! Permutations are canonical names (`Shader@level{DIM=value,...}`, no spaces); `<state>`
//! is the render pipeline's fixed-function state written without spaces (topology, cull,
//! depth and stencil, color targets with blend and write mask, sample count, vertex layout).
//! Records are sorted by their key (kind, permutations, state) and a key appears once.
//! Lines starting with `#` and blank lines are ignored.
//!
//! Merging adds frames and runs and keeps the earliest first frame, so it is associative and
//! commutative: any order of merging the same files gives the same bytes. Files of different
//! archives do not merge (their permutations need not mean the same code).

use std::collections::BTreeMap;
use std::fmt::Write as _;

/// What is recorded of one pipeline.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize, serde::Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum UsageKey {
    /// A compute pipeline (a `compute` line).
    Compute {
        /// The compute permutation's canonical name.
        compute: String,
    },
    /// A render pipeline (a `render` line).
    Render {
        /// The vertex permutation's canonical name.
        vertex: String,
        /// The fragment permutation's canonical name (`None`: a depth-only pipeline, `-`).
        fragment: Option<String>,
        /// The fixed-function state, written without spaces.
        state: String,
    },
}

impl UsageKey {
    /// The permutations the pipeline runs, vertex first.
    pub fn permutations(&self) -> Vec<&str> {
        match self {
            UsageKey::Compute { compute } => vec![compute.as_str()],
            UsageKey::Render { vertex, fragment, .. } => {
                std::iter::once(vertex.as_str()).chain(fragment.as_deref()).collect()
            }
        }
    }
}

/// How often a pipeline was asked for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct UseCount {
    /// Frames that asked for it at least once (summed over merged runs).
    pub frames: u64,
    /// The first frame that asked for it (the earliest over merged runs).
    pub first_frame: u64,
}

impl UseCount {
    fn merge(&mut self, other: UseCount) {
        self.frames += other.frames;
        self.first_frame = self.first_frame.min(other.first_frame);
    }
}

/// A usage file: the archive it was recorded with, and its records.
#[derive(Clone, Debug, PartialEq, Eq, Default)]
pub struct Usage {
    /// The archive's content hash, 64 hex digits.
    pub archive: String,
    /// Recordings merged into this one (1 for a fresh one).
    pub runs: u64,
    /// Each pipeline asked for, and how often.
    pub records: BTreeMap<UsageKey, UseCount>,
}

/// A usage file that cannot be read or merged.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum UsageError {
    /// A line that is not of the format.
    #[error("line {line}: {message}")]
    Syntax {
        /// Its number, from 1.
        line: usize,
        /// What is wrong with it.
        message: String,
    },
    /// Two files recorded with different archives.
    #[error("usage files of different archives do not merge ({a} and {b})")]
    Archives {
        /// The first file's archive content hash.
        a: String,
        /// The second's.
        b: String,
    },
}

const HEADER: &str = "kiln-usage 1";

impl Usage {
    /// An empty usage of the archive with content hash `archive`.
    pub fn new(archive: impl Into<String>) -> Usage {
        Usage { archive: archive.into(), runs: 1, records: BTreeMap::new() }
    }

    /// Every permutation any record runs, sorted, once each.
    pub fn permutations(&self) -> std::collections::BTreeSet<&str> {
        self.records.keys().flat_map(|k| k.permutations()).collect()
    }

    /// Adds `other`'s runs and records to this one's (see the module's note on merging).
    pub fn merge(&mut self, other: &Usage) -> Result<(), UsageError> {
        if self.archive != other.archive {
            return Err(UsageError::Archives { a: self.archive.clone(), b: other.archive.clone() });
        }
        self.runs += other.runs;
        for (k, c) in &other.records {
            match self.records.get_mut(k) {
                Some(mine) => mine.merge(*c),
                None => {
                    self.records.insert(k.clone(), *c);
                }
            }
        }
        Ok(())
    }

    /// The text of the file.
    pub fn to_text(&self) -> String {
        let mut out = format!("{HEADER}\narchive {}\nruns {}\n", self.archive, self.runs);
        for (k, c) in &self.records {
            let _ = match k {
                UsageKey::Compute { compute } => writeln!(out, "compute {compute} {} {}", c.frames, c.first_frame),
                UsageKey::Render { vertex, fragment, state } => writeln!(
                    out,
                    "render {vertex} {} {state} {} {}",
                    fragment.as_deref().unwrap_or("-"),
                    c.frames,
                    c.first_frame
                ),
            };
        }
        out
    }

    /// Reads a file's text. A key written twice is merged with itself (as [`Usage::merge`]).
    pub fn parse(text: &str) -> Result<Usage, UsageError> {
        let mut lines = text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty() && !l.starts_with('#'));
        let bad = |line: usize, message: &str| UsageError::Syntax { line: line + 1, message: message.to_string() };
        match lines.next() {
            Some((_, l)) if l.trim() == HEADER => {}
            Some((n, _)) => return Err(bad(n, &format!("expected `{HEADER}`"))),
            None => return Err(bad(0, &format!("empty file: expected `{HEADER}`"))),
        }
        let mut usage = Usage { runs: 1, ..Usage::default() };
        let mut archive = None;
        for (n, line) in lines {
            let fields: Vec<&str> = line.split_whitespace().collect();
            let number = |s: &str| s.parse::<u64>().map_err(|_| bad(n, &format!("`{s}` is not a number")));
            let (key, count) = match fields.as_slice() {
                ["archive", hash] if hash.len() == 64 && hash.bytes().all(|b| b.is_ascii_hexdigit()) => {
                    archive = Some(hash.to_ascii_lowercase());
                    continue;
                }
                ["runs", runs] => {
                    usage.runs = number(runs)?;
                    continue;
                }
                ["compute", cs, frames, first] => {
                    (UsageKey::Compute { compute: cs.to_string() }, UseCount { frames: number(frames)?, first_frame: number(first)? })
                }
                ["render", vs, fs, state, frames, first] => (
                    UsageKey::Render {
                        vertex: vs.to_string(),
                        fragment: (*fs != "-").then(|| fs.to_string()),
                        state: state.to_string(),
                    },
                    UseCount { frames: number(frames)?, first_frame: number(first)? },
                ),
                _ => return Err(bad(n, "expected `archive HASH`, `runs N`, `compute PERMUTATION FRAMES FIRST` or `render VERTEX FRAGMENT STATE FRAMES FIRST`")),
            };
            match usage.records.get_mut(&key) {
                Some(c) => c.merge(count),
                None => {
                    usage.records.insert(key, count);
                }
            }
        }
        usage.archive = archive.ok_or_else(|| bad(0, "no `archive HASH` line"))?;
        Ok(usage)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn usage(records: &[(&str, u64, u64)]) -> Usage {
        let mut u = Usage::new("ab".repeat(32));
        for &(name, frames, first_frame) in records {
            u.records.insert(UsageKey::Compute { compute: name.into() }, UseCount { frames, first_frame });
        }
        u
    }

    #[test]
    fn text_round_trips_and_merging_is_order_free() {
        let mut a = usage(&[("A@sm5{}", 3, 0), ("B@sm5{X=1}", 1, 2)]);
        a.records.insert(
            UsageKey::Render { vertex: "V@sm5{}".into(), fragment: None, state: "tri;cull=Back".into() },
            UseCount { frames: 2, first_frame: 1 },
        );
        let b = usage(&[("A@sm5{}", 1, 5), ("C@sm5{}", 4, 0)]);
        let c = usage(&[("B@sm5{X=1}", 2, 1)]);
        assert_eq!(Usage::parse(&a.to_text()).unwrap(), a);
        let merged = |order: [&Usage; 3]| {
            let mut m = order[0].clone();
            m.merge(order[1]).unwrap();
            m.merge(order[2]).unwrap();
            m.to_text()
        };
        let abc = merged([&a, &b, &c]);
        for order in [[&c, &b, &a], [&b, &a, &c], [&c, &a, &b]] {
            assert_eq!(merged(order), abc);
        }
        assert!(abc.contains("compute A@sm5{} 4 0\n"), "{abc}");
        assert!(abc.contains("compute B@sm5{X=1} 3 1\n"), "{abc}");
        assert!(abc.starts_with(&format!("kiln-usage 1\narchive {}\nruns 3\n", "ab".repeat(32))), "{abc}");
    }

    #[test]
    fn different_archives_and_bad_lines_are_errors() {
        let mut a = usage(&[]);
        let mut b = usage(&[]);
        b.archive = "cd".repeat(32);
        assert!(matches!(a.merge(&b), Err(UsageError::Archives { .. })));
        let e = Usage::parse("kiln-usage 1\narchive 00\n").unwrap_err();
        assert_eq!(e.to_string(), "line 2: expected `archive HASH`, `runs N`, `compute PERMUTATION FRAMES FIRST` or `render VERTEX FRAGMENT STATE FRAMES FIRST`");
        assert!(Usage::parse("").is_err());
    }
}
