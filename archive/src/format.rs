//! The byte layout of an archive (format version 4), shared by the writer and the reader.
//!
//! ```text
//! offset  size  field
//!      0     8  magic "KILNPAK\0"
//!      8     4  format version (u32, little endian): 4
//!     12     4  flags (u32, zero)
//!     16     8  blob section length in bytes (u64)
//!     24     8  dictionary section length (u64)
//!     32     8  manifest length (u64)
//!     40     8  blob count (u64)
//!     48     4  chunk length C in bytes (u32, a power of two from 1 KiB to 1 MiB)
//!     52    44  zero
//!     96    32  blake3 of header bytes 0..96, then the chunk hashes
//!    128     -  blob section, padding to 8, dictionary section, padding to 8, chunk hashes
//!               (below), manifest (binary, below), padding to 8, blob table (64 bytes per
//!               blob), end of file
//! ```
//!
//! The chunk hashes (format 4) are the blake3 (32 bytes) of each C-byte chunk of the
//! manifest, then of each C-byte chunk of the blob table (the last chunk of each may be
//! shorter): `ceil(manifest length / C) + ceil(blob count * 64 / C)` hashes. Opening checks
//! the header checksum, which covers the chunk hashes (32 bytes per C bytes of manifest and
//! table), and reads the chunks of the manifest's header, dictionaries and tables; every other
//! chunk is checked against its hash the first time a read touches it (one bit per chunk), so
//! that opening costs O(1) in the number of permutations (format 3 hashed the whole manifest
//! and table at open: 9.1 ms for a 100,000-permutation archive).
//!
//! The manifest (format 3 and 4; format 2 held JSON, parsed whole at open) is read in place
//! from the memory map. Every part starts at a multiple of 8 from the manifest's start:
//!
//! ```text
//! manifest header, 64 bytes: permutation count P, value count V, artifact count A,
//!     dictionary count D, tables length T, names length N (u64 each), 16 zero bytes
//! permutations  P x 32  sorted by name: name offset (u64, into names), name length (u32),
//!                       shader (u32), reflection (u32), first value (u32, into values),
//!                       first artifact (u32, into artifacts), artifact count (u32); the
//!                       value count is the shader's dimension count
//! ids           P x 24  sorted: permutation id (u128, see `permutation_id`), permutation
//!                       index (u32), 4 zero bytes
//! values        V x 8   i64
//! artifacts     A x 8   target (u8, index in `Target::ALL`), 3 zero bytes, blob (u32)
//! dictionaries  D x 56  target (u8), 7 zero bytes, offset (u64, from the start of the
//!                       dictionary section), length (u64), blake3 (32)
//! tables        T       JSON: kiln and naga versions, the (shader, level) records and the
//!                       distinct reflections, which no permutation count multiplies
//! names         N       the permutations' canonical names, UTF-8, one after another
//! ```
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
//! # Why per-target dictionaries, not compressed groups
//!
//! Measured on the bundled set (625 permutations, 2,457 distinct artifacts, 27.3 MiB raw;
//! format 1 stored it in 28.6 MB) with `compiler/examples/zstd_probe.rs` (release build; the
//! bench repeats the main rows), each artifact compressed alone and decompressed with a
//! reused context:
//!
//! | scheme                                        | compressed    | ratio | decompress one (median) |
//! | --------------------------------------------- | ------------- | ----- | ----------------------- |
//! | zstd -3 per artifact, no dictionary           | 8.55 MB       |  3.3x |                         |
//! | per-target dictionary 64 KiB, zstd -3         | 2.16 MB       | 13.1x | 1.2 µs                  |
//! | per-target dictionary 128 KiB, zstd -3        | 2.08 MB       | 13.6x | 1.4 µs                  |
//! | per-target dictionary 128 KiB, zstd -19       | 1.57 MB       | 18.0x | 7.4 µs                  |
//! | groups (shader, target) <= 64 KiB, zstd -3    | 2.76 MB       | 10.2x | 18.7 µs                 |
//! | groups <= 256 KiB, zstd -3                    | 1.28 MB       | 22.1x | 28.3 µs                 |
//! | groups <= 1 MiB, zstd -3                      | 0.90 MB       | 31.4x | 54.7 µs                 |
//! | one group per (shader, target), zstd -3       | 0.75 MB       | 37.5x | 365.8 µs                |
//!
//! On the generated set of `cargo bench -p kiln --bench archive` (1,024 permutations, 4,093
//! distinct artifacts, 9.95 MB raw), whose artifacts are nearer copies of each other than real
//! ones: no dictionary 3.7x; per-target dictionary 64 KiB 15.3x (0.6 µs), 128 KiB 13.7x
//! (0.6 µs); groups <= 64 KiB 35.3x (14.9 µs), <= 256 KiB 70.5x (27.9 µs), <= 1 MiB 108x
//! (74 µs). There the blobs are already only half of the archive (0.59 of 1.19 MB; the
//! manifest and blob table are the rest), so groups would make the file at most 2x smaller.
//!
//! Both schemes beat the goal of 1/8 of format 1. Groups compress better the larger they
//! are, but a lookup then decompresses (and a runtime would have to cache) a whole group to
//! use one artifact: 20 to 250 times the work of a dictionary lookup, and the time grows with
//! the group. Dictionaries keep every artifact its own zstd frame: a lookup decompresses
//! exactly the bytes it needs, checks exactly one checksum, and a corrupted blob damages one
//! permutation, not its neighbours. So Kiln trains one dictionary per target (WGSL, SPIR-V,
//! MSL, GLSL and HLSL share little with each other) at build time on a deterministic sample
//! of that target's artifacts, and compresses at level [`COMPRESSION_LEVEL`].
//!
//! The chosen scheme, measured by `cargo bench -p kiln --bench archive` (release build, this
//! shared 2-core machine, medians):
//!
//! | archive                                  | format 1 | format 2 | ratio | open    | lookup + decompress (first use) |
//! | ---------------------------------------- | -------- | -------- | ----- | ------- | ------------------------------- |
//! | bundled set, 625 permutations            | 28.74 MB | 2.46 MB  | 0.085 | 0.68 ms | 2.4 µs (7.2 µs)                 |
//! | generated set, 1,024 permutations        | 10.44 MB | 1.19 MB  | 0.114 | 0.63 ms | 0.9 µs (3.3 µs)                 |
//! | generated, 1,024 x 1 MiB incompressible  | 1.07 GB  | 1.07 GB  | 1.000 | 0.34 ms | 0.3 µs (156 µs)                 |
//!
//! The training sample is [`DICTIONARY_SAMPLE`] per target: with 8 MiB (every artifact of the
//! bundled set) training was about a third of a cold build's instructions; 2 MiB gives the
//! bundled set 2.70 MB (ratio 0.094) for about 15% less build CPU time (1 MiB: 3.45 MB, 0.120).
//! The table above was measured with 8 MiB.
//!
//! Training is one fastCover pass with fixed parameters (k = 1024, d = 8; `writer.rs`), not
//! `ZDICT_trainFromBuffer`'s search over five values of k. Callgrind, bundled set, `kiln build
//! --no-cache -j 1`: training 1.67 G instructions with the search, 0.38 G with one pass; the
//! whole build 10.96 G -> 9.66 G; the archive 2.70 MB -> 2.54 MB (ratio 0.088), identical
//! bytes with `-j 1` and `-j 2`. Since then fastCover runs with `accel` 4 (`FASTCOVER_ACCEL`),
//! and each blob is compressed with its dictionary attached rather than copied into the
//! context: the bundled set's archive 2.72 -> 2.70 MB, the naga_oil bench's set +1.5%, its
//! build 2.1% fewer instructions (training 9.4 -> 5.9 ms). The tables above predate both.
//!
//! Of the bundled set's 2.46 MB, blobs take 1.73 MB, dictionaries 0.31 MB, and the manifest
//! and blob table the rest. With format 2's JSON manifest, opening was mostly parsing it
//! (0.68 ms for the bundled set, growing with the number of permutations); format 3's binary
//! manifest is read in place, but opening still hashed the whole manifest and blob table and
//! range-checked every record and entry: O(manifest). Format 4 hashes them per chunk, each
//! chunk the first time a read touches it, and checks each record and entry on first use, so
//! that opening reads the header, the chunk hashes (32 bytes per [`CHUNK_LEN`] bytes, 93 KB
//! for the 48 MB of manifest and table of 100,000 permutations), the manifest's header,
//! dictionaries and JSON tables, and one empty cell per page of bits. `cargo bench -p kiln --bench
//! archive` (release, this 2-core machine shared with other builds at a load average of 4.7
//! to 5.0, medians of 51 opens; the same run for both formats):
//!
//! | archive                                          | format 3 open | format 4 open | format 4 first lookup after open (no artifact) |
//! | ------------------------------------------------ | ------------- | ------------- | ---------------------------------------------- |
//! | bundled set, 622 permutations, 2.72 MB           | 0.28 ms       | 0.21 ms       | 35 µs (10 µs)                                  |
//! | generated, 1,024 x 1 MiB incompressible          | 0.053 ms      | 0.018 ms      | 166 µs (9 µs)                                  |
//! | generated, 10,000 permutations (3.8 MB manifest) | 0.71 ms       | 0.053 ms      | 69 µs (38 µs)                                  |
//! | generated, 100,000 permutations (38 MB manifest) | 13.1 ms       | 0.064 ms      | 118 µs (79 µs)                                 |
//! | `kiln build` of a generated 100,000-permutation set (66.2 MB; `KILN_ARCHIVE_FILES`) | 9.1 ms (an earlier run) | 0.056 ms | 109 µs (68 µs) |
//!
//! What remains at open is O(shaders + distinct reflections): parsing the JSON tables (most of
//! the bundled set's 0.21 ms). A lookup by name and decompression of one artifact, median over
//! 2,000 names: bundled 6.9 µs on first use (chunks, record, blob and dictionary checked), 1.8 µs
//! again; 100,000 permutations 3.7 µs and 2.4 µs (format 3: 3.0 and 1.9). The first lookup after
//! an open costs more (the table above): the pages of the map it touches fault in, each chunk
//! its binary search reads is hashed (about 20 at 100,000 permutations), and the first
//! artifact of a target loads its dictionary. A walk of every record (`permutations`, so
//! `kiln inspect --list`) checks every chunk and record first: 0.05 ms for the bundled set,
//! 0.9 ms for 10,000 permutations, 10 to 21 ms for the generated 100,000 (6.6 ms for the
//! built one, whose names are shorter); format 3 paid about that at every open.
//!
//! [`CHUNK_LEN`] was chosen on the generated archive of 100,000 permutations (same bench,
//! one to three runs each at a load average of 4 to 6, ranges; 10,000 alike but smaller):
//!
//! | chunk  | chunk hashes | open           | first lookup after open | same, no artifact | lookup + decompress, first use | walk of every record |
//! | ------ | ------------ | -------------- | ----------------------- | ----------------- | ------------------------------ | -------------------- |
//! | 2 KiB  | 746 KB       | 0.150 ms       | 116 µs                  |                   | 11.3 µs                        | 32 ms                |
//! | 4 KiB  | 373 KB       | 0.092-0.097 ms | 109-114 µs              | 75-77 µs          | 7.3-7.8 µs                     | 21-29 ms             |
//! | 8 KiB  | 187 KB       | 0.072-0.076 ms | 113-121 µs              | 76-78 µs          | 5.4-5.8 µs                     | 15-21 ms             |
//! | 16 KiB | 93 KB        | 0.062-0.066 ms | 116-121 µs              | 79-85 µs          | 3.5-4.5 µs                     | 10-23 ms             |
//! | 32 KiB | 47 KB        | 0.064 ms       | 162 µs                  |                   | 3.5 µs                         | 14 ms                |
//!
//! Smaller chunks make the chunk hashes (hashed at open) larger and a walk slower (blake3 is
//! fastest on inputs of 16 of its 1 KiB chunks and more); larger ones make the first lookups
//! hash more bytes per chunk they read. The first lookup after an open is mostly page faults
//! and its first dictionary, and hardly depends on the chunk length up to 16 KiB; 16 KiB
//! gives the fastest open and first uses, and walks as fast as any.

