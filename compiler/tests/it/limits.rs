//! Limits per level: `limits = "default" | "downlevel" | { base = ..., <wgpu Limits field> = value }`.

use std::path::Path;
use std::process::Output;

/// A compute shader writing 6 storage textures: over WebGPU's default of 4 per stage, within
/// what D3D11.1- and Vulkan-class desktop hardware runs.
const SHADER: &str = r#"
@group(0) @binding(0) var t0: texture_storage_2d<rgba8unorm, write>;
@group(0) @binding(1) var t1: texture_storage_2d<rgba8unorm, write>;
@group(0) @binding(2) var t2: texture_storage_2d<rgba8unorm, write>;
@group(0) @binding(3) var t3: texture_storage_2d<rgba8unorm, write>;
@group(0) @binding(4) var t4: texture_storage_2d<rgba8unorm, write>;
@group(0) @binding(5) var t5: texture_storage_2d<rgba8unorm, write>;

@compute @workgroup_size(8, 8, 1)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let c = vec4<f32>(f32(STRENGTH) / 4.0);
    textureStore(t0, id.xy, c);
    textureStore(t1, id.xy, c);
    textureStore(t2, id.xy, c);
    textureStore(t3, id.xy, c);
    textureStore(t4, id.xy, c);
    textureStore(t5, id.xy, c);
}
"#;

fn config(limits: &str) -> String {
    format!(
        "[compiler]\ninclude = [\".\"]\n\n[levels.sm5]\ndefines = {{ SM5_PROFILE = 1 }}\ntargets = [\"spirv\", \"wgsl\"]\n{limits}\n\n\
         [[shader]]\nname = \"BlurCS\"\nsource = \"blur.usf\"\nentry = \"main\"\nstage = \"compute\"\n\
         dimensions = {{ STRENGTH = [1, 2] }}\n"
    )
}

fn build(dir: &Path, limits: &str) -> Output {
    std::fs::write(dir.join("blur.usf"), SHADER).unwrap();
    std::fs::write(dir.join("permutations.toml"), config(limits)).unwrap();
    crate::kiln_command()
        .args(["build", "--config", "permutations.toml", "--no-cache", "-o", "out.kpak"])
        .current_dir(dir)
        .output()
        .unwrap()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

#[test]
fn six_storage_textures_need_a_raised_limit() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();

    for limits in ["", "limits = \"default\"", "limits = { base = \"default\" }"] {
        let o = build(d, limits);
        assert_eq!(o.status.code(), Some(1), "{limits}: {}", stderr(&o));
        let e = stderr(&o);
        assert!(e.contains("over the desktop limit of 4 storage textures per stage"), "{e}");
        assert!(e.contains("max_storage_textures_per_shader_stage = 4 at the desktop limits"), "{e}");
        assert!(e.contains("BlurCS@sm5{STRENGTH=1}") && e.contains("blur.usf:6:23"), "{e}");
        assert!(!d.join("out.kpak").exists());
    }

    let o = build(d, "limits = { base = \"default\", max_storage_textures_per_shader_stage = 8 }");
    assert!(o.status.success(), "{}", stderr(&o));
    let archive = kiln::archive::Archive::open(&d.join("out.kpak")).unwrap();
    assert_eq!(archive.permutations().unwrap().count(), 2);

    // Lowered below what the shader uses: the error says where the value comes from.
    let o = build(d, "limits = { max_storage_textures_per_shader_stage = 5 }");
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    let e = stderr(&o);
    assert!(e.contains("max_storage_textures_per_shader_stage = 5, as the level's `limits` table sets it"), "{e}");

    // Downlevel as the base keeps its other limits.
    let o = build(d, "limits = { base = \"downlevel\", max_storage_textures_per_shader_stage = 8 }");
    assert!(o.status.success(), "{}", stderr(&o));
}

#[test]
fn bad_limits_are_located_config_errors() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let o = build(d, "limits = { base = \"default\", max_storage_texture_per_shader_stage = 8 }");
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    let e = stderr(&o);
    assert!(e.contains("error: unknown limit `max_storage_texture_per_shader_stage`"), "{e}");
    assert!(e.contains("permutations.toml:7:30"), "{e}");
    assert!(e.contains("such as `max_storage_textures_per_shader_stage`"), "{e}");

    let o = build(d, "limits = { max_storage_textures_per_shader_stage = \"8\" }");
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    let e = stderr(&o);
    assert!(
        e.contains(
            "limit `max_storage_textures_per_shader_stage` takes a non-negative integer (u32), not the string \"8\""
        ),
        "{e}"
    );
    assert!(e.contains("permutations.toml:7:52"), "{e}");

    let o = build(d, "limits = { max_bind_groups = -1 }");
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("takes a non-negative integer (u32), not -1"), "{}", stderr(&o));

    let o = build(d, "limits = { base = \"mobile\" }");
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("`base` is \"default\" or \"downlevel\""), "{}", stderr(&o));

    let o = build(d, "limits = \"mobile\"");
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("unknown variant `mobile`, expected `default` or `downlevel`"), "{}", stderr(&o));

    let o = build(d, "limits = 4");
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("permutations.toml:7:10"), "{}", stderr(&o));
}
