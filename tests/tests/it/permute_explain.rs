//! `explain`, deduplication groups and dead dimensions on the `mobile` fixture: these
//! preprocess every permutation.

use std::path::{Path, PathBuf};

use kiln::permute::{self, DeadDimension};
use kiln::preprocess::{self, SourceCache};

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("in/permute").join(name)
}

fn mobile() -> (permute::Config, SourceCache) {
    let config = permute::load(&fixture("mobile/permutations.toml")).unwrap_or_else(|e| panic!("{}", e.render()));
    let cache = SourceCache::new(config.dir.clone());
    (config, cache)
}

#[test]
fn explain_names_defines_rules_files_hash_and_group() {
    let (config, cache) = mobile();
    // The enum value by index; the name comes back canonical.
    let e = kiln::explain::explain(&config, &cache, "Tonemap@es3_1{BLEND_MODE=0,DEBUG_VIEW=1,GRAIN=0}").unwrap();
    // What the permutation must preprocess to, written out by hand (spacing does not matter).
    let expected_tokens = "
        const MAX_LIGHTS: u32 = 4u;
        fn saturate(x: f32) -> f32 { return clamp(x, 0.0, 1.0); }
        @fragment
        fn main(@location(0) uv: vec2<f32>) -> @location(0) vec4<f32> {
            var c = vec3<f32>(uv, 1.0);
            return vec4<f32>(saturate(c.x), c.yz, 1.0);
        }";
    let hash = preprocess::token_hash(expected_tokens);
    assert_eq!(
        e.text,
        format!(
            "Tonemap@es3_1{{BLEND_MODE=OPAQUE,DEBUG_VIEW=1,GRAIN=0}}
  shader:  Tonemap (fragment, entry main)
  source:  Private/Tonemap.usf (src/Private/Tonemap.usf)
  level:   es3_1 (targets: glsl, spirv, msl, wgsl; limits: downlevel)
  status:  kept

defines:
  FEATURE_LEVEL          = 3  level es3_1
  ES3_1_PROFILE          = 1  level es3_1
  BLEND_MODE             = 0  dimension
  BLEND_MODE_OPAQUE      = 0  enum value of BLEND_MODE
  BLEND_MODE_MASKED      = 1  enum value of BLEND_MODE
  BLEND_MODE_TRANSLUCENT = 2  enum value of BLEND_MODE
  DEBUG_VIEW             = 1  dimension
  GRAIN                  = 0  dimension

skip rules:
  1. BLEND_MODE == BLEND_MODE_TRANSLUCENT && GRAIN > 0: does not match (no grain on translucent overlays)

files read:
  src/Private/Tonemap.usf
  src/Private/Common.ush

token hash: {}
dedup group: 4 kept permutation(s) of Tonemap@es3_1 have this token stream and compile once:
  Tonemap@es3_1{{BLEND_MODE=OPAQUE,DEBUG_VIEW=0,GRAIN=0}}
  Tonemap@es3_1{{BLEND_MODE=OPAQUE,DEBUG_VIEW=1,GRAIN=0}}  (this one)
  Tonemap@es3_1{{BLEND_MODE=TRANSLUCENT,DEBUG_VIEW=0,GRAIN=0}}
  Tonemap@es3_1{{BLEND_MODE=TRANSLUCENT,DEBUG_VIEW=1,GRAIN=0}}
compacted module: shared with no permutation of another token stream
",
            hash.to_hex()
        )
    );
    assert_eq!(e.hash, Some(hash));
    assert!(e.kept && e.error.is_none());
}

#[test]
fn explain_a_skipped_permutation_with_derived_defines() {
    let (config, cache) = mobile();
    let e = kiln::explain::explain(
        &config,
        &cache,
        "MobileBasePassPS@es3_1{USE_VERTEX_FOG=1,FULLY_ROUGH=1,MAX_DYNAMIC_POINT_LIGHTS=2,DEFERRED_SHADING_PATH=1}",
    )
    .unwrap();
    let head: Vec<&str> = e.text.lines().take(20).collect();
    assert_eq!(
        head,
        [
            "MobileBasePassPS@es3_1{FULLY_ROUGH=1,MAX_DYNAMIC_POINT_LIGHTS=2,USE_VERTEX_FOG=1,DEFERRED_SHADING_PATH=1}",
            "  shader:  MobileBasePassPS (fragment, entry main_ps)",
            "  source:  /Engine/Private/MobileBasePassPixelShader.usf (src/Private/MobileBasePassPixelShader.usf)",
            "  level:   es3_1 (targets: glsl, spirv, msl, wgsl; limits: downlevel)",
            "  status:  skipped by rule 1 (deferred lights run in their own pass): not built",
            "",
            "defines:",
            "  FEATURE_LEVEL            = 3  level es3_1",
            "  ES3_1_PROFILE            = 1  level es3_1",
            "  MATERIAL_TWOSIDED        = 0  shader",
            "  FULLY_ROUGH              = 1  dimension",
            "  MAX_DYNAMIC_POINT_LIGHTS = 2  dimension",
            "  USE_VERTEX_FOG           = 1  dimension",
            "  DEFERRED_SHADING_PATH    = 1  dimension",
            "  PACK_INTERPOLANTS        = 1  derived: USE_VERTEX_FOG && ES3_1_PROFILE",
            "",
            "skip rules:",
            "  1. DEFERRED_SHADING_PATH && MAX_DYNAMIC_POINT_LIGHTS > 0: matches (deferred lights run in their own pass)",
            "",
            "files read:",
        ]
    );
    assert_eq!(e.files, ["src/Private/MobileBasePassPixelShader.usf", "src/Private/Common.ush"]);
    // Skipped, but with deferred shading the light count does not change the text: it has the
    // stream of the two kept permutations with no lights (FULLY_ROUGH does not matter either).
    let twins = [
        "MobileBasePassPS@es3_1{FULLY_ROUGH=0,MAX_DYNAMIC_POINT_LIGHTS=0,USE_VERTEX_FOG=1,DEFERRED_SHADING_PATH=1}",
        "MobileBasePassPS@es3_1{FULLY_ROUGH=1,MAX_DYNAMIC_POINT_LIGHTS=0,USE_VERTEX_FOG=1,DEFERRED_SHADING_PATH=1}",
    ];
    assert_eq!(e.group, twins);
    assert!(
        e.text.ends_with(&format!(
            "dedup group: 2 kept permutation(s) of MobileBasePassPS@es3_1 have this token stream and compile once:\n  {}\n  {}\ncompacted module: (none: not built)\n",
            twins[0], twins[1]
        )),
        "{}",
        e.text
    );
    let twin = kiln::explain::explain(&config, &cache, twins[1]).unwrap();
    assert_eq!(twin.group, twins);
    assert_eq!(twin.hash, e.hash);
    let forward = kiln::explain::explain(
        &config,
        &cache,
        "MobileBasePassPS@es3_1{FULLY_ROUGH=1,MAX_DYNAMIC_POINT_LIGHTS=2,USE_VERTEX_FOG=1,DEFERRED_SHADING_PATH=0}",
    )
    .unwrap();
    assert!(
        forward
            .text
            .ends_with("dedup group: no other kept permutation of MobileBasePassPS@es3_1 has this token stream\ncompacted module: shared with no permutation of another token stream\n"),
        "{}",
        forward.text
    );
}

