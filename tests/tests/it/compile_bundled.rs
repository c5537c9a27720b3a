//! The bundled permutation set (`permutations.toml` and `shader_src/` at the workspace
//! root, which the runtime embeds): it builds, and every artifact passes `spirv-val`
//! (SPIR-V), `glslangValidator` (GLSL, and HLSL through its HLSL front end) and naga (WGSL).
//! MSL has no compiler here. `KILN_BUNDLED_CONFIG` points the test at another set.

use std::path::PathBuf;

use crate::build_support::*;

#[test]
fn bundled_set_builds_and_every_artifact_validates() {
    let config = std::env::var_os("KILN_BUNDLED_CONFIG")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../permutations.toml")));
    assert!(config.is_file(), "the bundled permutation set {} is missing", config.display());
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("shaders.kpak");
    let mut opts = options(&config, &out, None);
    opts.emit_dir = Some(tmp.path().join("emit"));
    let report = build_ok(&opts);
    assert!(report.stats.permutations > 0);
    assert_eq!(report.stats.failed, 0);
    let checked = validate_archive(&out);
    assert_eq!(checked, report.stats.artifacts);
    // The loose files are the archive's: one per distinct artifact, plus the index.
    assert_eq!(std::fs::read_dir(tmp.path().join("emit")).unwrap().count(), report.stats.artifacts + 1);
}
