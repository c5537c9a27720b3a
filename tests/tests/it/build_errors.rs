//! Failures rendered on the original files: header, line, column, include chain, macro,
//! and the permutation's canonical name and level. Compared as whole rendered text.

use crate::build_support::*;
use kiln::build;

/// Builds lit.toml after `edit` changed the fixture; returns every rendered failure.
fn failures(edit: impl FnOnce(&std::path::Path)) -> (build::Report, String) {
    let fx = fixture();
    edit(fx.path());
    let out = fx.path().join("a.kpak");
    match build::run(&options(&fx.path().join("lit.toml"), &out, None)) {
        Err(build::Error::Failed(r)) => {
            assert!(!out.exists());
            let text = r.failures.join("\n");
            (*r, text)
        }
        Ok(_) => panic!("the build succeeded"),
        Err(e) => panic!("{e}"),
    }
}

fn replace(path: &std::path::Path, from: &str, to: &str) {
    let text = std::fs::read_to_string(path).unwrap();
    assert!(text.contains(from), "{from:?} not in {}", path.display());
    std::fs::write(path, text.replacen(from, to, 1)).unwrap();
}

#[test]
fn error_in_an_included_header_under_one_permutation() {
    let (report, text) = failures(|dir| {
        replace(
            &dir.join("include/fog.ush"),
            "    let d = distance(world, camera);\n",
            "    let d = distance(world, camera);\n#if FEATURE_LEVEL == 3 && NUM_LIGHTS == 2 && BLEND == BLEND_MASKED\n    let broken: u32 = d;\n#endif\n",
        )
    });
    assert_eq!(report.stats.failed, 1);
    assert_eq!(report.stats.compiled, 24, "the other permutations still compiled");
    assert_eq!(
        text,
        r#"error: the type of `broken` is expected to be `u32`, but got `f32`
   ┌─ include/fog.ush:10:9
   │
10 │     let broken: u32 = d;
   │         ^^^^^^ definition of `broken`
   │
   ┌─ lit.usf:4:1
   │
 4 │ #include "fog.ush"
   │ ------------------ included from here
   │
   = in permutation LitPS@es3_1{USE_FOG=1,BLEND=MASKED,NUM_LIGHTS=2} (level `es3_1`, downlevel limits)

"#
    );
}

#[test]
fn one_error_in_many_permutations_is_reported_once_naming_them_all() {
    let (report, text) = failures(|dir| {
        replace(&dir.join("include/fog.ush"), "return SATURATE(", "return SATURATE(camera + ");
    });
    // Every USE_FOG=1 key fails at both levels: 12 keys, 14 permutations (DEBUG_VIEW).
    assert_eq!(report.stats.failed, 14);
    assert_eq!(report.failures.len(), 2, "one diagnostic per level:\n{text}");
    let es = &report.failures[1];
    assert!(es.contains("┌─ include/fog.ush:"), "{es}");
    assert!(
        es.ends_with(
            "   = in 7 permutations (level `es3_1`, downlevel limits):
       LitVS@es3_1{USE_FOG=1,DEBUG_VIEW=0}
       LitVS@es3_1{USE_FOG=1,DEBUG_VIEW=1}
       LitPS@es3_1{USE_FOG=1,BLEND=OPAQUE,NUM_LIGHTS=0}
       LitPS@es3_1{USE_FOG=1,BLEND=OPAQUE,NUM_LIGHTS=2}
       LitPS@es3_1{USE_FOG=1,BLEND=MASKED,NUM_LIGHTS=0}
       LitPS@es3_1{USE_FOG=1,BLEND=MASKED,NUM_LIGHTS=2}
       LitPS@es3_1{USE_FOG=1,BLEND=TRANSLUCENT,NUM_LIGHTS=2}

"
        ),
        "{es}"
    );
}

#[test]
fn preprocessor_error_names_the_permutation() {
    let (report, text) = failures(|dir| {
        replace(
            &dir.join("include/fog.ush"),
            "#pragma once\n",
            "#pragma once\n#if ES3_1_PROFILE && !defined(BLEND)\n#error fog needs a blend mode on mobile\n#endif\n",
        )
    });
    assert_eq!(report.stats.failed, 2);
    assert_eq!(
        text,
        r#"error: #error fog needs a blend mode on mobile
  ┌─ include/fog.ush:4:1
  │
4 │ #error fog needs a blend mode on mobile
  │ ^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^
  │
  ┌─ lit.usf:4:1
  │
4 │ #include "fog.ush"
  │ ------------------ included from here
  │
  = in 2 permutations (level `es3_1`, downlevel limits):
      LitVS@es3_1{USE_FOG=1,DEBUG_VIEW=0}
      LitVS@es3_1{USE_FOG=1,DEBUG_VIEW=1}

"#
    );
}

