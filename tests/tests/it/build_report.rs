//! What a build reports: counts, filters, dead dimensions, and failures that do not stop
//! the other permutations.

use crate::build_support::*;
use kiln::archive::{Archive, Target};
use kiln::build;

#[test]
fn counts_and_dead_dimensions() {
    let fx = fixture();
    let r = build_ok(&options(&fx.path().join("lit.toml"), &fx.path().join("a.kpak"), None));
    assert_eq!(r.stats.permutations, 28);
    assert_eq!(r.stats.skipped, 4);
    assert_eq!(r.stats.unique_sources, 24);
    assert_eq!(r.stats.failed, 0);
    let dead: Vec<(String, String, String)> =
        r.dead_dimensions.iter().map(|d| (d.shader.clone(), d.level.clone(), d.dimension.clone())).collect();
    assert_eq!(
        dead,
        vec![
            ("LitVS".to_string(), "sm5".to_string(), "DEBUG_VIEW".to_string()),
            ("LitVS".to_string(), "es3_1".to_string(), "DEBUG_VIEW".to_string()),
        ]
    );
    assert!(r.warnings.contains(&"warning: dimension `DEBUG_VIEW` of `LitVS` never changes the shader's text at level `sm5`: its 2 values multiply the permutations for nothing".to_string()), "{:?}", r.warnings);
    assert_eq!(
        r.summary().split(" in ").next().unwrap(),
        "28 permutations (4 skipped), 24 distinct, 24 compiled, 0 cache hits, 0 failed"
    );
    // Files read: the config and every source and header.
    let names: Vec<String> =
        r.files_read.iter().map(|p| p.file_name().unwrap().to_string_lossy().into_owned()).collect();
    assert_eq!(names, vec!["common.ush", "fog.ush", "lit.toml", "lit.usf"]);
}

#[test]
fn level_and_target_filters() {
    let fx = fixture();
    let out = fx.path().join("a.kpak");
    let mut opts = options(&fx.path().join("lit.toml"), &out, None);
    opts.levels = vec!["es3_1".into()];
    opts.targets = vec![Target::Spirv, Target::Hlsl];
    let r = build_ok(&opts);
    assert_eq!(r.stats.permutations, 14);
    assert_eq!(r.stats.skipped, 2);
    assert_eq!(r.stats.unique_sources, 12);
    let a = Archive::open(&out).unwrap();
    for p in a.permutations().unwrap() {
        assert_eq!(p.shader().level, "es3_1");
        // es3_1 has no hlsl: the filter narrows, never adds.
        assert_eq!(p.targets().collect::<Vec<_>>(), vec![Target::Spirv]);
    }
    assert_eq!(r.stats.permutation_artifacts, 14);

    opts.levels = vec!["es2".into()];
    match build::run(&opts) {
        Err(e @ build::Error::Config(_)) => {
            assert_eq!(e.exit_code(), 2);
            assert!(e.to_string().contains("no level named `es2`"), "{e}");
            assert!(e.to_string().contains("(its levels: sm5, es3_1)"), "{e}");
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn stats_json_has_every_field() {
    let fx = fixture();
    let mut opts = options(&fx.path().join("compute.toml"), &fx.path().join("a.kpak"), Some(&fx.path().join("c")));
    let stats = fx.path().join("stats.json");
    opts.stats_json = Some(stats.clone());
    build_ok(&opts);
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&stats).unwrap()).unwrap();
    assert_eq!(v["permutations"], 4);
    assert_eq!(v["skipped"], 0);
    assert_eq!(v["unique_sources"], 4);
    assert_eq!(v["compiled"], 4);
    assert_eq!(v["cache_hits"], 0);
    assert_eq!(v["failed"], 0);
    assert!(v["artifacts"].as_u64().unwrap() >= 10);
    for k in ["total", "preprocess", "compile"] {
        assert!(v["seconds"][k].as_f64().unwrap() >= 0.0, "{k}");
    }
}

#[test]
fn a_failure_does_not_stop_the_others() {
    let fx = fixture();
    // Break the masked path only: 4 LitPS permutations per level... of which both levels.
    let usf = fx.path().join("lit.usf");
    let text = std::fs::read_to_string(&usf).unwrap();
    std::fs::write(&usf, text.replace("if (albedo.a < 0.5) {", "if (albedo.a < 0.5) { let oops: u32 = 1.5;")).unwrap();
    let out = fx.path().join("a.kpak");
    let stats = fx.path().join("stats.json");
    let mut opts = options(&fx.path().join("lit.toml"), &out, None);
    opts.stats_json = Some(stats.clone());
    match build::run(&opts) {
        Err(build::Error::Failed(r)) => {
            // BLEND=MASKED: USE_FOG x NUM_LIGHTS = 4 permutations per level.
            assert_eq!(r.stats.failed, 8);
            assert_eq!(r.stats.compiled, 24, "every distinct key was still compiled");
            assert!(!out.exists(), "no archive after a failure");
            let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&stats).unwrap()).unwrap();
            assert_eq!(v["failed"], 8);
            let all = r.failures.join("\n");
            for level in ["sm5", "es3_1"] {
                for fog in [0, 1] {
                    for lights in [0, 2] {
                        let name = format!("LitPS@{level}{{USE_FOG={fog},BLEND=MASKED,NUM_LIGHTS={lights}}}");
                        assert!(all.contains(&name), "{name} missing from\n{all}");
                    }
                }
            }
            assert!(all.contains("lit.usf:"), "{all}");
        }
        other => panic!("{other:?}"),
    }
}

