//! Unit tests of the archive format: round trips, determinism, damage of every kind.

use super::format::{
    header_checksum, ChunkHasher, Entry, Layout, ManifestCounts, Record, Sections, ENTRY_LEN, HEADER_LEN, RECORD_LEN,
};
use super::*;

fn shader() -> ShaderRecord {
    ShaderRecord {
        name: "Lit".into(),
        level: "sm5".into(),
        entry: "main_ps".into(),
        stage: Stage::Fragment,
        dimensions: vec![
            DimensionRecord { name: "FULLY_ROUGH".into(), labels: vec![] },
            DimensionRecord { name: "MODE".into(), labels: vec!["OPAQUE".into(), "MASKED".into()] },
        ],
    }
}

fn reflection() -> Reflection {
    Reflection {
        entry: "main_ps".into(),
        stage: Stage::Fragment,
        bindings: vec![Binding {
            group: 0,
            binding: 0,
            name: Some("u".into()),
            kind: BindingKind::UniformBuffer { min_size: 16 },
        }],
        vertex_inputs: vec![],
        color_outputs: vec![],
        workgroup_size: None,
    }
}

fn sample() -> Vec<u8> {
    let mut w = ArchiveWriter::new();
    w.set_naga_version("30.0.1");
    let s = w.add_shader(shader());
    let r = w.add_reflection(&reflection());
    for rough in 0..2 {
        for mode in 0..2 {
            let wgsl = w.add_blob(format!("// wgsl {rough}").as_bytes());
            let spv = w.add_blob(&[3, 2, 0x23, 7, rough as u8]);
            let label = ["OPAQUE", "MASKED"][mode];
            w.add_permutation(PermutationRecord {
                name: format!("Lit@sm5{{FULLY_ROUGH={rough},MODE={label}}}"),
                shader: s,
                values: vec![rough, mode as i64],
                reflection: r,
                artifacts: vec![(Target::Wgsl, wgsl), (Target::Spirv, spv)],
            });
        }
    }
    w.to_bytes().unwrap()
}

/// A WGSL-like text that differs a little with `i`, as permutations of one shader do.
fn artifact_text(i: usize, target: &str) -> String {
    let mut s = format!("// {target} permutation {i}\n");
    for f in 0..40 {
        s.push_str(&format!(
            "fn light_{f}(n: vec3<f32>, l: vec3<f32>) -> f32 {{\n    let k = {}.0 * dot(n, l);\n    return max(k, 0.0);\n}}\n",
            (f * 7 + i) % 13
        ));
    }
    s
}

/// A permutation's name and its artifacts.
type Artifacts = (String, Vec<(Target, Vec<u8>)>);

/// 96 permutations whose artifacts are big enough to train dictionaries.
fn big_permutations() -> Vec<Artifacts> {
    (0..96)
        .map(|i| {
            let name = format!("Lit@sm5{{FULLY_ROUGH={},MODE={}}}", i, ["OPAQUE", "MASKED"][i % 2]);
            let arts = vec![
                (Target::Wgsl, artifact_text(i, "wgsl").into_bytes()),
                (Target::Msl, artifact_text(i / 2, "msl").into_bytes()),
            ];
            (name, arts)
        })
        .collect()
}

/// Writes `perms` through a streaming writer, adding blobs and permutations in the order of
/// `order` (indices into `perms`), from `threads` threads.
fn stream(path: &std::path::Path, perms: &[Artifacts], order: &[usize], threads: usize) -> ArchiveSummary {
    stream_with(StreamingWriter::new(path).unwrap(), perms, order, threads)
}

/// [`stream`] through the writer `w`.
fn stream_with(w: StreamingWriter, perms: &[Artifacts], order: &[usize], threads: usize) -> ArchiveSummary {
    w.set_naga_version("30.0.1");
    let sh = shader();
    let refl = reflection();
    let chunks: Vec<&[usize]> = order.chunks(order.len().div_ceil(threads)).collect();
    std::thread::scope(|scope| {
        for chunk in chunks {
            let (w, sh, refl) = (&w, &sh, &refl);
            scope.spawn(move || {
                for &i in chunk {
                    let (name, arts) = &perms[i];
                    let mut artifacts = Vec::new();
                    for (t, bytes) in arts {
                        artifacts.push((*t, w.add_blob(bytes).unwrap()));
                    }
                    let values = vec![i as i64, (i % 2) as i64];
                    let p = NewPermutation { name: name.clone(), shader: sh, values, reflection: refl, artifacts };
                    w.add_permutation(p).unwrap();
                }
            });
        }
    });
    w.finish().unwrap()
}

#[test]
fn the_archive_is_the_same_whether_blobs_wait_in_memory_or_in_a_file() {
    let dir = tempfile::tempdir().unwrap();
    let perms = big_permutations();
    let order: Vec<usize> = (0..perms.len()).rev().collect();
    // All in a file, all in memory, and moved to a file part way (from three threads).
    let mut archives = Vec::new();
    for (i, limit) in [0, usize::MAX, 64 << 10].into_iter().enumerate() {
        let path = dir.path().join(format!("{i}.kpak"));
        stream_with(StreamingWriter::with_spool_memory(&path, limit).unwrap(), &perms, &order, 3);
        archives.push(std::fs::read(&path).unwrap());
    }
    assert!(archives.iter().all(|a| *a == archives[0]), "the spool's place changes no byte");
    let leftovers: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(leftovers.len(), 3, "no spool left behind: {leftovers:?}");
}

/// The table that finds blobs only finds them: made at a bound up front (too small, tight
/// or loose, and part way through the blobs), it changes no byte of the archive.
#[test]
fn the_archive_is_the_same_whatever_blobs_the_writer_expects() {
    let dir = tempfile::tempdir().unwrap();
    let perms = big_permutations();
    let order: Vec<usize> = (0..perms.len()).collect();
    let blobs: usize = perms.iter().map(|(_, a)| a.len()).sum();
    let mut archives = Vec::new();
    for (i, expected) in [None, Some(0), Some(3), Some(blobs), Some(blobs * 10)].into_iter().enumerate() {
        let path = dir.path().join(format!("{i}.kpak"));
        let w = StreamingWriter::new(&path).unwrap();
        // Some blobs in before the bound, as a build's preprocessing adds them.
        let (name, arts) = &perms[0];
        let first: Vec<_> = arts.iter().map(|(t, b)| (*t, w.add_blob(b).unwrap())).collect();
        if let Some(n) = expected {
            w.expect_blobs(n).unwrap();
        }
        let (sh, refl) = (shader(), reflection());
        let p =
            NewPermutation { name: name.clone(), shader: &sh, values: vec![0, 0], reflection: &refl, artifacts: first };
        w.add_permutation(p).unwrap();
        for &i in &order[1..] {
            let (name, arts) = &perms[i];
            let artifacts = arts.iter().map(|(t, b)| (*t, w.add_blob(b).unwrap())).collect();
            let values = vec![i as i64, (i % 2) as i64];
            w.add_permutation(NewPermutation { name: name.clone(), shader: &sh, values, reflection: &refl, artifacts })
                .unwrap();
        }
        w.set_naga_version("30.0.1");
        w.finish().unwrap();
        archives.push(std::fs::read(&path).unwrap());
    }
    assert!(archives.iter().all(|a| *a == archives[0]), "the table's size changes no byte");
}

