//! `kiln inspect` as a user runs it: the summary with raw and compressed sizes, `--list`,
//! one artifact's bytes (checked by `spirv-val` and `glslangValidator`), one permutation's
//! reflection, unknown names, damaged and foreign files, and paths that are not files.

use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

fn kiln(dir: &Path, args: &[&str]) -> Output {
    crate::kiln_command().args(args).current_dir(dir).output().unwrap()
}

/// Runs `kiln` and fails the test if it has not exited within a minute: a guard against a
/// hang (a FIFO opened for reading waits for a writer forever), not a measure of speed.
fn kiln_no_hang(dir: &Path, args: &[&str]) -> Output {
    let mut child = crate::kiln_command()
        .args(args)
        .current_dir(dir)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let start = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if start.elapsed() > Duration::from_secs(60) {
            let _ = child.kill();
            panic!("kiln {args:?} blocked");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.wait_with_output().unwrap()
}

/// A copy of `tests/in` with `lit.toml` built into `shaders.kpak`.
fn built() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    crate::cli_build::copy(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/in"), dir.path());
    let o = kiln(dir.path(), &["build", "--config", "lit.toml", "--no-cache"]);
    assert!(o.status.success(), "{}", stderr(&o));
    dir
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// Fails (never skips) when a validator is missing, naming the Debian package.
fn require_tool(tool: &str, package: &str) {
    let ok = Command::new(tool).arg("--version").output().map(|o| o.status.success()).unwrap_or(false);
    assert!(ok, "`{tool}` is required by this test: install the Debian package `{package}`");
}

#[test]
fn list_prints_every_permutation_of_the_build() {
    let fx = built();
    let d = fx.path();
    let o = kiln(d, &["inspect", "shaders.kpak", "--list"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let listed: Vec<String> = stdout(&o).lines().map(str::to_string).collect();
    let o = kiln(d, &["list", "--config", "lit.toml", "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let mut expected: Vec<String> = v["permutations"]
        .as_array()
        .expect("kiln list --json gives a list")
        .iter()
        .filter(|p| p["kept"].as_bool() == Some(true))
        .map(|p| p["name"].as_str().unwrap().to_string())
        .collect();
    expected.sort();
    assert_eq!(listed, expected);
    assert!(listed.iter().any(|n| n == "LitPS@es3_1{USE_FOG=1,BLEND=MASKED,NUM_LIGHTS=2}"));
}

#[test]
fn extracted_spirv_and_glsl_pass_the_reference_validators() {
    require_tool("spirv-val", "spirv-tools");
    require_tool("glslangValidator", "glslang-tools");
    let fx = built();
    let d = fx.path();
    let name = "LitPS@es3_1{USE_FOG=1,BLEND=MASKED,NUM_LIGHTS=2}";
    let o = kiln(d, &["inspect", "shaders.kpak", name, "--target", "spirv", "-o", "ps.spv"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v = Command::new("spirv-val").args(["--target-env", "vulkan1.0", "ps.spv"]).current_dir(d).output().unwrap();
    assert!(v.status.success(), "{}{}", stdout(&v), stderr(&v));
    // To stdout: the same bytes.
    let o = kiln(d, &["inspect", "shaders.kpak", name, "--target", "spirv"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(o.stdout, std::fs::read(d.join("ps.spv")).unwrap());
    assert_eq!(&o.stdout[..4], &0x0723_0203u32.to_le_bytes());

    // Enum values by index name the same permutation, dimensions in any order.
    let by_index = "LitPS@es3_1{NUM_LIGHTS=2,BLEND=1,USE_FOG=1}";
    for (target, file) in [("glsl", "ps.frag"), ("glsl", "ps2.frag")] {
        let n = if file == "ps.frag" { name } else { by_index };
        let o = kiln(d, &["inspect", "shaders.kpak", n, "--target", target, "-o", file]);
        assert!(o.status.success(), "{}", stderr(&o));
        let v = Command::new("glslangValidator").arg(file).current_dir(d).output().unwrap();
        assert!(v.status.success(), "{}{}", stdout(&v), stderr(&v));
    }
    assert_eq!(std::fs::read(d.join("ps.frag")).unwrap(), std::fs::read(d.join("ps2.frag")).unwrap());
    let vs = "LitVS@es3_1{USE_FOG=0,DEBUG_VIEW=0}";
    let o = kiln(d, &["inspect", "shaders.kpak", vs, "--target", "glsl", "-o", "vs.vert"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v = Command::new("glslangValidator").arg("vs.vert").current_dir(d).output().unwrap();
    assert!(v.status.success(), "{}{}", stdout(&v), stderr(&v));

    // -o /dev/null is written through, never renamed over.
    let o = kiln(d, &["inspect", "shaders.kpak", name, "--target", "wgsl", "-o", "/dev/null"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(std::os::unix::fs::FileTypeExt::is_char_device(&std::fs::metadata("/dev/null").unwrap().file_type()));

    // A target the permutation lacks, and an unknown target.
    let o = kiln(d, &["inspect", "shaders.kpak", name, "--target", "hlsl"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("has no hlsl artifact (it has: glsl, spirv, msl, wgsl)"), "{}", stderr(&o));
    let o = kiln(d, &["inspect", "shaders.kpak", name, "--target", "dxil"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("unknown target `dxil`"), "{}", stderr(&o));
}

#[test]
fn reflection_shows_bindings_inputs_outputs_and_workgroup_size() {
    let fx = built();
    let d = fx.path();
    let o = kiln(d, &["inspect", "shaders.kpak", "LitVS@sm5{USE_FOG=1,DEBUG_VIEW=0}", "--reflection"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(out.contains("permutation: LitVS@sm5{USE_FOG=1,DEBUG_VIEW=0}"), "{out}");
    assert!(out.contains("entry: vertex `main_vs`"), "{out}");
    assert!(out.contains("bind groups:\n  @group("), "{out}");
    assert!(out.contains("vertex inputs:\n  @location(0) "), "{out}");
    let o = kiln(d, &["inspect", "shaders.kpak", "LitPS@sm5{USE_FOG=0,BLEND=OPAQUE,NUM_LIGHTS=0}", "--reflection"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("color outputs:\n  @location(0): vec4<f32>"), "{}", stdout(&o));
    let o = kiln(
        d,
        &["inspect", "shaders.kpak", "LitPS@sm5{USE_FOG=0,BLEND=OPAQUE,NUM_LIGHTS=0}", "--reflection", "--json"],
    );
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v["entry"], "main_ps");

    let o = kiln(d, &["build", "--config", "compute.toml", "--no-cache", "-o", "compute.kpak"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let o = kiln(d, &["inspect", "compute.kpak", "--list"]);
    let first = stdout(&o).lines().next().unwrap().to_string();
    let o = kiln(d, &["inspect", "compute.kpak", &first, "--reflection"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("workgroup size: (64, 1, 1)"), "{}", stdout(&o));
    assert!(stdout(&o).contains("histogram: storage, read_write(256 B)"), "{}", stdout(&o));
}

#[test]
fn unknown_name_is_exit_2_with_the_nearest_names() {
    let fx = built();
    let d = fx.path();
    let o =
        kiln(d, &["inspect", "shaders.kpak", "LitPS@es3_1{USE_FOG=1,BLEND=TRANSLUCENT,NUM_LIGHTS=0}", "-t", "wgsl"]);
    assert_eq!(o.status.code(), Some(2));
    let err = stderr(&o);
    assert!(err.starts_with("error: permutation `LitPS@es3_1{USE_FOG=1,BLEND=TRANSLUCENT,NUM_LIGHTS=0}` is not in the archive; nearest:"), "{err}");
    assert!(
        err.contains("LitPS@es3_1{USE_FOG=1,BLEND=TRANSLUCENT,NUM_LIGHTS=2}  (differs in NUM_LIGHTS: 0 -> 2)"),
        "{err}"
    );
    assert!(o.stdout.is_empty());
    // A name but nothing to show.
    let o = kiln(d, &["inspect", "shaders.kpak", "LitVS@sm5{USE_FOG=1,DEBUG_VIEW=0}"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("--target T (its artifact) or --reflection"), "{}", stderr(&o));
}

#[test]
fn summary_shows_raw_and_compressed_sizes_per_target() {
    let fx = built();
    let d = fx.path();
    let o = kiln(d, &["inspect", "shaders.kpak"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(out.contains("format version: 5"), "{out}");
    for t in ["wgsl", "spirv", "msl", "glsl", "hlsl"] {
        let line = out.lines().find(|l| l.trim_start().starts_with(t)).unwrap_or_else(|| panic!("{t}: {out}"));
        assert!(line.contains(" raw, ") && line.contains(" compressed"), "{line}");
    }
    let o = kiln(d, &["inspect", "shaders.kpak", "--json"]);
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v["format_version"], 5);
    for (t, s) in v["targets"].as_object().unwrap() {
        let (raw, compressed) = (s["raw_bytes"].as_u64().unwrap(), s["compressed_bytes"].as_u64().unwrap());
        assert!(compressed > 0 && compressed < raw, "{t}: {compressed} of {raw}");
    }
}

#[test]
fn fifos_directories_and_old_versions_are_clear_errors() {
    let fx = built();
    let d = fx.path();
    let o = kiln_no_hang(d, &["inspect", "."]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("cannot read archive .: it is a directory, not a regular file"), "{}", stderr(&o));
    let fifo = d.join("pipe.kpak");
    let c = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
    // SAFETY: a valid NUL-terminated path.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o644) }, 0);
    for args in [&["inspect", "pipe.kpak"][..], &["inspect", "pipe.kpak", "--list"]] {
        let o = kiln_no_hang(d, args);
        assert_eq!(o.status.code(), Some(2));
        assert!(stderr(&o).contains("it is a FIFO, not a regular file"), "{}", stderr(&o));
    }
    // A format 1 archive (the same magic, version 1).
    let mut bytes = std::fs::read(d.join("shaders.kpak")).unwrap();
    bytes[8..12].copy_from_slice(&1u32.to_le_bytes());
    std::fs::write(d.join("old.kpak"), bytes).unwrap();
    let o = kiln(d, &["inspect", "old.kpak"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(
        stderr(&o)
            .contains("archive format version 1 is not supported (this build of kiln reads versions 4 to 5); rebuild"),
        "{}",
        stderr(&o)
    );
}

/// An archive of 2,000 permutations with tiny artifacts: a manifest of many chunks.
fn many_permutations(path: &Path) {
    use kiln::archive::{ArchiveWriter, DimensionRecord, PermutationRecord, Reflection, ShaderRecord, Target};
    let mut w = ArchiveWriter::new();
    let shader = w.add_shader(ShaderRecord {
        name: "ManyPS".into(),
        level: "sm5".into(),
        entry: "main_ps".into(),
        stage: kiln::Stage::Fragment,
        dimensions: vec![DimensionRecord { name: "VARIANT".into(), labels: vec![] }],
    });
    let reflection = w.add_reflection(&Reflection {
        entry: "main_ps".into(),
        stage: kiln::Stage::Fragment,
        bindings: vec![],
        vertex_inputs: vec![],
        color_outputs: vec![],
        workgroup_size: None,
    });
    for i in 0..2000i64 {
        let blob = w.add_blob(format!("// variant {}", i % 5).as_bytes());
        w.add_permutation(PermutationRecord {
            name: format!("ManyPS@sm5{{VARIANT={i}}}"),
            shader,
            values: vec![i],
            reflection,
            artifacts: vec![(Target::Wgsl, blob)],
        });
    }
    w.write(path).unwrap();
}

/// A damaged byte of the manifest's names (found when first read, not at open): `--list`,
/// the summary and `--json` walk every record and fail before printing any, and a lookup
/// that reads it names the permutation; exit code 2.
#[test]
fn damaged_manifest_chunk_is_a_clear_error_for_every_walk() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    many_permutations(&d.join("many.kpak"));
    let mut bytes = std::fs::read(d.join("many.kpak")).unwrap();
    let o = kiln(d, &["inspect", "many.kpak", "--list"]);
    assert!(o.status.success() && stdout(&o).lines().count() == 2000, "{}", stderr(&o));
    let u64_at = |o: usize| u64::from_le_bytes(bytes[o..o + 8].try_into().unwrap()) as usize;
    // The names close the manifest; the blob table closes the file. The last name is
    // `ManyPS@sm5{VARIANT=9}` (sorted by bytes, `}` after the digits).
    let manifest_end = bytes.len() - u64_at(40) * 64 - u64_at(32).next_multiple_of(8) + u64_at(32);
    bytes[manifest_end - 3] ^= 0x02;
    std::fs::write(d.join("damaged.kpak"), bytes).unwrap();
    for args in [
        &["inspect", "damaged.kpak", "--list"][..],
        &["inspect", "damaged.kpak"],
        &["inspect", "damaged.kpak", "--json"],
    ] {
        let o = kiln(d, args);
        assert_eq!(o.status.code(), Some(2), "{args:?}");
        let err = stderr(&o);
        assert!(err.contains("damaged.kpak: archive is corrupted: permutation number "), "{args:?}: {err}");
        assert!(err.contains("fails its checksum") && !err.contains("panicked"), "{args:?}: {err}");
        assert!(o.stdout.is_empty(), "{args:?}: nothing printed before the error");
    }
    let o = kiln(d, &["inspect", "damaged.kpak", "ManyPS@sm5{VARIANT=9}", "--target", "wgsl"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("permutation `ManyPS@sm5{VARIANT=9}`: looking it up"), "{}", stderr(&o));
    // A permutation whose lookup reads only intact chunks is still found.
    let o = kiln(d, &["inspect", "damaged.kpak", "ManyPS@sm5{VARIANT=0}", "--target", "wgsl"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(stdout(&o), "// variant 0");
}

/// Issue 28, case 10: names in a crafted archive (escape sequences, a bell, a newline, a
/// right-to-left override) are printed escaped by every view of `kiln inspect`.
#[test]
fn names_from_a_crafted_archive_are_printed_escaped() {
    use kiln::archive::{ArchiveWriter, DimensionRecord, PermutationRecord, Reflection, ShaderRecord, Stage, Target};
    let dir = tempfile::tempdir().unwrap();
    let evil = "S\x1b]0;owned\x07\x1b[2J\n\u{202e}";
    let mut w = ArchiveWriter::new();
    w.set_naga_version("30.0.1");
    let s = w.add_shader(ShaderRecord {
        name: evil.into(),
        level: "sm5\x1b[31m".into(),
        entry: "main\x1b[1m".into(),
        stage: Stage::Compute,
        dimensions: vec![DimensionRecord { name: "A\x1b[K".into(), labels: vec![] }],
    });
    let r = w.add_reflection(&Reflection {
        entry: "main".into(),
        stage: Stage::Compute,
        bindings: vec![],
        vertex_inputs: vec![],
        color_outputs: vec![],
        workgroup_size: Some([1, 1, 1]),
    });
    let blob = w.add_blob(b"// wgsl");
    let name = format!("{evil}@sm5{{A=0}}");
    w.add_permutation(PermutationRecord {
        name: name.clone(),
        shader: s,
        values: vec![0],
        reflection: r,
        artifacts: vec![(Target::Wgsl, blob)],
    });
    std::fs::write(dir.path().join("evil.kpak"), w.to_bytes().unwrap()).unwrap();
    let raw = |o: &Output| {
        let bytes = [&o.stdout[..], &o.stderr[..]].concat();
        let text = String::from_utf8_lossy(&bytes).into_owned();
        // JSON escapes control characters itself (`\u001b`); a bidirectional override is
        // no control byte there.
        let json = text.starts_with('{');
        assert!(!text.contains('\x1b') && !text.contains('\x07'), "{text:?}");
        assert!(json || !text.contains('\u{202e}'), "{text:?}");
        text
    };
    let d = dir.path();
    let listed = raw(&kiln(d, &["inspect", "evil.kpak", "--list"]));
    assert!(listed.contains("S\\u{1b}]0;owned\\u{7}\\u{1b}[2J\\u{a}\\u{202e}@sm5{A=0}"), "{listed}");
    raw(&kiln(d, &["inspect", "evil.kpak"]));
    raw(&kiln(d, &["inspect", "evil.kpak", "--json"]));
    raw(&kiln(d, &["inspect", "evil.kpak", &name, "--reflection"]));
    raw(&kiln(d, &["inspect", "evil.kpak", &name]));
    let o = kiln(d, &["inspect", "evil.kpak", "S\x1b[2J@sm5{A=1}"]);
    assert_eq!(o.status.code(), Some(2));
    raw(&o);
}
