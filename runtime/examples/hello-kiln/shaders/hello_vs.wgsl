// hello_vs.wgsl: a shape in the middle of the viewport, from the vertex index (no vertex
// buffers). SHAPE=TRIANGLE: 3 vertices, corners (-0.5, -0.5), (0.5, -0.5), (0, 0.5).
// SHAPE=QUAD: 6 vertices covering [-0.5, 0.5] x [-0.5, 0.5] in clip space.
#include "hello_common.wgsl"

@vertex
fn main_vs(@builtin(vertex_index) vertex_index: u32) -> HelloVSToPS {
#if SHAPE == SHAPE_QUAD
    var corners = array<vec2<f32>, 6>(
        vec2<f32>(-0.5, -0.5), vec2<f32>(0.5, -0.5), vec2<f32>(0.5, 0.5),
        vec2<f32>(-0.5, -0.5), vec2<f32>(0.5, 0.5), vec2<f32>(-0.5, 0.5),
    );
    let corner = corners[vertex_index % 6u];
#else
    var corners = array<vec2<f32>, 3>(vec2<f32>(-0.5, -0.5), vec2<f32>(0.5, -0.5), vec2<f32>(0.0, 0.5));
    let corner = corners[vertex_index % 3u];
#endif
    var out: HelloVSToPS;
    out.position = vec4<f32>(corner, 0.0, 1.0);
    return out;
}
