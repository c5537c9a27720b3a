//! The writers of the archive format (`format.rs`).
//!
//! [`StreamingWriter`] is what a build feeds: blobs and permutations are added from any
//! thread, in any order, as they are produced; blob bytes go to a spool, in memory while it
//! is small and then a file beside the output (unlinked as soon as it is created, so a
//! killed build leaves nothing behind), and memory holds only a table of a `u32` a cell
//! that finds each blob's number by its identity, and the manifest (where each blob's bytes
//! lie goes to a second unlinked file, read back at the end; the whole identities to a
//! third, read back to confirm a match in the table; they are spooled too, and the table is
//! let go once the caller says no more blobs come: [`StreamingWriter::seal_blobs`]). [`StreamingWriter::finish`] sorts
//! the permutations by canonical name, orders blobs by first use in that order, encodes the
//! manifest to the spool past the blobs (all but its header and dictionary records) and
//! lets go of its tables, then reads back where the blobs lie, trains one dictionary per
//! target on a deterministic sample, compresses, and writes the archive through a temporary
//! file and a rename, the spilled manifest copied into it. A caller that gives the
//! permutations in name order ([`StreamingWriter::begin_sorted`]) has each one encoded as
//! it comes instead: the writer then holds nothing per permutation, and writes the same
//! bytes. The bytes of the archive therefore depend only on
//! the set of permutations and blobs, never on the order they were added in or on the
//! number of threads, nor on the archive the writer replaces: a blob that archive holds
//! intact is added by reference (nothing spooled) and its stored bytes copied or
//! compressed again at the end ([`Previous`]).
//!
//! [`ArchiveWriter`] is the same assembly over an in-memory spool, with index-based handles,
//! for tests, benches and small tools.

use std::borrow::Cow;
use std::collections::HashMap;
use std::fs::File;
use std::io::{BufWriter, Cursor, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;

use super::format::{
    encode_artifact, encode_id, header_checksum, sibling_name, stored_sum, write_atomic_with, write_derived,
    ArchiveError, Arenas, BlobId, ChunkHasher, DictionaryRecord, Entry, Manifest, ManifestCounts, ManifestPermutation,
    Partial, PermutationRecord, PipelineRecord, Record, Sections, ShaderRecord, TablesOut, ARTIFACT_LEN, CHUNK_LEN,
    CODEC_STORED, CODEC_ZSTD, CODEC_ZSTD_DICT, COMPRESSION_LEVEL, DICTIONARY_SAMPLE, DICTIONARY_SIZE, HEADER_LEN,
    ID_LEN, NO_DICTIONARY, RECORD_LEN, VALUE_LEN,
};
use super::reuse::{Previous, Reused};
use super::{Reflection, Target};

mod sorted;

/// The content hash of a blob given to a writer: what a permutation names its artifacts by.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct BlobKey(blake3::Hash);

impl BlobKey {
    /// The key of `bytes` (their blake3).
    pub fn of(bytes: &[u8]) -> BlobKey {
        BlobKey(blake3::hash(bytes))
    }
    /// The key of bytes whose blake3 the caller computed already.
    pub fn from_hash(hash: blake3::Hash) -> BlobKey {
        BlobKey(hash)
    }
    /// The blob's blake3 hash.
    pub fn hash(&self) -> blake3::Hash {
        self.0
    }
}

/// A permutation given to [`StreamingWriter::add_permutation`] (its artifacts' blobs named
/// by [`BlobKey`]), or to [`StreamingWriter::add_permutation_numbered`] (by the numbers
/// [`StreamingWriter::add_blob_numbered`] gave).
#[derive(Clone, Debug)]
pub struct NewPermutation<'a, B = BlobKey> {
    /// Canonical name, `Shader@level{DIM=value,...}`; unique in the archive.
    pub name: String,
    /// Its (shader, level) record; every permutation of a pair must give an equal record.
    pub shader: &'a ShaderRecord,
    /// One value per dimension of the shader, in declared order.
    pub values: Vec<i64>,
    /// Its entry point's reflection.
    pub reflection: &'a Reflection,
    /// At most one blob per target, each added with [`StreamingWriter::add_blob`].
    pub artifacts: Vec<(Target, B)>,
}

/// Artifacts added once for any number of permutations ([`StreamingWriter::add_artifacts`]),
/// named by a permutation of [`StreamingWriter::add_permutation_ranged`]: `count` of them
/// from the `first`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ArtifactRange {
    /// The number [`StreamingWriter::add_artifacts`] gave, plus the artifacts before these
    /// among those it added.
    pub first: u32,
    /// How many (at most one a target).
    pub count: u8,
}

/// What [`StreamingWriter::finish`] wrote.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ArchiveSummary {
    /// Permutations in the archive.
    pub permutations: usize,
    /// Distinct blobs in the archive.
    pub blobs: usize,
    /// Their bytes before compression.
    pub raw_bytes: u64,
    /// Their bytes as stored (compressed).
    pub stored_bytes: u64,
    /// Bytes of the trained dictionaries.
    pub dictionary_bytes: u64,
    /// Size of the archive file.
    pub file_bytes: u64,
    /// Blobs copied, compressed as they were, from the archive the writer replaced (the
    /// file at its output, when this version wrote it) instead of compressed again.
    pub reused_blobs: usize,
}

/// The manifest side of a writer: interned shaders and reflections, pending permutations
/// (in the order added, their shaders in this numbering, their artifacts' blobs numbered by
/// the writer's [`BlobTable`]), their names, values and artifacts in arenas (no allocation
/// per permutation).
#[derive(Clone, Default)]
struct Entries {
    naga_version: String,
    partial: Option<Partial>,
    pipelines: Option<Vec<PipelineRecord>>,
    hooks: WriterHooks,
    shaders: Vec<ShaderRecord>,
    shader_index: FastMap<(String, String), u32>,
    reflections: Vec<Reflection>,
    reflection_index: FastMap<Reflection, u32>,
    /// The shader and reflection of the last permutation added: a caller adds a shader's
    /// permutations together, many with one reflection, and comparing a record costs less
    /// than hashing it (and cloning the shader's key) for every permutation.
    last: Option<(u32, u32)>,
    permutations: Vec<ManifestPermutation>,
    arenas: Arenas,
    /// A derived name made for the check in [`Entries::add`].
    scratch: String,
}

/// A map of the writer's own lookups, which only find what was added (the archive's bytes
/// do not depend on them): with the default SipHash, hashing a reflection cost more than
/// the rest of adding a permutation. FxHash is not resistant to chosen collisions, which
/// here could only slow a build whose own sources chose them.
type FastMap<K, V> = rustc_hash::FxHashMap<K, V>;

/// A blob's identity in a writer: a prefix of its blake3 (as long as the cache's pack
/// names; a collision between artifacts is not a practical concern). Its whole blake3,
/// which the archive stores, waits in the spool beside its bytes, so that a build holds
/// less per blob.
type Ident = [u8; 16];

/// The bytes of an [`Ident`].
const IDENT_BYTES: usize = 16;

fn ident(hash: &blake3::Hash) -> Ident {
    hash.as_bytes()[..16].try_into().expect("16 of 32 bytes")
}

/// What goes in the spool just before a blob's bytes: its whole blake3 (whose first bytes
/// are its [`Ident`]), then the xxh3-64 of that blake3 and the bytes. The check sum tells
/// a blob damaged on disk before the archive was written at a fraction of the cost of
/// hashing its bytes with blake3 again.
const ID_PREFIX: u64 = 40;

/// A blob's header in the spool ([`ID_PREFIX`]).
fn spool_header(hash: &blake3::Hash, bytes: &[u8]) -> [u8; ID_PREFIX as usize] {
    let mut head = [0u8; ID_PREFIX as usize];
    head[..32].copy_from_slice(hash.as_bytes());
    head[32..].copy_from_slice(&spool_sum(hash.as_bytes(), bytes).to_le_bytes());
    head
}

fn spool_sum(hash: &[u8], bytes: &[u8]) -> u64 {
    let mut h = xxhash_rust::xxh3::Xxh3::new();
    h.update(hash);
    h.update(bytes);
    h.digest()
}

/// Where an added blob's bytes lie in the spool (its identity just before them), or which
/// blob of the previous archive it is.
#[derive(Clone, Copy)]
struct Loc {
    offset: u64,
    len: u64,
    /// Its id in the previous archive when it was added by reference (nothing spooled),
    /// else [`SPOOLED`].
    previous: u32,
}

/// [`Loc::previous`] of a blob whose bytes are in the spool.
const SPOOLED: u32 = u32::MAX;

/// The length of a location record: a slot number (`u32`), a length (`u64`) and the blob's
/// id in the previous archive (`u32`, [`SPOOLED`] if none); the offset is the sum of the
/// spooled lengths before it (blobs are spooled in the order of their records).
const LOC_RECORD: usize = 16;

/// Where location records wait until `finish`.
enum LocLog {
    Memory(Vec<u8>),
    /// An unlinked file beside the spool, written through a buffer.
    File(BufWriter<File>),
}

/// The blobs of a writer, numbered by first sight and found by identity. Memory holds only
/// the table that finds slots by identity prefix and a bit saying whether each blob was
/// added; the whole identities go to [`IdentStore`] (a file for a [`StreamingWriter`]), read
/// back to confirm a match in the table, and where the blobs' bytes lie goes to a log, read
/// back when the archive is assembled. Each blob's identity is spooled too, just before its
/// bytes, where the archive's assembly checks it: once no more blobs come
/// ([`BlobTable::seal`]) the table that finds them is let go.
struct BlobTable {
    /// Each slot's whole identity (kept once sealed: the dictionaries' samples read them).
    idents: IdentStore,
    /// Slots given.
    slots: usize,
    /// Slots `0..previous` are the blobs of the archive being replaced, each slot's number
    /// its id there ([`BlobTable::seed`]); the slots after them are new blobs.
    previous: usize,
    /// Whether the slots of the archive being replaced were given (or it has none).
    seeded: bool,
    /// No more blobs: `table` is gone.
    sealed: bool,
    /// One bit per slot: its blob was added.
    added_bits: Vec<u64>,
    table: SlotTable,
    log: LocLog,
    /// Blobs added.
    added: usize,
    /// The next free offset of the spool.
    spooled: u64,
}

/// Slots by identity prefix: open addressing with linear probing over `cells` cells of a
/// `u32`, each the slot number plus one (0: empty) in its low `bits` bits and, above them,
/// the prefix's low bits as a tag. A slot number fits in `bits` bits because the table has
/// fewer than `2^bits` cells and is never full, and the tag spares most probes the read of
/// an identity: a tag match is only a candidate, confirmed by the whole identity. It holds
/// no prefixes of its own, so it grows by being dropped and rebuilt from the identities,
/// never holding the old cells and the new at once.
///
/// Its length is not a power of two: a table that doubles is, over the sets a build may
/// have, on average half again as large as it needs to be at the compile stage's end, where
/// it is the largest table of the blob side. It grows by half instead (a place is found by
/// multiplying, not masking), which costs each blob a few more moves as it grows.
#[derive(Default)]
struct SlotTable {
    cells: Vec<u32>,
    bits: u32,
    len: usize,
}

/// The smallest table's cells.
const MIN_TABLE_CELLS: usize = 16;

/// The most slots a table of `cells` cells takes before it grows (four fifths of it: a
/// probe then reads a dozen cells on average, in a cache line or two).
fn table_room(cells: usize) -> usize {
    cells / 5 * 4
}

/// The fewest cells whose room ([`table_room`]) is `slots` slots.
fn table_cells_for(slots: usize) -> usize {
    (slots / 4 + 1).saturating_mul(5).max(MIN_TABLE_CELLS)
}

/// The cells of the table that follows one of `cells` cells.
fn next_table_cells(cells: usize) -> usize {
    (cells + cells / 2).max(MIN_TABLE_CELLS)
}

impl SlotTable {
    fn with_cells(cells: usize) -> SlotTable {
        // Enough bits for every slot number plus one (at most `cells`).
        let bits = usize::BITS - cells.leading_zeros();
        SlotTable { cells: vec![0; cells], bits, len: 0 }
    }

    /// Whether one more slot would fill it past its room ([`table_room`]).
    fn is_full(&self) -> bool {
        self.len + 1 > table_room(self.cells.len())
    }

    fn mask(&self) -> u32 {
        ((1u64 << self.bits) - 1) as u32
    }

    fn tag(&self, prefix: u32) -> u32 {
        (u64::from(prefix) << self.bits) as u32
    }

    /// Where `prefix`'s probe starts: its hash's high 32 bits scaled to the table's length.
    fn home(&self, prefix: u32) -> usize {
        (((table_hash(prefix) >> 32) * self.cells.len() as u64) >> 32) as usize
    }

    /// The cell after cell `i`, wrapping at the end.
    fn next(&self, i: usize) -> usize {
        if i + 1 == self.cells.len() {
            0
        } else {
            i + 1
        }
    }

    /// Calls `is` with each slot whose tag is `prefix`'s, until it says yes: that slot.
    fn find(&self, prefix: u32, mut is: impl FnMut(u32) -> std::io::Result<bool>) -> std::io::Result<Option<u32>> {
        if self.cells.is_empty() {
            return Ok(None);
        }
        let (mask, tag) = (self.mask(), self.tag(prefix));
        let mut i = self.home(prefix);
        loop {
            let cell = self.cells[i];
            if cell == 0 {
                return Ok(None);
            }
            if cell & !mask == tag && is((cell & mask) - 1)? {
                return Ok(Some((cell & mask) - 1));
            }
            i = self.next(i);
        }
    }

    /// Puts slot `n` (not in the table, and room for it: see [`SlotTable::is_full`]).
    fn put(&mut self, prefix: u32, n: usize) {
        let mut i = self.home(prefix);
        while self.cells[i] != 0 {
            i = self.next(i);
        }
        self.cells[i] = self.tag(prefix) | (n as u32 + 1);
        self.len += 1;
    }
}

/// The slots' whole identities, by slot number: in memory, or in an unlinked file (one
/// [`Ident`] a slot, at `16 * slot`) written a chunk at a time, the last slots' in `pending`. Read
/// when a new identity's tag in the table is a known slot's (a blob added again, or rarely
/// two blobs whose tags agree), and in slot order when the table grows.
struct IdentStore {
    file: Option<File>,
    /// Slots before this one are in `file`.
    flushed: usize,
    pending: Vec<Ident>,
}

