//! The byte layout of an archive, its writer and its reader.
//!
//! ```text
//! offset  size  field
//!      0     8  magic "KILNPAK\0"
//!      8     4  format version (u32, little endian)
//!     12     4  flags (u32, zero)
//!     16     8  manifest length in bytes (u64)
//!     24     8  blob section length in bytes (u64)
//!     32    32  blake3 checksum of every byte after the header
//!     64     -  manifest (JSON), then padding to 8, then the blob section
//! ```
//!
//! Blobs are deduplicated by content and aligned to 8 bytes inside the blob section, so a
//! SPIR-V blob can be read as `u32` words straight from a memory map.

use std::borrow::Cow;
use std::collections::HashMap;
use std::fs::File;
use std::io::{IoSlice, Write};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::{Reflection, Stage, Target};

pub const MAGIC: [u8; 8] = *b"KILNPAK\0";
pub const FORMAT_VERSION: u32 = 1;
pub const HEADER_LEN: usize = 64;

#[derive(Debug, thiserror::Error)]
pub enum ArchiveError {
    #[error("cannot read archive {path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
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
    #[error("archive is corrupted: checksum mismatch (expected {expected}, computed {actual})")]
    Checksum { expected: String, actual: String },
    #[error("archive manifest is malformed: {0}")]
    Manifest(String),
}

/// Index of a blob in the archive.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct BlobId(pub u32);

/// A shader of the manifest: one (shader, level) pair with its dimensions, so lookups by
/// dimension values can build the canonical name.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ShaderRecord {
    pub name: String,
    pub level: String,
    pub entry: String,
    pub stage: Stage,
    /// Dimensions in declared order.
    pub dimensions: Vec<DimensionRecord>,
}

#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
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

#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
struct BlobRecord {
    offset: u64,
    len: u64,
}

#[derive(Clone, Debug, Default, Serialize, Deserialize)]
struct Manifest {
    kiln_version: String,
    naga_version: String,
    shaders: Vec<ShaderRecord>,
    reflections: Vec<Reflection>,
    blobs: Vec<BlobRecord>,
    permutations: Vec<PermutationRecord>,
}

/// Collects permutations and artifacts, deduplicating blobs and reflections, then writes
/// the archive atomically.
/// Blobs added with [`ArchiveWriter::add_blob_ref`] are borrowed until the archive is
/// written, not copied.
#[derive(Default)]
pub struct ArchiveWriter<'a> {
    manifest: Manifest,
    /// The distinct blobs, in blob-section order.
    blobs: Vec<Cow<'a, [u8]>>,
    /// Length of the blob section so far (blobs and the padding before each).
    blob_section_len: u64,
    blob_index: HashMap<blake3::Hash, BlobId>,
    reflection_index: HashMap<Reflection, u32>,
    shader_index: HashMap<(String, String), u32>,
}

/// Zero bytes that pad blobs to 8-byte offsets.
const PADDING: [u8; 8] = [0; 8];

impl<'a> ArchiveWriter<'a> {
    pub fn new() -> Self {
        let mut w = ArchiveWriter::default();
        w.manifest.kiln_version = crate::VERSION.to_string();
        w
    }

    /// Records the naga version the artifacts were produced with (shown by `kiln inspect`).
    pub fn set_naga_version(&mut self, version: &str) {
        self.manifest.naga_version = version.to_string();
    }

    /// Adds a (shader, level) record; returns its index. Adding the same pair twice returns
    /// the first index.
    pub fn add_shader(&mut self, record: ShaderRecord) -> u32 {
        let key = (record.name.clone(), record.level.clone());
        if let Some(&i) = self.shader_index.get(&key) {
            return i;
        }
        let i = self.manifest.shaders.len() as u32;
        self.manifest.shaders.push(record);
        self.shader_index.insert(key, i);
        i
    }

    /// Adds a blob, returning the id of an identical blob already added where there is one.
    pub fn add_blob(&mut self, bytes: &[u8]) -> BlobId {
        let hash = blake3::hash(bytes);
        if let Some(&id) = self.blob_index.get(&hash) {
            return id;
        }
        self.push_blob(Cow::Owned(bytes.to_vec()), hash)
    }

