use super::*;

fn compiled(tag: u8) -> Compiled {
    Compiled {
        artifacts: vec![(Target::Wgsl, vec![b'w', tag]), (Target::Spirv, vec![3, 2, 0x23, 7, tag])],
        reflection: Reflection {
            entry: "main".into(),
            stage: Stage::Fragment,
            bindings: vec![],
            vertex_inputs: vec![],
            color_outputs: vec![],
            workgroup_size: None,
        },
    }
}

/// An entry as Kiln wrote it before entries were compressed (version 2).
fn encode_v2(key: &Key, c: &Compiled) -> Vec<u8> {
    let hashes: Vec<blake3::Hash> = c.artifacts.iter().map(|(_, b)| blake3::hash(b)).collect();
    let frames = frames(c);
    let mut out = MAGIC.to_vec();
    out.extend_from_slice(entry_checksum(key, &frames, &hashes).as_bytes());
    body_pieces(key, c, &frames).iter().for_each(|p| out.extend_from_slice(p));
    out
}

/// A pack of `entries` as Kiln wrote it before entries were compressed.
fn old_pack(entries: &[Vec<u8>], keys: &[Key]) -> Vec<u8> {
    let mut rows = Vec::new();
    let mut offset = (PACK_HEADER + entries.len() * ROW) as u64;
    for (k, e) in keys.iter().zip(entries) {
        rows.extend_from_slice(&k.0);
        rows.extend_from_slice(&offset.to_le_bytes());
        rows.extend_from_slice(&(e.len() as u64).to_le_bytes());
        offset += e.len() as u64;
    }
    let mut out = PACK_MAGIC.to_vec();
    out.extend_from_slice(&(entries.len() as u64).to_le_bytes());
    out.extend_from_slice(blake3::hash(&rows).as_bytes());
    out.extend_from_slice(&rows);
    entries.iter().for_each(|e| out.extend_from_slice(e));
    out
}

fn key(text: &str) -> Key {
    Key::new(&blake3::hash(text.as_bytes()), "main", Stage::Fragment, "sm5", &Limits::desktop(), &[Target::Wgsl])
}

#[test]
fn key_depends_on_every_input() {
    let h = blake3::hash(b"tokens");
    let base = Key::new(&h, "main", Stage::Fragment, "sm5", &Limits::desktop(), &[Target::Wgsl]);
    let variants = [
        Key::new(&blake3::hash(b"other"), "main", Stage::Fragment, "sm5", &Limits::desktop(), &[Target::Wgsl]),
        Key::new(&h, "main2", Stage::Fragment, "sm5", &Limits::desktop(), &[Target::Wgsl]),
        Key::new(&h, "main", Stage::Vertex, "sm5", &Limits::desktop(), &[Target::Wgsl]),
        Key::new(&h, "main", Stage::Fragment, "es3_1", &Limits::desktop(), &[Target::Wgsl]),
        Key::new(&h, "main", Stage::Fragment, "sm5", &Limits::downlevel(), &[Target::Wgsl]),
        Key::new(&h, "main", Stage::Fragment, "sm5", &Limits::desktop(), &[Target::Wgsl, Target::Msl]),
    ];
    for v in variants {
        assert_ne!(v, base);
    }
    assert_eq!(base, Key::new(&h, "main", Stage::Fragment, "sm5", &Limits::desktop(), &[Target::Wgsl]));
}

/// A build's `Cache` leaves its own puts out of its index (it never looks them up), while
/// the index it read stays; the entries are in the packs for the next `Cache`.
#[test]
fn puts_stay_out_of_the_index_when_asked() {
    let dir = tempfile::tempdir().unwrap();
    let (old, new) = (key("old"), key("new"));
    Cache::open(dir.path()).unwrap().put(&old, &compiled(1)).unwrap();
    let cache = Cache::open(dir.path()).unwrap().without_indexing_puts();
    assert!(matches!(cache.get(&old), Lookup::Hit(..)));
    cache.put_pack(&[(new, &compiled(2))]).unwrap();
    assert!(matches!(cache.get(&new), Lookup::Miss));
    assert!(matches!(cache.get(&old), Lookup::Hit(..)));
    // Read again, the index has it.
    cache.release_index();
    assert!(matches!(cache.get(&new), Lookup::Hit(c, _) if c == compiled(2)));
    assert!(matches!(Cache::open(dir.path()).unwrap().get(&new), Lookup::Hit(c, _) if c == compiled(2)));
}