#[test]
fn explain_unknown_name_lists_the_closest() {
    let (config, cache) = mobile();
    let e =
        kiln::explain::explain(&config, &cache, "Tonemap@es3_1{BLEND_MODE=ADDITIVE,DEBUG_VIEW=1,GRAIN=0}").unwrap_err();
    assert_eq!(
        e.render(),
        "error: no permutation named `Tonemap@es3_1{BLEND_MODE=ADDITIVE,DEBUG_VIEW=1,GRAIN=0}`
  = `ADDITIVE` is not a value of dimension `BLEND_MODE` (enum [OPAQUE, MASKED, TRANSLUCENT])
closest permutations:
  Tonemap@es3_1{BLEND_MODE=OPAQUE,DEBUG_VIEW=1,GRAIN=0}  (BLEND_MODE: ADDITIVE -> OPAQUE)
  Tonemap@es3_1{BLEND_MODE=MASKED,DEBUG_VIEW=1,GRAIN=0}  (BLEND_MODE: ADDITIVE -> MASKED)
  Tonemap@es3_1{BLEND_MODE=TRANSLUCENT,DEBUG_VIEW=1,GRAIN=0}  (BLEND_MODE: ADDITIVE -> TRANSLUCENT)
  Tonemap@es3_1{BLEND_MODE=OPAQUE,DEBUG_VIEW=0,GRAIN=0}  (BLEND_MODE: ADDITIVE -> OPAQUE, DEBUG_VIEW: 1 -> 0)
  Tonemap@es3_1{BLEND_MODE=OPAQUE,DEBUG_VIEW=1,GRAIN=1}  (BLEND_MODE: ADDITIVE -> OPAQUE, GRAIN: 0 -> 1)
"
    );
}

#[test]
fn distinct_streams_and_dead_dimensions() {
    let (config, cache) = mobile();
    let analysis = permute::analyze(&config, &cache, |_, _| true);
    assert!(analysis.failed.is_empty(), "{}", analysis.failed[0].error);
    let distinct: Vec<(&str, &str, usize, usize)> = analysis
        .levels
        .iter()
        .map(|l| (l.shader.as_str(), l.level.as_str(), l.permutations.len(), l.distinct))
        .collect();
    // MobileBasePassPS: 16 forward streams (rough x lights x fog) + 2 deferred (fog); FULLY_ROUGH
    // and the light count do not change the deferred text. Tonemap: OPAQUE and TRANSLUCENT
    // share text, DEBUG_VIEW is never read: 2 at GRAIN=0, 2 each at GRAIN=1 and 2.
    assert_eq!(
        distinct,
        [("MobileBasePassPS", "es3_1", 20, 18), ("Tonemap", "sm5", 14, 6), ("Tonemap", "es3_1", 14, 6)]
    );
    let dead = permute::dead_dimensions(&config, &cache);
    assert_eq!(
        dead,
        [
            DeadDimension {
                shader: "Tonemap".into(),
                level: "sm5".into(),
                dimension: "DEBUG_VIEW".into(),
                multiplier: 2
            },
            DeadDimension {
                shader: "Tonemap".into(),
                level: "es3_1".into(),
                dimension: "DEBUG_VIEW".into(),
                multiplier: 2
            },
        ]
    );
    assert_eq!(
        dead[0].to_string(),
        "dimension `DEBUG_VIEW` of `Tonemap@sm5` never changes the preprocessed text: it multiplies the permutations by 2 for nothing"
    );
    // Each file was read once for all 48 permutations.
    assert_eq!(cache.len(), 3);
}
