//! `kiln-view` as a process: exit codes, files written, and the message when there is no
//! adapter.

use std::path::Path;
use std::process::{Command, Output};

fn kiln_view(args: &[&str], dir: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_kiln-view"))
        .args(args)
        .current_dir(dir)
        .env("KILN_PIPELINE_CACHE", dir.join("pipeline-cache"))
        .output()
        .expect("kiln-view runs")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).lines().collect::<Vec<_>>().join("\n")
}

/// Each pipeline five frames in a row on Vulkan with the Khronos validation layer on:
/// no validation message (`--validation` fails with them), every module from SPIR-V
/// passthrough, and none of the Wayland probe's `XDG_RUNTIME_DIR` noise.
#[test]
fn every_pipeline_renders_five_times_under_the_validation_layer_without_a_message() {
    let dir = tempfile::tempdir().unwrap();
    for pipeline in ["desktop", "mobile-forward", "mobile-deferred"] {
        let o = Command::new(env!("CARGO_BIN_EXE_kiln-view"))
            .args(["--pipeline", pipeline, "--size", "320x180", "--frames", "5", "--validation", "--no-pipeline-cache"])
            .current_dir(dir.path())
            .env_remove("XDG_RUNTIME_DIR")
            .output()
            .expect("kiln-view runs");
        let (out, err) = (String::from_utf8_lossy(&o.stdout), stderr(&o));
        assert!(o.status.success(), "{pipeline}: {err}{out}");
        assert!(
            !out.contains("Validation") && !err.contains("Validation") && !err.contains("VUID"),
            "{pipeline}: {err}{out}"
        );
        assert!(err.contains("modules from SPIR-V passthrough"), "{pipeline}: {err}");
        assert!(!err.contains("XDG_RUNTIME_DIR"), "{pipeline}: {err}");
    }
}

#[test]
fn the_pipeline_cache_is_written_per_adapter_and_a_corrupt_one_is_a_warning() {
    let dir = tempfile::tempdir().unwrap();
    let args = ["--pipeline", "mobile-forward", "--size", "64x36", "--pipeline-cache", "pc"];
    let o = kiln_view(&args, dir.path());
    assert!(o.status.success(), "{}", stderr(&o));
    let files: Vec<_> = std::fs::read_dir(dir.path().join("pc")).unwrap().flatten().map(|e| e.path()).collect();
    assert_eq!(files.len(), 1, "{files:?}");
    let name = files[0].file_name().unwrap().to_string_lossy().into_owned();
    assert!(name.starts_with("wgpu_pipeline_cache_vulkan_"), "{name}");
    std::fs::write(&files[0], b"not a cache").unwrap();
    let o = kiln_view(&args, dir.path());
    assert!(o.status.success(), "{}", stderr(&o));
    let warning = format!("warning: pipeline cache pc/{name} is ignored: it is not a Kiln pipeline cache");
    assert!(stderr(&o).contains(&warning), "{}", stderr(&o));
    assert!(std::fs::read(&files[0]).unwrap().starts_with(b"KILNPC1"), "rewritten after the frame");
}

/// Issue 28, case 5: a FIFO, a link to `/dev/zero` or a folder at the pipeline cache's path
/// is a warning and ignored: the viewer neither waits on it nor reads it without end
/// (run under `timeout` and `ulimit -v`).
#[test]
fn a_pipeline_cache_that_is_not_a_regular_file_is_ignored() {
    let dir = tempfile::tempdir().unwrap();
    let args = ["--pipeline", "mobile-forward", "--size", "64x36", "--pipeline-cache", "pc"];
    let o = kiln_view(&args, dir.path());
    assert!(o.status.success(), "{}", stderr(&o));
    let path = std::fs::read_dir(dir.path().join("pc")).unwrap().flatten().next().unwrap().path();
    let name = path.file_name().unwrap().to_string_lossy().into_owned();
    for (kind, why) in [("fifo", "FIFO"), ("zero", "device"), ("dir", "directory")] {
        if path.is_dir() {
            std::fs::remove_dir(&path).unwrap();
        } else {
            std::fs::remove_file(&path).unwrap();
        }
        match kind {
            "fifo" => {
                let c = std::ffi::CString::new(path.to_str().unwrap()).unwrap();
                // SAFETY: a path we own.
                assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o644) }, 0);
            }
            "zero" => std::os::unix::fs::symlink("/dev/zero", &path).unwrap(),
            _ => std::fs::create_dir(&path).unwrap(),
        }
        let o = Command::new("sh")
            .args(["-c", "ulimit -v 8000000 && exec timeout 120 \"$0\" \"$@\"", env!("CARGO_BIN_EXE_kiln-view")])
            .args(args)
            .current_dir(dir.path())
            .output()
            .unwrap();
        assert!(o.status.success(), "{kind}: {:?} {}", o.status, stderr(&o));
        let warning = format!("warning: pipeline cache pc/{name} cannot be read (it is a {why}");
        assert!(stderr(&o).contains(&warning), "{kind}: {}", stderr(&o));
        assert!(!stderr(&o).contains("panicked"), "{kind}: {}", stderr(&o));
    }
}

