//! The compressed encoding of a cache entry (version 6, and versions 5, 4 and 3 read), and
//! the cache's dictionaries.
//!
//! A version 6 entry keeps what a build needs without the artifacts' bytes in a head: each
//! artifact's target, length and blake3, and its reflection as a zstd frame of its own. Then
//! one zstd frame of its artifacts' bytes. Both frames are compressed with the dictionary of
//! the entry's kind (its targets' names, `spirv+msl+hlsl+wgsl`) when the cache has one, else
//! plainly. One frame for the artifacts rather than one per artifact: a level's sources
//! share names and constants across targets, and per-artifact framing cost a frame header
//! and a weaker match history per artifact. The head apart lets a build that rewrites an
//! archive holding every artifact of the entry read the reflection alone ([`head`]), never
//! decompressing the artifacts; the reflection's frame apart from the lengths is the same
//! bytes in every entry of a shader that shares it, so such a build decodes each distinct
//! reflection once ([`cached_reflection`]).
//!
//! Everything the head already says is left out of the frames (zstd's magic, its dictionary
//! id, its check sums: one xxh3-128 covers the whole entry), and the key is left out of the
//! entry (the pack's index and the remote's value hold it; the check sum covers it): a
//! cache of a million entries is then about twice its archive rather than more.
//!
//! A build too small for compression to pay writes its only pack with [`encode_stored`]: the
//! same entry, its frames made of raw blocks (zstd's block type for data that does not
//! compress), read and checked as any other.
//!
//! A dictionary is trained from a pack of a build that has written enough entries of a kind
//! without one ([`TRAIN_MIN_PIECES`] in the pack, [`TRAIN_MIN_BYTES`] in the build: a small
//! build trains none, training would be a large share of its time), kept in
//! the cache folder as `<id>.kcd` (magic, kind length (u8), kind, dictionary) and used by
//! every later pack; entries name it by its id (a prefix of the blake3 of its kind and
//! bytes), so an entry whose dictionary is gone fails to decode and is recompiled. `gc`
//! keeps dictionaries (they are small), `clear` removes them. Remote values are entries as
//! a pack holds them: the remote holds the dictionaries they name too, and a cache that
//! reads one fetches its dictionary into its folder (see `exchange.rs`).
//!
//! Layout (version 6, `docs/reference/cache-format.md`): [`MAGIC`], the check sum (xxh3-128
//! of the key, then of the entry after the check sum), the dictionary id (16, zero: none),
//! the length of the same entry in version 2 (u32: `kiln cache stats` reports it as the raw
//! size; the reflection's JSON length is what it leaves), the artifact count, per artifact
//! its target's code (u8), length and blake3 (32), the reflection frame's length and the
//! frame, then the artifacts' frame to the end (numbers as LEB128). The artifacts' blake3
//! are stored so that a build reading an entry need not hash its artifacts again (the
//! archive wants them).
//!
//! Version 5 had the head's check sum before the key (padded to 32 bytes), the key, a u64
//! raw length, the description (the artifacts' targets and lengths with the reflection) as
//! one frame, and frames with zstd's magic, dictionary id and check sum. Version 4 kept the
//! description inside the frame, the artifacts' blake3 beside it, and a blake3 checksum of
//! the body with each artifact replaced by its blake3; version 3 stored no hashes (they are
//! computed).

use std::cell::RefCell;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock};

use zstd::zstd_safe::{CCtx, CDict, DCtx, DDict};

use super::Key;
use crate::archive::{Reflection, Target};
use crate::compile::Compiled;

/// The version written (6); versions 5, 4 and 3 are still read.
pub(super) const MAGIC: &[u8; 8] = b"KILNCE\0\x06";
pub(super) const MAGIC_V5: &[u8; 8] = b"KILNCE\0\x05";
pub(super) const MAGIC_V4: &[u8; 8] = b"KILNCE\0\x04";
pub(super) const MAGIC_V3: &[u8; 8] = b"KILNCE\0\x03";
pub(super) const DICT_MAGIC: &[u8; 8] = b"KILNCD\0\x01";
pub(super) const DICT_EXTENSION: &str = "kcd";
/// Magic, checksum, key, raw length (the dictionary id follows): versions 3 to 5.
pub(super) const HEADER: usize = 8 + 32 + 32 + 8;
/// Magic, check sum, dictionary id, raw length (u32): version 6.
const HEADER_V6: usize = 8 + 16 + 16 + 4;
/// zstd's level with a dictionary: higher levels cost a cold build much more CPU for a
/// cache only a little smaller.
const LEVEL: i32 = 3;
/// zstd's level without one (small builds, remote values): the fastest.
const PLAIN_LEVEL: i32 = 1;
const NO_DICT: [u8; 16] = [0; 16];
/// A kind is trained only from a pack with at least this many entries of it...
const TRAIN_MIN_PIECES: usize = 32;
/// ... once the build has written this many bytes of its artifacts (this pack's included).
const TRAIN_MIN_BYTES: usize = 2 << 20;
/// At most about this many bytes of a kind's entries (evenly spaced) train its dictionary.
const TRAIN_SAMPLE: usize = 2 << 20;
/// The largest dictionary trained, at most half its sample: larger than the archive's, as
/// the cache compresses each entry alone and the dictionary is all the history its frames
/// have; fastCover stops short of it when the sample has no more to give.
const DICT_CAPACITY: usize = 1 << 20;
/// The largest raw length an entry may announce (a damaged length allocates no more).
const MAX_RAW: u64 = 1 << 30;

thread_local! {
    /// Each thread's compression context and the buffer it compresses into, made once.
    static CCTX: RefCell<(Option<CCtx<'static>>, Vec<u8>)> = const { RefCell::new((None, Vec::new())) };
    static DCTX: RefCell<Option<DCtx<'static>>> = const { RefCell::new(None) };
}

/// Drops this thread's compression context and its buffer ([`CCTX`]): a context keeps the
/// tables of its level (and a reference to the dictionary it last compressed with, made
/// again at each use), a few MiB a worker.
pub(super) fn drop_thread_context() {
    CCTX.with(|cell| *cell.borrow_mut() = (None, Vec::new()));
}

/// One dictionary of the cache.
pub(super) struct Dict {
    id: [u8; 16],
    kind: String,
    bytes: Vec<u8>,
    cdict: OnceLock<Option<CDict<'static>>>,
    ddict: OnceLock<Option<DDict<'static>>>,
}

impl Dict {
    fn new(kind: &str, bytes: Vec<u8>) -> Dict {
        Dict {
            id: dict_id(kind, &bytes),
            kind: kind.to_string(),
            bytes,
            cdict: OnceLock::new(),
            ddict: OnceLock::new(),
        }
    }
    fn cdict(&self) -> Option<&CDict<'static>> {
        self.cdict.get_or_init(|| CDict::try_create(&self.bytes, LEVEL)).as_ref()
    }
    fn ddict(&self) -> Option<&DDict<'static>> {
        self.ddict.get_or_init(|| DDict::try_create(&self.bytes)).as_ref()
    }
    pub(super) fn id(&self) -> &[u8; 16] {
        &self.id
    }
    /// The file's content: magic, kind length (u8), kind, dictionary.
    pub(super) fn file_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(9 + self.kind.len() + self.bytes.len());
        out.extend_from_slice(DICT_MAGIC);
        out.push(self.kind.len() as u8);
        out.extend_from_slice(self.kind.as_bytes());
        out.extend_from_slice(&self.bytes);
        out
    }
}