    /// [`ArchiveWriter::add_blob`] for a blob whose blake3 `hash` the caller computed (on
    /// another thread, say), borrowed until the archive is written.
    pub fn add_blob_ref(&mut self, bytes: &'a [u8], hash: blake3::Hash) -> BlobId {
        debug_assert_eq!(hash, blake3::hash(bytes));
        if let Some(&id) = self.blob_index.get(&hash) {
            return id;
        }
        self.push_blob(Cow::Borrowed(bytes), hash)
    }

    fn push_blob(&mut self, bytes: Cow<'a, [u8]>, hash: blake3::Hash) -> BlobId {
        self.blob_section_len = self.blob_section_len.next_multiple_of(8);
        let id = BlobId(self.manifest.blobs.len() as u32);
        self.manifest.blobs.push(BlobRecord { offset: self.blob_section_len, len: bytes.len() as u64 });
        self.blob_section_len += bytes.len() as u64;
        self.blobs.push(bytes);
        self.blob_index.insert(hash, id);
        id
    }

    pub fn add_reflection(&mut self, reflection: &Reflection) -> u32 {
        if let Some(&i) = self.reflection_index.get(reflection) {
            return i;
        }
        let i = self.manifest.reflections.len() as u32;
        self.manifest.reflections.push(reflection.clone());
        self.reflection_index.insert(reflection.clone(), i);
        i
    }

    pub fn add_permutation(&mut self, record: PermutationRecord) {
        self.manifest.permutations.push(record);
    }

    /// Number of distinct blobs so far.
    pub fn blob_count(&self) -> usize {
        self.manifest.blobs.len()
    }

    /// The blob section as pieces: each blob after the zero padding that aligns it.
    fn blob_pieces(&self) -> Vec<&[u8]> {
        let mut pieces = Vec::with_capacity(self.blobs.len() * 2);
        let mut at = 0u64;
        for blob in &self.blobs {
            let pad = (at.next_multiple_of(8) - at) as usize;
            if pad > 0 {
                pieces.push(&PADDING[..pad]);
            }
            pieces.push(&blob[..]);
            at += (pad + blob.len()) as u64;
        }
        debug_assert_eq!(at, self.blob_section_len);
        pieces
    }

    /// The manifest as JSON, padded to 8 bytes.
    fn manifest_bytes(&self) -> Vec<u8> {
        let mut manifest = serde_json::to_vec(&self.manifest).expect("manifest serializes");
        while manifest.len() % 8 != 0 {
            manifest.push(b' ');
        }
        manifest
    }

    /// The header of an archive whose body (manifest, then blobs) has blake3 `checksum`.
    fn header(&self, manifest_len: usize, checksum: blake3::Hash) -> Vec<u8> {
        let mut header = Vec::with_capacity(HEADER_LEN);
        header.extend_from_slice(&MAGIC);
        header.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        header.extend_from_slice(&0u32.to_le_bytes());
        header.extend_from_slice(&(manifest_len as u64).to_le_bytes());
        header.extend_from_slice(&self.blob_section_len.to_le_bytes());
        header.extend_from_slice(checksum.as_bytes());
        debug_assert_eq!(header.len(), HEADER_LEN);
        header
    }

    /// The whole archive as bytes.
    pub fn to_bytes(&self) -> Vec<u8> {
        let manifest = self.manifest_bytes();
        let mut body: Vec<&[u8]> = vec![&manifest];
        body.extend(self.blob_pieces());
        let mut out = self.header(manifest.len(), checksum(&body));
        out.reserve(manifest.len() + self.blob_section_len as usize);
        body.iter().for_each(|b| out.extend_from_slice(b));
        out
    }

    /// Writes the archive to `path` atomically: a temporary file in the same folder, synced,
    /// then renamed over `path`. A reader never sees a half-written archive.
    pub fn write(&self, path: &Path) -> Result<(), ArchiveError> {
        self.write_impl(path, true)
    }

