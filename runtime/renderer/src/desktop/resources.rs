//! What the desktop passes share: their view of the scene on the GPU (meshes, one instance
//! buffer, one material buffer, one draw per object), the lights, and the frame's render
//! targets.

use crate::gpu::BufferInit;
use glam::{Vec3, Vec4};

use crate::frame::{GroupedRenderPass, PassContext};
use crate::scene::gpu::GpuScene;
use crate::scene::{Mesh, Mobility, Scene};

use super::view::LocalLightGpu;
use super::DesktopError;

/// Texture formats of the desktop frame, by their Unreal names.
pub mod formats {
    use wgpu::TextureFormat;
    /// The distortion offsets DistortionAccum accumulates (glass and the fire's heat haze).
    pub const DISTORTION: TextureFormat = TextureFormat::Rg16Float;
    pub const SCENE_COLOR: TextureFormat = TextureFormat::Rgba16Float;
    pub const GBUFFER_A: TextureFormat = TextureFormat::Rgb10a2Unorm;
    pub const GBUFFER_B: TextureFormat = TextureFormat::Rgba8Unorm;
    pub const GBUFFER_C: TextureFormat = TextureFormat::Rgba8UnormSrgb;
    pub const SHADOW_DEPTH: TextureFormat = TextureFormat::Depth32Float;
    pub const SHADOW_MASK: TextureFormat = TextureFormat::Rgba8Unorm;
    pub const AO_SETUP: TextureFormat = TextureFormat::Rgba16Float;
    pub const AO: TextureFormat = TextureFormat::Rgba8Unorm;
    pub const TRANSLUCENCY: TextureFormat = TextureFormat::Rgba16Float;
    pub const BLOOM: TextureFormat = TextureFormat::Rgba16Float;
    pub const VISUALIZE: TextureFormat = TextureFormat::Rgba8Unorm;
}

/// Stencil bit the BasePass sets on lit (non-sky, non-unlit) pixels.
pub const STENCIL_LIT: u32 = 1;

pub use crate::scene::gpu::{Draw, GpuMesh};

/// The scene as the desktop shaders read it: a view over the renderer's [`GpuScene`]
/// uploaded in [`SceneLayout::Rows`](crate::scene::gpu::SceneLayout::Rows) (its buffers are
/// shared, not copied).
pub struct SceneBuffers {
    pub meshes: Vec<GpuMesh>,
    pub instances: wgpu::Buffer,
    pub materials: wgpu::Buffer,
    pub draws: Vec<Draw>,
    /// A unit sphere for light volumes.
    pub sphere: GpuMesh,
}

impl SceneBuffers {
    /// The desktop's view of `scene`, which must be in
    /// [`SceneLayout::Rows`](crate::scene::gpu::SceneLayout::Rows); uploads only the light
    /// volumes' sphere.
    pub fn new(device: &wgpu::Device, scene: &GpuScene) -> Result<SceneBuffers, DesktopError> {
        let rows = scene.rows.as_ref().ok_or(DesktopError::SceneLayout)?;
        let mut sphere = Mesh::new("LightSphere");
        // vertices on a sphere of radius 1/cos(pi/rings) so the faces enclose the unit sphere
        sphere.add_sphere(Vec3::ZERO, 1.0 / (std::f32::consts::PI / 16.0).cos(), 16, 24, 0.0, 0);
        Ok(SceneBuffers {
            meshes: scene.meshes.clone(),
            instances: rows.instances.clone(),
            materials: rows.materials.clone(),
            draws: rows.draws.clone(),
            sphere: GpuMesh::upload(device, &sphere),
        })
    }

    /// Draws `draw` with whatever pipeline and bind groups are set.
    pub fn draw(&self, pass: &mut wgpu::RenderPass<'_>, draw: &Draw) {
        let m = &self.meshes[draw.mesh];
        pass.set_vertex_buffer(0, m.vertices.slice(..));
        pass.set_index_buffer(m.indices.slice(..), wgpu::IndexFormat::Uint32);
        pass.draw_indexed(0..m.index_count, 0, draw.first_instance..draw.first_instance + draw.instance_count);
    }
}

