//! The runtime's archive access: the embedded archive opens and every permutation is found
//! by name and by the builder; missing names, truncated and corrupted archives are errors
//! that say what is wrong.

use kiln_runtime::{LookupError, ShaderArchive};

fn embedded() -> ShaderArchive {
    kiln_renderer::embedded_archive().expect("the embedded archive opens")
}

#[test]
fn embedded_archive_holds_both_levels() {
    let a = embedded();
    let names: Vec<String> = a.permutations().unwrap().map(|p| p.name().to_string()).collect();
    assert!(names.len() > 50, "{} permutations", names.len());
    assert!(names.iter().any(|n| n.contains("@sm5")));
    assert!(names.iter().any(|n| n.contains("@es3_1")));
}

#[test]
fn every_permutation_is_found_by_name_and_by_builder() {
    let a = embedded();
    let archive = a.archive();
    for p in a.permutations().unwrap() {
        assert_eq!(a.get(p.name()).unwrap().name(), p.name());
        let shader = p.shader();
        let mut q = a.shader(&shader.name).level(&shader.level);
        for (d, v) in shader.dimensions.iter().zip(p.values()) {
            q = q.with(&d.name, v);
        }
        assert_eq!(q.find().unwrap().name(), p.name(), "builder with indices");
        assert!(archive.get(p.name()).unwrap().is_some());
    }
}

#[test]
fn builder_accepts_enum_labels_and_any_order() {
    let a = embedded();
    let p = a
        .shader("MobileBasePassPS")
        .level("es3_1")
        .with("MATERIAL_BLEND_MODE", "MASKED")
        .with("DEFERRED_SHADING_PATH", 0)
        .with("USE_VERTEX_FOG", 1)
        .with("MAX_DYNAMIC_POINT_LIGHTS", 4)
        .with("FULLY_ROUGH", 1)
        .with("OUTPUT_GAMMA_SPACE", 0)
        .with("ENABLE_SKY_LIGHT", 1)
        .with("HQ_REFLECTIONS", 0)
        .with("DIRECTIONAL_LIGHT_CSM", 1)
        .find()
        .unwrap();
    assert_eq!(
        p.name(),
        "MobileBasePassPS@es3_1{FULLY_ROUGH=1,MAX_DYNAMIC_POINT_LIGHTS=4,USE_VERTEX_FOG=1,DEFERRED_SHADING_PATH=0,DIRECTIONAL_LIGHT_CSM=1,HQ_REFLECTIONS=0,ENABLE_SKY_LIGHT=1,OUTPUT_GAMMA_SPACE=0,MATERIAL_BLEND_MODE=MASKED}"
    );
    // A shader with one level needs no .level().
    assert_eq!(a.shader("PostProcessVS").find().unwrap().name(), "PostProcessVS@sm5{}");
}

#[test]
fn skipped_permutation_names_the_nearest_and_what_differs() {
    let a = embedded();
    // Skipped in permutations.toml: deferred lights run in their own pass.
    let err = a
        .shader("MobileBasePassPS")
        .level("es3_1")
        .with("FULLY_ROUGH", 0)
        .with("MAX_DYNAMIC_POINT_LIGHTS", 2)
        .with("USE_VERTEX_FOG", 0)
        .with("DEFERRED_SHADING_PATH", 1)
        .with("DIRECTIONAL_LIGHT_CSM", 0)
        .with("HQ_REFLECTIONS", 0)
        .with("ENABLE_SKY_LIGHT", 0)
        .with("OUTPUT_GAMMA_SPACE", 0)
        .with("MATERIAL_BLEND_MODE", "OPAQUE")
        .find()
        .err()
        .expect("lookup should fail");
    let LookupError::Missing { name, nearest } = &err else { panic!("{err}") };
    assert_eq!(
        name,
        "MobileBasePassPS@es3_1{FULLY_ROUGH=0,MAX_DYNAMIC_POINT_LIGHTS=2,USE_VERTEX_FOG=0,DEFERRED_SHADING_PATH=1,DIRECTIONAL_LIGHT_CSM=0,HQ_REFLECTIONS=0,ENABLE_SKY_LIGHT=0,OUTPUT_GAMMA_SPACE=0,MATERIAL_BLEND_MODE=OPAQUE}"
    );
    assert_eq!(nearest[0].differences.len(), 1, "{err}");
    let text = err.to_string();
    assert!(text.starts_with("permutation `MobileBasePassPS@es3_1{FULLY_ROUGH=0,MAX_DYNAMIC_POINT_LIGHTS=2"), "{text}");
    assert!(text.contains("; nearest:\n  MobileBasePassPS@es3_1{"), "{text}");
    assert!(
        text.contains("(differs in MAX_DYNAMIC_POINT_LIGHTS: 2 -> 0)")
            || text.contains("(differs in DEFERRED_SHADING_PATH: 1 -> 0)"),
        "{text}"
    );
}