#[test]
fn round_trip_dedups_blobs_and_finds_by_name() {
    let a = Archive::from_vec(sample()).unwrap();
    assert_eq!(a.permutations().unwrap().count(), 4);
    assert_eq!(a.blob_count(), 4, "two wgsl blobs and two spir-v blobs, each shared by two permutations");
    let p = a.get("Lit@sm5{FULLY_ROUGH=1,MODE=MASKED}").unwrap().unwrap();
    assert_eq!(&p.artifact(Target::Wgsl).unwrap().unwrap()[..], b"// wgsl 1");
    assert_eq!(&p.artifact(Target::Spirv).unwrap().unwrap()[..], &[3, 2, 0x23, 7, 1]);
    assert!(p.artifact(Target::Msl).unwrap().is_none());
    assert_eq!(p.reflection().bindings.len(), 1);
    assert_eq!(a.naga_version(), "30.0.1");
    let names: Vec<&str> = a.permutations().unwrap().map(|p| p.name()).collect();
    let mut sorted = names.clone();
    sorted.sort();
    assert_eq!(names, sorted, "permutations are stored sorted by name");
}

#[test]
fn every_permutation_is_found_by_name_and_by_id() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("big.kpak");
    let perms = big_permutations();
    let order: Vec<usize> = (0..perms.len()).rev().collect();
    stream(&path, &perms, &order, 2);
    let a = Archive::open(&path).unwrap();
    assert_eq!(a.permutation_count(), perms.len());
    for (i, (name, arts)) in perms.iter().enumerate() {
        let p = a.get(name).unwrap().unwrap_or_else(|| panic!("{name} not found"));
        assert_eq!(p.name(), name);
        assert_eq!(p.values(), &[i as i64, (i % 2) as i64]);
        let id = permutation_id("Lit", "sm5", &[i as i64, (i % 2) as i64]);
        assert_eq!(a.get_by_id(id).unwrap().unwrap().name(), name);
        let record = p.record();
        assert_eq!(record.artifacts.len(), arts.len());
        for (t, bytes) in arts {
            assert_eq!(&p.artifact(*t).unwrap().unwrap()[..], &bytes[..], "{name} {t}");
        }
    }
    assert!(a.get("Lit@sm5{FULLY_ROUGH=96,MODE=OPAQUE}").unwrap().is_none());
    assert!(a.get("").unwrap().is_none());
    assert!(a.get("~").unwrap().is_none());
    assert!(a.get_by_id(permutation_id("Lit", "sm5", &[96, 0])).unwrap().is_none());
}

/// The writer keeps names less their shader's `name@level` and values as i32 while they fit:
/// names that do not begin with it, prefixes of which one begins another (`A@es3` and
/// `A@es3_1`) and a value past i32 still give the whole names, sorted, and the values.
#[test]
fn names_without_their_prefix_and_values_past_i32_round_trip() {
    let mut w = ArchiveWriter::new();
    let one_dim = |level: &str| ShaderRecord {
        name: "A".into(),
        level: level.into(),
        entry: "main_ps".into(),
        stage: Stage::Fragment,
        dimensions: vec![DimensionRecord { name: "X".into(), labels: vec![] }],
    };
    let (es3, es3_1) = (w.add_shader(one_dim("es3")), w.add_shader(one_dim("es3_1")));
    let r = w.add_reflection(&reflection());
    let wide = 1i64 << 40;
    let perms = [
        ("A@es3{X=1}", es3, 1),
        ("A@es3_1{X=0}", es3_1, 0),
        ("A@es3_1{X=-7}", es3_1, -7),
        ("A@es3{X=1099511627776}", es3, wide),
        ("custom name", es3, 2),
        ("A@es", es3_1, 3),
    ];
    for (i, (name, shader, value)) in perms.iter().enumerate() {
        let blob = w.add_blob(format!("blob {i}").as_bytes());
        w.add_permutation(PermutationRecord {
            name: name.to_string(),
            shader: *shader,
            values: vec![*value],
            reflection: r,
            artifacts: vec![(Target::Wgsl, blob)],
        });
    }
    let a = Archive::from_vec(w.to_bytes().unwrap()).unwrap();
    let names: Vec<&str> = a.permutations().unwrap().map(|p| p.name()).collect();
    let mut sorted: Vec<&str> = perms.iter().map(|p| p.0).collect();
    sorted.sort();
    assert_eq!(names, sorted);
    for (i, (name, shader, value)) in perms.iter().enumerate() {
        let p = a.get(name).unwrap().unwrap_or_else(|| panic!("{name} not found"));
        assert_eq!(p.values(), &[*value]);
        assert_eq!(&p.artifact(Target::Wgsl).unwrap().unwrap()[..], format!("blob {i}").as_bytes());
        let level = if *shader == es3 { "es3" } else { "es3_1" };
        assert_eq!(a.get_by_id(permutation_id("A", level, &[*value])).unwrap().unwrap().name(), *name);
    }
}

/// Canonical names are made again from the values rather than kept: in byte order whatever
/// the number of digits, signs and labels (values past a dimension's labels are numbers),
/// beside names of the same shader that only look canonical (kept as they are).
#[test]
fn derived_names_sort_and_round_trip_beside_kept_ones() {
    let mut w = ArchiveWriter::new();
    let s = w.add_shader(shader());
    let r = w.add_reflection(&reflection());
    let mut names = Vec::new();
    for rough in [0i64, 1, 2, 9, 10, 11, 100, -1, -10, 1 << 40] {
        for mode in [0i64, 1, 2] {
            let label = ["OPAQUE", "MASKED", "2"][mode as usize];
            names.push((format!("Lit@sm5{{FULLY_ROUGH={rough},MODE={label}}}"), vec![rough, mode]));
        }
    }
    names.push(("Lit@sm5{FULLY_ROUGH=01,MODE=OPAQUE}".into(), vec![1, 0]));
    names.push(("Lit@sm5{FULLY_ROUGH=3}".into(), vec![3, 0]));
    names.push(("Lit@sm5".into(), vec![4, 1]));
    for (i, (name, values)) in names.iter().enumerate() {
        let blob = w.add_blob(format!("blob {i}").as_bytes());
        w.add_permutation(PermutationRecord {
            name: name.clone(),
            shader: s,
            values: values.clone(),
            reflection: r,
            artifacts: vec![(Target::Wgsl, blob)],
        });
    }
    let a = Archive::from_vec(w.to_bytes().unwrap()).unwrap();
    let read: Vec<&str> = a.permutations().unwrap().map(|p| p.name()).collect();
    let mut sorted: Vec<&str> = names.iter().map(|n| n.0.as_str()).collect();
    sorted.sort();
    assert_eq!(read, sorted);
    for (i, (name, values)) in names.iter().enumerate() {
        let p = a.get(name).unwrap().unwrap_or_else(|| panic!("{name} not found"));
        assert_eq!(p.values(), &values[..]);
        assert_eq!(&p.artifact(Target::Wgsl).unwrap().unwrap()[..], format!("blob {i}").as_bytes());
    }
}

#[test]
fn canonical_name_accepts_labels_indices_and_any_order() {
    let a = Archive::from_vec(sample()).unwrap();
    let n = a.canonical_name("Lit", "sm5", &[("MODE", "1"), ("FULLY_ROUGH", "0")]).unwrap();
    assert_eq!(n, "Lit@sm5{FULLY_ROUGH=0,MODE=MASKED}");
    assert!(a.get(&n).unwrap().is_some());
    let e = a.canonical_name("Lit", "sm5", &[("MODE", "1")]).unwrap_err();
    assert!(e.contains("FULLY_ROUGH"), "{e}");
    let e = a.canonical_name("Lit", "es3_1", &[]).unwrap_err();
    assert!(e.contains("has no level `es3_1`"), "{e}");
}

