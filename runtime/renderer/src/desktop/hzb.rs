//! BuildHZB: the hierarchical depth buffer of the prepass depth (`HZB.usf`). Mip 0 is the
//! scene depth resampled to half its size, each side rounded up to a power of two (as in the
//! seed's capture), every mip after it halves the one before down to 1x1, each
//! texel the farthest depth (reverse-Z: the minimum) of the texels it covers. Screen-space
//! reflections trace against it; its top mip holds the farthest depth of the view.
//!
//! Each mip reads its parent from a copy (`HZB parents`), not from the HZB itself: on wgpu's
//! GL backend a texture view is emulated by setting the texture object's
//! `TEXTURE_BASE_LEVEL`/`TEXTURE_MAX_LEVEL` when it is bound for sampling (wgpu-hal 30
//! `gles/queue.rs`, `BindTexture`), so sampling the one-mip view of level L-1 leaves the whole
//! texture with max level L-1, and GL treats an image unit bound to level L, outside
//! [base, max], as invalid: its stores are dropped. Every mip above 0 stayed 0 on GL (measured:
//! mips 2 and 4 read 0 everywhere on llvmpipe's GL, the depth of the view on lavapipe), so the
//! reflections found no hit there (their GL capture was black, 27.9 dB from Vulkan's).

use crate::frame::{ComputeSlot, PassContext, PassDecl, Slots};
use std::sync::Arc;

use bytemuck::{Pod, Zeroable};

use crate::keys;
use crate::pipelines::PipelineError;

use super::frame_view::{groups, uniform_buffer};

/// The BuildHZB declaration.
pub const PASS: PassDecl = PassDecl { name: "BuildHZB", reads: &["SceneDepth"], writes: &["HZB"] };

pub const HZB_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::R32Float;

#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
struct HzbParams {
    src_size: [u32; 2],
    dst_size: [u32; 2],
}

/// Mip 0's size for a scene of `scene` pixels: half the next power of two, at least 1.
pub fn hzb_size(scene: [u32; 2]) -> [u32; 2] {
    [(scene[0].next_power_of_two() / 2).max(1), (scene[1].next_power_of_two() / 2).max(1)]
}

/// The size of mip `level` of a chain starting at `size`.
pub fn mip_size(size: [u32; 2], level: u32) -> [u32; 2] {
    [(size[0] >> level).max(1), (size[1] >> level).max(1)]
}

pub struct Hzb {
    pub texture: wgpu::Texture,
    /// Mip L-1 of the HZB copied here before mip L is built from it (see the module docs).
    parents: wgpu::Texture,
    /// All mips, for sampling.
    pub view: wgpu::TextureView,
    pub size: [u32; 2],
    pub mip_count: u32,
    first: Arc<ComputeSlot>,
    rest: Arc<ComputeSlot>,
    bind_groups: Vec<wgpu::BindGroup>,
    _params: Vec<wgpu::Buffer>,
}