/// Builds a one-shader set written into a temporary folder, on one thread.
fn build_files(files: &[(&str, &str)], dims: &str) -> build::Report {
    let dir = tempfile::tempdir().unwrap();
    for (name, text) in files {
        std::fs::write(dir.path().join(name), text).unwrap();
    }
    std::fs::write(
        dir.path().join("set.toml"),
        format!(
            "[compiler]\ninclude = [\".\"]\n[levels.sm5]\ntargets = [\"wgsl\"]\n[[shader]]\nname = \"S\"\nsource = \"main.usf\"\nentry = \"main\"\nstage = \"compute\"\ndimensions = {{ {dims} }}\n"
        ),
    )
    .unwrap();
    let mut opts = options(&dir.path().join("set.toml"), &dir.path().join("a.kpak"), None);
    opts.jobs = Some(1);
    build_ok(&opts)
}

#[test]
fn permutations_differing_only_in_defines_their_files_never_name_are_preprocessed_once() {
    // lit.toml: LitVS's DEBUG_VIEW is named nowhere, so half of LitVS is not preprocessed.
    let fx = fixture();
    let mut opts = options(&fx.path().join("lit.toml"), &fx.path().join("a.kpak"), None);
    opts.jobs = Some(1);
    let r = build_ok(&opts);
    assert_eq!((r.stats.permutations, r.stats.unique_sources, r.stats.preprocessed), (28, 24, 24));

    // B is named only in a header that A=1 includes: with A=0 it cannot matter.
    let r = build_files(
        &[
            ("main.usf", "#if A\n#include \"b.ush\"\n#endif\n@compute @workgroup_size(1) fn main() {}\n"),
            ("b.ush", "#if B\nconst X: u32 = 1u;\n#else\nconst X: u32 = 2u;\n#endif\n"),
        ],
        "A = \"bool\", B = \"bool\"",
    );
    assert_eq!((r.stats.permutations, r.stats.unique_sources, r.stats.preprocessed), (4, 3, 3));
}

#[test]
fn token_pasting_turns_reuse_off() {
    // MODE is named only through `##`: every permutation is preprocessed, and both differ.
    let r = build_files(
        &[(
            "main.usf",
            "#define CAT(a, b) a##b\n#if CAT(MO, DE)\nconst X: u32 = 1u;\n#else\nconst X: u32 = 2u;\n#endif\n@compute @workgroup_size(1) fn main() {}\n",
        )],
        "MODE = \"bool\"",
    );
    assert_eq!((r.stats.permutations, r.stats.unique_sources, r.stats.preprocessed), (2, 2, 2));
    assert!(r.dead_dimensions.is_empty());
}
