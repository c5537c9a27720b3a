//! A manifest added in name order ([`super::StreamingWriter::add_permutation_sorted`]): each
//! permutation is encoded as it comes (its record, values, artifacts and name to their parts,
//! its id to a bucket), so that the writer holds nothing per permutation. The pending
//! permutations of an unsorted manifest, sorted and numbered at the end, are the largest
//! table a large build holds where its memory peaks; a caller that can give the
//! permutations in the archive's order saves all of it. The bytes are those the unsorted
//! path writes for the same permutations: shaders, reflections and blobs are numbered by
//! first use in name order, which is the order they come in here.

use std::fs::File;
use std::path::{Path, PathBuf};

use super::{
    encode_artifact, pad8, unlinked_file, ArchiveError, BlobId, BlobTable, FastMap, FileAt, ManifestCounts,
    NewPermutation, Reflection, ShaderRecord, SpillBuf, TablesOut, Target, ID_LEN, RECORD_LEN, VALUE_LEN,
};
use crate::format::Record;

/// Bytes a part keeps before it writes them to its file.
const PART_BUFFER: usize = 1 << 16;

/// Bytes of an id waiting in its bucket: the id and the permutation's index.
const PENDING_ID: usize = 20;

/// The most bytes of ids one bucket should hold (ids are uniform: buckets fill evenly), so
/// that sorting one adds little to the writer's memory.
const BUCKET_BYTES: usize = 1 << 20;

/// One part of the manifest as it is written: in memory, or in its own unlinked file a
/// buffer at a time.
struct Part {
    file: Option<File>,
    written: u64,
    pending: Vec<u8>,
}

impl Part {
    fn new(file: Option<File>) -> Part {
        Part { file, written: 0, pending: Vec::new() }
    }

    fn push(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        self.pending.extend_from_slice(bytes);
        if self.file.is_some() && self.pending.len() >= PART_BUFFER {
            self.flush()?;
        }
        Ok(())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        if let Some(f) = &self.file {
            f.write_all_at(&self.pending, self.written)?;
            self.written += self.pending.len() as u64;
            self.pending.clear();
        }
        Ok(())
    }

    fn len(&self) -> u64 {
        self.written + self.pending.len() as u64
    }

    /// The part, flushed, as the archive's writer copies it (borrowing its file).
    fn spill_buf(&mut self) -> std::io::Result<SpillBuf<'_>> {
        self.flush()?;
        Ok(match &self.file {
            Some(file) => SpillBuf::File { file, start: 0, written: self.written, pending: Vec::new() },
            None => SpillBuf::Memory(std::mem::take(&mut self.pending)),
        })
    }
}

/// The ids of the permutations, by their leading bits into buckets of blocks in one file (or
/// memory), sorted a bucket at a time at the end: never all of them in memory at once.
struct Ids {
    file: Option<File>,
    /// Bits of the id that pick its bucket (from its top).
    bits: u32,
    buckets: Vec<Bucket>,
    /// Where the next block goes in the file.
    next: u64,
}

#[derive(Default)]
struct Bucket {
    /// Blocks written: offset and length.
    blocks: Vec<(u64, u32)>,
    pending: Vec<u8>,
}

impl Ids {
    /// Room for `permutations` ids: buckets of at most [`BUCKET_BYTES`] if they fill evenly.
    fn new(file: Option<File>, permutations: usize) -> Ids {
        let wanted = (permutations * PENDING_ID).div_ceil(BUCKET_BYTES).next_power_of_two().min(1 << 10);
        let bits = if file.is_some() { wanted.trailing_zeros() } else { 0 };
        Ids { file, bits, buckets: (0..1usize << bits).map(|_| Bucket::default()).collect(), next: 0 }
    }

    fn push(&mut self, id: u128, index: u32) -> std::io::Result<()> {
        let b = if self.bits == 0 { 0 } else { (id >> (128 - self.bits)) as usize };
        let bucket = &mut self.buckets[b];
        bucket.pending.extend_from_slice(&id.to_le_bytes());
        bucket.pending.extend_from_slice(&index.to_le_bytes());
        // A bucket's buffer is a fraction of a bucket, so that all buffers together stay small.
        let limit = (BUCKET_BYTES >> 6).max(PENDING_ID) / PENDING_ID * PENDING_ID;
        if let Some(f) = self.file.as_ref().filter(|_| bucket.pending.len() >= limit) {
            f.write_all_at(&bucket.pending, self.next)?;
            bucket.blocks.push((self.next, bucket.pending.len() as u32));
            self.next += bucket.pending.len() as u64;
            bucket.pending.clear();
        }
        Ok(())
    }

