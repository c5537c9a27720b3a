//! Helpers shared by the compile and build tests: fixtures copied to a temporary folder,
//! builds through the library, and validation of every artifact with the reference tools.

#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Command;

use kiln::archive::{Archive, Stage, Target};
use kiln::build::{self, CacheDir, Options, Report};

/// `tests/in` of this repository.
pub fn inputs() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("in")
}

/// A copy of `tests/in` in a temporary folder (so tests can edit headers).
pub fn fixture() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    copy_dir(&inputs(), dir.path());
    dir
}

pub fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let dest = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &dest);
        } else {
            std::fs::copy(e.path(), dest).unwrap();
        }
    }
}

/// Options for a quiet build of `config` with its cache in `cache` (or none).
pub fn options(config: &Path, out: &Path, cache: Option<&Path>) -> Options {
    Options {
        config: config.to_path_buf(),
        output: Some(out.to_path_buf()),
        cache: match cache {
            Some(c) => CacheDir::Dir(c.to_path_buf()),
            None => CacheDir::Disabled,
        },
        jobs: Some(2),
        ..Options::default()
    }
}

/// A build that must succeed; panics with the rendered failures otherwise.
pub fn build_ok(options: &Options) -> Report {
    match build::run(options) {
        Ok(r) => r,
        Err(build::Error::Failed(r)) => panic!("build failed:\n{}", r.failures.join("\n")),
        Err(e) => panic!("build failed: {e}"),
    }
}

/// Fails (never skips) when a validator is missing, naming the Debian package.
pub fn require_tool(tool: &str, package: &str) {
    let ok = Command::new(tool).arg("--version").output().map(|o| o.status.success()).unwrap_or(false);
    assert!(
        ok,
        "`{tool}` is required by this test: install the Debian package `{package}` (apt-get install {package})"
    );
}

/// Checks one artifact: SPIR-V with `spirv-val`, GLSL with `glslangValidator`, WGSL by
/// parsing and validating it again with naga. Returns the problem, if any.
pub fn check_artifact(target: Target, stage: Stage, entry: &str, bytes: &[u8], scratch: &Path) -> Result<(), String> {
    match target {
        Target::Spirv => {
            let path = scratch.join("artifact.spv");
            std::fs::write(&path, bytes).unwrap();
            run_tool(Command::new("spirv-val").arg("--target-env").arg("vulkan1.0").arg(&path))
        }
        Target::Glsl => {
            let path = scratch.join(format!("artifact.{}", target.extension(stage)));
            std::fs::write(&path, bytes).unwrap();
            run_tool(Command::new("glslangValidator").arg(&path))
        }
        Target::Wgsl => {
            let text = std::str::from_utf8(bytes).map_err(|e| e.to_string())?;
            kiln::compile::validate(text, entry, stage, &kiln::compile::Limits::desktop())
                .map(|_| ())
                .map_err(|e| format!("naga rejects the WGSL it wrote: {e:?}\n{text}"))
        }
        Target::Hlsl => {
            // glslang's HLSL front end (the only HLSL compiler Debian packages). It lacks one
            // construct DXC and FXC accept and naga writes for zeroed arrays, `(uint[64])0`:
            // an artifact may fail only on lines holding that cast.
            let path = scratch.join("artifact.hlsl");
            std::fs::write(&path, bytes).unwrap();
            let stage = match stage {
                Stage::Vertex => "vert",
                Stage::Fragment => "frag",
                Stage::Compute => "comp",
            };
            let out = Command::new("glslangValidator")
                .args(["-D", "-V", "-S", stage, "-e", entry, "-o"])
                .arg(scratch.join("hlsl.spv"))
                .arg(&path)
                .output()
                .map_err(|e| format!("cannot run glslangValidator: {e}"))?;
            if out.status.success() {
                return Ok(());
            }
            let text = std::str::from_utf8(bytes).map_err(|e| e.to_string())?;
            let lines: Vec<&str> = text.lines().collect();
            let log = String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr);
            let errors: Vec<&str> =
                log.lines().filter(|l| l.starts_with("ERROR: ") && !l.contains("compilation errors")).collect();
            let only_zero_array_casts = !errors.is_empty()
                && errors.iter().all(|e| {
                    let line: Option<usize> = e.split(':').nth(2).and_then(|n| n.trim().parse().ok());
                    line.and_then(|n| lines.get(n.wrapping_sub(1))).is_some_and(|l| is_zero_array_cast(l))
                });
            if only_zero_array_casts {
                Ok(())
            } else {
                Err(format!("glslangValidator rejects the HLSL:\n{log}\n{text}"))
            }
        }
        Target::Msl => {
            // No Metal compiler runs here: the entry point must be there, by name.
            let text = std::str::from_utf8(bytes).map_err(|e| e.to_string())?;
            if text.contains(entry) || text.contains("main") {
                Ok(())
            } else {
                Err(format!("the {target} output does not mention entry point `{entry}`"))
            }
        }
    }
}

/// `x = (uint[64])0;`: a cast of zero to an array type.
fn is_zero_array_cast(line: &str) -> bool {
    line.find("])0").is_some_and(|end| line[..end].rfind('(').is_some_and(|open| line[open..end].contains('[')))
}

fn run_tool(cmd: &mut Command) -> Result<(), String> {
    let out = cmd.output().map_err(|e| format!("cannot run {cmd:?}: {e}"))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!(
            "{cmd:?} failed:\n{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        ))
    }
}

/// Validates every distinct artifact of an archive; returns how many were checked.
pub fn validate_archive(path: &Path) -> usize {
    require_tool("spirv-val", "spirv-tools");
    require_tool("glslangValidator", "glslang-tools");
    let archive = Archive::open(path).unwrap();
    let scratch = tempfile::tempdir().unwrap();
    let mut seen = std::collections::HashSet::new();
    let mut problems = Vec::new();
    for p in archive.permutations().unwrap() {
        for t in p.targets() {
            let id = p.blob_id(t).unwrap();
            if !seen.insert(id) {
                continue;
            }
            let shader = p.shader();
            if let Err(e) =
                check_artifact(t, shader.stage, &shader.entry, &p.artifact(t).unwrap().unwrap(), scratch.path())
            {
                problems.push(format!("{} ({t}): {e}", p.name()));
            }
        }
    }
    assert!(problems.is_empty(), "{} invalid artifacts:\n{}", problems.len(), problems.join("\n"));
    seen.len()
}
