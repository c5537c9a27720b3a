//! The server's state: open documents, the permutation sets they belong to, and the active
//! permutation of each shader with what preprocessing and validating it found.

use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use lsp_types::{DiagnosticSeverity, Range, Url};
use serde_json::Value;

use crate::permute::{self, Config, Permutation};
use crate::preprocess::{self, SourceCache};

/// Largest buffer the server checks; larger ones get one diagnostic saying so.
pub const MAX_DOC_BYTES: usize = 4 << 20;

/// An open buffer.
pub struct Doc {
    pub uri: Url,
    pub version: i32,
    pub text: Arc<str>,
}

/// The unsaved text of every open buffer, by canonical path.
pub type Overlays = Arc<Vec<(PathBuf, Arc<str>)>>;

/// A source cache whose files are the open buffers where one is open, else the disk.
pub fn cache_with(overlays: &Overlays, display_base: &Path) -> SourceCache {
    let cache = SourceCache::new(display_base.to_path_buf());
    for (path, text) in overlays.iter() {
        if text.len() <= MAX_DOC_BYTES {
            cache.set_text(path, text);
        }
    }
    cache
}

/// What the active permutation of one shader gave.
pub struct Active {
    /// Index into the configuration's levels.
    pub level: usize,
    /// One value per dimension.
    pub values: Vec<i64>,
    /// Its canonical name.
    pub name: String,
    /// The files it read (canonical), main file first.
    pub files: Vec<PathBuf>,
    /// Errors and warnings, located.
    pub diags: Vec<FileDiag>,
    /// Lines its conditionals excluded: (file, 1-based lines).
    pub skipped: Vec<(PathBuf, std::ops::Range<u32>)>,
    /// The preprocessed text, its map, and the cache its file ids belong to.
    pub output: Option<(preprocess::Output, Arc<SourceCache>)>,
}

/// One permutation set and what the server knows of it.
pub struct Workspace {
    pub config_path: PathBuf,
    /// The checked configuration, or its error in one line.
    pub config: Result<Arc<Config>, String>,
    /// Each problem of a configuration that does not load, located in the toml.
    pub config_errors: Vec<(lsp_types::Range, String)>,
    /// The active permutation's (level, values) of each shader that has been chosen.
    pub chosen: HashMap<usize, (usize, Vec<i64>)>,
    /// What each shader's active permutation gave (every shader, once the set is loaded).
    pub active: HashMap<usize, Active>,
    /// The background check's errors per shader (absent: not checked since the last edit).
    pub domain: HashMap<usize, Vec<FileDiag>>,
    /// Shaders whose domain is still to be checked.
    pub pending: HashSet<usize>,
    /// The files each shader's last domain check found some kept permutation reading.
    pub domain_files: HashMap<usize, HashSet<PathBuf>>,
    /// The shaders the last edit or choice rechecked (their domains are checked first).
    pub recent: Vec<usize>,
}

impl Workspace {
    /// Loads the set at `config_path` (the open buffer's text where the toml is open).
    pub fn load(config_path: &Path, docs: &HashMap<PathBuf, Doc>) -> Workspace {
        let (config, text) = match docs.get(config_path) {
            Some(d) => (permute::load_str(&d.text, config_path), d.text.to_string()),
            None => (permute::load(config_path), std::fs::read_to_string(config_path).unwrap_or_default()),
        };
        let mut config_errors = Vec::new();
        if let Err(e) = &config {
            for d in &e.diagnostics {
                let r = d.labels.first().map_or(0..0, |l| l.range.clone());
                config_errors.push((super::text::range_of(&text, r), d.message.clone()));
            }
        }
        let config = config.map(Arc::new).map_err(|e| e.to_string());
        Workspace {
            config_path: config_path.to_path_buf(),
            config,
            config_errors,
            chosen: HashMap::new(),
            active: HashMap::new(),
            domain: HashMap::new(),
            pending: HashSet::new(),
            domain_files: HashMap::new(),
            recent: Vec::new(),
        }
    }

    /// Whether `path` is served by this set: under an include root, or a shader's source.
    pub fn serves(&self, path: &Path) -> bool {
        let Ok(c) = &self.config else { return false };
        c.include_roots.iter().any(|r| path.starts_with(r.canonicalize().unwrap_or_else(|_| r.clone())))
            || c.shaders.iter().any(|s| s.source_path == path)
    }

