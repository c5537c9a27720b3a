//! Access to a Kiln archive: open it (memory-mapped file, embedded bytes or a vector),
//! find permutations by canonical name or with a builder, in one hash-map lookup.

use std::fmt;
use std::path::Path;

use kiln_archive::{Archive, ArchiveError, Lookup, Near, PermutationRef, Permutations};

/// Why a permutation could not be found.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum LookupError {
    /// The name is well formed but the archive does not hold it; `nearest` lists the closest
    /// permutations with the dimensions that differ.
    #[error("{}", render_missing(.name, .nearest))]
    Missing {
        /// The name looked up.
        name: String,
        /// The closest permutations, best first.
        nearest: Vec<Near>,
    },
    /// A partial archive (`kiln build --usage-only`) left the permutation out: no usage file
    /// recorded it. Never answered with another permutation.
    #[error(
        "permutation `{name}` was left out of this archive by `kiln build --usage-only`: the usage file did not \
         record it (record a run that uses it, or keep it with `[usage] keep` or its shader's `always = true`)"
    )]
    LeftOut {
        /// The name looked up.
        name: String,
    },
    /// The builder named a shader, level or dimension the archive does not know.
    #[error("cannot name permutation: {0}")]
    BadName(String),
    /// A record or manifest chunk the lookup read is damaged (the archive's error, which
    /// names the permutation).
    #[error("{0}")]
    Damaged(String),
}

fn render_missing(name: &str, nearest: &[Near]) -> String {
    let mut s = format!("permutation `{name}` is not in the archive");
    if nearest.is_empty() {
        s.push_str(" (the archive holds no permutations)");
        return s;
    }
    s.push_str("; nearest:");
    for n in nearest {
        s.push_str(&format!("\n  {}", n.name));
        if !n.differences.is_empty() {
            s.push_str(&format!("  (differs in {})", n.differences.join(", ")));
        }
    }
    s
}

/// A loaded archive of shader permutations.
///
/// Archives are untrusted unless the application says it embedded them at build time
/// ([`ShaderArchive::from_static_trusted`]): the runtime hands
/// SPIR-V to the driver unchanged (passthrough) only from a trusted archive, after a
/// structural check; from any other it creates modules from WGSL, which wgpu's naga parses and
/// validates (a driver may do anything with invalid SPIR-V).
pub struct ShaderArchive {
    archive: Archive,
    trusted: bool,
}

impl fmt::Debug for ShaderArchive {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("ShaderArchive")
            .field("bytes", &self.archive.len())
            .field("permutations", &self.archive.permutation_count())
            .field("trusted", &self.trusted)
            .finish()
    }
}

impl ShaderArchive {
    /// Memory-maps and verifies an archive file (header, version, checksum of the chunk
    /// hashes; the manifest is checked a chunk at a time as lookups read it).
    pub fn open(path: &Path) -> Result<ShaderArchive, ArchiveError> {
        Ok(ShaderArchive { archive: Archive::open(path)?, trusted: false })
    }

    /// An archive embedded with `include_bytes!` (untrusted: see [`ShaderArchive::trusted`]).
    pub fn from_static(bytes: &'static [u8]) -> Result<ShaderArchive, ArchiveError> {
        Ok(ShaderArchive { archive: Archive::from_static(bytes)?, trusted: false })
    }

    /// Opens an archive held in memory (not trusted for SPIR-V passthrough).
    pub fn from_vec(bytes: Vec<u8>) -> Result<ShaderArchive, ArchiveError> {
        Ok(ShaderArchive { archive: Archive::from_vec(bytes)?, trusted: false })
    }

    /// An archive the application's own `build.rs` compiled with `kiln::Build` and embedded
    /// with `include_bytes!`: trusted, so its SPIR-V is passed through to the driver.
    ///
    /// # Safety
    /// As [`ShaderArchive::assume_trusted`]: the bytes must be Kiln's own, unaltered output,
    /// built into this binary (the archive a renderer embeds from its build script).
    pub unsafe fn from_static_trusted(bytes: &'static [u8]) -> Result<ShaderArchive, ArchiveError> {
        Ok(ShaderArchive { archive: Archive::from_static(bytes)?, trusted: true })
    }

    /// Whether SPIR-V from this archive may go to the driver unchanged (SPIR-V passthrough,
    /// after the structural check of the runtime's `spirv` module). Only archives made with
    /// [`ShaderArchive::from_static_trusted`] or [`ShaderArchive::assume_trusted`] are.
    pub fn trusted(&self) -> bool {
        self.trusted
    }

