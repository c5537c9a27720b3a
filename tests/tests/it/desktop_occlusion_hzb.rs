//! BuildHZB and BeginOcclusionTests of the desktop frame's effects, on the rendered scene.

use crate::desktop_support::*;
use glam::{Mat4, Quat, Vec3};
use kiln_renderer::desktop::occlusion::PropVisibility;
use kiln_renderer::scene::{Camera, Mobility, Object, Scene};
use kiln_renderer::RendererOptions;

/// The HZB's 1x1 top mip holds the farthest (reverse-Z: smallest) depth of the whole view,
/// and every mip holds the farthest depth of the 2x2 texels under it.
#[test]
fn hzb_top_mip_holds_the_farthest_depth() {
    let gpu = gpu();
    let mut scene = Scene::bundled();
    // look down into the room: no sky, so the farthest depth is a surface's, not 0
    scene.camera = Camera {
        position: Vec3::new(0.0, 9.0, 3.0),
        target: Vec3::new(0.0, 0.0, -0.5),
        fov_y: 50f32.to_radians(),
        near: 0.1,
    };
    let r = renderer(&gpu, &scene, RendererOptions { width: 160, height: 90, ..Default::default() });
    r.render(false).unwrap();
    let effects = r.desktop_effects().expect("the desktop frame has effects");
    let (_, _, depth) = read_f32(&gpu, &effects.scene_depth(), 0);
    let farthest = depth.iter().copied().fold(f32::MAX, f32::min);
    let nearest = depth.iter().copied().fold(f32::MIN, f32::max);
    assert!(farthest > 0.0, "the view sees the sky (depth 0); the camera should look at the floor");
    assert!(nearest > farthest * 1.5, "the view has little depth range: {farthest}..{nearest}");

    let (hzb, mips) = effects.hzb();
    assert_eq!(
        (hzb.width(), hzb.height()),
        (128, 64),
        "mip 0 is half of 256x128, the view rounded up to powers of two"
    );
    let (tw, th, top) = read_f32(&gpu, &hzb, mips - 1);
    assert_eq!((tw, th), (1, 1));
    assert_eq!(top[0], farthest, "top mip {} but the farthest depth of the view is {farthest}", top[0]);

    // each texel of mip 3 is the min of its 2x2 parents in mip 2
    let (pw, ph, parent) = read_f32(&gpu, &hzb, 2);
    let (cw, ch, child) = read_f32(&gpu, &hzb, 3);
    for y in 0..ch {
        for x in 0..cw {
            let p = |dx: u32, dy: u32| parent[((2 * y + dy).min(ph - 1) * pw + (2 * x + dx).min(pw - 1)) as usize];
            let expected = p(0, 0).min(p(1, 0)).min(p(0, 1)).min(p(1, 1));
            assert_eq!(child[(y * cw + x) as usize], expected, "mip 3 texel ({x}, {y})");
        }
    }
}

/// The same chain on GL (llvmpipe): every mip is built, not only mip 0. wgpu's GL backend
/// emulates a one-mip view by narrowing the whole texture's base and max level while it is
/// sampled, which made GL drop the stores to the next mip when it was built from the HZB
/// itself: mips 1 and up stayed 0 on GL (the camera looks down at the floor, so every texel
/// of every mip holds a surface's depth, above 0).
#[test]
fn hzb_mips_are_built_on_gl_too() {
    let gpu = kiln_runtime::validation::CheckedGpu::new(&kiln_runtime::GpuOptions {
        backend: kiln_runtime::Backend::Gl,
        ..Default::default()
    })
    .unwrap_or_else(|e| panic!("{e}"));
    let mut scene = Scene::bundled();
    scene.camera = Camera {
        position: Vec3::new(0.0, 9.0, 3.0),
        target: Vec3::new(0.0, 0.0, -0.5),
        fov_y: 50f32.to_radians(),
        near: 0.1,
    };
    let r = renderer(&gpu, &scene, RendererOptions { width: 160, height: 90, ..Default::default() });
    r.render(false).unwrap();
    let effects = r.desktop_effects().unwrap();
    let (hzb, mips) = effects.hzb();
    let (_, _, mip0) = read_f32(&gpu, &hzb, 0);
    let farthest = mip0.iter().copied().fold(f32::MAX, f32::min);
    assert!(farthest > 0.0, "mip 0 sees the sky (depth 0); the camera should look at the floor");
    for level in 1..mips {
        let (pw, ph, parent) = read_f32(&gpu, &hzb, level - 1);
        let (cw, ch, child) = read_f32(&gpu, &hzb, level);
        for y in 0..ch {
            for x in 0..cw {
                let p = |dx: u32, dy: u32| parent[((2 * y + dy).min(ph - 1) * pw + (2 * x + dx).min(pw - 1)) as usize];
                let expected = p(0, 0).min(p(1, 0)).min(p(0, 1)).min(p(1, 1));
                assert_eq!(child[(y * cw + x) as usize], expected, "GL: mip {level} texel ({x}, {y})");
            }
        }
    }
    let (_, _, top) = read_f32(&gpu, &hzb, mips - 1);
    assert_eq!(top[0], farthest, "GL: the top mip is not the farthest depth of mip 0");
}