    /// [`ArchiveWriter::write`] without the fsync: still atomic for readers (temporary file
    /// and rename), not durable across a power loss, like a compiler's outputs. A truncated
    /// file after a crash is reported by [`Archive::open`] and rebuilt.
    pub fn write_unsynced(&self, path: &Path) -> Result<(), ArchiveError> {
        self.write_impl(path, false)
    }

    fn write_impl(&self, path: &Path, sync: bool) -> Result<(), ArchiveError> {
        // Written in pieces, never copied into one buffer: archives can be large. The body
        // goes first, after room for the header, while its checksum is computed (on another
        // thread where there is one); then the header.
        let manifest = self.manifest_bytes();
        let mut body: Vec<&[u8]> = vec![&manifest];
        body.extend(self.blob_pieces());
        write_atomic_with(path, sync, |f| {
            use std::io::{Seek, SeekFrom};
            use std::os::unix::fs::FileExt;
            f.seek(SeekFrom::Start(HEADER_LEN as u64))?;
            let (sum, written) = join(|| checksum(&body), || write_all_vectored(f, &body));
            written?;
            f.write_all_at(&self.header(manifest.len(), sum), 0)
        })
        .map_err(|source| ArchiveError::Write { path: path.to_path_buf(), source })
    }
}

/// blake3 of the concatenation of `pieces`.
fn checksum(pieces: &[&[u8]]) -> blake3::Hash {
    let mut h = blake3::Hasher::new();
    for piece in pieces {
        h.update(piece);
    }
    h.finalize()
}

/// Both closures, in parallel where the compiler's thread pool is built in.
fn join<A: Send, B: Send>(a: impl FnOnce() -> A + Send, b: impl FnOnce() -> B + Send) -> (A, B) {
    #[cfg(feature = "compiler")]
    return rayon::join(a, b);
    #[cfg(not(feature = "compiler"))]
    return (a(), b());
}

/// Writes `bytes` to `path` through a uniquely named temporary file and a rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    write_atomic_impl(path, &[bytes], true)
}

/// [`write_atomic`] without syncing the temporary file before the rename.
pub fn write_atomic_unsynced(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    write_atomic_impl(path, &[bytes], false)
}

/// Writes the concatenation of `pieces` through a temporary file and a rename.
fn write_atomic_impl(path: &Path, pieces: &[&[u8]], sync: bool) -> std::io::Result<()> {
    write_atomic_with(path, sync, |f| write_all_vectored(f, pieces))
}