#[test]
fn put_then_get_round_trips() {
    let dir = tempfile::tempdir().unwrap();
    let cache = Cache::open(dir.path()).unwrap();
    let k = key("a");
    assert!(matches!(cache.get(&k), Lookup::Miss));
    cache.put(&k, &compiled(1)).unwrap();
    match cache.get(&k) {
        Lookup::Hit(c, _) => assert_eq!(c, compiled(1)),
        other => panic!("{other:?}"),
    }
    let pack = cache.pack_of(&k).unwrap();
    let pack_len = fs::metadata(&pack).unwrap().len();
    let stored = pack_len - (PACK_HEADER + ROW) as u64;
    assert_eq!(
        cache.stats(),
        Stats {
            entries: 1,
            packs: 1,
            records: 0,
            bytes: pack_len,
            raw: encode_v2(&k, &compiled(1)).len() as u64,
            stored,
            temporaries: 0,
            ..Stats::default()
        }
    );
    // Another `Cache` on the folder reads it from the pack.
    match Cache::open(dir.path()).unwrap().get(&k) {
        Lookup::Hit(c, _) => assert_eq!(c, compiled(1)),
        other => panic!("{other:?}"),
    }
}

#[test]
fn a_pack_holds_many_entries_in_one_file() {
    let dir = tempfile::tempdir().unwrap();
    let cache = Cache::open(dir.path()).unwrap();
    let keys: Vec<Key> = (0..50).map(|i| key(&i.to_string())).collect();
    let values: Vec<Compiled> = (0..50).map(|i| compiled(i as u8)).collect();
    let entries: Vec<(Key, &Compiled)> = keys.iter().copied().zip(&values).collect();
    cache.put_pack(&entries).unwrap();
    let files: Vec<_> =
        fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().path()).filter(|p| !p.ends_with("CACHEDIR.TAG")).collect();
    assert_eq!(files.len(), 1, "{files:?}");
    let fresh = Cache::open(dir.path()).unwrap();
    for (k, v) in keys.iter().zip(&values) {
        match fresh.get(k) {
            Lookup::Hit(c, _) => assert_eq!(&c, v),
            other => panic!("{other:?}"),
        }
    }
    assert_eq!(fresh.stats().entries, 50);
    assert!(matches!(fresh.get(&key("not stored")), Lookup::Miss));
    // An empty pack is not written.
    cache.put_pack(&[]).unwrap();
    assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 2, "the pack and CACHEDIR.TAG");
}

/// Flips one byte of the file at `path`, `from_end` bytes before its end.
fn flip(path: &Path, from_end: usize) {
    let mut bytes = fs::read(path).unwrap();
    let at = bytes.len() - from_end;
    bytes[at] ^= 1;
    fs::write(path, bytes).unwrap();
}

#[test]
fn corrupted_entry_is_reported_then_served_from_the_newer_copy() {
    let dir = tempfile::tempdir().unwrap();
    let cache = Cache::open(dir.path()).unwrap();
    let (a, b) = (key("a"), key("b"));
    let (ca, cb) = (compiled(1), compiled(2));
    cache.put_pack(&[(a, &ca), (b, &cb)]).unwrap();
    let pack = cache.pack_of(&b).unwrap();
    // The last bytes belong to b's artifacts' frame.
    flip(&pack, 3);
    let cache = Cache::open(dir.path()).unwrap();
    match cache.get(&b) {
        // The entry's check sum (version 6), or the frame's (older versions), tells it.
        Lookup::Corrupt(why) => assert!(
            [" (checksum mismatch); recompiling", " (cannot decompress it); recompiling"]
                .iter()
                .any(|end| why == format!("cache entry {b} in {} is corrupted{end}", pack.display())),
            "{why}"
        ),
        other => panic!("{other:?}"),
    }
    assert!(matches!(cache.get(&a), Lookup::Hit(c, _) if c == ca), "the other entry is intact");
    // What a build does next: store the recompiled entry. From then on it is a hit, in
    // this process and the next.
    cache.put(&b, &cb).unwrap();
    assert!(matches!(cache.get(&b), Lookup::Hit(c, _) if c == cb));
    assert!(matches!(Cache::open(dir.path()).unwrap().get(&b), Lookup::Hit(c, _) if c == cb));
}

#[test]
fn a_damaged_newest_copy_is_served_from_an_older_pack() {
    let dir = tempfile::tempdir().unwrap();
    let cache = Cache::open(dir.path()).unwrap();
    let (a, b) = (key("a"), key("b"));
    let (ca, cb) = (compiled(1), compiled(2));
    cache.put_pack(&[(a, &ca)]).unwrap();
    let old = cache.pack_of(&a).unwrap();
    let long_ago = std::time::SystemTime::UNIX_EPOCH + std::time::Duration::from_secs(1_000_000_000);
    fs::File::options().write(true).open(&old).unwrap().set_modified(long_ago).unwrap();
    // A second copy of a, in a newer pack (its own contents, so its own name).
    cache.put_pack(&[(a, &ca), (b, &cb)]).unwrap();
    let cache = Cache::open(dir.path()).unwrap();
    let new = cache.pack_of(&a).unwrap();
    assert_ne!(new, old, "the newest copy is in the second pack");
    // a's entry comes first in the new pack: damage its last byte, just before b's entry
    // (where b's index row says it starts).
    let bytes = fs::read(&new).unwrap();
    let row = bytes.windows(32).position(|w| w == b.0).unwrap();
    let b_at = u64::from_le_bytes(bytes[row + 32..row + 40].try_into().unwrap()) as usize;
    flip(&new, bytes.len() - b_at + 1);
    let cache = Cache::open(dir.path()).unwrap();
    assert!(matches!(cache.get(&a), Lookup::Hit(c, _) if c == ca), "served from the older pack");
    assert!(matches!(cache.get(&b), Lookup::Hit(c, _) if c == cb));
}

