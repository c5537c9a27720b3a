//! The example depends on the thin runtime only: `cargo tree` (offline, `--locked`) of its
//! normal dependencies, and of kiln-runtime's, holds no bundled renderer, no compiler, no PNG
//! or CLI crate of the runtime's, and kiln-runtime has no build script (the bundled archive is compiled and
//! embedded by the renderer's `build.rs`).

use std::path::Path;
use std::process::Command;

fn cargo() -> Command {
    Command::new(std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into()))
}

fn manifest() -> &'static Path {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/Cargo.toml"))
}

/// `name version` of every package in the tree of `package` over the edge `kinds`.
fn tree(package: &str, kinds: &str) -> Vec<String> {
    let o = cargo()
        .args(["tree", "--offline", "--locked", "--manifest-path"])
        .arg(manifest())
        .args(["-p", package, "-e", kinds, "--prefix", "none", "--format", "{p}"])
        .output()
        .expect("cargo runs");
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "cargo tree -p {package} -e {kinds} failed:\n{stderr}");
    String::from_utf8_lossy(&o.stdout).lines().map(|l| l.trim_end_matches(" (*)").to_string()).collect()
}

fn crate_names(lines: &[String]) -> Vec<&str> {
    lines.iter().filter_map(|l| l.split_whitespace().next()).collect()
}

#[test]
fn the_runtime_pulls_in_no_renderer_png_cli_or_bundled_archive() {
    let lines = tree("kiln-runtime", "normal");
    let names = crate_names(&lines);
    assert_eq!(names.first(), Some(&"kiln-runtime"), "{lines:#?}");
    assert!(names.contains(&"wgpu"), "the tree looks wrong: {lines:#?}");
    // No compiler either: the archive is read through `kiln-archive`, whose writer (zstd's
    // dictionary builder, rayon) stays behind its feature.
    assert!(names.contains(&"kiln-archive"), "{lines:#?}");
    for unwanted in ["kiln-renderer", "kiln", "png", "clap", "glam", "rayon", "toml", "redis", "ureq"] {
        assert!(!names.contains(&unwanted), "kiln-runtime depends on `{unwanted}`:\n{}", lines.join("\n"));
    }
    // No build-dependencies (the bundled archive is compiled by kiln-renderer's build.rs).
    let build = tree("kiln-runtime", "build");
    assert_eq!(crate_names(&build), ["kiln-runtime"], "kiln-runtime has build-dependencies:\n{}", build.join("\n"));
}

#[test]
fn the_example_depends_on_the_thin_runtime_only() {
    let lines = tree("kiln-example-hello", "normal");
    let names = crate_names(&lines);
    assert!(names.contains(&"kiln-runtime"), "{lines:#?}");
    for unwanted in ["kiln-renderer", "clap", "glam"] {
        assert!(!names.contains(&unwanted), "the example depends on `{unwanted}`:\n{}", lines.join("\n"));
    }
}

#[test]
fn the_runtime_package_has_no_build_script() {
    let o = cargo()
        .args(["metadata", "--offline", "--locked", "--no-deps", "--format-version", "1", "--manifest-path"])
        .arg(manifest())
        .output()
        .expect("cargo runs");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let metadata: serde_json::Value = serde_json::from_slice(&o.stdout).expect("cargo metadata gives JSON");
    let packages = metadata["packages"].as_array().expect("packages");
    let runtime = packages.iter().find(|p| p["name"] == "kiln-runtime").expect("kiln-runtime in the workspace");
    let kinds: Vec<&serde_json::Value> =
        runtime["targets"].as_array().expect("targets").iter().flat_map(|t| t["kind"].as_array().unwrap()).collect();
    assert!(kinds.iter().any(|k| *k == "lib"), "no lib target: {kinds:?}");
    assert!(!kinds.iter().any(|k| *k == "custom-build"), "kiln-runtime has a build script: {kinds:?}");
}