#[test]
fn missing_name_lists_nearest_with_differences() {
    let a = Archive::from_vec(sample()).unwrap();
    match a.lookup("Lit@sm5{FULLY_ROUGH=2,MODE=MASKED}").unwrap() {
        Lookup::Found(_) => panic!("found a name that is not there"),
        Lookup::Missing(near) => {
            assert_eq!(near[0].differences, vec!["FULLY_ROUGH: 2 -> 0".to_string()]);
            assert!(near[0].name.contains("MODE=MASKED"));
        }
    }
}

#[test]
fn dictionaries_are_trained_and_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("big.kpak");
    let perms = big_permutations();
    let order: Vec<usize> = (0..perms.len()).collect();
    let summary = stream(&path, &perms, &order, 1);
    assert_eq!(summary.reused_blobs, 0, "no previous archive");
    let a = Archive::open(&path).unwrap();
    let dicts: Vec<Target> = a.dictionaries().map(|(t, _)| t).collect();
    assert_eq!(dicts, vec![Target::Wgsl, Target::Msl], "one dictionary per target");
    let raw: usize = perms.iter().flat_map(|(_, a)| a.iter().map(|(_, b)| b.len())).sum();
    assert!((a.len() as f64) < raw as f64 / 8.0, "{} bytes for {raw} raw", a.len());
    for (name, arts) in &perms {
        let p = a.get(name).unwrap().unwrap();
        for (t, bytes) in arts {
            assert_eq!(&p.artifact(*t).unwrap().unwrap()[..], &bytes[..], "{name} {t}");
            let info = a.blob_info(p.blob_id(*t).unwrap()).unwrap();
            assert!(info.dictionary && info.stored_len < info.raw_len, "{name} {t}: {info:?}");
        }
    }
}

/// `perms` with one artifact changed, one permutation gone and one added: a small edit.
fn edited(perms: &[Artifacts]) -> Vec<Artifacts> {
    let mut edited = perms.to_vec();
    edited[7].1[0].1 = artifact_text(1000, "edited").into_bytes();
    edited.remove(20);
    edited.push((
        "Lit@sm5{FULLY_ROUGH=500,MODE=OPAQUE}".into(),
        vec![(Target::Wgsl, artifact_text(500, "new").into_bytes())],
    ));
    edited
}

#[test]
fn rewriting_an_archive_copies_its_unchanged_blobs_and_gives_the_same_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let perms = big_permutations();
    let changed = edited(&perms);
    let all = |p: &[Artifacts]| (0..p.len()).collect::<Vec<usize>>();
    // The reference: the edited set written where no archive was.
    let fresh = stream(&dir.path().join("fresh.kpak"), &changed, &all(&changed), 1);
    assert_eq!(fresh.reused_blobs, 0);
    let out = dir.path().join("out.kpak");
    stream(&out, &perms, &all(&perms), 2);
    let rewritten = stream(&out, &changed, &all(&changed), 3);
    let fresh_bytes = std::fs::read(dir.path().join("fresh.kpak")).unwrap();
    assert!(std::fs::read(&out).unwrap() == fresh_bytes, "a rewritten archive differs from a fresh one");
    // A set this small samples every blob: the edit changed the WGSL dictionary, so its
    // blobs were compressed again, and left the MSL blobs and dictionary as they were.
    let mut msl: Vec<&[u8]> =
        changed.iter().flat_map(|(_, a)| a.iter().filter(|(t, _)| *t == Target::Msl)).map(|(_, b)| &b[..]).collect();
    msl.sort_unstable();
    msl.dedup();
    assert_eq!(rewritten.reused_blobs, msl.len(), "{rewritten:?}");
    // The same set again: everything is copied.
    let again = stream(&out, &changed, &all(&changed), 1);
    assert_eq!(again.reused_blobs, again.blobs);
    assert!(std::fs::read(&out).unwrap() == fresh_bytes);

    // A damaged previous archive (a blob's bytes, which no chunk hash covers): the damaged
    // blob is compressed again, the bytes are still the fresh archive's.
    let mut damaged = fresh_bytes.clone();
    damaged[HEADER_LEN + 5] ^= 0x40;
    std::fs::write(&out, &damaged).unwrap();
    let repaired = stream(&out, &changed, &all(&changed), 2);
    assert!(repaired.reused_blobs < repaired.blobs, "{repaired:?}");
    assert!(std::fs::read(&out).unwrap() == fresh_bytes, "a damaged previous archive changed the bytes");
    // A file that is no archive: nothing is copied.
    std::fs::write(&out, b"not an archive").unwrap();
    assert_eq!(stream(&out, &changed, &all(&changed), 1).reused_blobs, 0);
    assert!(std::fs::read(&out).unwrap() == fresh_bytes);
}

/// A previous archive damaged after the writer let go of a blob it holds (the blob was
/// added by reference) fails the build; it never gives other bytes.
#[test]
fn a_previous_archive_damaged_during_the_build_is_an_error_not_other_bytes() {
    use std::io::{Seek, Write};
    let dir = tempfile::tempdir().unwrap();
    let perms = big_permutations();
    let all: Vec<usize> = (0..perms.len()).collect();
    let out = dir.path().join("out.kpak");
    stream(&out, &perms, &all, 1);
    let before = std::fs::read(&out).unwrap();
    let w = StreamingWriter::new(&out).unwrap();
    let (sh, refl) = (shader(), reflection());
    for (i, (name, arts)) in perms.iter().enumerate() {
        let artifacts = arts.iter().map(|(t, bytes)| (*t, w.add_blob(bytes).unwrap())).collect();
        let values = vec![i as i64, (i % 2) as i64];
        w.add_permutation(NewPermutation { name: name.clone(), shader: &sh, values, reflection: &refl, artifacts })
            .unwrap();
    }
    // Every blob of the first blob's bytes on is damaged in place (the writer maps the file).
    let mut f = std::fs::OpenOptions::new().write(true).open(&out).unwrap();
    f.seek(std::io::SeekFrom::Start(HEADER_LEN as u64)).unwrap();
    f.write_all(&vec![0x5a; 4096]).unwrap();
    drop(f);
    let err = w.finish().expect_err("a damaged previous archive gave an archive").to_string();
    assert!(err.contains("the previous archive changed during the build"), "{err}");
    // The failed build left the (damaged) file as it was, not a mix of both.
    let after = std::fs::read(&out).unwrap();
    assert_eq!(after.len(), before.len());
    assert_eq!(after[HEADER_LEN..HEADER_LEN + 4096], [0x5a; 4096][..]);
}

/// A rewrite as a build makes it: blobs the previous archive holds added by reference (no
/// bytes), the others with their bytes, then no more blobs (the table that found them in
/// the previous archive dropped) before the manifest: every held blob is copied by id all the same, and the
/// bytes are a fresh archive's.
#[test]
fn blobs_found_before_sealing_are_copied_after_it() {
    let dir = tempfile::tempdir().unwrap();
    let perms = big_permutations();
    let changed = edited(&perms);
    let all: Vec<usize> = (0..changed.len()).collect();
    stream(&dir.path().join("fresh.kpak"), &changed, &all, 1);
    let out = dir.path().join("out.kpak");
    stream(&out, &perms, &(0..perms.len()).collect::<Vec<_>>(), 1);
    let mut w = StreamingWriter::new(&out).unwrap();
    w.set_naga_version("30.0.1");
    let (sh, refl) = (shader(), reflection());
    let mut numbered = Vec::new();
    let mut by_reference = 0;
    for (name, arts) in &changed {
        let mut artifacts = Vec::new();
        for (t, bytes) in arts {
            let hash = blake3::hash(bytes);
            let held = w.holds(&hash).then(|| w.add_blob_reference(hash, bytes.len() as u64).unwrap()).flatten();
            by_reference += usize::from(held.is_some());
            artifacts.push((*t, held.unwrap_or_else(|| w.add_blob_numbered(bytes, hash).unwrap())));
        }
        numbered.push((name.clone(), artifacts));
    }
    assert!(by_reference > 0);
    w.seal_blobs();
    for (i, (name, artifacts)) in numbered.into_iter().enumerate() {
        let values = vec![i as i64, (i % 2) as i64];
        w.add_permutation_numbered(NewPermutation { name, shader: &sh, values, reflection: &refl, artifacts }).unwrap();
    }
    let summary = w.finish().unwrap();
    assert!(summary.reused_blobs > 0, "{summary:?}");
    assert!(std::fs::read(&out).unwrap() == std::fs::read(dir.path().join("fresh.kpak")).unwrap());
}