/// Identities held in memory before a file is written.
const IDENT_CHUNK: usize = 4096;

impl IdentStore {
    fn get(&self, n: usize) -> std::io::Result<Ident> {
        if n >= self.flushed {
            return Ok(self.pending[n - self.flushed]);
        }
        let file = self.file.as_ref().expect("identities are flushed only to a file");
        let mut id = [0u8; 16];
        file.read_exact_at(&mut id, (n * IDENT_BYTES) as u64)?;
        Ok(id)
    }

    /// Calls `f` with each of the first `slots` slots and its identity, in slot order (the
    /// file read a chunk at a time).
    fn for_each(&self, slots: usize, mut f: impl FnMut(usize, &Ident)) -> std::io::Result<()> {
        let mut buf = vec![[0u8; IDENT_BYTES]; IDENT_CHUNK];
        let mut slot = 0;
        while slot < self.flushed.min(slots) {
            let n = (self.flushed.min(slots) - slot).min(IDENT_CHUNK);
            let file = self.file.as_ref().expect("identities are flushed only to a file");
            file.read_exact_at(buf[..n].as_flattened_mut(), (slot * IDENT_BYTES) as u64)?;
            buf[..n].iter().enumerate().for_each(|(i, id)| f(slot + i, id));
            slot += n;
        }
        for (i, id) in self.pending.iter().enumerate().take(slots.saturating_sub(self.flushed)) {
            f(self.flushed + i, id);
        }
        Ok(())
    }

    fn push(&mut self, id: Ident) -> std::io::Result<()> {
        self.pending.push(id);
        if let (Some(file), IDENT_CHUNK) = (&self.file, self.pending.len()) {
            file.write_all_at(self.pending.as_flattened(), (self.flushed * IDENT_BYTES) as u64)?;
            self.flushed += self.pending.len();
            self.pending.clear();
        }
        Ok(())
    }
}

impl Default for BlobTable {
    fn default() -> Self {
        BlobTable::new(LocLog::Memory(Vec::new()), None)
    }
}

/// A prefix of an identity (uniform), what the table finds slots by.
fn prefix(id: &Ident) -> u32 {
    u32::from_le_bytes(id[..4].try_into().expect("4 of 16 bytes"))
}

/// A prefix spread over 64 bits (the table takes its high bits as tags, its low bits as the
/// place).
fn table_hash(prefix: u32) -> u64 {
    u64::from(prefix).wrapping_mul(0x9E37_79B9_7F4A_7C15)
}

impl BlobTable {
    /// A table logging locations to `log` and identities to `idents` (in memory if `None`).
    fn new(log: LocLog, idents: Option<File>) -> Self {
        BlobTable {
            idents: IdentStore { file: idents, flushed: 0, pending: Vec::new() },
            slots: 0,
            previous: 0,
            seeded: false,
            sealed: false,
            added_bits: Vec::new(),
            table: SlotTable::default(),
            log,
            added: 0,
            spooled: 0,
        }
    }

    /// The number of the blob with `hash`, a new one if it is not known yet; `None` once
    /// sealed.
    fn number(&mut self, hash: &blake3::Hash) -> std::io::Result<Option<u32>> {
        if self.sealed {
            return Ok(None);
        }
        let id = ident(hash);
        let p = prefix(&id);
        // Every slot with this tag, confirmed by its whole identity (a tag, or a prefix,
        // shared by two blobs is rare, not impossible).
        let idents = &self.idents;
        if let Some(n) = self.table.find(p, |n| Ok(idents.get(n as usize)? == id))? {
            return Ok(Some(n));
        }
        let n = u32::try_from(self.slots).expect("fewer than 2^32 blobs");
        if self.table.is_full() {
            self.grow()?;
        }
        self.idents.push(id)?;
        self.table.put(p, self.slots);
        self.slots += 1;
        if self.added_bits.len() * 64 < self.slots {
            self.added_bits.push(0);
        }
        Ok(Some(n))
    }

    /// Grows the table by half ([`next_table_cells`]): the old one is dropped first and the
    /// new one filled from the identities (read back in slot order), so the two are never
    /// held together.
    fn grow(&mut self) -> std::io::Result<()> {
        let cells = next_table_cells(self.table.cells.len());
        self.table = SlotTable::default();
        let mut table = SlotTable::with_cells(cells);
        self.idents.for_each(self.slots, |n, id| table.put(prefix(id), n))?;
        self.table = table;
        Ok(())
    }

    /// Gives the blobs of the archive being replaced (their blake3s in id order from
    /// `previous`) the first slots, before any other: slot `n` is its blob `n`, so that
    /// this table alone finds the blobs of both archives.
    fn seed(&mut self, previous: &Previous) -> std::io::Result<()> {
        if self.slots != 0 {
            return Err(std::io::Error::other("the previous archive's blobs come after others"));
        }
        let count = previous.blob_count();
        u32::try_from(count).map_err(|_| std::io::Error::other("more than 2^32 blobs"))?;
        self.table = SlotTable::with_cells(table_cells_for(count));
        self.added_bits.resize(count.div_ceil(64), 0);
        let (idents, table, slots) = (&mut self.idents, &mut self.table, &mut self.slots);
        previous.for_each_hash(|hash| {
            let id: Ident = hash[..16].try_into().expect("16 of 32 bytes");
            idents.push(id)?;
            table.put(prefix(&id), *slots);
            *slots += 1;
            Ok(())
        })?;
        self.previous = count;
        Ok(())
    }

    /// Whether slot `n` is a blob of the archive being replaced ([`BlobTable::seed`]).
    fn is_previous(&self, n: u32) -> bool {
        (n as usize) < self.previous
    }

    /// Whether the blob with `hash` may be one of the archive being replaced that `accept`
    /// takes (by its slot): a slot whose tag matches, not confirmed by its identity.
    fn may_be_previous(&self, hash: &blake3::Hash, accept: impl Fn(u32) -> bool) -> bool {
        let found = self.table.find(prefix(&ident(hash)), |n| Ok(self.is_previous(n) && accept(n)));
        matches!(found, Ok(Some(_)))
    }

    /// Makes the table room for `more` blobs beyond those added at once, if it has less
    /// (and is not sealed): a caller that knows a close bound spares the table its growth,
    /// each step of which drops a table and builds one half again as large while the freed
    /// one may still be resident. Slots given but not added yet (the previous archive's)
    /// may be among the `more`: the table is made for the larger of its slots and the
    /// blobs added and to come, and grows past that if it must.
    fn expect(&mut self, more: usize) -> std::io::Result<()> {
        let blobs = self.slots.max(self.added.saturating_add(more));
        if self.sealed || table_room(self.table.cells.len()) >= blobs {
            return Ok(());
        }
        self.table = SlotTable::default();
        let mut table = SlotTable::with_cells(table_cells_for(blobs));
        self.idents.for_each(self.slots, |n, id| table.put(prefix(id), n))?;
        self.table = table;
        Ok(())
    }

    /// No more blobs will be added or named: lets go of what finds them (the identities
    /// stay, for the dictionaries' samples: [`samples`]).
    fn seal(&mut self) {
        self.sealed = true;
        self.table = SlotTable::default();
    }

    fn is_added(&self, n: u32) -> bool {
        self.added_bits[n as usize / 64] & (1 << (n % 64)) != 0
    }

    /// `artifacts` with blob numbers checked to be this table's.
    fn check_numbers(&self, name: &str, artifacts: &[(Target, u32)]) -> Result<(), ArchiveError> {
        match artifacts.iter().find(|(_, n)| *n as usize >= self.slots) {
            Some((t, n)) => Err(ArchiveError::Input(format!("permutation `{name}` names a {t} blob {n} of no writer"))),
            None => Ok(()),
        }
    }

    /// The number of the blob with `hash`, and whether it was added.
    fn find(&mut self, hash: &blake3::Hash) -> std::io::Result<(u32, bool)> {
        let n = self.number(hash)?.ok_or_else(|| std::io::Error::other("a blob was added after the last"))?;
        Ok((n, self.is_added(n)))
    }

    /// Adds blob `n` (a number [`BlobTable::find`] gave) of `len` bytes, the previous
    /// archive's blob `previous` or [`SPOOLED`]: where its identity and then its bytes go in
    /// the spool (`None` if it was added meanwhile, or by reference). The number is passed
    /// on rather than found again: finding it again probes the table and may read the
    /// identity back from its file.
    fn add(&mut self, n: u32, len: u64, previous: u32) -> std::io::Result<Option<u64>> {
        if n as usize >= self.slots {
            return Err(changed());
        }
        if self.is_added(n) {
            return Ok(None);
        }
        let mut record = [0u8; LOC_RECORD];
        record[..4].copy_from_slice(&n.to_le_bytes());
        record[4..12].copy_from_slice(&len.to_le_bytes());
        record[12..].copy_from_slice(&previous.to_le_bytes());
        match &mut self.log {
            LocLog::Memory(v) => v.extend_from_slice(&record),
            LocLog::File(f) => f.write_all(&record)?,
        }
        self.added_bits[n as usize / 64] |= 1 << (n % 64);
        self.added += 1;
        if previous != SPOOLED {
            return Ok(None);
        }
        let offset = self.spooled;
        self.spooled += ID_PREFIX + len;
        Ok(Some(offset))
    }

    /// [`BlobTable::find`] then [`BlobTable::add`]: the blob's number too.
    fn insert(&mut self, hash: &blake3::Hash, len: u64, previous: u32) -> std::io::Result<(u32, Option<u64>)> {
        let (n, _) = self.find(hash)?;
        Ok((n, self.add(n, len, previous)?))
    }

    /// Calls `f` with the id and location of every blob of the archive, in the order of the
    /// log (one pass over it, a buffer at a time), `id_of` giving each slot's id.
    fn scan(&mut self, id_of: &[u32], mut f: impl FnMut(usize, Loc)) -> std::io::Result<()> {
        let mut offset = 0u64;
        let mut put = |record: &[u8]| -> std::io::Result<()> {
            let n = u32::from_le_bytes(record[..4].try_into().expect("4 bytes")) as usize;
            let len = u64::from_le_bytes(record[4..12].try_into().expect("8 bytes"));
            let previous = u32::from_le_bytes(record[12..].try_into().expect("4 bytes"));
            if u32::try_from(len).is_err() {
                return Err(std::io::Error::other("an artifact of 4 GiB or more cannot go in an archive"));
            }
            match *id_of.get(n).ok_or_else(changed)? {
                // Added, named by no permutation: not in the archive.
                u32::MAX => {}
                id => f(id as usize, Loc { offset: offset + ID_PREFIX, len, previous }),
            }
            if previous == SPOOLED {
                offset += ID_PREFIX + len;
            }
            Ok(())
        };
        match &mut self.log {
            LocLog::Memory(v) => v.chunks_exact(LOC_RECORD).try_for_each(&mut put)?,
            LocLog::File(f) => {
                f.flush()?;
                let file = f.get_ref();
                let total = self.added * LOC_RECORD;
                let mut buf = vec![0u8; (1 << 16) / LOC_RECORD * LOC_RECORD];
                let mut at = 0;
                while at < total {
                    let n = (total - at).min(buf.len());
                    file.read_exact_at(&mut buf[..n], at as u64)?;
                    buf[..n].chunks_exact(LOC_RECORD).try_for_each(&mut put)?;
                    at += n;
                }
            }
        }
        if offset != self.spooled {
            return Err(changed());
        }
        Ok(())
    }

    /// The locations of the blobs `ids` (a window of the archive's blobs: where all of them
    /// lie would be held per blob at the build's end, where the build peaks).
    fn locations(&mut self, id_of: &[u32], ids: std::ops::Range<usize>) -> std::io::Result<BlobLocs> {
        let mut locs = BlobLocs {
            first: ids.start,
            offsets: vec![u64::MAX; ids.len()],
            lens: vec![0; ids.len()],
            previous: vec![SPOOLED; ids.len()],
        };
        self.scan(id_of, |id, loc| {
            if ids.contains(&id) {
                locs.offsets[id - ids.start] = loc.offset;
                locs.lens[id - ids.start] = loc.len as u32;
                locs.previous[id - ids.start] = loc.previous;
            }
        })?;
        if locs.offsets.contains(&u64::MAX) {
            return Err(changed());
        }
        Ok(locs)
    }
}

fn changed() -> std::io::Error {
    std::io::Error::other("a temporary file of the archive was changed")
}

/// Where a window of the archive's blobs lie in the spool, by blob id from `first` (see
/// [`BlobTable::locations`]).
#[derive(Default)]
struct BlobLocs {
    first: usize,
    offsets: Vec<u64>,
    lens: Vec<u32>,
    previous: Vec<u32>,
}

impl BlobLocs {
    fn get(&self, id: usize) -> Loc {
        let i = id - self.first;
        Loc { offset: self.offsets[i], len: u64::from(self.lens[i]), previous: self.previous[i] }
    }
}

/// Blobs whose locations are read from the log at a time while they are compressed (384
/// KiB of locations).
const LOC_WINDOW: usize = 1 << 15;

impl Entries {
    /// Adds `p`, its artifacts' blobs numbered (in the writer's [`BlobTable`]): its own, or
    /// the `range` of those already added if given (then `p` has none of its own).
    fn add(&mut self, p: NewPermutation<'_, u32>, range: Option<ArtifactRange>) -> Result<(), ArchiveError> {
        let (last_shader, last_reflection) = self.last.unzip();
        let shader = match last_shader.filter(|&s| self.shaders[s as usize] == *p.shader) {
            Some(s) => s,
            None => self.shader(&p)?,
        };
        let reflection = match last_reflection.filter(|&r| self.reflections[r as usize] == *p.reflection) {
            Some(r) => r,
            None => self.reflection(p.reflection),
        };
        self.last = Some((shader, reflection));
        self.add_with(p, shader, reflection, range)
    }

    /// The index of the shader of `p`, added if new; an error if another record has its name.
    fn shader(&mut self, p: &NewPermutation<'_, u32>) -> Result<u32, ArchiveError> {
        let key = (p.shader.name.clone(), p.shader.level.clone());
        Ok(match self.shader_index.get(&key) {
            Some(&i) if self.shaders[i as usize] == *p.shader => i,
            Some(_) => {
                return Err(ArchiveError::Input(format!(
                    "permutation `{}` gives shader `{}@{}` a record that differs from an earlier permutation's",
                    p.name, key.0, key.1
                )))
            }
            None => {
                let i = self.shaders.len() as u32;
                self.shaders.push(p.shader.clone());
                self.arenas.prefixes.push(format!("{}@{}", key.0, key.1));
                self.shader_index.insert(key, i);
                i
            }
        })
    }