    /// Marks the archive as written by Kiln's own build and not altered since, so that its
    /// SPIR-V is passed through to the driver.
    ///
    /// # Safety
    /// The structural check (the runtime's `spirv` module) is no validator: SPIR-V that passes it but
    /// is invalid (a bit flipped in an operand) is undefined behaviour in the driver. Call it
    /// only for archives from a source you trust as much as the binary itself.
    pub unsafe fn assume_trusted(mut self) -> ShaderArchive {
        self.trusted = true;
        self
    }

    /// The archive itself.
    pub fn archive(&self) -> &Archive {
        &self.archive
    }

    /// The archive's pipeline manifest (`kiln build --usage`), in first-use order; `None`
    /// for an archive built without usage files. `pipelines::manifest_keys` turns
    /// it into pipeline keys.
    pub fn pipeline_manifest(&self) -> Option<&[kiln_archive::PipelineRecord]> {
        self.archive.pipeline_manifest()
    }

    /// O(1) lookup by canonical name (`Shader@level{DIM=value,...}`).
    pub fn get(&self, name: &str) -> Result<PermutationRef<'_>, LookupError> {
        match self.archive.lookup(name) {
            Ok(Lookup::Found(p)) => Ok(p),
            Ok(Lookup::Missing(_)) if self.archive.left_out(name) => {
                Err(LookupError::LeftOut { name: name.to_string() })
            }
            Ok(Lookup::Missing(nearest)) => Err(LookupError::Missing { name: name.to_string(), nearest }),
            Err(e) => Err(LookupError::Damaged(e.to_string())),
        }
    }

    /// O(1) lookup by the id a typed key computes (`key.permutation_id(level)` in the
    /// `kiln_shaders.rs` that `kiln::Build::rust_bindings` generates): no name is formatted.
    /// `Ok(None)` when no permutation has that id; a damaged record or chunk on the way is
    /// an error.
    pub fn get_by_id(&self, id: u128) -> Result<Option<PermutationRef<'_>>, ArchiveError> {
        self.archive.get_by_id(id)
    }

    /// Starts a lookup by shader name and dimension values:
    /// `archive.shader("MobileBasePassPS").level("es3_1").with("FULLY_ROUGH", 1).find()`.
    pub fn shader<'a>(&'a self, name: &str) -> PermutationQuery<'a> {
        PermutationQuery { archive: self, shader: name.to_string(), level: None, values: Vec::new() }
    }

    /// Every permutation, sorted by name; the first walk checks every record first (see
    /// [`Archive::permutations`]).
    pub fn permutations(&self) -> Result<Permutations<'_>, ArchiveError> {
        self.archive.permutations()
    }
}

/// A permutation named by shader, level and dimension values. Every dimension must be
/// given (a default would pick a permutation silently); values are numbers or enum labels.
#[derive(Clone, Debug)]
pub struct PermutationQuery<'a> {
    archive: &'a ShaderArchive,
    shader: String,
    level: Option<String>,
    values: Vec<(String, String)>,
}

impl<'a> PermutationQuery<'a> {
    /// The feature level (`sm5`, `es3_1`). May be left out when the shader has one level.
    pub fn level(mut self, level: &str) -> Self {
        self.level = Some(level.to_string());
        self
    }

    /// A dimension's value: an integer (`1`, `4`) or, for an enum, its label or index.
    pub fn with(mut self, dimension: &str, value: impl fmt::Display) -> Self {
        self.values.push((dimension.to_string(), value.to_string()));
        self
    }

    /// The canonical name this query denotes.
    pub fn name(&self) -> Result<String, LookupError> {
        let level = match &self.level {
            Some(l) => l.clone(),
            None => {
                let levels: Vec<&str> = self
                    .archive
                    .archive
                    .shaders()
                    .iter()
                    .filter(|s| s.name == self.shader)
                    .map(|s| s.level.as_str())
                    .collect();
                match levels.as_slice() {
                    [one] => one.to_string(),
                    [] => {
                        return Err(LookupError::BadName(format!("no shader named `{}` in the archive", self.shader)))
                    }
                    many => {
                        return Err(LookupError::BadName(format!(
                            "shader `{}` has several levels ({}); say which with .level()",
                            self.shader,
                            many.join(", ")
                        )))
                    }
                }
            }
        };
        let values: Vec<(&str, &str)> = self.values.iter().map(|(d, v)| (d.as_str(), v.as_str())).collect();
        self.archive.archive.canonical_name(&self.shader, &level, &values).map_err(LookupError::BadName)
    }

    /// Finds the permutation; a missing one is an error naming the nearest.
    pub fn find(&self) -> Result<PermutationRef<'a>, LookupError> {
        let name = self.name()?;
        self.archive.get(&name)
    }
}