#[test]
fn truncated_or_damaged_packs_are_never_trusted() {
    let dir = tempfile::tempdir().unwrap();
    let cache = Cache::open(dir.path()).unwrap();
    let (a, b) = (key("a"), key("b"));
    let (ca, cb) = (compiled(1), compiled(2));
    cache.put_pack(&[(a, &ca), (b, &cb)]).unwrap();
    let pack = cache.pack_of(&a).unwrap();
    let bytes = fs::read(&pack).unwrap();

    // Truncated after a's entry: a is whole, b is corrupt.
    fs::write(&pack, &bytes[..bytes.len() - 10]).unwrap();
    let cache = Cache::open(dir.path()).unwrap();
    assert!(matches!(cache.get(&a), Lookup::Hit(c, _) if c == ca));
    match cache.get(&b) {
        Lookup::Corrupt(why) => assert!(why.contains("(entry is truncated)"), "{why}"),
        other => panic!("{other:?}"),
    }

    // A damaged index: the pack is removed with a warning, and its keys are misses.
    let mut damaged = bytes.clone();
    damaged[PACK_HEADER + 3] ^= 1;
    fs::write(&pack, &damaged).unwrap();
    let cache = Cache::open(dir.path()).unwrap();
    assert!(matches!(cache.get(&a), Lookup::Miss));
    assert_eq!(
        cache.warnings(),
        vec![format!(
            "warning: cache pack {} was damaged (index checksum mismatch) and is removed; its entries are recompiled",
            pack.display()
        )]
    );
    assert!(!pack.exists());

    // An index row moved to another key's entry: the entry's check sum covers its own key.
    let mut swapped = bytes.clone();
    let rows = PACK_HEADER..PACK_HEADER + 2 * ROW;
    let (first, second) =
        (swapped[rows.start..rows.start + 32].to_vec(), swapped[rows.start + ROW..rows.start + ROW + 32].to_vec());
    swapped[rows.start..rows.start + 32].copy_from_slice(&second);
    swapped[rows.start + ROW..rows.start + ROW + 32].copy_from_slice(&first);
    let rows_hash = blake3::hash(&swapped[rows.clone()]);
    swapped[16..48].copy_from_slice(rows_hash.as_bytes());
    fs::write(&pack, &swapped).unwrap();
    match Cache::open(dir.path()).unwrap().get(&a) {
        Lookup::Corrupt(why) => assert!(why.contains("(checksum mismatch)"), "{why}"),
        other => panic!("{other:?}"),
    }

    // A pack of an older Kiln.
    fs::write(&pack, b"KILNCP\0\x01 something else entirely, and longer than forty-eight bytes").unwrap();
    let cache = Cache::open(dir.path()).unwrap();
    assert!(matches!(cache.get(&a), Lookup::Miss));
    assert!(cache.warnings()[0].contains("(not a cache pack of this kiln)"), "{:?}", cache.warnings());
}

#[test]
fn interrupted_write_leaves_no_entry() {
    let dir = tempfile::tempdir().unwrap();
    let cache = Cache::open(dir.path()).unwrap();
    let k = key("a");
    // What a process killed in the middle of `put_pack` leaves: a partial temporary file
    // (here one of this running process, so it is not stale yet).
    let kept = dir.path().join(format!(".{}.kcp.{}.1.0.tmp", "ab".repeat(16), std::process::id()));
    let full = encode(&k, &compiled(1));
    fs::write(&kept, &full[..full.len() / 2]).unwrap();
    assert!(matches!(cache.get(&k), Lookup::Miss));
    assert_eq!(cache.stats(), Stats { temporaries: 1, ..Stats::default() });
    // gc leaves young temporaries alone (a concurrent writer may own them)...
    cache.gc(0);
    assert!(kept.exists());
    // ...and removes old ones.
    let old = SystemTime::now() - std::time::Duration::from_secs(3600);
    fs::File::options().append(true).open(&kept).unwrap().set_modified(old).unwrap();
    cache.gc(u64::MAX);
    assert!(!kept.exists());
}