/// How a local light is shadowed (Unreal: movable lights render a cube shadow of the
/// whole scene; stationary lights have their static shadows baked and render per-object
/// shadows for movable props only).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LocalShadow {
    None,
    PerObject,
    Cube,
}

/// A local light of the frame.
#[derive(Clone, Debug)]
pub struct FrameLight {
    pub name: String,
    pub gpu: LocalLightGpu,
    pub shadow: LocalShadow,
    pub spot: bool,
    pub inverse_squared: bool,
}

impl FrameLight {
    pub fn position(&self) -> Vec3 {
        self.gpu.position_radius.truncate()
    }

    pub fn radius(&self) -> f32 {
        self.gpu.position_radius.w
    }
}

/// `LocalLight.spot_angles.z`: 1 for lights ShadowedLights draws.
fn shadowed_flag(casts_shadows: bool) -> f32 {
    if casts_shadows {
        1.0
    } else {
        0.0
    }
}

/// Every point and spot light of the scene, in scene order (points, then spots).
pub fn frame_lights(scene: &Scene) -> Vec<FrameLight> {
    let shadow = |casts: bool, mobility: Mobility| match (casts, mobility) {
        (false, _) => LocalShadow::None,
        (true, Mobility::Movable) => LocalShadow::Cube,
        (true, _) => LocalShadow::PerObject,
    };
    let mut lights = Vec::new();
    for l in &scene.point_lights {
        lights.push(FrameLight {
            name: l.name.clone(),
            gpu: LocalLightGpu {
                position_radius: l.position.extend(l.radius),
                color_falloff: (l.color * l.intensity).extend(0.0),
                direction_type: Vec4::new(0.0, -1.0, 0.0, 1.0),
                spot_angles: Vec4::new(-2.0, 1.0, shadowed_flag(l.casts_shadows), 0.0),
            },
            shadow: shadow(l.casts_shadows, l.mobility),
            spot: false,
            inverse_squared: true,
        });
    }
    for l in &scene.spot_lights {
        let (cos_outer, cos_inner) = (l.outer_angle.cos(), l.inner_angle.cos());
        lights.push(FrameLight {
            name: l.name.clone(),
            gpu: LocalLightGpu {
                position_radius: l.position.extend(l.radius),
                color_falloff: (l.color * l.intensity).extend(0.0),
                direction_type: l.direction.normalize().extend(2.0),
                spot_angles: Vec4::new(
                    cos_outer,
                    1.0 / (cos_inner - cos_outer).max(1e-4),
                    shadowed_flag(l.casts_shadows),
                    0.0,
                ),
            },
            shadow: shadow(l.casts_shadows, l.mobility),
            spot: true,
            inverse_squared: true,
        });
    }
    lights
}

/// A 2D texture with a default view.
pub struct Texture {
    pub texture: wgpu::Texture,
    pub view: wgpu::TextureView,
}

impl Texture {
    pub fn new(
        device: &wgpu::Device,
        label: &str,
        format: wgpu::TextureFormat,
        width: u32,
        height: u32,
        usage: wgpu::TextureUsages,
    ) -> Texture {
        let texture = device.create_texture(&wgpu::TextureDescriptor {
            label: Some(label),
            size: wgpu::Extent3d { width: width.max(1), height: height.max(1), depth_or_array_layers: 1 },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format,
            usage,
            view_formats: &[],
        });
        let view = texture.create_view(&wgpu::TextureViewDescriptor { label: Some(label), ..Default::default() });
        Texture { texture, view }
    }

    /// A render target that later passes sample and `--dump-passes` copies.
    pub fn target(device: &wgpu::Device, label: &str, format: wgpu::TextureFormat, width: u32, height: u32) -> Texture {
        let usage = wgpu::TextureUsages::RENDER_ATTACHMENT
            | wgpu::TextureUsages::TEXTURE_BINDING
            | wgpu::TextureUsages::COPY_SRC;
        Texture::new(device, label, format, width, height, usage)
    }
}

