struct VsOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) world: vec3<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) uv: vec2<f32>,
    @location(3) fog: f32,
}

const FOG_DENSITY: f32 = 0.02f;

@group(1) @binding(0) 
var base_color: texture_2d<f32>;
@group(1) @binding(1) 
var base_sampler: sampler;

@fragment 
fn main_ps(i: VsOut) -> @location(0) vec4<f32> {
    var color: vec3<f32>;

    let albedo = textureSample(base_color, base_sampler, i.uv);
    color = (albedo.xyz * vec3<f32>(0.03f, 0.03f, 0.04f));
    let _e12 = color;
    color = mix(_e12, vec3<f32>(0.5f, 0.6f, 0.7f), i.fog);
    let _e19 = color;
    return vec4<f32>(_e19, 1f);
}
