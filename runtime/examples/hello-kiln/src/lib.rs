//! The smallest app on the Kiln runtime, as a library (`src/main.rs` is its command line).
//!
//! `build.rs` compiles `permutations.toml` (two shaders, `shaders/`) into an archive that
//! [`ARCHIVE`] embeds, and generates typed keys for it ([`shaders`]). [`render`] picks one
//! vertex and one pixel permutation by key, gets their pipeline from the runtime's
//! [`PipelineCache`] (lazy modules: SPIR-V passthrough on Vulkan, WGSL elsewhere; bind group
//! layouts from the archive's reflection), draws into an offscreen texture and reads it
//! back. Everything it uses of the runtime is public API.
//!
//! The colors (`shaders/hello_ps.wgsl`): `PALETTE=WARM` (1.0, 0.6, 0.2), `COOL`
//! (0.2, 0.6, 1.0), multiplied by [`Frame::tint`] when `TINT=1`.

use std::sync::Arc;

use kiln_runtime::pipelines::{
    Blend, ColorTarget, ErrorScopes, PipelineCache, PipelineError, RenderPipeline, RenderState,
};
use kiln_runtime::{Gpu, ShaderArchive};
use wgpu::util::DeviceExt;

/// The archive `build.rs` compiled from `permutations.toml`.
pub static ARCHIVE: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/shaders.kpak"));

/// The format of the rendered image (not sRGB: the shaders' values land in the bytes as
/// they are, `round(value * 255)`).
pub const FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;

/// The typed permutation keys `build.rs` generated from `permutations.toml`
/// (`kiln::Build::rust_bindings`): `Level`, and one module per shader with its `Key` and a
/// Rust enum per enum dimension. A dimension or value renamed in the toml is a compile error
/// here, not a failed lookup at run time.
pub mod shaders {
    include!(concat!(env!("OUT_DIR"), "/kiln_shaders.rs"));
}

pub use shaders::hello_ps::Palette;
pub use shaders::hello_vs::Shape;
use shaders::{Level, PermutationKey};

/// The one level of `permutations.toml`.
pub const LEVEL: Level = Level::Portable;

/// How many vertices the vertex shader's `SHAPE` draws.
fn vertices(shape: Shape) -> u32 {
    match shape {
        Shape::Triangle => 3,
        Shape::Quad => 6,
    }
}

/// What to draw.
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    pub shape: Shape,
    pub palette: Palette,
    /// `Some`: the `TINT=1` permutation, whose color is multiplied by this one (a uniform
    /// buffer); `None`: `TINT=0`, which has no bindings at all.
    pub tint: Option<[f32; 4]>,
    /// The color outside the shape.
    pub clear: [f32; 4],
}

impl Default for Frame {
    fn default() -> Frame {
        Frame {
            width: 64,
            height: 64,
            shape: Shape::Quad,
            palette: Palette::Warm,
            tint: Some([0.6, 1.0, 0.2, 1.0]),
            clear: [0.0, 0.0, 0.2, 1.0],
        }
    }
}

/// A rendered image, rows top to bottom, RGBA with a byte per channel.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    pub rgba: Vec<u8>,
}

impl Image {
    /// The pixel at column `x`, row `y` (0, 0 is the top left).
    pub fn pixel(&self, x: u32, y: u32) -> [u8; 4] {
        let i = (y as usize * self.width as usize + x as usize) * 4;
        [self.rgba[i], self.rgba[i + 1], self.rgba[i + 2], self.rgba[i + 3]]
    }
}

#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("the embedded shader archive cannot be read: {0}")]
    Archive(String),
    #[error("{shader} {key}: no such permutation at level `{level}` in permutations.toml")]
    NoPermutation { shader: &'static str, key: String, level: &'static str },
    #[error("{shader} {key} (`{name}`): not in the embedded archive, which is older than its keys")]
    NotInArchive { shader: &'static str, key: String, name: String },
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    #[error("a {width}x{height} frame is not possible: {why}")]
    Size { width: u32, height: u32, why: String },
    #[error("rendering failed: {0}")]
    Render(String),
}

