//! The archive and the loose files of a real build: every kept permutation is in the
//! archive under its canonical name with the artifacts `--emit-dir` wrote, and a truncated,
//! corrupted or foreign-version archive is a clear error.

mod build_support;

use std::collections::BTreeMap;

use build_support::*;
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
    assert_eq!(archive.permutations().count(), report.stats.permutations);
    assert_eq!(archive.blob_count(), report.stats.artifacts);
    assert_eq!(archive.naga_version(), kiln::compile::NAGA_VERSION);
    assert_eq!(archive.kiln_version(), kiln::VERSION);

    let index: BTreeMap<String, BTreeMap<String, String>> =
        serde_json::from_slice(&std::fs::read(emit.join("index.json")).unwrap()).unwrap();
    assert_eq!(index.len(), report.stats.permutations);
    let mut files = std::collections::BTreeSet::new();
    for p in archive.permutations() {
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

    let p = archive.get("LitPS@es3_1{USE_FOG=1,BLEND=MASKED,NUM_LIGHTS=2}").expect("by canonical name");
    assert_eq!(p.targets().collect::<Vec<_>>(), vec![Target::Glsl, Target::Spirv, Target::Msl, Target::Wgsl]);
    assert!(archive.get("LitPS@es3_1{USE_FOG=1,BLEND=TRANSLUCENT,NUM_LIGHTS=0}").is_none(), "skipped");
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
    let mut flipped = bytes.clone();
    let at = bytes.len() - 100;
    flipped[at] ^= 1;
    assert!(open(flipped).to_string().starts_with("archive is corrupted: checksum mismatch"));
    let mut other = bytes.clone();
    other[8..12].copy_from_slice(&2u32.to_le_bytes());
    assert_eq!(
        open(other).to_string(),
        "archive format version 2 is not supported (this build of kiln reads version 1); rebuild the archive with this kiln"
    );
    assert!(Archive::from_vec(bytes).is_ok());
}