    /// The shaders whose active permutation reads `path` (or whose source it is), then those
    /// of which only other permutations read it.
    pub fn readers(&self, path: &Path) -> Vec<usize> {
        let Ok(c) = &self.config else { return Vec::new() };
        let mut out: Vec<usize> = (0..c.shaders.len())
            .filter(|i| {
                c.shaders[*i].source_path == path
                    || self.active.get(i).is_some_and(|a| a.files.iter().any(|f| f == path))
            })
            .collect();
        let mut more: Vec<usize> = self
            .domain_files
            .iter()
            .filter(|(i, files)| !out.contains(i) && files.contains(path))
            .map(|(i, _)| *i)
            .collect();
        more.sort_unstable();
        out.extend(more);
        out
    }

    /// The active (level, values) of shader `i`: the chosen one, else its first kept permutation.
    pub fn active_key(&self, i: usize) -> Option<(usize, Vec<i64>)> {
        if let Some(k) = self.chosen.get(&i) {
            return Some(k.clone());
        }
        let c = self.config.as_ref().ok()?;
        let shader = c.shaders.get(i)?;
        let p = c.kept_where(|s, _| std::ptr::eq(s, shader)).next()?;
        let level = c.levels.iter().position(|l| std::ptr::eq(l, p.level))?;
        Some((level, p.values))
    }
}

/// Finds `permutations.toml` in `path`'s folder or above.
pub fn find_config(path: &Path) -> Option<PathBuf> {
    let mut dir = path.parent();
    while let Some(d) = dir {
        let candidate = d.join("permutations.toml");
        if candidate.is_file() {
            return Some(candidate.canonicalize().unwrap_or(candidate));
        }
        dir = d.parent();
    }
    None
}

/// Resolves a permutation choice for shader `i`: a canonical name (`Shader@level{...}`), or
/// partial dimension values (`{ "DIM": value }`): the first kept permutation that has them.
/// `Ok(None)`: the choice is not about this shader.
pub fn resolve_choice(config: &Config, i: usize, choice: &Value) -> Result<Option<(usize, Vec<i64>)>, String> {
    let shader = &config.shaders[i];
    let level_index = |p: &Permutation<'_>| config.levels.iter().position(|l| std::ptr::eq(l, p.level));
    match choice {
        Value::String(name) => {
            if !name.starts_with(&format!("{}@", shader.name)) {
                return Ok(None);
            }
            let p = config.find(name).map_err(|e| e.to_string())?;
            if !p.is_kept() {
                return Err(format!("`{name}` is skipped by a rule of `{}`", shader.name));
            }
            Ok(level_index(&p).map(|l| (l, p.values)))
        }
        Value::Object(map) => {
            let mut want: Vec<(usize, i64)> = Vec::new();
            for (k, v) in map {
                let Some(d) = shader.dimensions.iter().position(|d| d.name == *k) else { continue };
                let dim = &shader.dimensions[d];
                let text = match v {
                    Value::String(s) => s.clone(),
                    Value::Bool(b) => (*b as i64).to_string(),
                    other => other.to_string(),
                };
                let Some(vi) = dim.parse(&text) else {
                    return Err(format!("`{text}` is not a value of {} ({})", dim.name, dim.describe()));
                };
                want.push((d, dim.values[vi]));
            }
            if want.is_empty() {
                return Ok(None);
            }
            let found = config
                .kept_where(|s, _| std::ptr::eq(s, shader))
                .find(|p| want.iter().all(|&(d, v)| p.values[d] == v))
                .ok_or_else(|| format!("no kept permutation of `{}` has these values", shader.name))?;
            Ok(level_index(&found).map(|l| (l, found.values)))
        }
        _ => Err("a permutation is a canonical name or an object of dimension values".into()),
    }
}

/// A diagnostic located in a file.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FileDiag {
    pub path: PathBuf,
    pub range: Range,
    pub severity: DiagnosticSeverity,
    /// The error's own words (what two permutations' errors are compared by).
    pub message: String,
    /// Which permutations it comes from, as a line under the message.
    pub context: String,
}

impl FileDiag {
    /// Same error at the same place (whatever permutations it names).
    pub fn same(&self, other: &FileDiag) -> bool {
        self.path == other.path && self.range == other.range && self.message == other.message
    }
}