/// Creates a uniquely named temporary file beside `path`, lets `write` fill it, syncs it
/// when asked, then renames it to `path`; on any error the temporary file is removed.
fn write_atomic_with(
    path: &Path,
    sync: bool,
    write: impl FnOnce(&mut File) -> std::io::Result<()>,
) -> std::io::Result<()> {
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
    let tmp = dir.join(format!(".{name}.{}.{nanos}.{n}.tmp", std::process::id()));
    let result = (|| {
        let mut f = File::create(&tmp)?;
        write(&mut f)?;
        if sync {
            f.sync_all()?;
        }
        std::fs::rename(&tmp, path)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
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

enum Bytes {
    Static(&'static [u8]),
    Owned(Vec<u8>),
    Mapped(memmap2::Mmap),
}

impl Bytes {
    fn as_slice(&self) -> &[u8] {
        match self {
            Bytes::Static(b) => b,
            Bytes::Owned(v) => v,
            Bytes::Mapped(m) => m,
        }
    }
}

/// A loaded archive. The manifest is parsed at open; blobs stay where they are (in the
/// memory map or the embedded bytes) until an artifact is asked for.
pub struct Archive {
    bytes: Bytes,
    manifest: Manifest,
    blobs_start: usize,
    by_name: HashMap<String, u32>,
    by_shader: HashMap<(String, String), u32>,
    by_id: HashMap<u128, u32>,
}

/// The id of a permutation: the 128-bit FNV-1a hash of the shader's name, a 0 byte, the
/// level's name, a 0 byte, then each dimension's value (an enum's index) as 8 little-endian
/// bytes, in declared order. Typed keys compute the same hash from their fields.
pub fn permutation_id(shader: &str, level: &str, values: &[i64]) -> u128 {
    const OFFSET: u128 = 0x6c62272e07bb014262b821756295c58d;
    const PRIME: u128 = 0x0000000001000000000000000000013B;
    let mut h = OFFSET;
    let mut eat = |bytes: &[u8]| {
        for b in bytes {
            h ^= u128::from(*b);
            h = h.wrapping_mul(PRIME);
        }
    };
    eat(shader.as_bytes());
    eat(&[0]);
    eat(level.as_bytes());
    eat(&[0]);
    for v in values {
        eat(&v.to_le_bytes());
    }
    h
}

/// A permutation found in an archive.
#[derive(Clone, Copy)]
pub struct PermutationRef<'a> {
    archive: &'a Archive,
    record: &'a PermutationRecord,
}

impl<'a> PermutationRef<'a> {
    pub fn name(&self) -> &'a str {
        &self.record.name
    }
    pub fn shader(&self) -> &'a ShaderRecord {
        &self.archive.manifest.shaders[self.record.shader as usize]
    }
    pub fn values(&self) -> &'a [i64] {
        &self.record.values
    }
    pub fn reflection(&self) -> &'a Reflection {
        &self.archive.manifest.reflections[self.record.reflection as usize]
    }
    pub fn targets(&self) -> impl Iterator<Item = Target> + 'a {
        self.record.artifacts.iter().map(|(t, _)| *t)
    }
    pub fn blob_id(&self, target: Target) -> Option<BlobId> {
        self.record.artifacts.iter().find(|(t, _)| *t == target).map(|(_, b)| *b)
    }
    /// The artifact for `target`, borrowed from the archive's bytes.
    pub fn artifact(&self, target: Target) -> Option<&'a [u8]> {
        self.blob_id(target).map(|id| self.archive.blob(id))
    }
    pub fn record(&self) -> &'a PermutationRecord {
        self.record
    }
}

/// A near miss for a name that is not in the archive.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Near {
    pub name: String,
    /// `DIM: wanted -> available` for each dimension that differs.
    pub differences: Vec<String>,
}

/// The answer to a lookup by name.
pub enum Lookup<'a> {
    Found(PermutationRef<'a>),
    /// Not there; the closest permutations, best first.
    Missing(Vec<Near>),
}

impl Archive {
    /// Memory-maps an archive file and verifies it.
    pub fn open(path: &Path) -> Result<Archive, ArchiveError> {
        let io = |source| ArchiveError::Io { path: path.to_path_buf(), source };
        let file = File::open(path).map_err(io)?;
        // SAFETY: the map is read-only and private to this process. Archives are replaced by
        // rename, never rewritten in place, so the mapped file does not change under us.
        let map = unsafe { memmap2::Mmap::map(&file) }.map_err(io)?;
        Archive::from_source(Bytes::Mapped(map))
    }

    /// An archive embedded with `include_bytes!`.
    pub fn from_static(bytes: &'static [u8]) -> Result<Archive, ArchiveError> {
        Archive::from_source(Bytes::Static(bytes))
    }

    pub fn from_vec(bytes: Vec<u8>) -> Result<Archive, ArchiveError> {
        Archive::from_source(Bytes::Owned(bytes))
    }