    /// Writes the ids table to `out`: each id and index, sorted by id then index.
    fn write_sorted(mut self, out: &mut Part) -> std::io::Result<()> {
        let mut bytes = Vec::new();
        let mut ids: Vec<(u128, u32)> = Vec::new();
        for bucket in std::mem::take(&mut self.buckets) {
            bytes.clear();
            for &(offset, len) in &bucket.blocks {
                let at = bytes.len();
                bytes.resize(at + len as usize, 0);
                self.file.as_ref().ok_or_else(super::changed)?.read_exact_at(&mut bytes[at..], offset)?;
            }
            bytes.extend_from_slice(&bucket.pending);
            drop(bucket);
            ids.clear();
            ids.extend(bytes.chunks_exact(PENDING_ID).map(|c| {
                let id = u128::from_le_bytes(c[..16].try_into().expect("16 bytes"));
                (id, u32::from_le_bytes(c[16..].try_into().expect("4 bytes")))
            }));
            ids.sort_unstable();
            for &(id, index) in &ids {
                out.push(&super::encode_id(id, index))?;
            }
        }
        Ok(())
    }
}

/// The manifest of a writer whose permutations come in name order, encoded as they come.
pub(super) struct Sorted {
    /// The archive's path, for errors.
    output: PathBuf,
    shaders: Vec<ShaderRecord>,
    shader_index: FastMap<(String, String), u32>,
    reflections: Vec<Reflection>,
    reflection_index: FastMap<Reflection, u32>,
    /// The shader and reflection of the last permutation (see `Entries::last`).
    last: Option<(u32, u32)>,
    /// Each slot of the writer's blob table's blob id, by first use (`u32::MAX`: none yet).
    blob_ids: Vec<u32>,
    /// Each blob id's target.
    targets: Vec<Target>,
    /// The last permutation's name: each must come after it.
    previous: String,
    records: Part,
    values: Part,
    artifacts: Part,
    names: Part,
    ids: Ids,
    /// The ids table, sorted (at the end).
    ids_out: Part,
    counts: ManifestCounts,
}

/// What [`Sorted`] leaves for the archive's assembly.
pub(super) struct SortedParts {
    pub shaders: Vec<ShaderRecord>,
    pub reflections: Vec<Reflection>,
    pub counts: ManifestCounts,
    records: Part,
    ids: Part,
    values: Part,
    artifacts: Part,
    names: Part,
}

impl Sorted {
    /// A sorted manifest of about `permutations` (for the ids' buckets), its blobs in `slots`
    /// slots of the writer's table; its parts in unlinked files beside `beside` if
    /// `spill`, else in memory.
    pub(super) fn new(beside: &Path, spill: bool, permutations: usize, slots: usize) -> std::io::Result<Sorted> {
        let file = || spill.then(|| unlinked_file(beside)).transpose();
        Ok(Sorted {
            output: beside.to_path_buf(),
            shaders: Vec::new(),
            shader_index: FastMap::default(),
            reflections: Vec::new(),
            reflection_index: FastMap::default(),
            last: None,
            blob_ids: vec![u32::MAX; slots],
            targets: Vec::new(),
            previous: String::new(),
            records: Part::new(file()?),
            values: Part::new(file()?),
            artifacts: Part::new(file()?),
            names: Part::new(file()?),
            ids: Ids::new(file()?, permutations),
            ids_out: Part::new(file()?),
            counts: ManifestCounts::default(),
        })
    }

    /// Adds `p`, whose artifacts are `artifacts` (targets and slots of the writer's table).
    pub(super) fn add(
        &mut self,
        p: &NewPermutation<'_, u32>,
        artifacts: impl ExactSizeIterator<Item = (Target, u32)> + Clone,
    ) -> Result<(), ArchiveError> {
        let input = |m: String| ArchiveError::Input(m);
        if p.values.len() != p.shader.dimensions.len() {
            return Err(input(format!("permutation `{}` has the wrong number of values for its shader", p.name)));
        }
        if self.counts.permutations > 0 && p.name.as_str() <= self.previous.as_str() {
            return Err(input(format!("permutation `{}` was added twice, or out of name order", p.name)));
        }
        let count = u8::try_from(artifacts.len()).ok();
        let Some(count) = count.filter(|_| super::distinct(artifacts.clone().map(|a| a.0))) else {
            return Err(input(format!("permutation `{}` names artifacts of no writer, or two of one target", p.name)));
        };
        let shader = self.shader(p)?;
        let reflection = self.reflection(p.reflection);
        self.last = Some((shader, reflection));
        let too_many = || input("more than 2^32 values or artifacts".into());
        let record = Record {
            name_offset: self.counts.names_len,
            name_len: u32::try_from(p.name.len()).map_err(|_| too_many())?,
            shader,
            reflection,
            first_value: u32::try_from(self.counts.values).map_err(|_| too_many())?,
            first_artifact: u32::try_from(self.counts.artifacts).map_err(|_| too_many())?,
            artifact_count: u32::from(count),
        };
        let index = u32::try_from(self.counts.permutations).map_err(|_| too_many())?;
        let id = crate::permutation_id(&p.shader.name, &p.shader.level, &p.values);
        self.write(p, &record, artifacts, (id, index)).map_err(|source| self.failed(source))?;
        self.previous.clear();
        self.previous.push_str(&p.name);
        self.counts.permutations += 1;
        self.counts.values += p.values.len() as u64;
        self.counts.artifacts += u64::from(count);
        self.counts.names_len += p.name.len() as u64;
        Ok(())
    }