/// An archive of format 4 (no check sums of stored bytes) is read, not reused: the writer
/// compresses everything again and writes format 5, byte for byte a fresh build's.
#[test]
fn a_format_4_previous_archive_is_not_reused() {
    let dir = tempfile::tempdir().unwrap();
    let perms = big_permutations();
    let all: Vec<usize> = (0..perms.len()).collect();
    let fresh = dir.path().join("fresh.kpak");
    stream(&fresh, &perms, &all, 1);
    let fresh_bytes = std::fs::read(&fresh).unwrap();
    // The same archive as format 4 wrote it: zero where format 5 keeps check sums.
    let mut v4 = fresh_bytes.clone();
    v4[8..12].copy_from_slice(&4u32.to_le_bytes());
    let table_start = v4.len() - a_blob_count(&v4) * ENTRY_LEN;
    for entry in v4[table_start..].chunks_exact_mut(ENTRY_LEN) {
        entry[26..32].fill(0);
    }
    reseal(&mut v4);
    Archive::from_vec(v4.clone()).unwrap().verify_all().unwrap();
    let out = dir.path().join("out.kpak");
    std::fs::write(&out, &v4).unwrap();
    assert_eq!(stream(&out, &perms, &all, 2).reused_blobs, 0);
    assert!(std::fs::read(&out).unwrap() == fresh_bytes);
}

#[test]
fn bytes_depend_on_the_set_not_on_order_or_threads() {
    let dir = tempfile::tempdir().unwrap();
    let perms = big_permutations();
    let forward: Vec<usize> = (0..perms.len()).collect();
    let mut shuffled: Vec<usize> = (0..perms.len()).rev().collect();
    shuffled.rotate_left(37);
    stream(&dir.path().join("a.kpak"), &perms, &forward, 1);
    stream(&dir.path().join("b.kpak"), &perms, &shuffled, 4);
    let a = std::fs::read(dir.path().join("a.kpak")).unwrap();
    let b = std::fs::read(dir.path().join("b.kpak")).unwrap();
    assert!(a == b, "two insertion orders gave different archives");
    // The in-memory writer gives the same bytes too.
    let mut w = ArchiveWriter::new();
    w.set_naga_version("30.0.1");
    let s = w.add_shader(shader());
    let r = w.add_reflection(&reflection());
    for (i, (name, arts)) in perms.iter().enumerate() {
        let artifacts = arts.iter().map(|(t, bytes)| (*t, w.add_blob(bytes))).collect();
        let values = vec![i as i64, (i % 2) as i64];
        w.add_permutation(PermutationRecord { name: name.clone(), shader: s, values, reflection: r, artifacts });
    }
    assert!(w.to_bytes().unwrap() == a, "ArchiveWriter and StreamingWriter disagree");
    // Blobs named by the numbers the writer gave, as a build names them: the same bytes.
    let w = StreamingWriter::new(&dir.path().join("c.kpak")).unwrap();
    w.set_naga_version("30.0.1");
    let (sh, refl) = (shader(), reflection());
    for &i in &shuffled {
        let (name, arts) = &perms[i];
        let artifacts =
            arts.iter().map(|(t, bytes)| (*t, w.add_blob_numbered(bytes, blake3::hash(bytes)).unwrap())).collect();
        let values = vec![i as i64, (i % 2) as i64];
        let p = NewPermutation { name: name.clone(), shader: &sh, values, reflection: &refl, artifacts };
        w.add_permutation_numbered(p).unwrap();
    }
    w.finish().unwrap();
    assert!(std::fs::read(dir.path().join("c.kpak")).unwrap() == a, "blobs by number gave other bytes");
    std::fs::remove_file(dir.path().join("c.kpak")).unwrap();
    let leftovers: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(leftovers.len(), 2, "no spool or temporary file left behind: {leftovers:?}");
}

/// Permutations that name artifacts added once by range (as a build names its keys'
/// artifacts) give the bytes of permutations with their own; a range of no writer, or of
/// two artifacts of one target, is an error.
#[test]
fn artifacts_shared_by_range_give_the_same_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let perms = big_permutations();
    let order: Vec<usize> = (0..perms.len()).collect();
    stream(&dir.path().join("a.kpak"), &perms, &order, 1);
    let w = StreamingWriter::new(&dir.path().join("b.kpak")).unwrap();
    w.set_naga_version("30.0.1");
    let (sh, refl) = (shader(), reflection());
    // Permutations with the same artifacts share one range (the later ones first).
    let (mut targets, mut blobs, mut ranges) = (Vec::new(), Vec::new(), Vec::new());
    for (_, arts) in perms.iter().rev() {
        let numbered: Vec<(Target, u32)> =
            arts.iter().map(|(t, b)| (*t, w.add_blob_numbered(b, blake3::hash(b)).unwrap())).collect();
        let found = ranges.iter().find(|(_, n)| *n == numbered).map(|r| r.0);
        let first = found.unwrap_or_else(|| {
            let first = targets.len() as u32;
            targets.extend(numbered.iter().map(|a| a.0));
            blobs.extend(numbered.iter().map(|a| a.1));
            first
        });
        ranges.push((first, numbered));
    }
    ranges.reverse();
    let base = w.add_artifacts(targets, blobs).unwrap();
    for (i, (name, _)) in perms.iter().enumerate() {
        let values = vec![i as i64, (i % 2) as i64];
        let p = NewPermutation { name: name.clone(), shader: &sh, values, reflection: &refl, artifacts: vec![] };
        let range = ArtifactRange { first: base + ranges[i].0, count: ranges[i].1.len() as u8 };
        w.add_permutation_ranged(p, range).unwrap();
    }
    let p = |artifacts| NewPermutation {
        name: "Lit@sm5{FULLY_ROUGH=500,MODE=OPAQUE}".into(),
        shader: &sh,
        values: vec![500, 0],
        reflection: &refl,
        artifacts,
    };
    let past_the_end = ArtifactRange { first: base + 1000, count: 1 };
    assert!(w.add_permutation_ranged(p(vec![]), past_the_end).is_err());
    let two_of_one_target = w.add_artifacts(vec![Target::Wgsl, Target::Wgsl], vec![0, 1]).unwrap();
    assert!(w.add_permutation_ranged(p(vec![]), ArtifactRange { first: two_of_one_target, count: 2 }).is_err());
    assert!(w.add_permutation_ranged(p(vec![(Target::Wgsl, 0)]), ArtifactRange { first: base, count: 1 }).is_err());
    assert!(w.add_artifacts(vec![Target::Wgsl], vec![1 << 30]).is_err(), "a blob of no writer");
    assert!(w.add_artifacts(vec![Target::Wgsl], vec![]).is_err());
    w.finish().unwrap();
    let (a, b) = (std::fs::read(dir.path().join("a.kpak")).unwrap(), std::fs::read(dir.path().join("b.kpak")).unwrap());
    assert!(a == b, "artifacts by range gave other bytes");
}

