//! The archive and the loose files of a real build: every kept permutation is in the
//! archive under its canonical name with the artifacts `--emit-dir` wrote, and a truncated,
//! corrupted or foreign-version archive is a clear error.

use std::collections::BTreeMap;

use crate::build_support::*;
use kiln::archive::{Archive, ArchiveError, Target};

#[test]
fn round_trip_through_archive_and_emit_dir() {
    let fx = fixture();
    let config = fx.path().join("lit.toml");
    let out = fx.path().join("shaders.kpak");
    let emit = fx.path().join("emit");
    let mut opts = options(&config, &out, None);
    opts.emit_dir = Some(emit.clone());
    let report = build_ok(&opts);

    let archive = Archive::open(&out).unwrap();
    assert_eq!(archive.permutations().unwrap().count(), report.stats.permutations);
    assert_eq!(archive.blob_count(), report.stats.artifacts);
    assert_eq!(archive.naga_version(), kiln::compile::NAGA_VERSION);
    assert_eq!(archive.kiln_version(), kiln::VERSION);

    let index: BTreeMap<String, BTreeMap<String, String>> =
        serde_json::from_slice(&std::fs::read(emit.join("index.json")).unwrap()).unwrap();
    assert_eq!(index.len(), report.stats.permutations);
    let mut files = std::collections::BTreeSet::new();
    for p in archive.permutations().unwrap() {
        let targets = &index[p.name()];
        assert_eq!(targets.len(), p.targets().count(), "{}", p.name());
        for t in p.targets() {
            let file = &targets[t.name()];
            assert!(file.ends_with(&format!(".{}", t.extension(p.shader().stage))), "{file}");
            assert_eq!(
                std::fs::read(emit.join(file)).unwrap(),
                &p.artifact(t).unwrap().unwrap()[..],
                "{} {t}",
                p.name()
            );
            files.insert(file.clone());
        }
        // Names are canonical: the runtime builds them from dimension values.
        let shader = p.shader();
        let values: Vec<(String, String)> =
            shader.dimensions.iter().zip(p.values()).map(|(d, v)| (d.name.clone(), v.to_string())).collect();
        let pairs: Vec<(&str, &str)> = values.iter().map(|(a, b)| (a.as_str(), b.as_str())).collect();
        assert_eq!(archive.canonical_name(&shader.name, &shader.level, &pairs).unwrap(), p.name());
    }
    // Each distinct artifact is written once.
    let on_disk = std::fs::read_dir(&emit).unwrap().count() - 1;
    assert_eq!(on_disk, files.len());
    assert_eq!(files.len(), report.stats.artifacts);

    let p = archive.get("LitPS@es3_1{USE_FOG=1,BLEND=MASKED,NUM_LIGHTS=2}").unwrap().expect("by canonical name");
    assert_eq!(p.targets().collect::<Vec<_>>(), vec![Target::Glsl, Target::Spirv, Target::Msl, Target::Wgsl]);
    assert!(archive.get("LitPS@es3_1{USE_FOG=1,BLEND=TRANSLUCENT,NUM_LIGHTS=0}").unwrap().is_none(), "skipped");
}

#[test]
fn damaged_archives_are_clear_errors() {
    let fx = fixture();
    let out = fx.path().join("shaders.kpak");
    build_ok(&options(&fx.path().join("compute.toml"), &out, None));
    let bytes = std::fs::read(&out).unwrap();
    let open = |b: Vec<u8>| Archive::from_vec(b).err().expect("damaged archive accepted");

    match open(bytes[..bytes.len() - 1].to_vec()) {
        ArchiveError::Truncated { expected, actual } => {
            assert_eq!((expected, actual), (bytes.len() as u64, bytes.len() as u64 - 1))
        }
        e => panic!("{e}"),
    }
    // A byte of the chunk hashes (just before the manifest), which the header checksum
    // covers: refused at open.
    let u64_at = |o: usize| u64::from_le_bytes(bytes[o..o + 8].try_into().unwrap()) as usize;
    let manifest_start = bytes.len() - u64_at(40) * 64 - u64_at(32).next_multiple_of(8);
    let mut flipped = bytes.clone();
    flipped[manifest_start - 1] ^= 1;
    assert!(open(flipped).to_string().starts_with("archive is corrupted: header checksum mismatch"));
    // A byte of the blob table: its chunk is checked when first read.
    let mut flipped = bytes.clone();
    flipped[bytes.len() - 100] ^= 1;
    let a = Archive::from_vec(flipped).expect("the blob table is checked on use");
    let e = a.verify_all().unwrap_err().to_string();
    assert!(e.starts_with("archive is corrupted: ") && e.contains("fails its checksum"), "{e}");
    let mut other = bytes.clone();
    other[8..12].copy_from_slice(&1u32.to_le_bytes());
    assert_eq!(
        open(other).to_string(),
        "archive format version 1 is not supported (this build of kiln reads versions 4 to 5); rebuild the archive with this kiln"
    );
    assert!(Archive::from_vec(bytes).is_ok());
}

/// The blob table entry of `id` in an archive's bytes: (stored offset from the start of the
/// blob section, stored length). The table closes the file, 64 bytes per blob.
fn blob_entry(bytes: &[u8], id: kiln::archive::BlobId) -> (usize, usize) {
    let count = u64::from_le_bytes(bytes[40..48].try_into().unwrap()) as usize;
    let at = bytes.len() - count * 64 + id.0 as usize * 64;
    let u64_at = |o: usize| u64::from_le_bytes(bytes[at + o..at + o + 8].try_into().unwrap()) as usize;
    (u64_at(0), u64_at(8))
}

