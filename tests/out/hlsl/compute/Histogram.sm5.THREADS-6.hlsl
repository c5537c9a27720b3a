struct View {
    row_major float4x4 view_proj;
    row_major float4x4 model;
    float4 camera;
};

cbuffer view : register(b0) { View view; }
Texture2D<float4> input : register(t1);
RWByteAddressBuffer histogram : register(u2);
RWTexture2D<unorm float4> debug_out : register(u3);
groupshared uint local_bins[64];

float Lambert(float3 n, float3 to_light)
{
    return clamp(dot(normalize(n), normalize(to_light)), 0.0, 1.0);
}

uint naga_f2u32(float value) {
    return uint(clamp(value, 0.0, 4294967000.0));
}

uint2 NagaDimensions2D(Texture2D<float4> tex)
{
    uint4 ret;
    tex.GetDimensions(0, ret.x, ret.y, ret.z);
    return ret.xy;
}

[numthreads(64, 1, 1)]
void main_cs(uint3 id : SV_DispatchThreadID, uint li : SV_GroupIndex)
{
    if (li == 0) {
        local_bins = (uint[64])0;
    }
    GroupMemoryBarrierWithGroupSync();
    if ((li < 64u)) {
        { uint dummy = 0; InterlockedExchange(local_bins[min(uint(li), 63u)], 0u, dummy); }
    }
    GroupMemoryBarrierWithGroupSync();
    uint2 size = NagaDimensions2D(input);
    if (all((id.xy < size))) {
        float4 _e16 = input.Load(int3(int2(id.xy), int(0)));
        float3 c = _e16.xyz;
        float _e26 = view.camera.w;
        float lum = (dot(c, float3(0.2126, 0.7152, 0.0722)) * _e26);
        uint bin = naga_f2u32((clamp(lum, 0.0, 1.0) * 63.0));
        uint _e37; InterlockedAdd(local_bins[min(uint(bin), 63u)], 1u, _e37);
        debug_out[int2(id.xy)] = (lum).xxxx;
    }
    GroupMemoryBarrierWithGroupSync();
    if ((li < 64u)) {
        uint _e48; InterlockedOr(local_bins[min(uint(li), 63u)], 0, _e48);
        uint _e49; histogram.InterlockedAdd(li*4, _e48, _e49);
        return;
    } else {
        return;
    }
}