/// Permutations added in name order to a sorted manifest (`begin_sorted`), its parts in
/// memory or in files, their artifacts named by range or each permutation's own, give the
/// bytes of the same permutations added in any order; one out of name order, one added
/// twice, and an unsorted add after it began are errors.
#[test]
fn a_sorted_manifest_gives_the_same_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let perms = big_permutations();
    let order: Vec<usize> = (0..perms.len()).rev().collect();
    stream(&dir.path().join("a.kpak"), &perms, &order, 1);
    let a = std::fs::read(dir.path().join("a.kpak")).unwrap();
    let (sh, refl) = (shader(), reflection());
    let mut by_name: Vec<usize> = (0..perms.len()).collect();
    by_name.sort_by(|&x, &y| perms[x].0.cmp(&perms[y].0));
    for (k, (limit, own)) in [(usize::MAX, false), (0, false), (0, true)].into_iter().enumerate() {
        let path = dir.path().join(format!("s{k}.kpak"));
        let w = StreamingWriter::with_spool_memory(&path, limit).unwrap();
        w.set_naga_version("30.0.1");
        let (mut targets, mut blobs) = (Vec::new(), Vec::new());
        for (_, arts) in &perms {
            for (t, b) in arts {
                targets.push(*t);
                blobs.push(w.add_blob_numbered(b, blake3::hash(b)).unwrap());
            }
        }
        let own_artifacts: Vec<(Target, u32)> = targets.iter().copied().zip(blobs.iter().copied()).collect();
        let base = if own { 0 } else { w.add_artifacts(targets, blobs).unwrap() };
        w.begin_sorted(perms.len()).unwrap();
        assert!(w.begin_sorted(perms.len()).is_err(), "begun twice");
        let p = |i: usize| {
            let values = vec![i as i64, (i % 2) as i64];
            NewPermutation { name: perms[i].0.clone(), shader: &sh, values, reflection: &refl, artifacts: vec![] }
        };
        let range = |i: usize| ArtifactRange { first: base + 2 * i as u32, count: 2 };
        let add = |i: usize| match own {
            true => {
                let artifacts = own_artifacts[2 * i..2 * i + 2].to_vec();
                w.add_permutation_sorted_numbered(NewPermutation { artifacts, ..p(i) })
            }
            false => w.add_permutation_sorted(p(i), range(i)),
        };
        for (n, &i) in by_name.iter().enumerate() {
            add(i).unwrap();
            if n == 10 {
                assert!(add(by_name[3]).is_err(), "out of order");
                assert!(add(i).is_err(), "added twice");
                assert!(w.add_permutation_ranged(p(i), range(i)).is_err(), "unsorted after sorted");
            }
        }
        if own {
            let name = "zzz".to_string();
            let artifacts = vec![(Target::Wgsl, 1 << 30)];
            let stray = NewPermutation { name, shader: &sh, values: vec![0, 0], reflection: &refl, artifacts };
            assert!(w.add_permutation_sorted_numbered(stray).is_err(), "a blob of no writer");
        }
        let summary = w.finish().unwrap();
        assert_eq!(summary.permutations, perms.len());
        assert!(std::fs::read(&path).unwrap() == a, "a sorted manifest gave other bytes (spool limit {limit})");
    }
    let w = StreamingWriter::new(&dir.path().join("u.kpak")).unwrap();
    let base = w.add_artifacts(vec![Target::Wgsl], vec![w.add_blob_numbered(b"x", blake3::hash(b"x")).unwrap()]);
    let p = NewPermutation {
        name: perms[0].0.clone(),
        shader: &sh,
        values: vec![0, 0],
        reflection: &refl,
        artifacts: vec![],
    };
    w.add_permutation_ranged(p.clone(), ArtifactRange { first: base.unwrap(), count: 1 }).unwrap();
    assert!(w.begin_sorted(1).is_err(), "sorted after unsorted");
}

#[test]
fn writer_rejects_inconsistent_input() {
    let dir = tempfile::tempdir().unwrap();
    let w = StreamingWriter::new(&dir.path().join("x.kpak")).unwrap();
    let key = BlobKey::of(b"never added");
    let (sh, refl) = (shader(), reflection());
    let p = NewPermutation {
        name: "Lit@sm5{FULLY_ROUGH=0,MODE=OPAQUE}".into(),
        shader: &sh,
        values: vec![0, 0],
        reflection: &refl,
        artifacts: vec![(Target::Wgsl, key)],
    };
    w.add_permutation(p.clone()).unwrap();
    let msg = w.finish().unwrap_err().to_string();
    assert!(msg.contains("names a wgsl blob that was never added"), "{msg}");
    let w = StreamingWriter::new(&dir.path().join("x.kpak")).unwrap();
    w.add_blob(b"never added").unwrap();
    w.add_permutation(p.clone()).unwrap();
    w.add_permutation(p).unwrap();
    let msg = w.finish().unwrap_err().to_string();
    assert!(msg.contains("was added twice"), "{msg}");
    // A blob number the writer never gave.
    let w = StreamingWriter::new(&dir.path().join("x.kpak")).unwrap();
    let n = w.add_blob_numbered(b"one", blake3::hash(b"one")).unwrap();
    let p = NewPermutation {
        name: "Lit@sm5{FULLY_ROUGH=0,MODE=OPAQUE}".into(),
        shader: &sh,
        values: vec![0, 0],
        reflection: &refl,
        artifacts: vec![(Target::Wgsl, n + 1)],
    };
    let msg = w.add_permutation_numbered(p).unwrap_err().to_string();
    assert!(msg.contains("names a wgsl blob 1 of no writer"), "{msg}");
    drop(w);
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0, "nothing written, nothing left");
}

#[test]
fn truncation_is_an_error_at_every_length() {
    let bytes = sample();
    for len in [0, 1, 8, 11, 12, 63, 64, 65, HEADER_LEN - 1, HEADER_LEN, bytes.len() / 2, bytes.len() - 1] {
        let err = Archive::from_vec(bytes[..len].to_vec()).err().expect("truncated archive accepted");
        let msg = err.to_string();
        assert!(msg.contains("truncated") || msg.contains("shorter than"), "{len}: {msg}");
    }
}

/// Every flipped byte is found: at open (header, chunk hashes, the manifest's header and
/// tables, padding) or when the record, table entry, blob or dictionary it lies in is first
/// used, as an error naming a permutation (or, for an id, its chunk). The one
/// exception is a bit of a compressed block that zstd's decoder does not depend on (an FSE
/// or Huffman table entry of a symbol never decoded): then every artifact must still come
/// out byte for byte the original, having passed its checksum.
/// Issue 28, case 12: a file longer than its header says is not called truncated.
#[test]
fn trailing_bytes_are_not_called_truncated() {
    let mut bytes = sample();
    let len = bytes.len() as u64;
    bytes.extend_from_slice(b"appended");
    let msg = Archive::from_vec(bytes).err().expect("a longer archive accepted").to_string();
    assert_eq!(
        msg,
        format!("archive has 8 bytes after its end: the header announces {len} bytes, the file has {}", len + 8)
    );
}

