//! A set of 32-bit prefixes of uniform hashes, for the tables a build sizes by its
//! permutations and whose callers tolerate a prefix taken for another's (a false "already
//! there" only moves work elsewhere, never changes a byte).
//!
//! Open addressing with linear probing over a plain `u32` array sized at a quarter over
//! its bound (any length, not a power of two), so a slot is the prefix alone and the table
//! is at most a fifth empty. `hashbrown` rounds its buckets up to a power of two past the
//! bound and adds a control byte to each: up to two and a half times the room, grown in
//! steps with the set, at the build's peak.

/// The empty slot. A prefix equal to it is stored as [`ZERO_AS`] (two prefixes then agree:
/// tolerated, like any other two that agree).
const EMPTY: u32 = 0;
const ZERO_AS: u32 = 1;

/// The set ([module docs](self)).
#[derive(Debug, Default)]
pub struct PrefixSet {
    /// Empty until the first insert (a build that compiles nothing never touches them).
    slots: Vec<u32>,
    len: usize,
    /// The prefixes it holds without growing.
    bound: usize,
}

impl PrefixSet {
    /// A set that holds `bound` prefixes without growing, allocated at the first insert.
    pub fn with_bound(bound: usize) -> PrefixSet {
        PrefixSet { slots: Vec::new(), len: 0, bound }
    }

    /// How many prefixes it holds.
    #[cfg(test)]
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether it holds none.
    #[cfg(test)]
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Whether `prefix` is in the set.
    #[cfg(test)]
    pub fn contains(&self, prefix: u32) -> bool {
        self.find(stored(prefix)).is_ok()
    }

    /// Adds `prefix`: true if it was not there.
    pub fn insert(&mut self, prefix: u32) -> bool {
        if self.slots.is_empty() {
            self.slots = vec![EMPTY; slot_count(self.bound)];
        }
        if (self.len + 1) * 5 > self.slots.len() * 4 {
            self.grow();
        }
        match self.find(stored(prefix)) {
            Ok(_) => false,
            Err(at) => {
                self.slots[at] = stored(prefix);
                self.len += 1;
                true
            }
        }
    }

    /// Removes `prefix`: true if it was there. The slots after it in its probe run move back
    /// (no tombstones, so probes stay short however many are removed).
    pub fn remove(&mut self, prefix: u32) -> bool {
        let Ok(mut hole) = self.find(stored(prefix)) else { return false };
        self.slots[hole] = EMPTY;
        self.len -= 1;
        let n = self.slots.len();
        let mut at = hole;
        loop {
            at = (at + 1) % n;
            let p = self.slots[at];
            if p == EMPTY {
                return true;
            }
            // A prefix moves into the hole unless its home lies after the hole, up to `at`
            // (cyclically): it would no longer be found from its home.
            let home = home(p, n);
            let stays = if hole <= at { hole < home && home <= at } else { hole < home || home <= at };
            if !stays {
                self.slots[hole] = p;
                self.slots[at] = EMPTY;
                hole = at;
            }
        }
    }

    /// The slot holding `p` (`Ok`), or the empty slot where it would go (`Err`).
    fn find(&self, p: u32) -> Result<usize, usize> {
        let n = self.slots.len();
        if n == 0 {
            return Err(0);
        }
        let mut at = home(p, n);
        loop {
            match self.slots[at] {
                EMPTY => return Err(at),
                q if q == p => return Ok(at),
                _ => at = (at + 1) % n,
            }
        }
    }

    /// Twice the room, every prefix placed again (only a set made without its bound grows).
    fn grow(&mut self) {
        self.bound = (self.len + 1) * 2;
        let old = std::mem::replace(&mut self.slots, vec![EMPTY; slot_count(self.bound)]);
        self.len = 0;
        for p in old.into_iter().filter(|&p| p != EMPTY) {
            let at = self.find(p).expect_err("each prefix once");
            self.slots[at] = p;
            self.len += 1;
        }
    }
}

/// Slots for `bound` prefixes: a quarter over, and at least one always empty (probes end).
fn slot_count(bound: usize) -> usize {
    bound + bound / 4 + 2
}

fn stored(prefix: u32) -> u32 {
    if prefix == EMPTY {
        ZERO_AS
    } else {
        prefix
    }
}

/// A prefix's first slot: the prefix scaled onto the table (it is uniform already).
fn home(p: u32, n: usize) -> usize {
    ((u64::from(p) * n as u64) >> 32) as usize
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inserts_finds_and_removes_like_a_hash_set() {
        let mut set = PrefixSet::with_bound(1000);
        let mut model = std::collections::HashSet::new();
        // A small multiplier keeps prefixes clustered: long probe runs that wrap around.
        let mut x: u32 = 12345;
        for step in 0..20_000u32 {
            x = x.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            let p = if step % 3 == 0 { u32::MAX - (x % 64) } else { x % 4096 };
            let p = stored(p);
            if step % 2 == 0 && model.len() < 900 {
                assert_eq!(set.insert(p), model.insert(p), "insert {p}");
            } else {
                assert_eq!(set.remove(p), model.remove(&p), "remove {p}");
            }
            assert_eq!(set.len(), model.len());
        }
        for p in 0..4096 {
            assert_eq!(set.contains(p), model.contains(&stored(p)), "contains {p}");
        }
    }

    #[test]
    fn zero_is_a_prefix_like_one() {
        let mut set = PrefixSet::with_bound(4);
        assert_eq!(set.slots.capacity(), 0, "nothing allocated before the first insert");
        assert!(set.insert(0));
        assert!(set.contains(0));
        assert!(!set.insert(1), "0 and 1 are taken for each other");
        assert!(set.remove(1));
        assert!(set.is_empty());
    }

    #[test]
    fn a_set_without_a_bound_grows() {
        let mut set = PrefixSet::default();
        for p in 1..=10_000u32 {
            assert!(set.insert(p.wrapping_mul(2_654_435_761)));
        }
        assert_eq!(set.len(), 10_000);
        assert!((1..=10_000u32).all(|p| set.contains(p.wrapping_mul(2_654_435_761))));
        assert!(!set.contains(0x8000_0001));
    }
}
