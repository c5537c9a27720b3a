//! Entries exchanged with the remote cache: batched fills streamed into a local pack, and
//! the bundles of a build's keys, read on a fill and stored from the local entries.

use super::*;
use std::sync::atomic::AtomicU64;

/// Keys of a fill looked for in the local index and asked for at a time (their list is
/// 32 bytes a key).
const FILL_WINDOW: usize = 1 << 16;

impl Cache {
    /// Copies into the local cache the remote entries of `keys` that it lacks: from the parts
    /// of the bundle of `keys` most of whose keys it lacks when the remote streams
    /// ([`bundle`]), the rest fetched in batches ([`Remote::get_each`]); each checked as
    /// [`Cache::get`] checks it, and streamed into one pack as they arrive (no entry waits in
    /// memory). Whether every key is now held locally. A key the remote lacks is not asked
    /// for again this build; a corrupted entry is left to the build, which looks it up again,
    /// reports and recompiles it.
    pub fn fill_from_remote(&self, keys: &[Key]) -> bool {
        self.fill(keys, None)
    }

    /// [`Cache::fill_from_remote`] of `keys` (sorted, each once) without counting its hits:
    /// whether every key is held locally now, and which it filled (bit `i % 64` of word
    /// `i / 64` for `keys[i]`: a bit a key, where a list of the keys took 32 bytes a key),
    /// for a caller that fetched them before it knew which it uses to count those it does
    /// ([`Remote::count_hits`]).
    pub fn prefill_from_remote(&self, keys: &[Key]) -> (bool, Vec<u64>) {
        debug_assert!(keys.windows(2).all(|w| w[0] < w[1]), "sorted, each once");
        let filled: Vec<AtomicU64> = (0..keys.len().div_ceil(64)).map(|_| AtomicU64::new(0)).collect();
        let complete = self.fill(keys, Some(&filled));
        (complete, filled.into_iter().map(AtomicU64::into_inner).collect())
    }

    /// [`Cache::fill_from_remote`]; each key filled is counted as a hit, or marked in
    /// `filled` (by its place in `keys`, then sorted: see [`Cache::prefill_from_remote`]).
    pub(super) fn fill(&self, keys: &[Key], filled: Option<&[AtomicU64]>) -> bool {
        let Some(layer) = &self.remote else { return false };
        let hit = |key: &Key| match filled {
            Some(bits) => {
                if let Ok(i) = keys.binary_search(key) {
                    bits[i / 64].fetch_or(1 << (i % 64), Ordering::Relaxed);
                }
            }
            None => layer.remote.count_hit(),
        };
        // The single lookups' hits first: then the index knows them.
        let pending = layer.fills.lock().expect("no panics while locked").take();
        self.finish_fills(pending);
        let absent = layer.absent.lock().expect("no panics while locked").clone();
        // The keys to ask for are found a window at a time (the keys a fresh local cache
        // asks for are every key of the build: a list of them all doubled the fill's memory);
        // the index only grows during the fill, so no window finds more than this count.
        let known = |index: &Index, k: &Key| index.contains(k) || absent.contains(k);
        let unknown = self.with_index(|index| keys.iter().filter(|k| !known(index, k)).count());
        let complete = AtomicBool::new(absent.is_empty() || keys.iter().all(|k| !absent.contains(k)));
        // Not with signed values: a part is used as it streams, before its end could be
        // checked (each value is checked by itself; see `Remote::get_each`).
        let bundle = (layer.remote.streams() && !layer.remote.signs() && keys.len() >= bundle::MIN_KEYS)
            .then(|| bundle::Bundle::new(keys));
        let mut parts = vec![None; bundle.as_ref().map_or(0, |b| b.ids().len())];
        if unknown == 0 {
            self.keep_bundle(layer, bundle, parts);
            return complete.into_inner();
        }
        // Room for every key asked; failing to fill only costs a remote lookup next time.
        let pack = fill::FillPack::create(&self.dir, unknown).ok();
        let mut from_parts = Vec::new();
        if let (Some(b), Some(p), true) = (&bundle, &pack, unknown >= bundle::MIN_KEYS) {
            let mut missing: Vec<Key> =
                self.with_index(|index| keys.iter().filter(|k| !known(index, k)).copied().collect());
            missing.sort_unstable();
            (from_parts, parts) = self.fill_from_bundle(layer, b, &missing, p);
            from_parts.iter().for_each(hit);
        }
        self.keep_bundle(layer, bundle, parts);
        for window in keys.chunks(FILL_WINDOW) {
            let missing: Vec<Key> = self.with_index(|index| {
                let asked = |k: &Key| known(index, k) || from_parts.binary_search(k).is_ok();
                window.iter().filter(|k| !asked(k)).copied().collect()
            });
            self.fill_window(layer, &missing, pack.as_ref(), &complete, &hit);
        }
        // Written now, so that the build's lookups find them here (not in the remote again).
        self.finish_fills(pack);
        complete.into_inner()
    }