    /// The index of `reflection`, added if new.
    fn reflection(&mut self, reflection: &Reflection) -> u32 {
        match self.reflection_index.get(reflection) {
            Some(&i) => i,
            None => {
                let i = self.reflections.len() as u32;
                self.reflections.push(reflection.clone());
                self.reflection_index.insert(reflection.clone(), i);
                i
            }
        }
    }

    /// Adds `p`, whose shader and reflection are `shader` and `reflection` (and artifacts
    /// `range`, if given).
    fn add_with(
        &mut self,
        p: NewPermutation<'_, u32>,
        shader: u32,
        reflection: u32,
        range: Option<ArtifactRange>,
    ) -> Result<(), ArchiveError> {
        if p.values.len() != p.shader.dimensions.len() {
            return Err(ArchiveError::Input(format!(
                "permutation `{}` has {} values for the {} dimensions of `{}@{}`",
                p.name,
                p.values.len(),
                p.shader.dimensions.len(),
                p.shader.name,
                p.shader.level
            )));
        }
        // The caller's order of targets is kept: it is part of the permutation (the order of
        // the level's targets), not an order of arrival.
        let artifacts = &p.artifacts;
        let a = &mut self.arenas;
        let (first_artifact, artifact_count) = match range {
            Some(r) => {
                let targets =
                    (r.first as usize).checked_add(r.count.into()).and_then(|end| a.targets.get(r.first as usize..end));
                match targets {
                    Some(t) if artifacts.is_empty() && distinct(t.iter().copied()) => (r.first, r.count),
                    _ => {
                        return Err(ArchiveError::Input(format!(
                            "permutation `{}` names artifacts of no writer, or two of one target",
                            p.name
                        )))
                    }
                }
            }
            None if distinct(artifacts.iter().map(|a| a.0)) => {
                let first = u32::try_from(a.targets.len())
                    .map_err(|_| ArchiveError::Input("more than 2^32 artifacts".into()))?;
                a.targets.extend(artifacts.iter().map(|(t, _)| *t));
                a.blobs.extend(artifacts.iter().map(|(_, b)| *b));
                // Distinct targets (at most one a target).
                (first, artifacts.len() as u8)
            }
            None => {
                return Err(ArchiveError::Input(format!("permutation `{}` has two artifacts of one target", p.name)))
            }
        };
        let too_many = || ArchiveError::Input("more than 2^32 bytes of names, values or artifacts".into());
        // Canonical names begin with their shader's `name@level`: kept once, not per name.
        let own = p.name.strip_prefix(a.prefixes[shader as usize].as_str());
        // And go on with its dimensions and values, made again from them where needed.
        let derived = own.is_some_and(|own| {
            self.scratch.clear();
            write_derived(&p.shader.dimensions, p.values.iter().copied(), &mut self.scratch);
            self.scratch == own
        });
        let own_len = u32::try_from(own.unwrap_or(&p.name).len()).map_err(|_| too_many())?;
        let name = match derived {
            true => own_len,
            false => {
                let span = (u32::try_from(a.names.len()).map_err(|_| too_many())?, own_len);
                a.names.push_str(own.unwrap_or(&p.name));
                a.spans.push(span);
                u32::try_from(a.spans.len() - 1).map_err(|_| too_many())?
            }
        };
        let pending = ManifestPermutation {
            name,
            shader,
            reflection,
            first_value: u32::try_from(a.values.len()).map_err(|_| too_many())?,
            first_artifact,
            artifact_count,
            prefixed: own.is_some(),
            derived,
        };
        a.values.extend(&p.values);
        self.permutations.push(pending);
        Ok(())
    }
}

/// Whether no two of `targets` are the same.
fn distinct(targets: impl Iterator<Item = Target> + Clone) -> bool {
    targets.clone().enumerate().all(|(i, t)| targets.clone().take(i).all(|u| u != t))
}

/// Where blob bytes wait until the archive is assembled.
enum Spool<'a> {
    Memory(&'a [u8]),
    File(&'a File),
}

impl Spool<'_> {
    /// The blob at `loc`: the blake3 spooled with it, and its bytes (one read), once the
    /// spool's check sum shows them as they were added.
    fn read_blob(&self, loc: Loc) -> std::io::Result<([u8; 32], Cow<'_, [u8]>)> {
        let (start, end) = ((loc.offset - ID_PREFIX) as usize, (loc.offset + loc.len) as usize);
        let (head, bytes): ([u8; ID_PREFIX as usize], Cow<'_, [u8]>) = match self {
            Spool::Memory(m) => {
                let head = m[start..][..ID_PREFIX as usize].try_into().expect("a spool header");
                (head, Cow::Borrowed(&m[loc.offset as usize..end]))
            }
            Spool::File(f) => {
                let mut buf = vec![0u8; end - start];
                f.read_exact_at(&mut buf, loc.offset - ID_PREFIX)?;
                let head = buf[..ID_PREFIX as usize].try_into().expect("a spool header");
                buf.drain(..ID_PREFIX as usize);
                (head, Cow::Owned(buf))
            }
        };
        let hash: [u8; 32] = head[..32].try_into().expect("32 bytes");
        if spool_sum(&hash, &bytes).to_le_bytes() != head[32..] {
            return Err(std::io::Error::other("a spooled blob changed on disk before the archive was written"));
        }
        Ok((hash, bytes))
    }

    /// Reads `into.len()` bytes at `offset` into `into`.
    fn read_into(&self, offset: u64, into: &mut [u8]) -> std::io::Result<()> {
        match self {
            Spool::Memory(m) => {
                into.copy_from_slice(&m[offset as usize..offset as usize + into.len()]);
                Ok(())
            }
            Spool::File(f) => f.read_exact_at(into, offset),
        }
    }
}

/// Positioned reads and writes through a shared `&File`: the spool is written from many
/// threads at offsets they reserved, and read back while others write.
trait FileAt {
    fn read_exact_at(&self, buf: &mut [u8], offset: u64) -> std::io::Result<()>;
    fn write_all_at(&self, buf: &[u8], offset: u64) -> std::io::Result<()>;
}

#[cfg(unix)]
impl FileAt for File {
    fn read_exact_at(&self, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
        std::os::unix::fs::FileExt::read_exact_at(self, buf, offset)
    }
    fn write_all_at(&self, buf: &[u8], offset: u64) -> std::io::Result<()> {
        std::os::unix::fs::FileExt::write_all_at(self, buf, offset)
    }
}

#[cfg(windows)]
impl FileAt for File {
    fn read_exact_at(&self, mut buf: &mut [u8], mut offset: u64) -> std::io::Result<()> {
        use std::os::windows::fs::FileExt;
        while !buf.is_empty() {
            match self.seek_read(buf, offset) {
                Ok(0) => return Err(std::io::ErrorKind::UnexpectedEof.into()),
                Ok(n) => {
                    buf = &mut buf[n..];
                    offset += n as u64;
                }
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(e),
            }
        }
        Ok(())
    }
    fn write_all_at(&self, mut buf: &[u8], mut offset: u64) -> std::io::Result<()> {
        use std::os::windows::fs::FileExt;
        while !buf.is_empty() {
            match self.seek_write(buf, offset) {
                Ok(0) => return Err(std::io::ErrorKind::WriteZero.into()),
                Ok(n) => {
                    buf = &buf[n..];
                    offset += n as u64;
                }
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(e),
            }
        }
        Ok(())
    }
}

/// What the writer calls at its memory milestones, so that a build can trace its memory and
/// hand freed pages back to the system (the allocator may keep them a while) without the
/// archive crate knowing about either. Both do nothing by default.
#[derive(Clone, Copy, Debug)]
pub struct WriterHooks {
    /// Called with a stage's name once the stage's memory is in place.
    pub trace: fn(&str),
    /// Called where a large part of the writer's memory has just been freed.
    pub release: fn(),
}

impl Default for WriterHooks {
    fn default() -> Self {
        WriterHooks { trace: |_| {}, release: || {} }
    }
}

/// Adds blobs and permutations from any thread, spooling blob bytes to disk; see the module
/// documentation. `Send + Sync`: share it by reference across a thread pool.
pub struct StreamingWriter {
    output: PathBuf,
    entries: Mutex<Entries>,
    blobs: Mutex<BlobTable>,
    spool: SpoolSink,
    failed: AtomicBool,
    /// The archive at `output` this one replaces, opened when the first blob is added (a
    /// build that finds its archive up to date adds none, and pays nothing for it).
    previous: std::sync::OnceLock<Option<Previous>>,
    /// The manifest, when its permutations come in name order
    /// ([`StreamingWriter::begin_sorted`]).
    sorted: Mutex<Option<sorted::Sorted>>,
}

/// About the bytes of a permutation in a manifest (record, id, values, artifacts, name).
const MANIFEST_ESTIMATE: usize = 128;

/// The most blob bytes a [`StreamingWriter`] spools in memory before it moves them to a
/// file: a small set's blobs then never touch the file system (a file written and read
/// back costs a small build more than its compression), a large set's memory holds no more
/// than this while its blobs stream in.
const SPOOL_MEMORY: usize = 4 << 20;

/// Where a [`StreamingWriter`]'s blobs wait: in memory up to [`SPOOL_MEMORY`] bytes, then in
/// an unlinked file in `beside`'s folder (created then, what memory held copied into it).
/// Which one holds them changes nothing in the archive.
struct SpoolSink {
    /// The spooled bytes while in memory; `None` once moved to `file`.
    memory: Mutex<Option<Vec<u8>>>,
    /// The most bytes `memory` holds ([`SPOOL_MEMORY`]).
    limit: usize,
    file: std::sync::OnceLock<File>,
    beside: PathBuf,
}

impl SpoolSink {
    fn new(beside: PathBuf, limit: usize) -> SpoolSink {
        SpoolSink { memory: Mutex::new(Some(Vec::new())), limit, file: std::sync::OnceLock::new(), beside }
    }

    /// Writes `bytes` at `offset` (each offset is written once, by the thread that reserved
    /// it, in any order).
    fn write_all_at(&self, bytes: &[u8], offset: u64) -> std::io::Result<()> {
        if let Some(f) = self.file.get() {
            return f.write_all_at(bytes, offset);
        }
        let mut memory = lock(&self.memory);
        if let Some(m) = memory.as_mut() {
            let end = offset as usize + bytes.len();
            if end <= self.limit {
                if m.capacity() == 0 {
                    // Room for the whole bound at once: growing by doubling copied the
                    // bytes and touched twice the pages; pages never written stay untouched.
                    m.reserve_exact(self.limit.min(SPOOL_MEMORY));
                }
                if m.len() < end {
                    m.resize(end, 0);
                }
                m[offset as usize..end].copy_from_slice(bytes);
                return Ok(());
            }
            // Past the bound: what memory holds goes to the file, and so does all that follows.
            self.move_to_file(&mut memory)?;
        }
        drop(memory);
        self.file.get().expect("moved to its file under the lock").write_all_at(bytes, offset)
    }

    /// Moves what `memory` (this spool's, locked) holds to the file, created now.
    fn move_to_file(&self, memory: &mut Option<Vec<u8>>) -> std::io::Result<()> {
        if let Some(m) = memory.as_ref() {
            let f = unlinked_file(&self.beside)?;
            f.write_all_at(m, 0)?;
            let _ = self.file.set(f);
            *memory = None;
        }
        Ok(())
    }
}

/// A new file in `beside`'s folder, unlinked at once: the open handle keeps the data, and
/// nothing is left behind whatever happens next.
fn unlinked_file(beside: &Path) -> std::io::Result<File> {
    let path = sibling_name(beside, "spool")?;
    let file = std::fs::OpenOptions::new().read(true).write(true).create_new(true).open(&path)?;
    std::fs::remove_file(&path)?;
    Ok(file)
}

impl StreamingWriter {
    /// A writer of the archive at `output`. Its spool is created (and at once unlinked) in
    /// `output`'s folder, which is created if missing; where that fails (a read-only folder,
    /// `/dev` for `-o /dev/null`), in the system's temporary folder.
    pub fn new(output: &Path) -> Result<StreamingWriter, ArchiveError> {
        StreamingWriter::with_spool_memory(output, SPOOL_MEMORY)
    }

    /// [`StreamingWriter::new`] spooling at most `limit` bytes of blobs in memory.
    pub(crate) fn with_spool_memory(output: &Path, limit: usize) -> Result<StreamingWriter, ArchiveError> {
        let err = |source| ArchiveError::Write { path: output.to_path_buf(), source };
        let regular_or_new = std::fs::metadata(output).map_or(true, |m| m.is_file());
        // The blobs' locations, in an unlinked file beside the output (else in the system's
        // temporary folder), their identities in a second, and their bytes in memory or
        // a third in the same place ([`SpoolSink`]).
        let beside = match regular_or_new.then(|| unlinked_file(output)) {
            Some(Ok(f)) => Some((f, output.to_path_buf())),
            _ => None,
        };
        let (log, beside) = match beside {
            Some(found) => found,
            None => {
                let tmp = std::env::temp_dir().join("kiln-archive");
                (unlinked_file(&tmp).map_err(err)?, tmp)
            }
        };
        let log = BufWriter::with_capacity(1 << 16, log);
        let idents = unlinked_file(&beside).map_err(err)?;
        let entries = Entries { naga_version: String::new(), ..Default::default() };
        Ok(StreamingWriter {
            output: output.to_path_buf(),
            entries: Mutex::new(entries),
            blobs: Mutex::new(BlobTable::new(LocLog::File(log), Some(idents))),
            spool: SpoolSink::new(beside, limit),
            failed: AtomicBool::new(false),
            previous: std::sync::OnceLock::new(),
            sorted: Mutex::new(None),
        })
    }

    /// Sets what the writer calls at its memory milestones ([`WriterHooks`]).
    pub fn set_hooks(&self, hooks: WriterHooks) {
        self.entries.lock().unwrap_or_else(|e| e.into_inner()).hooks = hooks;
    }

    /// The archive's path.
    pub fn output(&self) -> &Path {
        &self.output
    }

