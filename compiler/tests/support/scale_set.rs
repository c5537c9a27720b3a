//! A generated `scale`-style permutation set: materials multiply the domain, as in an
//! engine where every material compiles its own base pass, shadow and vertex shaders.
//!
//! Three shaders (a base pass pixel shader, its vertex shader, a masked shadow-depth pixel
//! shader) at two levels (`sm5`: spirv, msl, hlsl, wgsl; `es3_1`, downlevel: glsl, spirv,
//! msl, wgsl), each with a `MATERIAL` range dimension. A material's number picks its
//! features (normal map, detail texture, 0 to 3 blend layers, masked, 4 kinds of vertex
//! animation) and its constants, so nearly every pixel-shader permutation is a distinct
//! key, while vertex shaders share keys between materials with the same vertex animation.
//! 16 permutations per material (10 base pass, 4 vertex, 2 shadow).
//!
//! Shared by `cargo bench -p kiln --bench scale` and the build tests (`#[path]` module).

#![allow(dead_code)]

use std::path::{Path, PathBuf};

/// Permutations per material.
pub const PER_MATERIAL: usize = 16;

/// Writes a set of about `permutations` permutations into `dir`; returns its config path
/// and the exact count of kept permutations.
pub fn write(dir: &Path, permutations: usize) -> (PathBuf, usize) {
    let materials = permutations.div_ceil(PER_MATERIAL).max(1);
    std::fs::create_dir_all(dir).unwrap();
    std::fs::write(dir.join("Common.ush"), COMMON).unwrap();
    std::fs::write(dir.join("Material.ush"), MATERIAL).unwrap();
    std::fs::write(dir.join("BasePassVS.usf"), BASE_VS).unwrap();
    std::fs::write(dir.join("BasePassPS.usf"), BASE_PS).unwrap();
    std::fs::write(dir.join("ShadowDepthPS.usf"), SHADOW_PS).unwrap();
    let config = CONFIG.replace("LAST_MATERIAL", &(materials - 1).to_string());
    let path = dir.join("permutations.toml");
    std::fs::write(&path, config).unwrap();
    (path, materials * PER_MATERIAL)
}

const CONFIG: &str = r#"# Generated: materials multiply the domain (compiler/tests/support/scale_set.rs).
[compiler]
include = ["."]

[levels.sm5]
defines = { FEATURE_LEVEL = 5 }
targets = ["spirv", "msl", "hlsl", "wgsl"]

[levels.es3_1]
defines = { FEATURE_LEVEL = 3 }
targets = ["glsl", "spirv", "msl", "wgsl"]
limits = "downlevel"

[[shader]]
name = "BasePassPS"
source = "BasePassPS.usf"
entry = "main_ps"
stage = "fragment"
levels = ["sm5", "es3_1"]
dimensions = { MATERIAL = { range = [0, LAST_MATERIAL] }, USE_FOG = "bool", NUM_LIGHTS = [1, 2, 4] }
skip = [ { when = "FEATURE_LEVEL == 3 && NUM_LIGHTS == 4", why = "mobile shades at most two lights" } ]

[[shader]]
name = "BasePassVS"
source = "BasePassVS.usf"
entry = "main_vs"
stage = "vertex"
levels = ["sm5", "es3_1"]
dimensions = { MATERIAL = { range = [0, LAST_MATERIAL] }, USE_SKINNING = "bool" }

[[shader]]
name = "ShadowDepthPS"
source = "ShadowDepthPS.usf"
entry = "main_ps"
stage = "fragment"
levels = ["sm5"]
dimensions = { MATERIAL = { range = [0, LAST_MATERIAL] }, MASKED = "bool" }
"#;

const COMMON: &str = r#"// Shared by every shader of the set.
#pragma once

struct View {
    view_proj: mat4x4<f32>,
    camera: vec4<f32>,
    fog: vec4<f32>,
    time: vec4<f32>,
};

struct Light {
    position: vec4<f32>,
    color: vec4<f32>,
};

struct Lights {
    l: array<Light, 4>,
};

struct VSOut {
    @builtin(position) pos: vec4<f32>,
    @location(0) uv: vec2<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) world: vec3<f32>,
};

@group(0) @binding(0) var<uniform> view: View;
@group(0) @binding(1) var<uniform> lights: Lights;

fn hash3(p: vec3<f32>) -> f32 {
    return fract(sin(dot(p, vec3<f32>(12.9898, 78.233, 37.719))) * 43758.5453);
}
"#;

const MATERIAL: &str = r#"// One material, chosen by MATERIAL: its bits pick features, its value the constants.
#pragma once
#include "Common.ush"

struct MaterialOut {
    base_color: vec3<f32>,
    roughness: f32,
    specular: f32,
    opacity: f32,
};

@group(1) @binding(0) var material_sampler: sampler;
@group(1) @binding(1) var base_texture: texture_2d<f32>;
#if (MATERIAL / 4) % 2
@group(1) @binding(2) var normal_texture: texture_2d<f32>;
#endif
#if (MATERIAL / 8) % 2
@group(1) @binding(3) var detail_texture: texture_2d<f32>;
#endif