#[test]
fn every_flipped_byte_is_detected() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("big.kpak");
    let perms: Vec<_> = big_permutations().into_iter().take(24).collect();
    let order: Vec<usize> = (0..perms.len()).collect();
    stream(&path, &perms, &order, 1);
    let bytes = std::fs::read(&path).unwrap();
    let original = Archive::from_vec(bytes.clone()).unwrap();
    assert!(original.dictionaries().count() > 0);
    let layout_blobs_end = HEADER_LEN + u64::from_le_bytes(bytes[16..24].try_into().unwrap()) as usize;
    for i in 0..bytes.len() {
        let mut b = bytes.clone();
        b[i] ^= 0x40;
        match Archive::from_vec(b) {
            Err(_) => {}
            Ok(a) => match a.verify_all() {
                Err(err) => {
                    // A blob, a dictionary or a blob table entry names the permutation that
                    // uses it; a record names itself; an id (which only lookups by id read)
                    // names its chunk.
                    let msg = err.to_string();
                    assert!(
                        msg.contains("artifact of permutation `Lit@sm5{")
                            || msg.contains("permutation `Lit@sm5{")
                            || msg.contains("permutation number ")
                            || msg.contains("the manifest's chunk"),
                        "byte {i}: {msg}"
                    );
                }
                Ok(()) => {
                    assert!(i < layout_blobs_end, "flipping byte {i}, outside the blob section, went unnoticed");
                    for p in a.permutations().unwrap() {
                        let o = original.get(p.name()).unwrap().unwrap();
                        for t in p.targets() {
                            assert_eq!(p.artifact(t).unwrap(), o.artifact(t).unwrap(), "byte {i}: {}", p.name());
                        }
                    }
                }
            },
        }
    }
}

#[test]
fn corrupted_blob_names_the_permutation_and_target() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("big.kpak");
    let perms = big_permutations();
    let order: Vec<usize> = (0..perms.len()).collect();
    stream(&path, &perms, &order, 1);
    let a = Archive::open(&path).unwrap();
    let p = a.get(&perms[5].0).unwrap().unwrap();
    let id = p.blob_id(Target::Msl).unwrap();
    let info = a.blob_info(id).unwrap();
    drop(a);
    // Find the blob's offset from the table and flip a byte in the middle of it; the header
    // and manifest checksum stays valid (it does not cover blobs).
    let mut bytes = std::fs::read(&path).unwrap();
    let table_start = bytes.len() - a_blob_count(&bytes) * ENTRY_LEN;
    let e = Entry::decode(&bytes[table_start + id.0 as usize * ENTRY_LEN..][..ENTRY_LEN]);
    assert_eq!(e.stored_len, info.stored_len);
    bytes[HEADER_LEN + (e.offset + e.stored_len / 2) as usize] ^= 0x01;
    let a = Archive::from_vec(bytes).unwrap();
    let sharing: Vec<&str> =
        a.permutations().unwrap().filter(|q| q.blob_id(Target::Msl) == Some(id)).map(|q| q.name()).collect();
    for name in &sharing {
        let msg = a.get(name).unwrap().unwrap().artifact(Target::Msl).unwrap_err().to_string();
        assert!(msg.contains(&format!("the msl artifact of permutation `{name}`")), "{msg}");
    }
    // Its other artifacts and its neighbours are intact.
    assert!(a.get(&perms[5].0).unwrap().unwrap().artifact(Target::Wgsl).is_ok());
    assert!(a.get(&perms[10].0).unwrap().unwrap().artifact(Target::Msl).is_ok());
}

fn a_blob_count(bytes: &[u8]) -> usize {
    u64::from_le_bytes(bytes[40..48].try_into().unwrap()) as usize
}

/// The section lengths of an archive's header, and the layout they give.
fn layout_of(bytes: &[u8]) -> (Sections, Layout) {
    let u64_at = |o: usize| u64::from_le_bytes(bytes[o..o + 8].try_into().unwrap());
    let sections = Sections {
        blobs_len: u64_at(16),
        dictionaries_len: u64_at(24),
        manifest_len: u64_at(32),
        blob_count: u64_at(40),
        chunk_len: u32::from_le_bytes(bytes[48..52].try_into().unwrap()),
    };
    (sections, sections.layout().unwrap())
}

/// Rewrites the chunk hashes and the header checksum after an edit, as a hostile tool would.
fn reseal(bytes: &mut [u8]) {
    let (sections, layout) = layout_of(bytes);
    reseal_at(bytes, &sections, &layout);
}

/// [`reseal`] with the sections where they were before the header's lengths were edited.
fn reseal_at(bytes: &mut [u8], sections: &Sections, layout: &Layout) {
    let mut h = ChunkHasher::new(sections.chunk_len);
    let manifest = layout.manifest as usize;
    h.update(&bytes[manifest..manifest + sections.manifest_len as usize]);
    h.finish();
    h.update(&bytes[layout.table as usize..layout.end as usize]);
    h.finish();
    bytes[layout.chunks as usize..manifest].copy_from_slice(&h.hashes);
    let sum = header_checksum(&bytes[..96], &bytes[layout.chunks as usize..manifest]);
    bytes[96..128].copy_from_slice(sum.as_bytes());
}

/// The permutation that uses blob 0 as its `target` artifact.
fn user_of_blob_0(a: &Archive) -> (String, Target) {
    a.permutations()
        .unwrap()
        .find_map(|p| p.targets().find(|t| p.blob_id(*t) == Some(BlobId(0))).map(|t| (p.name().to_string(), t)))
        .expect("blob 0 is used")
}

#[test]
fn hostile_table_entries_with_a_valid_checksum_are_errors_naming_the_permutation() {
    let bytes = sample();
    let (name, target) = user_of_blob_0(&Archive::from_vec(bytes.clone()).unwrap());
    let table_start = bytes.len() - a_blob_count(&bytes) * ENTRY_LEN;
    let edits: [(usize, &[u8], &str); 5] = [
        (16, &(1u64 << 40).to_le_bytes(), "announces"),
        (0, &(1u64 << 50).to_le_bytes(), "outside the blob section"),
        (24, &[9], "codec 9"),
        (25, &[3], "codec"),
        (26, &[1], "check sum of its stored bytes"),
    ];
    for (at, patch, wanted) in edits {
        let mut b = bytes.clone();
        b[table_start + at..table_start + at + patch.len()].copy_from_slice(patch);
        reseal(&mut b);
        // Opening reads no entry: the entry is checked when its blob is first used.
        let a = Archive::from_vec(b).expect("entries are checked on use");
        let p = a.get(&name).unwrap().unwrap();
        let msg = p.artifact(target).expect_err("hostile entry accepted").to_string();
        assert!(msg.contains(wanted), "{wanted}: {msg}");
        assert!(msg.contains(&format!("the {target} artifact of permutation `{name}`")), "{msg}");
        assert!(a.verify_all().is_err());
        // The check sum of the stored bytes is read with them, not with the entry's sizes.
        assert!(at == 26 || p.blob_info(target).is_err(), "{wanted}");
    }
    // Sealed as is, the archive opens and reads: the edits above were what was refused.
    let mut b = bytes.clone();
    reseal(&mut b);
    Archive::from_vec(b).unwrap().verify_all().unwrap();
}

/// A blob table entry damaged in place (its chunk's hash no longer holds): an error naming
/// the permutation and target that use it, every time, and the other entries still read.
#[test]
fn corrupted_blob_table_entry_names_the_permutation_and_target() {
    let bytes = sample();
    let (name, target) = user_of_blob_0(&Archive::from_vec(bytes.clone()).unwrap());
    let table_start = bytes.len() - a_blob_count(&bytes) * ENTRY_LEN;
    let mut b = bytes.clone();
    b[table_start + 16] ^= 0x01; // the raw length
    let a = Archive::from_vec(b).expect("the table is checked on use");
    for _ in 0..2 {
        let msg = a.get(&name).unwrap().unwrap().artifact(target).unwrap_err().to_string();
        assert!(msg.contains(&format!("the {target} artifact of permutation `{name}`")), "{msg}");
        assert!(msg.contains("blob table's chunk 0") && msg.contains("fails its checksum"), "{msg}");
    }
    assert!(a.verify_all().is_err());
}

