//! Reading an archive: open (header and manifest checked, O(manifest)), lookups by name,
//! and blobs checked and decompressed on first use.

use std::borrow::Cow;
use std::cell::RefCell;
use std::collections::HashMap;
use std::fs::File;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::OnceLock;

use zstd::zstd_safe::{DCtx, DDict};

use super::format::{
    decode_artifact, header_checksum, ArchiveError, BlobId, DictionaryRecord, DimensionRecord, Entry, ManifestCounts,
    ManifestLayout, PermutationRecord, Record, Sections, ShaderRecord, Tables, ARTIFACT_LEN, CODEC_STORED, CODEC_ZSTD,
    CODEC_ZSTD_DICT, DICTIONARY_LEN, ENTRY_LEN, FORMAT_VERSION, HEADER_LEN, ID_LEN, MAGIC, MAX_ARTIFACT_LEN,
    NO_DICTIONARY, RECORD_LEN, VALUE_LEN,
};
use super::{Reflection, Target};

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

/// A loaded archive. The header and manifest are checked and parsed at open; blobs stay
/// where they are (in the memory map or the embedded bytes) until an artifact is asked for,
/// and are checked then, once each. `Send + Sync`.
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

pub struct Archive {
    bytes: Bytes,
    blobs_start: usize,
    dictionaries_start: usize,
    table_start: usize,
    blob_count: usize,
    /// Where the manifest's parts lie in `bytes` (absolute offsets).
    records_start: usize,
    ids_start: usize,
    values_start: usize,
    artifacts_start: usize,
    names_start: usize,
    permutation_count: usize,
    tables: Tables,
    dictionaries: Vec<DictionaryRecord>,
    /// Each permutation's values, decoded on first use.
    values: Box<[OnceLock<Box<[i64]>>]>,
    /// Whether each blob has passed its checksum.
    verified: Box<[AtomicBool]>,
    /// Each dictionary, loaded (and checked) on first use.
    ddicts: Box<[OnceLock<Result<DDict<'static>, String>>]>,
    by_shader: HashMap<(String, String), u32>,
}

/// Sizes of one blob.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BlobInfo {
    /// Bytes of the artifact.
    pub raw_len: u64,
    /// Bytes it takes in the archive.
    pub stored_len: u64,
    /// Whether it is zstd-compressed.
    pub compressed: bool,
    /// Whether it was compressed with its target's dictionary.
    pub dictionary: bool,
}

/// A permutation found in an archive: an index into its manifest, whose fields are read in
/// place.
#[derive(Clone, Copy)]
pub struct PermutationRef<'a> {
    archive: &'a Archive,
    index: u32,
    record: Record,
}

