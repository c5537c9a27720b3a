//! Shared by the desktop part 2 tests: the bundled archive built from the root
//! `permutations.toml` (once per test process), a lavapipe device, a desktop renderer.

#![allow(dead_code)]

use std::path::PathBuf;
use std::sync::{Arc, OnceLock};

use kiln_runtime::frame::Image;
use kiln_runtime::scene::Scene;
use kiln_runtime::{Gpu, GpuOptions, Renderer, RendererOptions, ShaderArchive};

/// The root `permutations.toml`'s `sm5` permutations, compiled with Kiln into a temp dir.
pub fn archive() -> Arc<ShaderArchive> {
    static ARCHIVE: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    let (_, path) = ARCHIVE.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let config = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../permutations.toml");
        let path = kiln::Build::new(config)
            .out_dir(dir.path())
            .target(kiln::Target::Spirv)
            .target(kiln::Target::Wgsl)
            .cache_dir(dir.path().join("cache"))
            .cargo_output(false)
            .run()
            .unwrap_or_else(|e| panic!("building the bundled permutations failed: {e}"));
        (dir, path)
    });
    Arc::new(ShaderArchive::from_vec(std::fs::read(path).unwrap()).unwrap())
}

/// A Vulkan device (lavapipe on machines without a GPU): a missing adapter fails the test
/// with the runtime's message, which names `mesa-vulkan-drivers`.
pub fn gpu() -> Gpu {
    Gpu::new(&GpuOptions::default()).unwrap_or_else(|e| panic!("{e}"))
}

pub fn renderer(gpu: &Gpu, scene: &Scene, options: RendererOptions) -> Renderer {
    Renderer::new(gpu, archive(), scene, options).unwrap_or_else(|e| panic!("{e}"))
}

/// Where a test may write images for a person to look at (`KILN_TEST_DUMP`), if anywhere.
pub fn dump_dir(test: &str) -> Option<PathBuf> {
    let dir = PathBuf::from(std::env::var_os("KILN_TEST_DUMP")?).join(test);
    std::fs::create_dir_all(&dir).ok()?;
    Some(dir)
}

pub fn save(dir: &Option<PathBuf>, name: &str, image: &Image) {
    if let Some(d) = dir {
        std::fs::write(d.join(format!("{name}.png")), image.to_png()).unwrap();
    }
}

/// Mean absolute difference of two images' RGB, in 0..255.
pub fn mean_abs_diff(a: &Image, b: &Image) -> f64 {
    assert_eq!((a.width, a.height), (b.width, b.height));
    let sum: u64 = a.rgba.chunks(4).zip(b.rgba.chunks(4)).map(|(p, q)| (0..3).map(|i| u64::from(p[i].abs_diff(q[i]))).sum::<u64>()).sum();
    sum as f64 / (a.width * a.height * 3) as f64
}

/// Standard deviation of an image's luma.
pub fn luma_stddev(image: &Image) -> f64 {
    let lumas: Vec<f64> = image.rgba.chunks(4).map(|p| 0.299 * f64::from(p[0]) + 0.587 * f64::from(p[1]) + 0.114 * f64::from(p[2])).collect();
    let mean = lumas.iter().sum::<f64>() / lumas.len() as f64;
    (lumas.iter().map(|l| (l - mean) * (l - mean)).sum::<f64>() / lumas.len() as f64).sqrt()
}
