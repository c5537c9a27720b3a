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

layout(std140) uniform View_block_0Vertex { View _group_0_binding_0_vs; };

layout(location = 0) in vec3 _p2vs_location0;
layout(location = 1) in vec3 _p2vs_location1;
layout(location = 2) in vec2 _p2vs_location2;
layout(location = 0) smooth out vec3 _vs2fs_location0;
layout(location = 1) smooth out vec3 _vs2fs_location1;
layout(location = 2) smooth out vec2 _vs2fs_location2;
layout(location = 3) smooth out float _vs2fs_location3;

float Lambert(vec3 n, vec3 to_light) {
    return clamp(dot(normalize(n), normalize(to_light)), 0.0, 1.0);
}

float FogFactor(vec3 world, vec3 camera) {
    float d = distance(world, camera);
    return clamp((1.0 - exp((-(d) * FOG_DENSITY))), 0.0, 1.0);
}

void main() {
    vec3 position = _p2vs_location0;
    vec3 normal = _p2vs_location1;
    vec2 uv = _p2vs_location2;
    VsOut o = VsOut(vec4(0.0), vec3(0.0), vec3(0.0), vec2(0.0), 0.0);
    mat4x4 _e6 = _group_0_binding_0_vs.model;
    vec3 world_1 = (_e6 * vec4(position, 1.0)).xyz;
    mat4x4 _e14 = _group_0_binding_0_vs.view_proj;
    o.clip = (_e14 * vec4(world_1, 1.0));
    o.world = world_1;
    o.normal = normal;
    o.uv = uv;
    vec4 _e24 = _group_0_binding_0_vs.camera;
    float _e26 = FogFactor(world_1, _e24.xyz);
    o.fog = _e26;
    VsOut _e27 = o;
    gl_Position = _e27.clip;
    _vs2fs_location0 = _e27.world;
    _vs2fs_location1 = _e27.normal;
    _vs2fs_location2 = _e27.uv;
    _vs2fs_location3 = _e27.fog;
    gl_Position.yz = vec2(-gl_Position.y, gl_Position.z * 2.0 - gl_Position.w);
    return;
}

