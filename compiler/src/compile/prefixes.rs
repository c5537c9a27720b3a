//! A set of uniform hashes that may answer "already there" for one that is not (a Bloom
//! filter), for the tables a build sizes by its permutations and whose callers tolerate it:
//! a false "already there" only moves work elsewhere, never changes a byte.
//!
//! Twelve bits an item at its bound, eight of them set for each: about three in a thousand
//! answers are false there. A table of the items (even of 32-bit prefixes, as this set
//! was) held about five bytes an item, and a build holds two such sets while it
//! preprocesses, where it peaks.

/// Bits an item at the set's bound.
const BITS_PER_ITEM: usize = 12;

/// Bits set for each item.
const PROBES: u64 = 8;

/// The set ([module docs](self)).
#[derive(Debug, Default)]
pub struct Seen {
    /// Empty until the first insert (a build that compiles nothing never touches them).
    words: Vec<u64>,
    /// The items it was sized for.
    bound: usize,
}

impl Seen {
    /// A set sized for `bound` items, allocated at the first insert (more items only make
    /// false answers more frequent).
    pub fn with_bound(bound: usize) -> Seen {
        Seen { words: Vec::new(), bound }
    }

    /// Adds the item whose uniform hash is `hash`: true if it was not there (and, rarely,
    /// false when it was not: [module docs](self)).
    pub fn insert(&mut self, hash: u128) -> bool {
        if self.words.is_empty() {
            self.words = vec![0; (self.bound.max(64) * BITS_PER_ITEM).div_ceil(64)];
        }
        let mut new = false;
        for bit in probes(hash, self.words.len()) {
            let (word, mask) = (&mut self.words[bit / 64], 1u64 << (bit % 64));
            new |= *word & mask == 0;
            *word |= mask;
        }
        new
    }

    /// Whether the item whose hash is `hash` is there (or taken for one that is).
    #[cfg(test)]
    fn contains(&self, hash: u128) -> bool {
        !self.words.is_empty() && probes(hash, self.words.len()).all(|bit| self.words[bit / 64] & 1 << (bit % 64) != 0)
    }
}

/// The bits of `hash` in a set of `words` words: double hashing, the probes made from the
/// two halves of the hash (the second odd).
fn probes(hash: u128, words: usize) -> impl Iterator<Item = usize> {
    let bits = words as u64 * 64;
    let (a, b) = (hash as u64, (hash >> 64) as u64 | 1);
    (0..PROBES).map(move |i| ((u128::from(a.wrapping_add(b.wrapping_mul(i))) * u128::from(bits)) >> 64) as usize)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A uniform hash of `n` (splitmix64 of each half).
    fn hash(n: u64) -> u128 {
        let mix = |mut z: u64| {
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^ (z >> 31)
        };
        u128::from(mix(n.wrapping_mul(2).wrapping_add(0x9E37_79B9_7F4A_7C15)))
            | u128::from(mix(n.wrapping_mul(2).wrapping_add(1))) << 64
    }

    #[test]
    fn an_item_is_new_once_and_few_are_taken_for_others() {
        let mut set = Seen::with_bound(10_000);
        assert!(set.words.is_empty(), "nothing allocated before the first insert");
        let fresh = (0..10_000u64).filter(|&n| set.insert(hash(n))).count();
        // Each item inserted is there after; at most a few were taken for earlier ones.
        assert!((0..10_000u64).all(|n| !set.insert(hash(n))));
        assert!(fresh >= 9_950, "{fresh} of 10000 new");
        // Items never inserted: about three in a thousand answer "there" at the bound.
        let false_there = (10_000..110_000u64).filter(|&n| set.contains(hash(n))).count();
        assert!(false_there < 1_000, "{false_there} of 100000 taken for others");
    }

    #[test]
    fn a_set_without_a_bound_still_answers() {
        let mut set = Seen::default();
        assert!(set.insert(hash(1)));
        assert!(!set.insert(hash(1)));
        assert!(set.insert(hash(2)));
    }
}