#[test]
fn concurrent_puts_of_one_key_both_succeed() {
    let dir = tempfile::tempdir().unwrap();
    let k = key("a");
    std::thread::scope(|s| {
        for _ in 0..8 {
            s.spawn(|| {
                let cache = Cache::open(dir.path()).unwrap();
                for _ in 0..20 {
                    cache.put(&k, &compiled(1)).unwrap();
                    match cache.get(&k) {
                        Lookup::Hit(c, _) => assert_eq!(c, compiled(1)),
                        other => panic!("{other:?}"),
                    }
                    match Cache::open(dir.path()).unwrap().get(&k) {
                        Lookup::Hit(c, _) => assert_eq!(c, compiled(1)),
                        other => panic!("{other:?}"),
                    }
                }
            });
        }
    });
    let stats = Cache::open(dir.path()).unwrap().stats();
    // Identical packs have one name: each write replaced the last.
    assert_eq!((stats.entries, stats.packs, stats.temporaries), (1, 1, 0));
}

#[test]
fn gc_evicts_least_recently_used_packs_first() {
    let dir = tempfile::tempdir().unwrap();
    let cache = Cache::open(dir.path()).unwrap();
    let keys: Vec<Key> = ["a", "b", "c"].iter().map(|t| key(t)).collect();
    for (i, k) in keys.iter().enumerate() {
        cache.put(k, &compiled(i as u8)).unwrap();
        let t = SystemTime::now() - std::time::Duration::from_secs(100 - i as u64 * 10);
        fs::File::options().append(true).open(cache.pack_of(k).unwrap()).unwrap().set_modified(t).unwrap();
    }
    // Using "a" (from a fresh process's view) makes its pack the most recently used.
    let packs: Vec<PathBuf> = keys.iter().map(|k| cache.pack_of(k).unwrap()).collect();
    assert!(matches!(Cache::open(dir.path()).unwrap().get(&keys[0]), Lookup::Hit(..)));
    let one = fs::metadata(&packs[0]).unwrap().len();
    let report = cache.gc(one * 2);
    assert_eq!((report.removed, report.removed_packs, report.kept), (1, 1, 2));
    assert!(!packs[1].exists(), "b was the least recently used");
    assert!(packs[0].exists() && packs[2].exists());
    assert!(matches!(cache.get(&keys[1]), Lookup::Miss), "the index is read again after gc");
    assert_eq!(cache.clear().unwrap(), 2);
    assert_eq!(cache.stats(), Stats::default());
}

#[test]
fn records_round_trip_and_damage_is_a_miss() {
    let dir = tempfile::tempdir().unwrap();
    let cache = Cache::open(dir.path()).unwrap();
    let k = key("r");
    assert!(cache.get_records(&k).is_empty());
    let r = Record {
        key: key("a").to_hex(),
        token_hash: "t".into(),
        text_hash: "x".into(),
        files: vec![(PathBuf::from("/a/b.ush"), "h".into())],
        absent: vec![PathBuf::from("/a/c.ush")],
        warnings: vec!["warning: w".into()],
    };
    let records: Records = [("p1".to_string(), r)].into_iter().collect();
    cache.put_records(&k, &records).unwrap();
    assert_eq!(cache.get_records(&k), records);
    assert_eq!(cache.stats().records, 1);
    let path = cache.records_path(&k);
    let mut bytes = fs::read(&path).unwrap();
    let at = bytes.len() - 5;
    bytes[at] ^= 1;
    fs::write(&path, bytes).unwrap();
    assert!(cache.get_records(&k).is_empty());
    let report = cache.gc(0);
    assert_eq!((report.removed, report.removed_packs, report.removed_records), (0, 0, 1));
}

#[test]
fn sizes_parse_and_format() {
    assert_eq!(parse_size("10M"), Ok(10 << 20));
    assert_eq!(parse_size("1G"), Ok(1 << 30));
    assert_eq!(parse_size("512k"), Ok(512 << 10));
    assert_eq!(parse_size("2GiB"), Ok(2 << 30));
    assert_eq!(parse_size("1.5M"), Ok(3 << 19));
    assert_eq!(parse_size("100"), Ok(100));
    assert_eq!(parse_size("10Q"), Err("invalid size `10Q`: unknown unit `q` (use K, M, G or T)".to_string()));
    assert_eq!(parse_size("M"), Err("invalid size `M`: expected a number like 10M or 1G".to_string()));
    assert_eq!(format_size(100), "100 B");
    assert_eq!(format_size(3 << 19), "1.5 MiB");
}

#[test]
fn temporaries_of_dead_writers_are_removed_on_open() {
    let dir = tempfile::tempdir().unwrap();
    let mut child = std::process::Command::new("true").spawn().unwrap();
    let pid = child.id();
    child.wait().unwrap();
    let stale = dir.path().join(format!(".{}.kcp.{pid}.1.0.tmp", "cd".repeat(16)));
    fs::write(&stale, b"KILNCP").unwrap();
    Cache::open(dir.path()).unwrap();
    assert!(!stale.exists());
}

