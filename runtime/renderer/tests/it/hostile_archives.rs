//! Archives as a hostile user makes them: edited, then re-checksummed (written again with
//! Kiln's own writer, so every checksum holds). `kiln-view` must end with a clear error or a
//! frame, never a panic, an abort or a crash in the driver.

use std::path::Path;
use std::process::{Command, Output};

use kiln_archive::{ArchiveWriter, PermutationRecord, Reflection, Target};

/// The embedded archive written again after `edit` changed reflections and artifacts.
fn rewrite(edit: impl Fn(&str, &mut Reflection, Target, &mut Vec<u8>)) -> Vec<u8> {
    let archive = kiln_renderer::embedded_archive().unwrap();
    let mut w = ArchiveWriter::new();
    w.set_naga_version(archive.archive().naga_version());
    for p in archive.permutations().unwrap() {
        let shader = w.add_shader(p.shader().clone());
        let mut reflection = p.reflection().clone();
        let mut artifacts = Vec::new();
        for target in p.targets().collect::<Vec<_>>() {
            let mut bytes = p.artifact(target).unwrap().unwrap().to_vec();
            edit(p.name(), &mut reflection, target, &mut bytes);
            artifacts.push((target, w.add_blob(&bytes)));
        }
        let reflection = w.add_reflection(&reflection);
        w.add_permutation(PermutationRecord {
            name: p.name().to_string(),
            shader,
            values: p.values().to_vec(),
            reflection,
            artifacts,
        });
    }
    w.to_bytes().unwrap()
}

fn kiln_view(dir: &Path, archive: &[u8], args: &[&str]) -> Output {
    std::fs::write(dir.join("crafted.kpak"), archive).unwrap();
    Command::new(env!("CARGO_BIN_EXE_kiln-view"))
        .args(["--shaders", "crafted.kpak", "--size", "160x90", "--no-pipeline-cache"])
        .args(args)
        .current_dir(dir)
        .output()
        .expect("kiln-view runs")
}

/// Exit 0, 1 or 2 with no panic: a signal (abort, SIGSEGV, SIGBUS) has no exit code.
fn assert_clean_exit(o: &Output, what: &str) -> String {
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(matches!(o.status.code(), Some(0..=2)), "{what}: {:?}\n{err}", o.status);
    assert!(!err.contains("panicked"), "{what}: {err}");
    err
}

/// A class of manifest field: its name, an edit putting it out of range, the limit named.
type Case = (&'static str, fn(&mut Reflection), &'static str);

#[test]
fn out_of_range_manifest_fields_are_errors_naming_the_permutation_and_the_limit() {
    let dir = tempfile::tempdir().unwrap();
    // Each class of field, on every permutation that has one.
    let cases: [Case; 5] = [
        ("bind group index", |r| r.bindings.iter_mut().for_each(|b| b.group = 4_000_000_000), "max_bind_groups"),
        ("binding number", |r| r.bindings.iter_mut().for_each(|b| b.binding = u32::MAX), "max_bindings_per_bind_group"),
        (
            "buffer size",
            |r| {
                for b in &mut r.bindings {
                    if let kiln_archive::BindingKind::UniformBuffer { min_size } = &mut b.kind {
                        *min_size = u64::MAX;
                    }
                }
            },
            "max_uniform_buffer_binding_size",
        ),
        (
            "workgroup size",
            |r| {
                if r.workgroup_size.is_some() {
                    r.workgroup_size = Some([65535, 65535, 65535]);
                }
            },
            "max_compute_workgroup_size_x",
        ),
        (
            "vertex input location",
            |r| r.vertex_inputs.iter_mut().for_each(|v| v.location = 4_000_000_000),
            "max_vertex_attributes",
        ),
    ];
    for (what, edit, limit) in cases {
        let archive = rewrite(|_, r, _, _| edit(r));
        let o = kiln_view(dir.path(), &archive, &["--pipeline", "desktop"]);
        let err = assert_clean_exit(&o, what);
        assert_eq!(o.status.code(), Some(1), "{what}: {err}");
        assert!(err.contains("permutation `") && err.contains(limit), "{what}: {err}");
    }
}

#[test]
fn a_flipped_bit_in_every_artifact_is_an_error_or_a_frame_never_a_crash() {
    let dir = tempfile::tempdir().unwrap();
    // One bit per blob, at a position that differs from blob to blob.
    let flip = |name: &str, bytes: &mut Vec<u8>| {
        if bytes.is_empty() {
            return;
        }
        let h = name.bytes().fold(7u64, |h, b| h.wrapping_mul(31).wrapping_add(u64::from(b)));
        let bit = (h % (bytes.len() as u64 * 8)) as usize;
        bytes[bit / 8] ^= 1 << (bit % 8);
    };
    // SPIR-V: an archive from a file is untrusted, so its SPIR-V never reaches the driver.
    let spirv = rewrite(|name, _, t, bytes| {
        if t == Target::Spirv {
            flip(name, bytes)
        }
    });
    for pipeline in ["desktop", "mobile-forward", "mobile-deferred"] {
        let o = kiln_view(dir.path(), &spirv, &["--pipeline", pipeline]);
        let err = assert_clean_exit(&o, pipeline);
        assert_eq!(o.status.code(), Some(0), "{pipeline}: {err}");
        assert!(err.contains("modules from WGSL"), "{err}");
    }
    // WGSL: wgpu's naga parses and validates it; a broken module is a located error.
    let wgsl = rewrite(|name, _, t, bytes| {
        if t == Target::Wgsl {
            flip(name, bytes)
        }
    });
    for pipeline in ["desktop", "mobile-forward"] {
        let o = kiln_view(dir.path(), &wgsl, &["--pipeline", pipeline]);
        assert_clean_exit(&o, pipeline);
    }
}

#[test]
fn trusted_spirv_is_walked_and_checked_against_its_reflection_first() {
    // The structural check is what stands between a trusted archive and the driver: every
    // module of the bundled set passes it, and a module whose resources do not match its
    // reflection is refused before it reaches the device.
    let archive = kiln_renderer::embedded_archive().unwrap();
    let mut checked = 0;
    for p in archive.permutations().unwrap() {
        let bytes = p.artifact(Target::Spirv).unwrap().unwrap();
        let m = kiln_runtime::spirv::SpirvModule::parse(&bytes).unwrap_or_else(|e| panic!("{}: {e}", p.name()));
        m.check(p.reflection()).unwrap_or_else(|e| panic!("{}: {e}", p.name()));
        if let Some(b) = p.reflection().bindings.first() {
            let mut other = p.reflection().clone();
            other.bindings.retain(|x| (x.group, x.binding) != (b.group, b.binding));
            let e = m.check(&other).unwrap_err().to_string();
            let at = format!("@group({}) @binding({})", b.group, b.binding);
            assert!(e.contains(&at) && e.contains("lists nothing there"), "{}: {e}", p.name());
            checked += 1;
        }
    }
    assert!(checked > 100, "{checked}");
}