    /// Writes `p`'s record, values, artifacts (their blobs numbered by first use), name and id.
    fn write(
        &mut self,
        p: &NewPermutation<'_, u32>,
        record: &Record,
        artifacts: impl Iterator<Item = (Target, u32)>,
        (id, index): (u128, u32),
    ) -> std::io::Result<()> {
        self.records.push(&record.encode())?;
        for v in &p.values {
            self.values.push(&v.to_le_bytes())?;
        }
        for (t, slot) in artifacts {
            let cell = self.blob_ids.get_mut(slot as usize).ok_or_else(super::changed)?;
            if *cell == u32::MAX {
                *cell = self.targets.len() as u32;
                self.targets.push(t);
            }
            self.artifacts.push(&encode_artifact(t, BlobId(*cell)))?;
        }
        self.names.push(p.name.as_bytes())?;
        self.ids.push(id, index)
    }

    fn failed(&self, source: std::io::Error) -> ArchiveError {
        ArchiveError::Write { path: self.output.clone(), source }
    }

    /// The number of `p`'s shader by first use; an error if another record has its name.
    fn shader(&mut self, p: &NewPermutation<'_, u32>) -> Result<u32, ArchiveError> {
        if let Some(s) = self.last.map(|l| l.0).filter(|&s| self.shaders[s as usize] == *p.shader) {
            return Ok(s);
        }
        let key = (p.shader.name.clone(), p.shader.level.clone());
        match self.shader_index.get(&key) {
            Some(&i) if self.shaders[i as usize] == *p.shader => Ok(i),
            Some(_) => Err(ArchiveError::Input(format!(
                "permutation `{}` gives shader `{}@{}` a record that differs from an earlier permutation's",
                p.name, key.0, key.1
            ))),
            None => {
                let i = self.shaders.len() as u32;
                self.shaders.push(p.shader.clone());
                self.shader_index.insert(key, i);
                Ok(i)
            }
        }
    }

    /// The number of `reflection` by first use.
    fn reflection(&mut self, reflection: &Reflection) -> u32 {
        if let Some(r) = self.last.map(|l| l.1).filter(|&r| self.reflections[r as usize] == *reflection) {
            return r;
        }
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

    /// The blob numbering (each slot's id, each id's target) and the parts, its ids sorted;
    /// an error if a blob named was never added to `table`.
    pub(super) fn finish(self, table: &BlobTable) -> Result<(Vec<u32>, Vec<Target>, SortedParts), ArchiveError> {
        let Sorted {
            output,
            shaders,
            reflections,
            blob_ids,
            targets,
            records,
            values,
            artifacts,
            names,
            ids,
            mut ids_out,
            counts,
            ..
        } = self;
        let unadded = blob_ids.iter().enumerate().find(|&(s, &id)| id != u32::MAX && !table.is_added(s as u32));
        if let Some((_, &id)) = unadded {
            let target = targets[id as usize];
            return Err(ArchiveError::Input(format!("a permutation names a {target} blob that was never added")));
        }
        ids.write_sorted(&mut ids_out).map_err(|source| ArchiveError::Write { path: output, source })?;
        let parts = SortedParts { shaders, reflections, counts, records, ids: ids_out, values, artifacts, names };
        Ok((blob_ids, targets, parts))
    }
}

impl SortedParts {
    /// The parts, flushed, as the archive's writer copies them: the records, ids, values and
    /// artifacts (before the dictionary records), then the JSON tables (`tables`, padded to
    /// 8) and the names (after them).
    pub(super) fn spilled(
        &mut self,
        tables: &TablesOut<'_>,
    ) -> std::io::Result<(ManifestCounts, [SpillBuf<'_>; 4], [SpillBuf<'_>; 2])> {
        let mut json = serde_json::to_vec(tables).map_err(std::io::Error::other)?;
        let tables_len = json.len() as u64;
        pad8(&mut json, tables_len)?;
        let counts = ManifestCounts { tables_len, ..self.counts };
        let lens = [
            counts.permutations * RECORD_LEN as u64,
            counts.permutations * ID_LEN as u64,
            counts.values * VALUE_LEN as u64,
            counts.artifacts * super::ARTIFACT_LEN as u64,
            counts.names_len,
        ];
        let SortedParts { records, ids, values, artifacts, names, .. } = self;
        let parts = [records, ids, values, artifacts, names];
        if parts.iter().zip(lens).any(|(p, len)| p.len() != len) {
            return Err(std::io::Error::other("the manifest's parts differ from its counts"));
        }
        let [records, ids, values, artifacts, names] = parts;
        let front = [records.spill_buf()?, ids.spill_buf()?, values.spill_buf()?, artifacts.spill_buf()?];
        Ok((counts, front, [SpillBuf::Memory(json), names.spill_buf()?]))
    }
}
