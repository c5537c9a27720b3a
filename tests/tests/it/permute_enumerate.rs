//! Enumeration of a permutation set checked against an independent enumeration written out by
//! hand (nested loops and the skip rules as Rust closures).

use std::path::{Path, PathBuf};

use kiln::permute::{self, Count, Permutation};

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("in/permute").join(name)
}

#[test]
fn mobile_fixture_counts_match_an_independent_enumeration() {
    let config = permute::load(&fixture("mobile/permutations.toml")).unwrap_or_else(|e| panic!("{}", e.render()));

    // MobileBasePassPS at es3_1.
    let mut expected = Vec::new();
    for rough in [0, 1] {
        for lights in [0, 1, 2, 4] {
            for fog in [0, 1] {
                for deferred in [0, 1] {
                    let skipped = deferred != 0 && lights > 0;
                    let name = format!(
                        "MobileBasePassPS@es3_1{{FULLY_ROUGH={rough},MAX_DYNAMIC_POINT_LIGHTS={lights},USE_VERTEX_FOG={fog},DEFERRED_SHADING_PATH={deferred}}}"
                    );
                    expected.push((name, !skipped, fog)); // PACK_INTERPOLANTS = fog && ES3_1_PROFILE
                }
            }
        }
    }
    // Tonemap at both levels (sm5 first: file order of its levels, which it leaves out).
    for level in ["sm5", "es3_1"] {
        for (blend, label) in ["OPAQUE", "MASKED", "TRANSLUCENT"].iter().enumerate() {
            for debug in [0, 1] {
                for grain in 0..=2 {
                    let skipped = blend == 2 && grain > 0;
                    expected.push((
                        format!("Tonemap@{level}{{BLEND_MODE={label},DEBUG_VIEW={debug},GRAIN={grain}}}"),
                        !skipped,
                        -1,
                    ));
                }
            }
        }
    }

    let got: Vec<(String, bool, i64)> = config
        .permutations()
        .map(|p| {
            let packed = p.defines().iter().find(|d| d.name == "PACK_INTERPOLANTS").map_or(-1, |d| d.value);
            (p.name(), p.is_kept(), packed)
        })
        .collect();
    assert_eq!(got, expected);
    assert_eq!(
        config.counts(),
        vec![
            Count { shader: "MobileBasePassPS".into(), level: "es3_1".into(), kept: 20, skipped: 12 },
            Count { shader: "Tonemap".into(), level: "sm5".into(), kept: 14, skipped: 4 },
            Count { shader: "Tonemap".into(), level: "es3_1".into(), kept: 14, skipped: 4 },
        ]
    );
}

#[test]
fn every_name_round_trips_through_find() {
    let config = permute::load(&fixture("mobile/permutations.toml")).unwrap();
    for p in config.permutations() {
        let found = config.find(&p.name()).unwrap();
        assert_eq!(found, p);
    }
}

/// A generated set: several shaders, enum/range/list/bool dimensions and skip rules written
/// both as `#if` expressions and as Rust predicates.
#[test]
fn generated_set_matches_brute_force() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("src")).unwrap();
    std::fs::write(dir.path().join("src/S.usf"), "fn f() {}\n").unwrap();
    // (A, B, C, D, ES) -> skipped
    type Rule = fn(i64, i64, i64, i64, i64) -> bool;
    let rules: [(&str, Rule); 4] = [
        ("A == MODE_HIGH && B > 2", |a, b, _, _, _| a == 2 && b > 2),
        ("(C % 3 == 0) && !ES", |_, _, c, _, es| c % 3 == 0 && es == 0),
        ("D < 0 ? B == 1 : B == 4", |_, b, _, d, _| if d < 0 { b == 1 } else { b == 4 }),
        ("defined(ES) && A + D == 0", |a, _, _, d, es| es == 1 && a + d == 0),
    ];
    let mut toml = String::from("[compiler]\ninclude = [\"src\"]\n[levels.desk]\ndefines = { LEVEL = 5 }\n[levels.mob]\ndefines = { LEVEL = 3, ES = 1 }\n");
    for (i, (when, _)) in rules.iter().enumerate() {
        toml.push_str(&format!(
            "[[shader]]\nname = \"S{i}\"\nsource = \"S.usf\"\nstage = \"compute\"\ndimensions = {{ A = {{ enum = [\"LOW\", \"MID\", \"HIGH\"] }}, B = [1, 2, 4], C = {{ range = [0, 5] }}, D = [-1, 0, 1] }}\nskip = [{{ when = \"{when}\", why = \"rule {i}\" }}]\n"
        ));
    }
    std::fs::write(dir.path().join("permutations.toml"), &toml).unwrap();
    let config = permute::load(&dir.path().join("permutations.toml")).unwrap_or_else(|e| panic!("{}", e.render()));

    let mut expected = Vec::new();
    for (i, (_, rule)) in rules.iter().enumerate() {
        for (level, es) in [("desk", 0), ("mob", 1)] {
            let (mut kept, mut skipped) = (0, 0);
            for a in 0..3 {
                for b in [1, 2, 4] {
                    for c in 0..=5 {
                        for d in [-1, 0, 1] {
                            if rule(a, b, c, d, es) {
                                skipped += 1;
                            } else {
                                kept += 1;
                            }
                        }
                    }
                }
            }
            expected.push(Count { shader: format!("S{i}"), level: level.into(), kept, skipped });
        }
    }
    assert_eq!(config.counts(), expected);
    let kept: usize = config.permutations().filter(Permutation::is_kept).count();
    assert_eq!(kept, expected.iter().map(|c| c.kept).sum::<usize>());
}