/// The scene depth: reverse-Z depth with stencil; a depth-only view for sampling.
pub struct SceneDepth {
    pub texture: wgpu::Texture,
    pub attachment: wgpu::TextureView,
    pub depth_view: wgpu::TextureView,
    pub format: wgpu::TextureFormat,
    /// Whether the depth can be attached read-only (depth and stencil tests) while passes
    /// sample it. wgpu's GL backend cannot, nor a device without Depth32FloatStencil8 (the
    /// sampled copy needs a copyable format); there the lighting passes test in the shader
    /// only (depth bounds and shading model), without the attachment.
    pub read_only_attachment: bool,
    /// Where the depth is attached read-only: a copy of it, made once per frame by
    /// [`SceneDepth::copy_for_sampling`] before the first such pass, that those passes
    /// sample instead of the attached texture (as Unreal's "depth fetch" copies on
    /// platforms that cannot read a bound depth buffer). A pass that samples the depth it
    /// has attached, even read-only, has Vulkan store that attachment after the shader read
    /// it (wgpu 30 stores read-only depth-stencil attachments with
    /// `VK_ATTACHMENT_STORE_OP_STORE`): a write-after-read hazard within the pass.
    sampled: Option<(wgpu::Texture, wgpu::TextureView)>,
}

impl SceneDepth {
    pub fn new(device: &wgpu::Device, width: u32, height: u32) -> SceneDepth {
        // Depth32FloatStencil8 can be copied out for --dump-passes; Depth24PlusStencil8 is
        // the fallback every device has (its capture is drawn, as on GL). Both copy whole to
        // a texture of their format (the copy for sampling).
        let d32s8 = device.features().contains(wgpu::Features::DEPTH32FLOAT_STENCIL8);
        let format =
            if d32s8 { wgpu::TextureFormat::Depth32FloatStencil8 } else { wgpu::TextureFormat::Depth24PlusStencil8 };
        // The passes that attach the depth read-only sample a copy of it (below), and wgpu
        // copies Depth24PlusStencil8 nowhere: without Depth32FloatStencil8 those passes test
        // in the shader only, as on GL.
        let read_only_attachment = device.adapter_info().backend != wgpu::Backend::Gl && d32s8;
        let mut usage = wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING;
        if d32s8 || read_only_attachment {
            usage |= wgpu::TextureUsages::COPY_SRC;
        }
        let depth_only = |texture: &wgpu::Texture, label: &str| {
            texture.create_view(&wgpu::TextureViewDescriptor {
                label: Some(label),
                aspect: wgpu::TextureAspect::DepthOnly,
                ..Default::default()
            })
        };
        let t = Texture::new(device, "SceneDepthZ", format, width, height, usage);
        let depth_view = depth_only(&t.texture, "SceneDepthTexture");
        let sampled = read_only_attachment.then(|| {
            let copy = Texture::new(
                device,
                "SceneDepthCopy",
                format,
                width,
                height,
                wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            );
            let view = depth_only(&copy.texture, "SceneDepthCopy");
            (copy.texture, view)
        });
        SceneDepth { texture: t.texture, attachment: t.view, depth_view, format, read_only_attachment, sampled }
    }

    /// The depth-only view that passes attaching the depth with [`read_only_depth`] sample:
    /// the copy where there is one, else the depth itself (GL: those passes attach nothing).
    pub fn sampled_view(&self) -> &wgpu::TextureView {
        self.sampled.as_ref().map_or(&self.depth_view, |(_, view)| view)
    }

    /// Copies the depth for [`SceneDepth::sampled_view`] (where there is a copy): once per
    /// frame, after the last pass that writes depth and before the first that reads the copy.
    pub fn copy_for_sampling(&self, encoder: &mut wgpu::CommandEncoder) {
        if let Some((copy, _)) = &self.sampled {
            encoder.copy_texture_to_texture(self.texture.as_image_copy(), copy.as_image_copy(), self.texture.size());
        }
    }
}