    /// Asks the remote for `missing` and pushes each entry that passes its check into `pack`.
    fn fill_window(
        &self,
        layer: &Layer,
        missing: &[Key],
        pack: Option<&fill::FillPack>,
        complete: &AtomicBool,
        hit: &(impl Fn(&Key) + Sync),
    ) {
        layer.remote.get_each(missing, |key, value| {
            let Some(bytes) = value else {
                layer.absent.lock().expect("no panics while locked").insert(*key);
                complete.store(false, Ordering::Relaxed);
                return;
            };
            // The value's one checksum (one blake3 of the whole value, several times faster
            // than one per artifact); the entry's own is checked when the build uses it.
            // An entry whose dictionary cannot be had is as good as damaged.
            let Some(entry) = remote_entry(key, bytes).ok().filter(|e| self.dictionary_at_hand(e)) else {
                // Looked up again by the build, which reports it and recompiles.
                complete.store(false, Ordering::Relaxed);
                return;
            };
            hit(key);
            // A failed write leaves the pack unfinished (removed).
            if let Some(p) = pack {
                let _ = p.push(key, entry);
            }
        });
    }

    /// The entries of `wanted` (sorted) that the parts of `bundle` most of whose keys are
    /// wanted hold (else most of a part would be dropped), checked and pushed into `pack` as
    /// they arrive: the keys filled (sorted), and whether each part was whole (`None`: not
    /// read).
    pub(super) fn fill_from_bundle(
        &self,
        layer: &Layer,
        bundle: &bundle::Bundle,
        wanted: &[Key],
        pack: &fill::FillPack,
    ) -> (Vec<Key>, Vec<Option<bool>>) {
        let read: Vec<usize> = (0..bundle.ids().len())
            .filter(|&i| {
                let part = bundle.part(i);
                part.iter().filter(|k| wanted.binary_search(k).is_ok()).count() * 2 >= part.len()
            })
            .collect();
        let ids: Vec<Key> = read.iter().map(|&i| bundle.ids()[i]).collect();
        let filled = Mutex::new(Vec::with_capacity(wanted.len()));
        let parts = Mutex::new(vec![None; bundle.ids().len()]);
        layer.remote.get_streamed(&ids, |n, body| {
            let i = read[n];
            let mut mine = Vec::new();
            let whole = body.is_some_and(|body| {
                // One entry at a time (a part is never held whole).
                let mut value = Vec::new();
                bundle::read_part(body, bundle.part(i), &mut value, |key, entry| {
                    if wanted.binary_search(key).is_ok()
                        && self.dictionary_at_hand(entry)
                        && pack.push(key, entry).is_ok()
                    {
                        mine.push(*key);
                    }
                })
            });
            parts.lock().expect("no panics while locked")[i] = Some(whole);
            filled.lock().expect("no panics while locked").extend(mine);
        });
        let mut filled = filled.into_inner().expect("no panics while locked");
        filled.sort_unstable();
        (filled, parts.into_inner().expect("no panics while locked"))
    }

