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

struct FragmentInput_main_ps {
    float3 world_1 : LOC0;
    float3 normal : LOC1;
    float2 uv : LOC2;
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

float4 main_ps(FragmentInput_main_ps fragmentinput_main_ps) : SV_Target0
{
    VsOut i = { fragmentinput_main_ps.clip_, fragmentinput_main_ps.world_1, fragmentinput_main_ps.normal, fragmentinput_main_ps.uv, fragmentinput_main_ps.fog };
    float3 color = (float3)0;

    float4 albedo = base_color.Sample(base_sampler, i.uv);
    color = (albedo.xyz * float3(0.03, 0.03, 0.04));
    float3 _e12 = color;
    color = lerp(_e12, float3(0.5, 0.6, 0.7), i.fog);
    float3 _e19 = color;
    return float4(_e19, 1.0);
}
