// language: metal2.4
#include <metal_stdlib>
#include <simd/simd.h>

using metal::uint;

struct View {
    metal::float4x4 view_proj;
    metal::float4x4 model;
    metal::float4 camera;
};
struct type_7 {
    metal::atomic_uint inner[64];
};

float Lambert(
    metal::float3 n,
    metal::float3 to_light
) {
    return metal::clamp(metal::dot(metal::normalize(n), metal::normalize(to_light)), 0.0, 1.0);
}
uint naga_f2u32(float value) {
    return static_cast<uint>(metal::clamp(value, 0.0, 4294967000.0));
}


struct main_csInput {
};
[[max_total_threads_per_threadgroup(64)]] kernel void main_cs(
  metal::uint3 id [[thread_position_in_grid]]
, uint li [[thread_index_in_threadgroup]]
, constant View& view [[user(fake0)]]
, metal::texture2d<float, metal::access::sample> input [[user(fake0)]]
, device type_7& histogram [[user(fake0)]]
, metal::texture2d<float, metal::access::write> debug_out [[user(fake0)]]
, threadgroup type_7& local_bins
) {
    if (li == 0u) {
        for (int __i0 = 0; __i0 < 64; __i0++) {
            metal::atomic_store_explicit(&local_bins.inner[__i0], 0, metal::memory_order_relaxed);
        }
    }
    metal::threadgroup_barrier(metal::mem_flags::mem_threadgroup);
    if (li < 64u) {
        metal::atomic_store_explicit(&local_bins.inner[li], 0u, metal::memory_order_relaxed);
    }
    metal::threadgroup_barrier(metal::mem_flags::mem_threadgroup);
    metal::uint2 size = metal::uint2(input.get_width(), input.get_height());
    if (metal::all(id.xy < size)) {
        metal::float4 _e16 = input.read(metal::uint2(static_cast<metal::int2>(id.xy)), 0);
        metal::float3 c = _e16.xyz;
        float _e26 = view.camera.w;
        float lum = metal::dot(c, metal::float3(0.2126, 0.7152, 0.0722)) * _e26;
        uint bin = naga_f2u32(metal::clamp(lum, 0.0, 1.0) * 63.0);
        uint _e37 = metal::atomic_fetch_add_explicit(&local_bins.inner[bin], 1u, metal::memory_order_relaxed);
        debug_out.write(metal::float4(lum), metal::uint2(static_cast<metal::int2>(id.xy)));
    }
    metal::threadgroup_barrier(metal::mem_flags::mem_threadgroup);
    if (li < 64u) {
        uint _e48 = metal::atomic_load_explicit(&local_bins.inner[li], metal::memory_order_relaxed);
        uint _e49 = metal::atomic_fetch_add_explicit(&histogram.inner[li], _e48, metal::memory_order_relaxed);
        return;
    } else {
        return;
    }
}