impl<'a> PermutationRef<'a> {
    pub fn name(&self) -> &'a str {
        self.archive.name_of(&self.record)
    }
    pub fn shader(&self) -> &'a ShaderRecord {
        &self.archive.tables.shaders[self.record.shader as usize]
    }
    /// Index of its shader in [`Archive::shaders`].
    pub fn shader_index(&self) -> u32 {
        self.record.shader
    }
    pub fn values(&self) -> &'a [i64] {
        let archive = self.archive;
        archive.values[self.index as usize].get_or_init(|| {
            let n = archive.tables.shaders[self.record.shader as usize].dimensions.len();
            let start = archive.values_start + self.record.first_value as usize * VALUE_LEN;
            archive.bytes.as_slice()[start..start + n * VALUE_LEN]
                .chunks_exact(VALUE_LEN)
                .map(|b| i64::from_le_bytes(b.try_into().unwrap()))
                .collect()
        })
    }
    pub fn reflection(&self) -> &'a Reflection {
        &self.archive.tables.reflections[self.record.reflection as usize]
    }
    /// Index of its reflection in [`Archive::reflections`].
    pub fn reflection_index(&self) -> u32 {
        self.record.reflection
    }
    /// Its artifacts' targets and blobs, in the level's order of targets.
    fn artifacts(&self) -> impl Iterator<Item = (Target, BlobId)> + 'a {
        let start = self.archive.artifacts_start + self.record.first_artifact as usize * ARTIFACT_LEN;
        let bytes = &self.archive.bytes.as_slice()[start..start + self.record.artifact_count as usize * ARTIFACT_LEN];
        // Every artifact was checked at open.
        bytes.chunks_exact(ARTIFACT_LEN).filter_map(super::format::decode_artifact)
    }
    pub fn targets(&self) -> impl Iterator<Item = Target> + 'a {
        self.artifacts().map(|(t, _)| t)
    }
    pub fn blob_id(&self, target: Target) -> Option<BlobId> {
        self.artifacts().find(|(t, _)| *t == target).map(|(_, b)| b)
    }
    /// The artifact for `target` (`None` when the permutation has none), decompressed, and
    /// checked against its checksum the first time it is read. A corrupted blob is an error
    /// naming this permutation and the target.
    pub fn artifact(&self, target: Target) -> Result<Option<Cow<'a, [u8]>>, ArchiveError> {
        let Some(id) = self.blob_id(target) else { return Ok(None) };
        self.archive.blob(id).map(Some).map_err(|message| ArchiveError::Blob {
            permutation: self.name().to_string(),
            target,
            message,
        })
    }
    /// Its record, decoded (a copy: the manifest is read in place).
    pub fn record(&self) -> PermutationRecord {
        PermutationRecord {
            name: self.name().to_string(),
            shader: self.record.shader,
            values: self.values().to_vec(),
            reflection: self.record.reflection,
            artifacts: self.artifacts().collect(),
        }
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

thread_local! {
    /// One decompression context per thread, shared by every archive.
    static DCTX: RefCell<Option<DCtx<'static>>> = const { RefCell::new(None) };
}

/// What a path that is not a regular file is, for the error message.
fn file_kind(meta: &std::fs::Metadata) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    let t = meta.file_type();
    if t.is_dir() {
        "directory"
    } else if t.is_fifo() {
        "FIFO"
    } else if t.is_socket() {
        "socket"
    } else if t.is_char_device() {
        "character device"
    } else if t.is_block_device() {
        "block device"
    } else {
        "special file"
    }
}