/// A crate behind the back wall: its box query fails, it is culled one frame later and
/// tested in a group; when the camera moves round the wall the group's query passes, the
/// group is split, and the crate is drawn again.
#[test]
fn prop_behind_the_wall_is_culled_after_the_query_latency_and_reappears() {
    let gpu = gpu();
    let mut scene = Scene::bundled();
    let chair = scene.object("Chairs").unwrap().mesh;
    let bronze = scene.material_index("Bronze").unwrap();
    scene.objects.push(Object {
        name: "CrateBehindWall".into(),
        mesh: chair,
        material: bronze,
        instances: vec![Mat4::from_rotation_translation(Quat::IDENTITY, Vec3::new(0.0, 0.0, -8.0))],
        mobility: Mobility::Static,
        casts_shadow: true,
    });
    let crate_index = scene.objects.len() - 1;
    let r = renderer(&gpu, &scene, RendererOptions { width: 160, height: 90, ..Default::default() });
    let effects = r.desktop_effects().unwrap();

    // frame 1 issues the queries (the crate starts visible); frame 2 reads them
    r.render(false).unwrap();
    assert!(effects.is_visible(crate_index), "culled before any query result came back");
    r.render(false).unwrap();
    assert_eq!(
        effects.visibility(crate_index),
        Some(PropVisibility::Occluded),
        "the crate behind the wall is not culled one frame after its query"
    );
    let chairs = scene.objects.iter().position(|o| o.name == "Chairs").unwrap();
    assert!(effects.is_visible(chairs), "the chairs in plain view were culled");
    r.render(false).unwrap();
    let stats = effects.occlusion_stats();
    assert!(stats.grouped_queries >= 1, "the occluded crate is not tested in a group: {stats:?}");
    assert!(stats.light_queries >= 1, "no ShadowFrustumQueries: {stats:?}");

    // the camera walks round the wall: the crate's group query passes a frame later
    let behind = Camera {
        position: Vec3::new(0.0, 2.0, -13.0),
        target: Vec3::new(0.0, 0.5, -8.0),
        fov_y: 60f32.to_radians(),
        near: 0.1,
    };
    effects.set_camera(behind);
    let culled = r.render(false).unwrap();
    r.render(false).unwrap();
    assert!(effects.is_visible(crate_index), "the crate stays culled after the camera moved round the wall");
    // and it is drawn from the next frame on (this frame's draws were set up before its
    // queries were read): the centre of the view changes once the crate is back
    let shown = r.render(false).unwrap();
    let (w, h) = (shown.image.width, shown.image.height);
    let before = culled.image.mean_luma(w / 2 - 8, h / 2 - 4, w / 2 + 8, h / 2 + 12);
    let after = shown.image.mean_luma(w / 2 - 8, h / 2 - 4, w / 2 + 8, h / 2 + 12);
    let dir = dump_dir("desktop_occlusion");
    save(&dir, "culled", &culled.image);
    save(&dir, "shown", &shown.image);
    assert!((before - after).abs() > 3.0, "the crate did not reappear in the image (luma {before:.1} -> {after:.1})");
}