fn dict_id(kind: &str, bytes: &[u8]) -> [u8; 16] {
    let mut h = blake3::Hasher::new();
    h.update(&[kind.len() as u8]);
    h.update(kind.as_bytes());
    h.update(bytes);
    h.finalize().as_bytes()[..16].try_into().expect("16 bytes")
}

pub(super) fn dict_file_name(id: &[u8; 16]) -> String {
    let hex: String = id.iter().map(|b| format!("{b:02x}")).collect();
    format!("{hex}.{DICT_EXTENSION}")
}

/// The dictionary in the file at `path`, if whole (its id is the hash of its content).
fn read_dict(path: &Path) -> Option<Dict> {
    let d = parse_dict(&std::fs::read(path).ok()?)?;
    (path.file_name()?.to_str()? == dict_file_name(&d.id)).then_some(d)
}

/// The dictionary a file's content ([`Dict::file_bytes`]) holds; its id is the hash of its
/// kind and bytes, so a caller that expects an id tells a damaged one by comparing them.
pub(super) fn parse_dict(bytes: &[u8]) -> Option<Dict> {
    if bytes.len() < 9 || &bytes[..8] != DICT_MAGIC {
        return None;
    }
    let n = bytes[8] as usize;
    let kind = std::str::from_utf8(bytes.get(9..9 + n)?).ok()?;
    Some(Dict::new(kind, bytes[9 + n..].to_vec()))
}

/// The dictionaries of a cache folder, read when first needed.
#[derive(Default)]
pub(super) struct Dicts {
    state: Mutex<State>,
}

#[derive(Default)]
struct State {
    by_id: HashMap<[u8; 16], Arc<Dict>>,
    /// Bytes of artifacts of each kind written without a dictionary through this `Cache`.
    written: HashMap<String, usize>,
    /// The dictionary used to write each kind (the lowest id of those found), once the folder
    /// was scanned.
    by_kind: Option<HashMap<String, Arc<Dict>>>,
}

impl std::fmt::Debug for Dicts {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let n = self.state.lock().map(|s| s.by_id.len()).unwrap_or(0);
        f.debug_struct("Dicts").field("loaded", &n).finish()
    }
}

impl Dicts {
    /// Forgets every dictionary (the folder was cleared, or no more entries are written):
    /// each is read again from the folder when next asked for.
    pub(super) fn reset(&self) {
        *self.state.lock().expect("no panics while locked") = State::default();
    }

    /// The dictionary `id` of the cache at `dir`.
    pub(super) fn get(&self, dir: &Path, id: &[u8; 16]) -> Result<Arc<Dict>, String> {
        let mut state = self.state.lock().expect("no panics while locked");
        if let Some(d) = state.by_id.get(id) {
            return Ok(d.clone());
        }
        let d = read_dict(&dir.join(dict_file_name(id)))
            .filter(|d| d.id == *id)
            .ok_or_else(|| format!("its dictionary {} is missing or damaged", dict_file_name(id)))?;
        let d = Arc::new(d);
        state.by_id.insert(*id, d.clone());
        Ok(d)
    }

    /// The dictionary of each kind to write with, from the `.kcd` files of `files` the first
    /// time.
    fn for_writing(&self, files: impl FnOnce() -> Vec<PathBuf>) -> HashMap<String, Arc<Dict>> {
        let mut state = self.state.lock().expect("no panics while locked");
        if state.by_kind.is_none() {
            let mut by_kind: HashMap<String, Arc<Dict>> = HashMap::new();
            for path in files().into_iter().filter(|p| p.extension().is_some_and(|e| e == DICT_EXTENSION)) {
                let Some(d) = read_dict(&path) else { continue };
                let d = state.by_id.entry(d.id).or_insert_with(|| Arc::new(d)).clone();
                match by_kind.get(&d.kind) {
                    Some(old) if old.id <= d.id => {}
                    _ => {
                        by_kind.insert(d.kind.clone(), d);
                    }
                }
            }
            state.by_kind = Some(by_kind);
        }
        state.by_kind.clone().unwrap_or_default()
    }

    /// The bytes of artifacts of `kind` written without a dictionary before, counting `more`.
    fn written(&self, kind: &str, more: usize) -> usize {
        let mut state = self.state.lock().expect("no panics while locked");
        let n = state.written.entry(kind.to_string()).or_default();
        let before = *n;
        *n += more;
        before
    }

    /// Keeps a dictionary fetched from elsewhere (the remote cache) for reading entries that
    /// name it; it is not used to write, unless the folder's files hold it.
    pub(super) fn keep(&self, d: Dict) -> Arc<Dict> {
        let mut state = self.state.lock().expect("no panics while locked");
        state.by_id.entry(d.id).or_insert_with(|| Arc::new(d)).clone()
    }

    /// Keeps a newly trained dictionary (written to `dir` by the caller first).
    fn add(&self, d: Dict) -> Arc<Dict> {
        let mut state = self.state.lock().expect("no panics while locked");
        let d = Arc::new(d);
        state.by_id.insert(d.id, d.clone());
        state.by_kind.get_or_insert_with(HashMap::new).entry(d.kind.clone()).or_insert_with(|| d.clone()).clone()
    }
}

/// The dictionary kind of an entry: its targets' names.
fn kind_of(c: &Compiled) -> String {
    c.artifacts.iter().map(|(t, _)| t.name()).collect::<Vec<_>>().join("+")
}