#[test]
fn corrupted_blob_with_valid_header_names_the_permutation() {
    let fx = fixture();
    let out = fx.path().join("shaders.kpak");
    build_ok(&options(&fx.path().join("lit.toml"), &out, None));
    let bytes = std::fs::read(&out).unwrap();
    let archive = Archive::open(&out).unwrap();
    let name = "LitPS@es3_1{USE_FOG=1,BLEND=MASKED,NUM_LIGHTS=2}";
    let id = archive.get(name).unwrap().unwrap().blob_id(Target::Spirv).unwrap();
    let (offset, len) = blob_entry(&bytes, id);
    let mut damaged = bytes.clone();
    damaged[kiln::archive::HEADER_LEN + offset + len / 2] ^= 0x08;
    // Opening checks only the header and manifest: it succeeds.
    let a = Archive::from_vec(damaged).expect("blob damage is found on use, not at open");
    let users: Vec<String> = a
        .permutations()
        .unwrap()
        .filter(|p| p.blob_id(Target::Spirv) == Some(id))
        .map(|p| p.name().to_string())
        .collect();
    assert!(users.iter().any(|u| u == name));
    for user in &users {
        let e = a.get(user).unwrap().unwrap().artifact(Target::Spirv).unwrap_err();
        assert!(matches!(&e, ArchiveError::Blob { permutation, target: Target::Spirv, .. } if permutation == user));
        assert!(e.to_string().contains(&format!("the spirv artifact of permutation `{user}`")), "{e}");
        // Every later use gives the same error: nothing damaged is ever returned.
        assert!(a.get(user).unwrap().unwrap().artifact(Target::Spirv).is_err());
    }
    // The other artifacts are fine.
    assert!(a.get(name).unwrap().unwrap().artifact(Target::Wgsl).unwrap().is_some());
    assert!(a.verify_all().is_err());
    assert!(Archive::from_vec(bytes).unwrap().verify_all().is_ok());
}

#[test]
fn archive_damaged_in_place_with_size_and_mtime_kept_is_rebuilt() {
    let fx = fixture();
    let out = fx.path().join("shaders.kpak");
    let cache = fx.path().join("cache");
    let opts = options(&fx.path().join("lit.toml"), &out, Some(&cache));
    build_ok(&opts);
    let good = std::fs::read(&out).unwrap();
    let mtime = std::fs::metadata(&out).unwrap().modified().unwrap();
    // Up to date: the second build leaves the file alone.
    build_ok(&opts);
    assert_eq!(std::fs::metadata(&out).unwrap().modified().unwrap(), mtime, "an up-to-date archive was rewritten");

    // One byte of one blob flipped, in place; length and modification time put back.
    let archive = Archive::open(&out).unwrap();
    let id = archive.permutations().unwrap().next().unwrap().blob_id(Target::Wgsl).unwrap();
    drop(archive);
    let (offset, len) = blob_entry(&good, id);
    let mut damaged = good.clone();
    damaged[kiln::archive::HEADER_LEN + offset + len / 2] ^= 0x20;
    {
        use std::io::{Seek, SeekFrom, Write};
        let mut f = std::fs::OpenOptions::new().write(true).open(&out).unwrap();
        f.seek(SeekFrom::Start(0)).unwrap();
        f.write_all(&damaged).unwrap();
        f.set_modified(mtime).unwrap();
    }
    assert_eq!(std::fs::metadata(&out).unwrap().modified().unwrap(), mtime);
    assert_eq!(std::fs::metadata(&out).unwrap().len(), good.len() as u64);
    assert_eq!(std::fs::read(&out).unwrap(), damaged);

    build_ok(&opts);
    assert!(std::fs::read(&out).unwrap() == good, "the damaged archive was taken as up to date");
    Archive::open(&out).unwrap().verify_all().unwrap();
}

#[test]
fn build_archive_is_compressed_with_dictionaries_and_deterministic_across_jobs() {
    let fx = fixture();
    let config = fx.path().join("lit.toml");
    let one = fx.path().join("one.kpak");
    let two = fx.path().join("two.kpak");
    let mut opts = options(&config, &one, None);
    opts.jobs = Some(1);
    build_ok(&opts);
    let mut opts = options(&config, &two, None);
    opts.jobs = Some(2);
    build_ok(&opts);
    assert!(std::fs::read(&one).unwrap() == std::fs::read(&two).unwrap(), "-j 1 and -j 2 differ");
    let a = Archive::open(&one).unwrap();
    let (mut raw, mut stored) = (0u64, 0u64);
    for id in 0..a.blob_count() {
        let info = a.blob_info(kiln::archive::BlobId(id as u32)).unwrap();
        raw += info.raw_len;
        stored += info.stored_len;
    }
    assert!(stored * 2 < raw, "blobs are compressed: {stored} of {raw}");
    a.verify_all().unwrap();
    // No spool or temporary file is left beside the output.
    let stray: Vec<_> = std::fs::read_dir(fx.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with('.') && (n.ends_with(".spool") || n.ends_with(".tmp")))
        .collect();
    assert!(stray.is_empty(), "{stray:?}");
}
