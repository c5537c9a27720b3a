struct View {
    row_major float4x4 view_proj;
    row_major float4x4 model;
    float4 camera;
};

struct VsOut {
    float4 clip_ : SV_Position;
    float3 world : LOC0;
    float3 normal : LOC1;
    float2 uv : LOC2;
};

cbuffer view : register(b0) { View view; }
Texture2D<float4> base_color : register(t0, space1);
SamplerState nagaSamplerHeap[2048]: register(s0, space0);
SamplerComparisonState nagaComparisonSamplerHeap[2048]: register(s0, space1);
StructuredBuffer<uint> nagaGroup1SamplerIndexArray : register(t1, space255);
static const SamplerState base_sampler = nagaSamplerHeap[nagaGroup1SamplerIndexArray[1]];

struct VertexOutput_main_vs {
    float3 world : LOC0;
    float3 normal_1 : LOC1;
    float2 uv_1 : LOC2;
    float4 clip_ : SV_Position;
};

float Lambert(float3 n, float3 to_light)
{
    return clamp(dot(normalize(n), normalize(to_light)), 0.0, 1.0);
}

VertexOutput_main_vs main_vs(float3 position : LOC0, float3 normal : LOC1, float2 uv : LOC2)
{
    VsOut o = (VsOut)0;

    float4x4 _e6 = view.model;
    float3 world_1 = mul(float4(position, 1.0), _e6).xyz;
    float4x4 _e14 = view.view_proj;
    o.clip_ = mul(float4(world_1, 1.0), _e14);
    o.world = world_1;
    o.normal = normal;
    o.uv = uv;
    VsOut _e21 = o;
    const VsOut vsout = _e21;
    const VertexOutput_main_vs vsout_1 = { vsout.world, vsout.normal, vsout.uv, vsout.clip_ };
    return vsout_1;
}
