//! The content-hashed cache, seen through builds of `tests/in/lit.toml`.
//!
//! lit.toml has 28 kept permutations and 24 distinct keys: LitVS has 4 permutations per
//! level but DEBUG_VIEW never changes its text (2 keys per level); LitPS has 10 kept
//! permutations per level, all distinct. `USE_FOG = 1` selects 1 LitVS key and 5 LitPS keys
//! per level: 12 keys in all, the ones whose tokens change when `fog.ush` changes.

use std::path::{Path, PathBuf};

use crate::build_support::*;
use kiln::build;

const DISTINCT: usize = 24;
const WITH_FOG: usize = 12;

/// Distinct keys held by the cache's packs.
fn entries(cache: &Path) -> usize {
    kiln::cache::Cache::open(cache).unwrap().stats().entries as usize
}

/// The cache's pack files.
fn packs(cache: &Path) -> Vec<PathBuf> {
    let mut out: Vec<PathBuf> = std::fs::read_dir(cache)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "kcp"))
        .collect();
    out.sort();
    out
}

#[test]
fn second_build_compiles_nothing() {
    let fx = fixture();
    let cache = fx.path().join("cache");
    let config = fx.path().join("lit.toml");
    let first = build_ok(&options(&config, &fx.path().join("a.kpak"), Some(&cache)));
    assert_eq!(first.stats.permutations, 28);
    assert_eq!(first.stats.skipped, 4);
    assert_eq!(first.stats.unique_sources, DISTINCT);
    assert_eq!((first.stats.compiled, first.stats.cache_hits), (DISTINCT, 0));
    assert_eq!(entries(&cache), DISTINCT);
    assert_eq!(packs(&cache).len(), 1, "one pack per build");

    let second = build_ok(&options(&config, &fx.path().join("b.kpak"), Some(&cache)));
    assert_eq!((second.stats.compiled, second.stats.cache_hits), (0, DISTINCT));
    assert_eq!(std::fs::read(fx.path().join("a.kpak")).unwrap(), std::fs::read(fx.path().join("b.kpak")).unwrap());
}

#[test]
fn editing_a_header_recompiles_exactly_the_permutations_whose_tokens_changed() {
    let fx = fixture();
    let cache = fx.path().join("cache");
    let config = fx.path().join("lit.toml");
    let out = fx.path().join("shaders.kpak");
    build_ok(&options(&config, &out, Some(&cache)));

    // A comment and spacing change no token: nothing recompiles.
    let fog = fx.path().join("include/fog.ush");
    let text = std::fs::read_to_string(&fog).unwrap();
    std::fs::write(&fog, text.replace("fn FogFactor(", "// reformatted\nfn   FogFactor(\n")).unwrap();
    let r = build_ok(&options(&config, &out, Some(&cache)));
    assert_eq!((r.stats.compiled, r.stats.cache_hits), (0, DISTINCT));

    // A token change in fog.ush: only the USE_FOG=1 keys recompile.
    std::fs::write(&fog, text.replace("FOG_DENSITY: f32 = 0.02", "FOG_DENSITY: f32 = 0.03")).unwrap();
    let r = build_ok(&options(&config, &out, Some(&cache)));
    assert_eq!(r.stats.unique_sources, DISTINCT);
    assert_eq!((r.stats.compiled, r.stats.cache_hits), (WITH_FOG, DISTINCT - WITH_FOG));

    // And back: the old entries are still there.
    std::fs::write(&fog, &text).unwrap();
    let r = build_ok(&options(&config, &out, Some(&cache)));
    assert_eq!((r.stats.compiled, r.stats.cache_hits), (0, DISTINCT));
}

#[test]
fn a_new_header_that_shadows_an_include_is_picked_up() {
    let fx = fixture();
    let cache = fx.path().join("cache");
    let config = fx.path().join("lit.toml");
    let out = fx.path().join("shaders.kpak");
    build_ok(&options(&config, &out, Some(&cache)));
    let r = build_ok(&options(&config, &out, Some(&cache)));
    assert_eq!((r.stats.preprocessed, r.stats.compiled), (0, 0), "nothing changed");

    // `#include "common.ush"` in lit.usf looks beside lit.usf before the include root: a
    // file created there now wins, and every permutation including it is preprocessed again.
    let common = std::fs::read_to_string(fx.path().join("include/common.ush")).unwrap();
    let shadow = common.replace("vec3<f32>(0.03, 0.03, 0.04)", "vec3<f32>(0.5, 0.03, 0.04)");
    assert_ne!(shadow, common);
    std::fs::write(fx.path().join("common.ush"), shadow).unwrap();
    let r = build_ok(&options(&config, &out, Some(&cache)));
    // Every permutation includes it: none is served from its record (some share another
    // permutation's fresh preprocessing, through a dimension that never reaches the text).
    assert!(r.stats.preprocessed >= DISTINCT, "{:?}", r.stats);
    assert!(r.stats.compiled > 0, "the keys whose tokens changed are compiled: {:?}", r.stats);
    let archive = kiln::archive::Archive::open(&out).unwrap();
    let wgsl = archive
        .permutations()
        .unwrap()
        .filter_map(|p| p.artifact(kiln::archive::Target::Wgsl).unwrap())
        .any(|a| String::from_utf8_lossy(&a).contains("0.5"));
    assert!(wgsl, "the shadowing header's ambient reached the archive");
}