#[test]
fn only_kilns_own_files_are_cleared_or_evicted() {
    let dir = tempfile::tempdir().unwrap();
    // Files a user keeps beside the cache, with the names Kiln uses but not its contents.
    let foreign = [
        ("notes.stamp", &b"mine"[..]),
        ("0123456789abcdef0123456789abcdef.kcp", b"not a pack of kiln at all, just some user bytes here"),
        ("0123456789abcdef0123456789abcdef.stamp", b"my own stamp"),
        (&format!("{}.kpp", "e".repeat(64)), b"{}"),
        (".tmp-user", b"x"),
        ("old.kcp", b"KILNCP\0\x02"),
    ];
    assert!(Cache::open(dir.path()).is_ok());
    assert!(dir.path().join("CACHEDIR.TAG").is_file(), "a new cache is tagged");
    for (name, bytes) in &foreign {
        fs::write(dir.path().join(name), bytes).unwrap();
    }
    let cache = Cache::open(dir.path()).unwrap();
    // A folder holding other files is never tagged (it may be somebody's home).
    let home = tempfile::tempdir().unwrap();
    fs::write(home.path().join("thesis.txt"), "mine").unwrap();
    Cache::open(home.path()).unwrap();
    assert!(!home.path().join("CACHEDIR.TAG").exists());
    cache.put(&key("a"), &compiled(1)).unwrap();
    let k = key("r");
    cache.put_records(&k, &Records::new()).unwrap();
    assert_eq!(cache.stats().packs, 1);
    cache.gc(0);
    assert_eq!(cache.clear().unwrap(), 0);
    cache.put(&key("a"), &compiled(1)).unwrap();
    assert_eq!(cache.clear().unwrap(), 1);
    for (name, bytes) in &foreign {
        assert_eq!(fs::read(dir.path().join(name)).unwrap(), *bytes, "{name} is left alone");
    }
    assert!(cache.pack_of(&key("a")).is_none());
    assert!(!cache.records_path(&k).exists());
    // The damaged-looking foreign pack is reported, not removed.
    assert!(dir.path().join("0123456789abcdef0123456789abcdef.kcp").exists());
}

#[test]
fn a_fill_pack_streams_entries_and_leaves_its_unused_rows_a_hole() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (key("a"), key("b"));
    // Room for five entries, two written: three rows stay unused between index and entries.
    let pack = fill::FillPack::create(dir.path(), 5).unwrap();
    pack.push(&a, &encode(&a, &compiled(1))).unwrap();
    pack.push(&b, &encode(&b, &compiled(2))).unwrap();
    assert!(!pack.is_full());
    let path = pack.finish().unwrap().expect("a pack of two entries");
    let names: Vec<_> = fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().path()).collect();
    assert_eq!(names, vec![path], "the temporary file was renamed, nothing else is left");
    let cache = Cache::open(dir.path()).unwrap();
    assert!(matches!(cache.get(&a), Lookup::Hit(c, _) if c == compiled(1)));
    assert!(matches!(cache.get(&b), Lookup::Hit(c, _) if c == compiled(2)));
    assert_eq!(cache.stats().entries, 2);

    // Dropped unfinished (a failed fill) or finished empty: no file.
    let unfinished = fill::FillPack::create(dir.path(), 2).unwrap();
    unfinished.push(&a, &encode(&a, &compiled(1))).unwrap();
    drop(unfinished);
    assert_eq!(fill::FillPack::create(dir.path(), 2).unwrap().finish().unwrap(), None);
    assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1);
}

/// Entries of several chunks, from several threads: each is read back whole, the entries
/// start on a page.
#[test]
fn a_fill_pack_writes_its_entries_in_chunks_from_several_threads() {
    let dir = tempfile::tempdir().unwrap();
    let big = |i: u32| {
        let mut c = compiled(i as u8);
        // Of several pages and not a multiple of one: chunks end inside entries.
        c.artifacts[1].1 = (0..5_000 + i * 97).flat_map(|n| (n ^ i).to_le_bytes()).collect();
        c
    };
    let keys: Vec<Key> = (0..160).map(|i| key(&format!("big {i}"))).collect();
    let pack = fill::FillPack::create(dir.path(), keys.len() + 3).unwrap();
    std::thread::scope(|s| {
        for part in keys.chunks(40).enumerate() {
            let pack = &pack;
            s.spawn(move || {
                for (j, k) in part.1.iter().enumerate() {
                    let i = (part.0 * 40 + j) as u32;
                    pack.push(k, &encode(k, &big(i))).unwrap();
                }
            });
        }
    });
    let path = pack.finish().unwrap().expect("a pack");
    assert!(fs::metadata(&path).unwrap().len() > 3 << 20, "more than a few chunks");
    let cache = Cache::open(dir.path()).unwrap();
    for (i, k) in keys.iter().enumerate() {
        assert!(matches!(cache.get(k), Lookup::Hit(c, _) if c == big(i as u32)), "entry {i}");
    }
    let (_, rows) = open_pack(&path).unwrap().unwrap();
    let first = rows.iter().map(|r| r.1).min().unwrap();
    assert_eq!(first % 4096, 0, "entries start on a page");
}

