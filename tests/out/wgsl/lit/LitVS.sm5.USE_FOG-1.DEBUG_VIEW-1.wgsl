struct View {
    view_proj: mat4x4<f32>,
    model: mat4x4<f32>,
    camera: vec4<f32>,
}

struct VsOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) world: vec3<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) uv: vec2<f32>,
    @location(3) fog: f32,
}

const FOG_DENSITY: f32 = 0.02f;

@group(0) @binding(0) 
var<uniform> view: View;
@group(1) @binding(0) 
var base_color: texture_2d<f32>;
@group(1) @binding(1) 
var base_sampler: sampler;

fn Lambert(n: vec3<f32>, to_light: vec3<f32>) -> f32 {
    return clamp(dot(normalize(n), normalize(to_light)), 0f, 1f);
}

fn FogFactor(world: vec3<f32>, camera: vec3<f32>) -> f32 {
    let d = distance(world, camera);
    return clamp((1f - exp((-(d) * FOG_DENSITY))), 0f, 1f);
}

@vertex 
fn main_vs(@location(0) position: vec3<f32>, @location(1) normal: vec3<f32>, @location(2) uv: vec2<f32>) -> VsOut {
    var o: VsOut;

    let _e6 = view.model;
    let world_1 = (_e6 * vec4<f32>(position, 1f)).xyz;
    let _e14 = view.view_proj;
    o.clip = (_e14 * vec4<f32>(world_1, 1f));
    o.world = world_1;
    o.normal = normal;
    o.uv = uv;
    let _e24 = view.camera;
    let _e26 = FogFactor(world_1, _e24.xyz);
    o.fog = _e26;
    let _e27 = o;
    return _e27;
}