#[test]
fn renders_and_dumps_every_pass() {
    let dir = tempfile::tempdir().unwrap();
    let o = kiln_view(
        &["--pipeline", "mobile-deferred", "--size", "160x90", "--out", "f.png", "--dump-passes", "dump"],
        dir.path(),
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let png = std::fs::read(dir.path().join("f.png")).unwrap();
    assert_eq!(&png[1..4], b"PNG");
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("dump/passes.json")).unwrap()).unwrap();
    let names: Vec<&str> = json["passes"].as_array().unwrap().iter().map(|p| p["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["ShadowDepths", "BasePass", "MobileDeferredShading", "Translucency", "PostProcessing"]);
    assert_eq!(json["pipeline"], "mobile-deferred");
    // The mobile frame runs es3_1 permutations only.
    let permutations = json["permutations"].as_array().unwrap();
    assert!(permutations.len() >= 6);
    assert!(permutations.iter().all(|p| p.as_str().unwrap().contains("@es3_1{")), "{permutations:?}");
    assert!(permutations.iter().any(|p| p.as_str().unwrap().contains("DEFERRED_SHADING_PATH=1")), "{permutations:?}");
    for pass in json["passes"].as_array().unwrap() {
        for image in pass["images"].as_array().unwrap() {
            assert!(dir.path().join("dump").join(image.as_str().unwrap()).is_file(), "{image}");
        }
        assert!(pass["gpu_ms"].is_number() || !json["timestamps"].as_bool().unwrap(), "{pass}");
    }
    assert!(dir.path().join("dump/04_PostProcessing_Tonemapper.png").is_file());
    assert!(dir.path().join("dump/01_BasePass_GBufferA.png").is_file());
}

#[test]
fn gl_backend_dumps_depth_too() {
    let dir = tempfile::tempdir().unwrap();
    // Mobile deferred copies its depth into SceneDepthAux (a depth target the GL device
    // cannot copy to a buffer); the forward frame's MSAA depth is never stored, as in the seed.
    let o = kiln_view(
        &["--backend", "gl", "--pipeline", "mobile-deferred", "--size", "160x90", "--dump-passes", "dump"],
        dir.path(),
    );
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(dir.path().join("dump/00_ShadowDepths.png").is_file());
    assert!(dir.path().join("dump/02_MobileDeferredShading_SceneDepthAux.png").is_file());
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("dump/passes.json")).unwrap()).unwrap();
    assert_eq!(json["backend"], "gl");
}

#[test]
fn truncated_archive_is_a_usage_error() {
    let dir = tempfile::tempdir().unwrap();
    let bytes = kiln_renderer::EMBEDDED_ARCHIVE;
    std::fs::write(dir.path().join("cut.kpak"), &bytes[..bytes.len() / 2]).unwrap();
    let o = kiln_view(&["--shaders", "cut.kpak"], dir.path());
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    let expected = format!(
        "error: archive is truncated: the header announces {} bytes, the file has {}",
        bytes.len(),
        bytes.len() / 2
    );
    assert_eq!(stderr(&o), expected);
    assert!(!dir.path().join("frame.png").exists());
}

#[test]
fn archive_without_the_frames_shaders_is_a_usage_error_naming_the_permutation() {
    let dir = tempfile::tempdir().unwrap();
    kiln_archive::ArchiveWriter::new().write(&dir.path().join("empty.kpak")).unwrap();
    let o = kiln_view(&["--shaders", "empty.kpak"], dir.path());
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    // The frames name permutations with typed keys: the first one the frame needs is missing.
    assert_eq!(
        stderr(&o),
        "error: permutation `DepthPassVS@sm5{MATERIAL_MASKED=0}` is not in the archive (the archive holds no permutations)"
    );
}

