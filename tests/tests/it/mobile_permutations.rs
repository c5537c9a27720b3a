//! The mobile permutations in the embedded archive: PACK_INTERPOLANTS packs the vertex fog
//! into the varyings the unfogged base pass already has, and the `es3_1` level stays within
//! the mobile limits.

use kiln::archive::{BindingKind, Target};

fn varyings(wgsl: &str) -> usize {
    wgsl.matches("@location(").count()
}

#[test]
fn pack_interpolants_makes_vertex_fog_cost_no_varying() {
    let a = kiln_renderer::embedded_archive().unwrap();
    let vs = |fog: u32| {
        let p = a.shader("MobileBasePassVS").level("es3_1").with("USE_VERTEX_FOG", fog).find().unwrap();
        let text = std::str::from_utf8(&p.artifact(Target::Wgsl).unwrap().unwrap()).unwrap().to_string();
        // Vertex inputs are locations too: count the output struct's only.
        let out = &text[text.find("struct MobileBasePassInterpolants").expect("the interpolant struct")..];
        varyings(&out[..out.find('}').unwrap()])
    };
    // Without fog: world position, normal, uv. With fog (packed): position+u, normal+v, fog.
    assert_eq!(vs(0), 3);
    assert_eq!(vs(1), 3);
}

#[test]
fn mobile_pixel_shaders_stay_within_16_samplers_and_4_targets() {
    let a = kiln_renderer::embedded_archive().unwrap();
    let mut checked = 0;
    for p in a.permutations().unwrap().filter(|p| p.shader().level == "es3_1" && p.name().starts_with("Mobile")) {
        let r = p.reflection();
        let samplers = r.bindings.iter().filter(|b| matches!(b.kind, BindingKind::Sampler { .. })).count();
        let textures = r.bindings.iter().filter(|b| matches!(b.kind, BindingKind::Texture { .. })).count();
        assert!(samplers <= 16 && textures <= 16, "{}: {samplers} samplers, {textures} textures", p.name());
        assert!(r.color_outputs.len() <= 4, "{}: {} color outputs", p.name(), r.color_outputs.len());
        assert!(
            !r.bindings
                .iter()
                .any(|b| matches!(b.kind, BindingKind::StorageBuffer { .. } | BindingKind::StorageTexture { .. })),
            "{}: storage resources",
            p.name()
        );
        checked += 1;
    }
    assert!(checked > 400, "{checked} mobile permutations");
}