impl Archive {
    /// Memory-maps an archive file and checks its header and manifest. A path that is not a
    /// regular file (a directory, a FIFO, a device) is an error, found without blocking.
    pub fn open(path: &Path) -> Result<Archive, ArchiveError> {
        let io = |source| ArchiveError::Io { path: path.to_path_buf(), source };
        let not_file =
            |meta: &std::fs::Metadata| ArchiveError::NotAFile { path: path.to_path_buf(), kind: file_kind(meta) };
        let meta = std::fs::metadata(path).map_err(io)?;
        if !meta.is_file() {
            return Err(not_file(&meta));
        }
        let mut options = std::fs::OpenOptions::new();
        options.read(true);
        #[cfg(target_os = "linux")]
        {
            // O_NONBLOCK: were the path swapped for a FIFO after the check above, opening it
            // still does not wait for a writer.
            use std::os::unix::fs::OpenOptionsExt;
            options.custom_flags(0o4000);
        }
        let file: File = options.open(path).map_err(io)?;
        let meta = file.metadata().map_err(io)?;
        if !meta.is_file() {
            return Err(not_file(&meta));
        }
        if meta.len() == 0 {
            return Err(ArchiveError::TooShort { len: 0 });
        }
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
        if data.len() >= 12 && data[0..8] == MAGIC {
            // The version first: an archive of another version may have another header size.
            let version = u32::from_le_bytes(data[8..12].try_into().unwrap());
            if version != FORMAT_VERSION {
                return Err(ArchiveError::Version { found: version });
            }
        }
        if data.len() < HEADER_LEN {
            return Err(ArchiveError::TooShort { len: data.len() });
        }
        let magic: [u8; 8] = data[0..8].try_into().unwrap();
        if magic != MAGIC {
            return Err(ArchiveError::BadMagic { found: magic });
        }
        let u32_at = |o: usize| u32::from_le_bytes(data[o..o + 4].try_into().unwrap());
        let u64_at = |o: usize| u64::from_le_bytes(data[o..o + 8].try_into().unwrap());
        let flags = u32_at(12);
        if flags != 0 {
            return Err(ArchiveError::Manifest(format!("unknown header flags {flags:#x}")));
        }
        if data[48..96].iter().any(|&b| b != 0) {
            return Err(ArchiveError::Manifest("reserved header bytes are not zero".into()));
        }
        let sections = Sections {
            blobs_len: u64_at(16),
            dictionaries_len: u64_at(24),
            manifest_len: u64_at(32),
            blob_count: u64_at(40),
        };
        let layout = sections.layout().ok_or_else(|| ArchiveError::Manifest("section lengths overflow".into()))?;
        let actual = data.len() as u64;
        if layout.end != actual {
            return Err(ArchiveError::Truncated { expected: layout.end, actual });
        }
        // The padding between sections is covered by no checksum: it must be zero.
        let pads = [
            (layout.blobs + sections.blobs_len, layout.dictionaries),
            (layout.dictionaries + sections.dictionaries_len, layout.manifest),
            (layout.manifest + sections.manifest_len, layout.table),
        ];
        if pads.iter().any(|&(from, to)| data[from as usize..to as usize].iter().any(|&b| b != 0)) {
            return Err(ArchiveError::Manifest("padding between sections is not zero".into()));
        }
        let manifest_bytes = &data[layout.manifest as usize..(layout.manifest + sections.manifest_len) as usize];
        let table = &data[layout.table as usize..];
        let expected: [u8; 32] = data[96..128].try_into().unwrap();
        let computed = header_checksum(&data[..96], manifest_bytes, table);
        if computed.as_bytes() != &expected {
            return Err(ArchiveError::Checksum {
                expected: blake3::Hash::from_bytes(expected).to_hex().to_string(),
                actual: computed.to_hex().to_string(),
            });
        }
        let m = read_manifest(data, layout.manifest as usize, sections.manifest_len as usize, &sections)?;
        validate_table(table, &sections, m.dictionaries.len())?;
        let by_shader =
            m.tables.shaders.iter().enumerate().map(|(i, s)| ((s.name.clone(), s.level.clone()), i as u32)).collect();
        let blob_count = sections.blob_count as usize;
        let base = layout.manifest as usize;
        Ok(Archive {
            verified: (0..blob_count).map(|_| AtomicBool::new(false)).collect(),
            ddicts: (0..m.dictionaries.len()).map(|_| OnceLock::new()).collect(),
            values: (0..m.counts.permutations).map(|_| OnceLock::new()).collect(),
            blobs_start: layout.blobs as usize,
            dictionaries_start: layout.dictionaries as usize,
            table_start: layout.table as usize,
            blob_count,
            records_start: base + m.layout.records as usize,
            ids_start: base + m.layout.ids as usize,
            values_start: base + m.layout.values as usize,
            artifacts_start: base + m.layout.artifacts as usize,
            names_start: base + m.layout.names as usize,
            permutation_count: m.counts.permutations as usize,
            tables: m.tables,
            dictionaries: m.dictionaries,
            by_shader,
            bytes,
        })
    }

    /// The record of permutation `index` (< the permutation count).
    fn record(&self, index: usize) -> Record {
        let at = self.records_start + index * RECORD_LEN;
        Record::decode(&self.bytes.as_slice()[at..at + RECORD_LEN])
    }

    /// The name of a record checked at open.
    fn name_of(&self, r: &Record) -> &str {
        let start = self.names_start + r.name_offset as usize;
        // Checked at open to be in bounds and valid UTF-8.
        std::str::from_utf8(&self.bytes.as_slice()[start..start + r.name_len as usize]).unwrap_or("")
    }