#[test]
fn a_remote_value_is_checked_whole_and_bound_to_its_key() {
    let (a, b) = (key("a"), key("b"));
    let c = compiled(1);
    let hashes: Vec<blake3::Hash> = c.artifacts.iter().map(|(_, x)| blake3::hash(x)).collect();
    let value = remote_value(&a, &c, &hashes);
    assert_eq!(remote_entry(&a, &value).unwrap(), &encode(&a, &c)[..]);
    assert!(remote_entry(&b, &value).is_err(), "stored under another key");
    assert!(remote_entry(&a, &value[..value.len() - 1]).is_err(), "truncated");
    for at in [0, 8, REMOTE_HEADER + 50, value.len() - 1] {
        let mut bad = value.clone();
        bad[at] ^= 0x40;
        assert!(remote_entry(&a, &bad).is_err(), "byte {at} flipped");
    }
}

#[test]
fn a_bundle_cuts_its_sorted_keys_by_content_and_names_each_part_by_its_keys() {
    let keys: Vec<Key> = (0..3000).map(|i| key(&format!("k{i}"))).collect();
    let b = bundle::Bundle::new(&keys);
    let n = b.ids().len();
    assert!((4..40).contains(&n), "{n} parts of 3,000 keys (256 on average)");
    let parts: Vec<Key> = (0..n).flat_map(|i| b.part(i).to_vec()).collect();
    let mut sorted = keys.clone();
    sorted.sort();
    assert_eq!(parts, sorted, "every key once, in order");
    for i in 0..n {
        let part = b.part(i);
        let last = part[part.len() - 1];
        assert!(part.len() <= bundle::MAX_PART_KEYS);
        assert!(i == n - 1 || last.0[31] == 0 || part.len() == bundle::MAX_PART_KEYS, "cut after a key ending in 0");
        assert!(part[..part.len() - 1].iter().all(|k| k.0[31] != 0), "and only there");
    }
    // The order keys come in does not matter, nor do duplicates.
    let mut shuffled: Vec<Key> = keys.iter().rev().copied().collect();
    shuffled.push(keys[7]);
    assert_eq!(bundle::Bundle::new(&shuffled).ids(), b.ids());
    // One key less changes its own part only (or two, when it ended one).
    let fewer = bundle::Bundle::new(&keys[1..]);
    let changed = b.ids().iter().filter(|id| !fewer.ids().contains(id)).count();
    assert!((1..=2).contains(&changed), "{changed} parts changed");
    // A part never longer than its maximum: keys that never end one.
    let unending: Vec<Key> = (0..2100u32)
        .map(|i| {
            let mut k = [1u8; 32];
            k[..4].copy_from_slice(&i.to_be_bytes());
            Key(k)
        })
        .collect();
    let long = bundle::Bundle::new(&unending);
    assert_eq!((0..3).map(|i| long.part(i).len()).collect::<Vec<_>>(), vec![1024, 1024, 52]);
    assert!(bundle::Bundle::new(&[]).ids().is_empty());
}

/// A part of `n` keys (sorted) and the entry of each.
fn part_of(n: usize) -> (Vec<Key>, Vec<Vec<u8>>, Vec<u8>) {
    let mut keys: Vec<Key> = (0..n).map(|i| key(&format!("part {i}"))).collect();
    keys.sort();
    let entries: Vec<Vec<u8>> = keys.iter().enumerate().map(|(i, k)| encode(k, &compiled(i as u8))).collect();
    let size = bundle::part_overhead(n) + entries.iter().map(Vec::len).sum::<usize>();
    let value = bundle::encode_part(&keys, size, |k, out| {
        out.extend_from_slice(&entries[keys.iter().position(|x| x == k).unwrap()]);
        true
    });
    assert_eq!(value.as_ref().map(Vec::len), Some(size), "the size given is the part's");
    (keys, entries, value.unwrap())
}

fn read(value: &[u8], keys: &[Key]) -> (bool, Vec<(Key, Vec<u8>)>) {
    let mut got = Vec::new();
    let mut buffer = Vec::new();
    let whole = bundle::read_part(&mut &value[..], keys, &mut buffer, |k, e| got.push((*k, e.to_vec())));
    (whole, got)
}

#[test]
fn a_bundle_part_reads_back_every_checked_entry() {
    let (keys, entries, value) = part_of(5);
    let (whole, got) = read(&value, &keys);
    assert!(whole);
    assert_eq!(got, keys.iter().copied().zip(entries.iter().cloned()).collect::<Vec<_>>());
    // A writer lacking an entry writes no part.
    assert!(bundle::encode_part(&keys, 0, |k, out| {
        out.extend_from_slice(&entries[0]);
        *k != keys[2]
    })
    .is_none());
}