/// An entry's body as version 2 lays it out after the key: artifact count, per artifact its
/// frame and bytes, the reflection's length and JSON (version 4's frame content).
#[cfg(test)]
fn body(c: &Compiled) -> Vec<u8> {
    let frames = super::frames(c);
    let mut out = Vec::with_capacity(
        frames.iter().map(Vec::len).sum::<usize>() + c.artifacts.iter().map(|(_, b)| b.len()).sum::<usize>(),
    );
    out.extend_from_slice(&frames[0]);
    for (i, (_, bytes)) in c.artifacts.iter().enumerate() {
        out.extend_from_slice(&frames[1 + i]);
        out.extend_from_slice(bytes);
    }
    let n = frames.len();
    out.extend_from_slice(&frames[n - 2]);
    out.extend_from_slice(&frames[n - 1]);
    out
}

/// The dictionaries to write `entries` with: those of the cache at `dir`, and for each kind
/// without one, one trained from `entries` when they hold enough of it (written to `dir`
/// through `write`; a failed write trains nothing).
pub(super) fn dictionaries_for(
    dicts: &Dicts,
    dir: &Path,
    files: impl FnOnce() -> Vec<PathBuf>,
    entries: &[(Key, &Compiled, &[blake3::Hash])],
    write: impl Fn(&Path, &[u8]) -> bool,
) -> HashMap<String, Arc<Dict>> {
    let mut chosen = dicts.for_writing(files);
    // A dictionary removed from the folder since (by hand) is written again: the entries
    // about to name it must find it.
    chosen.retain(|_, d| {
        let path = dir.join(dict_file_name(&d.id));
        path.exists() || write(&path, &d.file_bytes())
    });
    let mut candidates: Vec<(String, Vec<&Compiled>)> = Vec::new();
    for (_, c, _) in entries {
        let kind = kind_of(c);
        if chosen.contains_key(&kind) {
            continue;
        }
        match candidates.iter_mut().find(|(k, _)| *k == kind) {
            Some((_, list)) => list.push(c),
            None => candidates.push((kind, vec![c])),
        }
    }
    for (kind, list) in candidates {
        let total: usize = list.iter().map(|c| c.artifacts.iter().map(|(_, b)| b.len()).sum::<usize>()).sum();
        let before = dicts.written(&kind, total);
        if list.len() < TRAIN_MIN_PIECES || before + total < TRAIN_MIN_BYTES {
            continue;
        }
        let stride = total.div_ceil(TRAIN_SAMPLE).max(1);
        // Reflections and artifacts alike: both frames of an entry use the dictionary.
        let sample: Vec<Vec<u8>> = list.iter().step_by(stride).flat_map(|c| [reflection_json(c), content(c)]).collect();
        let sizes: Vec<usize> = sample.iter().map(Vec::len).collect();
        let flat = sample.concat();
        let capacity = (flat.len() / 2).min(DICT_CAPACITY);
        let Some(bytes) = crate::archive::train_dictionary(&flat, &sizes, capacity).filter(|d| !d.is_empty()) else {
            continue;
        };
        let d = Dict::new(&kind, bytes);
        if write(&dir.join(dict_file_name(&d.id)), &d.file_bytes()) {
            chosen.insert(kind, dicts.add(d));
        }
    }
    chosen
}

/// `c` as a version 6 entry of `key`, with the blake3 of each artifact (`hashes`), its
/// reflection and its artifacts compressed with its kind's dictionary in `dicts` (none:
/// plainly).
pub(super) fn encode(key: &Key, c: &Compiled, hashes: &[blake3::Hash], dicts: &HashMap<String, Arc<Dict>>) -> Vec<u8> {
    let dict = dicts.get(&kind_of(c)).and_then(|d| d.cdict().map(|c| (d.id, c)));
    let cdict = dict.as_ref().map(|d| d.1);
    let json = reflection_json(c);
    let reflection = compress(&json, cdict);
    let frame = compress(&content(c), cdict);
    let mut out = entry_head(c, hashes, dict.as_ref().map_or(NO_DICT, |d| d.0), json.len(), &reflection, frame.len());
    out.extend_from_slice(&frame);
    seal(key, &mut out);
    out
}

/// `raw` as one magicless zstd frame without a dictionary id or check sum (the entry's
/// check sum covers its bytes, its head names the dictionary), compressed with `cdict`
/// (none: plainly). The returned bytes are copied out at their size from the worker's
/// reused buffer: the encoded entries of a pack wait to be written, each in a buffer of its
/// raw size (zeroed, so faulted in) otherwise.
fn compress(raw: &[u8], cdict: Option<&CDict<'static>>) -> Vec<u8> {
    CCTX.with(|cell| {
        use zstd::zstd_safe::{CParameter, FrameFormat, ResetDirective};
        let mut cell = cell.borrow_mut();
        let (context, dst) = &mut *cell;
        let cctx = context.get_or_insert_with(CCtx::create);
        dst.clear();
        dst.reserve(zstd::zstd_safe::compress_bound(raw.len()));
        let written = (|| {
            cctx.reset(ResetDirective::SessionAndParameters)?;
            match cdict {
                Some(cdict) => cctx.ref_cdict(cdict)?,
                None => cctx.set_parameter(CParameter::CompressionLevel(PLAIN_LEVEL))?,
            };
            cctx.set_parameter(CParameter::Format(FrameFormat::Magicless))?;
            cctx.set_parameter(CParameter::DictIdFlag(false))?;
            cctx.set_parameter(CParameter::ChecksumFlag(false))?;
            cctx.compress2(dst, raw)
        })();
        // The bound always fits a frame; an error (none expected) leaves an empty frame,
        // which fails to decode: the entry is then recompiled.
        if written.is_err() {
            dst.clear();
        }
        dst.to_vec()
    })
}

/// [`encode`] without compressing: the reflection and the artifacts go into zstd frames of
/// raw blocks ([`stored_frame`]), which any version 6 reader decodes and checks as it does
/// compressed ones. For a build so small that compressing its entries costs a noticeable
/// share of its time while the bytes saved do not matter (see `build::store`).
pub(super) fn encode_stored(key: &Key, c: &Compiled, hashes: &[blake3::Hash]) -> Vec<u8> {
    // The artifacts framed as they are, not gathered first: a small build's whole output
    // goes through here, and each copy of it faults in fresh pages.
    let pieces: Vec<&[u8]> = c.artifacts.iter().map(|(_, b)| b.as_slice()).collect();
    let len = pieces.iter().map(|p| p.len()).sum();
    let json = reflection_json(c);
    let mut reflection = Vec::with_capacity(stored_frame_len(json.len()));
    stored_frame(&[&json], &mut reflection);
    let mut out = entry_head(c, hashes, NO_DICT, json.len(), &reflection, stored_frame_len(len));
    stored_frame(&pieces, &mut out);
    seal(key, &mut out);
    out
}

