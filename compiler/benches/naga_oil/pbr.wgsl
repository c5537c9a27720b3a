// A forward PBR fragment shader of about 350 lines with 8 shader defs, in the subset of
// preprocessing both naga_oil and Kiln read (`#ifdef` / `#ifndef` / `#else` / `#endif`; the
// bench turns `#ifdef NAME` into `#if NAME` for Kiln, whose dimensions are always defined).

struct View {
    view_proj: mat4x4<f32>,
    inverse_view: mat4x4<f32>,
    world_position: vec3<f32>,
    exposure: f32,
    viewport: vec4<f32>,
    fog_color: vec4<f32>,
    fog_params: vec4<f32>,
}

struct Material {
    base_color: vec4<f32>,
    emissive: vec4<f32>,
    roughness: f32,
    metallic: f32,
    reflectance: f32,
    alpha_cutoff: f32,
    uv_transform: mat3x3<f32>,
    flags: u32,
    occlusion_strength: f32,
    normal_scale: f32,
    clearcoat: f32,
}

struct PointLight {
    position_radius: vec4<f32>,
    color_inverse_square_range: vec4<f32>,
}

struct Lights {
    directional_direction: vec4<f32>,
    directional_color: vec4<f32>,
    ambient_color: vec4<f32>,
    point_count: u32,
    cluster_dimensions: vec3<u32>,
    points: array<PointLight, 16>,
}

@group(0) @binding(0) var<uniform> view: View;
@group(0) @binding(1) var<uniform> lights: Lights;
@group(0) @binding(2) var shadow_map: texture_depth_2d;
@group(0) @binding(3) var shadow_sampler: sampler_comparison;
@group(0) @binding(4) var<uniform> light_view_proj: mat4x4<f32>;

@group(1) @binding(0) var<uniform> material: Material;
@group(1) @binding(1) var base_color_texture: texture_2d<f32>;
@group(1) @binding(2) var base_color_sampler: sampler;
@group(1) @binding(3) var normal_map_texture: texture_2d<f32>;
@group(1) @binding(4) var emissive_texture: texture_2d<f32>;
@group(1) @binding(5) var occlusion_texture: texture_2d<f32>;
@group(1) @binding(6) var metallic_roughness_texture: texture_2d<f32>;

const PI: f32 = 3.141592653589793;

struct FragmentInput {
    @builtin(position) position: vec4<f32>,
    @location(0) world_position: vec4<f32>,
    @location(1) world_normal: vec3<f32>,
    @location(2) uv: vec2<f32>,
    @location(3) world_tangent: vec4<f32>,
    @location(4) color: vec4<f32>,
}

struct PbrInput {
    base_color: vec4<f32>,
    emissive: vec3<f32>,
    perceptual_roughness: f32,
    metallic: f32,
    reflectance: f32,
    occlusion: f32,
    N: vec3<f32>,
    V: vec3<f32>,
    world_position: vec3<f32>,
    clearcoat: f32,
}

fn saturate(x: f32) -> f32 {
    return clamp(x, 0.0, 1.0);
}

fn perceptual_roughness_to_roughness(perceptual_roughness: f32) -> f32 {
    let clamped = clamp(perceptual_roughness, 0.089, 1.0);
    return clamped * clamped;
}

fn get_distance_attenuation(distance_square: f32, inverse_range_squared: f32) -> f32 {
    let factor = distance_square * inverse_range_squared;
    let smooth_factor = saturate(1.0 - factor * factor);
    let attenuation = smooth_factor * smooth_factor;
    return attenuation * 1.0 / max(distance_square, 0.0001);
}

fn D_GGX(roughness: f32, NoH: f32) -> f32 {
    let one_minus_no_h_squared = 1.0 - NoH * NoH;
    let a = NoH * roughness;
    let k = roughness / (one_minus_no_h_squared + a * a);
    return k * k * (1.0 / PI);
}

fn V_SmithGGXCorrelated(roughness: f32, NoV: f32, NoL: f32) -> f32 {
    let a2 = roughness * roughness;
    let lambda_v = NoL * sqrt((NoV - a2 * NoV) * NoV + a2);
    let lambda_l = NoV * sqrt((NoL - a2 * NoL) * NoL + a2);
    return 0.5 / (lambda_v + lambda_l);
}

