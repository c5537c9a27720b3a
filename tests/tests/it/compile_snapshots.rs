//! Snapshot tests in the naga style: every `tests/in/*.toml` permutation set is built, and
//! each permutation's artifact per target is compared with `tests/out/<target>/<set>/`,
//! its reflection with `tests/out/reflection/<set>/`, and the set's permutation list and
//! deduplication groups with `tests/out/summary/<set>.txt`. Any difference fails; run with
//! `KILN_BLESS=1` to rewrite the expected files (then review the diff). Every artifact also
//! goes through `spirv-val`, `glslangValidator` and naga.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::build_support::*;
use kiln::archive::{Archive, Target};

fn file_name(permutation: &str) -> String {
    // `LitPS@es3_1{USE_FOG=1,BLEND=MASKED}` -> `LitPS.es3_1.USE_FOG-1.BLEND-MASKED`
    permutation
        .replace(['@', '{'], ".")
        .replace('}', "")
        .replace(',', ".")
        .replace('=', "-")
        .trim_end_matches('.')
        .to_string()
}

struct Snapshots {
    bless: bool,
    expected: BTreeMap<PathBuf, Vec<u8>>,
    mismatches: Vec<String>,
}

impl Snapshots {
    fn check(&mut self, path: PathBuf, actual: &[u8]) {
        self.expected.insert(path.clone(), actual.to_vec());
        let old = std::fs::read(&path).ok();
        if old.as_deref() == Some(actual) {
            return;
        }
        if self.bless {
            std::fs::create_dir_all(path.parent().unwrap()).unwrap();
            std::fs::write(&path, actual).unwrap();
        } else if old.is_none() {
            self.mismatches.push(format!("{} is missing (run with KILN_BLESS=1 to create it)", path.display()));
        } else {
            self.mismatches.push(format!("{} differs", path.display()));
        }
    }

    /// Expected files of `set` that this run did not produce.
    fn stale(&mut self, root: &Path, set: &str) {
        for sub in ["wgsl", "spirv", "msl", "glsl", "hlsl", "reflection"] {
            let dir = root.join(sub).join(set);
            let Ok(entries) = std::fs::read_dir(&dir) else { continue };
            for e in entries {
                let path = e.unwrap().path();
                if !self.expected.contains_key(&path) {
                    if self.bless {
                        std::fs::remove_file(&path).unwrap();
                    } else {
                        self.mismatches.push(format!("{} is no longer produced", path.display()));
                    }
                }
            }
        }
    }
}

#[test]
fn snapshots_match_and_every_artifact_validates() {
    let out_root = Path::new(env!("CARGO_MANIFEST_DIR")).join("out");
    let mut snapshots = Snapshots { bless: crate::support::bless(), expected: BTreeMap::new(), mismatches: Vec::new() };
    let mut sets: Vec<PathBuf> = std::fs::read_dir(inputs())
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .collect();
    sets.sort();
    assert!(sets.len() >= 2, "expected the snapshot inputs under {}", inputs().display());
    let tmp = tempfile::tempdir().unwrap();
    let mut checked = 0;
    for config in &sets {
        let set = config.file_stem().unwrap().to_str().unwrap().to_string();
        let archive_path = tmp.path().join(format!("{set}.kpak"));
        let report = build_ok(&options(config, &archive_path, None));
        let archive = Archive::open(&archive_path).unwrap();

        let mut summary = format!(
            "permutations {} skipped {} unique_sources {} artifacts {}\n",
            report.stats.permutations, report.stats.skipped, report.stats.unique_sources, report.stats.artifacts
        );
        for d in &report.dead_dimensions {
            summary += &format!("dead {} @{} {}\n", d.shader, d.level, d.dimension);
        }
        let mut groups: BTreeMap<Vec<(Target, u32)>, usize> = BTreeMap::new();
        for p in archive.permutations().unwrap() {
            let blobs: Vec<(Target, u32)> = p.targets().map(|t| (t, p.blob_id(t).unwrap().0)).collect();
            let n = groups.len();
            let group = *groups.entry(blobs).or_insert(n);
            summary += &format!("{} -> output set {group}\n", p.name());
            let base = file_name(p.name());
            for t in p.targets() {
                let ext = t.extension(p.shader().stage);
                snapshots.check(
                    out_root.join(t.name()).join(&set).join(format!("{base}.{ext}")),
                    &p.artifact(t).unwrap().unwrap(),
                );
            }
            let mut json = serde_json::to_string_pretty(p.reflection()).unwrap();
            json.push('\n');
            snapshots.check(out_root.join("reflection").join(&set).join(format!("{base}.json")), json.as_bytes());
        }
        snapshots.check(out_root.join("summary").join(format!("{set}.txt")), summary.as_bytes());
        snapshots.stale(&out_root, &set);
        checked += validate_archive(&archive_path);
    }
    assert!(checked > 0);
    assert!(snapshots.mismatches.is_empty(), "snapshot differences:\n{}", snapshots.mismatches.join("\n"));
}

#[test]
fn file_names_are_plain() {
    assert_eq!(file_name("LitPS@es3_1{USE_FOG=1,BLEND=MASKED}"), "LitPS.es3_1.USE_FOG-1.BLEND-MASKED");
    assert_eq!(file_name("Plain@sm5{}"), "Plain.sm5");
}