/// The content of an entry's frame: its artifacts, one after another.
fn content(c: &Compiled) -> Vec<u8> {
    c.artifacts.iter().flat_map(|(_, b)| b.iter().copied()).collect()
}

/// An entry's reflection as JSON (as version 2 stores it).
fn reflection_json(c: &Compiled) -> Vec<u8> {
    serde_json::to_vec(&c.reflection).expect("reflection serializes")
}

/// The length of `c` as a version 2 entry (magic, checksum, key, artifact count, per
/// artifact its name, length and bytes, the reflection's length and JSON), `json` bytes
/// of JSON: the raw size `kiln cache stats` reports.
fn v2_len(mut artifacts: impl Iterator<Item = (Target, u64)>, json: u64) -> Option<u64> {
    let fixed = (super::MAGIC.len() + 64 + 4 + 8) as u64;
    artifacts.try_fold(fixed.checked_add(json)?, |n, (t, len)| {
        n.checked_add(1 + t.name().len() as u64 + 8)?.checked_add(len)
    })
}

/// The one-byte code of each target in a version 6 head (its position here). Codes are
/// never reused: a new target takes the next one.
const TARGET_CODES: [Target; 5] = [Target::Wgsl, Target::Spirv, Target::Msl, Target::Glsl, Target::Hlsl];

fn target_code(t: Target) -> u8 {
    TARGET_CODES.iter().position(|&c| c == t).expect("every target has a code") as u8
}

/// A version 6 entry up to its frame, with room for a frame of `frame_len` bytes and its
/// check sum left zero ([`seal`] writes it): magic, check sum, dictionary id, the version 2
/// length (u32), the artifact count, per artifact its target's code, length and blake3,
/// then the reflection's frame (`reflection`, `json_len` bytes of JSON) and its length. The
/// reflection has a frame of its own, apart from the artifacts' lengths, so that its bytes
/// are the same in every entry of a shader that shares it and a reader decodes each once.
fn entry_head(
    c: &Compiled,
    hashes: &[blake3::Hash],
    dict: [u8; 16],
    json_len: usize,
    reflection: &[u8],
    frame_len: usize,
) -> Vec<u8> {
    assert_eq!(hashes.len(), c.artifacts.len(), "one hash per artifact");
    let raw = v2_len(c.artifacts.iter().map(|(t, b)| (*t, b.len() as u64)), json_len as u64).unwrap_or(u64::MAX);
    let mut out = Vec::with_capacity(HEADER_V6 + 48 * hashes.len() + 8 + reflection.len() + frame_len);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&[0; 16]);
    out.extend_from_slice(&dict);
    // A longer entry than u32 says is refused on reading anyway (`MAX_RAW`).
    out.extend_from_slice(&u32::try_from(raw).unwrap_or(u32::MAX).to_le_bytes());
    put_varint(&mut out, hashes.len() as u64);
    for ((t, bytes), h) in c.artifacts.iter().zip(hashes) {
        out.push(target_code(*t));
        put_varint(&mut out, bytes.len() as u64);
        out.extend_from_slice(h.as_bytes());
    }
    put_varint(&mut out, reflection.len() as u64);
    out.extend_from_slice(reflection);
    out
}

/// Writes the check sum of the whole version 6 entry `out` of `key`.
fn seal(key: &Key, out: &mut [u8]) {
    let sum = entry_sum(key, &out[24..]);
    out[8..24].copy_from_slice(&sum);
}

/// The check sum of a version 6 entry: xxh3-128 of its key, then of the entry after the
/// check sum to its end. The key is not stored (the pack's index and the remote's value
/// hold it): an entry read under another key fails its check sum. Not a blake3: it only
/// tells damage in what this cache wrote (the artifacts' blake3 it holds were computed
/// when they were compiled), and a blake3 of every entry was a visible share of a warm
/// build. It covers the frames whole (they carry no check sum of their own).
fn entry_sum(key: &Key, rest: &[u8]) -> [u8; 16] {
    let mut h = xxhash_rust::xxh3::Xxh3::new();
    h.update(&key.0);
    h.update(rest);
    h.digest128().to_le_bytes()
}

/// Appends `n` as LEB128 (7 bits a byte, low first).
fn put_varint(out: &mut Vec<u8>, mut n: u64) {
    while n >= 0x80 {
        out.push(n as u8 | 0x80);
        n >>= 7;
    }
    out.push(n as u8);
}

/// The check sum of a version 5 entry's head (after the check sum, up to the frame).
fn head_sum_v5(bytes: &[u8]) -> [u8; 16] {
    xxhash_rust::xxh3::xxh3_128(bytes).to_le_bytes()
}

/// The largest block of a zstd frame (`Block_Maximum_Size` of RFC 8878).
const ZSTD_BLOCK_MAX: usize = 128 << 10;

/// The length of [`stored_frame`] of `len` bytes: header descriptor, content size, a
/// header per block (one at least), the content.
fn stored_frame_len(len: usize) -> usize {
    1 + 8 + 3 * len.div_ceil(ZSTD_BLOCK_MAX).max(1) + len
}

/// The content `pieces` (one after another) as one magicless zstd frame (RFC 8878) of raw
/// (stored) blocks, appended to `out`, with the frame's content size and no check sum, as
/// [`compress`] frames them: no compression work, only a copy.
fn stored_frame(pieces: &[&[u8]], out: &mut Vec<u8>) {
    let len: usize = pieces.iter().map(|p| p.len()).sum();
    // Frame header descriptor: an 8-byte content size, a single segment (the window is the
    // content, so no window descriptor), no check sum, no dictionary id.
    out.push(0b1110_0000);
    out.extend_from_slice(&(len as u64).to_le_bytes());
    let (mut left, mut block_left) = (len, 0);
    if len == 0 {
        // An empty content is one empty last block.
        out.extend_from_slice(&[1, 0, 0]);
    }
    for mut piece in pieces.iter().copied() {
        while !piece.is_empty() {
            if block_left == 0 {
                // Block header: last-block bit, block type 0 (raw), then the size.
                block_left = left.min(ZSTD_BLOCK_MAX);
                left -= block_left;
                let header = (block_left as u32) << 3 | u32::from(left == 0);
                out.extend_from_slice(&header.to_le_bytes()[..3]);
            }
            let (now, rest) = piece.split_at(piece.len().min(block_left));
            out.extend_from_slice(now);
            block_left -= now.len();
            piece = rest;
        }
    }
}