#[test]
fn a_damaged_truncated_or_foreign_part_gives_only_checked_entries_and_is_not_whole() {
    let (keys, entries, value) = part_of(4);
    let record = |i: usize| 8 + (0..i).map(|j| 40 + REMOTE_HEADER + entries[j].len()).sum::<usize>();
    // A byte of the third entry flipped: the others, not that one.
    let mut bad = value.clone();
    bad[record(2) + 40 + REMOTE_HEADER + 100] ^= 1;
    let (whole, got) = read(&bad, &keys);
    assert!(!whole);
    assert_eq!(got.iter().map(|g| g.0).collect::<Vec<_>>(), vec![keys[0], keys[1], keys[3]]);
    // Cut inside the third record, or just after the second: the first two.
    for cut in [record(2) + 60, record(2)] {
        let (whole, got) = read(&value[..cut], &keys);
        assert!(!whole, "cut at {cut}");
        assert_eq!(got.len(), 2, "cut at {cut}");
    }
    // A length that runs past the end: nothing more.
    let mut long = value.clone();
    long[record(3) + 32..record(3) + 40].copy_from_slice(&u64::MAX.to_le_bytes());
    assert_eq!(read(&long, &keys), (false, read(&value[..record(3)], &keys).1));
    // Another part's keys, or no part at all: nothing.
    assert_eq!(read(&value, &keys[1..]), (false, vec![]));
    assert_eq!(read(b"<html>not found</html>", &keys), (false, vec![]));
    // A record left out (the rest in order) still gives the others.
    let without = [&value[..record(1)], &value[record(2)..]].concat();
    let (whole, got) = read(&without, &keys);
    assert!(!whole);
    assert_eq!(got.len(), 3);
}

#[test]
fn keys_are_ordered_as_their_bytes() {
    // Keys that differ in each word, in the last byte only, and not at all.
    let mut keys: Vec<Key> = (0..64u8).map(|i| Key(*blake3::hash(&[i]).as_bytes())).collect();
    for i in 0..32 {
        let mut k = keys[0];
        k.0[i] ^= 0x80;
        keys.push(k);
        k.0[31] ^= 1;
        keys.push(k);
    }
    keys.push(keys[0]);
    for a in &keys {
        for b in &keys {
            assert_eq!(a.cmp(b), a.0.cmp(&b.0), "{a} against {b}");
            assert_eq!(a.partial_cmp(b), Some(a.0.cmp(&b.0)));
        }
    }
}

/// A pack written before entries were compressed (version 2 entries) is still read, and
/// `stats` counts its entries' raw size as stored.
#[test]
fn a_pack_of_the_old_uncompressed_format_is_still_read() {
    let dir = tempfile::tempdir().unwrap();
    let keys = [key("old a"), key("old b")];
    let entries: Vec<Vec<u8>> = keys.iter().zip(1..).map(|(k, i)| encode_v2(k, &compiled(i))).collect();
    fs::write(dir.path().join(format!("{}.{PACK_EXTENSION}", "ab".repeat(16))), old_pack(&entries, &keys)).unwrap();
    let cache = Cache::open(dir.path()).unwrap();
    for (k, i) in keys.iter().zip(1..) {
        assert!(matches!(cache.get(k), Lookup::Hit(c, _) if c == compiled(i)));
    }
    let s = cache.stats();
    let raw: u64 = entries.iter().map(|e| e.len() as u64).sum();
    assert_eq!((s.entries, s.raw, s.stored), (2, raw, raw));
    // A damaged old entry is reported, not trusted.
    flip(&dir.path().join(format!("{}.{PACK_EXTENSION}", "ab".repeat(16))), 3);
    assert!(matches!(Cache::open(dir.path()).unwrap().get(&keys[1]), Lookup::Corrupt(_)));
}

/// An old remote value (version 2: an uncompressed entry) is still read.
#[test]
fn an_old_remote_value_is_still_read() {
    let (k, c) = (key("old remote"), compiled(3));
    let entry = encode_v2(&k, &c);
    let mut value = REMOTE_MAGIC_V2.to_vec();
    value.extend_from_slice(&remote_checksum(&k, &entry));
    value.extend_from_slice(&entry);
    let cache = Cache::open(tempfile::tempdir().unwrap().path()).unwrap();
    assert_eq!(cache.decode(&k, remote_entry(&k, &value).unwrap()).unwrap(), c);
}

/// Entries like a build's: similar texts, one per target.
fn similar(i: u32) -> Compiled {
    let text = |lang: &str| {
        (0..120)
            .map(|l| format!("{lang} let v{l} = material_{} * {l}.0 + sample(tex{}, uv);\n", i % 7, (i + l) % 5))
            .collect::<String>()
            .into_bytes()
    };
    let mut c = compiled(i as u8);
    c.artifacts = vec![(Target::Wgsl, text("wgsl")), (Target::Msl, text("msl"))];
    c
}

