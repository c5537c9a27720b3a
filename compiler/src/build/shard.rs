//! A shard's texts: the preprocessed text of each key's first freshly preprocessed
//! permutation, kept from preprocessing to the compile stage.
//!
//! A shard learns its share only once every key is known (shares are balanced by cost over
//! all keys), so it cannot compile while it preprocesses, as a plain build does. Rather than
//! preprocessing its keys' first permutations a second time, it keeps every key's text,
//! compressed (zstd's fastest level), in an unlinked temporary
//! file: memory holds a key's prefix and a table entry per key, and a killed build leaves nothing
//! behind. A text that cannot be kept (a full disk) is only preprocessed again.

use std::collections::HashMap;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::sync::Mutex;

use crate::cache::Key;

/// zstd level of the kept texts: fast, the file is read once.
const LEVEL: i32 = 1;

/// Where a text lies in the file: offset, stored length, text length.
#[derive(Clone, Copy)]
struct Place {
    offset: u64,
    stored: u32,
    len: u32,
}

pub(super) struct Texts {
    /// The unlinked file and its length.
    file: Mutex<(File, u64)>,
    /// Each key's text; `None` while it is being written.
    index: Mutex<HashMap<Key, Option<Place>>>,
}

impl Texts {
    /// `None` when no temporary file can be made (texts are then preprocessed again).
    pub fn new() -> Option<Texts> {
        let file = tempfile::tempfile().ok()?;
        Some(Texts { file: Mutex::new((file, 0)), index: Mutex::default() })
    }

    /// Keeps `text` as `key`'s, unless a text of `key` is kept already.
    pub fn keep(&self, key: &Key, text: &str) {
        {
            let mut index = self.index.lock().expect("no panics while locked");
            if index.contains_key(key) {
                return;
            }
            index.insert(*key, None);
        }
        let place = self.write(text);
        let mut index = self.index.lock().expect("no panics while locked");
        match place {
            Some(p) => index.insert(*key, Some(p)),
            None => index.remove(key),
        };
    }

    fn write(&self, text: &str) -> Option<Place> {
        let len = u32::try_from(text.len()).ok()?;
        let bytes = zstd::bulk::compress(text.as_bytes(), LEVEL).ok()?;
        let stored = u32::try_from(bytes.len()).ok()?;
        let mut file = self.file.lock().expect("no panics while locked");
        let offset = file.1;
        file.0.write_all_at(&bytes, offset).ok()?;
        file.1 += bytes.len() as u64;
        Some(Place { offset, stored, len })
    }

    /// The text kept for `key`, read back once (its entry is then dropped).
    pub fn take(&self, key: &Key) -> Option<String> {
        let place = self.index.lock().expect("no panics while locked").remove(key).flatten()?;
        let mut bytes = vec![0u8; place.stored as usize];
        self.file.lock().expect("no panics while locked").0.read_exact_at(&mut bytes, place.offset).ok()?;
        let text = zstd::bulk::decompress(&bytes, place.len as usize).ok()?;
        (text.len() == place.len as usize).then(|| String::from_utf8(text).ok()).flatten()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn texts_are_kept_once_per_key_and_read_back_once() {
        let texts = Texts::new().unwrap();
        let (a, b) = (Key([1; 32]), Key([2; 32]));
        let long = "fn main() { return; }\n".repeat(500);
        texts.keep(&a, &long);
        texts.keep(&a, "another text of the same key");
        texts.keep(&b, "");
        assert_eq!(texts.take(&a).as_deref(), Some(long.as_str()), "the first text of a key is kept");
        assert_eq!(texts.take(&a), None, "read back once");
        assert_eq!(texts.take(&b).as_deref(), Some(""));
        assert_eq!(texts.take(&Key([3; 32])), None);
        assert!(texts.file.lock().unwrap().1 < long.len() as u64 / 4, "compressed");
    }
}