#[test]
fn downlevel_limit_names_the_binding_and_the_limit() {
    let (report, text) = failures(|dir| {
        replace(
            &dir.join("include/common.ush"),
            "@group(0) @binding(0) var<uniform> view: View;\n",
            "@group(0) @binding(0) var<uniform> view: View;\n@group(0) @binding(1) var<storage, read> skin: array<mat4x4<f32>>;\n",
        );
        replace(&dir.join("lit.usf"), "let world = (view.model *", "let world = (skin[0] * view.model *");
    });
    // Only the es3_1 vertex shaders: 2 keys, 4 permutations.
    assert_eq!(report.stats.failed, 4);
    assert_eq!(
        text,
        r#"error: binding `skin` is a storage buffer in a vertex shader, which the downlevel limits do not allow
   ┌─ include/common.ush:10:23
   │
10 │ @group(0) @binding(1) var<storage, read> skin: array<mat4x4<f32>>;
   │                       ^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^ used by the vertex entry point
   │
   ┌─ lit.usf:2:1
   │
 2 │ #include "common.ush"
   │ --------------------- included from here
   │
   = GLES 3.1 has no storage buffers or storage textures in vertex shaders (wgpu's VERTEX_STORAGE downlevel flag)
   = in 4 permutations (level `es3_1`, downlevel limits):
       LitVS@es3_1{USE_FOG=0,DEBUG_VIEW=0}
       LitVS@es3_1{USE_FOG=0,DEBUG_VIEW=1}
       LitVS@es3_1{USE_FOG=1,DEBUG_VIEW=0}
       LitVS@es3_1{USE_FOG=1,DEBUG_VIEW=1}

"#
    );
}

#[test]
fn missing_entry_point_names_the_shader_and_its_source() {
    let fx = fixture();
    replace(&fx.path().join("compute.toml"), "entry = \"main_cs\"", "entry = \"main\"");
    match build::run(&options(&fx.path().join("compute.toml"), &fx.path().join("a.kpak"), None)) {
        Err(build::Error::Failed(r)) => assert_eq!(
            r.failures[0],
            "error: no entry point named `main`
 = the module's entry points: `main_cs` (compute)
 = shader `Histogram` of compute.toml names entry point `main` (compute) in histogram.usf
 = in 2 permutations (level `sm5`, default limits):
     Histogram@sm5{THREADS=6}
     Histogram@sm5{THREADS=7}

"
        ),
        other => panic!("{other:?}"),
    }
}

#[test]
fn members_of_one_key_are_each_reported_at_their_own_lines() {
    // Two permutations with the same tokens and different spacing share one compile; the
    // error is still shown where each one's text is.
    let fx = tempfile::tempdir().unwrap();
    std::fs::write(
        fx.path().join("k.toml"),
        "[compiler]\ninclude = [\".\"]\n[levels.sm5]\ntargets = [\"wgsl\"]\n[[shader]]\nname = \"S\"\nsource = \"s.usf\"\nentry = \"main\"\nstage = \"compute\"\ndimensions = { MODE = \"bool\" }\n",
    )
    .unwrap();
    std::fs::write(
        fx.path().join("s.usf"),
        "#if MODE == 0\nfn f() -> f32 { return 1u; }\n#else\n\n\nfn   f() -> f32 {\n    return 1u;\n}\n#endif\n@compute @workgroup_size(1) fn main() { _ = f(); }\n",
    )
    .unwrap();
    match build::run(&options(&fx.path().join("k.toml"), &fx.path().join("a.kpak"), None)) {
        Err(build::Error::Failed(r)) => {
            assert_eq!((r.stats.unique_sources, r.stats.compiled, r.stats.failed), (1, 1, 2));
            assert_eq!(r.failures.len(), 2, "{:?}", r.failures);
            assert!(r.failures[0].contains("┌─ s.usf:2:1\n"), "{}", r.failures[0]);
            assert!(r.failures[0].contains("2 │ fn f() -> f32 { return 1u; }\n"), "{}", r.failures[0]);
            assert!(r.failures[0].contains("in permutation S@sm5{MODE=0}"), "{}", r.failures[0]);
            assert!(r.failures[1].contains("┌─ s.usf:6:1\n"), "{}", r.failures[1]);
            assert!(r.failures[1].contains("7 │ │     return 1u;\n  │ │            -- "), "{}", r.failures[1]);
            assert!(r.failures[1].contains("in permutation S@sm5{MODE=1}"), "{}", r.failures[1]);
        }
        other => panic!("{other:?}"),
    }
}