    /// Records the naga version the artifacts were produced with (shown by `kiln inspect`).
    pub fn set_naga_version(&self, version: &str) {
        lock(&self.entries).naga_version = version.to_string();
    }

    /// Marks the archive partial: `partial.left_out` names the permutations left out (sorted
    /// here). Without it the archive's bytes are as they always were.
    pub fn set_partial(&self, mut partial: Partial) {
        partial.left_out.sort_unstable();
        lock(&self.entries).partial = Some(partial);
    }

    /// Stores a pipeline manifest (`kiln build --usage`), in the order given (a renderer
    /// creates them in that order). Without it the archive's bytes are as they always were.
    pub fn set_pipelines(&self, pipelines: Vec<PipelineRecord>) {
        lock(&self.entries).pipelines = Some(pipelines);
    }

    /// Adds a blob (an artifact's bytes); adding the same bytes again is free.
    pub fn add_blob(&self, bytes: &[u8]) -> Result<BlobKey, ArchiveError> {
        self.add_blob_hashed(bytes, blake3::hash(bytes))
    }

    /// [`StreamingWriter::add_blob`] for bytes whose blake3 `hash` the caller computed.
    pub fn add_blob_hashed(&self, bytes: &[u8], hash: blake3::Hash) -> Result<BlobKey, ArchiveError> {
        self.add_blob_numbered(bytes, hash).map(|_| BlobKey(hash))
    }

    /// [`StreamingWriter::add_blob_hashed`], giving the blob's number in this writer (4
    /// bytes to keep instead of its hash, for [`StreamingWriter::add_permutation_numbered`]).
    /// A blob the archive being replaced holds intact is added by reference: its bytes are
    /// not spooled, but copied from that archive when this one is written.
    pub fn add_blob_numbered(&self, bytes: &[u8], hash: blake3::Hash) -> Result<u32, ArchiveError> {
        debug_assert_eq!(hash, blake3::hash(bytes));
        let fail = |source| {
            self.failed.store(true, Ordering::Relaxed);
            ArchiveError::Write { path: self.output.clone(), source }
        };
        let previous = self.previous();
        let mut table = self.table(previous).map_err(fail)?;
        let (n, added) = table.find(&hash).map_err(fail)?;
        if added {
            return Ok(n);
        }
        let reference = match table.is_previous(n) && previous.is_some_and(|p| p.is_intact(n)) {
            true => n,
            false => SPOOLED,
        };
        let Some(offset) = table.add(n, bytes.len() as u64, reference).map_err(fail)? else {
            return Ok(n);
        };
        drop(table);
        // Written outside the lock (threads spool their blobs in parallel), after the
        // blob's identity, in one write.
        let mut spooled = Vec::with_capacity(ID_PREFIX as usize + bytes.len());
        spooled.extend_from_slice(&spool_header(&hash, bytes));
        spooled.extend_from_slice(bytes);
        self.spool.write_all_at(&spooled, offset).map_err(fail)?;
        Ok(n)
    }

    /// The archive being replaced, opened (its blobs checked) when first asked for: before
    /// the first blob is numbered ([`StreamingWriter::table`]).
    fn previous(&self) -> Option<&Previous> {
        self.previous.get_or_init(|| Previous::open(&self.output)).as_ref()
    }

    /// The blob table, its first slots the blobs of `previous` (this writer's
    /// [`StreamingWriter::previous`], opened outside the lock) once it is first asked for.
    fn table(&self, previous: Option<&Previous>) -> std::io::Result<std::sync::MutexGuard<'_, BlobTable>> {
        let mut table = lock(&self.blobs);
        if !table.seeded {
            table.seeded = true;
            if let Some(p) = previous {
                table.seed(p)?;
            }
        }
        Ok(table)
    }

    /// Whether the archive being replaced may hold the blob whose blake3 is `hash` intact:
    /// [`StreamingWriter::add_blob_reference`] then adds it without its bytes (a cache hit
    /// need not decompress them), or gives `None` for the few it answered yes for wrongly.
    /// Only the blobs not added yet are then confirmed (by their whole identity in the
    /// table).
    pub fn holds(&self, hash: &blake3::Hash) -> bool {
        let Some(previous) = self.previous() else { return false };
        self.table(Some(previous)).is_ok_and(|t| t.may_be_previous(hash, |n| previous.is_intact(n)))
    }

    /// Adds the blob of `len` bytes whose blake3 is `hash` without its bytes: its number,
    /// or `None` when neither this writer nor the archive being replaced holds it (the
    /// caller then adds it with [`StreamingWriter::add_blob_numbered`]).
    pub fn add_blob_reference(&self, hash: blake3::Hash, len: u64) -> Result<Option<u32>, ArchiveError> {
        let fail = |source| {
            self.failed.store(true, Ordering::Relaxed);
            ArchiveError::Write { path: self.output.clone(), source }
        };
        let previous = self.previous();
        let mut table = self.table(previous).map_err(fail)?;
        let (n, added) = table.find(&hash).map_err(fail)?;
        if added {
            return Ok(Some(n));
        }
        if !(table.is_previous(n) && previous.is_some_and(|p| p.is_intact(n))) {
            return Ok(None);
        }
        let offset = table.add(n, len, n).map_err(fail)?;
        debug_assert!(offset.is_none(), "a blob by reference is not spooled");
        Ok(Some(n))
    }

    /// Adds a permutation. Its blobs may be added before or after it, until `finish`.
    pub fn add_permutation(&self, p: NewPermutation<'_>) -> Result<(), ArchiveError> {
        self.unsorted()?;
        let p = {
            let mut blobs = lock(&self.blobs);
            let mut failed = None;
            let p = numbered(p, |k| match blobs.number(&k.0) {
                Ok(n) => n,
                Err(e) => {
                    failed = Some(e);
                    None
                }
            });
            if let Some(source) = failed {
                self.failed.store(true, Ordering::Relaxed);
                return Err(ArchiveError::Write { path: self.output.clone(), source });
            }
            p.ok_or_else(|| {
                ArchiveError::Input("a permutation named by blob keys was added after the blobs were sealed".into())
            })?
        };
        lock(&self.entries).add(p, None)
    }

    /// [`StreamingWriter::add_permutation`] with its blobs named by the numbers
    /// [`StreamingWriter::add_blob_numbered`] gave (a number it did not give is an error).
    pub fn add_permutation_numbered(&self, p: NewPermutation<'_, u32>) -> Result<(), ArchiveError> {
        self.unsorted()?;
        lock(&self.blobs).check_numbers(&p.name, &p.artifacts)?;
        lock(&self.entries).add(p, None)
    }

    /// Adds artifacts (each one's target and blob, numbered by
    /// [`StreamingWriter::add_blob_numbered`]) for permutations to name by range
    /// ([`StreamingWriter::add_permutation_ranged`]): the first one's number. A caller whose
    /// permutations share artifacts (those of one cache key) hands them over once, rather
    /// than a copy per permutation; the archive is the same either way.
    pub fn add_artifacts(&self, targets: Vec<Target>, blobs: Vec<u32>) -> Result<u32, ArchiveError> {
        if targets.len() != blobs.len() {
            return Err(ArchiveError::Input("artifacts of more targets than blobs, or fewer".into()));
        }
        let slots = lock(&self.blobs).slots;
        if let Some(i) = blobs.iter().position(|&n| n as usize >= slots) {
            return Err(ArchiveError::Input(format!(
                "an artifact names a {} blob {} of no writer",
                targets[i], blobs[i]
            )));
        }
        let a = &mut lock(&self.entries).arenas;
        let first = u32::try_from(a.targets.len()).ok().filter(|f| f.checked_add(blobs.len() as u32).is_some());
        let first = first.ok_or_else(|| ArchiveError::Input("more than 2^32 artifacts".into()))?;
        if a.targets.is_empty() {
            (a.targets, a.blobs) = (targets, blobs);
        } else {
            a.targets.extend(targets);
            a.blobs.extend(blobs);
        }
        Ok(first)
    }

    /// [`StreamingWriter::add_permutation_numbered`] of a permutation whose artifacts are the
    /// `artifacts` of those [`StreamingWriter::add_artifacts`] added (`p` has none of its own).
    pub fn add_permutation_ranged(
        &self,
        p: NewPermutation<'_, u32>,
        artifacts: ArtifactRange,
    ) -> Result<(), ArchiveError> {
        self.unsorted()?;
        lock(&self.entries).add(p, Some(artifacts))
    }

    /// An error once the permutations come in name order ([`StreamingWriter::begin_sorted`]).
    fn unsorted(&self) -> Result<(), ArchiveError> {
        match lock(&self.sorted).is_some() {
            true => Err(ArchiveError::Input("a permutation added out of name order to a sorted manifest".into())),
            false => Ok(()),
        }
    }

    /// Readies the writer for about `permutations` permutations that come in the archive's
    /// order (by name, each once), added with [`StreamingWriter::add_permutation_sorted`]
    /// alone: each is encoded as it comes, so the writer holds nothing per permutation
    /// (the unsorted manifest's pending permutations are the largest table of a large
    /// build's end). The archive is the same either way. An error once permutations were
    /// added otherwise.
    pub fn begin_sorted(&self, permutations: usize) -> Result<(), ArchiveError> {
        let mut sorted = lock(&self.sorted);
        if sorted.is_some() || !lock(&self.entries).permutations.is_empty() {
            return Err(ArchiveError::Input("a sorted manifest begun after permutations were added".into()));
        }
        let slots = lock(&self.blobs).slots;
        // Its parts in files where the manifest would not fit the spool's memory, or where
        // the blobs' bytes are in a file already (a large set).
        let spill =
            self.spool.file.get().is_some() || permutations.saturating_mul(MANIFEST_ESTIMATE) > self.spool.limit;
        let s = sorted::Sorted::new(&self.spool.beside, spill, permutations, slots)
            .map_err(|source| ArchiveError::Write { path: self.output.clone(), source })?;
        *sorted = Some(s);
        Ok(())
    }

    /// Adds the next permutation of a sorted manifest ([`StreamingWriter::begin_sorted`]),
    /// its artifacts named by range as [`StreamingWriter::add_permutation_ranged`]'s: an
    /// error if its name does not come after the last one's.
    pub fn add_permutation_sorted(
        &self,
        p: NewPermutation<'_, u32>,
        artifacts: ArtifactRange,
    ) -> Result<(), ArchiveError> {
        let mut sorted = lock(&self.sorted);
        let Some(s) = sorted.as_mut() else {
            return Err(ArchiveError::Input("a permutation added in name order to an unsorted manifest".into()));
        };
        let e = lock(&self.entries);
        let (targets, blobs) = (&e.arenas.targets, &e.arenas.blobs);
        let range = (artifacts.first as usize).checked_add(artifacts.count.into()).and_then(|end| {
            Some((targets.get(artifacts.first as usize..end)?, blobs.get(artifacts.first as usize..end)?))
        });
        let Some(range) = range else {
            return Err(ArchiveError::Input(format!("permutation `{}` names artifacts of no writer", p.name)));
        };
        s.add(&p, range.0.iter().copied().zip(range.1.iter().copied()))
    }

    /// [`StreamingWriter::add_permutation_sorted`] of a permutation that names its own
    /// artifacts (blobs numbered by [`StreamingWriter::add_blob_numbered`]): a caller that
    /// reads each permutation's artifacts as it comes holds none of them, where handing
    /// them over ([`StreamingWriter::add_artifacts`]) keeps all of them until the end.
    pub fn add_permutation_sorted_numbered(&self, p: NewPermutation<'_, u32>) -> Result<(), ArchiveError> {
        lock(&self.blobs).check_numbers(&p.name, &p.artifacts)?;
        let mut sorted = lock(&self.sorted);
        let Some(s) = sorted.as_mut() else {
            return Err(ArchiveError::Input("a permutation added in name order to an unsorted manifest".into()));
        };
        s.add(&p, p.artifacts.iter().copied())
    }

    /// Room for `permutations` more permutations with `name_bytes` bytes of names (at most:
    /// less their shaders' prefixes), `values` values and `artifacts` artifacts in all: a
    /// caller that knows the manifest's size saves the copies of arenas that grow by
    /// doubling (and their transient peak; room never used is never touched).
    pub fn reserve(&self, permutations: usize, name_bytes: usize, values: usize, artifacts: usize) {
        let mut e = lock(&self.entries);
        e.permutations.reserve_exact(permutations);
        e.arenas.names.reserve_exact(name_bytes);
        e.arenas.values.reserve_exact(values);
        e.arenas.targets.reserve_exact(artifacts);
        e.arenas.blobs.reserve_exact(artifacts);
    }

    /// Room for `blobs` more blobs: a caller that knows a bound saves the copies of the
    /// added bits as they grow (their pages past the blobs added are never touched). The
    /// table that finds blobs still grows: a table at a loose bound would be touched all
    /// over, empty or not.
    pub fn reserve_blobs(&self, blobs: usize) {
        let mut table = lock(&self.blobs);
        table.added_bits.reserve_exact(blobs.div_ceil(64));
    }

    /// Number of distinct blobs added so far.
    pub fn blob_count(&self) -> usize {
        lock(&self.blobs).added
    }

    /// At most `more` distinct blobs are named beyond those named so far: the table that
    /// finds them by content is made that large now, if it is smaller, instead of growing
    /// as they come (see [`StreamingWriter::reserve_blobs`] for a loose bound, which should
    /// not). Only the table's size depends on it: blob numbers and the archive's bytes do
    /// not.
    pub fn expect_blobs(&self, more: usize) -> Result<(), ArchiveError> {
        self.table(self.previous()).and_then(|mut t| t.expect(more)).map_err(|source| {
            self.failed.store(true, Ordering::Relaxed);
            ArchiveError::Write { path: self.output.clone(), source }
        })
    }

    /// No more blobs will be added, nor permutations named by [`BlobKey`] (those are
    /// errors now; [`StreamingWriter::add_permutation_numbered`] still works): lets go of the
    /// table that finds blobs by content (the previous archive's among them: those found
    /// are taken by id from here on), before the manifest is added.
    pub fn seal_blobs(&mut self) {
        lock(&self.blobs).seal();
    }

    /// Assembles the archive and writes it atomically (temporary file, fsync, rename).
    pub fn finish(self) -> Result<ArchiveSummary, ArchiveError> {
        self.finish_impl(true)
    }

    /// [`StreamingWriter::finish`] without the fsync: still atomic for readers, not durable
    /// across a power loss, like a compiler's outputs.
    pub fn finish_unsynced(self) -> Result<ArchiveSummary, ArchiveError> {
        self.finish_impl(false)
    }

    fn finish_impl(self, sync: bool) -> Result<ArchiveSummary, ArchiveError> {
        let err = |source| ArchiveError::Write { path: self.output.clone(), source };
        if self.failed.load(Ordering::Relaxed) {
            return Err(err(std::io::Error::other("a blob could not be spooled")));
        }
        let entries = self.entries.into_inner().unwrap_or_else(|e| e.into_inner());
        let blobs = self.blobs.into_inner().unwrap_or_else(|e| e.into_inner());
        let mut plan = match self.sorted.into_inner().unwrap_or_else(|e| e.into_inner()) {
            Some(sorted) => plan_sorted(entries, blobs, sorted)?,
            None => plan(entries, blobs)?,
        };
        plan.previous = self.previous.into_inner().flatten();
        (plan.hooks.trace)("archive planned");
        // The manifest and the blob table are spilled past the blobs: to the file when all
        // of it would not fit the spool's memory (blobs added by reference leave the spool
        // nearly empty, however large the set).
        let spilled =
            plan.targets.len() * super::format::ENTRY_LEN + plan.manifest.permutations.len() * (RECORD_LEN + ID_LEN);
        if plan.spool_len as usize + spilled > self.spool.limit {
            self.spool.move_to_file(&mut lock(&self.spool.memory)).map_err(err)?;
        }
        let memory = self.spool.memory.into_inner().unwrap_or_else(|e| e.into_inner());
        let spool = match (&memory, self.spool.file.get()) {
            (Some(m), _) => Spool::Memory(m),
            (None, Some(f)) => Spool::File(f),
            (None, None) => return Err(err(std::io::Error::other("the spool's file is missing"))),
        };
        let mut summary = ArchiveSummary::default();
        write_atomic_with(&self.output, sync, |f| {
            summary = write_archive(plan, &spool, f)?;
            Ok(())
        })
        .map_err(err)?;
        Ok(summary)
    }
}