    fn permutation(&self, index: usize) -> PermutationRef<'_> {
        PermutationRef { archive: self, index: index as u32, record: self.record(index) }
    }

    pub fn kiln_version(&self) -> &str {
        &self.tables.kiln_version
    }
    pub fn naga_version(&self) -> &str {
        &self.tables.naga_version
    }
    /// Size of the whole archive in bytes.
    pub fn len(&self) -> usize {
        self.bytes.as_slice().len()
    }
    pub fn is_empty(&self) -> bool {
        self.permutation_count == 0
    }
    /// Number of permutations.
    pub fn permutation_count(&self) -> usize {
        self.permutation_count
    }
    pub fn shaders(&self) -> &[ShaderRecord] {
        &self.tables.shaders
    }
    pub fn blob_count(&self) -> usize {
        self.blob_count
    }
    pub fn reflections(&self) -> &[Reflection] {
        &self.tables.reflections
    }

    /// Every permutation, sorted by name.
    pub fn permutations(&self) -> impl ExactSizeIterator<Item = PermutationRef<'_>> {
        (0..self.permutation_count).map(move |i| self.permutation(i))
    }

    /// The table entry of a blob; ids come from this archive's records, checked at open.
    fn entry(&self, id: BlobId) -> Option<Entry> {
        let i = id.0 as usize;
        if i >= self.blob_count {
            return None;
        }
        let at = self.table_start + i * ENTRY_LEN;
        Some(Entry::decode(&self.bytes.as_slice()[at..at + ENTRY_LEN]))
    }

    /// Sizes of a blob, from the table (nothing is decompressed).
    pub fn blob_info(&self, id: BlobId) -> Option<BlobInfo> {
        self.entry(id).map(|e| BlobInfo {
            raw_len: e.raw_len,
            stored_len: e.stored_len,
            compressed: e.codec != CODEC_STORED,
            dictionary: e.codec == CODEC_ZSTD_DICT,
        })
    }

    /// Each target's dictionary and its size in bytes.
    pub fn dictionaries(&self) -> impl Iterator<Item = (Target, u64)> + '_ {
        self.dictionaries.iter().map(|d| (d.target, d.len))
    }

    /// The dictionary `index`, checked against its checksum and loaded on first use.
    fn ddict(&self, index: usize) -> Result<&DDict<'static>, String> {
        let cell = self.ddicts.get(index).ok_or_else(|| format!("dictionary {index} does not exist"))?;
        let loaded = cell.get_or_init(|| {
            let d = &self.dictionaries[index];
            let start = self.dictionaries_start + d.offset as usize;
            let bytes = &self.bytes.as_slice()[start..start + d.len as usize];
            if blake3::hash(bytes).as_bytes() != &d.blake3 {
                return Err(format!("the {} dictionary fails its checksum", d.target));
            }
            DDict::try_create(bytes).ok_or_else(|| format!("the {} dictionary cannot be loaded", d.target))
        });
        loaded.as_ref().map_err(|e| e.clone())
    }

    /// The blob's bytes, decompressed; checked against its checksum the first time. The
    /// error says what is wrong (callers add the permutation's name:
    /// [`PermutationRef::artifact`]).
    pub fn blob(&self, id: BlobId) -> Result<Cow<'_, [u8]>, String> {
        let e = self.entry(id).ok_or_else(|| format!("blob {} does not exist", id.0))?;
        let start = self.blobs_start + e.offset as usize;
        let stored = &self.bytes.as_slice()[start..start + e.stored_len as usize];
        let bytes: Cow<'_, [u8]> = match e.codec {
            CODEC_STORED => Cow::Borrowed(stored),
            _ => {
                let ddict = match e.codec {
                    CODEC_ZSTD_DICT => Some(self.ddict(e.dictionary as usize)?),
                    _ => None,
                };
                let mut out = Vec::new();
                out.try_reserve_exact(e.raw_len as usize)
                    .map_err(|_| format!("cannot allocate {} bytes to decompress it", e.raw_len))?;
                let result = DCTX.with(|cell| {
                    let mut slot = cell.borrow_mut();
                    let dctx = match &mut *slot {
                        Some(d) => d,
                        None => slot.insert(DCtx::try_create().ok_or("cannot create a zstd context")?),
                    };
                    match ddict {
                        Some(dd) => dctx.decompress_using_ddict(&mut out, stored, dd),
                        None => dctx.decompress(&mut out, stored),
                    }
                    .map_err(zstd::zstd_safe::get_error_name)
                });
                match result {
                    Ok(n) if n as u64 == e.raw_len => Cow::Owned(out),
                    Ok(n) => return Err(format!("it decompresses to {n} bytes, not the {} announced", e.raw_len)),
                    Err(why) => return Err(format!("it does not decompress: {why}")),
                }
            }
        };
        let flag = &self.verified[id.0 as usize];
        if !flag.load(Ordering::Acquire) {
            if blake3::hash(&bytes).as_bytes() != &e.hash {
                return Err("its checksum does not match its bytes".into());
            }
            flag.store(true, Ordering::Release);
        }
        Ok(bytes)
    }

    /// Checks every blob (decompressing each once); the first failure is returned, named
    /// by a permutation that uses it.
    pub fn verify_all(&self) -> Result<(), ArchiveError> {
        for p in self.permutations() {
            for t in p.targets() {
                p.artifact(t)?;
            }
        }
        Ok(())
    }

    /// Lookup by canonical name: a binary search of the records, sorted by name (O(log n)
    /// string comparisons, read in place).
    pub fn get(&self, name: &str) -> Option<PermutationRef<'_>> {
        let (mut lo, mut hi) = (0usize, self.permutation_count);
        while lo < hi {
            let mid = lo + (hi - lo) / 2;
            match self.name_of(&self.record(mid)).cmp(name) {
                std::cmp::Ordering::Less => lo = mid + 1,
                std::cmp::Ordering::Greater => hi = mid,
                std::cmp::Ordering::Equal => return Some(self.permutation(mid)),
            }
        }
        None
    }

    /// Lookup by [`permutation_id`], the id that typed keys (`Key::permutation_id`, see
    /// `kiln::bindings`) compute from their fields without formatting a name: a binary search
    /// of the manifest's sorted ids (16-byte comparisons, read in place). The permutation
    /// found is checked to have that id.
    pub fn get_by_id(&self, id: u128) -> Option<PermutationRef<'_>> {
        let data = self.bytes.as_slice();
        let at = |i: usize| {
            let o = self.ids_start + i * ID_LEN;
            let id = u128::from_le_bytes(data[o..o + 16].try_into().unwrap());
            (id, u32::from_le_bytes(data[o + 16..o + 20].try_into().unwrap()) as usize)
        };
        let (mut lo, mut hi) = (0usize, self.permutation_count);
        while lo < hi {
            let mid = lo + (hi - lo) / 2;
            let (found, index) = at(mid);
            match found.cmp(&id) {
                std::cmp::Ordering::Less => lo = mid + 1,
                std::cmp::Ordering::Greater => hi = mid,
                std::cmp::Ordering::Equal => {
                    if index >= self.permutation_count {
                        return None;
                    }
                    let p = self.permutation(index);
                    let s = p.shader();
                    return (permutation_id(&s.name, &s.level, p.values()) == id).then_some(p);
                }
            }
        }
        None
    }

    /// The (shader, level) record, if the archive has that pair.
    pub fn shader(&self, shader: &str, level: &str) -> Option<&ShaderRecord> {
        self.by_shader.get(&(shader.to_string(), level.to_string())).map(|&i| &self.tables.shaders[i as usize])
    }

    /// Builds the canonical name of (shader, level, values) from the shader's dimension
    /// order. Values may be given in any order; every dimension must be given, by value or
    /// (for an enum) by label. Returns an error message naming what is wrong.
    pub fn canonical_name(&self, shader: &str, level: &str, values: &[(&str, &str)]) -> Result<String, String> {
        let record = self.shader(shader, level).ok_or_else(|| {
            let levels: Vec<&str> =
                self.tables.shaders.iter().filter(|s| s.name == shader).map(|s| s.level.as_str()).collect();
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
        for p in self.permutations() {
            let have = parse_name(p.name());
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
            scored.push((score, Near { name: p.name().to_string(), differences: diffs }));
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

/// The manifest, read: its counts and layout, its tables and dictionaries parsed.
struct ReadManifest {
    counts: ManifestCounts,
    layout: ManifestLayout,
    tables: Tables,
    dictionaries: Vec<DictionaryRecord>,
}

/// Reads the manifest at `data[start..start + len]` and checks every index and range of its
/// records, so that later accessors cannot go out of bounds. O(permutations), with no
/// allocation per permutation: each record is a few integer comparisons.
fn read_manifest(data: &[u8], start: usize, len: usize, sections: &Sections) -> Result<ReadManifest, ArchiveError> {
    let bad = |msg: String| ArchiveError::Manifest(msg);
    let m = &data[start..start + len];
    let counts = ManifestCounts::decode(m).ok_or_else(|| bad("the manifest's header is malformed".into()))?;
    let layout = counts.layout().ok_or_else(|| bad("the manifest's counts overflow".into()))?;
    if layout.end != len as u64 {
        return Err(bad(format!("the manifest's counts give {} bytes, the header {len}", layout.end)));
    }
    let part = |from: u64, to: u64| &m[from as usize..to as usize];
    let tables: Tables = serde_json::from_slice(part(layout.tables, layout.tables + counts.tables_len))
        .map_err(|e| bad(format!("its tables: {e}")))?;
    if part(layout.tables + counts.tables_len, layout.names).iter().any(|&b| b != 0) {
        return Err(bad("padding after the tables is not zero".into()));
    }
    if counts.dictionaries > NO_DICTIONARY as u64 {
        return Err(bad(format!("{} dictionaries", counts.dictionaries)));
    }
    let mut dictionaries = Vec::new();
    for (i, b) in part(layout.dictionaries, layout.tables).chunks_exact(DICTIONARY_LEN).enumerate() {
        let d = DictionaryRecord::decode(b).ok_or_else(|| bad(format!("dictionary {i} is malformed")))?;
        match d.offset.checked_add(d.len) {
            Some(end) if end <= sections.dictionaries_len => {}
            _ => return Err(bad(format!("dictionary {i} lies outside the dictionary section"))),
        }
        dictionaries.push(d);
    }
    for (i, b) in part(layout.artifacts, layout.dictionaries).chunks_exact(ARTIFACT_LEN).enumerate() {
        match decode_artifact(b) {
            Some((_, blob)) if (blob.0 as u64) < sections.blob_count => {}
            Some((t, _)) => return Err(bad(format!("artifact {i} names a missing {t} blob"))),
            None => return Err(bad(format!("artifact {i} is malformed"))),
        }
    }
    let names = std::str::from_utf8(part(layout.names, layout.end))
        .map_err(|e| bad(format!("permutation names are not UTF-8: {e}")))?;
    let dims: Vec<u64> = tables.shaders.iter().map(|s| s.dimensions.len() as u64).collect();
    let reflections = tables.reflections.len() as u64;
    for (i, b) in part(layout.records, layout.ids).chunks_exact(RECORD_LEN).enumerate() {
        let r = Record::decode(b);
        let end = r.name_offset.checked_add(r.name_len as u64).unwrap_or(u64::MAX);
        let Some(name) = usize::try_from(end).ok().and_then(|end| names.get(r.name_offset as usize..end)) else {
            return Err(bad(format!("permutation {i}'s name lies outside the names or splits a character")));
        };
        let Some(&n) = dims.get(r.shader as usize) else {
            return Err(bad(format!("permutation `{name}` names shader {} of {}", r.shader, dims.len())));
        };
        if r.reflection as u64 >= reflections {
            return Err(bad(format!("permutation `{name}` names a missing reflection")));
        }
        if r.first_value as u64 + n > counts.values {
            return Err(bad(format!("permutation `{name}`'s {n} values lie outside the values")));
        }
        if r.first_artifact as u64 + r.artifact_count as u64 > counts.artifacts {
            return Err(bad(format!("permutation `{name}`'s artifacts lie outside the artifacts")));
        }
    }
    Ok(ReadManifest { counts, layout, tables, dictionaries })
}

/// Checks every entry of the blob table.
fn validate_table(table: &[u8], sections: &Sections, dictionaries: usize) -> Result<(), ArchiveError> {
    let bad = |msg: String| Err(ArchiveError::Manifest(msg));
    for (i, bytes) in table.chunks_exact(ENTRY_LEN).enumerate() {
        let e = Entry::decode(bytes);
        if !Entry::reserved_zero(bytes) {
            return bad(format!("blob {i} has non-zero reserved bytes"));
        }
        match e.offset.checked_add(e.stored_len) {
            Some(end) if end <= sections.blobs_len => {}
            _ => return bad(format!("blob {i} lies outside the blob section")),
        }
        if e.raw_len > MAX_ARTIFACT_LEN {
            return bad(format!("blob {i} announces {} bytes, more than the {MAX_ARTIFACT_LEN} allowed", e.raw_len));
        }
        match e.codec {
            CODEC_STORED if e.stored_len == e.raw_len && e.dictionary == NO_DICTIONARY => {}
            CODEC_ZSTD if e.dictionary == NO_DICTIONARY => {}
            CODEC_ZSTD_DICT if (e.dictionary as usize) < dictionaries => {}
            c => return bad(format!("blob {i} has codec {c} with dictionary {}", e.dictionary)),
        }
    }
    Ok(())
}
