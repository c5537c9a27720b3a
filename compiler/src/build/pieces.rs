//! A shard's preprocessing records shared by pieces, while the shards that run together
//! preprocess.
//!
//! Shards that find no records of their configuration (the first ones to run) would each
//! preprocess the whole set. Instead the plan's order is cut into pieces of a fixed number
//! of permutations; each piece's records are stored in the remote cache under a key of
//! their own as soon as the piece is done, and a shard looks for a piece there before
//! preprocessing it. Each shard starts at another piece (spread so that two shards run
//! one after the other, `2k` and `2k + 1`, start half the set apart), takes half the pieces
//! forward from there, then the others backward from the piece before its first: two
//! shards running together each preprocess their own half and, where one is faster, meet
//! the other inside its half rather than trailing it (which would preprocess every piece
//! it reaches twice).
//! A piece that is missing, damaged (its checksum) or whose records do not hold is
//! preprocessed: pieces only skip work, they never decide a result.

use std::ops::Range;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

use super::plan::Shard;
use super::records::Records;
use crate::cache::Key;
use crate::compile::Limits;

/// Permutations per piece: a piece's records are a few hundred KiB, its lookup one round
/// trip.
const PIECE: usize = 4096;

pub(super) struct Pieces {
    size: usize,
    /// The pieces in the order this shard takes them.
    sequence: Vec<usize>,
    /// Where each piece's first permutation comes in that order.
    offset: Vec<usize>,
    /// How many permutations the plan holds.
    len: usize,
    /// The key of the configuration's whole set of records.
    records_key: Key,
    pieces: Vec<Piece>,
}

#[derive(Default)]
struct Piece {
    /// Its records found in the remote cache, until the piece is done.
    found: Mutex<Option<Arc<Records>>>,
    /// Whether it was found: a piece found is not stored again.
    was_found: AtomicBool,
    /// Its permutations done.
    done: AtomicUsize,
}

impl Pieces {
    /// The pieces of a plan of `len` permutations, for `shard`: of [`PIECE`] permutations,
    /// or `KILN_RECORD_PIECE`'s number (for tests: a small set in several pieces). Shards
    /// that share pieces must cut them alike: the size is in each piece's key.
    pub fn new(len: usize, shard: &Shard, records_key: Key) -> Pieces {
        let size = std::env::var("KILN_RECORD_PIECE").ok().and_then(|v| v.parse().ok()).filter(|&n: &usize| n > 0);
        Pieces::with_size(len, shard, records_key, size.unwrap_or(PIECE))
    }

    fn with_size(len: usize, shard: &Shard, records_key: Key, size: usize) -> Pieces {
        let count = len.div_ceil(size);
        let start = spread(shard.index, shard.count, count);
        let forward = count.div_ceil(2);
        let sequence: Vec<usize> = (0..forward)
            .map(|k| (start + k) % count)
            .chain((1..=count - forward).map(|k| (start + count - k) % count))
            .collect();
        let mut offset = vec![0; count];
        let mut at = 0;
        for &p in &sequence {
            offset[p] = at;
            at += ((p + 1) * size).min(len) - p * size;
        }
        let pieces = (0..count).map(|_| Piece::default()).collect();
        Pieces { size, sequence, offset, len, records_key, pieces }
    }

    /// The order in which this shard takes the permutations: piece by piece (see the
    /// module's documentation), each piece's in plan order.
    pub fn order(&self) -> impl Iterator<Item = usize> + Send + use<> {
        let (size, len) = (self.size, self.len);
        self.sequence.clone().into_iter().flat_map(move |p| p * size..((p + 1) * size).min(len))
    }

    /// Where permutation `i` comes in [`Pieces::order`].
    pub fn position(&self, i: usize) -> usize {
        self.offset.get(i / self.size).map_or(i, |o| o + i % self.size)
    }

    /// One past the position of the last permutation of `run` taken: the end of one of its
    /// parts in a piece (within a piece they are taken in order).
    pub fn run_end(&self, run: Range<usize>) -> usize {
        let size = self.size;
        let ends = (run.start / size + 1..run.end.div_ceil(size)).map(|p| p * size).chain([run.end]);
        ends.map(|end| self.position(end - 1) + 1).max().unwrap_or(0)
    }

