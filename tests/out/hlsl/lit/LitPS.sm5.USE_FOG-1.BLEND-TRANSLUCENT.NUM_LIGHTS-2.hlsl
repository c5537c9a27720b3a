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

struct Light {
    float4 position;
    float4 color;
};

static const float FOG_DENSITY = 0.02;

cbuffer view : register(b0) { View view; }
Texture2D<float4> base_color : register(t0, space1);
SamplerState nagaSamplerHeap[2048]: register(s0, space0);
SamplerComparisonState nagaComparisonSamplerHeap[2048]: register(s0, space1);
StructuredBuffer<uint> nagaGroup1SamplerIndexArray : register(t1, space255);
static const SamplerState base_sampler = nagaSamplerHeap[nagaGroup1SamplerIndexArray[1]];
cbuffer lights : register(b0, space2) { Light lights[2]; }

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
    uint l = 0u;

    float4 albedo = base_color.Sample(base_sampler, i.uv);
    color = (albedo.xyz * float3(0.03, 0.03, 0.04));
    uint2 loop_bound = uint2(4294967295u, 4294967295u);
    bool loop_init = true;
    while(true) {
        if (all(loop_bound == uint2(0u, 0u))) { break; }
        loop_bound -= uint2(loop_bound.y == 0u, 1u);
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
            float3 _e17 = color;
            uint _e20 = l;
            float4 _e23 = lights[_e20].position;
            const float _e27 = Lambert(i.normal, (_e23.xyz - i.world));
            uint _e29 = l;
            float4 _e32 = lights[_e29].color;
            color = (_e17 + ((_e27 * _e32.xyz) * albedo.xyz));
        }
    }
    float3 _e41 = color;
    color = lerp(_e41, float3(0.5, 0.6, 0.7), i.fog);
    float3 _e48 = color;
    return float4(_e48, albedo.w);
}