/// `p` with its artifacts' keys turned into numbers by `number` (`None` where it gives none).
fn numbered<'a>(
    p: NewPermutation<'a>,
    mut number: impl FnMut(&BlobKey) -> Option<u32>,
) -> Option<NewPermutation<'a, u32>> {
    let artifacts = p.artifacts.iter().map(|(t, k)| Some((*t, number(k)?))).collect::<Option<_>>()?;
    Some(NewPermutation { name: p.name, shader: p.shader, values: p.values, reflection: p.reflection, artifacts })
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    // A panic elsewhere while holding the lock leaves plain data behind: still usable.
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// Collects permutations and artifacts in memory, with index-based handles, and writes the
/// same archive a [`StreamingWriter`] would.
#[derive(Default)]
pub struct ArchiveWriter {
    entries: Entries,
    /// Local handles of `add_shader` and `add_reflection`.
    shaders: Vec<ShaderRecord>,
    shader_handles: HashMap<(String, String), u32>,
    reflections: Vec<Reflection>,
    reflection_handles: HashMap<Reflection, u32>,
    /// Each blob (a `BlobId` is its number), and where its bytes lie in `spool`.
    blobs: BlobTable,
    spool: Vec<u8>,
    /// The first inconsistency found by `add_permutation`, reported when writing.
    error: Option<String>,
}

impl ArchiveWriter {
    /// An empty archive.
    pub fn new() -> Self {
        ArchiveWriter::default()
    }

    /// Records the naga version the artifacts were produced with (shown by `kiln inspect`).
    pub fn set_naga_version(&mut self, version: &str) {
        self.entries.naga_version = version.to_string();
    }

    /// Stores a pipeline manifest, as [`StreamingWriter::set_pipelines`].
    pub fn set_pipelines(&mut self, pipelines: Vec<PipelineRecord>) {
        self.entries.pipelines = Some(pipelines);
    }

    /// Adds a (shader, level) record; returns its handle. Adding the same pair twice returns
    /// the first handle. Shaders no permutation uses are left out of the archive.
    pub fn add_shader(&mut self, record: ShaderRecord) -> u32 {
        let key = (record.name.clone(), record.level.clone());
        if let Some(&i) = self.shader_handles.get(&key) {
            return i;
        }
        let i = self.shaders.len() as u32;
        self.shaders.push(record);
        self.shader_handles.insert(key, i);
        i
    }

    /// Adds a blob, returning the handle of an identical blob already added where there is one.
    pub fn add_blob(&mut self, bytes: &[u8]) -> BlobId {
        self.add_blob_hashed(bytes, blake3::hash(bytes))
    }

    /// [`ArchiveWriter::add_blob`] for bytes whose blake3 `hash` the caller computed.
    pub fn add_blob_hashed(&mut self, bytes: &[u8], hash: blake3::Hash) -> BlobId {
        debug_assert_eq!(hash, blake3::hash(bytes));
        let (n, offset) = self.blobs.insert(&hash, bytes.len() as u64, SPOOLED).expect("a log in memory");
        if offset.is_some() {
            self.spool.extend_from_slice(&spool_header(&hash, bytes));
            self.spool.extend_from_slice(bytes);
        }
        BlobId(n)
    }

    /// Adds `reflection` once, and gives its index in the manifest.
    pub fn add_reflection(&mut self, reflection: &Reflection) -> u32 {
        if let Some(&i) = self.reflection_handles.get(reflection) {
            return i;
        }
        let i = self.reflections.len() as u32;
        self.reflections.push(reflection.clone());
        self.reflection_handles.insert(reflection.clone(), i);
        i
    }

    /// Adds a permutation whose `shader`, `reflection` and blob ids are handles this writer
    /// gave. A bad handle is reported when the archive is written.
    pub fn add_permutation(&mut self, record: PermutationRecord) {
        let shader = self.shaders.get(record.shader as usize);
        let reflection = self.reflections.get(record.reflection as usize);
        let artifacts: Vec<(Target, u32)> = record.artifacts.iter().map(|(t, id)| (*t, id.0)).collect();
        let known = self.blobs.check_numbers(&record.name, &artifacts).is_ok();
        let (Some(shader), Some(reflection), true) = (shader, reflection, known) else {
            self.error.get_or_insert_with(|| format!("permutation `{}` names a handle of no writer", record.name));
            return;
        };
        let p = NewPermutation { name: record.name, shader, values: record.values, reflection, artifacts };
        if let Err(e) = self.entries.add(p, None) {
            self.error.get_or_insert_with(|| e.to_string());
        }
    }

    /// Number of distinct blobs so far.
    pub fn blob_count(&self) -> usize {
        self.blobs.added
    }

    fn plan(&self) -> Result<Plan, ArchiveError> {
        if let Some(e) = &self.error {
            return Err(ArchiveError::Input(e.clone()));
        }
        let LocLog::Memory(log) = &self.blobs.log else {
            return Err(ArchiveError::Input("an in-memory writer with a log in a file".into()));
        };
        let mut table = BlobTable::new(LocLog::Memory(log.clone()), None);
        table.slots = self.blobs.slots;
        table.added = self.blobs.added;
        table.spooled = self.blobs.spooled;
        table.added_bits = self.blobs.added_bits.clone();
        table.idents.pending = self.blobs.idents.pending.clone();
        plan(self.entries.clone(), table)
    }

    /// The whole archive as bytes.
    pub fn to_bytes(&self) -> Result<Vec<u8>, ArchiveError> {
        let plan = self.plan()?;
        let mut out = Cursor::new(Vec::new());
        write_archive(plan, &Spool::Memory(&self.spool), &mut out)
            .map_err(|source| ArchiveError::Write { path: PathBuf::from("<memory>"), source })?;
        Ok(out.into_inner())
    }

    /// Writes the archive to `path` atomically: a temporary file in the same folder, synced,
    /// then renamed over `path`. A reader never sees a half-written archive.
    pub fn write(&self, path: &Path) -> Result<ArchiveSummary, ArchiveError> {
        self.write_impl(path, true)
    }

    /// [`ArchiveWriter::write`] without the fsync.
    pub fn write_unsynced(&self, path: &Path) -> Result<ArchiveSummary, ArchiveError> {
        self.write_impl(path, false)
    }

    fn write_impl(&self, path: &Path, sync: bool) -> Result<ArchiveSummary, ArchiveError> {
        let plan = self.plan()?;
        let mut summary = ArchiveSummary::default();
        write_atomic_with(path, sync, |f| {
            summary = write_archive(plan, &Spool::Memory(&self.spool), f)?;
            Ok(())
        })
        .map_err(|source| ArchiveError::Write { path: path.to_path_buf(), source })?;
        Ok(summary)
    }
}

/// What the archive will hold, in its final order; only the blob bytes are still elsewhere.
struct Plan {
    hooks: WriterHooks,
    manifest: Manifest,
    /// Each blob of the archive's target, by blob id.
    targets: Vec<Target>,
    /// Each slot of the writer's table's blob id (`u32::MAX` for a blob added but named by
    /// no permutation): the numbering made here, kept for the blobs' locations rather than
    /// made again from a list of each id's slot (4 bytes a blob fewer at the build's end).
    id_of: Vec<u32>,
    /// The writer's blob table, sealed: where its log of blob locations is (read back once
    /// the manifest is spilled, see [`write_archive`]).
    table: BlobTable,
    /// Where the spool's blobs end.
    spool_len: u64,
    /// The archive this one replaces, whose compressed blobs may be copied.
    previous: Option<Previous>,
    /// The manifest's parts, encoded as its permutations came in name order (then
    /// `manifest` has its shaders and reflections, and no permutations).
    sorted: Option<sorted::SortedParts>,
}

/// Sorts permutations by name and numbers shaders, reflections and blobs by first use, so
/// the result depends on the set added, not on the order of adding. The arenas are kept:
/// the manifest's permutations point into them. The permutations are sorted and the
/// artifacts' slots turned into blob ids in place: no second copy of either table (they
/// grow with the set, and this runs at the build's end, on top of the manifest).
fn plan(entries: Entries, mut table: BlobTable) -> Result<Plan, ArchiveError> {
    table.seal();
    let (spool_len, slots) = (table.spooled, table.slots);
    let Entries { naga_version, partial, pipelines, hooks, shaders, reflections, mut permutations, mut arenas, .. } =
        entries;
    let mut buffers = Default::default();
    permutations.sort_unstable_by(|a, b| arenas.cmp_names((a, b), &shaders, &mut buffers));
    if let Some(w) = permutations.windows(2).find(|w| arenas.cmp_names((&w[0], &w[1]), &shaders, &mut buffers).is_eq())
    {
        return Err(ArchiveError::Input(format!("permutation `{}` was added twice", arenas.name_of(&w[0], &shaders))));
    }
    drop(buffers);
    let mut shaders: Vec<Option<ShaderRecord>> = shaders.into_iter().map(Some).collect();
    let mut reflections: Vec<Option<Reflection>> = reflections.into_iter().map(Some).collect();
    let mut shader_map: Vec<Option<u32>> = vec![None; shaders.len()];
    let mut reflection_map: Vec<Option<u32>> = vec![None; reflections.len()];
    let mut manifest =
        Manifest { kiln_version: crate::VERSION.to_string(), naga_version, partial, pipelines, ..Default::default() };
    // The shaders' prefixes in the manifest's numbering.
    let mut prefixes = Vec::with_capacity(shaders.len());
    // Each slot's blob id, by first use.
    let mut blob_ids: Vec<u32> = vec![u32::MAX; slots];
    // At most every blob added is named: room for them all at once, not grown by doubling
    // on top of the manifest.
    let mut targets = Vec::with_capacity(table.added);
    // One bit an artifact: its blob is numbered already.
    let mut numbered = vec![0u64; arenas.targets.len().div_ceil(64)];
    for p in permutations.iter_mut() {
        p.shader = *shader_map[p.shader as usize].get_or_insert_with(|| {
            manifest.shaders.push(shaders[p.shader as usize].take().expect("taken once"));
            prefixes.push(std::mem::take(&mut arenas.prefixes[p.shader as usize]));
            manifest.shaders.len() as u32 - 1
        });
        p.reflection = *reflection_map[p.reflection as usize].get_or_insert_with(|| {
            manifest.reflections.push(reflections[p.reflection as usize].take().expect("taken once"));
            manifest.reflections.len() as u32 - 1
        });
        let first = p.first_artifact as usize;
        let range = first..first + p.artifact_count as usize;
        // Each artifact's slot becomes its blob id once: at the first permutation that names
        // it (permutations may share artifacts: see `StreamingWriter::add_artifacts`).
        for (k, (target, slot)) in range.clone().zip(arenas.targets[range.clone()].iter().zip(&mut arenas.blobs[range]))
        {
            if numbered[k / 64] & (1 << (k % 64)) != 0 {
                continue;
            }
            numbered[k / 64] |= 1 << (k % 64);
            *slot = match blob_ids[*slot as usize] {
                u32::MAX => {
                    if !table.is_added(*slot) {
                        // The prefixes and shaders in the manifest's numbering, as `p`'s now.
                        arenas.prefixes = std::mem::take(&mut prefixes);
                        return Err(ArchiveError::Input(format!(
                            "permutation `{}` names a {target} blob that was never added",
                            arenas.name_of(p, &manifest.shaders)
                        )));
                    }
                    let id = targets.len() as u32;
                    targets.push(*target);
                    blob_ids[*slot as usize] = id;
                    id
                }
                id => id,
            };
        }
    }
    table.added_bits = Vec::new();
    arenas.prefixes = prefixes;
    manifest.permutations = permutations;
    manifest.arenas = arenas;
    Ok(Plan { hooks, manifest, targets, id_of: blob_ids, table, spool_len, previous: None, sorted: None })
}