    /// The piece that `i` starts, if it starts one.
    pub fn starts(&self, i: usize) -> Option<usize> {
        i.is_multiple_of(self.size).then_some(i / self.size)
    }

    /// The key of piece `n`'s records: the whole set's key, the cut and the piece.
    pub fn key(&self, n: usize) -> Key {
        let inputs = format!("kiln records piece v1\n{}\n{}\n{}\n{n}", self.records_key.to_hex(), self.size, self.len);
        Key::new(&blake3::hash(inputs.as_bytes()), "", crate::Stage::Compute, "", &Limits::desktop(), &[])
    }

    /// Keeps piece `n`'s records, found in the remote cache.
    pub fn found(&self, n: usize, records: Records) {
        *self.pieces[n].found.lock().expect("no panics while locked") = Some(Arc::new(records));
        self.pieces[n].was_found.store(true, Ordering::Relaxed);
    }

    /// The records found for permutation `i`'s piece.
    pub fn records(&self, i: usize) -> Option<Arc<Records>> {
        self.pieces.get(i / self.size)?.found.lock().expect("no panics while locked").clone()
    }

    /// Marks permutation `i` done; when it was the last of its piece, the piece's records
    /// found are let go, and the piece's number and permutations are given if it is to be
    /// stored (it was not found).
    pub fn done(&self, i: usize) -> Option<(usize, Range<usize>)> {
        let n = i / self.size;
        let piece = self.pieces.get(n)?;
        let range = n * self.size..((n + 1) * self.size).min(self.len);
        if piece.done.fetch_add(1, Ordering::AcqRel) + 1 != range.len() {
            return None;
        }
        *piece.found.lock().expect("no panics while locked") = None;
        (!piece.was_found.load(Ordering::Relaxed)).then_some((n, range))
    }
}

/// The first of `pieces` that shard `index` of `count` takes: its index's bits reversed as
/// a fraction of the set, so that shards `2k` and `2k + 1` (run together) start half the
/// set apart, and more shards run together spread evenly.
fn spread(index: usize, count: usize, pieces: usize) -> usize {
    let bits = count.max(2).next_power_of_two().trailing_zeros();
    let reversed = (index as u64).reverse_bits() >> (64 - bits);
    ((reversed * pieces as u64) >> bits) as usize
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pairs_start_half_the_set_apart() {
        assert_eq!((0..8).map(|i| spread(i, 8, 80)).collect::<Vec<_>>(), [0, 40, 20, 60, 10, 50, 30, 70]);
        assert_eq!(spread(1, 2, 7), 3);
        assert_eq!(spread(0, 1, 7), 0);
        assert_eq!(spread(2, 3, 8), 2);
    }

    #[test]
    fn every_permutation_once_and_each_piece_stored_once() {
        let shard = Shard { index: 1, count: 2 };
        let p = Pieces::with_size(10, &shard, Key([1; 32]), 4);
        let order: Vec<usize> = p.order().collect();
        assert_eq!(order, [4, 5, 6, 7, 8, 9, 0, 1, 2, 3]);
        assert!(order.iter().enumerate().all(|(n, &i)| p.position(i) == n));
        assert_eq!(p.run_end(2..6), 10, "the part in piece 0 is taken last");
        assert_eq!(p.run_end(4..6), 2);
        let other = Pieces::with_size(10, &Shard { index: 0, count: 2 }, Key([1; 32]), 2);
        assert_eq!(other.order().collect::<Vec<_>>(), [0, 1, 2, 3, 4, 5, 8, 9, 6, 7], "half forward, half back");
        assert_eq!((other.run_end(5..10), other.run_end(8..10)), (10, 8));
        assert_eq!(p.starts(8), Some(2));
        assert_eq!(p.starts(9), None);
        p.found(0, Records::default());
        assert!(p.records(3).is_some());
        let stored: Vec<_> = order.iter().filter_map(|&i| p.done(i)).collect();
        assert_eq!(stored, [(1, 4..8), (2, 8..10)], "piece 0 was found");
        assert!(p.records(3).is_none(), "let go once done");
        assert_ne!(p.key(0), p.key(1));
    }
}