/// Whether `bytes` starts as a compressed entry (version 3 to 6).
pub(super) fn is_compressed(bytes: &[u8]) -> bool {
    [MAGIC, MAGIC_V5, MAGIC_V4, MAGIC_V3].iter().any(|m| bytes.starts_with(*m))
}

/// Whether `bytes` starts as an entry with a head ([`head`] reads it alone).
pub(super) fn has_head(bytes: &[u8]) -> bool {
    bytes.starts_with(MAGIC) || bytes.starts_with(MAGIC_V5)
}

/// Whether the compressed entry `bytes` is one of `key`: version 6 by its check sum (it
/// holds no key), older versions by the key they hold.
pub(super) fn is_entry_of(bytes: &[u8], key: &Key) -> bool {
    if bytes.starts_with(MAGIC) {
        return bytes.len() >= HEADER_V6 && entry_sum(key, &bytes[24..]) == bytes[8..24];
    }
    is_compressed(bytes) && bytes.len() >= HEADER && bytes[40..72] == key.0
}

/// The raw length the header of a compressed entry announces (its first [`HEADER`] bytes,
/// or all of it if shorter).
pub(super) fn raw_len(header: &[u8]) -> Option<u64> {
    if header.starts_with(MAGIC) {
        return header.get(40..44).map(|b| u64::from(u32::from_le_bytes(b.try_into().expect("4 bytes"))));
    }
    (header.len() >= HEADER && is_compressed(header)).then(|| u64::from_le_bytes(header[72..80].try_into().unwrap()))
}

/// Whether the compressed entry `bytes` names a dictionary.
#[cfg(test)]
pub(super) fn uses_dictionary(bytes: &[u8]) -> Result<bool, String> {
    Ok(dictionary_of(bytes)?.is_some())
}

/// The id of the dictionary the compressed entry `bytes` names, if any.
pub(super) fn dictionary_of(bytes: &[u8]) -> Result<Option<[u8; 16]>, String> {
    let at = if bytes.starts_with(MAGIC) { 24 } else { HEADER };
    let id: [u8; 16] = bytes.get(at..at + 16).ok_or("entry is truncated")?.try_into().expect("16 bytes");
    Ok((id != NO_DICT).then_some(id))
}

/// The artifacts' blake3 a version 4 entry stores after its dictionary id, and where its
/// frame starts; for version 3, none (they are computed) and the frame's start.
fn stored_hashes(bytes: &[u8]) -> Result<(Option<Vec<blake3::Hash>>, usize), String> {
    if bytes.starts_with(MAGIC_V3) {
        return Ok((None, HEADER + 16));
    }
    let count = bytes.get(HEADER + 16..HEADER + 20).ok_or("entry is truncated")?;
    let count = u32::from_le_bytes(count.try_into().expect("4 bytes")) as usize;
    let start = HEADER + 20;
    let end = count.checked_mul(32).and_then(|n| n.checked_add(start)).filter(|&e| e <= bytes.len());
    let end = end.ok_or("entry is truncated")?;
    check_frame(&bytes[end..])?;
    Ok((Some(read_hashes(&bytes[start..end])), end))
}

/// The blake3 hashes one after another in `bytes`.
fn read_hashes(bytes: &[u8]) -> Vec<blake3::Hash> {
    bytes.chunks_exact(32).map(|h| blake3::Hash::from_bytes(h.try_into().expect("32 bytes"))).collect()
}

/// Without zstd's check sum, nothing would tell a damaged frame of a version 4 or 5 entry
/// (byte 4 of a frame is its header descriptor; bit 2 announces the check sum).
fn check_frame(frame: &[u8]) -> Result<(), String> {
    if frame.len() < 5 || frame[4] & 0x04 == 0 {
        return Err("its frame has no check sum".into());
    }
    Ok(())
}

/// What a version 6 or 5 entry holds before its frame, checked: its artifacts (target,
/// length, blake3), its reflection, its dictionary id, and the frame.
pub(super) struct Head<'a> {
    pub(super) artifacts: Vec<(Target, u64, blake3::Hash)>,
    pub(super) reflection: Reflection,
    dict: [u8; 16],
    frame: &'a [u8],
    /// Whether the frame is magicless (version 6).
    magicless: bool,
}

/// Finds a dictionary of the cache by id.
type DictFor<'f> = &'f dyn Fn(&[u8; 16]) -> Result<Arc<Dict>, String>;

/// The head of the version 6 or 5 entry `bytes` of `key`, checked (a version 5 entry's
/// frame is not read); `dict` finds the dictionary its reflection is compressed with.
pub(super) fn head<'a>(key: &Key, bytes: &'a [u8], dict: DictFor<'_>) -> Result<Head<'a>, String> {
    if bytes.starts_with(MAGIC_V5) {
        return head_v5(key, bytes, dict);
    }
    if bytes.len() < HEADER_V6 || !bytes.starts_with(MAGIC) {
        return Err("not a cache entry of this kiln".into());
    }
    if entry_sum(key, &bytes[24..]) != bytes[8..24] {
        // The key is in the sum: another key's entry is a mismatch too.
        return Err("checksum mismatch".into());
    }
    let dict_id: [u8; 16] = bytes[24..40].try_into().expect("16 bytes");
    let raw = u64::from(u32::from_le_bytes(bytes[40..44].try_into().expect("4 bytes")));
    let mut r = super::Reader { bytes, at: HEADER_V6 };
    let count = r.varint()?;
    // Each artifact takes 34 bytes at least: a damaged count allocates no more than that.
    let mut artifacts = Vec::with_capacity(count.min(bytes.len() as u64 / 34) as usize);
    for _ in 0..count {
        let code = r.take(1)?[0];
        let target = *TARGET_CODES.get(code as usize).ok_or_else(|| format!("unknown target code {code}"))?;
        let len = r.varint()?;
        artifacts.push((target, len, blake3::Hash::from_bytes(r.take(32)?.try_into().expect("32 bytes"))));
    }
    let framed = r.varint()?;
    let reflection = r.take(usize::try_from(framed).map_err(|_| "entry is truncated")?)?;
    // The JSON's length is what the version 2 length leaves.
    let json_len = v2_len(artifacts.iter().map(|a| (a.0, a.1)), 0).and_then(|n| raw.checked_sub(n));
    let json_len = json_len.filter(|&n| n <= MAX_RAW).ok_or("bad length")?;
    let reflection = cached_reflection(reflection, &dict_id, json_len as usize, dict)?;
    Ok(Head { artifacts, reflection, dict: dict_id, frame: &bytes[r.at..], magicless: true })
}