/// [`plan`] of a manifest whose permutations came in name order ([`sorted::Sorted`]):
/// encoded already, its blobs numbered.
fn plan_sorted(entries: Entries, mut table: BlobTable, sorted: sorted::Sorted) -> Result<Plan, ArchiveError> {
    table.seal();
    let spool_len = table.spooled;
    let Entries { naga_version, partial, pipelines, hooks, arenas, .. } = entries;
    // The keys' artifacts, which the permutations named by range: encoded with them.
    drop(arenas);
    let (id_of, targets, mut parts) = sorted.finish(&table)?;
    table.added_bits = Vec::new();
    let manifest = Manifest {
        kiln_version: crate::VERSION.to_string(),
        naga_version,
        partial,
        pipelines,
        shaders: std::mem::take(&mut parts.shaders),
        reflections: std::mem::take(&mut parts.reflections),
        ..Default::default()
    };
    Ok(Plan { hooks, manifest, targets, id_of, table, spool_len, previous: None, sorted: Some(parts) })
}

/// Runs `f` over `items` with one `init()` state per worker of the current rayon pool (the
/// build's own pool when a build writes the archive), the results in `items`' order.
fn par_map<T: Sync, U: Send, S>(
    items: &[T],
    init: impl Fn() -> S + Sync + Send,
    f: impl Fn(&mut S, &T) -> U + Sync + Send,
) -> Vec<U> {
    use rayon::prelude::*;
    items.par_iter().map_init(init, f).collect()
}

/// Trains a target's dictionary on `sample` (locations of an evenly spaced sample of its
/// blobs, at most [`DICTIONARY_SAMPLE`] bytes); `None` when there is too little to learn
/// from. The sample is read straight into the one buffer zstd trains on (no copy per blob
/// from the spool; a blob added by reference is decompressed from the previous archive).
fn train(sample: &[Loc], sources: &BlobSources<'_, '_>) -> std::io::Result<Option<Vec<u8>>> {
    let sizes: Vec<usize> = sample.iter().map(|b| b.len as usize).collect();
    let sampled: usize = sizes.iter().sum();
    // A dictionary pays for itself only over many artifacts of a kind.
    let capacity = (sampled / 16).min(DICTIONARY_SIZE);
    if sample.len() < 8 || capacity < 1024 {
        return Ok(None);
    }
    let mut flat = vec![0u8; sampled];
    let mut at = 0;
    for b in sample {
        let len = b.len as usize;
        match b.previous {
            SPOOLED => sources.spool.read_into(b.offset, &mut flat[at..at + len])?,
            id => {
                let previous = sources.previous.ok_or_else(changed)?;
                let raw = previous.raw(id).map_err(std::io::Error::other)?;
                flat.get_mut(at..at + len).filter(|_| raw.len() == len).ok_or_else(changed)?.copy_from_slice(&raw);
                // Sampled blobs lie all over the file, and each read maps the pages around
                // it: given back as they come, not once the sample is read.
                previous.release_pages();
            }
        }
        at += len;
    }
    Ok(train_fast_cover(&flat, &sizes, capacity).filter(|d| !d.is_empty()))
}

/// Each target's sample: the blobs whose identity (the start of their blake3) begins with
/// `k` zero bits, `k` the least for which the target's bytes divided by 2^k come to at most
/// one and a half [`DICTIONARY_SAMPLE`] (so the expected sample is 0.75 to 1.5 times that),
/// in id order, at most twice that many bytes; none for a target of fewer than
/// [`DICTIONARY_MIN_BYTES`] or [`DICTIONARY_MIN_BLOBS`]. Which blobs a sample holds depends on each blob alone, not on its place
/// among the others: a change to a few blobs leaves the sample, and so the dictionary, as
/// it was unless one of them is sampled (or the target's bytes cross a power of two, which
/// changes `k`), and the previous archive's compressed blobs stay
/// reusable ([`Previous`]). Located in three passes over the log and one over the
/// identities, not from a table of every blob's place.
fn samples(
    blob_targets: &[Target],
    table: &mut BlobTable,
    id_of: &[u32],
) -> std::io::Result<[Vec<Loc>; Target::ALL.len()]> {
    let (mut totals, mut counts) = ([0u64; Target::ALL.len()], [0usize; Target::ALL.len()]);
    table.scan(id_of, |id, loc| {
        totals[blob_targets[id] as usize] += loc.len;
        counts[blob_targets[id] as usize] += 1;
    })?;
    // A target with too few bytes or blobs to pay for a dictionary's training samples nothing.
    let mut shifts = [None; Target::ALL.len()];
    for (t, shift) in shifts.iter_mut().enumerate() {
        if totals[t] >= DICTIONARY_MIN_BYTES && counts[t] >= DICTIONARY_MIN_BLOBS {
            *shift = Some((0..64).find(|k| totals[t] >> k <= DICTIONARY_SAMPLE as u64 * 3 / 2).unwrap_or(64));
        }
    }
    let mut picked: Vec<u32> = Vec::new();
    table.idents.for_each(table.slots, |slot, id| {
        let blob = id_of.get(slot).copied().unwrap_or(u32::MAX);
        if blob == u32::MAX {
            return;
        }
        let Some(k) = shifts[blob_targets[blob as usize] as usize] else { return };
        let start = u64::from_be_bytes(id[..8].try_into().expect("8 of 16 bytes"));
        if k == 0 || start >> (64 - k) == 0 {
            picked.push(blob);
        }
    })?;
    picked.sort_unstable();
    let mut locs = vec![Loc { offset: 0, len: 0, previous: SPOOLED }; picked.len()];
    table.scan(id_of, |id, loc| {
        if let Ok(i) = picked.binary_search(&(id as u32)) {
            locs[i] = loc;
        }
    })?;
    let mut samples: [Vec<Loc>; Target::ALL.len()] = Default::default();
    let mut bytes = [0u64; Target::ALL.len()];
    for (id, loc) in picked.iter().zip(locs) {
        let t = blob_targets[*id as usize] as usize;
        if bytes[t] + loc.len <= 2 * DICTIONARY_SAMPLE as u64 {
            bytes[t] += loc.len;
            samples[t].push(loc);
        }
    }
    Ok(samples)
}

/// fastCover segment size `k` and d-mer size `d` of dictionary training, fixed: one training
/// instead of `ZDICT_trainFromBuffer`'s search over five values of `k` (each a training and a
/// test compression). The measurements behind this and the next two constants are in
/// `docs/design/2026-11-archive-format-measurements.md`.
const FASTCOVER_K: u32 = 1024;
/// fastCover's d-mer size.
const FASTCOVER_D: u32 = 8;
/// log2 of fastCover's frequency table's entries at most (zstd's default is 20): smaller
/// tables, which a build zeroes and touches per target, for dictionaries about as good.
const FASTCOVER_F: u32 = 18;

/// log2 of fastCover's frequency table's entries for `sampled` bytes of samples: a quarter
/// as many entries as bytes, from 2^14 to 2^[`FASTCOVER_F`]. A small set's samples fill
/// few entries of a large table, which costs its zeroing and page faults for nothing.
fn fastcover_f(sampled: usize) -> u32 {
    let bits = usize::BITS - sampled.max(1).leading_zeros();
    bits.saturating_sub(2).clamp(14, FASTCOVER_F)
}

/// fastCover's acceleration (1 to 10): how sparsely it samples the d-mers it counts; sparser
/// trains faster for dictionaries about as good.
const FASTCOVER_ACCEL: u32 = 4;

/// A dictionary of at most `capacity` bytes trained on the samples laid end to end in `flat`
/// (`sizes` long each), with the archive's fixed fastCover parameters; `None` when zstd
/// finds nothing to learn. Deterministic. The compiler's cache trains its own with this.
pub fn train_dictionary(flat: &[u8], sizes: &[usize], capacity: usize) -> Option<Vec<u8>> {
    train_fast_cover(flat, sizes, capacity)
}

/// One fastCover training with fixed parameters on the samples laid end to end in `flat`
/// (`sizes` long each) into at most `capacity` bytes; `None` when zstd finds nothing to
/// learn. Deterministic: same samples, same dictionary.
fn train_fast_cover(flat: &[u8], sizes: &[usize], capacity: usize) -> Option<Vec<u8>> {
    use zstd::zstd_safe::zstd_sys;
    if sizes.iter().sum::<usize>() != flat.len() {
        return None;
    }
    let params = zstd_sys::ZDICT_fastCover_params_t {
        k: FASTCOVER_K,
        d: FASTCOVER_D,
        f: fastcover_f(flat.len()),
        steps: 0,
        nbThreads: 1,
        splitPoint: 1.0,
        accel: FASTCOVER_ACCEL,
        shrinkDict: 0,
        shrinkDictMaxRegression: 0,
        zParams: zstd_sys::ZDICT_params_t { compressionLevel: COMPRESSION_LEVEL, notificationLevel: 0, dictID: 0 },
    };
    let mut dict = vec![0u8; capacity];
    // SAFETY: `dict` is writable for `capacity` bytes, `flat` holds exactly the sum of `sizes`
    // bytes (checked above), and `sizes` has fewer than u32::MAX elements (checked by the
    // conversion); zstd reads and writes only within those bounds.
    let written = unsafe {
        zstd_sys::ZDICT_trainFromBuffer_fastCover(
            dict.as_mut_ptr().cast(),
            capacity,
            flat.as_ptr().cast(),
            sizes.as_ptr(),
            u32::try_from(sizes.len()).ok()?,
            params,
        )
    };
    // SAFETY: ZDICT_isError only inspects the code.
    if unsafe { zstd_sys::ZDICT_isError(written) } != 0 {
        return None;
    }
    dict.truncate(written);
    Some(dict)
}

/// The fewest bytes of a target's artifacts that get a dictionary. Below this the whole
/// target compresses to a few hundred KiB without one, and training it is a good part of a
/// small build's time: the dictionary saves bytes nobody misses at the cost of time. The
/// unit tests' sets are smaller, and train from a lower threshold.
const DICTIONARY_MIN_BYTES: u64 = if cfg!(test) { 64 << 10 } else { 512 << 10 };

/// The fewest distinct blobs of a target that get a dictionary, whatever their bytes: a set
/// of about a hundred sources has no more per target, and there its training was a large
/// share of what the build costs beyond naga's own work (large sources, so many bytes)
/// while the archive it shrinks stays around a megabyte. Decided from the set's blobs
/// alone, so the archive's bytes still depend only on the set. The unit tests' sets are
/// smaller, and train from a lower count.
const DICTIONARY_MIN_BLOBS: usize = if cfg!(test) { 8 } else { 128 };

/// The most bytes of samples, all targets together, that are trained in parallel.
const PARALLEL_TRAINING_BYTES: u64 = 4 << 20;

/// The trained dictionaries, by target, and each one's compiled form for compression (the
/// compiled form, zstd's tables of a dictionary, made on the same worker that trained it).
type Dictionaries = (Vec<(Target, Vec<u8>)>, Vec<Option<zstd::zstd_safe::CDict<'static>>>);

/// Trains the dictionary of each of `targets` (those with enough to learn from), one after
/// another: this runs at the build's end on top of the manifest, where a build's memory
/// peaks, so trainings do not add their samples and tables to each other's.
fn dictionaries(
    blob_targets: &[Target],
    table: &mut BlobTable,
    id_of: &[u32],
    targets: &[Target],
    sources: &BlobSources<'_, '_>,
) -> std::io::Result<Dictionaries> {
    let samples = samples(blob_targets, table, id_of)?;
    let train_one = |_: &mut (), t: &Target| -> std::io::Result<_> {
        Ok(train(&samples[*t as usize], sources)?.map(|d| {
            let cdict = zstd::zstd_safe::CDict::try_create(&d, COMPRESSION_LEVEL);
            (*t, d, cdict)
        }))
    };
    // Small samples train side by side: their buffers and tables are small, and on a small
    // set the trainings are a good part of the archive's time.
    let sampled: u64 = samples.iter().flatten().map(|l| l.len).sum();
    let trained: Vec<_> = if sampled <= PARALLEL_TRAINING_BYTES {
        par_map(targets, || (), train_one)
    } else {
        targets.iter().map(|t| train_one(&mut (), t)).collect()
    };

    let (mut dictionaries, mut cdicts) = (Vec::new(), Vec::new());
    for t in trained {
        if let Some((target, d, cdict)) = t? {
            dictionaries.push((target, d));
            cdicts.push(cdict);
        }
    }
    Ok((dictionaries, cdicts))
}

/// Writes the archive of `plan` to `out` (from its current position 0) and returns its sizes.
///
/// It consumes the plan: the manifest is encoded first (but for its header and dictionary
/// records, which wait for the dictionaries) to the spool file past the blobs and their
/// table, or to memory with an in-memory spool, and its arenas let go before the blobs are
/// compressed (the release hook is called then); it is copied into the archive, hashed as it
/// goes, once the blobs are written.
fn write_archive<W: Write + Seek>(plan: Plan, spool: &Spool<'_>, out: &mut W) -> std::io::Result<ArchiveSummary> {
    let Plan { hooks, manifest, targets: blobs, id_of, table: mut blob_table, spool_len, previous, mut sorted } = plan;
    let spilled = match sorted.as_mut() {
        Some(parts) => spilled_sorted(&manifest, parts)?,
        None => {
            let spill_at = spool_len + blobs.len() as u64 * super::format::ENTRY_LEN as u64;
            spill_manifest(manifest, spool, spill_at, hooks)?
        }
    };
    let mut summary = ArchiveSummary { permutations: spilled.counts.permutations as usize, ..Default::default() };
    // Where each blob lies is read back from the log only now that the manifest is gone, a
    // window of blob ids at a time.
    (hooks.release)();
    (hooks.trace)("manifest spilled");

    let mut out = BufWriter::with_capacity(1 << 20, out);
    out.seek(SeekFrom::Start(0))?;
    out.write_all(&[0u8; HEADER_LEN])?;

    // Dictionaries, trained (and made ready to compress with) one target after another.
    let targets: Vec<Target> = Target::ALL.into_iter().filter(|t| blobs.contains(t)).collect();
    let sources = BlobSources { spool, previous: previous.as_ref() };
    let (dictionaries, cdicts) = dictionaries(&blobs, &mut blob_table, &id_of, &targets, &sources)?;

    // The blob section, compressed in batches so memory holds one batch at a time.
    let mut table = SpillBuf::new(spool, spool_len, blobs.len() * super::format::ENTRY_LEN);
    let dicts = BlobDictionaries { targets: &blobs, dictionaries: &dictionaries, cdicts: &cdicts };
    let (blobs_len, raw_bytes, reused) = write_blobs(&dicts, &sources, &mut blob_table, &id_of, &mut out, &mut table)?;
    (summary.raw_bytes, summary.reused_blobs) = (raw_bytes, reused);
    summary.blobs = blobs.len();
    let blob_count = blobs.len() as u64;
    drop((blobs, id_of, blob_table, previous));
    summary.stored_bytes = blobs_len;
    pad8(&mut out, HEADER_LEN as u64 + blobs_len)?;

    let (dictionary_records, dict_offset) = write_dictionaries(&dictionaries, &mut out)?;
    summary.dictionary_bytes = dict_offset;
    drop(cdicts);
    drop(dictionaries);
    let counts = ManifestCounts { dictionaries: dictionary_records.len() as u64, ..spilled.counts };
    let manifest_len = counts.layout().ok_or_else(|| std::io::Error::other("the manifest's parts overflow"))?.end;
    let sections =
        Sections { blobs_len, dictionaries_len: dict_offset, manifest_len, blob_count, chunk_len: CHUNK_LEN };
    let layout = sections.layout().ok_or_else(|| std::io::Error::other("archive sections overflow"))?;
    pad8(&mut out, layout.dictionaries + dict_offset)?;
    // The chunk hashes come before the manifest: their room is left now and filled once the
    // manifest and table, hashed as they are written, are done.
    let hashes_len = (layout.manifest - layout.chunks) as usize;
    std::io::copy(&mut std::io::repeat(0).take(hashes_len as u64), &mut out)?;
    let mut hasher = ChunkHasher::new(CHUNK_LEN);
    let mut tee = Tee { out: &mut out, hasher: &mut hasher, written: 0 };
    // The manifest: its header, the spilled records, ids, values and artifacts, the
    // dictionary records, then the spilled tables and names.
    tee.write_all(&counts.encode())?;
    let SpilledManifest { front, back, .. } = spilled;
    for part in front {
        part.copy_to(&mut tee)?;
    }
    for d in &dictionary_records {
        tee.write_all(&d.encode())?;
    }
    for part in back {
        part.copy_to(&mut tee)?;
    }
    if tee.written != manifest_len {
        return Err(std::io::Error::other("the manifest's length differs from its counts"));
    }
    hasher.finish();
    pad8(&mut out, layout.manifest + manifest_len)?;
    let mut tee = Tee { out: &mut out, hasher: &mut hasher, written: 0 };
    table.copy_to(&mut tee)?;
    hasher.finish();
    if hasher.hashes.len() != hashes_len {
        return Err(std::io::Error::other("the chunk hashes' length differs from the layout's"));
    }
    let fields = sections.header_fields();
    let sum = header_checksum(&fields, &hasher.hashes);
    out.seek(SeekFrom::Start(layout.chunks))?;
    out.write_all(&hasher.hashes)?;
    out.seek(SeekFrom::Start(0))?;
    out.write_all(&fields)?;
    out.write_all(sum.as_bytes())?;
    out.flush()?;
    summary.file_bytes = layout.end;
    Ok(summary)
}

/// The manifest whose permutations came in name order: its `parts`, encoded already, and
/// its tables from `manifest` (which has no permutations).
fn spilled_sorted<'a>(manifest: &Manifest, parts: &'a mut sorted::SortedParts) -> std::io::Result<SpilledManifest<'a>> {
    let tables = manifest.tables_out();
    let (counts, front, back) = parts.spilled(&tables)?;
    Ok(SpilledManifest { counts, front, back })
}