/// The frame's full and reduced resolution targets.
pub struct Targets {
    pub width: u32,
    pub height: u32,
    pub scene_depth: SceneDepth,
    pub scene_color: Texture,
    /// Tiled lighting writes SceneColor + lights here (storage), then copies it back.
    pub scene_color_tiled: Texture,
    pub gbuffer_a: Texture,
    pub gbuffer_b: Texture,
    pub gbuffer_c: Texture,
    pub shadow_mask: Texture,
    pub light_grid_visualize: Texture,
    pub ao_setup: Texture,
    pub ao_half: Texture,
    pub ao_full: Texture,
    pub translucency: Texture,
    pub bloom: Vec<Texture>,
}

/// Levels of the bloom chain (1/2 to 1/32 resolution).
pub const BLOOM_LEVELS: u32 = 5;

impl Targets {
    pub fn new(device: &wgpu::Device, width: u32, height: u32) -> Targets {
        let (hw, hh) = (width.div_ceil(2), height.div_ceil(2));
        let t = |label: &str, format, w, h| Texture::target(device, label, format, w, h);
        let scene_color = Texture::new(
            device,
            "SceneColor",
            formats::SCENE_COLOR,
            width,
            height,
            wgpu::TextureUsages::RENDER_ATTACHMENT
                | wgpu::TextureUsages::TEXTURE_BINDING
                | wgpu::TextureUsages::COPY_SRC
                | wgpu::TextureUsages::COPY_DST,
        );
        Targets {
            width,
            height,
            scene_depth: SceneDepth::new(device, width, height),
            scene_color,
            scene_color_tiled: Texture::new(
                device,
                "SceneColorTiled",
                formats::SCENE_COLOR,
                width,
                height,
                wgpu::TextureUsages::STORAGE_BINDING | wgpu::TextureUsages::COPY_SRC,
            ),
            gbuffer_a: t("GBufferA", formats::GBUFFER_A, width, height),
            gbuffer_b: t("GBufferB", formats::GBUFFER_B, width, height),
            gbuffer_c: t("GBufferC", formats::GBUFFER_C, width, height),
            shadow_mask: t("ShadowMask", formats::SHADOW_MASK, width, height),
            light_grid_visualize: t("LightGrid", formats::VISUALIZE, width, height),
            ao_setup: t("AmbientOcclusionSetup", formats::AO_SETUP, hw, hh),
            ao_half: t("AmbientOcclusionHalf", formats::AO, hw, hh),
            ao_full: t("AmbientOcclusion", formats::AO, width, height),
            translucency: t("SeparateTranslucency", formats::TRANSLUCENCY, width, height),
            bloom: (1..=BLOOM_LEVELS)
                .map(|i| t(&format!("Bloom{i}"), formats::BLOOM, (width >> i).max(1), (height >> i).max(1)))
                .collect(),
        }
    }
}

/// Samplers and small constant textures.
pub struct Samplers {
    /// Comparison sampler of the shadow maps (standard depth: lit when ref <= stored).
    pub shadow: wgpu::Sampler,
    pub linear: wgpu::Sampler,
    /// 4x4 random rotations for the ambient occlusion.
    pub random_normals: Texture,
}

