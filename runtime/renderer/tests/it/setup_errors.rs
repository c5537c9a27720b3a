//! Issue 28, case 7: a device lost before or while a renderer is set up is an error that
//! says so, never a panic (wgpu's `create_buffer_init` panics on a buffer it cannot map).

use std::sync::Arc;

use kiln_renderer::scene::Scene;
use kiln_renderer::{FramePipeline, RenderError, Renderer, RendererOptions};
use kiln_runtime::{Gpu, GpuOptions};

#[test]
fn a_lost_device_is_an_error_of_the_setup_not_a_panic() {
    let gpu = Gpu::new(&GpuOptions::default()).unwrap_or_else(|e| panic!("{e}"));
    let archive = Arc::new(kiln_renderer::embedded_archive().unwrap());
    let scene = Scene::bundled();
    let options = |pipeline| RendererOptions { pipeline, width: 64, height: 36, comparison: false };
    // A working device first: the setup succeeds.
    assert!(Renderer::new(&gpu, archive.clone(), &scene, options(FramePipeline::MobileForward)).is_ok());
    gpu.device.destroy();
    // The runtime's buffer creation on it: no panic (wgpu's own panics here).
    let _buffer = kiln_runtime::gpu::BufferInit::create_buffer_init(
        &gpu.device,
        &wgpu::util::BufferInitDescriptor {
            label: Some("after loss"),
            contents: &[1, 2, 3],
            usage: wgpu::BufferUsages::VERTEX,
        },
    );
    for pipeline in [FramePipeline::MobileForward, FramePipeline::MobileDeferred, FramePipeline::Desktop] {
        match Renderer::new(&gpu, archive.clone(), &scene, options(pipeline)) {
            Err(RenderError::DeviceLost(why)) => assert!(why.contains("Destroyed"), "{pipeline:?}: {why}"),
            Err(e) => panic!("{pipeline:?}: {e}"),
            Ok(_) => panic!("{pipeline:?}: set up on a destroyed device"),
        }
    }
}