fn F_Schlick_vec(f0: vec3<f32>, f90: f32, VoH: f32) -> vec3<f32> {
    return f0 + (vec3<f32>(f90) - f0) * pow(1.0 - VoH, 5.0);
}

fn F_Schlick(f0: f32, f90: f32, VoH: f32) -> f32 {
    return f0 + (f90 - f0) * pow(1.0 - VoH, 5.0);
}

fn fresnel(f0: vec3<f32>, LoH: f32) -> vec3<f32> {
    let f90 = saturate(dot(f0, vec3<f32>(50.0 * 0.33)));
    return F_Schlick_vec(f0, f90, LoH);
}

fn specular(f0: vec3<f32>, roughness: f32, NoV: f32, NoL: f32, NoH: f32, LoH: f32, intensity: f32) -> vec3<f32> {
    let D = D_GGX(roughness, NoH);
    let V = V_SmithGGXCorrelated(roughness, NoV, NoL);
    let F = fresnel(f0, LoH);
    return (intensity * D * V) * F;
}

fn Fd_Burley(roughness: f32, NoV: f32, NoL: f32, LoH: f32) -> f32 {
    let f90 = 0.5 + 2.0 * roughness * LoH * LoH;
    let light_scatter = F_Schlick(1.0, f90, NoL);
    let view_scatter = F_Schlick(1.0, f90, NoV);
    return light_scatter * view_scatter * (1.0 / PI);
}

fn EnvBRDFApprox(f0: vec3<f32>, perceptual_roughness: f32, NoV: f32) -> vec3<f32> {
    let c0 = vec4<f32>(-1.0, -0.0275, -0.572, 0.022);
    let c1 = vec4<f32>(1.0, 0.0425, 1.04, -0.04);
    let r = perceptual_roughness * c0 + c1;
    let a004 = min(r.x * r.x, exp2(-9.28 * NoV)) * r.x + r.y;
    let AB = vec2<f32>(-1.04, 1.04) * a004 + r.zw;
    return f0 * AB.x + AB.y;
}

fn point_light(world_position: vec3<f32>, light: PointLight, roughness: f32, NdotV: f32, N: vec3<f32>, V: vec3<f32>, R: vec3<f32>, F0: vec3<f32>, diffuse_color: vec3<f32>) -> vec3<f32> {
    let light_to_frag = light.position_radius.xyz - world_position;
    let distance_square = dot(light_to_frag, light_to_frag);
    let range_attenuation = get_distance_attenuation(distance_square, light.color_inverse_square_range.w);
    let a = roughness;
    let center_to_ray = dot(light_to_frag, R) * R - light_to_frag;
    let closest_point = light_to_frag + center_to_ray * saturate(light.position_radius.w * inverseSqrt(dot(center_to_ray, center_to_ray)));
    let L_specular = normalize(closest_point);
    let normalization_factor = a / saturate(a + (light.position_radius.w * 0.5 * inverseSqrt(distance_square)));
    let specular_intensity = normalization_factor * normalization_factor;
    var L = L_specular;
    var H = normalize(L + V);
    var NoL = saturate(dot(N, L));
    var NoH = saturate(dot(N, H));
    var LoH = saturate(dot(L, H));
    let specular_light = specular(F0, roughness, NdotV, NoL, NoH, LoH, specular_intensity);
    L = normalize(light_to_frag);
    H = normalize(L + V);
    NoL = saturate(dot(N, L));
    NoH = saturate(dot(N, H));
    LoH = saturate(dot(L, H));
    let diffuse = diffuse_color * Fd_Burley(roughness, NdotV, NoL, LoH);
    return (diffuse + specular_light) * light.color_inverse_square_range.rgb * (range_attenuation * NoL);
}

