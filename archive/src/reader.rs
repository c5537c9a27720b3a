//! Reading an archive: open (header and chunk hashes checked, O(1) in the number of
//! permutations), lookups by name or id (each manifest chunk checked the first time a read
//! touches it, each record the first time it is used), and blobs checked and decompressed on
//! first use.

use std::borrow::Cow;
use std::cell::RefCell;
use std::collections::HashMap;
use std::fs::File;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::OnceLock;

use zstd::zstd_safe::{DCtx, DDict};

use super::format::{
    decode_artifact, header_checksum, stored_sum, ArchiveError, BlobId, DictionaryRecord, DimensionRecord, Entry,
    ManifestCounts, ManifestLayout, Partial, PermutationRecord, PipelineRecord, Record, Sections, ShaderRecord, Tables,
    ARTIFACT_LEN, CHUNK_HASH_LEN, CODEC_STORED, CODEC_ZSTD, CODEC_ZSTD_DICT, DICTIONARY_LEN, ENTRY_LEN, FORMAT_VERSION,
    HEADER_LEN, ID_LEN, MAGIC, MANIFEST_HEADER_LEN, MAX_ARTIFACT_LEN, NO_DICTIONARY, OLDEST_FORMAT_VERSION, RECORD_LEN,
    VALUE_LEN,
};
use super::{edit_distance, Reflection, Target};

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