use std::fs::File;
use std::io::{IoSlice, Write};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::{Reflection, Stage, Target};

pub const MAGIC: [u8; 8] = *b"KILNPAK\0";
pub const FORMAT_VERSION: u32 = 4;
pub const HEADER_LEN: usize = 128;
/// Bytes of one chunk of the manifest and of the blob table that one hash covers (chosen by
/// measuring: the module doc's table). The reader takes the length from the header.
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

#[derive(Debug, thiserror::Error)]
pub enum ArchiveError {
    #[error("cannot read archive {path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("cannot read archive {path}: it is a {kind}, not a regular file")]
    NotAFile { path: PathBuf, kind: &'static str },
    #[error("cannot write archive {path}: {source}")]
    Write { path: PathBuf, source: std::io::Error },
    #[error("not a kiln archive: the file is {len} bytes, shorter than the {HEADER_LEN}-byte header")]
    TooShort { len: usize },
    #[error("not a kiln archive: bad magic bytes {found:02x?}")]
    BadMagic { found: [u8; 8] },
    #[error("archive format version {found} is not supported (this build of kiln reads version {FORMAT_VERSION}); rebuild the archive with this kiln")]
    Version { found: u32 },
    #[error("archive is truncated: the header announces {expected} bytes, the file has {actual}")]
    Truncated { expected: u64, actual: u64 },
    #[error("archive is corrupted: header checksum mismatch (expected {expected}, computed {actual})")]
    Checksum { expected: String, actual: String },
    #[error("archive manifest is malformed: {0}")]
    Manifest(String),
    /// A chunk of the manifest or blob table that no permutation's use reads (an id, say)
    /// failed its hash in [`crate::Archive::verify_all`].
    #[error("archive is corrupted: {0}")]
    Corrupted(String),
    /// A blob failed its check or its decompression the first time it was used.
    #[error("archive is corrupted: the {target} artifact of permutation `{permutation}`: {message}")]
    Blob { permutation: String, target: Target, message: String },
    /// A permutation record failed its check (its chunk's hash, or a range) the first time
    /// it was read. `permutation` is its name, or the name being looked up, or its number
    /// when its name cannot be trusted.
    #[error("archive is corrupted: permutation {permutation}: {message}")]
    Permutation { permutation: String, message: String },
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
    pub name: String,
    pub level: String,
    pub entry: String,
    pub stage: Stage,
    /// Dimensions in declared order.
    pub dimensions: Vec<DimensionRecord>,
}

#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct DimensionRecord {
    pub name: String,
    /// For an enum dimension, the name of each index; empty otherwise.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub labels: Vec<String>,
}

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
    pub shaders: Vec<ShaderRecord>,
    pub reflections: Vec<Reflection>,
    /// Sorted by name.
    pub permutations: Vec<ManifestPermutation>,
    pub arenas: Arenas,
}

