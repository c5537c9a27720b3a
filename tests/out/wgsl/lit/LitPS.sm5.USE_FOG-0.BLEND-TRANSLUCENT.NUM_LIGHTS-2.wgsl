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
}

struct Light {
    position: vec4<f32>,
    color: vec4<f32>,
}

@group(0) @binding(0) 
var<uniform> view: View;
@group(1) @binding(0) 
var base_color: texture_2d<f32>;
@group(1) @binding(1) 
var base_sampler: sampler;
@group(2) @binding(0) 
var<uniform> lights: array<Light, 2>;

fn Lambert(n: vec3<f32>, to_light: vec3<f32>) -> f32 {
    return clamp(dot(normalize(n), normalize(to_light)), 0f, 1f);
}

@fragment 
fn main_ps(i: VsOut) -> @location(0) vec4<f32> {
    var color: vec3<f32>;
    var l: u32 = 0u;

    let albedo = textureSample(base_color, base_sampler, i.uv);
    color = (albedo.xyz * vec3<f32>(0.03f, 0.03f, 0.04f));
    loop {
        let _e14 = l;
        if (_e14 < 2u) {
        } else {
            break;
        }
        {
            let _e17 = color;
            let _e20 = l;
            let _e23 = lights[_e20].position;
            let _e27 = Lambert(i.normal, (_e23.xyz - i.world));
            let _e29 = l;
            let _e32 = lights[_e29].color;
            color = (_e17 + ((_e27 * _e32.xyz) * albedo.xyz));
        }
        continuing {
            let _e39 = l;
            l = (_e39 + 1u);
        }
    }
    let _e41 = color;
    return vec4<f32>(_e41, albedo.w);
}