/// The most reflections each thread keeps decoded ([`cached_reflection`]): a set has far
/// fewer distinct ones; past this, the memo starts again.
const REFLECTIONS_KEPT: usize = 4096;

thread_local! {
    /// Reflections decoded by this thread, by dictionary id, then their frame's bytes.
    static REFLECTIONS: RefCell<HashMap<[u8; 16], HashMap<Box<[u8]>, Reflection>>> = RefCell::new(HashMap::new());
}

/// The reflection of the frame `frame` (compressed with dictionary `id`, `json_len` bytes
/// of JSON). Every entry of a shader that shares a reflection holds the same frame, so a
/// build that reads the heads of many entries decompresses and parses each distinct one
/// once (per thread), and clones it for the others.
fn cached_reflection(frame: &[u8], id: &[u8; 16], json_len: usize, dict: DictFor<'_>) -> Result<Reflection, String> {
    let known = REFLECTIONS.with(|m| m.borrow().get(id).and_then(|by_frame| by_frame.get(frame).cloned()));
    if let Some(r) = known {
        return Ok(r);
    }
    let mut json = vec![0u8; json_len];
    if decompress(frame, id, dict, &mut json, true)? != json_len {
        return Err("bad length".into());
    }
    let reflection: Reflection = serde_json::from_slice(&json).map_err(|e| format!("bad reflection: {e}"))?;
    REFLECTIONS.with(|m| {
        let mut m = m.borrow_mut();
        if m.values().map(HashMap::len).sum::<usize>() >= REFLECTIONS_KEPT {
            m.clear();
        }
        m.entry(*id).or_default().insert(frame.into(), reflection.clone());
    });
    Ok(reflection)
}

/// The head of the version 5 entry `bytes` of `key`: the description (artifact count, per
/// artifact its target's name and length, the reflection's length and JSON) is one frame
/// with zstd's magic and check sum, the head's own check sum before the key.
fn head_v5<'a>(key: &Key, bytes: &'a [u8], dict: DictFor<'_>) -> Result<Head<'a>, String> {
    if bytes.len() < HEADER + 20 {
        return Err("not a cache entry of this kiln".into());
    }
    if bytes[40..72] != key.0 {
        return Err("the entry belongs to another key".into());
    }
    let mut r = super::Reader { bytes, at: HEADER };
    let dict_id: [u8; 16] = r.take(16)?.try_into().expect("16 bytes");
    let count = u32::from_le_bytes(r.take(4)?.try_into().expect("4 bytes")) as usize;
    let hashes = read_hashes(r.take(count.checked_mul(32).ok_or("entry is truncated")?)?);
    let desc_len = u32::from_le_bytes(r.take(4)?.try_into().expect("4 bytes")) as usize;
    let desc_frame_len = u32::from_le_bytes(r.take(4)?.try_into().expect("4 bytes")) as usize;
    let desc_frame = r.take(desc_frame_len)?;
    if head_sum_v5(&bytes[40..r.at]) != bytes[8..24] || bytes[24..40] != [0; 16] {
        return Err("checksum mismatch".into());
    }
    let frame = &bytes[r.at..];
    check_frame(frame)?;
    if desc_len as u64 > MAX_RAW {
        return Err("bad length".into());
    }
    let mut desc = vec![0u8; desc_len];
    if decompress(desc_frame, &dict_id, dict, &mut desc, false)? != desc_len {
        return Err("bad length".into());
    }
    let mut d = super::Reader { bytes: &desc, at: 0 };
    if u32::from_le_bytes(d.take(4)?.try_into().expect("4 bytes")) as usize != count {
        return Err("bad artifact count".into());
    }
    let mut artifacts = Vec::with_capacity(count);
    for hash in hashes {
        let n = d.take(1)?[0] as usize;
        let name = std::str::from_utf8(d.take(n)?).map_err(|_| "bad target name".to_string())?;
        let target = Target::from_name(name).ok_or_else(|| format!("unknown target `{name}`"))?;
        artifacts.push((target, d.u64()?, hash));
    }
    let n = d.u64()? as usize;
    let reflection = serde_json::from_slice(d.take(n)?).map_err(|e| format!("bad reflection: {e}"))?;
    if d.at != desc.len() {
        return Err("trailing bytes".into());
    }
    Ok(Head { artifacts, reflection, dict: dict_id, frame, magicless: false })
}

/// The version 6 or 5 entry `bytes` of `key`, its artifacts decompressed, checked.
fn decode_headed(key: &Key, bytes: &[u8], dict: DictFor<'_>) -> Result<(Compiled, Vec<blake3::Hash>), String> {
    let head = head(key, bytes, dict)?;
    let total = head.artifacts.iter().try_fold(0u64, |t, a| t.checked_add(a.1)).filter(|&t| t <= MAX_RAW);
    let total = total.ok_or("bad length")? as usize;
    let mut content = vec![0u8; total];
    if decompress(head.frame, &head.dict, dict, &mut content, head.magicless)? != total {
        return Err("bad length".into());
    }
    let mut at = 0;
    let mut hashes = Vec::with_capacity(head.artifacts.len());
    let artifacts = head
        .artifacts
        .into_iter()
        .map(|(target, len, hash)| {
            hashes.push(hash);
            at += len as usize;
            (target, content[at - len as usize..at].to_vec())
        })
        .collect();
    Ok((Compiled { artifacts, reflection: head.reflection }, hashes))
}

/// Decompresses `frame` (with dictionary `id` unless [`NO_DICT`]; `magicless`: as
/// [`compress`] writes it, else with zstd's magic) into `out`: the bytes written.
fn decompress(
    frame: &[u8],
    id: &[u8; 16],
    dict: DictFor<'_>,
    out: &mut [u8],
    magicless: bool,
) -> Result<usize, String> {
    use zstd::zstd_safe::{DParameter, FrameFormat, ResetDirective};
    let d = if *id == NO_DICT { None } else { Some(dict(id)?) };
    let result = DCTX.with(|cell| {
        let mut cell = cell.borrow_mut();
        let dctx = match cell.as_mut() {
            Some(d) => d,
            None => cell.insert(DCtx::try_create().ok_or("cannot create a zstd context")?),
        };
        let format = if magicless { FrameFormat::Magicless } else { FrameFormat::One };
        let ddict = match &d {
            Some(d) => Some(d.ddict().ok_or("its dictionary cannot be loaded")?),
            None => None,
        };
        (|| {
            dctx.reset(ResetDirective::SessionAndParameters)?;
            dctx.set_parameter(DParameter::Format(format))?;
            if let Some(ddict) = ddict {
                dctx.ref_ddict(ddict)?;
            }
            dctx.decompress(out, frame)
        })()
        .map_err(|_| "cannot decompress it")
    });
    if result.is_err() {
        // A context left mid-frame is made again.
        DCTX.with(|cell| *cell.borrow_mut() = None);
    }
    Ok(result?)
}