#[test]
fn verify_looks_every_permutation_up_and_creates_its_module() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("s.kpak"), kiln_renderer::EMBEDDED_ARCHIVE).unwrap();
    let archive = kiln_renderer::embedded_archive().unwrap();
    let count = archive.permutations().unwrap().count();
    let distinct = |target| {
        archive
            .permutations()
            .unwrap()
            .map(|p| p.blob_id(target).unwrap())
            .collect::<std::collections::HashSet<_>>()
            .len()
    };
    // An archive from a file is not trusted with passthrough: its modules come from WGSL,
    // which wgpu validates; `--trust-shaders` passes its SPIR-V through.
    for (args, target, source) in [
        (&["--shaders", "s.kpak", "--verify"][..], kiln_archive::Target::Wgsl, "WGSL"),
        (
            &["--shaders", "s.kpak", "--verify", "--trust-shaders"][..],
            kiln_archive::Target::Spirv,
            "SPIR-V passthrough",
        ),
    ] {
        let o = kiln_view(args, dir.path());
        assert!(o.status.success(), "{}", stderr(&o));
        let out = String::from_utf8_lossy(&o.stdout);
        let expected = format!(
            "{count} permutations looked up by name and by dimension values; {} distinct modules created from {source} on ",
            distinct(target)
        );
        assert!(out.starts_with(&expected), "{out}");
    }
}

#[test]
fn bad_size_is_a_usage_error() {
    let dir = tempfile::tempdir().unwrap();
    let o = kiln_view(&["--size", "640by360"], dir.path());
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("`640by360` is not WIDTHxHEIGHT"), "{}", stderr(&o));
}

#[test]
fn no_vulkan_driver_fails_naming_the_debian_package() {
    let dir = tempfile::tempdir().unwrap();
    // The Vulkan loader sees no driver at all: the state of a machine without
    // mesa-vulkan-drivers.
    let o = Command::new(env!("CARGO_BIN_EXE_kiln-view"))
        .current_dir(dir.path())
        .env("VK_ICD_FILENAMES", dir.path().join("none.json"))
        .env("VK_DRIVER_FILES", dir.path().join("none.json"))
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    let text = stderr(&o);
    assert!(text.starts_with("error: no vulkan adapter found"), "{text}");
    assert!(text.contains("Debian package `mesa-vulkan-drivers`"), "{text}");
}

#[test]
fn help_documents_every_option() {
    let dir = tempfile::tempdir().unwrap();
    let o = kiln_view(&["--help"], dir.path());
    assert!(o.status.success());
    let text = String::from_utf8_lossy(&o.stdout);
    for option in ["--pipeline", "--backend", "--size", "--out", "--dump-passes", "--shaders"] {
        assert!(text.contains(option), "{option} missing from --help");
    }
}

/// `--record-usage` and `--stats-json`: the frames' pipelines, all created before the first
/// frame (the renderer builds its passes up front), none during the frames.
#[test]
fn record_usage_and_stats_json_describe_the_frames() {
    let dir = tempfile::tempdir().unwrap();
    let args = [
        "--pipeline",
        "mobile-forward",
        "--size",
        "64x36",
        "--frames",
        "3",
        "--no-pipeline-cache",
        "--record-usage",
        "frames.usage",
        "--stats-json",
        "stats.json",
    ];
    let o = kiln_view(&args, dir.path());
    assert!(o.status.success(), "{}", stderr(&o));
    let usage = std::fs::read_to_string(dir.path().join("frames.usage")).unwrap();
    let usage = kiln_runtime::pipelines::Usage::parse(&usage).unwrap();
    assert_eq!(usage.runs, 1);
    assert_eq!(usage.archive, kiln_renderer::embedded_archive().unwrap().archive().content_hash());
    assert!(usage.permutations().iter().all(|p| p.contains("@es3_1{")));
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(dir.path().join("stats.json")).unwrap()).unwrap();
    assert_eq!(v["frames"], 3);
    assert_eq!(v["pipelines_created_before_first_frame"].as_u64(), Some(usage.records.len() as u64));
    assert_eq!(v["pipelines_created_during_frames"], 0);
    assert_eq!(v["fallback_draws"], 0);
    assert!(v["first_frame_ms"].as_f64().unwrap() > 0.0);
    assert!(v["slowest_frame_ms"].as_f64().unwrap() >= v["first_frame_ms"].as_f64().unwrap());
}

