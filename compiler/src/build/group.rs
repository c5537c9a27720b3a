//! Grouping: the plan's preprocessed permutations into distinct keys, each with its
//! permutations, and this process's share of them (`--shard`).

use super::plan::{level_targets, Plan};
use super::preprocess::Preprocessed;
use super::Error;
use crate::cache::Key;

impl Plan<'_> {
    /// The distinct keys in order of first appearance, each with its permutations, and the
    /// keys this process must produce; `same` is [`representatives`]'s.
    pub fn group<'p>(&self, pre: &'p Preprocessed, same: Vec<u32>) -> Result<Keys<'p>, Error> {
        let (of, count) = number_by_first_appearance(same, (0..self.len()).map(|i| pre.row_number(i)));
        let (starts, members) = members_by_key(of, count);
        let mut keys = Keys { pre, starts, members, share: Vec::new() };
        let read_back = super::preprocess::read_back;
        keys.share = match self.options.shard {
            None => vec![true; keys.len()],
            Some(shard) if self.hashed_shares() => keys
                .iter()
                .map(|key| key.map(|key| shard.hashes_to(&key)))
                .collect::<Result<_, _>>()
                .map_err(read_back)?,
            Some(shard) => {
                let costs = self.key_costs(pre, &keys)?;
                let all: Vec<Key> = keys.iter().collect::<Result<_, _>>().map_err(read_back)?;
                assign(&all, &costs, shard.count).into_iter().map(|s| s == shard.index).collect()
            }
        };
        Ok(keys)
    }

    /// Each key's cost for `--shard`: its longest member's text times its level's targets.
    fn key_costs(&self, pre: &Preprocessed, keys: &Keys<'_>) -> Result<Vec<u64>, Error> {
        // Each row's text length, read again (the rows are in their file).
        let mut text_lens = Vec::with_capacity(pre.row_count());
        pre.each_row(|r| text_lens.push(r.text_len)).map_err(super::preprocess::read_back)?;
        Ok((0..keys.len())
            .map(|k| {
                let members = keys.members(k);
                let (_, level) = self.shader_level(members[0] as usize);
                let len =
                    members.iter().filter_map(|&m| pre.row_number(m as usize)).map(|r| u64::from(text_lens[r])).max();
                len.unwrap_or(0).max(1) * level_targets(level, &self.options.targets).len().max(1) as u64
            })
            .collect())
    }
}

/// Each row's representative: the first row with its key. Rows are sorted by the first
/// four bytes of their key and their number (8 bytes a row, the keys read from the rows'
/// file), and the rows of a shared prefix (the rows of one key, and rare collisions) are
/// told apart by their whole keys, read again: the keys (32 bytes a row) are never held.
pub(super) fn representatives(pre: &Preprocessed) -> std::io::Result<Vec<u32>> {
    let rows = pre.row_count();
    let mut pairs: Vec<u64> = Vec::with_capacity(rows);
    let mut r = 0u64;
    pre.each_row(|row| {
        pairs.push(u64::from(u32::from_le_bytes(row.key.0[..4].try_into().expect("4 of 32 bytes"))) << 32 | r);
        r += 1;
    })?;
    pairs.sort_unstable();
    let mut same = vec![0u32; rows];
    let mut keys = pre.keys();
    let mut run = Vec::new();
    for shared in pairs.chunk_by(|a, b| a >> 32 == b >> 32) {
        if let [one] = shared {
            same[*one as u32 as usize] = *one as u32;
            continue;
        }
        // By key, then row: the first row of each key is its representative.
        run.clear();
        for &p in shared {
            run.push((keys.row(p as u32 as usize)?, p as u32));
        }
        run.sort_unstable();
        for (k, &(key, row)) in run.iter().enumerate() {
            same[row as usize] = match k {
                0 => row,
                _ if run[k - 1].0 != key => row,
                _ => same[run[k - 1].1 as usize],
            };
        }
    }
    Ok(same)
}

/// Each permutation's key number by first appearance, from `same` (each row's
/// representative row) and `rows` (each permutation's row, `None` where it has none), and
/// the number of keys. A representative's number is written over its own entry of `same`,
/// marked by the top bit (a representative points at itself until then), so that no second
/// table of a number a row is held beside it; past 2^31 rows, where the mark does not fit,
/// the numbers go in a table of their own.
fn number_by_first_appearance(mut same: Vec<u32>, rows: impl Iterator<Item = Option<usize>>) -> (Vec<u32>, usize) {
    const NUMBERED: u32 = 1 << 31;
    if same.len() >= NUMBERED as usize {
        return number_apart(&same, rows);
    }
    let mut count = 0u32;
    let of = rows
        .map(|r| {
            let Some(r) = r else { return u32::MAX };
            // A numbered representative holds its number; any other row its representative.
            let first = if same[r] & NUMBERED != 0 { r } else { same[r] as usize };
            if same[first] & NUMBERED == 0 {
                same[first] = count | NUMBERED;
                count += 1;
            }
            same[first] & !NUMBERED
        })
        .collect();
    (of, count as usize)
}