/// Where the permutations of a manifest (or of a writer, before they are sorted) keep their
/// names, values and artifacts: about 70 bytes a permutation, where whole names, 8-byte
/// values and (target, blob) pairs took about 100 (the writer's largest table at 100k
/// permutations, held at the build's end).
#[derive(Clone, Debug, Default)]
pub(crate) struct Arenas {
    /// Each shader's `name@level`, the start of its permutations' canonical names.
    pub prefixes: Vec<String>,
    /// Each permutation's name, less its shader's prefix where it begins with it.
    pub names: String,
    pub values: Values,
    /// Each artifact's target, and its blob (a slot of the writer's table, then a blob id).
    pub targets: Vec<Target>,
    pub blobs: Vec<u32>,
}

/// Permutation values: 4 bytes each while every one fits an `i32` (dimension values are
/// small), 8 once one does not.
#[derive(Clone, Debug)]
pub(crate) enum Values {
    Narrow(Vec<i32>),
    Wide(Vec<i64>),
}

impl Default for Values {
    fn default() -> Self {
        Values::Narrow(Vec::new())
    }
}

impl Values {
    pub fn len(&self) -> usize {
        match self {
            Values::Narrow(v) => v.len(),
            Values::Wide(v) => v.len(),
        }
    }

    pub fn reserve_exact(&mut self, n: usize) {
        match self {
            Values::Narrow(v) => v.reserve_exact(n),
            Values::Wide(v) => v.reserve_exact(n),
        }
    }

