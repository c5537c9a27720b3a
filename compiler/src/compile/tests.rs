use super::*;
use crate::archive::{Binding, BindingKind, ColorOutput, NumericType, SampleKind, ScalarKind, TextureDim, VertexInput};

const TRIANGLE: &str = r#"
struct Globals { view_proj: mat4x4<f32>, tint: vec4<f32> }
@group(0) @binding(0) var<uniform> globals: Globals;
@group(1) @binding(0) var base_color: texture_2d<f32>;
@group(1) @binding(1) var base_sampler: sampler;
@group(1) @binding(2) var unused_tex: texture_2d<f32>;

struct VsIn { @location(0) position: vec3<f32>, @location(2) uv: vec2<f32> }
struct VsOut { @builtin(position) clip: vec4<f32>, @location(0) uv: vec2<f32> }

@vertex
fn main_vs(v: VsIn, @builtin(vertex_index) vi: u32) -> VsOut {
    return VsOut(globals.view_proj * vec4<f32>(v.position, 1.0), v.uv);
}

@fragment
fn main_ps(i: VsOut) -> @location(0) vec4<f32> {
    return textureSample(base_color, base_sampler, i.uv) * globals.tint;
}
"#;

fn f32x(n: u8) -> NumericType {
    NumericType { scalar: ScalarKind::Float, width: 4, components: n }
}

#[test]
fn every_target_is_written_for_each_entry_point() {
    for (entry, stage) in [("main_vs", Stage::Vertex), ("main_ps", Stage::Fragment)] {
        let out = compile(TRIANGLE, entry, stage, &Options::default()).unwrap();
        let targets: Vec<Target> = out.artifacts.iter().map(|(t, _)| *t).collect();
        assert_eq!(targets, Target::ALL.to_vec());
        for (t, bytes) in &out.artifacts {
            assert!(!bytes.is_empty(), "{t} is empty");
        }
        let spv = &out.artifacts[1].1;
        assert_eq!(&spv[..4], &0x0723_0203u32.to_le_bytes(), "SPIR-V magic");
        let glsl = std::str::from_utf8(&out.artifacts[3].1).unwrap();
        assert!(glsl.starts_with("#version 310 es"), "{glsl}");
        let wgsl = std::str::from_utf8(&out.artifacts[0].1).unwrap();
        let other = if entry == "main_vs" { "fn main_ps" } else { "fn main_vs" };
        assert!(!wgsl.contains(other), "only the requested entry point is kept:\n{wgsl}");
    }
}

#[test]
fn reflection_lists_only_what_the_entry_point_uses() {
    let vs = compile(TRIANGLE, "main_vs", Stage::Vertex, &Options::default()).unwrap().reflection;
    assert_eq!(
        vs.bindings,
        vec![Binding {
            group: 0,
            binding: 0,
            name: Some("globals".into()),
            kind: BindingKind::UniformBuffer { min_size: 80 }
        }]
    );
    assert_eq!(
        vs.vertex_inputs,
        vec![
            VertexInput { location: 0, name: Some("position".into()), ty: f32x(3) },
            VertexInput { location: 2, name: Some("uv".into()), ty: f32x(2) },
        ]
    );
    assert!(vs.color_outputs.is_empty());
    assert_eq!(vs.workgroup_size, None);

    let ps = compile(TRIANGLE, "main_ps", Stage::Fragment, &Options::default()).unwrap().reflection;
    let kinds: Vec<_> = ps.bindings.iter().map(|b| (b.group, b.binding, b.kind.clone())).collect();
    assert_eq!(
        kinds,
        vec![
            (0, 0, BindingKind::UniformBuffer { min_size: 80 }),
            (1, 0, BindingKind::Texture { dim: TextureDim::D2, sample: SampleKind::Float, multisampled: false }),
            (1, 1, BindingKind::Sampler { comparison: false }),
        ]
    );
    assert_eq!(ps.color_outputs, vec![ColorOutput { location: 0, ty: f32x(4) }]);
}

#[test]
fn compute_reflection_has_workgroup_size_and_storage() {
    let src = r#"
@group(0) @binding(0) var<storage, read_write> data: array<vec4<f32>>;
@group(0) @binding(1) var out_tex: texture_storage_2d<rgba16float, write>;
@compute @workgroup_size(8, 4, 1)
fn cs(@builtin(global_invocation_id) id: vec3<u32>) {
    data[id.x] = data[id.x] * 2.0;
    textureStore(out_tex, vec2<i32>(id.xy), data[id.x]);
}
"#;
    let r = compile(src, "cs", Stage::Compute, &Options::default()).unwrap().reflection;
    assert_eq!(r.workgroup_size, Some([8, 4, 1]));
    assert_eq!(r.bindings[0].kind, BindingKind::StorageBuffer { read_only: false, min_size: 16 });
    assert_eq!(
        r.bindings[1].kind,
        BindingKind::StorageTexture {
            dim: TextureDim::D2,
            format: "rgba16float".into(),
            access: crate::archive::StorageAccess::WriteOnly
        }
    );
}

