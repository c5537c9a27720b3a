#version 310 es

precision highp float;
precision highp int;

layout(local_size_x = 64, local_size_y = 1, local_size_z = 1) in;

struct View {
    mat4x4 view_proj;
    mat4x4 model;
    vec4 camera;
};
layout(std140) uniform View_block_0Compute { View _group_0_binding_0_cs; };

uniform highp sampler2D _group_0_binding_1_cs;

layout(std430) buffer type_7_block_1Compute { uint _group_0_binding_2_cs[64]; };

layout(rgba8) writeonly uniform highp image2D _group_0_binding_3_cs;

shared uint local_bins[64];


float Lambert(vec3 n, vec3 to_light) {
    return clamp(dot(normalize(n), normalize(to_light)), 0.0, 1.0);
}

void main() {
    if (gl_LocalInvocationID == uvec3(0u)) {
        local_bins = uint[64](0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u);
    }
    memoryBarrierShared();
    barrier();
    uvec3 id = gl_GlobalInvocationID;
    uint li = gl_LocalInvocationIndex;
    if ((li < 64u)) {
        atomicExchange(local_bins[li], 0u);
    }
    memoryBarrierShared();
    barrier();
    uvec2 size = uvec2(textureSize(_group_0_binding_1_cs, 0).xy);
    if (all(lessThan(id.xy, size))) {
        vec4 _e16 = texelFetch(_group_0_binding_1_cs, ivec2(id.xy), 0);
        vec3 c = _e16.xyz;
        float _e26 = _group_0_binding_0_cs.camera.w;
        float lum = (dot(c, vec3(0.2126, 0.7152, 0.0722)) * _e26);
        uint bin = uint((clamp(lum, 0.0, 1.0) * 63.0));
        uint _e37 = atomicAdd(local_bins[bin], 1u);
        imageStore(_group_0_binding_3_cs, ivec2(id.xy), vec4(lum));
    }
    memoryBarrierShared();
    barrier();
    if ((li < 64u)) {
        uint _e48 = atomicOr(local_bins[li], 0u);
        uint _e49 = atomicAdd(_group_0_binding_2_cs[li], _e48);
        return;
    } else {
        return;
    }
}

