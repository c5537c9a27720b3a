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
};
layout(std140) uniform View_block_0Vertex { View _group_0_binding_0_vs; };

layout(location = 0) in vec3 _p2vs_location0;
layout(location = 1) in vec3 _p2vs_location1;
layout(location = 2) in vec2 _p2vs_location2;
layout(location = 0) smooth out vec3 _vs2fs_location0;
layout(location = 1) smooth out vec3 _vs2fs_location1;
layout(location = 2) smooth out vec2 _vs2fs_location2;

float Lambert(vec3 n, vec3 to_light) {
    return clamp(dot(normalize(n), normalize(to_light)), 0.0, 1.0);
}

void main() {
    vec3 position = _p2vs_location0;
    vec3 normal = _p2vs_location1;
    vec2 uv = _p2vs_location2;
    VsOut o = VsOut(vec4(0.0), vec3(0.0), vec3(0.0), vec2(0.0));
    mat4x4 _e6 = _group_0_binding_0_vs.model;
    vec3 world = (_e6 * vec4(position, 1.0)).xyz;
    mat4x4 _e14 = _group_0_binding_0_vs.view_proj;
    o.clip = (_e14 * vec4(world, 1.0));
    o.world = world;
    o.normal = normal;
    o.uv = uv;
    VsOut _e21 = o;
    gl_Position = _e21.clip;
    _vs2fs_location0 = _e21.world;
    _vs2fs_location1 = _e21.normal;
    _vs2fs_location2 = _e21.uv;
    gl_Position.yz = vec2(-gl_Position.y, gl_Position.z * 2.0 - gl_Position.w);
    return;
}

