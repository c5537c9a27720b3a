//! Assemble: the archive, the loose files of `--emit-dir` and the archive's stamp.
//!
//! Each key's artifacts arrive ([`Assembler::add`]) as they are produced, in any order;
//! [`Assembler::finish`] writes the permutations in enumeration order, so the bytes depend
//! only on the set (not on `-j`, the cache state or shards). Nothing is kept when the build
//! writes neither an archive nor loose files (a check or a shard).

use std::collections::{BTreeMap, HashMap};
use std::sync::Mutex;

use super::plan::{Keys, Plan};
use super::preprocess::Preprocessed;
use super::store::Store;
use super::Error;
use crate::archive::{self, ArchiveWriter, DimensionRecord, PermutationRecord, ShaderRecord, Stage};
use crate::cache::Key;
use crate::compile::{self, Compiled};

pub(super) struct Assembler<'p> {
    plan: &'p Plan<'p>,
    /// Each key's artifacts with their blake3, until the archive is written.
    keys: Mutex<HashMap<Key, (Compiled, Vec<blake3::Hash>)>>,
}

/// What [`Assembler::finish`] wrote: distinct blobs and (permutation, target) pairs.
pub(super) struct Written {
    pub artifacts: usize,
    pub permutation_artifacts: usize,
    pub archive: Option<std::path::PathBuf>,
}

impl<'p> Assembler<'p> {
    pub fn new(plan: &'p Plan<'p>) -> Assembler<'p> {
        Assembler { plan, keys: Mutex::default() }
    }

    /// A key's artifacts, with the blake3 of each.
    pub fn add(&self, key: &Key, _stage: Stage, c: &Compiled, hashes: &[blake3::Hash]) {
        if !self.plan.assembles() {
            return;
        }
        self.keys.lock().expect("no panics while locked").insert(*key, (c.clone(), hashes.to_vec()));
    }

    /// Everything the archive's content depends on: each kept permutation's name, shader
    /// record and key, in order, and the versions.
    fn fingerprint(&self, pre: &Preprocessed) -> blake3::Hash {
        let mut h = blake3::Hasher::new();
        h.update(b"kiln build fingerprint v1\0");
        h.update(crate::VERSION.as_bytes());
        h.update(b"\0");
        h.update(compile::NAGA_VERSION.as_bytes());
        for (p, r) in self.plan.kept.iter().zip(pre) {
            let Ok(r) = r else { continue };
            let dims: Vec<(&str, &[String])> =
                p.shader.dimensions.iter().map(|d| (d.name.as_str(), d.labels.as_slice())).collect();
            let line = format!("\0{}\0{}\0{}\0{:?}\0{:?}\0", p.name(), p.shader.entry, p.shader.stage, p.values, dims);
            h.update(line.as_bytes());
            h.update(&r.key.0);
        }
        h.finalize()
    }

    /// The artifact counts of the archive when it is already the output of this build:
    /// every permutation has the key it had when the archive was written, and the archive
    /// is the file that build wrote (like cargo's freshness check). Only with a cache (the
    /// stamp lives there), nothing failed, and no `--emit-dir`.
    pub fn up_to_date(&self, store: &Store, pre: &Preprocessed, keys: &Keys, failed: bool) -> Option<(usize, usize)> {
        let options = self.plan.options;
        let out = options.output.as_ref().filter(|_| options.emit_dir.is_none() && !failed)?;
        let keys: Vec<Key> = keys.groups.iter().map(|g| g.0).collect();
        store.fresh_archive(out, &self.fingerprint(pre), &keys)
    }

    /// Writes the archive and the loose files, then stamps the archive.
    pub fn finish(&self, pre: &Preprocessed, store: &Store) -> Result<Written, Error> {
        let options = self.plan.options;
        let mut written = Written { artifacts: 0, permutation_artifacts: 0, archive: None };
        if !self.plan.assembles() {
            return Ok(written);
        }
        let keys = self.keys.lock().expect("no panics while locked");
        let mut writer = ArchiveWriter::new();
        writer.set_naga_version(compile::NAGA_VERSION);
        let mut index: BTreeMap<String, BTreeMap<&'static str, String>> = BTreeMap::new();
        let mut emitted: HashMap<blake3::Hash, String> = HashMap::new();
        for (p, pm) in self.plan.kept.iter().zip(pre) {
            let Ok(pm) = pm else { continue };
            let (c, hashes) = &keys[&pm.key];
            let shader = writer.add_shader(ShaderRecord {
                name: p.shader.name.clone(),
                level: p.level.name.clone(),
                entry: p.shader.entry.clone(),
                stage: p.shader.stage,
                dimensions: p
                    .shader
                    .dimensions
                    .iter()
                    .map(|d| DimensionRecord { name: d.name.clone(), labels: d.labels.clone() })
                    .collect(),
            });
            let reflection = writer.add_reflection(&c.reflection);
            let name = p.name();
            let mut artifacts = Vec::with_capacity(c.artifacts.len());
            for ((t, bytes), hash) in c.artifacts.iter().zip(hashes) {
                let hash = *hash;
                artifacts.push((*t, writer.add_blob_ref(bytes, hash)));
                if let Some(dir) = &options.emit_dir {
                    let file = match emitted.get(&hash) {
                        Some(f) => f.clone(),
                        None => {
                            let f = format!("{}.{}", &hash.to_hex()[..32], t.extension(p.shader.stage));
                            archive::write_atomic_unsynced(&dir.join(&f), bytes).map_err(|e| {
                                Error::Io(format!("error: cannot write {}: {e}", dir.join(&f).display()))
                            })?;
                            emitted.insert(hash, f.clone());
                            f
                        }
                    };
                    index.entry(name.clone()).or_default().insert(t.name(), file);
                }
            }
            written.permutation_artifacts += artifacts.len();
            writer.add_permutation(PermutationRecord { name, shader, values: p.values.clone(), reflection, artifacts });
        }
        written.artifacts = writer.blob_count();
        if let Some(dir) = &options.emit_dir {
            let json = serde_json::to_vec_pretty(&index).expect("index serializes");
            let path = dir.join("index.json");
            archive::write_atomic_unsynced(&path, &json)
                .map_err(|e| Error::Io(format!("error: cannot write {}: {e}", path.display())))?;
        }
        if let Some(out) = &options.output {
            writer.write_unsynced(out).map_err(|e| Error::Io(format!("error: {e}")))?;
            written.archive = Some(out.clone());
            if options.emit_dir.is_none() {
                store.stamp_archive(out, &self.fingerprint(pre), (written.artifacts, written.permutation_artifacts));
            }
        }
        Ok(written)
    }
}