/// Writes the dictionary section: each dictionary's bytes, one after another; gives their
/// records and the section's length.
fn write_dictionaries(
    dictionaries: &[(Target, Vec<u8>)],
    out: &mut impl Write,
) -> std::io::Result<(Vec<DictionaryRecord>, u64)> {
    let mut offset = 0u64;
    let mut records = Vec::with_capacity(dictionaries.len());
    for (t, d) in dictionaries {
        out.write_all(d)?;
        records.push(DictionaryRecord { target: *t, offset, len: d.len() as u64, blake3: *blake3::hash(d).as_bytes() });
        offset += d.len() as u64;
    }
    Ok((records, offset))
}

/// Each blob's target, and the archive's dictionaries (by index) with their compiled forms.
struct BlobDictionaries<'a> {
    targets: &'a [Target],
    dictionaries: &'a [(Target, Vec<u8>)],
    cdicts: &'a [Option<zstd::zstd_safe::CDict<'static>>],
}

/// Where the blobs come from: the spool, and the archive being replaced ([`Previous`]),
/// whose compressed blobs are copied where compressing again would give the same bytes.
struct BlobSources<'a, 'b> {
    spool: &'a Spool<'b>,
    previous: Option<&'a Previous>,
}

/// A blob as it goes into the archive: codec, dictionary index, stored bytes (borrowed from
/// the previous archive's map where copied from it, not copied again), blake3, and the
/// check sum of its stored bytes where it was copied (read in the previous archive's
/// table, and just checked against them, so not computed a third time).
type StoredBlob<'a> = (u8, u8, Cow<'a, [u8]>, [u8; 32], Option<u64>);

/// Writes the blob section to `out` in blob id order, compressed in batches (so memory
/// holds one batch at a time), and each blob's table entry to
/// `table`; gives the section's length, the blobs' raw bytes and how many were copied from
/// the previous archive.
fn write_blobs(
    dicts: &BlobDictionaries<'_>,
    sources: &BlobSources<'_, '_>,
    blob_table: &mut BlobTable,
    id_of: &[u32],
    out: &mut impl Write,
    table: &mut SpillBuf<'_>,
) -> std::io::Result<(u64, u64, usize)> {
    let count = dicts.targets.len();
    // The blake3 of each dictionary the blobs are compressed with (`None` where zstd could
    // not load it, and blobs of its target are compressed without it).
    let dict_hashes: Vec<Option<[u8; 32]>> = (dicts.dictionaries.iter().zip(dicts.cdicts))
        .map(|((_, d), c)| c.as_ref().map(|_| *blake3::hash(d).as_bytes()))
        .collect();
    let dict_of = |t: Target| dicts.dictionaries.iter().position(|(dt, _)| *dt == t);
    let (mut offset, mut raw_bytes, mut reused, mut start) = (0u64, 0u64, 0, 0);
    let mut locs = BlobLocs::default();
    while start < count {
        if start == locs.first + locs.offsets.len() {
            drop(std::mem::take(&mut locs));
            locs = blob_table.locations(id_of, start..count.min(start + LOC_WINDOW))?;
        }
        let window_end = locs.first + locs.offsets.len();
        let mut end = start;
        let mut batch_bytes = 0u64;
        while end < window_end && (end == start || batch_bytes < (16 << 20)) && end - start < 512 {
            batch_bytes += locs.get(end).len;
            end += 1;
        }
        let batch: Vec<usize> = (start..end).collect();
        let stored = par_map(
            &batch,
            || (),
            |_, &b| -> std::io::Result<StoredBlob> {
                let loc = locs.get(b);
                let dict = dict_of(dicts.targets[b]).and_then(|i| dicts.cdicts[i].as_ref().map(|c| (i, c)));
                let (hash, raw) = match loc.previous {
                    // The whole blake3, which the table stores, as spooled (checked with its bytes).
                    SPOOLED => sources.spool.read_blob(loc)?,
                    id => {
                        let p = sources.previous.ok_or_else(changed)?;
                        let want = dict.map(|(i, _)| dict_hashes[i].as_ref().expect("loaded"));
                        match p.reuse(id, loc.len, want).map_err(std::io::Error::other)? {
                            (hash, Reused::Stored(codec, bytes, sum)) => {
                                let index = dict.map_or(NO_DICTIONARY, |(i, _)| i as u8);
                                return Ok((codec, index, Cow::Borrowed(bytes), hash, Some(sum)));
                            }
                            (hash, Reused::Raw(raw)) => (hash, raw),
                        }
                    }
                };
                if raw.len() as u64 != loc.len {
                    return Err(changed());
                }
                let (codec, dictionary, bytes) = compress_blob(raw, dict);
                Ok((codec, dictionary, Cow::Owned(bytes), hash, None))
            },
        );
        for (&b, s) in batch.iter().zip(stored) {
            let (codec, dictionary, bytes, hash, copied) = s?;
            out.write_all(&bytes)?;
            reused += usize::from(copied.is_some());
            let len = locs.get(b).len;
            let stored_len = bytes.len() as u64;
            let sum = copied.unwrap_or_else(|| stored_sum(&bytes));
            let entry = Entry { offset, stored_len, raw_len: len, codec, dictionary, sum, hash };
            table.push(&entry.encode())?;
            offset += bytes.len() as u64;
            raw_bytes += len;
        }
        if let Some(p) = sources.previous {
            // The previous archive's pages read for this batch: the file keeps them.
            p.release_pages();
        }
        start = end;
    }
    Ok((offset, raw_bytes, reused))
}

thread_local! {
    /// Each thread's zstd context, made once and reused for every blob it compresses (a
    /// context per rayon split allocated and faulted in its tables again each time), and the
    /// buffer it compresses into.
    static CCTX: std::cell::RefCell<(Option<zstd::zstd_safe::CCtx<'static>>, Vec<u8>)> =
        const { std::cell::RefCell::new((None, Vec::new())) };
}

/// One blob as stored: (codec, dictionary index, bytes), with its target's dictionary
/// `dict` (index, compiled dictionary) if it has one; stored raw when zstd does not shrink
/// it. zstd's output depends only on the input and parameters, not on the context's history.
fn compress_blob(raw: Cow<'_, [u8]>, dict: Option<(usize, &zstd::zstd_safe::CDict<'static>)>) -> (u8, u8, Vec<u8>) {
    let compressed = CCTX.with(|cell| {
        let mut cell = cell.borrow_mut();
        let (context, dst) = &mut *cell;
        dst.clear();
        dst.reserve(zstd::zstd_safe::compress_bound(raw.len()));
        let cctx = context.get_or_insert_with(zstd::zstd_safe::CCtx::create);
        let (codec, index, ok) = match dict {
            Some((i, cdict)) => {
                let (ok, clean) = compress_attached(cctx, dst, &raw, cdict);
                if !clean {
                    *context = None;
                }
                (CODEC_ZSTD_DICT, i as u8, ok)
            }
            None => (CODEC_ZSTD, NO_DICTIONARY, cctx.compress(dst, &raw, COMPRESSION_LEVEL).is_ok()),
        };
        // Copied out at its size: a batch's blobs wait to be written, each in a buffer of
        // its raw size otherwise.
        (ok && dst.len() < raw.len()).then(|| (codec, index, dst.to_vec()))
    });
    compressed.unwrap_or_else(|| (CODEC_STORED, NO_DICTIONARY, raw.into_owned()))
}

/// Compresses `raw` with `cdict` attached, not copied: zstd's own choice, for inputs of more
/// than a few kilobytes, copies the dictionary's match tables into the context before every
/// blob, which costs more time than attaching them and saves next to no space. The frame is the one
/// `ZSTD_compress_usingCDict` writes (content size and dictionary id, no checksum), and
/// deterministic: same input, dictionary and level, same bytes. Gives whether it compressed,
/// and whether the context is clean again (it must not keep referring to `cdict`, which the
/// writer drops once the blobs are written: a context that is not is dropped by the caller).
fn compress_attached(
    cctx: &mut zstd::zstd_safe::CCtx<'static>,
    dst: &mut Vec<u8>,
    raw: &[u8],
    cdict: &zstd::zstd_safe::CDict<'static>,
) -> (bool, bool) {
    use zstd::zstd_safe::{CParameter, DictAttachPref, ResetDirective};
    let compressed = cctx
        .ref_cdict(cdict)
        .and_then(|_| cctx.set_parameter(CParameter::ForceAttachDict(DictAttachPref::ForceAttach)))
        .and_then(|_| cctx.compress2(dst, raw));
    let clean = cctx.reset(ResetDirective::SessionAndParameters).is_ok();
    (compressed.is_ok(), clean)
}

/// The manifest encoded but for its header and dictionary records (see [`spill_manifest`]).
struct SpilledManifest<'a> {
    /// Its counts, but for the dictionaries' (zero).
    counts: ManifestCounts,
    /// Its records, ids, values and artifacts: what comes before the dictionary records, in
    /// that order (each part spilled on its own, so that they can be made in another).
    front: [SpillBuf<'a>; 4],
    /// Its tables (padded to 8) and names: what comes after them.
    back: [SpillBuf<'a>; 2],
}

/// Encodes the binary manifest (layout in `format.rs`) of `manifest` to the spool file at
/// `at` (to memory with an in-memory spool), all but its header and dictionary records,
/// which depend on the dictionaries: the parts before the dictionary records, then those
/// after. Each part lies at an offset the counts give, so each is made when it least adds
/// to the memory held, and each arena goes as soon as nothing else needs it: the names
/// first, then the artifacts, and the values and records once the ids (which need both)
/// are made, before they are sorted; the release hook is called once the names are gone.
fn spill_manifest<'a>(
    mut manifest: Manifest,
    spool: &Spool<'a>,
    at: u64,
    hooks: WriterHooks,
) -> std::io::Result<SpilledManifest<'a>> {
    let (p, arenas) = (&manifest.permutations, &manifest.arenas);
    let counts = ManifestCounts {
        permutations: p.len() as u64,
        values: p.iter().map(|p| manifest.shaders[p.shader as usize].dimensions.len() as u64).sum(),
        artifacts: p.iter().map(|p| p.artifact_count as u64).sum(),
        dictionaries: 0,
        tables_len: 0,
        names_len: p.iter().map(|p| p.whole_name_len(arenas)).sum(),
    };
    let lens = [
        counts.permutations * RECORD_LEN as u64,
        counts.permutations * ID_LEN as u64,
        counts.values * VALUE_LEN as u64,
        counts.artifacts * ARTIFACT_LEN as u64,
    ];
    let starts = [at, at + lens[0], at + lens[0] + lens[1], at + lens[0] + lens[1] + lens[2]];
    let mut back = SpillBuf::new(spool, starts[3] + lens[3], 0);
    let tables = manifest.tables_out();
    serde_json::to_writer(&mut back, &tables).map_err(std::io::Error::other)?;
    let tables_len = back.len();
    // The tables start at a multiple of 8 from the manifest's start (every part before them
    // is a whole number of 8-byte fields), so the names' padding depends only on their length.
    pad8(&mut back, tables_len)?;
    write_names(&manifest, &mut back)?;
    back.flush()?;
    manifest.arenas.names = String::new();
    (hooks.release)();

    let [records, ids, values, artifacts] = starts.map(|start| SpillBuf::new(spool, start, 0));
    let records = write_records(&manifest, records)?;
    let artifacts = write_artifacts(&manifest, artifacts)?;
    manifest.arenas.targets = Vec::new();
    manifest.arenas.blobs = Vec::new();
    let values = write_values(&manifest, values)?;
    let ids = write_ids(manifest, ids)?;
    let front = [records, ids, values, artifacts];
    if front.iter().zip(lens).any(|(part, len)| part.len() != len) {
        return Err(std::io::Error::other("the manifest's parts differ from its counts"));
    }
    Ok(SpilledManifest {
        counts: ManifestCounts { tables_len, ..counts },
        front,
        back: [back, SpillBuf::Memory(Vec::new())],
    })
}