#[test]
fn missing_entry_point_lists_the_ones_there() {
    let e = compile(TRIANGLE, "main", Stage::Vertex, &Options::default()).unwrap_err();
    assert_eq!(e.kind, ErrorKind::EntryPoint);
    assert_eq!(e.message, "no entry point named `main`");
    assert_eq!(e.notes, vec!["the module's entry points: `main_vs` (vertex), `main_ps` (fragment)".to_string()]);
}

#[test]
fn wrong_stage_points_at_the_function() {
    let e = compile(TRIANGLE, "main_ps", Stage::Vertex, &Options::default()).unwrap_err();
    assert_eq!(e.message, "entry point `main_ps` is a fragment shader, not a vertex shader");
    let (range, label) = &e.labels[0];
    assert_eq!(&TRIANGLE[range.clone()], "main_ps");
    assert_eq!(label, "declared as a fragment entry point here");
}

#[test]
fn parse_error_has_a_span_in_the_preprocessed_text() {
    let src = "@fragment\nfn main_ps() -> @location(0) vec4<f32> {\n    return vec4<f32>(1.0) +;\n}\n";
    let e = compile(src, "main_ps", Stage::Fragment, &Options::default()).unwrap_err();
    assert_eq!(e.kind, ErrorKind::Parse);
    assert_eq!(e.message, "expected expression, found \";\"");
    assert_eq!(&src[e.labels[0].0.clone()], ";");
}

#[test]
fn validation_error_has_spans_and_notes() {
    let src =
        "@fragment\nfn main_ps() -> @location(0) vec4<f32> {\n    let x: u32 = 1u;\n    return vec4<f32>(x);\n}\n";
    let e = compile(src, "main_ps", Stage::Fragment, &Options::default()).unwrap_err();
    assert!(matches!(e.kind, ErrorKind::Validation | ErrorKind::Parse), "{e:?}");
    assert!(!e.labels.is_empty(), "{e:?}");
}

#[test]
fn downlevel_rejects_storage_buffers_in_vertex_shaders() {
    let src = r#"
@group(0) @binding(3) var<storage, read> positions: array<vec4<f32>>;
@vertex
fn vs(@builtin(vertex_index) i: u32) -> @builtin(position) vec4<f32> { return positions[i]; }
"#;
    let options = Options { targets: vec![Target::Wgsl], limits: Limits::downlevel() };
    let e = compile(src, "vs", Stage::Vertex, &options).unwrap_err();
    assert_eq!(e.kind, ErrorKind::Limit);
    assert_eq!(
        e.message,
        "binding `positions` is a storage buffer in a vertex shader, which the downlevel limits do not allow"
    );
    assert_eq!(&src[e.labels[0].0.clone()], "var<storage, read> positions: array<vec4<f32>>;");
    assert!(compile(src, "vs", Stage::Vertex, &Options { limits: Limits::desktop(), ..options }).is_ok());
}

#[test]
fn downlevel_counts_storage_buffers_per_stage() {
    let mut src = String::new();
    for i in 0..5 {
        src += &format!("@group(0) @binding({i}) var<storage, read_write> b{i}: array<u32>;\n");
    }
    src += "@compute @workgroup_size(1)\nfn cs() {\n";
    for i in 0..5 {
        src += &format!("    b{i}[0] = 1u;\n");
    }
    src += "}\n";
    let options = Options { targets: vec![Target::Spirv], limits: Limits::downlevel() };
    let e = compile(&src, "cs", Stage::Compute, &options).unwrap_err();
    assert_eq!(e.message, "binding `b4` is the 5th storage buffer of the compute stage, over the downlevel limit of 4 storage buffers per stage");
    assert_eq!(e.notes, vec!["max_storage_buffers_per_shader_stage = 4 at the downlevel limits".to_string()]);
    assert!(compile(&src, "cs", Stage::Compute, &Options { limits: Limits::desktop(), ..options }).is_ok());
}

#[test]
fn downlevel_limits_color_outputs_and_uniform_size() {
    let src = r#"
struct Out { @location(0) a: vec4<f32>, @location(4) b: vec4<f32> }
@fragment fn ps() -> Out { return Out(vec4<f32>(0.0), vec4<f32>(1.0)); }
"#;
    let options = Options { targets: vec![Target::Wgsl], limits: Limits::downlevel() };
    let e = compile(src, "ps", Stage::Fragment, &options).unwrap_err();
    assert_eq!(e.message, "color output @location(4) is beyond the downlevel limit of 4 color attachments");

    let src = r#"
@group(0) @binding(0) var<uniform> big: array<vec4<f32>, 1025>;
@fragment fn ps() -> @location(0) vec4<f32> { return big[3]; }
"#;
    let e = compile(src, "ps", Stage::Fragment, &options).unwrap_err();
    assert_eq!(e.message, "uniform buffer `big` is 16400 bytes, over the downlevel limit of 16384 bytes");
}