/// The embedded archive, trusted for SPIR-V passthrough: `build.rs` wrote it into this binary
/// with Kiln's own build, so it is as trustworthy as the code.
pub fn archive() -> Result<Arc<ShaderArchive>, Error> {
    // SAFETY: these bytes are the archive `kiln::Build` compiled in our build.rs and
    // `include_bytes!` put into the binary; nothing else writes them.
    let archive = unsafe { ShaderArchive::from_static_trusted(ARCHIVE) };
    Ok(Arc::new(archive.map_err(|e| Error::Archive(e.to_string()))?))
}

/// The canonical names of the (vertex, pixel) permutations `frame` draws with: typed keys,
/// found in the archive by id (one hash-map lookup, no name formatted or parsed).
pub fn permutations(archive: &ShaderArchive, frame: &Frame) -> Result<(String, String), Error> {
    let vs = shaders::hello_vs::Key { shape: frame.shape };
    let ps = shaders::hello_ps::Key { palette: frame.palette, tint: frame.tint.is_some() };
    Ok((find(archive, vs)?, find(archive, ps)?))
}

fn find<K: PermutationKey>(archive: &ShaderArchive, key: K) -> Result<String, Error> {
    let (shader, level) = (K::SHADER, LEVEL.name());
    let id =
        key.permutation_id(LEVEL).ok_or_else(|| Error::NoPermutation { shader, key: format!("{key:?}"), level })?;
    match archive.get_by_id(id).map_err(|e| Error::Archive(e.to_string()))? {
        Some(permutation) => Ok(permutation.name().to_string()),
        None => Err(Error::NotInArchive {
            shader,
            key: format!("{key:?}"),
            name: key.canonical_name(LEVEL).unwrap_or_default(),
        }),
    }
}

/// Renders `frame` on `gpu` with pipelines from `cache` (a cache over [`archive`]) and reads
/// the image back.
pub fn render(gpu: &Gpu, cache: &PipelineCache, frame: &Frame) -> Result<Image, Error> {
    let device = &gpu.device;
    check_size(gpu, frame)?;
    let (vs, ps) = permutations(cache.archive(), frame)?;
    // One lookup in the runtime's cache: created on first use (modules, bind group layouts
    // from the reflection of both stages, the pipeline), found by key afterwards.
    let state = RenderState::fullscreen(ColorTarget::new(FORMAT, Blend::Replace));
    let pipeline = cache.render(&vs, Some(&ps), &state)?;
    let (_tint, bind_groups) = bind_groups(device, &pipeline, frame)?;

    let scope = ErrorScopes::push(device);
    let target = Target::new(device, frame);
    let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("hello") });
    draw(&mut encoder, &target.view, &pipeline, &bind_groups, frame);
    target.copy_out(&mut encoder);
    gpu.queue.submit([encoder.finish()]);
    if let Some(message) = scope.pop() {
        return Err(Error::Render(message));
    }
    target.read_back(gpu, frame)
}

/// Each side within 1 and the device's largest texture.
fn check_size(gpu: &Gpu, frame: &Frame) -> Result<(), Error> {
    let max = gpu.device.limits().max_texture_dimension_2d;
    if frame.width == 0 || frame.height == 0 || frame.width > max || frame.height > max {
        let why = format!("each side must be 1 to {max} pixels on {}", gpu.info.name);
        return Err(Error::Size { width: frame.width, height: frame.height, why });
    }
    Ok(())
}

/// The resources the reflection asks for, by their names in the shader: `Tint` for the
/// TINT=1 permutations; the TINT=0 ones list none. Gives the tint buffer (where there is
/// one) and a bind group per group of the pipeline's layout.
fn bind_groups(
    device: &wgpu::Device,
    pipeline: &RenderPipeline,
    frame: &Frame,
) -> Result<(Option<wgpu::Buffer>, Vec<wgpu::BindGroup>), Error> {
    let tint = frame.tint.map(|color| {
        device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("hello tint"),
            contents: &color.iter().flat_map(|c| c.to_le_bytes()).collect::<Vec<u8>>(),
            usage: wgpu::BufferUsages::UNIFORM,
        })
    });
    let mut resources = Vec::new();
    if let Some(buffer) = &tint {
        resources.push(("Tint", buffer.as_entire_binding()));
    }
    let bind_groups = (0..pipeline.layout.groups.len() as u32)
        .map(|group| pipeline.layout.bind_group(device, group, "hello", &resources))
        .collect::<Result<Vec<_>, _>>()?;
    Ok((tint, bind_groups))
}

