//! Local entries: lookups in the packs and writing new packs.

use super::*;

impl Cache {
    /// Whether some pack holds `key` (its content is checked by [`Cache::get`]).
    pub fn contains(&self, key: &Key) -> bool {
        self.with_index(|index| index.contains(key))
    }

    /// The newest pack holding `key`.
    pub fn pack_of(&self, key: &Key) -> Option<PathBuf> {
        self.with_index(|index| index.newest(key).map(|l| l.pack.path.clone()))
    }

    /// The entry of `key`: from a local pack, else from the remote cache (checked, then
    /// queued to be filled into the local cache).
    pub fn get(&self, key: &Key) -> Lookup {
        self.get_unless_held(key, &|_| false)
    }

    /// [`Cache::get`], except that a local entry (version 5) whose artifacts' blake3 all
    /// satisfy `held` is [`Lookup::Held`]: its artifacts are not decompressed (the caller
    /// has them elsewhere, as a build has the blobs of the archive it replaces).
    pub fn get_unless_held(&self, key: &Key, held: &dyn Fn(&blake3::Hash) -> bool) -> Lookup {
        let local = self.get_local(key, held);
        let Some(layer) = &self.remote else { return local };
        if matches!(local, Lookup::Hit(..) | Lookup::Held(_)) {
            return local;
        }
        if layer.absent.lock().expect("no panics while locked").contains(key) {
            return local;
        }
        let Some(bytes) = layer.remote.get(key) else {
            layer.absent.lock().expect("no panics while locked").insert(*key);
            return local;
        };
        match remote_entry(key, &bytes).and_then(|entry| Ok((self.decode_hashed(key, entry)?, entry))) {
            Ok(((c, hashes), entry)) => {
                layer.remote.count_hit();
                let mut fills = layer.fills.lock().expect("no panics while locked");
                if fills.as_ref().is_some_and(fill::FillPack::is_full) {
                    self.finish_fills(fills.take());
                }
                if fills.is_none() {
                    *fills = fill::FillPack::create(&self.dir, FILL_ROWS).ok();
                }
                // Failing to fill only costs a remote lookup next time.
                if fills.as_mut().is_some_and(|p| p.push(key, entry).is_err()) {
                    *fills = None;
                }
                Lookup::Hit(c, hashes)
            }
            Err(why) => Lookup::Corrupt(format!(
                "remote cache entry {key} at {} is corrupted ({why}); recompiling",
                layer.remote.url()
            )),
        }
    }

    /// The entry `bytes` of `key`, of either version, checked.
    #[cfg(test)]
    pub(super) fn decode(&self, key: &Key, bytes: &[u8]) -> Result<Compiled, String> {
        self.decode_hashed(key, bytes).map(|(c, _)| c)
    }

    /// The entry `bytes` of `key`, of either version, checked, and the blake3 of each
    /// artifact (its checksum is made of them).
    pub(super) fn decode_hashed(&self, key: &Key, bytes: &[u8]) -> Result<(Compiled, Vec<blake3::Hash>), String> {
        if codec::is_compressed(bytes) {
            return codec::decode(key, bytes, &|id| self.dict(id));
        }
        decode_v2_hashed(key, bytes, None)
    }

    /// The entry `bytes` of `key` checked: [`Lookup::Held`] when it is a version 5 entry
    /// whose artifacts all satisfy `held`, else [`Lookup::Hit`].
    fn decode_unless_held(
        &self,
        key: &Key,
        bytes: &[u8],
        held: &dyn Fn(&blake3::Hash) -> bool,
    ) -> Result<Lookup, String> {
        if codec::has_head(bytes) {
            let head = codec::head(key, bytes, &|id| self.dict(id))?;
            if !head.artifacts.is_empty() && head.artifacts.iter().all(|a| held(&a.2)) {
                return Ok(Lookup::Held(Held { reflection: head.reflection, artifacts: head.artifacts }));
            }
        }
        self.decode_hashed(key, bytes).map(|(c, hashes)| Lookup::Hit(c, hashes))
    }

    pub(super) fn get_local(&self, key: &Key, held: &dyn Fn(&blake3::Hash) -> bool) -> Lookup {
        let locations = self.with_index(|index| index.copies(key));
        let mut corrupt = None;
        for l in &locations {
            let mut bytes = vec![0; l.len as usize];
            let decoded = match l.pack.file.read_exact_at(&mut bytes, l.offset) {
                Ok(()) => self.decode_unless_held(key, &bytes, held),
                Err(_) => Err("entry is truncated".to_string()),
            };
            match decoded {
                Ok(found) => {
                    l.pack.touch();
                    return found;
                }
                Err(why) => {
                    corrupt.get_or_insert_with(|| {
                        format!("cache entry {key} in {} is corrupted ({why}); recompiling", l.pack.path.display())
                    });
                }
            }
        }
        corrupt.map_or(Lookup::Miss, Lookup::Corrupt)
    }

    /// Stores one entry (a pack of one).
    pub fn put(&self, key: &Key, compiled: &Compiled) -> Result<(), Error> {
        self.put_pack(&[(*key, compiled)])
    }