/// [`number_by_first_appearance`] with the numbers in a table of their own.
fn number_apart(same: &[u32], rows: impl Iterator<Item = Option<usize>>) -> (Vec<u32>, usize) {
    let mut number = vec![u32::MAX; same.len()];
    let mut count = 0u32;
    let of = rows
        .map(|r| {
            let Some(r) = r else { return u32::MAX };
            let first = same[r] as usize;
            if number[first] == u32::MAX {
                number[first] = count;
                count += 1;
            }
            number[first]
        })
        .collect();
    (of, count as usize)
}

/// `(starts, members)`: the members of each of `count` keys one after another, key `k`'s at
/// `members[starts[k]..starts[k + 1]]` (a counting sort of `of`, each permutation's key
/// number). Numbers of permutations, so below 2^32 ([`Plan::new`]).
fn members_by_key(mut of: Vec<u32>, count: usize) -> (Vec<u32>, Vec<u32>) {
    let mut starts = vec![0u32; count + 1];
    for &k in of.iter().filter(|&&k| k != u32::MAX) {
        starts[k as usize + 1] += 1;
    }
    for k in 0..count {
        starts[k + 1] += starts[k];
    }
    let placed = starts[count] as usize;
    // Each key's next free place: its start, moved one on per member (no second table).
    if placed == of.len() && placed < INVERTED as usize {
        // Every permutation has a key: its place among the members goes over its key number,
        // and the places, a permutation of them, are inverted in the same table.
        for k in of.iter_mut() {
            let next = &mut starts[*k as usize];
            *k = *next;
            *next += 1;
        }
        invert(&mut of);
        return (shifted_back(starts, count), of);
    }
    let mut members = vec![0u32; placed];
    for (i, &k) in of.iter().enumerate().filter(|(_, &k)| k != u32::MAX) {
        members[starts[k as usize] as usize] = i as u32;
        starts[k as usize] += 1;
    }
    drop(of);
    (shifted_back(starts, count), members)
}

/// Each start was moved to the next key's: the starts shifted back.
fn shifted_back(mut starts: Vec<u32>, count: usize) -> Vec<u32> {
    starts.copy_within(0..count, 1);
    starts[0] = 0;
    starts
}

/// The mark of a place already inverted by [`invert`].
const INVERTED: u32 = 1 << 31;

/// Inverts `places`, a permutation of `0..places.len()` (below 2^31), in place: afterwards
/// `places[p] = i` where `places[i]` was `p`. Each cycle is followed once, its places marked.
fn invert(places: &mut [u32]) {
    for start in 0..places.len() {
        if places[start] & INVERTED != 0 {
            continue;
        }
        let (mut prev, mut at) = (start as u32, places[start] as usize);
        while at != start {
            let next = places[at];
            places[at] = prev | INVERTED;
            prev = at as u32;
            at = next as usize;
        }
        places[start] = prev | INVERTED;
    }
    places.iter_mut().for_each(|p| *p &= !INVERTED);
}

/// The distinct keys of a build, by first appearance, with their permutations. A key is
/// its first member's, read from the rows' file where it is needed: not a copy of each,
/// which would grow with the set.
pub(super) struct Keys<'p> {
    pre: &'p Preprocessed,
    /// The members of key `k` are `members[starts[k]..starts[k + 1]]`.
    starts: Vec<u32>,
    /// Indices into the plan's kept permutations, ascending within each key.
    members: Vec<u32>,
    /// Whether each key is in this process's share (every key without `--shard`).
    pub share: Vec<bool>,
}

/// Keys read at a time ([`Keys::read`]).
pub(super) const KEYS_READ: usize = 256;

impl Keys<'_> {
    pub fn len(&self) -> usize {
        self.starts.len() - 1
    }

    /// Key `k`.
    pub fn key(&self, k: usize) -> std::io::Result<Key> {
        Ok(self.read(k..k + 1)?[0])
    }

    /// Keys `range`, in order.
    pub fn read(&self, range: std::ops::Range<usize>) -> std::io::Result<Vec<Key>> {
        let mut keys = self.pre.keys();
        range
            .map(|k| keys.of(self.members(k)[0] as usize)?.ok_or_else(|| std::io::Error::other("a key without a row")))
            .collect()
    }

    /// Every key in order, [`KEYS_READ`] at a time; the first error ends it.
    pub fn iter(&self) -> impl Iterator<Item = std::io::Result<Key>> + '_ {
        let len = self.len();
        (0..len).step_by(KEYS_READ).flat_map(move |start| match self.read(start..len.min(start + KEYS_READ)) {
            Ok(keys) => keys.into_iter().map(Ok).collect::<Vec<_>>(),
            Err(e) => vec![Err(e)],
        })
    }

    /// The permutations of key `k`, ascending.
    pub fn members(&self, k: usize) -> &[u32] {
        &self.members[self.starts[k] as usize..self.starts[k + 1] as usize]
    }
}