    pub fn extend(&mut self, values: &[i64]) {
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
            Values::Narrow(v) => i64::from(v[i]),
            Values::Wide(v) => v[i],
        }
    }
}

impl Arenas {
    /// The name of `p` in two parts: its shader's prefix (empty when not `prefixed`), then
    /// its own bytes.
    pub fn name_parts(&self, p: &ManifestPermutation) -> (&str, &str) {
        let own = &self.names[p.name_start as usize..p.name_start as usize + p.name_len as usize];
        match p.prefixed {
            true => (&self.prefixes[p.shader as usize], own),
            false => ("", own),
        }
    }

    /// The whole name of `p`, for messages.
    pub fn name_of(&self, p: &ManifestPermutation) -> String {
        let (prefix, own) = self.name_parts(p);
        format!("{prefix}{own}")
    }

    /// Orders `a` and `b` by their whole names (byte order, as the archive's).
    pub fn cmp_names(&self, a: &ManifestPermutation, b: &ManifestPermutation) -> std::cmp::Ordering {
        let ((pa, na), (pb, nb)) = (self.name_parts(a), self.name_parts(b));
        if pa == pb {
            return na.cmp(nb);
        }
        pa.bytes().chain(na.bytes()).cmp(pb.bytes().chain(nb.bytes()))
    }