    /// Fetches the preprocessing records under `key` from the remote cache into this
    /// folder's records file ([`Cache::records_path`]): streamed to a temporary file (a
    /// large set's records, held whole, were the largest part of a fresh local cache's
    /// memory), and renamed into place once their magic and checksum are checked; a reader
    /// then reads them in place ([`Cache::open_local_records`]). `Some(true)` once the file
    /// is there, `Some(false)` when the remote has no whole records under `key`, `None` when
    /// they arrived but could not be kept (a local write failed: the caller may hold them).
    pub fn fetch_remote_records(&self, key: &Key) -> Option<bool> {
        let Some(remote) = self.remote() else { return Some(false) };
        let (mut whole, mut kept) = (false, true);
        let written = crate::output::write_with(&self.records_path(key), false, |f, _| {
            let mut head = Vec::with_capacity(40);
            let mut body = blake3::Hasher::new();
            let mut out = std::io::BufWriter::with_capacity(1 << 16, f);
            // A local write that fails is not the remote's failure: the rest is only hashed.
            let mut write = |out: &mut std::io::BufWriter<&mut std::fs::File>, bytes: &[u8]| {
                kept = kept && std::io::Write::write_all(out, bytes).is_ok();
            };
            let arrived = remote.get_to(key, &mut |mut piece| {
                if head.len() < 40 {
                    let n = (40 - head.len()).min(piece.len());
                    head.extend_from_slice(&piece[..n]);
                    write(&mut out, &piece[..n]);
                    piece = &piece[n..];
                }
                body.update(piece);
                write(&mut out, piece);
                Ok(())
            });
            kept = kept && std::io::Write::flush(&mut out).is_ok();
            whole = arrived
                && head.len() == 40
                && &head[..8] == RECORD_MAGIC
                && body.finalize().as_bytes()[..] == head[8..40];
            match whole && kept {
                true => Ok(()),
                false => Err(std::io::Error::other("the remote records were not kept")),
            }
        });
        match (written, whole) {
            (Ok(()), _) => Some(true),
            (Err(_), true) => None,
            (Err(_), false) => Some(false),
        }
    }

    /// Keeps `bundle` for [`Cache::put_bundle`] when this build writes and a part of it is
    /// not known whole.
    pub(super) fn keep_bundle(&self, layer: &Layer, bundle: Option<bundle::Bundle>, parts: Vec<Option<bool>>) {
        let keep = layer.remote.writes() && parts.iter().any(|p| *p != Some(true));
        *layer.bundle.lock().expect("no panics while locked") = bundle.filter(|_| keep).map(|b| (b, parts));
    }

    /// Stores the parts of the bundle of the last fill's keys ([`bundle`]) that the remote
    /// lacks (asked with `HEAD` when the fill did not read them) or held damaged, from the
    /// local cache's entries, in read-write mode. A build calls this once every key's entry
    /// is in the local cache (after writing the archive); failing to only costs the next
    /// fresh cache a `GET` per key.
    pub fn put_bundle(&self) {
        let Some(layer) = &self.remote else { return };
        let Some((bundle, parts)) = layer.bundle.lock().expect("no panics while locked").take() else { return };
        (0..parts.len()).into_par_iter().for_each(|i| {
            let id = &bundle.ids()[i];
            if !layer.remote.writes() || parts[i].or_else(|| layer.remote.contains(id)) != Some(false) {
                return;
            }
            let keys = bundle.part(i);
            let size = bundle::part_overhead(keys.len()) + self.local_size(keys);
            if let Some(value) = bundle::encode_part(keys, size, |key, out| self.append_local_entry(key, out)) {
                layer.remote.store(id, &value);
            }
        });
    }

    /// Appends the newest local entry of `key` to `out`; whether there was one. Only its
    /// magic and key are checked: a build that assembles compiled or checked (on lookup or
    /// from the remote) every entry of its keys, and its readers check the entry's own
    /// checksum on use (a blake3 of every entry would add a noticeable share to the writing
    /// build's time).
    pub(super) fn append_local_entry(&self, key: &Key, out: &mut Vec<u8>) -> bool {
        let Some(l) = self.with_index(|index| index.newest(key)) else {
            return false;
        };
        let start = out.len();
        out.resize(start + l.len as usize, 0);
        let entry = &mut out[start..];
        let ok = l.pack.file.read_exact_at(entry, l.offset).is_ok() && is_entry_of(entry, key);
        if !ok {
            out.truncate(start);
            return false;
        }
        // An entry compressed with one of this cache's dictionaries goes out as it is once the
        // remote holds the dictionary, else without it.
        let shared = match codec::is_compressed(&out[start..]).then(|| codec::dictionary_of(&out[start..])) {
            None | Some(Ok(None)) => true,
            Some(Ok(Some(id))) => self.remote.as_ref().is_some_and(|layer| self.share_dict(layer, &id)),
            Some(Err(_)) => false,
        };
        if !shared {
            let portable = codec::decode(key, &out[start..], &|id| self.dicts.get(&self.dir, id))
                .map(|(c, hashes)| codec::encode(key, &c, &hashes, &HashMap::new()));
            out.truncate(start);
            match portable {
                Ok(entry) => out.extend_from_slice(&entry),
                Err(_) => return false,
            }
        }
        true
    }

