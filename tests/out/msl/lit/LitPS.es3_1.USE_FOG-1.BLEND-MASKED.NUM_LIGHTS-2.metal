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
    float fog;
    char _pad5[4];
};
struct Light {
    metal::float4 position;
    metal::float4 color;
};
struct type_7 {
    Light inner[2];
};
constant float FOG_DENSITY = 0.02;

float Lambert(
    metal::float3 n,
    metal::float3 to_light
) {
    return metal::clamp(metal::dot(metal::normalize(n), metal::normalize(to_light)), 0.0, 1.0);
}

float FogFactor(
    metal::float3 world,
    metal::float3 camera
) {
    float d = metal::distance(world, camera);
    return metal::clamp(1.0 - metal::exp(-(d) * FOG_DENSITY), 0.0, 1.0);
}

struct main_psInput {
    metal::float3 world_1 [[user(loc0), center_perspective]];
    metal::float3 normal [[user(loc1), center_perspective]];
    metal::float2 uv [[user(loc2), center_perspective]];
    float fog [[user(loc3), center_perspective]];
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
    const VsOut i = { clip, varyings.world_1, varyings.normal, varyings.uv, varyings.fog };
    metal::float3 color = {};
    uint l = 0u;
    metal::float4 albedo = base_color.sample(base_sampler, i.uv);
    if (albedo.w < 0.5) {
        metal::discard_fragment();
    }
    color = albedo.xyz * metal::float3(0.03, 0.03, 0.04);
    uint2 loop_bound = uint2(4294967295u);
    bool loop_init = true;
    while(true) {
        if (metal::all(loop_bound == uint2(0u))) { break; }
        loop_bound -= uint2(loop_bound.y == 0u, 1u);
        if (!loop_init) {
            uint _e42 = l;
            l = _e42 + 1u;
        }
        loop_init = false;
        uint _e17 = l;
        if (_e17 < 2u) {
        } else {
            break;
        }
        {
            metal::float3 _e20 = color;
            uint _e23 = l;
            metal::float4 _e26 = lights.inner[_e23].position;
            float _e30 = Lambert(i.normal, _e26.xyz - i.world);
            uint _e32 = l;
            metal::float4 _e35 = lights.inner[_e32].color;
            color = _e20 + ((_e30 * _e35.xyz) * albedo.xyz);
        }
    }
    metal::float3 _e44 = color;
    color = metal::mix(_e44, metal::float3(0.5, 0.6, 0.7), i.fog);
    metal::float3 _e51 = color;
    return main_psOutput { metal::float4(_e51, albedo.w) };
}