/// The entry `bytes` of `key` (version 3 to 6), decompressed and checked, with its
/// artifacts' blake3; `dict` finds a dictionary by id.
pub(super) fn decode(key: &Key, bytes: &[u8], dict: DictFor<'_>) -> Result<(Compiled, Vec<blake3::Hash>), String> {
    if has_head(bytes) {
        return decode_headed(key, bytes, dict);
    }
    if bytes.len() < HEADER + 16 || !is_compressed(bytes) {
        return Err("not a cache entry of this kiln".into());
    }
    if bytes[40..72] != key.0 {
        return Err("the entry belongs to another key".into());
    }
    let raw = u64::from_le_bytes(bytes[72..80].try_into().unwrap());
    if !(72..=MAX_RAW).contains(&raw) {
        return Err("bad length".into());
    }
    let id: [u8; 16] = bytes[HEADER..HEADER + 16].try_into().unwrap();
    let (hashes, start) = stored_hashes(bytes)?;
    let frame = &bytes[start..];
    // The version 2 entry: its header, then the body decompressed after it.
    let mut v2 = vec![0u8; raw as usize];
    v2[..8].copy_from_slice(super::MAGIC);
    v2[8..72].copy_from_slice(&bytes[8..72]);
    if decompress(frame, &id, dict, &mut v2[72..], false)? as u64 != raw - 72 {
        return Err("bad length".into());
    }
    super::decode_v2_hashed(key, &v2, hashes.as_deref())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::archive::Stage;

    fn compiled() -> Compiled {
        Compiled {
            artifacts: vec![
                (Target::Wgsl, b"fn main() {}\n".repeat(9)),
                (Target::Spirv, vec![3, 2, 0x23, 7, 1, 0, 0, 0]),
            ],
            reflection: Reflection {
                entry: "main".into(),
                stage: Stage::Fragment,
                bindings: vec![],
                vertex_inputs: vec![],
                color_outputs: vec![],
                workgroup_size: None,
            },
        }
    }

    fn hashes(c: &Compiled) -> Vec<blake3::Hash> {
        c.artifacts.iter().map(|(_, b)| blake3::hash(b)).collect()
    }

    fn no_dicts(_: &[u8; 16]) -> Result<Arc<Dict>, String> {
        Err("no dictionary".into())
    }

    /// The content of the magicless frame `frame` of `len` bytes, as zstd reads it.
    fn magicless(frame: &[u8], len: usize) -> Vec<u8> {
        let mut out = vec![0; len];
        assert_eq!(decompress(frame, &NO_DICT, &no_dicts, &mut out, true), Ok(len));
        out
    }

    /// No copy of `entry` (of `key`, holding `c`) with one byte flipped decodes to other
    /// artifacts or other hashes: it fails, or (a flip zstd or the reader ignores) gives `c`.
    fn every_damage_is_caught(key: &Key, entry: &[u8], c: &Compiled) {
        for at in 0..entry.len() {
            let mut damaged = entry.to_vec();
            damaged[at] ^= 0x10;
            if let Ok(got) = decode(key, &damaged, &no_dicts) {
                assert_eq!(got, (c.clone(), hashes(c)), "byte {at} flipped gave another entry");
            }
        }
    }

    /// A stored entry (raw zstd blocks) decodes as a compressed one does, zstd itself reads
    /// its frame, and no damaged copy of it decodes to other artifacts or other hashes.
    #[test]
    fn a_stored_entry_is_read_as_a_compressed_one_and_every_damage_is_caught() {
        let (key, c) = (Key([9; 32]), compiled());
        let entry = encode_stored(&key, &c, &hashes(&c));
        assert_eq!(decode(&key, &entry, &no_dicts).unwrap(), (c.clone(), hashes(&c)));
        let frame = head(&key, &entry, &no_dicts).unwrap().frame;
        assert_eq!(magicless(frame, content(&c).len()), content(&c), "a frame zstd reads");
        every_damage_is_caught(&key, &entry, &c);
    }

    /// Frames of raw blocks split at zstd's block size, and the empty content, are what
    /// zstd reads back.
    #[test]
    fn stored_frames_of_any_size_are_read_by_zstd() {
        for len in [0, 1, ZSTD_BLOCK_MAX - 1, ZSTD_BLOCK_MAX, ZSTD_BLOCK_MAX + 1, 3 * ZSTD_BLOCK_MAX + 7] {
            let content: Vec<u8> = (0..len).map(|i| (i * 7 % 251) as u8).collect();
            let (a, b) = content.split_at(len / 3);
            let mut frame = Vec::new();
            stored_frame(&[a, &[], b], &mut frame);
            assert_eq!(frame.len(), stored_frame_len(len));
            assert_eq!(magicless(&frame, len), content, "{len} bytes");
        }
    }

    /// A version 5 entry as version 5 kilns wrote it: the description (the version 2 body
    /// without the artifacts' bytes) in a frame of its own, zstd's magic and check sum in
    /// both frames.
    fn encode_v5(key: &Key, c: &Compiled) -> Vec<u8> {
        let desc = super::super::frames(c).concat();
        let zstd = |raw: &[u8]| {
            let mut z = zstd::bulk::Compressor::new(PLAIN_LEVEL).unwrap();
            z.set_parameter(zstd::zstd_safe::CParameter::ChecksumFlag(true)).unwrap();
            z.compress(raw).unwrap()
        };
        let desc_frame = zstd(&desc);
        let mut out = MAGIC_V5.to_vec();
        out.extend_from_slice(&[0; 32]);
        out.extend_from_slice(&key.0);
        out.extend_from_slice(&((super::super::MAGIC.len() + 64 + body(c).len()) as u64).to_le_bytes());
        out.extend_from_slice(&NO_DICT);
        out.extend_from_slice(&(c.artifacts.len() as u32).to_le_bytes());
        hashes(c).iter().for_each(|h| out.extend_from_slice(h.as_bytes()));
        out.extend_from_slice(&(desc.len() as u32).to_le_bytes());
        out.extend_from_slice(&(desc_frame.len() as u32).to_le_bytes());
        out.extend_from_slice(&desc_frame);
        let sum = head_sum_v5(&out[40..]);
        out[8..24].copy_from_slice(&sum);
        out.extend_from_slice(&zstd(&content(c)));
        out
    }

    /// A version 5 entry is still read, its head alone too, and no damaged copy of it
    /// decodes to other artifacts or hashes.
    #[test]
    fn a_version_5_entry_is_still_read() {
        let (key, c) = (Key([6; 32]), compiled());
        let entry = encode_v5(&key, &c);
        assert_eq!(decode(&key, &entry, &no_dicts).unwrap(), (c.clone(), hashes(&c)));
        assert_eq!(head(&key, &entry, &no_dicts).unwrap().reflection, c.reflection);
        assert_eq!(raw_len(&entry[..HEADER]), Some(body(&c).len() as u64 + 72));
        every_damage_is_caught(&key, &entry, &c);
    }

    /// Entries whose reflections are equal hold the same bytes for it (a reader decodes it
    /// once), whatever their artifacts; the raw size is version 2's; a version 6 entry read
    /// under another key is refused.
    #[test]
    fn equal_reflections_are_equal_frames() {
        let (key, c) = (Key([4; 32]), compiled());
        let mut other = compiled();
        other.artifacts[0].1 = b"fn other() {}\n".repeat(3);
        let frame = compress(&reflection_json(&c), None);
        for entry in
            [encode(&key, &c, &hashes(&c), &HashMap::new()), encode(&key, &other, &hashes(&other), &HashMap::new())]
        {
            assert!(entry.windows(frame.len()).any(|w| w == frame), "the reflection's frame, as it is");
        }
        let entry = encode(&key, &c, &hashes(&c), &HashMap::new());
        assert_eq!(raw_len(&entry), Some(body(&c).len() as u64 + 72));
        assert!(is_entry_of(&entry, &key) && !is_entry_of(&entry, &Key([3; 32])));
        assert!(decode(&Key([3; 32]), &entry, &no_dicts).is_err());
        // Read twice (the second from the memo), the same.
        for _ in 0..2 {
            assert_eq!(decode(&key, &entry, &no_dicts).unwrap(), (c.clone(), hashes(&c)));
        }
    }

    /// A version 6 entry gives back the hashes it was written with, and no damaged copy of
    /// it (any one byte flipped) decodes to other artifacts or other hashes, nor its head
    /// to another reflection or other hashes.
    #[test]
    fn a_version_6_entry_keeps_its_hashes_and_every_damage_is_caught() {
        let (key, c) = (Key([7; 32]), compiled());
        let entry = encode(&key, &c, &hashes(&c), &HashMap::new());
        assert!(entry.starts_with(MAGIC));
        assert_eq!(decode(&key, &entry, &no_dicts).unwrap(), (c.clone(), hashes(&c)));
        let described = |h: Head<'_>| (h.reflection, h.artifacts);
        let want: Vec<(Target, u64, blake3::Hash)> =
            c.artifacts.iter().zip(hashes(&c)).map(|((t, b), h)| (*t, b.len() as u64, h)).collect();
        assert_eq!(described(head(&key, &entry, &no_dicts).unwrap()), (c.reflection.clone(), want.clone()));
        every_damage_is_caught(&key, &entry, &c);
        for at in 0..entry.len() {
            let mut damaged = entry.clone();
            damaged[at] ^= 0x10;
            if let Ok(got) = head(&key, &damaged, &no_dicts) {
                assert_eq!(described(got), (c.reflection.clone(), want.clone()), "byte {at} flipped");
            }
        }
    }

    /// The header of a version 4 or 3 entry of `key` holding `c` (magic, checksum, key, raw
    /// length, no dictionary), as older kilns wrote it.
    fn old_header(magic: &[u8; 8], key: &Key, c: &Compiled) -> Vec<u8> {
        let mut entry = magic.to_vec();
        entry.extend_from_slice(super::super::entry_checksum(key, &super::super::frames(c), &hashes(c)).as_bytes());
        entry.extend_from_slice(&key.0);
        entry.extend_from_slice(&((super::super::MAGIC.len() + 64 + body(c).len()) as u64).to_le_bytes());
        entry.extend_from_slice(&NO_DICT);
        entry
    }

    /// A version 4 entry (the reflection inside the frame, written by older kilns) is still
    /// read, and no damaged copy of it decodes to other artifacts or hashes.
    #[test]
    fn a_version_4_entry_is_still_read() {
        let (key, c) = (Key([5; 32]), compiled());
        let raw = body(&c);
        let mut entry = old_header(MAGIC_V4, &key, &c);
        entry.extend_from_slice(&2u32.to_le_bytes());
        hashes(&c).iter().for_each(|h| entry.extend_from_slice(h.as_bytes()));
        let mut z = zstd::bulk::Compressor::new(PLAIN_LEVEL).unwrap();
        z.set_parameter(zstd::zstd_safe::CParameter::ChecksumFlag(true)).unwrap();
        entry.extend_from_slice(&z.compress(&raw).unwrap());
        assert_eq!(decode(&key, &entry, &no_dicts).unwrap(), (c.clone(), hashes(&c)));
        every_damage_is_caught(&key, &entry, &c);
    }

    /// A version 3 entry (no hashes stored, no check sum in its frame) is still read, its
    /// hashes computed.
    #[test]
    fn a_version_3_entry_is_still_read() {
        let (key, c) = (Key([9; 32]), compiled());
        let raw = body(&c);
        let mut entry = old_header(MAGIC_V3, &key, &c);
        entry.extend_from_slice(&zstd::bulk::compress(&raw, PLAIN_LEVEL).unwrap());
        assert_eq!(decode(&key, &entry, &no_dicts).unwrap(), (c.clone(), hashes(&c)));
        // A version 4 header on a frame without zstd's check sum is refused.
        let mut v4 = MAGIC_V4.to_vec();
        v4.extend_from_slice(&entry[8..HEADER + 16]);
        v4.extend_from_slice(&2u32.to_le_bytes());
        hashes(&c).iter().for_each(|h| v4.extend_from_slice(h.as_bytes()));
        v4.extend_from_slice(&entry[HEADER + 16..]);
        assert_eq!(decode(&key, &v4, &no_dicts).unwrap_err(), "its frame has no check sum");
    }
}