impl Hzb {
    /// The chain for a scene depth of `scene_size`, reading `scene_depth` (a depth-aspect view).
    pub fn new(
        device: &wgpu::Device,
        cache: Slots<'_>,
        scene_depth: &wgpu::TextureView,
        scene_size: [u32; 2],
    ) -> Result<Hzb, PipelineError> {
        let first = cache.compute(&keys::name(keys::hzb_build_cs::Key { hzb_first_mip: true }, keys::Level::Sm5)?)?;
        let rest = cache.compute(&keys::name(keys::hzb_build_cs::Key { hzb_first_mip: false }, keys::Level::Sm5)?)?;
        let size = hzb_size(scene_size);
        let mip_count = 32 - size[0].max(size[1]).leading_zeros();
        let texture = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("HZB"),
            size: wgpu::Extent3d { width: size[0], height: size[1], depth_or_array_layers: 1 },
            mip_level_count: mip_count,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: HZB_FORMAT,
            usage: wgpu::TextureUsages::STORAGE_BINDING
                | wgpu::TextureUsages::TEXTURE_BINDING
                | wgpu::TextureUsages::COPY_SRC,
            view_formats: &[],
        });
        let parents = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("HZB parents"),
            size: wgpu::Extent3d { width: size[0], height: size[1], depth_or_array_layers: 1 },
            mip_level_count: mip_count,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: HZB_FORMAT,
            usage: wgpu::TextureUsages::COPY_DST | wgpu::TextureUsages::TEXTURE_BINDING,
            view_formats: &[],
        });
        let mip_view = |texture: &wgpu::Texture, level: u32| {
            texture.create_view(&wgpu::TextureViewDescriptor {
                label: Some(&format!("HZB mip {level}")),
                base_mip_level: level,
                mip_level_count: Some(1),
                ..Default::default()
            })
        };
        let mut bind_groups = Vec::new();
        let mut params = Vec::new();
        for level in 0..mip_count {
            let dst = mip_size(size, level);
            let src = if level == 0 { scene_size } else { mip_size(size, level - 1) };
            let buffer =
                uniform_buffer(device, &format!("HZB mip {level} params"), &HzbParams { src_size: src, dst_size: dst });
            let out = mip_view(&texture, level);
            let bind_group = if level == 0 {
                first.layout.bind_group(
                    device,
                    0,
                    "HZB mip 0",
                    &[
                        ("params", buffer.as_entire_binding()),
                        ("SceneDepthTexture", wgpu::BindingResource::TextureView(scene_depth)),
                        ("out_mip", wgpu::BindingResource::TextureView(&out)),
                    ],
                )?
            } else {
                let parent = mip_view(&parents, level - 1);
                rest.layout.bind_group(
                    device,
                    0,
                    &format!("HZB mip {level}"),
                    &[
                        ("params", buffer.as_entire_binding()),
                        ("ParentMipDepthTexture", wgpu::BindingResource::TextureView(&parent)),
                        ("out_mip", wgpu::BindingResource::TextureView(&out)),
                    ],
                )?
            };
            bind_groups.push(bind_group);
            params.push(buffer);
        }
        let view = texture.create_view(&wgpu::TextureViewDescriptor { label: Some("HZB"), ..Default::default() });
        Ok(Hzb { texture, parents, view, size, mip_count, first, rest, bind_groups, _params: params })
    }

    /// One dispatch per mip, in order (each reads a copy of the one before).
    pub fn record(&self, ctx: &mut PassContext<'_>) {
        for (level, bind_group) in self.bind_groups.iter().enumerate() {
            let dst = mip_size(self.size, level as u32);
            if level > 0 {
                let parent = level as u32 - 1;
                let [w, h] = mip_size(self.size, parent);
                ctx.encoder().copy_texture_to_texture(
                    wgpu::TexelCopyTextureInfo {
                        texture: &self.texture,
                        mip_level: parent,
                        origin: wgpu::Origin3d::ZERO,
                        aspect: wgpu::TextureAspect::All,
                    },
                    wgpu::TexelCopyTextureInfo {
                        texture: &self.parents,
                        mip_level: parent,
                        origin: wgpu::Origin3d::ZERO,
                        aspect: wgpu::TextureAspect::All,
                    },
                    wgpu::Extent3d { width: w, height: h, depth_or_array_layers: 1 },
                );
            }
            let ready = if level == 0 { &self.first } else { &self.rest }.ready(ctx.pipelines());
            let mut pass = ctx.open_compute_pass(&format!("HZB(mip={level}) {}x{}", dst[0], dst[1]));
            if let Some(p) = ready {
                pass.set_pipeline(&p.pipeline);
                pass.set_bind_group(0, bind_group, &[]);
                pass.dispatch_workgroups(groups(dst[0], 8), groups(dst[1], 8), 1);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mip0_is_half_the_next_power_of_two() {
        assert_eq!(hzb_size([1916, 1014]), [1024, 512]);
        assert_eq!(hzb_size([640, 360]), [512, 256]);
        assert_eq!(hzb_size([512, 256]), [256, 128]);
        assert_eq!(hzb_size([1, 1]), [1, 1]);
    }

    #[test]
    fn chain_ends_at_one_texel() {
        let size = hzb_size([640, 360]);
        let count = 32 - size[0].max(size[1]).leading_zeros();
        assert_eq!(count, 10);
        assert_eq!(mip_size(size, count - 1), [1, 1]);
        assert_eq!(mip_size(size, 8), [2, 1]);
    }
}
