struct View {
    view_proj: mat4x4<f32>,
    model: mat4x4<f32>,
    camera: vec4<f32>,
}

@group(0) @binding(0) 
var<uniform> view: View;
@group(0) @binding(1) 
var input: texture_2d<f32>;
@group(0) @binding(2) 
var<storage, read_write> histogram: array<atomic<u32>, 64>;
@group(0) @binding(3) 
var debug_out: texture_storage_2d<rgba8unorm,write>;
var<workgroup> local_bins: array<atomic<u32>, 64>;

fn Lambert(n: vec3<f32>, to_light: vec3<f32>) -> f32 {
    return clamp(dot(normalize(n), normalize(to_light)), 0f, 1f);
}

@compute @workgroup_size(64, 1, 1) 
fn main_cs(@builtin(global_invocation_id) id: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    if (li < 64u) {
        atomicStore((&local_bins[li]), 0u);
    }
    workgroupBarrier();
    let size = textureDimensions(input);
    if all((id.xy < size)) {
        let _e16 = textureLoad(input, vec2<i32>(id.xy), 0i);
        let c = _e16.xyz;
        let _e26 = view.camera.w;
        let lum = (dot(c, vec3<f32>(0.2126f, 0.7152f, 0.0722f)) * _e26);
        let bin = u32((clamp(lum, 0f, 1f) * 63f));
        let _e37 = atomicAdd((&local_bins[bin]), 1u);
        textureStore(debug_out, vec2<i32>(id.xy), vec4(lum));
    }
    workgroupBarrier();
    if (li < 64u) {
        let _e48 = atomicLoad((&local_bins[li]));
        let _e49 = atomicAdd((&histogram[li]), _e48);
        return;
    } else {
        return;
    }
}