    fn from_source(bytes: Bytes) -> Result<Archive, ArchiveError> {
        let data = bytes.as_slice();
        if data.len() < HEADER_LEN {
            return Err(ArchiveError::TooShort { len: data.len() });
        }
        let magic: [u8; 8] = data[0..8].try_into().unwrap();
        if magic != MAGIC {
            return Err(ArchiveError::BadMagic { found: magic });
        }
        let u32_at = |o: usize| u32::from_le_bytes(data[o..o + 4].try_into().unwrap());
        let u64_at = |o: usize| u64::from_le_bytes(data[o..o + 8].try_into().unwrap());
        let version = u32_at(8);
        if version != FORMAT_VERSION {
            return Err(ArchiveError::Version { found: version });
        }
        let flags = u32_at(12);
        if flags != 0 {
            return Err(ArchiveError::Manifest(format!("unknown header flags {flags:#x}")));
        }
        let manifest_len = u64_at(16);
        let blobs_len = u64_at(24);
        let expected = (HEADER_LEN as u64).checked_add(manifest_len).and_then(|v| v.checked_add(blobs_len));
        let actual = data.len() as u64;
        match expected {
            Some(e) if e == actual => {}
            Some(e) => return Err(ArchiveError::Truncated { expected: e, actual }),
            None => return Err(ArchiveError::Manifest("section lengths overflow".into())),
        }
        let checksum: [u8; 32] = data[32..64].try_into().unwrap();
        let computed = blake3::hash(&data[HEADER_LEN..]);
        if computed.as_bytes() != &checksum {
            return Err(ArchiveError::Checksum {
                expected: blake3::Hash::from_bytes(checksum).to_hex().to_string(),
                actual: computed.to_hex().to_string(),
            });
        }
        let manifest_end = HEADER_LEN + manifest_len as usize;
        let manifest: Manifest = serde_json::from_slice(&data[HEADER_LEN..manifest_end])
            .map_err(|e| ArchiveError::Manifest(e.to_string()))?;
        validate(&manifest, blobs_len)?;
        let by_name = manifest.permutations.iter().enumerate().map(|(i, p)| (p.name.clone(), i as u32)).collect();
        let by_shader =
            manifest.shaders.iter().enumerate().map(|(i, s)| ((s.name.clone(), s.level.clone()), i as u32)).collect();
        let by_id = manifest
            .permutations
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let s = &manifest.shaders[p.shader as usize];
                (permutation_id(&s.name, &s.level, &p.values), i as u32)
            })
            .collect();
        Ok(Archive { bytes, manifest, blobs_start: manifest_end, by_name, by_shader, by_id })
    }

    pub fn kiln_version(&self) -> &str {
        &self.manifest.kiln_version
    }
    pub fn naga_version(&self) -> &str {
        &self.manifest.naga_version
    }
    /// Size of the whole archive in bytes.
    pub fn len(&self) -> usize {
        self.bytes.as_slice().len()
    }
    pub fn is_empty(&self) -> bool {
        self.manifest.permutations.is_empty()
    }
    pub fn shaders(&self) -> &[ShaderRecord] {
        &self.manifest.shaders
    }
    pub fn blob_count(&self) -> usize {
        self.manifest.blobs.len()
    }
    pub fn reflections(&self) -> &[Reflection] {
        &self.manifest.reflections
    }

    pub fn permutations(&self) -> impl Iterator<Item = PermutationRef<'_>> {
        self.manifest.permutations.iter().map(move |record| PermutationRef { archive: self, record })
    }

    /// The blob's bytes. Ids come from this archive's records, which were bounds-checked at
    /// open; an id from elsewhere that is out of range gives an empty slice.
    pub fn blob(&self, id: BlobId) -> &[u8] {
        match self.manifest.blobs.get(id.0 as usize) {
            Some(b) => {
                let start = self.blobs_start + b.offset as usize;
                &self.bytes.as_slice()[start..start + b.len as usize]
            }
            None => &[],
        }
    }

    /// O(1) lookup by canonical name.
    pub fn get(&self, name: &str) -> Option<PermutationRef<'_>> {
        let i = *self.by_name.get(name)?;
        Some(PermutationRef { archive: self, record: &self.manifest.permutations[i as usize] })
    }

    /// O(1) lookup by [`permutation_id`], the id that typed keys (`Key::permutation_id`, see
    /// [`crate::bindings`]) compute from their fields without formatting a name.
    pub fn get_by_id(&self, id: u128) -> Option<PermutationRef<'_>> {
        let i = *self.by_id.get(&id)?;
        Some(PermutationRef { archive: self, record: &self.manifest.permutations[i as usize] })
    }

    /// The (shader, level) record, if the archive has that pair.
    pub fn shader(&self, shader: &str, level: &str) -> Option<&ShaderRecord> {
        self.by_shader.get(&(shader.to_string(), level.to_string())).map(|&i| &self.manifest.shaders[i as usize])
    }

    /// Builds the canonical name of (shader, level, values) from the shader's dimension
    /// order. Values may be given in any order; every dimension must be given, by value or
    /// (for an enum) by label. Returns an error message naming what is wrong.
    pub fn canonical_name(&self, shader: &str, level: &str, values: &[(&str, &str)]) -> Result<String, String> {
        let record = self.shader(shader, level).ok_or_else(|| {
            let levels: Vec<&str> =
                self.manifest.shaders.iter().filter(|s| s.name == shader).map(|s| s.level.as_str()).collect();
            if levels.is_empty() {
                format!("no shader named `{shader}` in the archive")
            } else {
                format!("shader `{shader}` has no level `{level}` in the archive (it has: {})", levels.join(", "))
            }
        })?;
        for (dim, _) in values {
            if !record.dimensions.iter().any(|d| d.name == *dim) {
                let names: Vec<&str> = record.dimensions.iter().map(|d| d.name.as_str()).collect();
                return Err(format!(
                    "shader `{shader}` has no dimension `{dim}` (its dimensions: {})",
                    names.join(", ")
                ));
            }
        }
        let mut parts = Vec::with_capacity(record.dimensions.len());
        for d in &record.dimensions {
            let value = values
                .iter()
                .rev()
                .find(|(n, _)| *n == d.name)
                .map(|(_, v)| *v)
                .ok_or_else(|| format!("no value given for dimension `{}` of `{shader}`", d.name))?;
            parts.push(format!("{}={}", d.name, display_value(d, value)));
        }
        Ok(format!("{shader}@{level}{{{}}}", parts.join(",")))
    }

    /// Lookup by name with near misses: for a name that is not in the archive, the closest
    /// permutations of the same shader (fewest differing dimensions), with the differences.
    pub fn lookup(&self, name: &str) -> Lookup<'_> {
        if let Some(p) = self.get(name) {
            return Lookup::Found(p);
        }
        Lookup::Missing(self.nearest(name, 5))
    }

    /// The `limit` permutations closest to `name`.
    pub fn nearest(&self, name: &str, limit: usize) -> Vec<Near> {
        let wanted = parse_name(name);
        let mut scored: Vec<(usize, Near)> = Vec::new();
        for p in &self.manifest.permutations {
            let have = parse_name(&p.name);
            let mut diffs = Vec::new();
            let mut score = 0usize;
            if have.shader != wanted.shader {
                score += 100 + edit_distance(&have.shader, &wanted.shader);
                diffs.push(format!("shader: {} -> {}", wanted.shader, have.shader));
            }
            if have.level != wanted.level {
                score += 10;
                diffs.push(format!("level: {} -> {}", wanted.level, have.level));
            }
            for (k, v) in &have.dims {
                match wanted.dims.iter().find(|(wk, _)| wk == k) {
                    Some((_, wv)) if wv == v => {}
                    Some((_, wv)) => {
                        score += 1;
                        diffs.push(format!("{k}: {wv} -> {v}"));
                    }
                    None => {
                        score += 1;
                        diffs.push(format!("{k}: (missing) -> {v}"));
                    }
                }
            }
            for (k, wv) in &wanted.dims {
                if !have.dims.iter().any(|(hk, _)| hk == k) {
                    score += 1;
                    diffs.push(format!("{k}: {wv} -> (no such dimension)"));
                }
            }
            scored.push((score, Near { name: p.name.clone(), differences: diffs }));
        }
        scored.sort_by(|a, b| a.0.cmp(&b.0).then_with(|| a.1.name.cmp(&b.1.name)));
        scored.into_iter().take(limit).map(|(_, n)| n).collect()
    }
}

