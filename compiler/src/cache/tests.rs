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

#[test]
fn put_then_get_round_trips() {
    let dir = tempfile::tempdir().unwrap();
    let cache = Cache::open(dir.path()).unwrap();
    let k = key("a");
    assert!(matches!(cache.get(&k), Lookup::Miss));
    cache.put(&k, &compiled(1)).unwrap();
    match cache.get(&k) {
        Lookup::Hit(c) => assert_eq!(c, compiled(1)),
        other => panic!("{other:?}"),
    }
    assert_eq!(
        cache.stats(),
        Stats { entries: 1, records: 0, bytes: fs::metadata(cache.path(&k)).unwrap().len(), temporaries: 0 }
    );
}

#[test]
fn corrupted_entry_is_reported_removed_and_missed_next_time() {
    let dir = tempfile::tempdir().unwrap();
    let cache = Cache::open(dir.path()).unwrap();
    let k = key("a");
    cache.put(&k, &compiled(1)).unwrap();
    let path = cache.path(&k);
    let mut bytes = fs::read(&path).unwrap();
    let last = bytes.len() - 3;
    bytes[last] ^= 1;
    fs::write(&path, bytes).unwrap();
    match cache.get(&k) {
        Lookup::Corrupt(why) => assert!(why.contains("checksum mismatch"), "{why}"),
        other => panic!("{other:?}"),
    }
    assert!(matches!(cache.get(&k), Lookup::Miss));
}

#[test]
fn truncated_or_foreign_entries_are_corrupt() {
    let dir = tempfile::tempdir().unwrap();
    let cache = Cache::open(dir.path()).unwrap();
    let (a, b) = (key("a"), key("b"));
    cache.put(&a, &compiled(1)).unwrap();
    let bytes = fs::read(cache.path(&a)).unwrap();
    fs::write(cache.path(&a), &bytes[..bytes.len() / 2]).unwrap();
    assert!(matches!(cache.get(&a), Lookup::Corrupt(_)));
    // An entry copied under another key's name is not trusted either.
    fs::create_dir_all(cache.path(&b).parent().unwrap()).unwrap();
    fs::write(cache.path(&b), &bytes).unwrap();
    match cache.get(&b) {
        Lookup::Corrupt(why) => assert!(why.contains("another key"), "{why}"),
        other => panic!("{other:?}"),
    }
}

#[test]
fn interrupted_write_leaves_no_entry() {
    let dir = tempfile::tempdir().unwrap();
    let cache = Cache::open(dir.path()).unwrap();
    let k = key("a");
    // What a process killed in the middle of `put` leaves: a partial temporary file.
    let folder = cache.path(&k).parent().unwrap().to_path_buf();
    fs::create_dir_all(&folder).unwrap();
    let tmp = tempfile::Builder::new().prefix(".tmp-").tempfile_in(&folder).unwrap();
    let full = encode(&k, &compiled(1));
    fs::write(tmp.path(), &full[..full.len() / 2]).unwrap();
    let (_, kept) = tmp.keep().unwrap();
    assert!(matches!(cache.get(&k), Lookup::Miss));
    assert_eq!(cache.stats(), Stats { entries: 0, records: 0, bytes: 0, temporaries: 1 });
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
    let cache = Cache::open(dir.path()).unwrap();
    let k = key("a");
    std::thread::scope(|s| {
        for _ in 0..8 {
            s.spawn(|| {
                for _ in 0..20 {
                    cache.put(&k, &compiled(1)).unwrap();
                    match cache.get(&k) {
                        Lookup::Hit(c) => assert_eq!(c, compiled(1)),
                        other => panic!("{other:?}"),
                    }
                }
            });
        }
    });
    assert_eq!(cache.stats().entries, 1);
    assert_eq!(cache.stats().temporaries, 0);
}

#[test]
fn gc_evicts_least_recently_used_first() {
    let dir = tempfile::tempdir().unwrap();
    let cache = Cache::open(dir.path()).unwrap();
    let keys: Vec<Key> = ["a", "b", "c"].iter().map(|t| key(t)).collect();
    for (i, k) in keys.iter().enumerate() {
        cache.put(k, &compiled(i as u8)).unwrap();
        let t = SystemTime::now() - std::time::Duration::from_secs(100 - i as u64 * 10);
        fs::File::options().append(true).open(cache.path(k)).unwrap().set_modified(t).unwrap();
    }
    // Using "a" makes it the most recently used.
    assert!(matches!(cache.get(&keys[0]), Lookup::Hit(_)));
    let one = fs::metadata(cache.path(&keys[0])).unwrap().len();
    let report = cache.gc(one * 2);
    assert_eq!(report.removed, 1);
    assert_eq!(report.kept, 2);
    assert!(!cache.path(&keys[1]).exists(), "b was the least recently used");
    assert!(cache.path(&keys[0]).exists() && cache.path(&keys[2]).exists());
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
    assert_eq!((report.removed, report.removed_records), (0, 1));
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