#[test]
fn two_builds_at_once_on_one_cache_both_succeed() {
    let fx = fixture();
    let cache = fx.path().join("cache");
    let config = fx.path().join("lit.toml");
    let outs = [fx.path().join("a.kpak"), fx.path().join("b.kpak")];
    let reports: Vec<build::Report> = std::thread::scope(|s| {
        let handles: Vec<_> = outs.iter().map(|o| s.spawn(|| build_ok(&options(&config, o, Some(&cache))))).collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    for r in &reports {
        assert_eq!(r.stats.compiled + r.stats.cache_hits, DISTINCT);
    }
    assert_eq!(std::fs::read(&outs[0]).unwrap(), std::fs::read(&outs[1]).unwrap());
    // Nothing is corrupted or half-written: a third build is served entirely from the cache.
    let third = build_ok(&options(&config, &fx.path().join("c.kpak"), Some(&cache)));
    assert_eq!((third.stats.compiled, third.stats.cache_hits), (0, DISTINCT));
    assert!(third.warnings.iter().all(|w| !w.contains("corrupted")), "{:?}", third.warnings);
    assert_eq!(entries(&cache), DISTINCT);
}

#[test]
fn corrupted_entry_is_reported_and_recompiled() {
    let fx = fixture();
    let cache = fx.path().join("cache");
    let config = fx.path().join("lit.toml");
    build_ok(&options(&config, &fx.path().join("a.kpak"), Some(&cache)));
    // Flip a byte near the end of the pack: inside its last entry.
    let pack = packs(&cache).pop().unwrap();
    let mut bytes = std::fs::read(&pack).unwrap();
    let at = bytes.len() - 10;
    bytes[at] ^= 0x20;
    std::fs::write(&pack, bytes).unwrap();

    let r = build_ok(&options(&config, &fx.path().join("b.kpak"), Some(&cache)));
    assert_eq!((r.stats.compiled, r.stats.cache_hits), (1, DISTINCT - 1));
    let warning = r.warnings.iter().find(|w| w.contains("corrupted")).expect("a warning about the entry");
    // Entries are compressed: the flipped byte fails to decompress, or decompresses to
    // other bytes.
    let ends = ["checksum mismatch", "cannot decompress it"]
        .map(|why| format!(" in {} is corrupted ({why}); recompiling", pack.display()));
    assert!(warning.starts_with("warning: cache entry ") && ends.iter().any(|e| warning.ends_with(e)), "{warning}");
    assert_eq!(std::fs::read(fx.path().join("a.kpak")).unwrap(), std::fs::read(fx.path().join("b.kpak")).unwrap());
    let r = build_ok(&options(&config, &fx.path().join("c.kpak"), Some(&cache)));
    assert_eq!(r.stats.compiled, 0, "the recompiled entry was stored again");
    assert!(r.warnings.iter().all(|w| !w.contains("corrupted")), "{:?}", r.warnings);
}

#[test]
fn interrupted_write_leaves_no_entry_and_does_not_disturb_builds() {
    let fx = fixture();
    let cache = fx.path().join("cache");
    let config = fx.path().join("lit.toml");
    build_ok(&options(&config, &fx.path().join("a.kpak"), Some(&cache)));
    // A writer killed half way leaves only its temporary file: replace the pack by that
    // (named as a live writer's, this process's: a dead one's is removed on open).
    let pack = packs(&cache).pop().unwrap();
    let bytes = std::fs::read(&pack).unwrap();
    std::fs::remove_file(&pack).unwrap();
    let name = pack.file_name().unwrap().to_str().unwrap();
    let tmp = pack.with_file_name(format!(".{name}.{}.1.0.tmp", std::process::id()));
    std::fs::write(&tmp, &bytes[..bytes.len() / 2]).unwrap();
    let stats = kiln::cache::Cache::open(&cache).unwrap().stats();
    assert_eq!((stats.entries, stats.temporaries), (0, 1));

    let r = build_ok(&options(&config, &fx.path().join("b.kpak"), Some(&cache)));
    assert_eq!((r.stats.compiled, r.stats.cache_hits), (DISTINCT, 0));
    assert!(r.warnings.iter().all(|w| !w.contains("corrupted") && !w.contains("damaged")), "{:?}", r.warnings);
    assert_eq!(std::fs::read(fx.path().join("a.kpak")).unwrap(), std::fs::read(fx.path().join("b.kpak")).unwrap());
    assert_eq!(entries(&cache), DISTINCT);
}

#[test]
fn no_cache_compiles_everything_and_writes_no_entry() {
    let fx = fixture();
    let config = fx.path().join("lit.toml");
    let r = build_ok(&options(&config, &fx.path().join("a.kpak"), None));
    assert_eq!((r.stats.compiled, r.stats.cache_hits), (DISTINCT, 0));
    let r = build_ok(&options(&config, &fx.path().join("a.kpak"), None));
    assert_eq!((r.stats.compiled, r.stats.cache_hits), (DISTINCT, 0));
}

#[test]
fn an_up_to_date_archive_is_left_alone_and_a_touched_one_is_rewritten() {
    let fx = fixture();
    let cache = fx.path().join("cache");
    let config = fx.path().join("lit.toml");
    let out = fx.path().join("shaders.kpak");
    build_ok(&options(&config, &out, Some(&cache)));
    let bytes = std::fs::read(&out).unwrap();
    let modified = std::fs::metadata(&out).unwrap().modified().unwrap();

    let r = build_ok(&options(&config, &out, Some(&cache)));
    assert_eq!((r.stats.compiled, r.stats.cache_hits, r.stats.preprocessed), (0, DISTINCT, 0));
    assert_eq!(r.stats.artifacts, 60);
    assert_eq!(std::fs::metadata(&out).unwrap().modified().unwrap(), modified, "not rewritten");

    // Deleted or replaced: written again from the cache.
    std::fs::remove_file(&out).unwrap();
    let r = build_ok(&options(&config, &out, Some(&cache)));
    assert_eq!((r.stats.compiled, r.stats.cache_hits), (0, DISTINCT));
    assert_eq!(std::fs::read(&out).unwrap(), bytes);
    std::fs::write(&out, b"something else").unwrap();
    build_ok(&options(&config, &out, Some(&cache)));
    assert_eq!(std::fs::read(&out).unwrap(), bytes);

    // Other options give another archive.
    let mut opts = options(&config, &out, Some(&cache));
    opts.targets = vec![kiln::archive::Target::Wgsl];
    let r = build_ok(&opts);
    assert_eq!(r.stats.compiled, DISTINCT, "other targets are other keys");
    assert_ne!(std::fs::read(&out).unwrap(), bytes);
}

/// A configuration change keeps the preprocessing records of the permutations it does not
/// touch: a dimension value added preprocesses only the new permutations, a level's define
/// changed preprocesses that level's again (never served a stale record), and the archive
/// is the one a build without a cache writes.
#[test]
fn records_survive_a_configuration_change_that_does_not_touch_them() {
    let fx = fixture();
    let cache = fx.path().join("cache");
    let config = fx.path().join("lit.toml");
    let out = fx.path().join("shaders.kpak");
    build_ok(&options(&config, &out, Some(&cache)));
    let text = std::fs::read_to_string(&config).unwrap();
    let fresh = |name: &str| {
        let path = fx.path().join(name);
        build_ok(&options(&config, &path, None));
        std::fs::read(path).unwrap()
    };

    // NUM_LIGHTS = 4: six more LitPS permutations per level.
    let more = text.replace("NUM_LIGHTS = [0, 2]", "NUM_LIGHTS = [0, 2, 4]");
    assert_ne!(more, text);
    std::fs::write(&config, &more).unwrap();
    let r = build_ok(&options(&config, &out, Some(&cache)));
    assert_eq!(r.stats.permutations, 40);
    assert!((1..=12).contains(&r.stats.preprocessed), "only the new permutations: {:?}", r.stats);
    assert_eq!(std::fs::read(&out).unwrap(), fresh("more.kpak"));

    // A level's define changed: that level's permutations are preprocessed again.
    std::fs::write(&config, more.replace("SM5_PROFILE = 1", "SM5_PROFILE = 2")).unwrap();
    let r = build_ok(&options(&config, &out, Some(&cache)));
    assert!((1..=20).contains(&r.stats.preprocessed), "the sm5 permutations only: {:?}", r.stats);
    assert_eq!(std::fs::read(&out).unwrap(), fresh("define.kpak"));
}
