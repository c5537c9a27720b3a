//! Bundles: the entries of a build's keys in a few large remote values, so that a fresh
//! local cache fills from a plain file server with a few `GET`s instead of one per key.
//!
//! A build that assembles an archive (in read-write mode, with an HTTP remote) stores, beside
//! each entry under its own key, the entries of all its distinct keys in parts: the keys
//! sorted and cut after each key whose last byte is 0 (256 keys a part on average, at most
//! [`MAX_PART_KEYS`]), each part under a key derived from its own keys (still
//! `<prefix>/<key>`: any server of the convention serves it). Cut by content, a changed
//! key changes only its own part: after an edit a writer stores the parts of the keys it
//! changed, not the whole set again. A build with a fresh local cache reads the parts most
//! of whose keys it lacks as they arrive (a part is never held whole) and asks one `GET`
//! per key for the rest. Serving one `GET` per key cost a server about as much CPU as the
//! rest of a warm-remote build.
//!
//! A part: [`MAGIC`], then for each key of the part, in order, the key, the length of its
//! value (u64) and its remote value ([`super::remote_value_of`], checked by its own checksum
//! as any remote value). A record that fails its check is skipped (that key is fetched on
//! its own); a record that is not one of the part's keys in order, or a truncated one, ends
//! the part; either makes the part not whole, and the next build that writes and reads it
//! stores it again.

use std::io::{self, Read};

use super::fault::MAX_VALUE;
use super::{Key, REMOTE_HEADER, REMOTE_MAGIC};

/// Fewer keys than this are fetched one `GET` each (pipelined, one batch or two).
pub(super) const MIN_KEYS: usize = 64;
/// The most keys of a part (the writer holds one part per worker, so this bounds its
/// memory).
pub(super) const MAX_PART_KEYS: usize = 1024;
const MAGIC: &[u8; 8] = b"KILNBD\0\x01";

/// The parts of the bundle of a set of keys.
#[derive(Debug)]
pub(super) struct Bundle {
    /// Sorted, without duplicates.
    keys: Vec<Key>,
    /// Where each part starts in `keys`.
    starts: Vec<usize>,
    /// Each part's key.
    ids: Vec<Key>,
}

impl Bundle {
    pub fn new(keys: &[Key]) -> Bundle {
        let mut keys = keys.to_vec();
        keys.sort_unstable();
        keys.dedup();
        let mut starts = vec![0];
        for (i, key) in keys.iter().enumerate().take(keys.len().saturating_sub(1)) {
            if key.0[31] == 0 || i + 1 - starts[starts.len() - 1] == MAX_PART_KEYS {
                starts.push(i + 1);
            }
        }
        if keys.is_empty() {
            starts.clear();
        }
        let mut bundle = Bundle { keys, starts, ids: Vec::new() };
        bundle.ids = (0..bundle.starts.len())
            .map(|i| {
                let part = bundle.part(i);
                let mut h = blake3::Hasher::new();
                h.update(b"kiln remote bundle part v1\0");
                h.update(&(part.len() as u64).to_le_bytes());
                part.iter().for_each(|k| {
                    h.update(&k.0);
                });
                Key(*h.finalize().as_bytes())
            })
            .collect();
        bundle
    }

    /// Each part's key, in order.
    pub fn ids(&self) -> &[Key] {
        &self.ids
    }

    /// The keys of part `i`.
    pub fn part(&self, i: usize) -> &[Key] {
        let end = self.starts.get(i + 1).copied().unwrap_or(self.keys.len());
        &self.keys[self.starts[i]..end]
    }
}

/// The value of a part holding `keys` (`size` bytes, room made at once), `append` adding
/// each key's entry to it; `None` when one is missing.
pub(super) fn encode_part(keys: &[Key], size: usize, append: impl Fn(&Key, &mut Vec<u8>) -> bool) -> Option<Vec<u8>> {
    let mut out = Vec::with_capacity(size);
    out.extend_from_slice(MAGIC);
    for key in keys {
        let at = out.len();
        out.extend_from_slice(&key.0);
        out.extend_from_slice(&[0; 8]);
        out.extend_from_slice(REMOTE_MAGIC);
        out.extend_from_slice(&[0; REMOTE_HEADER - 8]);
        if !append(key, &mut out) {
            return None;
        }
        let len = (out.len() - at - 40) as u64;
        out[at + 32..at + 40].copy_from_slice(&len.to_le_bytes());
        let sum = super::remote_checksum(key, &out[at + 40 + REMOTE_HEADER..]);
        out[at + 48..at + 40 + REMOTE_HEADER].copy_from_slice(&sum);
    }
    Some(out)
}

/// The bytes a part takes beyond its entries': its magic, and a key, a length and a value
/// header per entry.
pub(super) fn part_overhead(keys: usize) -> usize {
    MAGIC.len() + keys * (40 + REMOTE_HEADER)
}

/// Reads the part of `keys` from `body` as it arrives, each value into `value`, and calls
/// `entry` with each key whose value passes its check and that value's entry. Whether the
/// part was whole: every key, each checked, and nothing after.
pub(super) fn read_part(
    body: &mut dyn Read,
    keys: &[Key],
    value: &mut Vec<u8>,
    mut entry: impl FnMut(&Key, &[u8]),
) -> bool {
    let mut magic = [0; 8];
    if body.read_exact(&mut magic).is_err() || &magic != MAGIC {
        return false;
    }
    let (mut next, mut whole) = (0, true);
    loop {
        let mut head = [0; 40];
        match read_up_to(body, &mut head) {
            Ok(0) => return whole && next == keys.len(),
            Ok(40) => {}
            _ => return false,
        }
        let key = Key(head[..32].try_into().expect("32 bytes"));
        let len = u64::from_le_bytes(head[32..].try_into().expect("8 bytes"));
        // The part's keys in order, some possibly left out.
        let Some(skipped) = keys[next..].iter().position(|k| *k == key) else { return false };
        whole &= skipped == 0;
        next += skipped + 1;
        if len > MAX_VALUE {
            return false;
        }
        value.clear();
        // Grown as it comes past a megabyte: a damaged length reserves no more.
        value.reserve((len as usize).min(1 << 20));
        match body.take(len).read_to_end(value) {
            Ok(n) if n as u64 == len => {}
            _ => return false,
        }
        match super::remote_entry(&key, value) {
            Ok(e) => entry(&key, e),
            Err(_) => whole = false,
        }
    }
}

/// Fills `buffer` from `reader` unless it ends first; how much was read.
fn read_up_to(reader: &mut dyn Read, buffer: &mut [u8]) -> io::Result<usize> {
    let mut n = 0;
    while n < buffer.len() {
        match reader.read(&mut buffer[n..]) {
            Ok(0) => break,
            Ok(k) => n += k,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(n)
}
