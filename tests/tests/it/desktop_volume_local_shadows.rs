//! InjectTranslucentVolume injects the shadow-casting local lights with their own shadows:
//! a slab between a point light and a region of the translucency lighting volume darkens the
//! light that region receives, for a movable light (its cube shadow) and a stationary one (its
//! per-object shadow of the slab, a movable prop), against the same light injected unshadowed;
//! a region beside the light, which the slab does not hide, keeps its light.

use crate::desktop_support::*;
use glam::{Mat4, Vec3};
use kiln_renderer::desktop::effects::{EffectOptions, TranslucencyLightingMode};
use kiln_renderer::desktop::translucent_volume::{TranslucentVolumes, VOLUME_SIZE};
use kiln_renderer::scene::{Camera, Material, Mesh, Mobility, Object, PointLight, Scene};
use kiln_renderer::RendererOptions;

/// 3.5 m over the slab: outside the bounding sphere of the slab's draw (2.45 m, the box
/// around its instances' spheres), which a per-object shadow needs.
const LIGHT: Vec3 = Vec3::new(0.0, 5.5, 0.0);
/// 4.5 m under the light, 1 m under the slab.
const BEHIND_SLAB: Vec3 = Vec3::new(0.0, 1.0, 0.0);
/// 2.5 m beside the light, level with it: no slab in the way (and outside the per-object
/// shadow's frustum, which is unshadowed).
const BESIDE: Vec3 = Vec3::new(2.5, 5.5, 0.0);

/// Nothing but a 2 x 0.1 x 2 m slab (a movable prop, so the stationary light draws it into a
/// per-object shadow; nothing animates it) and one shadow-casting point light above it; the
/// camera looks at the slab from 3.5 m, so that the fine volume cascade (5 m around the
/// camera) holds the light, the slab and both probe points.
fn scene(mobility: Mobility) -> Scene {
    let mut scene = Scene::bundled();
    scene.objects.clear();
    scene.emitters.clear();
    scene.spot_lights.clear();
    scene.sun.enabled = false;
    scene.point_lights = vec![PointLight {
        name: "SlabLight".into(),
        position: LIGHT,
        color: Vec3::ONE,
        intensity: 10.0,
        radius: 8.0,
        mobility,
        casts_shadows: true,
    }];
    let mut slab = Mesh::new("Slab");
    slab.add_box(Vec3::new(-1.0, -0.05, -1.0), Vec3::new(1.0, 0.05, 1.0), 1.0);
    scene.meshes.push(slab);
    scene.materials.push(Material::opaque("SlabPaint", Vec3::splat(0.5), 0.0, 0.8));
    scene.objects.push(Object {
        name: "Slab".into(),
        mesh: scene.meshes.len() - 1,
        material: scene.materials.len() - 1,
        instances: vec![Mat4::from_translation(Vec3::new(0.0, 2.0, 0.0))],
        mobility: Mobility::Movable,
        casts_shadow: true,
    });
    scene.camera = Camera {
        position: Vec3::new(0.0, 2.5, 3.5),
        target: Vec3::new(0.0, 2.0, 0.0),
        fov_y: 60f32.to_radians(),
        near: 0.1,
    };
    scene
}

