//! The byte layout of an archive (format version 4), shared by the writer and the reader.
//!
//! The layout, field by field (the header, the sections in file order, the chunk hashes,
//! the manifest's parts and the blob table), is specified in
//! `docs/reference/archive-format.md`; the lengths of its fixed parts are the constants
//! below ([`HEADER_LEN`], [`CHUNK_LEN`] and the manifest's record lengths).
//!
//! Opening checks the header checksum, which covers the chunk hashes, and reads the chunks
//! of the manifest's header, dictionaries and tables; every other chunk is checked against
//! its hash the first time a read touches it (one bit per chunk), so that opening costs O(1)
//! in the number of permutations.
//!
//! The manifest (format 3 and 4; format 2 held JSON, parsed whole at open) is read in place
//! from the memory map; every part starts at a multiple of 8 from the manifest's start.
//!
//! Opening parses the tables; each permutation record is checked the first time it is used
//! (a lookup that finds it, or a walk of every record, which checks each as it goes): its
//! name, values and artifacts in range, its shader and reflection in the tables, its name
//! UTF-8, and the chunks it lies in against their hashes. A bad record is an error naming the
//! permutation, never a panic. A lookup by name is a binary search of the records (each
//! step checks the chunks it reads), by id one of the ids. Nothing per permutation is
//! copied, allocated or written at open: the bits of checked chunks, records and blobs and
//! the cells of decoded values are allocated a page (4,096 bits, 1,024 cells) at a time on
//! first use, so opening writes one empty cell per page.
//!
//! A blob table entry is `stored offset (u64, from the start of the blob section), stored
//! length (u64), raw length (u64), codec (u8: 0 stored as is, 1 zstd, 2 zstd with a
//! dictionary), dictionary index (u8), 6 zero bytes, blake3 of the raw bytes (32)`.
//!
//! Each blob table entry is checked (its chunk's hash, then its ranges, codec and
//! dictionary) the first time its blob is used; each blob's blake3 the first time it is
//! decompressed, each dictionary's the first time it is loaded.
//!
//! # Choices
//!
//! Each artifact is its own zstd frame, compressed at [`COMPRESSION_LEVEL`] with its
//! target's dictionary (WGSL, SPIR-V, MSL, GLSL and HLSL share little with each other),
//! trained at build time on a deterministic sample of at most [`DICTIONARY_SAMPLE`] bytes of
//! that target's artifacts: a lookup decompresses exactly the bytes it needs and checks one
//! checksum, and a corrupted blob damages one permutation, not its neighbours (compressed
//! groups of artifacts would make the file smaller and every lookup a group's work). The
//! manifest is read in place and hashed per [`CHUNK_LEN`] chunk on first use, so that
//! opening is O(shaders + distinct reflections), not O(permutations). The measurements
//! behind these choices are in `docs/design/2026-11-archive-format-measurements.md`.

use std::cmp::Ordering;
use std::fs::File;
use std::io::{IoSlice, Write};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::{Reflection, Stage, Target};

/// The first 8 bytes of every archive.
pub const MAGIC: [u8; 8] = *b"KILNPAK\0";
/// The archive format this build writes.
pub const FORMAT_VERSION: u32 = 5;
/// The oldest format this build reads: version 4 differs only in its blob table entries,
/// whose six reserved bytes are zero where version 5 keeps a check sum of the stored bytes.
pub const OLDEST_FORMAT_VERSION: u32 = 4;
/// Bytes of the fixed header at the start of an archive.
pub const HEADER_LEN: usize = 128;
/// Bytes of one chunk of the manifest and of the blob table that one hash covers (chosen by
/// measuring: see the module doc's choices). The reader takes the length from the header.
pub const CHUNK_LEN: u32 = 16 << 10;
/// Bytes of one chunk hash.
pub(crate) const CHUNK_HASH_LEN: usize = 32;
/// Bytes of one blob table entry.
pub(crate) const ENTRY_LEN: usize = 64;
/// zstd level of artifacts (with their target's dictionary).
pub const COMPRESSION_LEVEL: i32 = 3;
/// Largest dictionary trained per target.
pub const DICTIONARY_SIZE: usize = 128 << 10;
/// At most this many bytes of a target's artifacts train its dictionary (a deterministic,
/// evenly spaced sample), so training time stays bounded however large the set.
pub const DICTIONARY_SAMPLE: usize = 2 << 20;
/// The largest artifact an archive may announce: a hostile raw length cannot make the reader
/// allocate more.
pub const MAX_ARTIFACT_LEN: u64 = 256 << 20;

pub(crate) const CODEC_STORED: u8 = 0;
pub(crate) const CODEC_ZSTD: u8 = 1;
pub(crate) const CODEC_ZSTD_DICT: u8 = 2;
pub(crate) const NO_DICTIONARY: u8 = 0xff;

