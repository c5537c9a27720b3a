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
struct Light {
    vec4 position;
    vec4 color;
};
const float FOG_DENSITY = 0.02;

uniform highp sampler2D _group_1_binding_0_fs;

layout(std140) uniform type_7_block_0Fragment { Light _group_2_binding_0_fs[2]; };

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
    uint l = 0u;
    vec4 albedo = texture(_group_1_binding_0_fs, vec2(i.uv));
    color = (albedo.xyz * vec3(0.03, 0.03, 0.04));
    bool loop_init = true;
    while(true) {
        if (!loop_init) {
            uint _e39 = l;
            l = (_e39 + 1u);
        }
        loop_init = false;
        uint _e14 = l;
        if ((_e14 < 2u)) {
        } else {
            break;
        }
        {
            vec3 _e17 = color;
            uint _e20 = l;
            vec4 _e23 = _group_2_binding_0_fs[_e20].position;
            float _e27 = Lambert(i.normal, (_e23.xyz - i.world));
            uint _e29 = l;
            vec4 _e32 = _group_2_binding_0_fs[_e29].color;
            color = (_e17 + ((_e27 * _e32.xyz) * albedo.xyz));
        }
    }
    vec3 _e41 = color;
    color = mix(_e41, vec3(0.5, 0.6, 0.7), i.fog);
    vec3 _e48 = color;
    _fs2p_location0 = vec4(_e48, albedo.w);
    return;
}

