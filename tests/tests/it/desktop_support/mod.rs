//! Shared by the desktop effects tests: the bundled archive built from the root
//! `permutations.toml` (once per test process), a lavapipe device, a desktop renderer.

#![allow(dead_code)]

use std::path::PathBuf;
use std::sync::{Arc, OnceLock};

use kiln_renderer::frame::Image;
use kiln_renderer::scene::Scene;
use kiln_renderer::{Renderer, RendererOptions};
use kiln_runtime::validation::CheckedGpu;
use kiln_runtime::{Gpu, GpuOptions, ShaderArchive};

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
    let archive = ShaderArchive::from_vec(std::fs::read(path).unwrap()).unwrap();
    // SAFETY: Kiln's own build wrote this archive a moment ago from the bundled sources, as
    // it does the embedded one, so its SPIR-V is passed through like the embedded archive's.
    Arc::new(unsafe { archive.assume_trusted() })
}

/// A Vulkan device (lavapipe on machines without a GPU): a missing adapter fails the test
/// with the runtime's message, which names `mesa-vulkan-drivers`.
pub fn gpu() -> CheckedGpu {
    CheckedGpu::new(&GpuOptions::default()).unwrap_or_else(|e| panic!("{e}"))
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
    let sum: u64 = a
        .rgba
        .chunks(4)
        .zip(b.rgba.chunks(4))
        .map(|(p, q)| (0..3).map(|i| u64::from(p[i].abs_diff(q[i]))).sum::<u64>())
        .sum();
    sum as f64 / (a.width * a.height * 3) as f64
}

/// Standard deviation of an image's luma.
pub fn luma_stddev(image: &Image) -> f64 {
    let lumas: Vec<f64> = image
        .rgba
        .chunks(4)
        .map(|p| 0.299 * f64::from(p[0]) + 0.587 * f64::from(p[1]) + 0.114 * f64::from(p[2]))
        .collect();
    let mean = lumas.iter().sum::<f64>() / lumas.len() as f64;
    (lumas.iter().map(|l| (l - mean) * (l - mean)).sum::<f64>() / lumas.len() as f64).sqrt()
}

/// Reads mip `level` of a single-channel 32-bit float texture (R32Float, or the depth aspect
/// of a depth texture) back as rows of f32.
pub fn read_f32(gpu: &kiln_runtime::Gpu, texture: &wgpu::Texture, level: u32) -> (u32, u32, Vec<f32>) {
    let (w, h) = ((texture.width() >> level).max(1), (texture.height() >> level).max(1));
    let row = (w * 4).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
    let buffer = gpu.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("test readback"),
        size: u64::from(row * h),
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let aspect = if texture.format().is_depth_stencil_format() {
        wgpu::TextureAspect::DepthOnly
    } else {
        wgpu::TextureAspect::All
    };
    let mut encoder =
        gpu.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("test readback") });
    encoder.copy_texture_to_buffer(
        wgpu::TexelCopyTextureInfo { texture, mip_level: level, origin: wgpu::Origin3d::ZERO, aspect },
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
    let mut out = Vec::with_capacity((w * h) as usize);
    for y in 0..h {
        let r = &bytes[(y * row) as usize..];
        for x in 0..w as usize {
            out.push(f32::from_le_bytes([r[x * 4], r[x * 4 + 1], r[x * 4 + 2], r[x * 4 + 3]]));
        }
    }
    (w, h, out)
}

/// Reads a buffer's first `n` f32 values.
pub fn read_buffer_f32(gpu: &kiln_runtime::Gpu, src: &wgpu::Buffer, n: usize) -> Vec<f32> {
    let size = (n * 4) as u64;
    let buffer = gpu.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("test readback"),
        size,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut encoder =
        gpu.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("test readback") });
    encoder.copy_buffer_to_buffer(src, 0, &buffer, 0, size);
    gpu.queue.submit([encoder.finish()]);
    buffer.slice(..).map_async(wgpu::MapMode::Read, |_| {});
    gpu.wait();
    let bytes = buffer.slice(..).get_mapped_range().unwrap();
    bytemuck::pod_collect_to_vec(&bytes)
}

/// Reads an RG16F texture back as (x, y) pairs.
pub fn read_rg16f(gpu: &kiln_runtime::Gpu, texture: &wgpu::Texture) -> (u32, u32, Vec<[f32; 2]>) {
    let (w, h) = (texture.width(), texture.height());
    let row = (w * 4).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
    let buffer = gpu.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("test readback"),
        size: u64::from(row * h),
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut encoder =
        gpu.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("test readback") });
    encoder.copy_texture_to_buffer(
        texture.as_image_copy(),
        wgpu::TexelCopyBufferInfo {
            buffer: &buffer,
            layout: wgpu::TexelCopyBufferLayout { offset: 0, bytes_per_row: Some(row), rows_per_image: Some(h) },
        },
        texture.size(),
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
            let i = (y * row + x * 4) as usize;
            out.push([half(&bytes[i..i + 2]), half(&bytes[i + 2..i + 4])]);
        }
    }
    (w, h, out)
}