/// Why an archive could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum ArchiveError {
    /// The file could not be opened, mapped or read.
    #[error("cannot read archive {path}: {source}")]
    Io {
        /// The archive's path.
        path: PathBuf,
        /// What the system said.
        source: std::io::Error,
    },
    /// The path names a directory, a device or a pipe, not a regular file.
    #[error("cannot read archive {path}: it is a {kind}, not a regular file")]
    NotAFile {
        /// The archive's path.
        path: PathBuf,
        /// What it is instead (`directory`, `fifo`, ...).
        kind: &'static str,
    },
    /// The archive could not be written.
    #[error("cannot write archive {path}: {source}")]
    Write {
        /// The archive's path.
        path: PathBuf,
        /// What the system said.
        source: std::io::Error,
    },
    /// Fewer bytes than the header.
    #[error("not a kiln archive: the file is {len} bytes, shorter than the {HEADER_LEN}-byte header")]
    TooShort {
        /// The file's length.
        len: usize,
    },
    /// The file does not start with [`MAGIC`].
    #[error("not a kiln archive: bad magic bytes {found:02x?}")]
    BadMagic {
        /// Its first 8 bytes.
        found: [u8; 8],
    },
    /// A format version other than [`FORMAT_VERSION`].
    #[error("archive format version {found} is not supported (this build of kiln reads versions {OLDEST_FORMAT_VERSION} to {FORMAT_VERSION}); rebuild the archive with this kiln")]
    Version {
        /// The version the header gives.
        found: u32,
    },
    /// The file is shorter than its header says.
    #[error("archive is truncated: the header announces {expected} bytes, the file has {actual}")]
    Truncated {
        /// The length the header announces.
        expected: u64,
        /// The file's length.
        actual: u64,
    },
    /// Longer than its header says: bytes appended, or two files run together.
    #[error("archive has {} bytes after its end: the header announces {expected} bytes, the file has {actual}", actual - expected)]
    TrailingBytes {
        /// The length the header announces.
        expected: u64,
        /// The file's length.
        actual: u64,
    },
    /// The header's own checksum does not match.
    #[error("archive is corrupted: header checksum mismatch (expected {expected}, computed {actual})")]
    Checksum {
        /// The checksum the header holds (hex).
        expected: String,
        /// The checksum of the bytes read (hex).
        actual: String,
    },
    /// The manifest does not decode: what is wrong with it.
    #[error("archive manifest is malformed: {0}")]
    Manifest(String),
    /// A chunk of the manifest or blob table that no permutation's use reads (an id, say)
    /// failed its hash in [`crate::Archive::verify_all`].
    #[error("archive is corrupted: {0}")]
    Corrupted(String),
    /// A blob failed its check or its decompression the first time it was used.
    #[error("archive is corrupted: the {target} artifact of permutation `{permutation}`: {message}")]
    Blob {
        /// The permutation's name.
        permutation: String,
        /// The artifact's target.
        target: Target,
        /// What failed.
        message: String,
    },
    /// A permutation record failed its check (its chunk's hash, or a range) the first time
    /// it was read. `permutation` is its name, or the name being looked up, or its number
    /// when its name cannot be trusted.
    #[error("archive is corrupted: permutation {permutation}: {message}")]
    Permutation {
        /// The permutation's name, the name looked up, or its number.
        permutation: String,
        /// What failed.
        message: String,
    },
    /// The writer was given inconsistent input.
    #[error("cannot write archive: {0}")]
    Input(String),
}

/// Index of a blob in the archive.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct BlobId(pub u32);

/// A shader of the manifest: one (shader, level) pair with its dimensions, so lookups by
/// dimension values can build the canonical name.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct ShaderRecord {
    /// The shader's name in `permutations.toml`.
    pub name: String,
    /// The feature level.
    pub level: String,
    /// The entry point's name.
    pub entry: String,
    /// The entry point's stage.
    pub stage: Stage,
    /// Dimensions in declared order.
    pub dimensions: Vec<DimensionRecord>,
}

/// A dimension of a shader in the manifest.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct DimensionRecord {
    /// The dimension's name (its define).
    pub name: String,
    /// For an enum dimension, the name of each index; empty otherwise.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub labels: Vec<String>,
}

/// A permutation of the manifest, as the writer is given it and the reader decodes it.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PermutationRecord {
    /// Canonical name, `Shader@level{DIM=value,...}`.
    pub name: String,
    /// Index into the manifest's shaders.
    pub shader: u32,
    /// One value per dimension of the shader, in declared order.
    pub values: Vec<i64>,
    /// Index into the manifest's reflections.
    pub reflection: u32,
    /// One blob per target, in the level's order of targets.
    pub artifacts: Vec<(Target, BlobId)>,
}

/// A dictionary of the dictionary section.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct DictionaryRecord {
    pub target: Target,
    /// From the start of the dictionary section.
    pub offset: u64,
    pub len: u64,
    /// blake3 of the dictionary.
    pub blake3: [u8; 32],
}

/// The manifest as the writer holds it before encoding it: its permutations in archive
/// order, pointing into arenas of names, values and artifacts (no allocation per
/// permutation). The dictionary records are added as the manifest is written, once the
/// dictionaries are trained.
#[derive(Clone, Debug, Default)]
pub(crate) struct Manifest {
    pub kiln_version: String,
    pub naga_version: String,
    pub partial: Option<Partial>,
    pub pipelines: Option<Vec<PipelineRecord>>,
    pub shaders: Vec<ShaderRecord>,
    pub reflections: Vec<Reflection>,
    /// Sorted by name.
    pub permutations: Vec<ManifestPermutation>,
    pub arenas: Arenas,
}