#[test]
fn downlevel_has_no_cube_arrays() {
    let src = r#"
@group(0) @binding(0) var t: texture_cube_array<f32>;
@group(0) @binding(1) var s: sampler;
@fragment fn ps() -> @location(0) vec4<f32> { return textureSample(t, s, vec3<f32>(1.0), 0); }
"#;
    let options = Options { targets: vec![Target::Wgsl], limits: Limits::downlevel() };
    let e = compile(src, "ps", Stage::Fragment, &options).unwrap_err();
    assert_eq!(e.kind, ErrorKind::Validation);
    assert!(compile(src, "ps", Stage::Fragment, &Options { limits: Limits::desktop(), ..options }).is_ok());
}

#[test]
fn only_what_the_entry_point_uses_is_validated() {
    // A shared header's desktop helper (a cube array texture) next to a mobile entry point
    // that never calls it: the mobile permutation compiles; the one that calls it does not.
    let src = r#"
@group(0) @binding(0) var t: texture_cube_array<f32>;
@group(0) @binding(1) var s: sampler;
fn desktop_only() -> vec4<f32> { return textureSample(t, s, vec3<f32>(1.0), 0); }
@fragment fn mobile_ps() -> @location(0) vec4<f32> { return vec4<f32>(0.5); }
@fragment fn desktop_ps() -> @location(0) vec4<f32> { return desktop_only(); }
"#;
    let options = Options { targets: vec![Target::Wgsl, Target::Glsl], limits: Limits::downlevel() };
    let out = compile(src, "mobile_ps", Stage::Fragment, &options).unwrap();
    let wgsl = std::str::from_utf8(&out.artifacts[0].1).unwrap();
    assert!(!wgsl.contains("desktop_only") && !wgsl.contains("texture_cube_array"), "{wgsl}");
    let e = compile(src, "desktop_ps", Stage::Fragment, &options).unwrap_err();
    assert_eq!(e.kind, ErrorKind::Validation);
    assert!(e.message.contains("capability") || e.notes.iter().any(|n| n.contains("CUBE_ARRAY")), "{e:?}");
}

#[test]
fn workgroup_limits() {
    let src = "@compute @workgroup_size(512) fn cs() {}";
    let e = compile(src, "cs", Stage::Compute, &Options::default()).unwrap_err();
    assert_eq!(e.message, "workgroup size (512, 1, 1) is 512 along x, over the desktop limit of 256");
    let src = "var<workgroup> tile: array<vec4<f32>, 1024>;\n@compute @workgroup_size(64) fn cs() { tile[0] = vec4<f32>(1.0); }";
    let options = Options { targets: vec![Target::Wgsl], limits: Limits::downlevel() };
    let e = compile(src, "cs", Stage::Compute, &options).unwrap_err();
    assert_eq!(e.message, "workgroup variables take 16384 bytes up to `tile`, over the downlevel limit of 16352 bytes");
    assert!(compile(src, "cs", Stage::Compute, &Options::default()).is_ok());
}

#[test]
fn writer_failures_become_errors() {
    // f64 is rejected by validation at both levels (no FLOAT64 capability), never reaching
    // the MSL writer's panic.
    let src = "@fragment fn ps() -> @location(0) vec4<f32> { let x: f64 = 1.0lf; return vec4<f32>(f32(x)); }";
    let e = compile(src, "ps", Stage::Fragment, &Options::default()).unwrap_err();
    assert_eq!(e.kind, ErrorKind::Validation);
}

#[test]
fn a_panicking_writer_is_an_error_of_the_permutation() {
    let e = writers::guarded(Target::Msl, || panic!("unsupported scalar width")).unwrap_err();
    assert_eq!(e.kind, ErrorKind::Writer(Target::Msl));
    assert_eq!(e.message, "the msl writer panicked: unsupported scalar width");
    assert_eq!(e.notes, vec![format!("naga {NAGA_VERSION} cannot write this shader as msl")]);
    let e = writers::guarded(Target::Hlsl, || Err("no".to_string())).unwrap_err();
    assert_eq!(e.message, "the hlsl writer failed: no");
    // Later panics outside writers still reach the normal hook (and the flag is reset).
    assert_eq!(writers::guarded(Target::Wgsl, || Ok(vec![1])).unwrap(), vec![1]);
}

#[test]
fn naga_version_matches_cargo_lock() {
    let lock = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../Cargo.lock")).unwrap();
    let at = lock.find("name = \"naga\"\nversion = \"").expect("naga in Cargo.lock");
    let rest = &lock[at + "name = \"naga\"\nversion = \"".len()..];
    assert_eq!(&rest[..rest.find('"').unwrap()], NAGA_VERSION);
}

#[test]
fn find_function_skips_other_identifiers() {
    let src = "fn main_ps_helper() {}\n// main_ps\nfn  main_ps() {}";
    let r = find_function(src, "main_ps").unwrap();
    assert_eq!(r, 38..45);
}