impl Samplers {
    pub fn new(device: &wgpu::Device, queue: &wgpu::Queue) -> Samplers {
        let random_normals = Texture::new(
            device,
            "RandomNormalTexture",
            wgpu::TextureFormat::Rgba8Unorm,
            4,
            4,
            wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
        );
        // Deterministic rotations spread over the circle (a shuffled 16-step sequence).
        let order = [0u32, 8, 4, 12, 2, 10, 6, 14, 1, 9, 5, 13, 3, 11, 7, 15];
        let mut texels = Vec::with_capacity(64);
        for k in order {
            let a = k as f32 / 16.0 * std::f32::consts::TAU;
            texels.extend_from_slice(&[
                ((a.cos() * 0.5 + 0.5) * 255.0) as u8,
                ((a.sin() * 0.5 + 0.5) * 255.0) as u8,
                128,
                255,
            ]);
        }
        queue.write_texture(
            wgpu::TexelCopyTextureInfo {
                texture: &random_normals.texture,
                mip_level: 0,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            &texels,
            wgpu::TexelCopyBufferLayout { offset: 0, bytes_per_row: Some(16), rows_per_image: Some(4) },
            wgpu::Extent3d { width: 4, height: 4, depth_or_array_layers: 1 },
        );
        Samplers {
            shadow: device.create_sampler(&wgpu::SamplerDescriptor {
                label: Some("ShadowDepthSampler"),
                mag_filter: wgpu::FilterMode::Linear,
                min_filter: wgpu::FilterMode::Linear,
                compare: Some(wgpu::CompareFunction::LessEqual),
                ..Default::default()
            }),
            linear: device.create_sampler(&wgpu::SamplerDescriptor {
                label: Some("LinearSampler"),
                mag_filter: wgpu::FilterMode::Linear,
                min_filter: wgpu::FilterMode::Linear,
                ..Default::default()
            }),
            random_normals,
        }
    }
}

/// A storage buffer holding a slice (at least one element, so empty lists bind).
pub fn storage<T: bytemuck::Pod + Default>(
    device: &wgpu::Device,
    label: &str,
    values: &[T],
    extra: wgpu::BufferUsages,
) -> wgpu::Buffer {
    let one = [T::default()];
    let values = if values.is_empty() { &one[..] } else { values };
    device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some(label),
        contents: bytemuck::cast_slice(values),
        usage: wgpu::BufferUsages::STORAGE | extra,
    })
}

/// Color attachment helper.
pub fn color_attachment(
    view: &wgpu::TextureView,
    clear: Option<wgpu::Color>,
) -> Option<wgpu::RenderPassColorAttachment<'_>> {
    Some(wgpu::RenderPassColorAttachment {
        view,
        depth_slice: None,
        resolve_target: None,
        ops: wgpu::Operations {
            load: clear.map_or(wgpu::LoadOp::Load, wgpu::LoadOp::Clear),
            store: wgpu::StoreOp::Store,
        },
    })
}

/// A render pass with these attachments and no queries.
pub fn begin<'e>(
    ctx: &'e mut PassContext<'_>,
    label: &str,
    colors: &[Option<wgpu::RenderPassColorAttachment<'_>>],
    depth: Option<wgpu::RenderPassDepthStencilAttachment<'_>>,
) -> GroupedRenderPass<'e> {
    ctx.open_render_pass(&wgpu::RenderPassDescriptor {
        label: Some(label),
        color_attachments: colors,
        depth_stencil_attachment: depth,
        timestamp_writes: None,
        occlusion_query_set: None,
        multiview_mask: None,
    })
}

/// The scene depth bound read-only (depth and stencil tested, nothing written). A pass that
/// attaches it samples [`SceneDepth::sampled_view`], never the attached texture.
pub fn read_only_depth(depth: &SceneDepth) -> Option<wgpu::RenderPassDepthStencilAttachment<'_>> {
    if !depth.read_only_attachment {
        return None;
    }
    Some(wgpu::RenderPassDepthStencilAttachment { view: &depth.attachment, depth_ops: None, stencil_ops: None })
}

/// Stencil test "lit pixels only" (reads the BasePass's mark, writes nothing).
pub fn stencil_lit_only() -> wgpu::StencilState {
    let face = wgpu::StencilFaceState {
        compare: wgpu::CompareFunction::Equal,
        fail_op: wgpu::StencilOperation::Keep,
        depth_fail_op: wgpu::StencilOperation::Keep,
        pass_op: wgpu::StencilOperation::Keep,
    };
    wgpu::StencilState { front: face, back: face, read_mask: STENCIL_LIT, write_mask: 0 }
}