fn directional_light(roughness: f32, NdotV: f32, N: vec3<f32>, V: vec3<f32>, F0: vec3<f32>, diffuse_color: vec3<f32>) -> vec3<f32> {
    let incident_light = lights.directional_direction.xyz;
    let half_vector = normalize(incident_light + V);
    let NoL = saturate(dot(N, incident_light));
    let NoH = saturate(dot(N, half_vector));
    let LoH = saturate(dot(incident_light, half_vector));
    let diffuse = diffuse_color * Fd_Burley(roughness, NdotV, NoL, LoH);
    let specular_light = specular(F0, roughness, NdotV, NoL, NoH, LoH, 1.0);
    return (specular_light + diffuse) * lights.directional_color.rgb * NoL;
}

#ifdef SHADOWS
fn fetch_directional_shadow(world_position: vec3<f32>, surface_normal: vec3<f32>) -> f32 {
    let offset_position = world_position + surface_normal * 0.02;
    let clip = light_view_proj * vec4<f32>(offset_position, 1.0);
    if (clip.w <= 0.0) {
        return 1.0;
    }
    let ndc = clip.xyz / clip.w;
    let uv = ndc.xy * vec2<f32>(0.5, -0.5) + vec2<f32>(0.5, 0.5);
    let depth = ndc.z - 0.002;
    var visibility = 0.0;
    for (var y = -1; y <= 1; y = y + 1) {
        for (var x = -1; x <= 1; x = x + 1) {
            let offset = vec2<f32>(f32(x), f32(y)) / 2048.0;
            visibility = visibility + textureSampleCompareLevel(shadow_map, shadow_sampler, uv + offset, depth);
        }
    }
    return visibility / 9.0;
}
#endif

#ifdef FOG
fn apply_fog(color: vec4<f32>, world_position: vec3<f32>) -> vec4<f32> {
    let distance = length(world_position - view.world_position);
    let density = view.fog_params.x;
    let height_falloff = view.fog_params.y;
    let height = max(world_position.y - view.fog_params.z, 0.0);
    let fog_amount = 1.0 - exp(-distance * density * exp(-height * height_falloff));
    let sun = pow(saturate(dot(normalize(world_position - view.world_position), lights.directional_direction.xyz)), 8.0);
    let fog_color = mix(view.fog_color.rgb, lights.directional_color.rgb, sun * 0.5);
    return vec4<f32>(mix(color.rgb, fog_color, saturate(fog_amount)), color.a);
}
#endif

#ifdef TONEMAP
fn tonemap_aces(color: vec3<f32>) -> vec3<f32> {
    let a = 2.51;
    let b = 0.03;
    let c = 2.43;
    let d = 0.59;
    let e = 0.14;
    return saturate_vec((color * (a * color + b)) / (color * (c * color + d) + e));
}

fn saturate_vec(v: vec3<f32>) -> vec3<f32> {
    return clamp(v, vec3<f32>(0.0), vec3<f32>(1.0));
}

fn screen_space_dither(frag_coord: vec2<f32>) -> vec3<f32> {
    var dither = vec3<f32>(dot(vec2<f32>(171.0, 231.0), frag_coord)).xxx;
    dither = fract(dither.rgb / vec3<f32>(103.0, 71.0, 97.0));
    return (dither - 0.5) / 255.0;
}
#endif

fn apply_normal_mapping(world_normal: vec3<f32>, world_tangent: vec4<f32>, uv: vec2<f32>, is_front: bool) -> vec3<f32> {
    var N = normalize(world_normal);
    if (!is_front) {
        N = -N;
    }
#ifdef NORMAL_MAP
    var T = normalize(world_tangent.xyz - N * dot(world_tangent.xyz, N));
    var B = cross(N, T) * world_tangent.w;
    var Nt = textureSample(normal_map_texture, base_color_sampler, uv).rgb * 2.0 - 1.0;
    Nt = vec3<f32>(Nt.xy * material.normal_scale, Nt.z);
    N = normalize(Nt.x * T + Nt.y * B + Nt.z * N);
#endif
    return N;
}

fn calculate_view(world_position: vec4<f32>) -> vec3<f32> {
    return normalize(view.world_position.xyz - world_position.xyz);
}