fn display_value(d: &DimensionRecord, value: &str) -> String {
    if d.labels.is_empty() {
        return value.to_string();
    }
    if d.labels.iter().any(|l| l == value) {
        return value.to_string();
    }
    match value.parse::<usize>() {
        Ok(i) if i < d.labels.len() => d.labels[i].clone(),
        _ => value.to_string(),
    }
}

struct ParsedName {
    shader: String,
    level: String,
    dims: Vec<(String, String)>,
}

fn parse_name(name: &str) -> ParsedName {
    let (head, rest) = match name.find('{') {
        Some(i) => (&name[..i], name[i + 1..].trim_end_matches('}')),
        None => (name, ""),
    };
    let (shader, level) = match head.split_once('@') {
        Some((s, l)) => (s, l),
        None => (head, ""),
    };
    let dims = rest
        .split(',')
        .filter(|s| !s.trim().is_empty())
        .map(|kv| match kv.split_once('=') {
            Some((k, v)) => (k.trim().to_string(), v.trim().to_string()),
            None => (kv.trim().to_string(), String::new()),
        })
        .collect();
    ParsedName { shader: shader.trim().to_string(), level: level.trim().to_string(), dims }
}

fn edit_distance(a: &str, b: &str) -> usize {
    let b: Vec<char> = b.chars().collect();
    let mut prev: Vec<usize> = (0..=b.len()).collect();
    for (i, ca) in a.chars().enumerate() {
        let mut cur = vec![i + 1; b.len() + 1];
        for (j, cb) in b.iter().enumerate() {
            cur[j + 1] = (prev[j] + usize::from(ca != *cb)).min(prev[j + 1] + 1).min(cur[j] + 1);
        }
        prev = cur;
    }
    prev[b.len()]
}