/// Greedy longest-processing-time assignment of keys to `shards` by estimated cost: keys
/// sorted by cost (descending), then by key bytes, each to the least loaded shard (the
/// lowest index among equals). Depends only on the keys and their costs, so every shard
/// process computes the same assignment.
///
/// More shards than keys leave the shards past the keys' count empty: the heap holds one
/// entry per key at most (the same assignment), whatever the count.
pub(super) fn assign(keys: &[Key], costs: &[u64], shards: usize) -> Vec<usize> {
    let mut order: Vec<usize> = (0..keys.len()).collect();
    order.sort_by(|&a, &b| costs[b].cmp(&costs[a]).then(keys[a].cmp(&keys[b])));
    let mut load: std::collections::BinaryHeap<std::cmp::Reverse<(u64, usize)>> =
        (0..shards.min(keys.len()).max(1)).map(|s| std::cmp::Reverse((0u64, s))).collect();
    let mut out = vec![0; keys.len()];
    for k in order {
        let std::cmp::Reverse((l, s)) = load.pop().expect("at least one shard");
        out[k] = s;
        load.push(std::cmp::Reverse((l + costs[k], s)));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn representatives_are_the_first_rows_of_their_keys() {
        // Keys 1 and 3 share their first four bytes with key 0, and key 1 is key 0's again.
        let key = |first: u8, rest: u8| {
            let mut k = Key([rest; 32]);
            k.0[..4].copy_from_slice(&[first, 9, 9, 9]);
            k
        };
        let keys = [key(0, 1), key(0, 1), key(5, 1), key(0, 2), key(5, 1), key(7, 7)];
        let pre = Preprocessed::of_keys(&keys);
        assert_eq!(representatives(&pre).unwrap(), vec![0, 0, 2, 3, 2, 5]);
    }

    #[test]
    fn numbering_in_place_matches_numbering_apart() {
        // Rows 0..6: rows 1, 3 and 5 share representative 1, row 4 is represented by 0.
        let same = vec![0, 1, 2, 1, 0, 1];
        let rows = [Some(3), None, Some(2), Some(0), Some(1), Some(4), Some(5), None];
        let (of, count) = number_by_first_appearance(same.clone(), rows.iter().copied());
        assert_eq!(count, 3);
        assert_eq!(of, vec![0, u32::MAX, 1, 2, 0, 2, 0, u32::MAX]);
        assert_eq!((of, count), number_apart(&same, rows.iter().copied()));
    }

    #[test]
    fn members_in_place_match_members_apart() {
        let of = vec![2, 0, 1, 0, 2, 2, 1];
        let (starts, members) = members_by_key(of.clone(), 3);
        assert_eq!(starts, vec![0, 2, 4, 7]);
        assert_eq!(members, vec![1, 3, 2, 6, 0, 4, 5]);
        // With a permutation without a key, the members go in a table of their own.
        let mut failed = of;
        failed.push(u32::MAX);
        assert_eq!(members_by_key(failed, 3), (starts, members));
        let mut places = vec![3, 0, 4, 1, 2, 5];
        invert(&mut places);
        assert_eq!(places, vec![1, 3, 4, 0, 2, 5]);
    }

    #[test]
    fn assignment_balances_cost_and_ignores_order() {
        let keys: Vec<Key> = (0..40u8).map(|i| Key([i; 32])).collect();
        let costs: Vec<u64> = (0..40u64).map(|i| 1 + (i * 37) % 101).collect();
        let a = assign(&keys, &costs, 4);
        let mut load = [0u64; 4];
        for (k, s) in a.iter().enumerate() {
            load[*s] += costs[k];
        }
        let (min, max) = (*load.iter().min().unwrap(), *load.iter().max().unwrap());
        assert!(max - min <= *costs.iter().max().unwrap(), "{load:?}");
        // The same keys in another order get the same shards.
        let mut rev_keys = keys.clone();
        let mut rev_costs = costs.clone();
        rev_keys.reverse();
        rev_costs.reverse();
        let mut b = assign(&rev_keys, &rev_costs, 4);
        b.reverse();
        assert_eq!(a, b);
    }
}