/// A loaded archive. Opening checks the header and the chunk hashes and parses the tables;
/// the manifest's records and the blob table stay where they are (in the memory map or the
/// embedded bytes) and each chunk of them is checked the first time a read touches it, each
/// record and entry the first time it is used; blobs are checked the first time their
/// artifact is asked for, once each. `Send + Sync`.
pub struct Archive {
    bytes: Bytes,
    /// The format version of its header (one this build reads).
    format_version: u32,
    blobs_start: usize,
    blobs_len: u64,
    dictionaries_start: usize,
    /// Where the chunk hashes lie in `bytes`, and the chunk length's log2.
    chunk_hashes_start: usize,
    chunk_shift: u32,
    manifest_start: usize,
    manifest_len: usize,
    /// How many chunks the manifest has: the table's chunks are numbered after them.
    manifest_chunks: usize,
    table_start: usize,
    blob_count: usize,
    /// Where the manifest's parts lie, from the manifest's start.
    layout: ManifestLayout,
    counts: ManifestCounts,
    permutation_count: usize,
    tables: Tables,
    dictionaries: Vec<DictionaryRecord>,
    /// Whether each chunk of the manifest and the table has passed its hash.
    chunks_ok: Bits,
    /// Whether each permutation's record has passed its checks.
    records_ok: Bits,
    /// Whether every record has (so that a walk of them checks nothing more).
    all_records_ok: AtomicBool,
    /// Each permutation's values, decoded on first use, in pages of [`VALUE_PAGE`] cells
    /// allocated on first use.
    values: Box<[OnceLock<ValuePages>]>,
    /// Whether each blob has passed its checksum.
    verified: Bits,
    /// Each dictionary, loaded (and checked) on first use.
    ddicts: Box<[OnceLock<Result<DDict<'static>, String>>]>,
    by_shader: HashMap<(String, String), u32>,
}

/// One permutation's values in pages of [`VALUE_PAGE`] cells, each decoded on first use.
type ValuePages = Box<[OnceLock<Box<[i64]>>]>;
/// The first walk of every record releases the pages it touched ([`Archive::release_pages`])
/// after each this many records.
pub const RELEASE_EVERY: usize = 1 << 14;

/// Cells of decoded values per page.
const VALUE_PAGE: usize = 1024;

/// Bits set once, read and set from any thread, in pages of [`BITS_PAGE`] bits allocated
/// (zeroed) on the first set of one of theirs: opening writes one empty cell per page (25 for
/// the 100,000 permutations of a large archive), nothing per bit.
struct Bits(Box<[OnceLock<Box<[AtomicU64]>>]>);

/// Bits per page of [`Bits`].
const BITS_PAGE: usize = 4096;

impl Bits {
    fn new(n: usize) -> Bits {
        Bits((0..n.div_ceil(BITS_PAGE)).map(|_| OnceLock::new()).collect())
    }
    fn get(&self, i: usize) -> bool {
        let word = self.0.get(i / BITS_PAGE).and_then(|p| p.get()).map(|p| &p[i % BITS_PAGE / 64]);
        word.is_some_and(|w| w.load(Ordering::Acquire) & (1 << (i % 64)) != 0)
    }
    fn set(&self, i: usize) {
        if let Some(page) = self.0.get(i / BITS_PAGE) {
            let page = page.get_or_init(|| (0..BITS_PAGE / 64).map(|_| AtomicU64::new(0)).collect());
            page[i % BITS_PAGE / 64].fetch_or(1 << (i % 64), Ordering::Release);
        }
    }
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
    /// Its canonical name, `Shader@level{DIM=value,...}`.
    pub fn name(&self) -> &'a str {
        self.archive.name_of(&self.record)
    }
    /// Its (shader, level) record.
    pub fn shader(&self) -> &'a ShaderRecord {
        &self.archive.tables.shaders[self.record.shader as usize]
    }
    /// Index of its shader in [`Archive::shaders`].
    pub fn shader_index(&self) -> u32 {
        self.record.shader
    }
    /// One value per dimension of its shader, in declared order.
    pub fn values(&self) -> &'a [i64] {
        let archive = self.archive;
        let index = self.index as usize;
        let page =
            archive.values[index / VALUE_PAGE].get_or_init(|| (0..VALUE_PAGE).map(|_| OnceLock::new()).collect());
        page[index % VALUE_PAGE].get_or_init(|| self.decode_values().collect())
    }
    /// Its dimension values, decoded from the manifest each call and not kept (a walk of
    /// every permutation's [`PermutationRef::values`] keeps a page entry for each).
    pub fn decode_values(&self) -> impl Iterator<Item = i64> + 'a {
        let archive = self.archive;
        // In range and checked: the record was checked before this reference was made.
        let n = self.shader().dimensions.len();
        let start = archive.manifest_start
            + (archive.layout.values + self.record.first_value as u64 * VALUE_LEN as u64) as usize;
        let bytes = archive.bytes.as_slice().get(start..start + n * VALUE_LEN).unwrap_or_default();
        bytes.chunks_exact(VALUE_LEN).map(|b| i64::from_le_bytes(b.try_into().unwrap()))
    }
    /// Its entry point's reflection.
    pub fn reflection(&self) -> &'a Reflection {
        &self.archive.tables.reflections[self.record.reflection as usize]
    }
    /// Index of its reflection in [`Archive::reflections`].
    pub fn reflection_index(&self) -> u32 {
        self.record.reflection
    }
    /// Its artifacts' targets and blobs, in the level's order of targets.
    fn artifacts(&self) -> impl Iterator<Item = (Target, BlobId)> + 'a {
        let archive = self.archive;
        let start = archive.manifest_start
            + (archive.layout.artifacts + self.record.first_artifact as u64 * ARTIFACT_LEN as u64) as usize;
        let len = self.record.artifact_count as usize * ARTIFACT_LEN;
        // In range and checked: the record was checked before this reference was made.
        let bytes = archive.bytes.as_slice().get(start..start + len).unwrap_or_default();
        bytes.chunks_exact(ARTIFACT_LEN).filter_map(super::format::decode_artifact)
    }
    /// The targets it has an artifact for, in the level's order.
    pub fn targets(&self) -> impl Iterator<Item = Target> + 'a {
        self.artifacts().map(|(t, _)| t)
    }
    /// The blob holding its artifact for `target`, if it has one.
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
    /// Sizes of the artifact for `target` (`None` when the permutation has none), from its
    /// blob table entry; a damaged entry is an error naming this permutation and the target.
    pub fn blob_info(&self, target: Target) -> Result<Option<BlobInfo>, ArchiveError> {
        let Some(id) = self.blob_id(target) else { return Ok(None) };
        self.archive.blob_info(id).map(Some).map_err(|message| ArchiveError::Blob {
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

/// The permutations of an archive, sorted by name ([`Archive::permutations`]); every record
/// was checked before the walk began.
pub struct Permutations<'a> {
    archive: &'a Archive,
    next: usize,
    end: usize,
}

impl<'a> Iterator for Permutations<'a> {
    type Item = PermutationRef<'a>;
    fn next(&mut self) -> Option<PermutationRef<'a>> {
        while self.next < self.end {
            let i = self.next;
            self.next += 1;
            // Checked (its bit set) before the walk: this only reads the record again.
            if let Ok(p) = self.archive.permutation(i) {
                return Some(p);
            }
        }
        None
    }
    fn size_hint(&self) -> (usize, Option<usize>) {
        (self.end - self.next, Some(self.end - self.next))
    }
}

impl ExactSizeIterator for Permutations<'_> {}

/// A near miss for a name that is not in the archive.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Near {
    /// The near permutation's canonical name.
    pub name: String,
    /// `DIM: wanted -> available` for each dimension that differs.
    pub differences: Vec<String>,
}

/// The answer to a lookup by name.
pub enum Lookup<'a> {
    /// The permutation of that name.
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
    let t = meta.file_type();
    if t.is_dir() {
        return "directory";
    }
    special_kind(&t)
}

#[cfg(not(unix))]
fn special_kind(_: &std::fs::FileType) -> &'static str {
    "special file"
}