/// A manifest chunk damaged in place: a lookup that reads it, a walk of every record and a
/// lookup by id are errors naming the permutation; chunks not read are not checked.
#[test]
fn corrupted_manifest_chunk_is_an_error_naming_the_permutation() {
    // 2,000 permutations with small artifacts: a manifest of many chunks.
    let mut w = ArchiveWriter::new();
    let s = w.add_shader(shader());
    let r = w.add_reflection(&reflection());
    let mut names = Vec::new();
    for i in 0..2000i64 {
        let blob = w.add_blob(format!("// wgsl {}", i % 7).as_bytes());
        let name = format!("Lit@sm5{{FULLY_ROUGH={i},MODE={}}}", ["OPAQUE", "MASKED"][i as usize % 2]);
        names.push(name.clone());
        let record = PermutationRecord { name, shader: s, values: vec![i, i % 2], reflection: r, artifacts: vec![] };
        w.add_permutation(PermutationRecord { artifacts: vec![(Target::Wgsl, blob)], ..record });
    }
    names.sort();
    let bytes = w.to_bytes().unwrap();
    let (start, len) = manifest_range(&bytes);
    let chunk = CHUNK_LEN as usize;
    assert!(len > 8 * chunk, "the manifest spans many chunks ({len} bytes)");
    let counts = ManifestCounts::decode(&bytes[start..]).unwrap();
    let layout = counts.layout().unwrap();
    // The last name: the last permutation's, in the manifest's last chunk.
    let last = names.last().unwrap();
    let mut b = bytes.clone();
    b[start + len - 1] ^= 0x01;
    let a = Archive::from_vec(b).expect("the names are checked on use");
    let msg = a.get(last).err().expect("damaged name read").to_string();
    assert!(msg.starts_with(&format!("archive is corrupted: permutation `{last}`: ")), "{msg}");
    assert!(msg.contains("manifest's chunk") && msg.contains("fails its checksum"), "{msg}");
    // Names in other chunks are found (the first is in another chunk than the last).
    assert_eq!(a.get(&names[0]).unwrap().unwrap().name(), names[0]);
    // The walk of every record is refused before it yields one.
    let msg = a.permutations().err().expect("walk over a damaged chunk").to_string();
    assert!(msg.contains("archive is corrupted: permutation number ") && msg.contains("fails its checksum"), "{msg}");
    assert!(a.verify_all().is_err());
    assert!(matches!(a.lookup(last), Err(ArchiveError::Permutation { .. })));

    // A record damaged: the lookups whose binary search reads it fail, naming the name
    // looked up; a lookup by id reading a damaged id fails naming the id.
    let mut b = bytes.clone();
    let mid = counts.permutations as usize / 2;
    b[start + layout.records as usize + mid * RECORD_LEN + 9] ^= 0x01;
    let a = Archive::from_vec(b).unwrap();
    for name in &names {
        match a.get(name) {
            Ok(p) => assert_eq!(p.unwrap().name(), name.as_str()),
            Err(e) => assert!(e.to_string().contains(&format!("permutation `{name}`: looking it up")), "{e}"),
        }
    }
    assert!(a.get(&names[0]).is_err(), "the first step of every search reads the middle record");
    let mut b = bytes.clone();
    b[start + layout.ids as usize + (counts.permutations as usize / 2) * 24] ^= 0x01;
    let a = Archive::from_vec(b).unwrap();
    let id = permutation_id("Lit", "sm5", &[0, 0]);
    let msg = a.get_by_id(id).err().expect("damaged id read").to_string();
    assert!(msg.contains(&format!("permutation with id {id:032x}")) && msg.contains("fails its checksum"), "{msg}");
}

#[test]
fn older_and_newer_format_versions_are_named() {
    // A format 1 archive: the same magic, version 1, a 64-byte header.
    let mut v1 = MAGIC.to_vec();
    v1.extend_from_slice(&1u32.to_le_bytes());
    v1.resize(64 + 16, 0);
    let msg = Archive::from_vec(v1).err().unwrap().to_string();
    assert!(msg.contains("archive format version 1 is not supported"), "{msg}");
    assert!(msg.contains("rebuild"), "{msg}");
    let mut bytes = sample();
    bytes[8..12].copy_from_slice(&7u32.to_le_bytes());
    let msg = Archive::from_vec(bytes).err().unwrap().to_string();
    assert!(msg.contains("format version 7 is not supported"), "{msg}");
}

#[test]
fn format_2_and_3_archives_are_refused_with_a_rebuild_hint() {
    for version in [2u32, 3] {
        let mut bytes = sample();
        bytes[8..12].copy_from_slice(&version.to_le_bytes());
        let msg = Archive::from_vec(bytes).err().unwrap().to_string();
        assert!(msg.contains(&format!("archive format version {version} is not supported")), "{msg}");
        assert!(msg.contains("reads versions 4 to 5") && msg.contains("rebuild"), "{msg}");
    }
}

/// Where the manifest starts, and its length.
fn manifest_range(bytes: &[u8]) -> (usize, usize) {
    let manifest_len = u64::from_le_bytes(bytes[32..40].try_into().unwrap()) as usize;
    let table_start = bytes.len() - a_blob_count(bytes) * ENTRY_LEN;
    (table_start - manifest_len.next_multiple_of(8), manifest_len)
}

/// A change to one permutation record.
type Edit = fn(&mut Record);

#[test]
fn hostile_permutation_records_with_a_valid_checksum_are_errors() {
    let bytes = sample();
    let (start, _) = manifest_range(&bytes);
    let counts = ManifestCounts::decode(&bytes[start..]).unwrap();
    let records = start + counts.layout().unwrap().records as usize;
    let edits: [(Edit, &str); 6] = [
        (|r| r.name_offset = 1 << 40, "name lies outside"),
        (|r| r.name_len += 1000, "name lies outside"),
        (|r| r.shader = 7, "names shader 7 of 1"),
        (|r| r.reflection = 3, "missing reflection"),
        (|r| r.first_value = u32::MAX, "values lie outside"),
        (|r| r.artifact_count = 9, "artifacts lie outside"),
    ];
    for (edit, wanted) in edits {
        let mut b = bytes.clone();
        let at = records + RECORD_LEN;
        let mut r = Record::decode(&b[at..at + RECORD_LEN]);
        edit(&mut r);
        b[at..at + RECORD_LEN].copy_from_slice(&r.encode());
        reseal(&mut b);
        // Opening reads no record: each is checked when first used, here by the walk.
        let a = Archive::from_vec(b).expect("records are checked on use");
        let msg = a.permutations().err().expect("hostile record accepted").to_string();
        assert!(msg.contains(wanted), "{wanted}: {msg}");
        assert!(msg.starts_with("archive is corrupted: permutation "), "{msg}");
        assert!(a.verify_all().is_err());
    }
    // A name cut inside a UTF-8 character, and counts that do not add up to the length.
    let mut b = bytes.clone();
    let (_, len) = manifest_range(&b);
    b[start + len - 1] = 0xc3;
    reseal(&mut b);
    assert!(Archive::from_vec(b).unwrap().permutations().err().unwrap().to_string().contains("UTF-8"));
    let mut b = bytes.clone();
    b[start..start + 8].copy_from_slice(&5u64.to_le_bytes());
    reseal(&mut b);
    assert!(Archive::from_vec(b).err().unwrap().to_string().contains("counts give"));
}

#[test]
fn atomic_write_then_mmap_open() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("sub/shaders.kpak");
    let mut w = ArchiveWriter::new();
    let s = w.add_shader(shader());
    let r = w.add_reflection(&reflection());
    let b = w.add_blob(b"x");
    let name = "Lit@sm5{FULLY_ROUGH=0,MODE=OPAQUE}".to_string();
    w.add_permutation(PermutationRecord {
        name,
        shader: s,
        values: vec![0, 0],
        reflection: r,
        artifacts: vec![(Target::Wgsl, b)],
    });
    w.write(&path).unwrap();
    let a = Archive::open(&path).unwrap();
    assert_eq!(&a.blob(BlobId(0)).unwrap()[..], b"x");
    let leftovers: Vec<_> = std::fs::read_dir(path.parent().unwrap()).unwrap().collect();
    assert_eq!(leftovers.len(), 1, "no temporary file left behind");
}