#[test]
fn builder_errors_name_the_unknown_part() {
    let a = embedded();
    let e = a.shader("NoSuchPS").level("sm5").find().err().expect("lookup should fail").to_string();
    assert_eq!(e, "cannot name permutation: no shader named `NoSuchPS` in the archive");
    let e = a
        .shader("ExponentialHeightFogPS")
        .level("sm5")
        .with("SUPPORT_FOG_DIRECTIONAL_LIGHT_INSCATTERING", 0)
        .with("BOGUS", 1)
        .find()
        .err()
        .expect("lookup should fail")
        .to_string();
    assert_eq!(e, "cannot name permutation: shader `ExponentialHeightFogPS` has no dimension `BOGUS` (its dimensions: SUPPORT_FOG_DIRECTIONAL_LIGHT_INSCATTERING)");
    let e = a.shader("VisualizeDepthPS").find().err().expect("lookup should fail").to_string();
    assert_eq!(
        e,
        "cannot name permutation: shader `VisualizeDepthPS` has several levels (es3_1, sm5); say which with .level()"
    );
    let e = a
        .shader("StandardDeferredLightingPS")
        .level("sm5")
        .with("LIGHT_TYPE", "POINT")
        .find()
        .err()
        .expect("lookup should fail")
        .to_string();
    assert!(e.contains("no value given for dimension `USE_SHADOW_MASK`"), "{e}");
}

#[test]
fn truncated_and_corrupted_archives_are_errors() {
    let bytes = kiln_renderer::EMBEDDED_ARCHIVE.to_vec();
    for len in [0, 10, 64, bytes.len() / 3, bytes.len() - 1] {
        let e = ShaderArchive::from_vec(bytes[..len].to_vec()).unwrap_err().to_string();
        assert!(e.contains("truncated") || e.contains("shorter than"), "{len}: {e}");
    }
    // A byte of the chunk hashes (just before the manifest): the header checksum, at open.
    let u64_at = |o: usize| u64::from_le_bytes(bytes[o..o + 8].try_into().unwrap()) as usize;
    let manifest_start = bytes.len() - u64_at(40) * 64 - u64_at(32).next_multiple_of(8);
    let mut flipped = bytes.clone();
    flipped[manifest_start - 5] ^= 0x10;
    let e = ShaderArchive::from_vec(flipped).unwrap_err().to_string();
    assert!(e.contains("checksum mismatch"), "{e}");
    // A byte of the blob table: its chunk's hash, when first read.
    let mut flipped = bytes.clone();
    flipped[bytes.len() - 5] ^= 0x10;
    let a = ShaderArchive::from_vec(flipped).expect("the table is checked on use");
    let e = a.archive().verify_all().unwrap_err().to_string();
    assert!(e.contains("fails its checksum"), "{e}");
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("none.kpak");
    let e = ShaderArchive::open(&missing).unwrap_err().to_string();
    assert!(e.starts_with("cannot read archive"), "{e}");
}

#[test]
fn opening_a_file_maps_the_same_archive() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("shaders.kpak");
    std::fs::write(&path, kiln_renderer::EMBEDDED_ARCHIVE).unwrap();
    let a = ShaderArchive::open(&path).unwrap();
    assert_eq!(a.permutations().unwrap().count(), embedded().permutations().unwrap().count());
}

#[test]
fn a_corrupted_blob_is_an_error_naming_the_permutation_when_used() {
    let bytes = kiln_renderer::EMBEDDED_ARCHIVE.to_vec();
    let archive = embedded();
    let p = archive.permutations().unwrap().find(|p| p.blob_id(kiln::archive::Target::Wgsl).is_some()).unwrap();
    let (name, id) = (p.name().to_string(), p.blob_id(kiln::archive::Target::Wgsl).unwrap());
    // The blob table closes the file, 64 bytes per blob: offset and stored length first.
    let count = u64::from_le_bytes(bytes[40..48].try_into().unwrap()) as usize;
    let at = bytes.len() - count * 64 + id.0 as usize * 64;
    let offset = u64::from_le_bytes(bytes[at..at + 8].try_into().unwrap()) as usize;
    let len = u64::from_le_bytes(bytes[at + 8..at + 16].try_into().unwrap()) as usize;
    let mut damaged = bytes.clone();
    damaged[kiln::archive::HEADER_LEN + offset + len / 2] ^= 0x04;
    let a = ShaderArchive::from_vec(damaged).expect("opening checks header and manifest only");
    let e = a.get(&name).unwrap().artifact(kiln::archive::Target::Wgsl).unwrap_err().to_string();
    assert!(e.contains(&format!("the wgsl artifact of permutation `{name}`")), "{e}");
    // The intact archive reads the same permutation.
    assert!(archive.get(&name).unwrap().artifact(kiln::archive::Target::Wgsl).unwrap().is_some());
}

#[test]
fn directories_and_fifos_are_refused_without_blocking() {
    let dir = tempfile::tempdir().unwrap();
    let e = ShaderArchive::open(dir.path()).unwrap_err().to_string();
    assert!(e.contains("it is a directory, not a regular file"), "{e}");
    let fifo = dir.path().join("shaders.kpak");
    assert!(std::process::Command::new("mkfifo").arg(&fifo).status().unwrap().success());
    let e = ShaderArchive::open(&fifo).unwrap_err().to_string();
    assert!(e.contains("it is a FIFO, not a regular file"), "{e}");
}