fn pbr(in: PbrInput) -> vec4<f32> {
    var output_color = in.base_color;
    let emissive = in.emissive;
    let metallic = in.metallic;
    let perceptual_roughness = in.perceptual_roughness;
    let roughness = perceptual_roughness_to_roughness(perceptual_roughness);
    let occlusion = in.occlusion;
    let NdotV = max(dot(in.N, in.V), 0.0001);
    let reflectance = in.reflectance;
    let F0 = 0.16 * reflectance * reflectance * (1.0 - metallic) + output_color.rgb * metallic;
    let diffuse_color = output_color.rgb * (1.0 - metallic);
    let R = reflect(-in.V, in.N);
    var light_accum = vec3<f32>(0.0);
    let n_points = min(lights.point_count, 16u);
    for (var i = 0u; i < n_points; i = i + 1u) {
        light_accum = light_accum + point_light(in.world_position, lights.points[i], roughness, NdotV, in.N, in.V, R, F0, diffuse_color);
    }
    var sun = directional_light(roughness, NdotV, in.N, in.V, F0, diffuse_color);
#ifdef SHADOWS
    sun = sun * fetch_directional_shadow(in.world_position, in.N);
#endif
    light_accum = light_accum + sun;
    let diffuse_ambient = EnvBRDFApprox(diffuse_color, 1.0, NdotV);
    let specular_ambient = EnvBRDFApprox(F0, perceptual_roughness, NdotV);
    var color = light_accum + (diffuse_ambient + specular_ambient) * lights.ambient_color.rgb * occlusion;
    if (in.clearcoat > 0.0) {
        let Fc = F_Schlick(0.04, 1.0, NdotV) * in.clearcoat;
        color = color * (1.0 - Fc) + vec3<f32>(Fc) * lights.ambient_color.rgb;
    }
    color = color + emissive * output_color.a;
    return vec4<f32>(color, output_color.a);
}

@fragment
fn fragment(in: FragmentInput, @builtin(front_facing) is_front: bool) -> @location(0) vec4<f32> {
    let uv = (material.uv_transform * vec3<f32>(in.uv, 1.0)).xy;
    var output_color = material.base_color * textureSample(base_color_texture, base_color_sampler, uv);
#ifdef VERTEX_COLORS
    output_color = output_color * in.color;
#endif
    var pbr_input: PbrInput;
    pbr_input.reflectance = material.reflectance;
    pbr_input.clearcoat = material.clearcoat;
    var metallic = material.metallic;
    var perceptual_roughness = material.roughness;
    let metallic_roughness = textureSample(metallic_roughness_texture, base_color_sampler, uv);
    metallic = metallic * metallic_roughness.b;
    perceptual_roughness = perceptual_roughness * metallic_roughness.g;
    pbr_input.metallic = metallic;
    pbr_input.perceptual_roughness = perceptual_roughness;
    var emissive = material.emissive;
#ifdef EMISSIVE
    emissive = vec4<f32>(emissive.rgb * textureSample(emissive_texture, base_color_sampler, uv).rgb, 1.0);
#endif
    pbr_input.emissive = emissive.rgb;
    var occlusion = 1.0;
#ifdef OCCLUSION
    occlusion = mix(1.0, textureSample(occlusion_texture, base_color_sampler, uv).r, material.occlusion_strength);
#endif
    pbr_input.occlusion = occlusion;
    pbr_input.world_position = in.world_position.xyz;
    pbr_input.N = apply_normal_mapping(in.world_normal, in.world_tangent, uv, is_front);
    pbr_input.V = calculate_view(in.world_position);
#ifdef ALPHA_MASK
    if (output_color.a < material.alpha_cutoff) {
        discard;
    }
    output_color.a = 1.0;
#endif
    pbr_input.base_color = output_color;
    output_color = pbr(pbr_input);
#ifdef FOG
    output_color = apply_fog(output_color, in.world_position.xyz);
#endif
#ifdef TONEMAP
    var rgb = tonemap_aces(output_color.rgb * view.exposure);
    rgb = rgb + screen_space_dither(in.position.xy);
    output_color = vec4<f32>(rgb, output_color.a);
#endif
    return output_color;
}