/// Where the permutations of a manifest (or of a writer, before they are sorted) keep their
/// names, values and artifacts: names less their shared prefix, narrow values and artifacts
/// in two parallel lists, which hold less than whole names, 8-byte values and (target, blob)
/// pairs (this is the writer's largest table, held at the build's end).
#[derive(Clone, Debug, Default)]
pub(crate) struct Arenas {
    /// Each shader's `name@level`, the start of its permutations' canonical names.
    pub prefixes: Vec<String>,
    /// Each permutation's name, less its shader's prefix where it begins with it; nothing
    /// for a derived name ([`ManifestPermutation::derived`]).
    pub names: String,
    /// Each name in `names`: its start and length (the few names that are not derived:
    /// a derived one's permutation holds its length instead, 8 bytes a permutation less).
    pub spans: Vec<(u32, u32)>,
    pub values: Values,
    /// Each artifact's target, and its blob (a slot of the writer's table, then a blob id).
    pub targets: Vec<Target>,
    pub blobs: Vec<u32>,
}

/// Permutation values: a `u16` each while every one fits (dimension values are small: enum
/// indices, bools, counts), an `i32` once one does not, an `i64` once one does not fit that.
/// Widening copies what was added once (at most twice in all).
#[derive(Clone, Debug)]
pub(crate) enum Values {
    Short(Vec<u16>),
    Narrow(Vec<i32>),
    Wide(Vec<i64>),
}

impl Default for Values {
    fn default() -> Self {
        Values::Short(Vec::new())
    }
}

impl Values {
    pub fn len(&self) -> usize {
        match self {
            Values::Short(v) => v.len(),
            Values::Narrow(v) => v.len(),
            Values::Wide(v) => v.len(),
        }
    }

    pub fn reserve_exact(&mut self, n: usize) {
        match self {
            Values::Short(v) => v.reserve_exact(n),
            Values::Narrow(v) => v.reserve_exact(n),
            Values::Wide(v) => v.reserve_exact(n),
        }
    }

    pub fn extend(&mut self, values: &[i64]) {
        if let Values::Short(v) = self {
            if values.iter().all(|&x| u16::try_from(x).is_ok()) {
                v.extend(values.iter().map(|&x| x as u16));
                return;
            }
            let mut narrow = Vec::with_capacity(v.capacity());
            narrow.extend(v.iter().map(|&x| i32::from(x)));
            *self = Values::Narrow(narrow);
        }
        if let Values::Narrow(v) = self {
            if values.iter().all(|&x| i32::try_from(x).is_ok()) {
                v.extend(values.iter().map(|&x| x as i32));
                return;
            }
            let mut wide = Vec::with_capacity(v.capacity());
            wide.extend(v.iter().map(|&x| i64::from(x)));
            *self = Values::Wide(wide);
        }
        if let Values::Wide(v) = self {
            v.extend_from_slice(values);
        }
    }

    pub fn get(&self, i: usize) -> i64 {
        match self {
            Values::Short(v) => i64::from(v[i]),
            Values::Narrow(v) => i64::from(v[i]),
            Values::Wide(v) => v[i],
        }
    }
}

impl Arenas {
    /// Writes the whole name of `p` to `out` (`shaders` in the numbering of `p.shader`): a
    /// derived name made again from its shader's dimensions and its values.
    pub fn write_name(&self, p: &ManifestPermutation, shaders: &[ShaderRecord], out: &mut String) {
        if p.prefixed {
            out.push_str(&self.prefixes[p.shader as usize]);
        }
        if !p.derived {
            out.push_str(self.own_name(p));
            return;
        }
        let dims = &shaders[p.shader as usize].dimensions;
        write_derived(dims, self.values_of(p, dims.len()), out);
    }

    /// The name of `p` kept in `names` (not derived): its whole name less its shader's
    /// prefix if `prefixed`.
    fn own_name(&self, p: &ManifestPermutation) -> &str {
        let (start, len) = self.spans[p.name as usize];
        &self.names[start as usize..][..len as usize]
    }

    /// The whole name of `p`, for messages.
    pub fn name_of(&self, p: &ManifestPermutation, shaders: &[ShaderRecord]) -> String {
        let mut name = String::new();
        self.write_name(p, shaders, &mut name);
        name
    }

    /// Orders `a` and `b` by their whole names (byte order, as the archive's). Two derived
    /// names of one shader differ only in their values, compared one dimension at a time
    /// (no name is made); the others are made into `buffers`.
    pub fn cmp_names(
        &self,
        (a, b): (&ManifestPermutation, &ManifestPermutation),
        shaders: &[ShaderRecord],
        buffers: &mut (String, String),
    ) -> std::cmp::Ordering {
        if a.shader == b.shader && a.prefixed == b.prefixed && !a.derived && !b.derived {
            return self.own_name(a).cmp(self.own_name(b));
        }
        if a.shader == b.shader && a.derived && b.derived {
            return self.cmp_derived(a, b, &shaders[a.shader as usize].dimensions);
        }
        buffers.0.clear();
        buffers.1.clear();
        self.write_name(a, shaders, &mut buffers.0);
        self.write_name(b, shaders, &mut buffers.1);
        buffers.0.cmp(&buffers.1)
    }

