// hello_ps.wgsl: one flat color. PALETTE picks it; TINT=1 multiplies it by a uniform the
// app fills (so only the TINT=1 permutations have a binding: the runtime makes each
// pipeline's bind group layout from its permutations' reflection).
#include "hello_common.wgsl"

#if TINT
struct HelloTint {
    color: vec4<f32>,
}

@group(0) @binding(0) var<uniform> Tint: HelloTint;
#endif

@fragment
fn main_ps(input: HelloVSToPS) -> @location(0) vec4<f32> {
#if PALETTE == PALETTE_COOL
    var color = vec4<f32>(0.2, 0.6, 1.0, 1.0);
#else
    var color = vec4<f32>(1.0, 0.6, 0.2, 1.0);
#endif
#if TINT
    color = color * Tint.color;
#endif
    return color;
}
