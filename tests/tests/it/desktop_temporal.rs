//! Temporal effects and volumetric fog of the desktop frame's effects, on the rendered scene.

use crate::desktop_support::*;
use kiln_renderer::desktop::effects::EffectOptions;
use kiln_renderer::frame::Image;
use kiln_renderer::scene::Scene;
use kiln_renderer::RendererOptions;

const W: u32 = 160;
const H: u32 = 90;
/// The supersampled reference: SS x SS samples per pixel.
const SS: u32 = 4;

fn luma(image: &Image) -> Vec<f64> {
    image.rgba.chunks(4).map(|p| 0.299 * f64::from(p[0]) + 0.587 * f64::from(p[1]) + 0.114 * f64::from(p[2])).collect()
}

/// Box-filters an image rendered at SS times the size down to W x H (luma).
fn downsample(image: &Image) -> Vec<f64> {
    let l = luma(image);
    let mut out = vec![0.0; (W * H) as usize];
    for y in 0..H {
        for x in 0..W {
            let mut sum = 0.0;
            for sy in 0..SS {
                for sx in 0..SS {
                    sum += l[((y * SS + sy) * image.width + x * SS + sx) as usize];
                }
            }
            out[(y * W + x) as usize] = sum / f64::from(SS * SS);
        }
    }
    out
}

/// Still frames: no animation, no motion blur, a fixed exposure, no particles (their state
/// depends on how many frames ran) and no volumetric fog (its jittered froxels converge over
/// frames too), so only the geometry's edges differ between the renders compared.
fn still(taa: bool) -> EffectOptions {
    EffectOptions {
        taa,
        motion_blur: false,
        eye_adaptation: false,
        animate: false,
        volumetric_fog: false,
        particles: false,
        ..EffectOptions::default()
    }
}

/// TAA's jittered frames accumulated over 16 frames come closer to a 4x4 supersampled
/// reference along the edges of the scene than the same frame without TAA.
#[test]
fn taa_reduces_edge_aliasing_against_a_supersampled_reference() {
    let scene = Scene::bundled();
    // a device per renderer (lavapipe 22.3 has crashed building a second frame's pipelines on
    // one device)
    let render = |w: u32, h: u32, taa: bool, frames: usize| {
        let gpu = gpu();
        let r = renderer(&gpu, &scene, RendererOptions { width: w, height: h, ..Default::default() });
        r.desktop_effects().unwrap().set_options(still(taa));
        let mut last = None;
        for _ in 0..frames {
            last = Some(r.render(false).unwrap().image);
        }
        last.unwrap()
    };
    let reference_image = render(W * SS, H * SS, false, 1);
    let reference = downsample(&reference_image);
    let aliased = render(W, H, false, 1);
    let resolved = render(W, H, true, 16);
    let dir = dump_dir("desktop_taa");
    save(&dir, "reference", &reference_image);
    save(&dir, "no_taa", &aliased);
    save(&dir, "taa", &resolved);

    // edges: pixels where the reference's luma changes by more than 6 to a neighbour
    let mut edges = Vec::new();
    for y in 1..H - 1 {
        for x in 1..W - 1 {
            let i = (y * W + x) as usize;
            let g = (reference[i + 1] - reference[i - 1]).abs()
                + (reference[i + W as usize] - reference[i - W as usize]).abs();
            if g > 6.0 {
                edges.push(i);
            }
        }
    }
    assert!(edges.len() > 200, "the reference has too few edges to measure ({})", edges.len());
    let error = |image: &Image| {
        let l = luma(image);
        edges.iter().map(|&i| (l[i] - reference[i]).abs()).sum::<f64>() / edges.len() as f64
    };
    let (e_aliased, e_resolved) = (error(&aliased), error(&resolved));
    eprintln!("edge error against the 4x4 supersampled reference: no TAA {e_aliased:.2}, TAA {e_resolved:.2} (ratio {:.2}) over {} edge pixels", e_resolved / e_aliased, edges.len());
    assert!(
        e_resolved < 0.85 * e_aliased,
        "TAA does not reduce edge aliasing: error {e_resolved:.2} with TAA, {e_aliased:.2} without"
    );
}

/// The directional light's shadow carves shafts into the volumetric fog: the in-scattered
/// light of a froxel slice through the room varies far more with the shadow than without.
#[test]
fn volumetric_fog_shows_the_directional_lights_shafts() {
    let scattering = |shadows: bool| {
        let gpu = gpu();
        let mut scene = Scene::bundled();
        scene.sun.casts_shadows = shadows;
        let r = renderer(&gpu, &scene, RendererOptions { width: W * 2, height: H * 2, ..Default::default() });
        r.desktop_effects().unwrap().set_options(EffectOptions {
            animate: false,
            fog_density: 0.03,
            ..EffectOptions::default()
        });
        let mut frame = None;
        for _ in 0..3 {
            frame = Some(r.render(true).unwrap());
        }
        let frame = frame.unwrap();
        frame
            .passes
            .iter()
            .flat_map(|p| p.images.iter())
            .find(|(n, _)| n == "VolumetricFog_LightScattering")
            .map(|(_, i)| i.clone())
            .expect("no LightScattering image")
    };
    let shadowed = scattering(true);
    let unshadowed = scattering(false);
    let dir = dump_dir("desktop_fog");
    save(&dir, "shadowed", &shadowed);
    save(&dir, "unshadowed", &unshadowed);
    let mean = |i: &Image| luma(i).iter().sum::<f64>() / (i.width * i.height) as f64;
    let (s_dev, u_dev) = (luma_stddev(&shadowed), luma_stddev(&unshadowed));
    eprintln!(
        "LightScattering slice: luma stddev {s_dev:.2} with the sun's shadow, {u_dev:.2} without; mean {:.2} / {:.2}",
        mean(&shadowed),
        mean(&unshadowed)
    );
    assert!(mean(&shadowed) < mean(&unshadowed), "the shadow does not darken the fog");
    assert!(
        s_dev > 1.3 * u_dev,
        "no light shafts: the shadowed fog varies as little as the unshadowed (stddev {s_dev:.2} vs {u_dev:.2})"
    );
}
