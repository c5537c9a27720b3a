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

struct VertexOutput_main_vs {
    float3 world : LOC0;
    float3 normal_1 : LOC1;
    float2 uv_1 : LOC2;
    float4 clip_ : SV_Position;
};

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
