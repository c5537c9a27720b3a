// language: metal2.4
#include <metal_stdlib>
#include <simd/simd.h>

using metal::uint;

struct View {
    metal::float4x4 view_proj;
    metal::float4x4 model;
    metal::float4 camera;
};
struct VsOut {
    metal::float4 clip;
    metal::float3 world;
    metal::float3 normal;
    metal::float2 uv;
    char _pad4[8];
};
struct Light {
    metal::float4 position;
    metal::float4 color;
};
struct type_7 {
    Light inner[2];
};

float Lambert(
    metal::float3 n,
    metal::float3 to_light
) {
    return metal::clamp(metal::dot(metal::normalize(n), metal::normalize(to_light)), 0.0, 1.0);
}

struct main_psInput {
    metal::float3 world [[user(loc0), center_perspective]];
    metal::float3 normal [[user(loc1), center_perspective]];
    metal::float2 uv [[user(loc2), center_perspective]];
};
struct main_psOutput {
    metal::float4 member [[color(0)]];
};
fragment main_psOutput main_ps(
  main_psInput varyings [[stage_in]]
, metal::float4 clip [[position]]
, metal::texture2d<float, metal::access::sample> base_color [[user(fake0)]]
, metal::sampler base_sampler [[user(fake0)]]
, constant type_7& lights [[user(fake0)]]
) {
    const VsOut i = { clip, varyings.world, varyings.normal, varyings.uv };
    metal::float3 color = {};
    uint l = 0u;
    metal::float4 albedo = base_color.sample(base_sampler, i.uv);
    color = albedo.xyz * metal::float3(0.03, 0.03, 0.04);
    uint2 loop_bound = uint2(4294967295u);
    bool loop_init = true;
    while(true) {
        if (metal::all(loop_bound == uint2(0u))) { break; }
        loop_bound -= uint2(loop_bound.y == 0u, 1u);
        if (!loop_init) {
            uint _e39 = l;
            l = _e39 + 1u;
        }
        loop_init = false;
        uint _e14 = l;
        if (_e14 < 2u) {
        } else {
            break;
        }
        {
            metal::float3 _e17 = color;
            uint _e20 = l;
            metal::float4 _e23 = lights.inner[_e20].position;
            float _e27 = Lambert(i.normal, _e23.xyz - i.world);
            uint _e29 = l;
            metal::float4 _e32 = lights.inner[_e29].color;
            color = _e17 + ((_e27 * _e32.xyz) * albedo.xyz);
        }
    }
    metal::float3 _e41 = color;
    return main_psOutput { metal::float4(_e41, albedo.w) };
}
