#version 310 es

precision highp float;
precision highp int;

struct View {
    mat4x4 view_proj;
    mat4x4 model;
    vec4 camera;
};
struct VsOut {
    vec4 clip;
    vec3 world;
    vec3 normal;
    vec2 uv;
    float fog;
};
const float FOG_DENSITY = 0.02;

uniform highp sampler2D _group_1_binding_0_fs;

layout(location = 0) smooth in vec3 _vs2fs_location0;
layout(location = 1) smooth in vec3 _vs2fs_location1;
layout(location = 2) smooth in vec2 _vs2fs_location2;
layout(location = 3) smooth in float _vs2fs_location3;
layout(location = 0) out vec4 _fs2p_location0;

float Lambert(vec3 n, vec3 to_light) {
    return clamp(dot(normalize(n), normalize(to_light)), 0.0, 1.0);
}

float FogFactor(vec3 world, vec3 camera) {
    float d = distance(world, camera);
    return clamp((1.0 - exp((-(d) * FOG_DENSITY))), 0.0, 1.0);
}

void main() {
    VsOut i = VsOut(gl_FragCoord, _vs2fs_location0, _vs2fs_location1, _vs2fs_location2, _vs2fs_location3);
    vec3 color = vec3(0.0);
    vec4 albedo = texture(_group_1_binding_0_fs, vec2(i.uv));
    if ((albedo.w < 0.5)) {
        discard;
    }
    color = (albedo.xyz * vec3(0.03, 0.03, 0.04));
    vec3 _e15 = color;
    color = mix(_e15, vec3(0.5, 0.6, 0.7), i.fog);
    vec3 _e22 = color;
    _fs2p_location0 = vec4(_e22, albedo.w);
    return;
}