/// Reads layer `layer` of an RGBA16F 2D array texture as RGBA rows.
fn read_layer(gpu: &kiln_runtime::Gpu, texture: &wgpu::Texture, layer: u32) -> Vec<[f32; 4]> {
    let (w, h) = (texture.width(), texture.height());
    let row = (w * 8).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
    let buffer = gpu.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("volume readback"),
        size: u64::from(row * h),
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut encoder =
        gpu.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("volume readback") });
    encoder.copy_texture_to_buffer(
        wgpu::TexelCopyTextureInfo {
            texture,
            mip_level: 0,
            origin: wgpu::Origin3d { x: 0, y: 0, z: layer },
            aspect: wgpu::TextureAspect::All,
        },
        wgpu::TexelCopyBufferInfo {
            buffer: &buffer,
            layout: wgpu::TexelCopyBufferLayout { offset: 0, bytes_per_row: Some(row), rows_per_image: Some(h) },
        },
        wgpu::Extent3d { width: w, height: h, depth_or_array_layers: 1 },
    );
    gpu.queue.submit([encoder.finish()]);
    buffer.slice(..).map_async(wgpu::MapMode::Read, |_| {});
    gpu.wait();
    let bytes = buffer.slice(..).get_mapped_range().unwrap();
    let half = |b: &[u8]| {
        let h = u16::from_le_bytes([b[0], b[1]]);
        let sign = if h & 0x8000 != 0 { -1.0 } else { 1.0 };
        let exp = i32::from((h >> 10) & 0x1f);
        let frac = f32::from(h & 0x3ff);
        sign * if exp == 0 { frac * 2f32.powi(-24) } else { (1.0 + frac / 1024.0) * 2f32.powi(exp - 15) }
    };
    let mut out = Vec::new();
    for y in 0..h {
        for x in 0..w {
            let i = (y * row + x * 8) as usize;
            out.push(std::array::from_fn(|c| half(&bytes[i + 2 * c..])));
        }
    }
    out
}

/// The light the fine cascade (filtered) holds at each probe point after one frame: luminance
/// of the Ambient volume's rgb.
fn injected(mobility: Mobility, shadows: bool) -> [f32; 2] {
    let gpu = gpu();
    let scene = scene(mobility);
    let r = renderer(&gpu, &scene, RendererOptions { width: 160, height: 90, ..Default::default() });
    let effects = r.desktop_effects().unwrap();
    effects.set_options(EffectOptions {
        translucency_lighting: TranslucencyLightingMode::SurfaceLightingVolume,
        translucency_volume_shadows: shadows,
        ..EffectOptions::off()
    });
    r.render(false).unwrap_or_else(|e| panic!("{e}"));
    let ambient = effects.translucency_volume().ambient[0].clone();
    let (origin, cell) = TranslucentVolumes::cascade_box(scene.camera.position, 0);
    [BEHIND_SLAB, BESIDE].map(|p| {
        let c = ((p - origin) / cell).floor();
        assert!(
            c.cmpge(Vec3::ZERO).all() && c.cmplt(Vec3::splat(VOLUME_SIZE as f32)).all(),
            "{p} is outside the fine cascade"
        );
        let texel = read_layer(&gpu, &ambient, c.z as u32)[(c.y as u32 * VOLUME_SIZE + c.x as u32) as usize];
        0.299 * texel[0] + 0.587 * texel[1] + 0.114 * texel[2]
    })
}

/// Measured on lavapipe (luminance of the filtered injected light): both lights 0.384
/// unshadowed behind the slab and 0.000 shadowed (ratio 0.000), 1.278 beside the light
/// either way (ratio 1.000). Before the local lights were injected with their shadows the
/// ratio behind the slab was 1.000. Bounds: the slab must take at least half the light
/// behind it and at most 5% beside the light.
#[test]
fn a_slab_between_a_local_light_and_the_volume_darkens_the_light_injected_behind_it() {
    for (kind, mobility) in
        [("movable (cube shadow)", Mobility::Movable), ("stationary (per-object shadow)", Mobility::Stationary)]
    {
        let shadowed = injected(mobility, true);
        let unshadowed = injected(mobility, false);
        let ratio = [shadowed[0] / unshadowed[0], shadowed[1] / unshadowed[1]];
        eprintln!(
            "{kind}: shadowed {shadowed:?}, unshadowed {unshadowed:?}; behind the slab {:.3}, beside the light {:.3}",
            ratio[0], ratio[1]
        );
        assert!(
            unshadowed[0] > 0.01 && unshadowed[1] > 0.01,
            "{kind}: the light does not reach the probes ({unshadowed:?})"
        );
        assert!(ratio[0] < 0.5, "{kind}: the slab does not darken the light injected behind it ({:.3})", ratio[0]);
        assert!(
            ratio[1] > 0.95,
            "{kind}: the light beside it, which the slab does not hide, is darkened ({:.3})",
            ratio[1]
        );
    }
}