fn material(uv: vec2<f32>, n: vec3<f32>) -> MaterialOut {
    var m: MaterialOut;
    let id = f32(MATERIAL);
    let tint = vec3<f32>(fract(id * 0.137), fract(id * 0.311), fract(id * 0.719));
    m.base_color = textureSample(base_texture, material_sampler, uv * (1.0 + fract(id * 0.05))).rgb * tint;
    m.roughness = fract(id * 0.0731);
    m.specular = 0.5;
    m.opacity = 1.0;
#if (MATERIAL / 4) % 2
    let nt = textureSample(normal_texture, material_sampler, uv).xyz * 2.0 - 1.0;
    m.roughness = m.roughness * (0.5 + 0.5 * nt.z);
#endif
#if (MATERIAL / 8) % 2
    let detail = textureSample(detail_texture, material_sampler, uv * 8.0);
    m.base_color = m.base_color * detail.rgb * 2.0;
#endif
#if (MATERIAL / 16) % 4 >= 1
    for (var layer = 0; layer < (MATERIAL / 16) % 4; layer++) {
        let w = 0.25 * f32(layer + 1) * hash3(vec3<f32>(uv, f32(layer)));
        m.base_color = mix(m.base_color, tint.zxy, w);
        m.roughness = mix(m.roughness, fract(id * 0.017 + f32(layer)), w);
    }
#endif
#if MATERIAL % 2
    m.opacity = textureSample(base_texture, material_sampler, uv).a;
#endif
    return m;
}
"#;

const BASE_VS: &str = r#"// Base pass vertex shader: skinning, and the material's vertex animation.
#include "Common.ush"

struct VSIn {
    @location(0) position: vec3<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) uv: vec2<f32>,
#if USE_SKINNING
    @location(3) joints: vec4<u32>,
    @location(4) weights: vec4<f32>,
#endif
};

#if USE_SKINNING
struct Bones {
    m: array<mat4x4<f32>, 64>,
};
@group(2) @binding(0) var<uniform> bones: Bones;
#endif

@vertex
fn main_vs(input: VSIn) -> VSOut {
    var p = input.position;
    var n = input.normal;
#if USE_SKINNING
    var skin = mat4x4<f32>(vec4<f32>(0.0), vec4<f32>(0.0), vec4<f32>(0.0), vec4<f32>(0.0));
    for (var i = 0; i < 4; i++) {
        skin += bones.m[input.joints[i]] * input.weights[i];
    }
    p = (skin * vec4<f32>(p, 1.0)).xyz;
    n = normalize((skin * vec4<f32>(n, 0.0)).xyz);
#endif
#if MATERIAL % 4 == 1
    p += vec3<f32>(sin(view.time.x + p.y), 0.0, cos(view.time.x + p.x)) * 0.05;
#elif MATERIAL % 4 == 2
    p += n * 0.01 * sin(view.time.x * 3.0);
#elif MATERIAL % 4 == 3
    p.y += hash3(p) * 0.02;
#endif
    var out: VSOut;
    out.pos = view.view_proj * vec4<f32>(p, 1.0);
    out.uv = input.uv;
    out.normal = n;
    out.world = p;
    return out;
}
"#;

const BASE_PS: &str = r#"// Base pass pixel shader: the material, lit by NUM_LIGHTS lights, with optional fog.
#include "Common.ush"
#include "Material.ush"

fn shade(m: MaterialOut, light: Light, world: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    let l = normalize(light.position.xyz - world);
    let v = normalize(view.camera.xyz - world);
    let h = normalize(l + v);
    let ndl = max(dot(n, l), 0.0);
    let ndh = max(dot(n, h), 0.0);
    let spec = pow(ndh, mix(8.0, 128.0, 1.0 - m.roughness));
    return (m.base_color * ndl + vec3<f32>(spec * m.specular)) * light.color.rgb;
}

#if USE_FOG
fn apply_fog(c: vec3<f32>, world: vec3<f32>) -> vec3<f32> {
    let d = distance(view.camera.xyz, world);
    return mix(c, view.fog.rgb, clamp(d * view.fog.w, 0.0, 1.0));
}
#endif

@fragment
fn main_ps(input: VSOut) -> @location(0) vec4<f32> {
    let n = normalize(input.normal);
    let m = material(input.uv, n);
    var color = vec3<f32>(0.0);
    for (var i = 0; i < NUM_LIGHTS; i++) {
        color += shade(m, lights.l[i], input.world, n);
    }
#if USE_FOG
    color = apply_fog(color, input.world);
#endif
    return vec4<f32>(color, m.opacity);
}
"#;

const SHADOW_PS: &str = r#"// Shadow depth pixel shader: masked materials clip on their opacity.
#include "Common.ush"
#include "Material.ush"

@fragment
fn main_ps(input: VSOut) {
#if MASKED
    let m = material(input.uv, normalize(input.normal));
    if m.opacity < 0.5 {
        discard;
    }
#endif
}
"#;