    /// [`Arenas::cmp_names`] of two derived names of a shader with `dims`: each value as
    /// written, followed by what follows it in the name (`,` or the closing `}`).
    fn cmp_derived(&self, a: &ManifestPermutation, b: &ManifestPermutation, dims: &[DimensionRecord]) -> Ordering {
        let values = self.values_of(a, dims.len()).zip(self.values_of(b, dims.len()));
        for (i, (d, (va, vb))) in dims.iter().zip(values).enumerate() {
            if va == vb {
                continue;
            }
            let end = if i + 1 == dims.len() { b'}' } else { b',' };
            match cmp_shown(d, va, vb, end) {
                Ordering::Equal => {}
                other => return other,
            }
        }
        Ordering::Equal
    }

    /// The `count` values of `p` (its shader's dimension count).
    pub fn values_of(&self, p: &ManifestPermutation, count: usize) -> impl Iterator<Item = i64> + '_ {
        (p.first_value as usize..p.first_value as usize + count).map(|i| self.values.get(i))
    }
}

/// A permutation of [`Manifest`] (or of a writer): ranges of its arenas (the values' count
/// is its shader's dimension count), its shader and reflection in the manifest's (or the
/// writer's) numbering.
#[derive(Clone, Copy, Debug)]
pub(crate) struct ManifestPermutation {
    /// A derived name's length (less its shader's prefix, if `prefixed`), else the number of
    /// its span in the names arena ([`Arenas::spans`]).
    pub name: u32,
    pub shader: u32,
    pub reflection: u32,
    pub first_value: u32,
    pub first_artifact: u32,
    /// At most one artifact per target.
    pub artifact_count: u8,
    /// Whether its name begins with its shader's `name@level`, left out of the names arena.
    pub prefixed: bool,
    /// Whether the rest of its name is its shader's dimensions and its values as a canonical
    /// name writes them (`{DIM=value,...}`, `name` bytes): made again where it is needed,
    /// not kept in the names arena, which would be the largest part of a large manifest.
    pub derived: bool,
}

/// Writes what a canonical name has after its shader's `name@level`: `{DIM=value,...}`,
/// each value as [`shown`].
pub(crate) fn write_derived(dims: &[DimensionRecord], values: impl Iterator<Item = i64>, out: &mut String) {
    let mut buffer = [0u8; 20];
    out.push('{');
    for (i, (d, v)) in dims.iter().zip(values).enumerate() {
        if i > 0 {
            out.push(',');
        }
        out.push_str(&d.name);
        out.push('=');
        out.push_str(std::str::from_utf8(shown(d, v, &mut buffer)).expect("a label or a number"));
    }
    out.push('}');
}

/// `value` of dimension `d` as a canonical name writes it (its label, else the number, made
/// in `buffer`: an `i64` takes at most 20 bytes).
fn shown<'a>(d: &'a DimensionRecord, value: i64, buffer: &'a mut [u8; 20]) -> &'a [u8] {
    if let Some(label) = usize::try_from(value).ok().and_then(|i| d.labels.get(i)) {
        return label.as_bytes();
    }
    decimal(value, buffer)
}

/// `value` in decimal, as `{value}` formats it, made in `buffer` from its end: the sort of
/// a large manifest compares values millions of times, and the formatting machinery costs
/// several times the digits.
fn decimal(value: i64, buffer: &mut [u8; 20]) -> &[u8] {
    let mut rest = value.unsigned_abs();
    let mut start = buffer.len();
    loop {
        start -= 1;
        buffer[start] = b'0' + (rest % 10) as u8;
        rest /= 10;
        if rest == 0 {
            break;
        }
    }
    if value < 0 {
        start -= 1;
        buffer[start] = b'-';
    }
    &buffer[start..]
}

/// The order of two values of dimension `d` as written in a name, each followed by `end`
/// (`,` or `}`, what follows it there): the order of the names that differ first there.
/// Numbers are compared as their digits would be, without making them.
fn cmp_shown(d: &DimensionRecord, a: i64, b: i64, end: u8) -> Ordering {
    let labelled = |v: i64| usize::try_from(v).is_ok_and(|i| i < d.labels.len());
    if labelled(a) || labelled(b) {
        let (mut x, mut y) = ([0u8; 20], [0u8; 20]);
        let (x, y) = (shown(d, a, &mut x), shown(d, b, &mut y));
        return x.iter().chain([&end]).cmp(y.iter().chain([&end]));
    }
    match (a < 0, b < 0) {
        // `-` sorts before every digit.
        (true, false) => Ordering::Less,
        (false, true) => Ordering::Greater,
        _ => cmp_digits(a.unsigned_abs(), b.unsigned_abs(), end),
    }
}

/// The order of the decimal digits of `x` and `y`, each followed by `end` (not a digit).
fn cmp_digits(x: u64, y: u64, end: u8) -> Ordering {
    let digits = |v: u64| v.checked_ilog10().map_or(1, |l| l + 1);
    let (dx, dy) = (digits(x), digits(y));
    match dx.cmp(&dy) {
        Ordering::Equal => x.cmp(&y),
        // The shorter against as many leading digits of the longer; where those are the
        // same, `end` against the longer's next digit.
        Ordering::Less => match x.cmp(&(y / 10u64.pow(dy - dx))) {
            Ordering::Equal => end.cmp(&b'0'),
            other => other,
        },
        Ordering::Greater => match (x / 10u64.pow(dx - dy)).cmp(&y) {
            Ordering::Equal => b'0'.cmp(&end),
            other => other,
        },
    }
}

