//! Shared setup of the mobile frame tests: a device per backend (a render test fails, never
//! skips, when there is none), the embedded archive, the bundled scene, image comparison.

#![allow(dead_code)]

use std::path::PathBuf;
use std::sync::Arc;

use kiln_renderer::frame::Image;

pub use crate::support::{golden_dir, psnr, read_png};
use kiln_renderer::mobile::{self, MobileOptions};
use kiln_renderer::scene::gpu::{GpuScene, SceneLayout};
use kiln_renderer::scene::Scene;
use kiln_runtime::pipelines::PipelineCache;
use kiln_runtime::{Backend, GpuOptions};

pub const WIDTH: u32 = 320;
pub const HEIGHT: u32 = 180;

pub struct Rig {
    /// Fails the test with the messages if validation reported any.
    pub gpu: kiln_runtime::validation::CheckedGpu,
    pub cache: PipelineCache,
}

/// A device on `backend` with the embedded archive. Panics with the package to install when
/// there is no adapter: a render test must fail, not skip.
pub fn rig(backend: Backend) -> Rig {
    let gpu = kiln_runtime::validation::CheckedGpu::new(&GpuOptions { backend, ..GpuOptions::default() })
        .unwrap_or_else(|e| {
            panic!("{e}\n(the mobile frame tests need a {backend} adapter: install `mesa-vulkan-drivers`)")
        });
    let archive = kiln_renderer::embedded_archive().expect("the embedded archive opens");
    let cache = PipelineCache::new(&gpu, Arc::new(archive));
    Rig { gpu, cache }
}

impl Rig {
    pub fn render(&self, scene: &Scene, options: MobileOptions) -> Image {
        self.render_passes(scene, options, false).1
    }

    pub fn render_passes(
        &self,
        scene: &Scene,
        options: MobileOptions,
        capture: bool,
    ) -> (Vec<kiln_renderer::frame::PassResult>, Image) {
        let gpu_scene = GpuScene::upload(&self.gpu.device, scene, SceneLayout::PerObject);
        let (w, h) = match std::env::var("KILN_MOBILE_SIZE")
            .ok()
            .and_then(|s| s.split_once('x').map(|(a, b)| (a.parse().unwrap(), b.parse().unwrap())))
        {
            Some(size) => size,
            None => (WIDTH, HEIGHT),
        };
        let (passes, image) = mobile::render(
            &mobile::MobileContext { gpu: &self.gpu, cache: &self.cache, scene, gpu_scene: &gpu_scene },
            options,
            (w, h),
            capture,
        )
        .unwrap_or_else(|e| panic!("mobile frame: {e}"));
        if let Ok(dir) = std::env::var("KILN_MOBILE_DUMP") {
            let dir = PathBuf::from(dir);
            std::fs::create_dir_all(&dir).unwrap();
            let n = std::fs::read_dir(&dir).unwrap().count();
            std::fs::write(dir.join(format!("{n:03}_frame.png")), image.to_png()).unwrap();
            for (i, p) in passes.iter().enumerate() {
                for (name, img) in &p.images {
                    std::fs::write(dir.join(format!("{n:03}_{i:02}_{name}.png")), img.to_png()).unwrap();
                }
            }
        }
        (passes, image)
    }
}