#[cfg(unix)]
fn special_kind(t: &std::fs::FileType) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    if t.is_fifo() {
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
    /// Memory-maps an archive file and checks its header and chunk hashes. A path that is not a
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

    /// Opens an archive held in memory (checked as [`Archive::open`] checks a file).
    pub fn from_vec(bytes: Vec<u8>) -> Result<Archive, ArchiveError> {
        Archive::from_source(Bytes::Owned(bytes))
    }

    fn from_source(bytes: Bytes) -> Result<Archive, ArchiveError> {
        let data = bytes.as_slice();
        if data.len() >= 12 && data[0..8] == MAGIC {
            // The version first: an archive of another version may have another header size.
            let version = u32::from_le_bytes(data[8..12].try_into().unwrap());
            if !(OLDEST_FORMAT_VERSION..=FORMAT_VERSION).contains(&version) {
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
        if data[52..96].iter().any(|&b| b != 0) {
            return Err(ArchiveError::Manifest("reserved header bytes are not zero".into()));
        }
        let sections = Sections {
            blobs_len: u64_at(16),
            dictionaries_len: u64_at(24),
            manifest_len: u64_at(32),
            blob_count: u64_at(40),
            chunk_len: u32_at(48),
        };
        let layout = sections.layout().ok_or_else(|| {
            ArchiveError::Manifest("section lengths overflow or the chunk length is not allowed".into())
        })?;
        let actual = data.len() as u64;
        if layout.end > actual {
            return Err(ArchiveError::Truncated { expected: layout.end, actual });
        }
        if layout.end < actual {
            return Err(ArchiveError::TrailingBytes { expected: layout.end, actual });
        }
        // The padding between sections is covered by no checksum: it must be zero.
        let pads = [
            (layout.blobs + sections.blobs_len, layout.dictionaries),
            (layout.dictionaries + sections.dictionaries_len, layout.chunks),
            (layout.manifest + sections.manifest_len, layout.table),
        ];
        if pads.iter().any(|&(from, to)| data[from as usize..to as usize].iter().any(|&b| b != 0)) {
            return Err(ArchiveError::Manifest("padding between sections is not zero".into()));
        }
        // The header checksum covers the chunk hashes (one per chunk of the manifest and of
        // the table); every chunk is checked against its hash when first read.
        let expected: [u8; 32] = data[96..128].try_into().unwrap();
        let computed = header_checksum(&data[..96], &data[layout.chunks as usize..layout.manifest as usize]);
        if computed.as_bytes() != &expected {
            return Err(ArchiveError::Checksum {
                expected: blake3::Hash::from_bytes(expected).to_hex().to_string(),
                actual: computed.to_hex().to_string(),
            });
        }
        let blob_count = sections.blob_count as usize;
        let chunks = (layout.manifest_chunks + layout.table_chunks) as usize;
        let mut archive = Archive {
            format_version: u32_at(8),
            blobs_start: layout.blobs as usize,
            blobs_len: sections.blobs_len,
            dictionaries_start: layout.dictionaries as usize,
            chunk_hashes_start: layout.chunks as usize,
            chunk_shift: sections.chunk_len.trailing_zeros(),
            manifest_start: layout.manifest as usize,
            manifest_len: sections.manifest_len as usize,
            manifest_chunks: layout.manifest_chunks as usize,
            table_start: layout.table as usize,
            blob_count,
            layout: ManifestLayout {
                records: 0,
                ids: 0,
                values: 0,
                artifacts: 0,
                dictionaries: 0,
                tables: 0,
                names: 0,
                end: 0,
            },
            counts: ManifestCounts {
                permutations: 0,
                values: 0,
                artifacts: 0,
                dictionaries: 0,
                tables_len: 0,
                names_len: 0,
            },
            permutation_count: 0,
            tables: Tables {
                kiln_version: String::new(),
                naga_version: String::new(),
                shaders: Vec::new(),
                reflections: Vec::new(),
                partial: None,
                pipelines: None,
            },
            dictionaries: Vec::new(),
            chunks_ok: Bits::new(chunks),
            records_ok: Bits::new(0),
            all_records_ok: AtomicBool::new(false),
            values: Box::new([]),
            verified: Bits::new(blob_count),
            ddicts: Box::new([]),
            by_shader: HashMap::new(),
            bytes,
        };
        archive.read_manifest(&sections)?;
        let permutations = archive.counts.permutations as usize;
        archive.permutation_count = permutations;
        archive.records_ok = Bits::new(permutations);
        archive.values = (0..permutations.div_ceil(VALUE_PAGE)).map(|_| OnceLock::new()).collect();
        archive.ddicts = (0..archive.dictionaries.len()).map(|_| OnceLock::new()).collect();
        archive.by_shader = archive
            .tables
            .shaders
            .iter()
            .enumerate()
            .map(|(i, s)| ((s.name.clone(), s.level.clone()), i as u32))
            .collect();
        Ok(archive)
    }

    /// Reads the manifest's header, dictionaries and tables (checking the chunks they lie
    /// in), and checks that its counts give its length, so that every record's range can be
    /// checked against them on first use. O(1) in the number of permutations.
    fn read_manifest(&mut self, sections: &Sections) -> Result<(), ArchiveError> {
        let bad = |msg: String| ArchiveError::Manifest(msg);
        let header = self.manifest_bytes(0, MANIFEST_HEADER_LEN as u64).map_err(|m| bad(format!("its header: {m}")))?;
        let counts = ManifestCounts::decode(header).ok_or_else(|| bad("the manifest's header is malformed".into()))?;
        let layout = counts.layout().ok_or_else(|| bad("the manifest's counts overflow".into()))?;
        let len = self.manifest_len;
        if layout.end != len as u64 {
            return Err(bad(format!("the manifest's counts give {} bytes, the header {len}", layout.end)));
        }
        if counts.dictionaries > NO_DICTIONARY as u64 {
            return Err(bad(format!("{} dictionaries", counts.dictionaries)));
        }
        let tables_bytes =
            self.manifest_bytes(layout.tables, counts.tables_len).map_err(|m| bad(format!("its tables: {m}")))?;
        let tables: Tables = serde_json::from_slice(tables_bytes).map_err(|e| bad(format!("its tables: {e}")))?;
        check_pipelines(tables.pipelines.as_deref().unwrap_or_default()).map_err(bad)?;
        let pad_start = layout.tables + counts.tables_len;
        let pad =
            self.manifest_bytes(pad_start, layout.names - pad_start).map_err(|m| bad(format!("its tables: {m}")))?;
        if pad.iter().any(|&b| b != 0) {
            return Err(bad("padding after the tables is not zero".into()));
        }
        let dict_bytes = self
            .manifest_bytes(layout.dictionaries, layout.tables - layout.dictionaries)
            .map_err(|m| bad(format!("its dictionaries: {m}")))?;
        let mut dictionaries = Vec::new();
        for (i, b) in dict_bytes.chunks_exact(DICTIONARY_LEN).enumerate() {
            let d = DictionaryRecord::decode(b).ok_or_else(|| bad(format!("dictionary {i} is malformed")))?;
            match d.offset.checked_add(d.len) {
                Some(end) if end <= sections.dictionaries_len => {}
                _ => return Err(bad(format!("dictionary {i} lies outside the dictionary section"))),
            }
            dictionaries.push(d);
        }
        self.counts = counts;
        self.layout = layout;
        self.tables = tables;
        self.dictionaries = dictionaries;
        Ok(())
    }

    /// `len` bytes of the manifest from `from`; each chunk they lie in is checked against its
    /// hash the first time it is read. The error says what failed.
    fn manifest_bytes(&self, from: u64, len: u64) -> Result<&[u8], String> {
        self.region_bytes(self.manifest_start, self.manifest_len, 0, "manifest", from, len)
    }

    /// [`Archive::manifest_bytes`] of the blob table.
    fn table_bytes(&self, from: u64, len: u64) -> Result<&[u8], String> {
        let table_len = self.blob_count * ENTRY_LEN;
        self.region_bytes(self.table_start, table_len, self.manifest_chunks, "blob table", from, len)
    }

    fn region_bytes(
        &self,
        start: usize,
        region_len: usize,
        first_chunk: usize,
        what: &str,
        from: u64,
        len: u64,
    ) -> Result<&[u8], String> {
        let end = match from.checked_add(len) {
            Some(end) if end <= region_len as u64 => end as usize,
            _ => return Err(format!("bytes {from}..{from}+{len} lie outside the {what} ({region_len} bytes)")),
        };
        let from = from as usize;
        let data = self.bytes.as_slice();
        if from < end {
            for c in from >> self.chunk_shift..=(end - 1) >> self.chunk_shift {
                let index = first_chunk + c;
                if self.chunks_ok.get(index) {
                    continue;
                }
                let at = c << self.chunk_shift;
                let bytes = &data[start + at..start + region_len.min(at + (1 << self.chunk_shift))];
                let want = &data[self.chunk_hashes_start + index * CHUNK_HASH_LEN..][..CHUNK_HASH_LEN];
                if blake3::hash(bytes).as_bytes() != want {
                    return Err(format!(
                        "the {what}'s chunk {c} (file bytes {}..{}) fails its checksum",
                        start + at,
                        start + at + bytes.len()
                    ));
                }
                self.chunks_ok.set(index);
            }
        }
        Ok(&data[start + from..start + end])
    }

    /// The record of permutation `index`, its chunk checked.
    fn record_at(&self, index: usize) -> Result<Record, String> {
        self.manifest_bytes(self.layout.records + (index * RECORD_LEN) as u64, RECORD_LEN as u64).map(Record::decode)
    }

    /// The name bytes of a record, their chunks checked.
    fn name_bytes(&self, r: &Record) -> Result<&[u8], String> {
        match r.name_offset.checked_add(r.name_len as u64) {
            Some(end) if end <= self.counts.names_len => {
                self.manifest_bytes(self.layout.names + r.name_offset, r.name_len as u64)
            }
            _ => Err(format!("its name lies outside the names ({} bytes at {})", r.name_len, r.name_offset)),
        }
    }

    /// Permutation `index` (< the permutation count), its record checked the first time: the
    /// chunks it lies in, its name, shader, reflection, values and artifacts. An error names
    /// the permutation (by its number where its name cannot be read).
    fn permutation(&self, index: usize) -> Result<PermutationRef<'_>, ArchiveError> {
        let number = || format!("number {index} of {}", self.permutation_count);
        let err = |permutation: String, message: String| ArchiveError::Permutation { permutation, message };
        let record = self.record_at(index).map_err(|m| err(number(), format!("its record: {m}")))?;
        if self.records_ok.get(index) {
            return Ok(PermutationRef { archive: self, index: index as u32, record });
        }
        let name = self.name_bytes(&record).map_err(|m| err(number(), m))?;
        let name = std::str::from_utf8(name).map_err(|e| err(number(), format!("its name is not UTF-8: {e}")))?;
        let who = || format!("`{name}`");
        let r = &record;
        let Some(shader) = self.tables.shaders.get(r.shader as usize) else {
            return Err(err(who(), format!("it names shader {} of {}", r.shader, self.tables.shaders.len())));
        };
        if r.reflection as usize >= self.tables.reflections.len() {
            return Err(err(who(), format!("it names a missing reflection ({})", r.reflection)));
        }
        let n = shader.dimensions.len() as u64;
        if r.first_value as u64 + n > self.counts.values {
            return Err(err(who(), format!("its {n} values lie outside the values")));
        }
        self.manifest_bytes(self.layout.values + r.first_value as u64 * VALUE_LEN as u64, n * VALUE_LEN as u64)
            .map_err(|m| err(who(), format!("its values: {m}")))?;
        if r.first_artifact as u64 + r.artifact_count as u64 > self.counts.artifacts {
            return Err(err(who(), "its artifacts lie outside the artifacts".into()));
        }
        let artifacts = self
            .manifest_bytes(
                self.layout.artifacts + r.first_artifact as u64 * ARTIFACT_LEN as u64,
                r.artifact_count as u64 * ARTIFACT_LEN as u64,
            )
            .map_err(|m| err(who(), format!("its artifacts: {m}")))?;
        for (i, b) in artifacts.chunks_exact(ARTIFACT_LEN).enumerate() {
            match decode_artifact(b) {
                Some((_, blob)) if (blob.0 as usize) < self.blob_count => {}
                Some((t, blob)) => {
                    return Err(err(who(), format!("its artifact {i} names a missing {t} blob ({})", blob.0)))
                }
                None => return Err(err(who(), format!("its artifact {i} is malformed"))),
            }
        }
        self.records_ok.set(index);
        Ok(PermutationRef { archive: self, index: index as u32, record })
    }

    /// The name of a record checked by [`Archive::permutation`].
    fn name_of(&self, r: &Record) -> &str {
        let start = self.manifest_start + (self.layout.names + r.name_offset) as usize;
        self.bytes
            .as_slice()
            .get(start..start + r.name_len as usize)
            .and_then(|b| std::str::from_utf8(b).ok())
            .unwrap_or("")
    }

    /// The pipeline manifest of a `kiln build --usage` archive: the pipelines recorded runs
    /// asked for, in first-use order; `None` for an archive built without usage files.
    pub fn pipeline_manifest(&self) -> Option<&[PipelineRecord]> {
        self.tables.pipelines.as_deref()
    }

    /// What a `kiln build --usage-only` archive left out; `None` for a whole archive.
    pub fn partial(&self) -> Option<&Partial> {
        self.tables.partial.as_ref()
    }

    /// Whether `name` is a permutation this partial archive left out.
    pub fn left_out(&self, name: &str) -> bool {
        self.partial().is_some_and(|p| p.left_out.binary_search_by(|n| n.as_str().cmp(name)).is_ok())
    }

    /// The archive's format version (from [`OLDEST_FORMAT_VERSION`] to [`FORMAT_VERSION`]).
    pub fn format_version(&self) -> u32 {
        self.format_version
    }
    /// The version of Kiln that wrote the archive.
    pub fn kiln_version(&self) -> &str {
        &self.tables.kiln_version
    }
    /// The version of naga that compiled its artifacts.
    pub fn naga_version(&self) -> &str {
        &self.tables.naga_version
    }
    /// The archive's content hash, 64 hex digits: its header checksum, the blake3 hash of
    /// the header's fields and of the chunk hashes, which cover the manifest and the table,
    /// whose entries hold the hash of every blob and dictionary. Archives with the same hash
    /// hold the same permutations and artifacts.
    pub fn content_hash(&self) -> String {
        let bytes: [u8; 32] = self.bytes.as_slice()[96..128].try_into().expect("a checked header");
        blake3::Hash::from_bytes(bytes).to_hex().to_string()
    }

    /// Size of the whole archive in bytes.
    pub fn len(&self) -> usize {
        self.bytes.as_slice().len()
    }
    /// Whether the archive holds no permutation.
    pub fn is_empty(&self) -> bool {
        self.permutation_count == 0
    }
    /// Number of permutations.
    pub fn permutation_count(&self) -> usize {
        self.permutation_count
    }
    /// Every (shader, level) record, in manifest order.
    pub fn shaders(&self) -> &[ShaderRecord] {
        &self.tables.shaders
    }
    /// How many distinct blobs the archive holds.
    pub fn blob_count(&self) -> usize {
        self.blob_count
    }
    /// Every distinct reflection, in manifest order.
    pub fn reflections(&self) -> &[Reflection] {
        &self.tables.reflections
    }

    /// Drops the pages of a mapped archive that reads have touched from this process's
    /// resident set: they stay in the page cache and fault back in (minor faults) on the next
    /// read. A walk of every record touches pages in proportion to the archive, so without
    /// this a tool's peak grew with the archive. Nothing for an archive in memory;
    /// failing is harmless.
    pub fn release_pages(&self) {
        if let Bytes::Mapped(m) = &self.bytes {
            // SAFETY: the map is read-only: dropped pages are read again from the file.
            let _ = unsafe { m.unchecked_advise(memmap2::UncheckedAdvice::DontNeed) };
        }
    }

    /// Every permutation, sorted by name. The first walk checks every record (and so every
    /// chunk of the manifest's records, values, artifacts and names) before it yields one:
    /// a bad record is an error naming it, and no walk sees part of a damaged manifest.
    pub fn permutations(&self) -> Result<Permutations<'_>, ArchiveError> {
        if !self.all_records_ok.load(Ordering::Acquire) {
            for i in 0..self.permutation_count {
                self.permutation(i)?;
                if (i + 1) % RELEASE_EVERY == 0 {
                    self.release_pages();
                }
            }
            self.all_records_ok.store(true, Ordering::Release);
        }
        Ok(Permutations { archive: self, next: 0, end: self.permutation_count })
    }

    /// The table entry of a blob, its chunk and fields checked (each read: a few
    /// comparisons). The error says what is wrong.
    fn entry(&self, id: BlobId) -> Result<Entry, String> {
        let i = id.0 as usize;
        if i >= self.blob_count {
            return Err(format!("blob {i} does not exist"));
        }
        let bytes = self.table_bytes((i * ENTRY_LEN) as u64, ENTRY_LEN as u64).map_err(|m| format!("blob {i}: {m}"))?;
        let e = Entry::decode(bytes);
        if self.format_version == OLDEST_FORMAT_VERSION && !Entry::reserved_zero(bytes) {
            return Err(format!("blob {i} has non-zero reserved bytes"));
        }
        match e.offset.checked_add(e.stored_len) {
            Some(end) if end <= self.blobs_len => {}
            _ => return Err(format!("blob {i} lies outside the blob section")),
        }
        if e.raw_len > MAX_ARTIFACT_LEN {
            return Err(format!("blob {i} announces {} bytes, more than the {MAX_ARTIFACT_LEN} allowed", e.raw_len));
        }
        match e.codec {
            CODEC_STORED if e.stored_len == e.raw_len && e.dictionary == NO_DICTIONARY => {}
            CODEC_ZSTD if e.dictionary == NO_DICTIONARY => {}
            CODEC_ZSTD_DICT if (e.dictionary as usize) < self.dictionaries.len() => {}
            c => return Err(format!("blob {i} has codec {c} with dictionary {}", e.dictionary)),
        }
        Ok(e)
    }

    /// A blob's table entry (checked) and its bytes as stored, compressed or not, for a
    /// writer that copies them into the next archive ([`crate::reuse`]).
    #[cfg(feature = "writer")]
    pub(crate) fn stored_blob(&self, id: BlobId) -> Result<(Entry, &[u8]), String> {
        let e = self.entry(id)?;
        let start = self.blobs_start + e.offset as usize;
        Ok((e, &self.bytes.as_slice()[start..start + e.stored_len as usize]))
    }

    /// Each dictionary's target and blake3, by index (the blake3 is the one its record
    /// announces: [`Archive::blob`] checks a dictionary's bytes against it when it loads it).
    #[cfg(feature = "writer")]
    pub(crate) fn dictionary_hashes(&self) -> Vec<(Target, [u8; 32])> {
        self.dictionaries.iter().map(|d| (d.target, d.blake3)).collect()
    }

    /// Sizes of a blob, from its table entry (checked; nothing is decompressed).
    pub fn blob_info(&self, id: BlobId) -> Result<BlobInfo, String> {
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
        let e = self.entry(id)?;
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
        if !self.verified.get(id.0 as usize) {
            if self.format_version > OLDEST_FORMAT_VERSION && stored_sum(stored) != e.sum {
                return Err("it fails the check sum of its stored bytes".into());
            }
            if blake3::hash(&bytes).as_bytes() != &e.hash {
                return Err("its checksum does not match its bytes".into());
            }
            self.verified.set(id.0 as usize);
        }
        Ok(bytes)
    }

    /// Checks every byte the archive's uses read: every record, every blob (decompressing
    /// each once) and every chunk of the manifest and blob table (the ids, and entries no
    /// permutation uses, included). The first failure is returned, named by a permutation
    /// where one is concerned.
    pub fn verify_all(&self) -> Result<(), ArchiveError> {
        for p in self.permutations()? {
            for t in p.targets() {
                p.artifact(t)?;
            }
        }
        self.manifest_bytes(0, self.manifest_len as u64).map_err(ArchiveError::Corrupted)?;
        self.table_bytes(0, (self.blob_count * ENTRY_LEN) as u64).map_err(ArchiveError::Corrupted)?;
        for i in 0..self.blob_count {
            self.entry(BlobId(i as u32)).map_err(ArchiveError::Corrupted)?;
        }
        Ok(())
    }

    /// Lookup by canonical name: a binary search of the records, sorted by name (O(log n)
    /// byte-string comparisons, read in place; each chunk a step reads is checked the first
    /// time). `Ok(None)` when the archive does not hold it; a damaged record or chunk on the
    /// way is an error naming `name`.
    pub fn get(&self, name: &str) -> Result<Option<PermutationRef<'_>>, ArchiveError> {
        let err = |message: String| ArchiveError::Permutation { permutation: format!("`{name}`"), message };
        let (mut lo, mut hi) = (0usize, self.permutation_count);
        while lo < hi {
            let mid = lo + (hi - lo) / 2;
            let found = self
                .record_at(mid)
                .and_then(|r| self.name_bytes(&r))
                .map_err(|m| err(format!("looking it up, record {mid}: {m}")))?;
            match found.cmp(name.as_bytes()) {
                std::cmp::Ordering::Less => lo = mid + 1,
                std::cmp::Ordering::Greater => hi = mid,
                std::cmp::Ordering::Equal => return self.permutation(mid).map(Some),
            }
        }
        Ok(None)
    }

    /// Lookup by [`permutation_id`], the id that typed keys (`Key::permutation_id`, see
    /// `kiln::bindings`) compute from their fields without formatting a name: a binary search
    /// of the manifest's sorted ids (16-byte comparisons, read in place). The permutation
    /// found is checked to have that id. `Ok(None)` when no permutation has it.
    pub fn get_by_id(&self, id: u128) -> Result<Option<PermutationRef<'_>>, ArchiveError> {
        let err = |message: String| ArchiveError::Permutation { permutation: format!("with id {id:032x}"), message };
        let at = |i: usize| -> Result<(u128, usize), ArchiveError> {
            let b = self
                .manifest_bytes(self.layout.ids + (i * ID_LEN) as u64, ID_LEN as u64)
                .map_err(|m| err(format!("looking it up, id {i}: {m}")))?;
            let id = u128::from_le_bytes(b[0..16].try_into().unwrap());
            Ok((id, u32::from_le_bytes(b[16..20].try_into().unwrap()) as usize))
        };
        let (mut lo, mut hi) = (0usize, self.permutation_count);
        while lo < hi {
            let mid = lo + (hi - lo) / 2;
            let (found, index) = at(mid)?;
            match found.cmp(&id) {
                std::cmp::Ordering::Less => lo = mid + 1,
                std::cmp::Ordering::Greater => hi = mid,
                std::cmp::Ordering::Equal => {
                    if index >= self.permutation_count {
                        return Err(err(format!(
                            "its id entry names permutation {index} of {}",
                            self.permutation_count
                        )));
                    }
                    let p = self.permutation(index)?;
                    let s = p.shader();
                    return Ok((permutation_id(&s.name, &s.level, p.values()) == id).then_some(p));
                }
            }
        }
        Ok(None)
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
    pub fn lookup(&self, name: &str) -> Result<Lookup<'_>, ArchiveError> {
        if let Some(p) = self.get(name)? {
            return Ok(Lookup::Found(p));
        }
        Ok(Lookup::Missing(self.nearest(name, 5)?))
    }

    /// The `limit` permutations closest to `name`. The shader names are compared first, once
    /// each (a shader's name decides most of the score), and only the permutations of the
    /// closest shaders are compared value by value; a name is compared on its first
    /// 256 characters and 64 dimensions.
    pub fn nearest(&self, name: &str, limit: usize) -> Result<Vec<Near>, ArchiveError> {
        let wanted = parse_name(name);
        let wanted_shader = capped(&wanted.shader, NEAR_NAME_CHARS);
        // Each shader's part of the score, by shader record.
        let base: Vec<usize> = self
            .shaders()
            .iter()
            .map(|s| {
                if s.name == wanted.shader {
                    0
                } else {
                    100 + edit_distance(capped(&s.name, NEAR_NAME_CHARS), wanted_shader)
                }
            })
            .collect();
        let mut scored: Vec<(usize, Near)> = Vec::new();
        let mut worst = usize::MAX;
        for p in self.permutations()? {
            let base = base.get(p.shader_index() as usize).copied().unwrap_or(usize::MAX);
            if scored.len() >= limit && base > worst {
                continue;
            }
            let have = parse_name(p.name());
            let mut diffs = Vec::new();
            let mut score = base;
            if have.shader != wanted.shader {
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
            if scored.len() >= limit && score > worst {
                continue;
            }
            scored.push((score, Near { name: p.name().to_string(), differences: diffs }));
            if scored.len() >= 4 * limit.max(1) {
                scored.sort_by(|a, b| a.0.cmp(&b.0).then_with(|| a.1.name.cmp(&b.1.name)));
                scored.truncate(limit);
            }
            if scored.len() >= limit {
                worst = scored.iter().map(|s| s.0).max().unwrap_or(usize::MAX);
            }
        }
        scored.sort_by(|a, b| a.0.cmp(&b.0).then_with(|| a.1.name.cmp(&b.1.name)));
        Ok(scored.into_iter().take(limit).map(|(_, n)| n).collect())
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

/// The characters of a shader name that near-miss search compares (a longer name asked
/// for is compared on these: the search costs at most this times each shader name).
const NEAR_NAME_CHARS: usize = 256;
/// The dimensions of a name asked for that near-miss search compares.
const NEAR_DIMENSIONS: usize = 64;

/// `text` cut to at most `chars` characters.
fn capped(text: &str, chars: usize) -> &str {
    text.char_indices().nth(chars).map_or(text, |(i, _)| &text[..i])
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
        .take(NEAR_DIMENSIONS)
        .map(|kv| match kv.split_once('=') {
            Some((k, v)) => (k.trim().to_string(), v.trim().to_string()),
            None => (kv.trim().to_string(), String::new()),
        })
        .collect();
    ParsedName { shader: shader.trim().to_string(), level: level.trim().to_string(), dims }
}

/// The pipeline manifest's records hold what a usage file's lines hold: names and state
/// text, not empty and without white space (so that listing them, escaped, is one record a
/// line).
fn check_pipelines(records: &[PipelineRecord]) -> Result<(), String> {
    use crate::usage::UsageKey;
    let clean = |s: &str| !s.is_empty() && !s.chars().any(char::is_whitespace);
    for (i, r) in records.iter().enumerate() {
        let ok = match &r.key {
            UsageKey::Compute { compute } => clean(compute),
            UsageKey::Render { vertex, fragment, state } => {
                clean(vertex) && fragment.as_deref().is_none_or(clean) && clean(state)
            }
        };
        if !ok {
            return Err(format!(
                "pipeline {i} of its pipeline manifest has an empty name or state, or one with white space"
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod bits_tests {
    use super::Bits;

    #[test]
    fn bits_across_pages_and_out_of_range() {
        let bits = Bits::new(10_001);
        assert!((0..10_001).all(|i| !bits.get(i)), "created zero");
        for i in [0, 63, 64, 4095, 4096, 10_000] {
            bits.set(i);
        }
        let set: Vec<usize> = (0..10_001).filter(|&i| bits.get(i)).collect();
        assert_eq!(set, vec![0, 63, 64, 4095, 4096, 10_000]);
        // Past the end: never set, never panics.
        bits.set(1 << 20);
        assert!(!bits.get(1 << 20) && !bits.get(12_288));
        assert!(!Bits::new(0).get(0));
    }
}