/// Clears the target to the frame's clear color and draws the shape over it.
fn draw(
    encoder: &mut wgpu::CommandEncoder,
    view: &wgpu::TextureView,
    pipeline: &RenderPipeline,
    bind_groups: &[wgpu::BindGroup],
    frame: &Frame,
) {
    let [r, g, b, a] = frame.clear.map(f64::from);
    let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
        label: Some("hello"),
        color_attachments: &[Some(wgpu::RenderPassColorAttachment {
            view,
            depth_slice: None,
            resolve_target: None,
            ops: wgpu::Operations {
                load: wgpu::LoadOp::Clear(wgpu::Color { r, g, b, a }),
                store: wgpu::StoreOp::Store,
            },
        })],
        depth_stencil_attachment: None,
        timestamp_writes: None,
        occlusion_query_set: None,
        multiview_mask: None,
    });
    pass.set_pipeline(&pipeline.pipeline);
    for (group, bind_group) in bind_groups.iter().enumerate() {
        pass.set_bind_group(group as u32, bind_group, &[]);
    }
    pass.draw(0..vertices(frame.shape), 0..1);
}

/// The offscreen texture the frame is drawn into, and the buffer it is copied to for
/// reading (rows padded to wgpu's copy alignment).
struct Target {
    texture: wgpu::Texture,
    view: wgpu::TextureView,
    readback: wgpu::Buffer,
    /// Bytes per row in `readback`.
    padded: u32,
}

impl Target {
    fn new(device: &wgpu::Device, frame: &Frame) -> Target {
        let texture = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("hello target"),
            size: wgpu::Extent3d { width: frame.width, height: frame.height, depth_or_array_layers: 1 },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: FORMAT,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
            view_formats: &[],
        });
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        let padded =
            (frame.width * 4).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
        let readback = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("hello readback"),
            size: u64::from(padded) * u64::from(frame.height),
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        Target { texture, view, readback, padded }
    }

    /// Copies the texture into the readback buffer.
    fn copy_out(&self, encoder: &mut wgpu::CommandEncoder) {
        encoder.copy_texture_to_buffer(
            wgpu::TexelCopyTextureInfo {
                texture: &self.texture,
                mip_level: 0,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            wgpu::TexelCopyBufferInfo {
                buffer: &self.readback,
                layout: wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(self.padded),
                    rows_per_image: Some(self.texture.height()),
                },
            },
            self.texture.size(),
        );
    }

    /// Waits for the copy, maps the buffer and gives its rows without the padding; a failed
    /// map or a lost device is an error.
    fn read_back(&self, gpu: &Gpu, frame: &Frame) -> Result<Image, Error> {
        let (sender, receiver) = std::sync::mpsc::channel();
        self.readback.slice(..).map_async(wgpu::MapMode::Read, move |result| drop(sender.send(result)));
        gpu.device.poll(wgpu::PollType::wait_indefinitely()).map_err(|e| Error::Render(e.to_string()))?;
        match receiver.recv() {
            Ok(Ok(())) => {}
            Ok(Err(e)) => return Err(Error::Render(format!("reading the image back: {e}"))),
            Err(_) => return Err(Error::Render("reading the image back: the map never completed".into())),
        }
        if let Some(reason) = gpu.lost.reason() {
            return Err(Error::Render(format!("the device was lost: {reason}")));
        }
        let mapped = self.readback.slice(..).get_mapped_range().map_err(|e| Error::Render(e.to_string()))?;
        let mut rgba = Vec::with_capacity(frame.width as usize * frame.height as usize * 4);
        for row in mapped.chunks_exact(self.padded as usize) {
            rgba.extend_from_slice(&row[..frame.width as usize * 4]);
        }
        Ok(Image { width: frame.width, height: frame.height, rgba })
    }
}