impl ManifestPermutation {
    /// The length of its whole name.
    pub fn whole_name_len(&self, arenas: &Arenas) -> u64 {
        let prefix = if self.prefixed { arenas.prefixes[self.shader as usize].len() } else { 0 };
        let own = if self.derived { self.name } else { arenas.spans[self.name as usize].1 };
        (prefix + own as usize) as u64
    }
}

/// Bytes of the manifest's header, of one permutation record, one id, one value, one
/// artifact and one dictionary record.
pub(crate) const MANIFEST_HEADER_LEN: usize = 64;
pub(crate) const RECORD_LEN: usize = 32;
pub(crate) const ID_LEN: usize = 24;
pub(crate) const VALUE_LEN: usize = 8;
pub(crate) const ARTIFACT_LEN: usize = 8;
pub(crate) const DICTIONARY_LEN: usize = 56;

/// The JSON tables of the manifest, as written.
#[derive(Serialize)]
pub(crate) struct TablesOut<'a> {
    pub kiln_version: &'a str,
    pub naga_version: &'a str,
    pub shaders: &'a [ShaderRecord],
    pub reflections: &'a [Reflection],
    /// Absent from every archive but a `kiln build --usage-only` one: archives without it
    /// are byte for byte what they were before it existed.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub partial: Option<&'a Partial>,
    /// Absent from every archive but a `kiln build --usage` one, for the same reason.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pipelines: Option<&'a [PipelineRecord]>,
}

impl Manifest {
    /// Its JSON tables, as written (both manifest writers encode them from here).
    pub(crate) fn tables_out(&self) -> TablesOut<'_> {
        TablesOut {
            kiln_version: &self.kiln_version,
            naga_version: &self.naga_version,
            shaders: &self.shaders,
            reflections: &self.reflections,
            partial: self.partial.as_ref(),
            pipelines: self.pipelines.as_deref(),
        }
    }
}

/// The JSON tables of the manifest, as read.
#[derive(Deserialize)]
pub(crate) struct Tables {
    pub kiln_version: String,
    pub naga_version: String,
    pub shaders: Vec<ShaderRecord>,
    pub reflections: Vec<Reflection>,
    #[serde(default)]
    pub partial: Option<Partial>,
    #[serde(default)]
    pub pipelines: Option<Vec<PipelineRecord>>,
}

/// A pipeline of the archive's pipeline manifest (`kiln build --usage`): a pipeline a
/// recorded run asked for, whose permutations the archive holds. The manifest lists them in
/// the order a renderer first asked for them (first frame, then key), so that creating them
/// in that order makes the first frames' pipelines ready first.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PipelineRecord {
    /// The pipeline's key: its kind, permutations and (render) fixed-function state text.
    #[serde(flatten)]
    pub key: crate::usage::UsageKey,
    /// The first frame that asked for it (the earliest over the merged runs).
    pub first_frame: u64,
}

/// What a partial archive (`kiln build --usage-only`) left out: the kept permutations of its
/// configuration that no usage file recorded, no `[usage] keep` pattern matched and no
/// `always = true` shader asked for. A lookup of one of them is an error saying so, never a
/// substitute.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Partial {
    /// Canonical names, sorted.
    pub left_out: Vec<String>,
}

/// The counts of the manifest's header.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) struct ManifestCounts {
    pub permutations: u64,
    pub values: u64,
    pub artifacts: u64,
    pub dictionaries: u64,
    pub tables_len: u64,
    pub names_len: u64,
}

/// Where each part of the manifest starts, from the manifest's start, and where it ends.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct ManifestLayout {
    pub records: u64,
    pub ids: u64,
    pub values: u64,
    pub artifacts: u64,
    pub dictionaries: u64,
    pub tables: u64,
    pub names: u64,
    pub end: u64,
}

impl ManifestCounts {
    pub fn encode(&self) -> [u8; MANIFEST_HEADER_LEN] {
        let mut b = [0u8; MANIFEST_HEADER_LEN];
        let fields =
            [self.permutations, self.values, self.artifacts, self.dictionaries, self.tables_len, self.names_len];
        for (i, v) in fields.iter().enumerate() {
            b[i * 8..i * 8 + 8].copy_from_slice(&v.to_le_bytes());
        }
        b
    }

    /// `None` when `bytes` is shorter than the header or its reserved bytes are not zero.
    pub fn decode(bytes: &[u8]) -> Option<ManifestCounts> {
        let b = bytes.get(..MANIFEST_HEADER_LEN)?;
        if b[48..].iter().any(|&x| x != 0) {
            return None;
        }
        let f = |i: usize| u64::from_le_bytes(b[i * 8..i * 8 + 8].try_into().unwrap());
        Some(ManifestCounts {
            permutations: f(0),
            values: f(1),
            artifacts: f(2),
            dictionaries: f(3),
            tables_len: f(4),
            names_len: f(5),
        })
    }

