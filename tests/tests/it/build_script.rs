//! `kiln::Build`, the build-script API: the archive in the output folder, the `cargo:`
//! lines, and failures rendered with their locations.

use crate::build_support::*;
use kiln::archive::Archive;
use kiln::Build;

#[test]
fn writes_the_archive_and_cargo_lines() {
    let fx = fixture();
    let out_dir = fx.path().join("out");
    let mut lines = Vec::new();
    let archive = Build::new(fx.path().join("lit.toml"))
        .out_dir(&out_dir)
        .cache_dir(fx.path().join("cache"))
        .run_with_output(&mut lines)
        .unwrap();
    assert_eq!(archive, out_dir.join("shaders.kpak"));
    assert_eq!(Archive::open(&archive).unwrap().permutations().unwrap().count(), 28);
    let text = String::from_utf8(lines).unwrap();
    let dir = fx.path().canonicalize().unwrap();
    let expected = format!(
        "cargo:rerun-if-changed={config}
cargo:rerun-if-env-changed=KILN_CACHE_DIR
cargo:rerun-if-changed={d}/include/common.ush
cargo:rerun-if-changed={d}/include/fog.ush
cargo:rerun-if-changed={d}/lit.usf
cargo:warning=warning: dimension `DEBUG_VIEW` of `LitVS` never changes the shader's text at level `sm5`: its 2 values multiply the permutations for nothing
cargo:warning=warning: dimension `DEBUG_VIEW` of `LitVS` never changes the shader's text at level `es3_1`: its 2 values multiply the permutations for nothing
",
        config = fx.path().join("lit.toml").display(),
        d = dir.display()
    );
    assert_eq!(text, expected);
}

#[test]
fn failures_are_rendered_for_cargo() {
    let fx = fixture();
    let usf = fx.path().join("histogram.usf");
    let text = std::fs::read_to_string(&usf).unwrap();
    std::fs::write(&usf, text.replace("#define BINS 64", "#define BINS 64u\n#error no")).unwrap();
    let mut lines = Vec::new();
    let err = Build::new(fx.path().join("compute.toml"))
        .out_dir(fx.path().join("out"))
        .no_cache()
        .run_with_output(&mut lines)
        .unwrap_err();
    assert_eq!(err.code, 1);
    assert!(err.message.starts_with("error: #error no\n  ┌─ histogram.usf:5:1\n"), "{}", err.message);
    assert!(err.message.contains("= in 2 permutations (level `sm5`, default limits):"), "{}", err.message);
    assert!(
        err.message.ends_with(&format!(
            "error: 4 of 4 shader permutations failed ({})",
            fx.path().join("compute.toml").display()
        )),
        "{}",
        err.message
    );
    // Cargo must rerun the script when the broken file is fixed.
    let text = String::from_utf8(lines).unwrap();
    assert!(text.contains(&format!("cargo:rerun-if-changed={}\n", usf.canonicalize().unwrap().display())), "{text}");
    assert!(!fx.path().join("out/shaders.kpak").exists());
}

#[test]
fn without_an_output_folder_it_says_what_to_call() {
    let err = Build::new("permutations.toml").cargo_output(false).run().unwrap_err();
    assert_eq!(err.code, 2);
    assert!(err.message.contains("call .out_dir_from_env()"), "{}", err.message);
}
