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

float Lambert(
    metal::float3 n,
    metal::float3 to_light
) {
    return metal::clamp(metal::dot(metal::normalize(n), metal::normalize(to_light)), 0.0, 1.0);
}

struct main_vsInput {
    metal::float3 position [[attribute(0)]];
    metal::float3 normal [[attribute(1)]];
    metal::float2 uv [[attribute(2)]];
};
struct main_vsOutput {
    metal::float4 clip [[position]];
    metal::float3 world [[user(loc0), center_perspective]];
    metal::float3 normal [[user(loc1), center_perspective]];
    metal::float2 uv [[user(loc2), center_perspective]];
};
vertex main_vsOutput main_vs(
  main_vsInput varyings [[stage_in]]
, constant View& view [[user(fake0)]]
) {
    const auto position = varyings.position;
    const auto normal = varyings.normal;
    const auto uv = varyings.uv;
    VsOut o = {};
    metal::float4x4 _e6 = view.model;
    metal::float3 world = (_e6 * metal::float4(position, 1.0)).xyz;
    metal::float4x4 _e14 = view.view_proj;
    o.clip = _e14 * metal::float4(world, 1.0);
    o.world = world;
    o.normal = normal;
    o.uv = uv;
    VsOut _e21 = o;
    const auto _tmp = _e21;
    return main_vsOutput { _tmp.clip, _tmp.world, _tmp.normal, _tmp.uv };
}