#[test]
fn empty_archive_round_trips() {
    let a = Archive::from_vec(ArchiveWriter::new().to_bytes().unwrap()).unwrap();
    assert_eq!(a.permutations().unwrap().count(), 0);
    assert_eq!(a.blob_count(), 0);
}

#[test]
fn directories_and_fifos_are_refused_without_blocking() {
    let dir = tempfile::tempdir().unwrap();
    let msg = Archive::open(dir.path()).err().unwrap().to_string();
    assert!(msg.contains("it is a directory, not a regular file"), "{msg}");
    let fifo = dir.path().join("fifo");
    let c = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
    // SAFETY: a valid NUL-terminated path.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o644) }, 0);
    let msg = Archive::open(&fifo).err().unwrap().to_string();
    assert!(msg.contains("it is a FIFO, not a regular file"), "{msg}");
    let msg = Archive::open(std::path::Path::new("/dev/null")).err().unwrap().to_string();
    assert!(msg.contains("character device"), "{msg}");
}

/// A bounded fuzz loop over the reader with a valid checksum: random bytes of the header's
/// lengths, the manifest and the blob table changed, the checksum recomputed, as a hostile
/// tool would. Opening, reading every artifact and every lookup must give errors, never
/// panic or allocate without bound.
#[test]
fn resealed_random_damage_never_panics() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("big.kpak");
    let perms: Vec<_> = big_permutations().into_iter().take(16).collect();
    let order: Vec<usize> = (0..perms.len()).collect();
    stream(&path, &perms, &order, 1);
    let bytes = std::fs::read(&path).unwrap();
    let (sections, layout) = layout_of(&bytes);
    let manifest_len = sections.manifest_len as usize;
    let table_start = layout.table as usize;
    let manifest_start = layout.manifest as usize;
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    let (mut opened, mut failed) = (0, 0);
    for round in 0..3000 {
        let mut b = bytes.clone();
        for _ in 0..1 + next() % 4 {
            let at = match next() % 3 {
                0 => 16 + (next() % 32) as usize,
                1 => manifest_start + (next() % manifest_len as u64) as usize,
                _ => table_start + (next() % (bytes.len() - table_start) as u64) as usize,
            };
            b[at] = match next() % 4 {
                0 => b[at] ^ (1 << (next() % 8)),
                1 => 0xff,
                2 => 0,
                _ => next() as u8,
            };
        }
        reseal_at(&mut b, &sections, &layout);
        match Archive::from_vec(b) {
            Err(_) => failed += 1,
            Ok(a) => {
                opened += 1;
                let _ = a.verify_all();
                for p in a.permutations().into_iter().flatten() {
                    let _ = a.lookup(p.name());
                    let _ = p.shader();
                    let _ = p.reflection();
                    let _ = a.get_by_id(permutation_id(&p.shader().name, &p.shader().level, p.values()));
                    p.targets().for_each(|t| drop(p.artifact(t)));
                }
                for (name, _) in &perms {
                    if let Ok(Some(p)) = a.get(name) {
                        p.targets().for_each(|t| drop(p.artifact(t)));
                    }
                }
                let _ = a.lookup(&format!("Lit@sm5{{FULLY_ROUGH={round}}}"));
            }
        }
    }
    assert!(opened > 0 && failed > 0, "the loop reached both outcomes: {opened} opened, {failed} refused");
}

#[test]
fn artifacts_are_read_and_checked_from_many_threads_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("big.kpak");
    let perms = big_permutations();
    let order: Vec<usize> = (0..perms.len()).collect();
    stream(&path, &perms, &order, 1);
    let mut bytes = std::fs::read(&path).unwrap();
    // Damage the msl blob of permutation 0 (its neighbours stay intact).
    let a = Archive::from_vec(bytes.clone()).unwrap();
    let id = a.get(&perms[0].0).unwrap().unwrap().blob_id(Target::Msl).unwrap();
    let table_start = bytes.len() - a_blob_count(&bytes) * ENTRY_LEN;
    let e = Entry::decode(&bytes[table_start + id.0 as usize * ENTRY_LEN..][..ENTRY_LEN]);
    bytes[HEADER_LEN + (e.offset + e.stored_len / 2) as usize] ^= 0x10;
    let a = Archive::from_vec(bytes).unwrap();
    std::thread::scope(|scope| {
        for _ in 0..8 {
            scope.spawn(|| {
                for (name, arts) in &perms {
                    let p = a.get(name).unwrap().unwrap();
                    for (t, want) in arts {
                        match p.artifact(*t) {
                            Ok(got) => assert_eq!(&got.unwrap()[..], &want[..], "{name} {t}"),
                            Err(e) => assert!(p.blob_id(*t) == Some(id), "{name} {t}: {e}"),
                        }
                    }
                }
            });
        }
    });
    assert!(a.get(&perms[0].0).unwrap().unwrap().artifact(Target::Msl).is_err());
}

fn sample_with_pipelines(pipelines: Vec<PipelineRecord>) -> Vec<u8> {
    let mut w = ArchiveWriter::new();
    w.set_naga_version("30.0.1");
    let s = w.add_shader(shader());
    let r = w.add_reflection(&reflection());
    let wgsl = w.add_blob(b"// wgsl");
    w.add_permutation(PermutationRecord {
        name: "Lit@sm5{FULLY_ROUGH=0,MODE=OPAQUE}".into(),
        shader: s,
        values: vec![0, 0],
        reflection: r,
        artifacts: vec![(Target::Wgsl, wgsl)],
    });
    w.set_pipelines(pipelines);
    w.to_bytes().unwrap()
}

#[test]
fn pipeline_manifest_round_trips_in_its_order_and_is_absent_by_default() {
    use crate::usage::UsageKey;
    assert_eq!(Archive::from_vec(sample()).unwrap().pipeline_manifest(), None);
    let records = vec![
        PipelineRecord {
            key: UsageKey::Render {
                vertex: "Lit@sm5{FULLY_ROUGH=0,MODE=OPAQUE}".into(),
                fragment: None,
                state: "tri;cull=Back".into(),
            },
            first_frame: 0,
        },
        PipelineRecord {
            key: UsageKey::Compute { compute: "Lit@sm5{FULLY_ROUGH=0,MODE=OPAQUE}".into() },
            first_frame: 2,
        },
    ];
    let bytes = sample_with_pipelines(records.clone());
    let a = Archive::from_vec(bytes).unwrap();
    assert_eq!(a.pipeline_manifest(), Some(&records[..]));
    a.verify_all().unwrap();
}

#[test]
fn pipeline_records_with_spaces_or_empty_names_are_refused_at_open() {
    use crate::usage::UsageKey;
    for key in [
        UsageKey::Compute { compute: String::new() },
        UsageKey::Compute { compute: "A B".into() },
        UsageKey::Render { vertex: "V".into(), fragment: Some("F\n".into()), state: "s".into() },
        UsageKey::Render { vertex: "V".into(), fragment: None, state: "a b".into() },
    ] {
        let bytes = sample_with_pipelines(vec![PipelineRecord { key, first_frame: 0 }]);
        let Err(e) = Archive::from_vec(bytes) else { panic!("a bad pipeline record opened") };
        let e = e.to_string();
        assert!(e.contains("pipeline 0 of its pipeline manifest"), "{e}");
    }
}