    /// The `count` values of `p` (its shader's dimension count).
    pub fn values_of(&self, p: &ManifestPermutation, count: usize) -> impl Iterator<Item = i64> + '_ {
        (p.first_value as usize..p.first_value as usize + count).map(|i| self.values.get(i))
    }
}

/// A permutation of [`Manifest`] (or of a writer): ranges of its arenas (the values' count
/// is its shader's dimension count), its shader and reflection in the manifest's (or the
/// writer's) numbering. 28 bytes.
#[derive(Clone, Copy, Debug)]
pub(crate) struct ManifestPermutation {
    pub name_start: u32,
    /// Its own bytes in the names arena (its whole name less its shader's prefix, if
    /// `prefixed`).
    pub name_len: u32,
    pub shader: u32,
    pub reflection: u32,
    pub first_value: u32,
    pub first_artifact: u32,
    /// At most one artifact per target.
    pub artifact_count: u8,
    /// Whether its name begins with its shader's `name@level`, left out of the names arena.
    pub prefixed: bool,
}

impl ManifestPermutation {
    /// The length of its whole name.
    pub fn whole_name_len(&self, arenas: &Arenas) -> u64 {
        let prefix = if self.prefixed { arenas.prefixes[self.shader as usize].len() } else { 0 };
        (prefix + self.name_len as usize) as u64
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
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
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
    pub hash: [u8; 32],
}

impl Entry {
    pub fn encode(&self) -> [u8; ENTRY_LEN] {
        let mut b = [0u8; ENTRY_LEN];
        b[0..8].copy_from_slice(&self.offset.to_le_bytes());
        b[8..16].copy_from_slice(&self.stored_len.to_le_bytes());
        b[16..24].copy_from_slice(&self.raw_len.to_le_bytes());
        b[24] = self.codec;
        b[25] = self.dictionary;
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
            hash: bytes[32..64].try_into().unwrap(),
        }
    }

    /// Whether the six reserved bytes are zero.
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
    /// power of two from 1 KiB to 1 MiB.
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

    /// The first 96 bytes of the header (before the checksum).
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

/// The checksum of the header: blake3 of its first 96 bytes and the chunk hashes.
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
    /// The hashes so far, 32 bytes each.
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
