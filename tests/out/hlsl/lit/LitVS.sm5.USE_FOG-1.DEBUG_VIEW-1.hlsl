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
    float fog : LOC3;
};

static const float FOG_DENSITY = 0.02;

cbuffer view : register(b0) { View view; }
Texture2D<float4> base_color : register(t0, space1);
SamplerState nagaSamplerHeap[2048]: register(s0, space0);
SamplerComparisonState nagaComparisonSamplerHeap[2048]: register(s0, space1);
StructuredBuffer<uint> nagaGroup1SamplerIndexArray : register(t1, space255);
static const SamplerState base_sampler = nagaSamplerHeap[nagaGroup1SamplerIndexArray[1]];

struct VertexOutput_main_vs {
    float3 world_1 : LOC0;
    float3 normal_1 : LOC1;
    float2 uv_1 : LOC2;
    float fog : LOC3;
    float4 clip_ : SV_Position;
};

float Lambert(float3 n, float3 to_light)
{
    return clamp(dot(normalize(n), normalize(to_light)), 0.0, 1.0);
}

float FogFactor(float3 world, float3 camera)
{
    float d = distance(world, camera);
    return clamp((1.0 - exp((-(d) * FOG_DENSITY))), 0.0, 1.0);
}

VertexOutput_main_vs main_vs(float3 position : LOC0, float3 normal : LOC1, float2 uv : LOC2)
{
    VsOut o = (VsOut)0;

    float4x4 _e6 = view.model;
    float3 world_2 = mul(float4(position, 1.0), _e6).xyz;
    float4x4 _e14 = view.view_proj;
    o.clip_ = mul(float4(world_2, 1.0), _e14);
    o.world = world_2;
    o.normal = normal;
    o.uv = uv;
    float4 _e24 = view.camera;
    const float _e26 = FogFactor(world_2, _e24.xyz);
    o.fog = _e26;
    VsOut _e27 = o;
    const VsOut vsout = _e27;
    const VertexOutput_main_vs vsout_1 = { vsout.world, vsout.normal, vsout.uv, vsout.fog, vsout.clip_ };
    return vsout_1;
}