    /// The offsets these counts give, `None` on overflow.
    pub fn layout(&self) -> Option<ManifestLayout> {
        let part = |start: u64, count: u64, len: usize| start.checked_add(count.checked_mul(len as u64)?);
        let records = MANIFEST_HEADER_LEN as u64;
        let ids = part(records, self.permutations, RECORD_LEN)?;
        let values = part(ids, self.permutations, ID_LEN)?;
        let artifacts = part(values, self.values, VALUE_LEN)?;
        let dictionaries = part(artifacts, self.artifacts, ARTIFACT_LEN)?;
        let tables = part(dictionaries, self.dictionaries, DICTIONARY_LEN)?;
        let names = tables.checked_add(self.tables_len)?.checked_next_multiple_of(8)?;
        let end = names.checked_add(self.names_len)?;
        Some(ManifestLayout { records, ids, values, artifacts, dictionaries, tables, names, end })
    }
}

/// One permutation record of the manifest, decoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Record {
    pub name_offset: u64,
    pub name_len: u32,
    pub shader: u32,
    pub reflection: u32,
    pub first_value: u32,
    pub first_artifact: u32,
    pub artifact_count: u32,
}

impl Record {
    pub fn encode(&self) -> [u8; RECORD_LEN] {
        let mut b = [0u8; RECORD_LEN];
        b[0..8].copy_from_slice(&self.name_offset.to_le_bytes());
        let rest =
            [self.name_len, self.shader, self.reflection, self.first_value, self.first_artifact, self.artifact_count];
        for (i, v) in rest.iter().enumerate() {
            b[8 + i * 4..12 + i * 4].copy_from_slice(&v.to_le_bytes());
        }
        b
    }

    /// `bytes` is exactly [`RECORD_LEN`] long.
    pub fn decode(bytes: &[u8]) -> Record {
        let u32_at = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().unwrap());
        Record {
            name_offset: u64::from_le_bytes(bytes[0..8].try_into().unwrap()),
            name_len: u32_at(8),
            shader: u32_at(12),
            reflection: u32_at(16),
            first_value: u32_at(20),
            first_artifact: u32_at(24),
            artifact_count: u32_at(28),
        }
    }
}

/// An entry of the manifest's ids table: a permutation's id and its index (the rest zero).
pub(crate) fn encode_id(id: u128, index: u32) -> [u8; ID_LEN] {
    let mut b = [0u8; ID_LEN];
    b[0..16].copy_from_slice(&id.to_le_bytes());
    b[16..20].copy_from_slice(&index.to_le_bytes());
    b
}

/// An artifact of the manifest: its target's index in [`Target::ALL`] and its blob.
pub(crate) fn encode_artifact(target: Target, blob: BlobId) -> [u8; ARTIFACT_LEN] {
    let mut b = [0u8; ARTIFACT_LEN];
    b[0] = Target::ALL.iter().position(|t| *t == target).expect("a target of Target::ALL") as u8;
    b[4..8].copy_from_slice(&blob.0.to_le_bytes());
    b
}

/// `None` for an unknown target or non-zero reserved bytes.
pub(crate) fn decode_artifact(bytes: &[u8]) -> Option<(Target, BlobId)> {
    let target = *Target::ALL.get(bytes[0] as usize)?;
    if bytes[1..4] != [0, 0, 0] {
        return None;
    }
    Some((target, BlobId(u32::from_le_bytes(bytes[4..8].try_into().unwrap()))))
}

impl DictionaryRecord {
    pub fn encode(&self) -> [u8; DICTIONARY_LEN] {
        let mut b = [0u8; DICTIONARY_LEN];
        b[0] = Target::ALL.iter().position(|t| *t == self.target).expect("a target of Target::ALL") as u8;
        b[8..16].copy_from_slice(&self.offset.to_le_bytes());
        b[16..24].copy_from_slice(&self.len.to_le_bytes());
        b[24..56].copy_from_slice(&self.blake3);
        b
    }

    /// `None` for an unknown target or non-zero reserved bytes.
    pub fn decode(bytes: &[u8]) -> Option<DictionaryRecord> {
        let target = *Target::ALL.get(bytes[0] as usize)?;
        if bytes[1..8].iter().any(|&x| x != 0) {
            return None;
        }
        Some(DictionaryRecord {
            target,
            offset: u64::from_le_bytes(bytes[8..16].try_into().unwrap()),
            len: u64::from_le_bytes(bytes[16..24].try_into().unwrap()),
            blake3: bytes[24..56].try_into().unwrap(),
        })
    }
}

/// One blob table entry, decoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Entry {
    pub offset: u64,
    pub stored_len: u64,
    pub raw_len: u64,
    pub codec: u8,
    pub dictionary: u8,
    /// [`stored_sum`] of the stored bytes (format 5; zero in format 4).
    pub sum: u64,
    pub hash: [u8; 32],
}

/// The check sum of a blob's stored bytes kept in its table entry (format 5): the low 48
/// bits of their xxh3-64. It tells stored bytes damaged since they were written without
/// decompressing them and hashing the result, so that a writer can copy a previous
/// archive's compressed blob at the cost of reading it once.
pub(crate) fn stored_sum(stored: &[u8]) -> u64 {
    xxhash_rust::xxh3::xxh3_64(stored) & STORED_SUM_MASK
}

/// The bits of [`stored_sum`] an entry keeps.
const STORED_SUM_MASK: u64 = (1 << 48) - 1;