    /// The bytes of the local entries of `keys` (the newest copy of each).
    pub(super) fn local_size(&self, keys: &[Key]) -> usize {
        self.with_index(|index| keys.iter().filter_map(|k| index.newest(k).map(|l| l.len as usize)).sum())
    }

    /// Writes the index of a fill pack and renames it into place; the index of this `Cache`
    /// (if read) then knows its entries. Failing to only costs remote lookups next time.
    pub(super) fn finish_fills(&self, pack: Option<fill::FillPack>) {
        let Some(Ok(Some(path))) = pack.map(fill::FillPack::finish) else { return };
        let mut index = self.index.write().expect("no panics while locked");
        if let Some(index) = index.as_mut() {
            index.add(&path);
        }
    }
}

impl Cache {
    /// The remote value of the `entry` of `key`, encoded as the local pack holds it, once
    /// the remote holds the dictionary it names (stored once per build): a reader fetches
    /// the dictionary when it first needs it ([`Cache::dict`]). `None` for an entry whose
    /// dictionary cannot be stored (no reader could decode it).
    pub(super) fn remote_value_for(&self, layer: &Layer, key: &Key, entry: &[u8]) -> Option<(Key, Vec<u8>)> {
        if let Ok(Some(id)) = codec::dictionary_of(entry) {
            if !self.share_dict(layer, &id) {
                return None;
            }
        }
        Some((*key, remote_value_of(key, entry)))
    }

    /// Whether the dictionary the remote `entry` names, if any, is in this cache or fetched
    /// from the remote into it.
    fn dictionary_at_hand(&self, entry: &[u8]) -> bool {
        match codec::dictionary_of(entry) {
            Ok(Some(id)) => self.dict(&id).is_ok(),
            Ok(None) => true,
            Err(_) => !codec::is_compressed(entry),
        }
    }

    /// Whether the remote holds the dictionary `id` of this cache: stored by this build
    /// (once), or found there.
    pub(super) fn share_dict(&self, layer: &Layer, id: &[u8; 16]) -> bool {
        let mut shared = layer.dicts_shared.lock().expect("no panics while locked");
        if shared.contains(id) {
            return true;
        }
        let Ok(d) = self.dicts.get(&self.dir, id) else { return false };
        let stored = layer.remote.store(&remote_dict_key(id), &d.file_bytes());
        if stored {
            shared.insert(*id);
        }
        stored
    }

    /// The dictionary `id`: the folder's, else the remote's (an entry a remote fill brought
    /// names the dictionary of the cache that compiled it), checked against its id and then
    /// written into the folder for later builds (held in memory only, when it cannot be).
    pub(super) fn dict(&self, id: &[u8; 16]) -> Result<Arc<codec::Dict>, String> {
        let local = self.dicts.get(&self.dir, id);
        let Some(layer) = self.remote.as_ref().filter(|_| local.is_err()) else { return local };
        let _one = layer.dict_fetch.lock().expect("no panics while locked");
        // Fetched by another worker meanwhile.
        if let Ok(d) = self.dicts.get(&self.dir, id) {
            return Ok(d);
        }
        let rkey = remote_dict_key(id);
        if layer.absent.lock().expect("no panics while locked").contains(&rkey) {
            return local;
        }
        let Some(d) = layer.remote.get(&rkey).and_then(|bytes| codec::parse_dict(&bytes)).filter(|d| d.id() == id)
        else {
            layer.absent.lock().expect("no panics while locked").insert(rkey);
            return local;
        };
        let _ = self.write_file(&self.dir.join(codec::dict_file_name(id)), &d.file_bytes());
        layer.dicts_shared.lock().expect("no panics while locked").insert(*id);
        Ok(self.dicts.keep(d))
    }
}