/// Checks every index and range in the manifest, so later accessors cannot go out of bounds.
fn validate(m: &Manifest, blobs_len: u64) -> Result<(), ArchiveError> {
    let bad = |msg: String| Err(ArchiveError::Manifest(msg));
    for (i, b) in m.blobs.iter().enumerate() {
        match b.offset.checked_add(b.len) {
            Some(end) if end <= blobs_len => {}
            _ => return bad(format!("blob {i} lies outside the blob section")),
        }
    }
    for p in &m.permutations {
        let Some(shader) = m.shaders.get(p.shader as usize) else {
            return bad(format!("permutation `{}` names shader {} of {}", p.name, p.shader, m.shaders.len()));
        };
        if p.values.len() != shader.dimensions.len() {
            return bad(format!(
                "permutation `{}` has {} values for {} dimensions",
                p.name,
                p.values.len(),
                shader.dimensions.len()
            ));
        }
        if p.reflection as usize >= m.reflections.len() {
            return bad(format!("permutation `{}` names a missing reflection", p.name));
        }
        for (t, blob) in &p.artifacts {
            if blob.0 as usize >= m.blobs.len() {
                return bad(format!("permutation `{}` names a missing {t} blob", p.name));
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::archive::{Binding, BindingKind};

    fn sample() -> Vec<u8> {
        let mut w = ArchiveWriter::new();
        w.set_naga_version("30.0.1");
        let s = w.add_shader(ShaderRecord {
            name: "Lit".into(),
            level: "sm5".into(),
            entry: "main_ps".into(),
            stage: Stage::Fragment,
            dimensions: vec![
                DimensionRecord { name: "FULLY_ROUGH".into(), labels: vec![] },
                DimensionRecord { name: "MODE".into(), labels: vec!["OPAQUE".into(), "MASKED".into()] },
            ],
        });
        let r = w.add_reflection(&Reflection {
            entry: "main_ps".into(),
            stage: Stage::Fragment,
            bindings: vec![Binding {
                group: 0,
                binding: 0,
                name: Some("u".into()),
                kind: BindingKind::UniformBuffer { min_size: 16 },
            }],
            vertex_inputs: vec![],
            color_outputs: vec![],
            workgroup_size: None,
        });
        for rough in 0..2 {
            for mode in 0..2 {
                let wgsl = w.add_blob(format!("// wgsl {rough}").as_bytes());
                let spv = w.add_blob(&[3, 2, 0x23, 7, rough as u8]);
                let label = ["OPAQUE", "MASKED"][mode];
                w.add_permutation(PermutationRecord {
                    name: format!("Lit@sm5{{FULLY_ROUGH={rough},MODE={label}}}"),
                    shader: s,
                    values: vec![rough, mode as i64],
                    reflection: r,
                    artifacts: vec![(Target::Wgsl, wgsl), (Target::Spirv, spv)],
                });
            }
        }
        w.to_bytes()
    }

    #[test]
    fn round_trip_dedups_blobs_and_finds_by_name() {
        let bytes = sample();
        let a = Archive::from_vec(bytes).unwrap();
        assert_eq!(a.permutations().count(), 4);
        assert_eq!(a.blob_count(), 4, "two wgsl blobs and two spir-v blobs, each shared by two permutations");
        let p = a.get("Lit@sm5{FULLY_ROUGH=1,MODE=MASKED}").unwrap();
        assert_eq!(p.artifact(Target::Wgsl).unwrap(), b"// wgsl 1");
        assert_eq!(p.artifact(Target::Spirv).unwrap(), &[3, 2, 0x23, 7, 1]);
        assert!(p.artifact(Target::Msl).is_none());
        assert_eq!(p.reflection().bindings.len(), 1);
        assert_eq!(a.naga_version(), "30.0.1");
    }

    #[test]
    fn canonical_name_accepts_labels_indices_and_any_order() {
        let a = Archive::from_vec(sample()).unwrap();
        let n = a.canonical_name("Lit", "sm5", &[("MODE", "1"), ("FULLY_ROUGH", "0")]).unwrap();
        assert_eq!(n, "Lit@sm5{FULLY_ROUGH=0,MODE=MASKED}");
        assert!(a.get(&n).is_some());
        let e = a.canonical_name("Lit", "sm5", &[("MODE", "1")]).unwrap_err();
        assert!(e.contains("FULLY_ROUGH"), "{e}");
        let e = a.canonical_name("Lit", "es3_1", &[]).unwrap_err();
        assert!(e.contains("has no level `es3_1`"), "{e}");
    }

    #[test]
    fn missing_name_lists_nearest_with_differences() {
        let a = Archive::from_vec(sample()).unwrap();
        match a.lookup("Lit@sm5{FULLY_ROUGH=2,MODE=MASKED}") {
            Lookup::Found(_) => panic!("found a name that is not there"),
            Lookup::Missing(near) => {
                assert_eq!(near[0].differences, vec!["FULLY_ROUGH: 2 -> 0".to_string()]);
                assert!(near[0].name.contains("MODE=MASKED"));
            }
        }
    }

    #[test]
    fn truncation_is_an_error_at_every_length() {
        let bytes = sample();
        for len in [0, 1, 8, 63, 64, 65, bytes.len() / 2, bytes.len() - 1] {
            let err = Archive::from_vec(bytes[..len].to_vec()).err().expect("truncated archive accepted");
            let msg = err.to_string();
            assert!(msg.contains("truncated") || msg.contains("shorter than"), "{len}: {msg}");
        }
    }

    #[test]
    fn every_flipped_byte_is_detected() {
        let bytes = sample();
        for i in 0..bytes.len() {
            let mut b = bytes.clone();
            b[i] ^= 0x40;
            assert!(Archive::from_vec(b).is_err(), "flipping byte {i} went unnoticed");
        }
    }

    #[test]
    fn other_format_version_is_named() {
        let mut bytes = sample();
        bytes[8..12].copy_from_slice(&7u32.to_le_bytes());
        let msg = Archive::from_vec(bytes).err().unwrap().to_string();
        assert!(msg.contains("format version 7 is not supported"), "{msg}");
    }

    #[test]
    fn atomic_write_then_mmap_open() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sub/shaders.kpak");
        let mut w = ArchiveWriter::new();
        w.add_blob(b"x");
        w.write(&path).unwrap();
        let a = Archive::open(&path).unwrap();
        assert_eq!(a.blob(BlobId(0)), b"x");
        let leftovers: Vec<_> = std::fs::read_dir(path.parent().unwrap()).unwrap().collect();
        assert_eq!(leftovers.len(), 1, "no temporary file left behind");
    }
}