impl Entry {
    pub fn encode(&self) -> [u8; ENTRY_LEN] {
        let mut b = [0u8; ENTRY_LEN];
        b[0..8].copy_from_slice(&self.offset.to_le_bytes());
        b[8..16].copy_from_slice(&self.stored_len.to_le_bytes());
        b[16..24].copy_from_slice(&self.raw_len.to_le_bytes());
        b[24] = self.codec;
        b[25] = self.dictionary;
        b[26..32].copy_from_slice(&(self.sum & STORED_SUM_MASK).to_le_bytes()[..6]);
        b[32..64].copy_from_slice(&self.hash);
        b
    }

    /// `bytes` is exactly [`ENTRY_LEN`] long.
    pub fn decode(bytes: &[u8]) -> Entry {
        let u64_at = |o: usize| u64::from_le_bytes(bytes[o..o + 8].try_into().unwrap());
        Entry {
            offset: u64_at(0),
            stored_len: u64_at(8),
            raw_len: u64_at(16),
            codec: bytes[24],
            dictionary: bytes[25],
            sum: bytes[26..32].iter().rev().fold(0, |sum, &b| sum << 8 | u64::from(b)),
            hash: bytes[32..64].try_into().unwrap(),
        }
    }

    /// Whether the six bytes that format 4 reserved (format 5's check sum) are zero.
    pub fn reserved_zero(bytes: &[u8]) -> bool {
        bytes[26..32].iter().all(|&b| b == 0)
    }
}

/// Section lengths of the header.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Sections {
    pub blobs_len: u64,
    pub dictionaries_len: u64,
    pub manifest_len: u64,
    pub blob_count: u64,
    /// Bytes per chunk hash (a power of two, checked by [`Sections::layout`]).
    pub chunk_len: u32,
}

/// Where each section starts, and where the file ends.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Layout {
    pub blobs: u64,
    pub dictionaries: u64,
    /// The chunk hashes: `manifest_chunks` of the manifest, then `table_chunks` of the table.
    pub chunks: u64,
    pub manifest_chunks: u64,
    pub table_chunks: u64,
    pub manifest: u64,
    pub table: u64,
    pub end: u64,
}

impl Sections {
    /// The offsets these lengths give, `None` on overflow or a chunk length that is not a
    /// power of two in the range the reference page gives.
    pub fn layout(&self) -> Option<Layout> {
        if !self.chunk_len.is_power_of_two() || !(1 << 10..=1 << 20).contains(&self.chunk_len) {
            return None;
        }
        let align = |v: u64| v.checked_next_multiple_of(8);
        let table_len = self.blob_count.checked_mul(ENTRY_LEN as u64)?;
        let manifest_chunks = self.manifest_len.div_ceil(self.chunk_len as u64);
        let table_chunks = table_len.div_ceil(self.chunk_len as u64);
        let blobs = HEADER_LEN as u64;
        let dictionaries = align(blobs.checked_add(self.blobs_len)?)?;
        let chunks = align(dictionaries.checked_add(self.dictionaries_len)?)?;
        let hashes = (manifest_chunks + table_chunks).checked_mul(CHUNK_HASH_LEN as u64)?;
        let manifest = chunks.checked_add(hashes)?;
        let table = align(manifest.checked_add(self.manifest_len)?)?;
        let end = table.checked_add(table_len)?;
        Some(Layout { blobs, dictionaries, chunks, manifest_chunks, table_chunks, manifest, table, end })
    }

    /// The header up to its checksum.
    pub fn header_fields(&self) -> [u8; 96] {
        let mut h = [0u8; 96];
        h[0..8].copy_from_slice(&MAGIC);
        h[8..12].copy_from_slice(&FORMAT_VERSION.to_le_bytes());
        h[16..24].copy_from_slice(&self.blobs_len.to_le_bytes());
        h[24..32].copy_from_slice(&self.dictionaries_len.to_le_bytes());
        h[32..40].copy_from_slice(&self.manifest_len.to_le_bytes());
        h[40..48].copy_from_slice(&self.blob_count.to_le_bytes());
        h[48..52].copy_from_slice(&self.chunk_len.to_le_bytes());
        h
    }
}

/// The checksum of the header: blake3 of the header up to the checksum, then the chunk hashes.
pub(crate) fn header_checksum(fields: &[u8], chunk_hashes: &[u8]) -> blake3::Hash {
    let mut h = blake3::Hasher::new();
    h.update(fields);
    h.update(chunk_hashes);
    h.finalize()
}

/// The chunk hashes of a region (the manifest, then the table) fed in pieces of any size:
/// one blake3 per `chunk` bytes, the last chunk of each region cut short by [`finish`].
///
/// [`finish`]: ChunkHasher::finish
pub(crate) struct ChunkHasher {
    chunk: usize,
    hasher: blake3::Hasher,
    filled: usize,
    /// The hashes so far, `CHUNK_HASH_LEN` bytes each.
    pub hashes: Vec<u8>,
}

impl ChunkHasher {
    pub fn new(chunk: u32) -> ChunkHasher {
        ChunkHasher { chunk: chunk as usize, hasher: blake3::Hasher::new(), filled: 0, hashes: Vec::new() }
    }

    pub fn update(&mut self, mut bytes: &[u8]) {
        while !bytes.is_empty() {
            let n = (self.chunk - self.filled).min(bytes.len());
            self.hasher.update(&bytes[..n]);
            self.filled += n;
            bytes = &bytes[n..];
            if self.filled == self.chunk {
                self.finish();
            }
        }
    }