    /// Stores `entries` as one pack, atomically.
    pub fn put_pack(&self, entries: &[(Key, &Compiled)]) -> Result<(), Error> {
        let hashes: Vec<Vec<blake3::Hash>> =
            entries.par_iter().map(|(_, c)| c.artifacts.iter().map(|(_, b)| blake3::hash(b)).collect()).collect();
        let entries: Vec<(Key, &Compiled, &[blake3::Hash])> =
            entries.iter().zip(&hashes).map(|((k, c), h)| (*k, *c, &h[..])).collect();
        self.put_pack_hashed(&entries, Packing::Compressed)
    }

    /// [`Cache::put_pack`] with the blake3 of every artifact already known (in the order of
    /// each entry's artifacts). With a remote cache, the pack also holds the remote hits not
    /// yet filled in (finished as a pack of their own), and each of `entries` is stored to
    /// the remote (in read-write mode). `packing` says how the local pack stores them.
    pub fn put_pack_hashed(
        &self,
        entries: &[(Key, &Compiled, &[blake3::Hash])],
        packing: Packing,
    ) -> Result<(), Error> {
        if let Some(layer) = &self.remote {
            let pending = layer.fills.lock().expect("no panics while locked").take();
            self.finish_fills(pending);
        }
        if entries.is_empty() {
            return Ok(());
        }
        let encoded = self.encode_entries(entries, packing);
        let local = self.write_pack(entries, &encoded);
        // The entries as the pack holds them (compressed once, with the cache's dictionaries).
        if let Some(layer) = self.remote.as_ref().filter(|l| l.remote.writes()) {
            let values: Vec<(Key, Vec<u8>)> = entries
                .iter()
                .zip(&encoded)
                .filter_map(|((key, ..), entry)| self.remote_value_for(layer, key, entry))
                .collect();
            layer.remote.put_each(&values);
        }
        local
    }

    /// `entries` as a pack holds them: compressed ([`codec`]; a dictionary is trained first
    /// for each kind the cache has none of, when `entries` hold enough of it), or stored
    /// ([`Packing::Stored`]: neither compressed nor counted towards a dictionary).
    fn encode_entries(&self, entries: &[(Key, &Compiled, &[blake3::Hash])], packing: Packing) -> Vec<Vec<u8>> {
        match packing {
            Packing::Stored => {
                entries.par_iter().map(|(key, c, hashes)| codec::encode_stored(key, c, hashes)).collect()
            }
            Packing::Compressed => {
                let files = || self.files().map(|(p, _)| p).collect();
                let write = |path: &Path, bytes: &[u8]| self.write_file(path, bytes).is_ok();
                let dicts = codec::dictionaries_for(&self.dicts, &self.dir, files, entries, write);
                entries.par_iter().map(|(key, c, hashes)| codec::encode(key, c, hashes, &dicts)).collect()
            }
        }
    }

    /// Writes `entries`, `encoded` by [`Cache::encode_entries`], as one pack.
    fn write_pack(&self, entries: &[(Key, &Compiled, &[blake3::Hash])], encoded: &[Vec<u8>]) -> Result<(), Error> {
        let count = entries.len();
        let mut rows = Vec::with_capacity(count * ROW);
        let mut offset = (PACK_HEADER + count * ROW) as u64;
        for (key, entry) in entries.iter().map(|e| e.0).zip(encoded) {
            rows.extend_from_slice(&key.0);
            rows.extend_from_slice(&offset.to_le_bytes());
            rows.extend_from_slice(&(entry.len() as u64).to_le_bytes());
            offset += entry.len() as u64;
        }
        let rows_hash = blake3::hash(&rows);
        let count = (count as u64).to_le_bytes();
        // Named by content: two builds writing the same pack rename one over the other.
        let mut name = blake3::Hasher::new();
        name.update(rows_hash.as_bytes());
        for entry in encoded {
            name.update(&entry[8..40]);
        }
        let path = self.dir.join(format!("{}.{PACK_EXTENSION}", &name.finalize().to_hex()[..32]));
        let mut pieces: Vec<&[u8]> = vec![PACK_MAGIC, &count, rows_hash.as_bytes(), &rows];
        pieces.extend(encoded.iter().map(Vec::as_slice));
        self.write_pieces(&path, &pieces)?;
        // Later lookups through this `Cache` see the new pack.
        let mut index = self.index.write().expect("no panics while locked");
        if let Some(index) = index.as_mut().filter(|_| self.index_puts) {
            index.add(&path);
        }
        Ok(())
    }

    pub(super) fn write_file(&self, path: &Path, bytes: &[u8]) -> Result<(), Error> {
        self.write_pieces(path, &[bytes])
    }

    /// Writes the concatenation of `pieces` to a temporary file in the cache folder, then
    /// renames it to `path` ([`crate::output`]: the folder is made again if it was removed
    /// under us, and whatever is not a regular file at `path` is never renamed over).
    pub(super) fn write_pieces(&self, path: &Path, pieces: &[&[u8]]) -> Result<(), Error> {
        crate::archive::write_pieces(path, pieces, false).map_err(|source| Error { path: path.to_path_buf(), source })
    }
}