/// The permutations' records (their names, values and artifacts one after another).
fn write_records<'a>(manifest: &Manifest, mut out: SpillBuf<'a>) -> std::io::Result<SpillBuf<'a>> {
    let too_many = || std::io::Error::other("the manifest has more than 2^32 values or artifacts");
    let (mut name_offset, mut first_value, mut first_artifact) = (0u64, 0u32, 0u32);
    for p in &manifest.permutations {
        let value_count = manifest.shaders[p.shader as usize].dimensions.len();
        let name_len = p.whole_name_len(&manifest.arenas);
        let record = Record {
            name_offset,
            name_len: u32::try_from(name_len).map_err(|_| too_many())?,
            shader: p.shader,
            reflection: p.reflection,
            first_value,
            first_artifact,
            artifact_count: u32::from(p.artifact_count),
        };
        out.write_all(&record.encode())?;
        name_offset += name_len;
        first_value = u32::try_from(value_count).ok().and_then(|n| first_value.checked_add(n)).ok_or_else(too_many)?;
        first_artifact = first_artifact.checked_add(u32::from(p.artifact_count)).ok_or_else(too_many)?;
    }
    out.flush()?;
    Ok(out)
}

/// The permutations' artifacts, one after another.
fn write_artifacts<'a>(manifest: &Manifest, mut out: SpillBuf<'a>) -> std::io::Result<SpillBuf<'a>> {
    let a = &manifest.arenas;
    for p in &manifest.permutations {
        let range = p.first_artifact as usize..p.first_artifact as usize + p.artifact_count as usize;
        for (t, b) in a.targets[range.clone()].iter().zip(&a.blobs[range]) {
            out.write_all(&encode_artifact(*t, BlobId(*b)))?;
        }
    }
    out.flush()?;
    Ok(out)
}

/// The permutations' values, one after another.
fn write_values<'a>(manifest: &Manifest, mut out: SpillBuf<'a>) -> std::io::Result<SpillBuf<'a>> {
    for p in &manifest.permutations {
        for v in manifest.arenas.values_of(p, manifest.shaders[p.shader as usize].dimensions.len()) {
            out.write_all(&v.to_le_bytes())?;
        }
    }
    out.flush()?;
    Ok(out)
}

/// The permutation id of the `i`th permutation of `manifest`.
fn id_of_permutation(manifest: &Manifest, i: usize, values: &mut Vec<i64>) -> u128 {
    let p = &manifest.permutations[i];
    let s = &manifest.shaders[p.shader as usize];
    values.clear();
    values.extend(manifest.arenas.values_of(p, s.dimensions.len()));
    super::permutation_id(&s.name, &s.level, values)
}

/// The ids table: each permutation's id and index, sorted by id then index. What is sorted
/// is the id's high half and the index, 12 bytes a permutation (the whole id and index are
/// 20, padded to 24), on top of the records and values (the other arenas are gone by now);
/// each whole id is made again as it is written, and the rare ids whose high halves agree
/// are put in order by their whole ids then.
fn write_ids<'a>(manifest: Manifest, mut out: SpillBuf<'a>) -> std::io::Result<SpillBuf<'a>> {
    let mut values = Vec::new();
    let mut ids: Vec<[u32; 3]> = (0..manifest.permutations.len())
        .map(|i| {
            let high = (id_of_permutation(&manifest, i, &mut values) >> 64) as u64;
            [(high >> 32) as u32, high as u32, i as u32]
        })
        .collect();
    ids.sort_unstable();
    let mut run = Vec::new();
    let mut start = 0;
    while start < ids.len() {
        let end = start + ids[start..].iter().take_while(|x| x[..2] == ids[start][..2]).count();
        run.clear();
        run.extend(ids[start..end].iter().map(|x| (id_of_permutation(&manifest, x[2] as usize, &mut values), x[2])));
        if end - start > 1 {
            run.sort_unstable();
        }
        for &(id, index) in &run {
            out.write_all(&encode_id(id, index))?;
        }
        start = end;
    }
    out.flush()?;
    Ok(out)
}

/// The whole names of the manifest's permutations, in order, one after another (derived
/// names made again one at a time).
fn write_names(manifest: &Manifest, out: &mut impl Write) -> std::io::Result<()> {
    let mut name = String::new();
    for p in &manifest.permutations {
        name.clear();
        manifest.arenas.write_name(p, &manifest.shaders, &mut name);
        out.write_all(name.as_bytes())?;
    }
    Ok(())
}

/// Bytes written ahead of where the archive takes them: the blob table while the blobs and
/// the manifest are written (it comes last in the file), and the manifest while the blobs
/// are. With a spool file, in that file past the blobs (both grow with the set, and memory
/// need not hold them); else in memory.
enum SpillBuf<'a> {
    Memory(Vec<u8>),
    File { file: &'a File, start: u64, written: u64, pending: Vec<u8> },
}

/// A [`SpillBuf`] writes its file a buffer of this many bytes at a time.
const SPILL_BUFFER: usize = 1 << 16;

impl<'a> SpillBuf<'a> {
    /// A buffer at `start` in `spool`'s file, or in memory (room for `capacity` bytes).
    fn new(spool: &Spool<'a>, start: u64, capacity: usize) -> Self {
        match spool {
            Spool::File(file) => SpillBuf::File { file, start, written: 0, pending: Vec::new() },
            Spool::Memory(_) => SpillBuf::Memory(Vec::with_capacity(capacity)),
        }
    }

    fn push(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        match self {
            SpillBuf::Memory(v) => v.extend_from_slice(bytes),
            SpillBuf::File { pending, .. } => {
                pending.extend_from_slice(bytes);
                if pending.len() >= SPILL_BUFFER {
                    self.flush_pending()?;
                }
            }
        }
        Ok(())
    }

    /// Bytes pushed.
    fn len(&self) -> u64 {
        match self {
            SpillBuf::Memory(v) => v.len() as u64,
            SpillBuf::File { written, pending, .. } => *written + pending.len() as u64,
        }
    }

    fn flush_pending(&mut self) -> std::io::Result<()> {
        if let SpillBuf::File { file, start, written, pending } = self {
            file.write_all_at(pending, *start + *written)?;
            *written += pending.len() as u64;
            pending.clear();
        }
        Ok(())
    }

    /// Writes `len` bytes from `from` to `out` (after [`SpillBuf::flush_pending`]).
    fn copy_range(&self, from: u64, len: u64, out: &mut impl Write) -> std::io::Result<()> {
        match self {
            SpillBuf::Memory(v) => out.write_all(&v[from as usize..(from + len) as usize]),
            SpillBuf::File { file, start, written, .. } => {
                if from + len > *written {
                    return Err(std::io::Error::other("a spilled part of the archive was not flushed"));
                }
                let mut buf = vec![0u8; (len as usize).min(1 << 20)];
                let mut at = 0u64;
                while at < len {
                    let n = (len - at).min(buf.len() as u64) as usize;
                    file.read_exact_at(&mut buf[..n], *start + from + at)?;
                    out.write_all(&buf[..n])?;
                    at += n as u64;
                }
                Ok(())
            }
        }
    }

    /// Writes everything pushed to `out`.
    fn copy_to(mut self, out: &mut impl Write) -> std::io::Result<()> {
        self.flush_pending()?;
        self.copy_range(0, self.len(), out)
    }
}

impl Write for SpillBuf<'_> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.push(buf)?;
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.flush_pending()
    }
}

/// Writes to `out` and feeds the same bytes to `hasher`.
struct Tee<'a, W: Write> {
    out: &'a mut W,
    hasher: &'a mut ChunkHasher,
    written: u64,
}

impl<W: Write> Write for Tee<'_, W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.out.write(buf)?;
        self.hasher.update(&buf[..n]);
        self.written += n as u64;
        Ok(n)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.out.flush()
    }
}

/// Zero bytes from `at` to the next multiple of 8.
fn pad8(out: &mut impl Write, at: u64) -> std::io::Result<()> {
    let pad = (at.next_multiple_of(8) - at) as usize;
    out.write_all(&[0u8; 8][..pad])
}

#[cfg(test)]
mod blob_table_tests {
    use super::*;

    /// A hash whose first 4 bytes are `prefix` and whose next 4 are `rest`.
    fn hash(prefix: u32, rest: u32) -> blake3::Hash {
        let mut b = [0u8; 32];
        b[..4].copy_from_slice(&prefix.to_le_bytes());
        b[4..8].copy_from_slice(&rest.to_le_bytes());
        blake3::Hash::from_bytes(b)
    }

    /// A spill buffer in a file (past other bytes, written in several buffers) gives back the
    /// same ranges as one in memory, and leaves the bytes before its start alone.
    #[test]
    fn spilled_ranges_read_back_as_written() {
        let file = tempfile::tempfile().unwrap();
        file.write_all_at(b"blobs", 0).unwrap();
        let bytes: Vec<u8> = (0..3 * SPILL_BUFFER + 1234).map(|i| (i * 7 % 251) as u8).collect();
        let (spool_file, spool_memory) = (Spool::File(&file), Spool::Memory(&[]));
        let mut bufs = [SpillBuf::new(&spool_file, 5, 0), SpillBuf::new(&spool_memory, 5, 0)];
        for buf in &mut bufs {
            // Pieces of uneven sizes, some larger than the buffer.
            let mut at = 0;
            for n in [1, 31, SPILL_BUFFER + 3, 7, 2 * SPILL_BUFFER].into_iter().cycle() {
                let end = (at + n).min(bytes.len());
                buf.write_all(&bytes[at..end]).unwrap();
                at = end;
                if at == bytes.len() {
                    break;
                }
            }
            assert_eq!(buf.len(), bytes.len() as u64);
            buf.flush().unwrap();
            for (from, len) in [(0, bytes.len()), (SPILL_BUFFER - 1, 2), (100, 2 * SPILL_BUFFER + 5), (bytes.len(), 0)]
            {
                let mut out = Vec::new();
                buf.copy_range(from as u64, len as u64, &mut out).unwrap();
                assert_eq!(out, &bytes[from..from + len]);
            }
        }
        let [file_buf, _] = bufs;
        let mut all = Vec::new();
        file_buf.copy_to(&mut all).unwrap();
        assert_eq!(all, bytes);
        let mut head = [0u8; 5];
        file.read_exact_at(&mut head, 0).unwrap();
        assert_eq!(&head, b"blobs");
    }

    /// A target's sample is picked by each blob's identity, not by its place among the
    /// others: a blob added, removed or changed elsewhere leaves every other blob in or out
    /// of the sample as it was (so the dictionary stays as it was unless one of them is
    /// sampled), and the sample comes to about [`DICTIONARY_SAMPLE`] bytes.
    #[test]
    fn samples_depend_on_each_blob_not_on_its_neighbours() {
        // Blob `n` is 3,000 + n bytes long, which names it in the sample; the set is well
        // inside one sampling rate (a set whose size crosses a power of two changes it).
        let sample_of = |blobs: &[u64]| -> Vec<u64> {
            let mut t = BlobTable::new(LocLog::Memory(Vec::new()), Some(tempfile::tempfile().unwrap()));
            for n in blobs {
                t.insert(&blake3::hash(&n.to_le_bytes()), 3000 + n, SPOOLED).unwrap();
            }
            t.seal();
            let id_of: Vec<u32> = (0..blobs.len() as u32).collect();
            let s = samples(&vec![Target::Wgsl; blobs.len()], &mut t, &id_of).unwrap();
            assert!(s.iter().enumerate().all(|(t, v)| t == Target::Wgsl as usize || v.is_empty()));
            s[Target::Wgsl as usize].iter().map(|l| l.len - 3000).collect()
        };
        let before: Vec<u64> = (0..4096).collect();
        let mut after = before.clone();
        after.remove(100);
        after.insert(2000, 5000);
        after[3000] = 6000;
        let (a, b) = (sample_of(&before), sample_of(&after));
        let bytes: u64 = a.iter().map(|n| 3000 + n).sum();
        assert!(
            (DICTIONARY_SAMPLE as u64 / 4..=2 * DICTIONARY_SAMPLE as u64).contains(&bytes),
            "{bytes} bytes sampled"
        );
        let keep = |v: &[u64], out: &[u64]| v.iter().copied().filter(|n| !out.contains(n)).collect::<Vec<u64>>();
        assert_eq!(keep(&a, &[100, 3000]), keep(&b, &[5000, 6000]));
        assert!(a.len() < before.len() / 4, "a sample, not every blob: {}", a.len());
    }

    /// Slots past several flushed chunks of identities, each prefix shared by two blobs: every
    /// blob named again finds its own slot (confirmed from the file), never its neighbour's.
    #[test]
    fn shared_prefixes_are_told_apart_by_the_whole_identity() {
        for file in [None, Some(tempfile::tempfile().unwrap())] {
            let mut t = BlobTable::new(LocLog::Memory(Vec::new()), file);
            let count = 3 * IDENT_CHUNK as u32 + 7;
            for i in 0..count {
                assert_eq!(t.number(&hash(i, 1)).unwrap(), Some(2 * i));
                assert_eq!(t.number(&hash(i, 2)).unwrap(), Some(2 * i + 1));
            }
            for i in (0..count).rev() {
                assert_eq!(t.number(&hash(i, 2)).unwrap(), Some(2 * i + 1));
                assert_eq!(t.number(&hash(i, 1)).unwrap(), Some(2 * i));
            }
            assert_eq!(t.slots, 2 * count as usize);
            t.seal();
            assert_eq!(t.number(&hash(0, 1)).unwrap(), None);
        }
    }
}