    /// Ends the current region: its last, partial chunk gets its hash.
    pub fn finish(&mut self) {
        if self.filled > 0 {
            self.hashes.extend_from_slice(self.hasher.finalize().as_bytes());
            self.hasher.reset();
            self.filled = 0;
        }
    }
}

/// Writes `bytes` to `path` as [`crate::output::write_with`] does (atomically; a device or a
/// FIFO written through; never renamed over anything else), synced.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    write_pieces(path, &[bytes], true)
}

/// [`write_atomic`] without syncing the temporary file before the rename.
pub fn write_atomic_unsynced(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    write_pieces(path, &[bytes], false)
}

/// Writes the concatenation of `pieces` (see [`write_atomic`]).
pub fn write_pieces(path: &Path, pieces: &[&[u8]], sync: bool) -> std::io::Result<()> {
    crate::output::write_with(path, sync, |f, _| write_all_vectored(f, pieces))
}

/// A file name beside `path` that no other writer uses: `.NAME.PID.NANOS.N.SUFFIX`.
pub(crate) fn sibling_name(path: &Path, suffix: &str) -> std::io::Result<PathBuf> {
    static COUNTER: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    std::fs::create_dir_all(dir)?;
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let nanos =
        std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.subsec_nanos()).unwrap_or(0);
    let n = COUNTER.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    Ok(dir.join(format!(".{name}.{}.{nanos}.{n}.{suffix}", std::process::id())))
}

/// Lets `write` fill `path` as [`crate::output::write_with`] does: a regular file through a
/// temporary file beside it and a rename (removed on any error); a device or a FIFO, which
/// cannot seek, through an unlinked temporary file in the system's temporary folder, copied
/// to it in order; a directory or a socket refused.
pub(crate) fn write_atomic_with(
    path: &Path,
    sync: bool,
    write: impl FnOnce(&mut File) -> std::io::Result<()>,
) -> std::io::Result<()> {
    crate::output::write_with(path, sync, |f, sink| match sink {
        crate::output::Sink::Temporary => write(f),
        crate::output::Sink::Stream => {
            use std::io::{Seek, SeekFrom};
            let tmp = sibling_name(&std::env::temp_dir().join("kiln-output"), "tmp")?;
            let mut t = File::options().read(true).write(true).create_new(true).open(&tmp)?;
            let _ = std::fs::remove_file(&tmp);
            write(&mut t)?;
            t.seek(SeekFrom::Start(0))?;
            std::io::copy(&mut t, f).map(|_| ())
        }
    })
}

/// Writes every piece in order with as few `writev` calls as the system allows.
pub(crate) fn write_all_vectored(out: &mut impl Write, pieces: &[&[u8]]) -> std::io::Result<()> {
    // IOV_MAX is 1024 on Linux.
    for batch in pieces.chunks(1024) {
        let mut slices: Vec<IoSlice<'_>> = batch.iter().map(|p| IoSlice::new(p)).collect();
        let mut rest = &mut slices[..];
        IoSlice::advance_slices(&mut rest, 0);
        while !rest.is_empty() {
            match out.write_vectored(rest) {
                Ok(0) => return Err(std::io::ErrorKind::WriteZero.into()),
                Ok(n) => IoSlice::advance_slices(&mut rest, n),
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(e),
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod decimal_tests {
    use super::{cmp_shown, decimal, shown, DimensionRecord};

    /// Values compared without their digits sort as their digits (then `,` or `}`) do,
    /// labels and numbers, both signs, any lengths.
    #[test]
    fn values_compare_as_their_names_do() {
        let d = DimensionRecord { name: "D".into(), labels: vec!["OPAQUE".into(), "2".into(), "10".into()] };
        let mut values = vec![0i64, 1, 2, 3, 9, 10, 11, 19, 20, 99, 100, 101, 1000, -1, -9, -10, -100];
        values.extend([i64::MAX, i64::MIN, i64::MIN + 1, 1 << 40, (1 << 40) + 1, 10_000_000_000_000_000_000u64 as i64]);
        let mut x = 0x2545_f491_4f6c_dd1du64;
        for _ in 0..400 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            values.push((x as i64) >> (x % 64));
        }
        let (mut bx, mut by) = ([0u8; 20], [0u8; 20]);
        for &a in &values {
            for &b in &values {
                for end in [b',', b'}'] {
                    let want =
                        shown(&d, a, &mut bx).iter().chain([&end]).cmp(shown(&d, b, &mut by).iter().chain([&end]));
                    assert_eq!(cmp_shown(&d, a, b, end), want, "{a} {b} {}", end as char);
                }
            }
        }
    }

    /// The digits made by hand are the ones `{value}` formats, at the ends of the range too.
    #[test]
    fn decimal_matches_the_formatter() {
        let mut values = vec![0i64, 1, -1, 9, 10, -10, 99, 100, i64::MAX, i64::MIN, i64::MIN + 1];
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        for _ in 0..10_000 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            values.push(x as i64 >> (x % 64));
        }
        let mut buffer = [0u8; 20];
        for v in values {
            assert_eq!(decimal(v, &mut buffer), v.to_string().as_bytes(), "{v}");
        }
    }
}
