// hello_common.wgsl: what the example's vertex shader hands its pixel shader.

struct HelloVSToPS {
    @builtin(position) position: vec4<f32>,
}