/// `kiln build --usage` of a recorded run gives an archive with a pipeline manifest, which
/// kiln-view creates before the first frame: no frame creates a pipeline. `--no-precache`
/// leaves it to the renderer.
#[test]
fn a_pipeline_manifest_is_precached_before_the_first_frame() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let base = ["--pipeline", "mobile-forward", "--size", "64x36", "--no-pipeline-cache", "--frames", "2"];
    let o = kiln_view(&[&base[..], &["--record-usage", "frames.usage"]].concat(), d);
    assert!(o.status.success(), "{}", stderr(&o));
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let options = kiln::build::Options {
        config: root.join("permutations.toml"),
        output: Some(d.join("with.kpak")),
        cache: kiln::build::CacheDir::Disabled,
        usage: vec![d.join("frames.usage")],
        levels: vec!["es3_1".into()],
        jobs: Some(2),
        ..kiln::build::Options::default()
    };
    kiln::build::run(&options).unwrap_or_else(|e| panic!("{e}"));
    let usage = std::fs::read_to_string(d.join("frames.usage")).unwrap();
    let recorded = kiln_runtime::pipelines::Usage::parse(&usage).unwrap().records.len() as u64;
    let archive = kiln_archive::Archive::open(&d.join("with.kpak")).unwrap();
    assert_eq!(archive.pipeline_manifest().map(|m| m.len() as u64), Some(recorded));
    assert!(recorded > 0);

    let stats = |extra: &[&str]| -> serde_json::Value {
        let args = [&base[..], &["--shaders", "with.kpak", "--stats-json", "stats.json"], extra].concat();
        let o = kiln_view(&args, d);
        assert!(o.status.success(), "{}", stderr(&o));
        serde_json::from_slice(&std::fs::read(d.join("stats.json")).unwrap()).unwrap()
    };
    let counts = |v: &serde_json::Value| {
        ["precached", "pipelines_created_before_first_frame", "pipelines_created_during_frames", "fallback_draws"]
            .map(|k| v[k].as_u64().unwrap_or_else(|| panic!("{k} in {v}")))
    };
    assert_eq!(counts(&stats(&[])), [recorded, recorded, 0, 0]);
    // Without precaching the renderer creates the same pipelines as it is built.
    assert_eq!(counts(&stats(&["--no-precache"])), [0, recorded, 0, 0]);
    // `--no-stall` precaches alongside the frames, and its renderer creates nothing when it
    // is built: every manifest pipeline is the precache's, none is created twice.
    let v = stats(&["--no-stall"]);
    assert_eq!(counts(&v)[0], recorded);
    assert!(counts(&v)[1] + counts(&v)[2] <= recorded, "{v}");
    let o = kiln_view(&["--no-stall=sideways"], d);
    assert_eq!(o.status.code(), Some(2));
}

/// A pipeline manifest whose state text does not read is a usage error naming the field,
/// before any frame.
#[test]
fn a_manifest_state_that_does_not_read_is_a_usage_error() {
    let dir = tempfile::tempdir().unwrap();
    let mut w = kiln_archive::ArchiveWriter::new();
    w.set_pipelines(vec![kiln_archive::PipelineRecord {
        key: kiln_archive::usage::UsageKey::Render {
            vertex: "V@sm5{}".into(),
            fragment: None,
            state: "TriangleList;cull=Sideways".into(),
        },
        first_frame: 0,
    }]);
    w.write(&dir.path().join("bad.kpak")).unwrap();
    let o = kiln_view(&["--shaders", "bad.kpak"], dir.path());
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).starts_with("error: the archive's pipeline manifest: render state text"), "{}", stderr(&o));
    assert!(stderr(&o).contains("field `cull`"), "{}", stderr(&o));
    // Without precaching the manifest is not read: the frame's missing permutation is the error.
    let o = kiln_view(&["--shaders", "bad.kpak", "--no-precache"], dir.path());
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("is not in the archive"), "{}", stderr(&o));
}

/// `--no-stall` without a manifest: the renderer is built without creating a pipeline, the
/// first frame finds none ready and skips its draws (counted), and once the workers have
/// created them the frames draw every draw again, the same image as a blocking run's. All of
/// it under the validation layer: a skipped draw leaves its pass valid.
#[test]
fn a_no_stall_frame_never_waits_for_a_pipeline() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let base = ["--pipeline", "mobile-forward", "--size", "32x18", "--no-pipeline-cache", "--validation"];
    let o = kiln_view(&[&base[..], &["--frames", "2", "--out", "blocking.png"]].concat(), d);
    assert!(o.status.success(), "{}", stderr(&o));
    // Enough frames for the workers to finish on a slow software device; the last frames
    // must then draw everything.
    let args =
        [&base[..], &["--frames", "300", "--no-stall", "--stats-json", "s.json", "--out", "no-stall.png"]].concat();
    let o = kiln_view(&args, d);
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(d.join("s.json")).unwrap()).unwrap();
    let per_frame: Vec<u64> =
        v["fallback_draws_per_frame"].as_array().unwrap().iter().map(|n| n.as_u64().unwrap()).collect();
    assert_eq!(per_frame.len(), 300, "{v}");
    assert!(per_frame[0] > 0, "the first frame skipped no draw: {v}");
    assert_eq!(per_frame.last(), Some(&0), "the last frame still skipped draws: {v}");
    assert_eq!(v["fallback_draws"].as_u64(), Some(per_frame.iter().sum()), "{v}");
    assert_eq!(v["pipelines_created_before_first_frame"].as_u64(), Some(0), "{v}");
    assert_eq!(
        std::fs::read(d.join("no-stall.png")).unwrap(),
        std::fs::read(d.join("blocking.png")).unwrap(),
        "once every pipeline is ready the frame is the blocking run's"
    );
}