/// A pack with enough of a kind trains its dictionary, kept in the cache folder: its entries
/// and later packs' are compressed with it; an entry whose dictionary is gone is reported and
/// recompiled; an entry leaves for the remote (a bundle part) without the dictionary.
#[test]
fn a_big_pack_trains_dictionaries_that_later_entries_use() {
    let dir = tempfile::tempdir().unwrap();
    let cache = Cache::open(dir.path()).unwrap();
    let keys: Vec<Key> = (0..300).map(|i| key(&format!("similar {i}"))).collect();
    let values: Vec<Compiled> = (0..300).map(similar).collect();
    let entries: Vec<(Key, &Compiled)> = keys.iter().copied().zip(&values).collect();
    // 100 entries are too few to train on; 200 more are enough.
    cache.put_pack(&entries[..100]).unwrap();
    assert_eq!(Cache::open(dir.path()).unwrap().stats().dictionaries, 0);
    cache.put_pack(&entries[100..]).unwrap();
    let dicts = || -> Vec<PathBuf> {
        let mut d: Vec<PathBuf> = fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.extension().is_some_and(|e| e == codec::DICT_EXTENSION))
            .collect();
        d.sort();
        d
    };
    assert_eq!(dicts().len(), 1, "one for the entries of wgsl and msl");
    let fresh = Cache::open(dir.path()).unwrap();
    for (k, v) in keys.iter().zip(&values) {
        assert!(matches!(fresh.get(k), Lookup::Hit(c, _) if c == *v));
    }
    let s = fresh.stats();
    assert_eq!((s.entries, s.dictionaries), (300, 1));
    assert!(s.raw > 5 * s.stored, "raw {} stored {}", s.raw, s.stored);
    // Out to the remote: no dictionary named.
    let mut out = Vec::new();
    assert!(fresh.append_local_entry(&keys[250], &mut out));
    assert_eq!(codec::uses_dictionary(&out), Ok(false));
    let no_dicts = |_: &[u8; 16]| -> Result<Arc<codec::Dict>, String> { Err("none".into()) };
    assert_eq!(codec::decode(&keys[250], &out, &no_dicts).unwrap().0, values[250]);
    // A dictionary gone: its entries are corrupt, recompiled; gc keeps dictionaries.
    assert_eq!(fresh.gc(u64::MAX).removed_packs, 0);
    assert_eq!(dicts().len(), 1);
    for d in dicts() {
        fs::remove_file(d).unwrap();
    }
    match Cache::open(dir.path()).unwrap().get(&keys[250]) {
        Lookup::Corrupt(why) => assert!(why.contains("dictionary"), "{why}"),
        other => panic!("{other:?}"),
    }
    // `clear` removes dictionaries with the rest.
    cache.put_pack(&entries[..100]).unwrap();
    assert_eq!(dicts().len(), 1, "written again from memory");
    cache.clear().unwrap();
    assert!(dicts().is_empty());
}

/// The index numbers its rows in as few bits as the packs read need, and widens them when
/// a pack added later needs more; keys that share their first bytes (the part a slot
/// keeps) are told apart by the whole key read from the pack.
#[test]
fn the_index_widens_its_row_numbers_and_tells_keys_with_one_prefix_apart() {
    let dir = tempfile::tempdir().unwrap();
    let cache = Cache::open(dir.path()).unwrap();
    let first = key("first");
    cache.put(&first, &compiled(0)).unwrap();
    assert!(matches!(cache.get(&first), Lookup::Hit(c, _) if c == compiled(0)));
    // One row read: then a pack of many, half of them sharing their first 16 bytes.
    let mut keys: Vec<Key> = (0..40).map(|i| key(&i.to_string())).collect();
    for (i, k) in keys.iter_mut().enumerate().take(20) {
        k.0[..16].copy_from_slice(&[7; 16]);
        k.0[31] = i as u8;
    }
    let values: Vec<Compiled> = (0..40).map(|i| compiled(i as u8 + 1)).collect();
    let entries: Vec<(Key, &Compiled)> = keys.iter().copied().zip(&values).collect();
    cache.put_pack(&entries).unwrap();
    let mut absent = keys[0];
    absent.0[31] = 200;
    for fresh in [false, true] {
        let cache = if fresh { Cache::open(dir.path()).unwrap() } else { cache.clone() };
        assert!(matches!(cache.get(&first), Lookup::Hit(c, _) if c == compiled(0)));
        for (k, v) in keys.iter().zip(&values) {
            assert!(matches!(cache.get(k), Lookup::Hit(c, _) if &c == v), "fresh {fresh}");
        }
        assert!(matches!(cache.get(&absent), Lookup::Miss));
    }
}
