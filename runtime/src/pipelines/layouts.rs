//! Bind group and pipeline layouts from reflection: stages merged into groups, one
//! layout entry per binding, vertex inputs checked against the vertex layout.

use std::num::NonZeroU64;

use kiln_archive::Stage;
use kiln_archive::{Binding, BindingKind, Reflection, SampleKind, StorageAccess, TextureDim};

use super::modules::{check_scope, short_label, ErrorScopes};
use super::{PipelineError, VertexLayout};
use crate::spirv::VulkanBindings;

/// One resource binding of a pipeline, merged over its stages.
#[derive(Clone, Debug)]
pub struct MergedBinding {
    /// Its `@binding` in the group.
    pub binding: u32,
    /// Its name in the shader (what [`PipelineLayoutInfo::bind_group`] matches resources by).
    pub name: Option<String>,
    /// The resource it takes.
    pub kind: BindingKind,
    /// The stages that use it.
    pub visibility: wgpu::ShaderStages,
}

/// The bind group layouts of a pipeline, one per group index from 0 to the highest used.
#[derive(Clone, Debug)]
pub struct PipelineLayoutInfo {
    /// The pipeline's label, in errors and on wgpu objects.
    pub label: String,
    /// Each group's bindings, sorted by binding.
    pub groups: Vec<Vec<MergedBinding>>,
    /// Each group's wgpu layout.
    pub bind_group_layouts: Vec<wgpu::BindGroupLayout>,
    /// The wgpu pipeline layout of those groups.
    pub layout: wgpu::PipelineLayout,
    /// How wgpu's Vulkan backend numbers these bindings (passthrough modules follow it).
    pub vulkan_bindings: VulkanBindings,
}

impl PipelineLayoutInfo {
    /// A bind group for `group`, with each binding's resource given by its name in the
    /// shader. Every binding the reflection lists must be given; resources it does not list
    /// are left out (callers pass one list for every pipeline of a pass).
    pub fn bind_group(
        &self,
        device: &wgpu::Device,
        group: u32,
        label: &str,
        resources: &[(&str, wgpu::BindingResource<'_>)],
    ) -> Result<wgpu::BindGroup, PipelineError> {
        let bindings = self.groups.get(group as usize).map(Vec::as_slice).unwrap_or(&[]);
        let mut entries = Vec::with_capacity(bindings.len());
        for b in bindings {
            let name = b.name.clone().unwrap_or_default();
            let resource = resources.iter().find(|(n, _)| *n == name).map(|(_, r)| r.clone()).ok_or_else(|| {
                PipelineError::MissingResource {
                    label: self.label.clone(),
                    group,
                    binding: b.binding,
                    name: name.clone(),
                }
            })?;
            entries.push(wgpu::BindGroupEntry { binding: b.binding, resource });
        }
        let layout = &self.bind_group_layouts[group as usize];
        let scope = ErrorScopes::push(device);
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(short_label(label)),
            layout,
            entries: &entries,
        });
        check_scope(scope, || format!("bind group `{label}`"))?;
        Ok(bind_group)
    }

    /// Whether the pipeline uses group `group` at all.
    pub fn uses_group(&self, group: u32) -> bool {
        self.groups.get(group as usize).is_some_and(|g| !g.is_empty())
    }
}

/// How wgpu-hal's Vulkan backend numbers the bindings of these groups.
pub(super) fn vulkan_bindings(groups: &[Vec<MergedBinding>]) -> VulkanBindings {
    VulkanBindings::new(groups.iter().map(|g| g.iter().map(|b| b.binding).collect()).collect())
}

pub(super) fn stage_bits(stage: Stage) -> wgpu::ShaderStages {
    match stage {
        Stage::Vertex => wgpu::ShaderStages::VERTEX,
        Stage::Fragment => wgpu::ShaderStages::FRAGMENT,
        Stage::Compute => wgpu::ShaderStages::COMPUTE,
    }
}

/// Groups a layout may have at most whatever the reflection says: a backstop for callers of
/// [`merge_bindings`] that did not [`check_limits`] first (wgpu allows at most 8).
const MAX_GROUPS: u32 = 32;

/// Merges the bindings of a pipeline's stages into groups (index = group number).
pub fn merge_bindings(label: &str, reflections: &[&Reflection]) -> Result<Vec<Vec<MergedBinding>>, PipelineError> {
    let mut groups: Vec<Vec<MergedBinding>> = Vec::new();
    for r in reflections {
        for Binding { group, binding, name, kind } in &r.bindings {
            if *group >= MAX_GROUPS {
                return Err(PipelineError::Limit {
                    name: label.to_string(),
                    what: format!("@group({group}) @binding({binding}): group {group} is past {MAX_GROUPS}"),
                });
            }
            let g = *group as usize;
            if groups.len() <= g {
                groups.resize_with(g + 1, Vec::new);
            }
            match groups[g].iter_mut().find(|b| b.binding == *binding) {
                Some(existing) => {
                    if existing.kind != *kind {
                        return Err(PipelineError::StageConflict {
                            label: label.to_string(),
                            group: *group,
                            binding: *binding,
                            kind_a: format!("{:?}", existing.kind),
                            kind_b: format!("{kind:?}"),
                        });
                    }
                    existing.visibility |= stage_bits(r.stage);
                    if existing.name.is_none() {
                        existing.name = name.clone();
                    }
                }
                None => groups[g].push(MergedBinding {
                    binding: *binding,
                    name: name.clone(),
                    kind: kind.clone(),
                    visibility: stage_bits(r.stage),
                }),
            }
        }
    }
    for g in &mut groups {
        g.sort_by_key(|b| b.binding);
    }
    Ok(groups)
}

pub(super) fn view_dimension(dim: TextureDim) -> wgpu::TextureViewDimension {
    match dim {
        TextureDim::D1 => wgpu::TextureViewDimension::D1,
        TextureDim::D2 => wgpu::TextureViewDimension::D2,
        TextureDim::D2Array => wgpu::TextureViewDimension::D2Array,
        TextureDim::Cube => wgpu::TextureViewDimension::Cube,
        TextureDim::CubeArray => wgpu::TextureViewDimension::CubeArray,
        TextureDim::D3 => wgpu::TextureViewDimension::D3,
    }
}

/// The texel format of a storage texture, by its WGSL name.
pub fn storage_format(name: &str) -> Option<wgpu::TextureFormat> {
    use wgpu::TextureFormat as F;
    Some(match name {
        "rgba8unorm" => F::Rgba8Unorm,
        "rgba8snorm" => F::Rgba8Snorm,
        "rgba8uint" => F::Rgba8Uint,
        "rgba8sint" => F::Rgba8Sint,
        "rgba16uint" => F::Rgba16Uint,
        "rgba16sint" => F::Rgba16Sint,
        "rgba16float" => F::Rgba16Float,
        "r32uint" => F::R32Uint,
        "r32sint" => F::R32Sint,
        "r32float" => F::R32Float,
        "rg32uint" => F::Rg32Uint,
        "rg32sint" => F::Rg32Sint,
        "rg32float" => F::Rg32Float,
        "rgba32uint" => F::Rgba32Uint,
        "rgba32sint" => F::Rgba32Sint,
        "rgba32float" => F::Rgba32Float,
        "bgra8unorm" => F::Bgra8Unorm,
        "r16float" => F::R16Float,
        "rg16float" => F::Rg16Float,
        "r8unorm" => F::R8Unorm,
        "rgb10a2unorm" => F::Rgb10a2Unorm,
        "rg11b10ufloat" => F::Rg11b10Ufloat,
        _ => return None,
    })
}

/// The layout entry of a merged binding. A float texture is filterable unless its name
/// ends in `DepthTexture` (depth read as an unfilterable float, as the mobile path does).
pub(super) fn layout_entry(label: &str, b: &MergedBinding) -> Result<wgpu::BindGroupLayoutEntry, PipelineError> {
    let ty = match &b.kind {
        BindingKind::UniformBuffer { min_size } => wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Uniform,
            has_dynamic_offset: false,
            min_binding_size: NonZeroU64::new(*min_size),
        },
        BindingKind::StorageBuffer { read_only, min_size } => wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Storage { read_only: *read_only },
            has_dynamic_offset: false,
            min_binding_size: NonZeroU64::new(*min_size),
        },
        BindingKind::Sampler { comparison: true } => wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Comparison),
        BindingKind::Sampler { comparison: false } => wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Filtering),
        BindingKind::Texture { dim, sample, multisampled } => {
            let depth_named = b.name.as_deref().is_some_and(|n| n.ends_with("DepthTexture"));
            wgpu::BindingType::Texture {
                sample_type: match sample {
                    SampleKind::Float => wgpu::TextureSampleType::Float { filterable: !depth_named && !multisampled },
                    SampleKind::Depth => wgpu::TextureSampleType::Depth,
                    SampleKind::Sint => wgpu::TextureSampleType::Sint,
                    SampleKind::Uint => wgpu::TextureSampleType::Uint,
                },
                view_dimension: view_dimension(*dim),
                multisampled: *multisampled,
            }
        }
        BindingKind::StorageTexture { dim, format, access } => wgpu::BindingType::StorageTexture {
            access: match access {
                StorageAccess::ReadOnly => wgpu::StorageTextureAccess::ReadOnly,
                StorageAccess::WriteOnly => wgpu::StorageTextureAccess::WriteOnly,
                StorageAccess::ReadWrite => wgpu::StorageTextureAccess::ReadWrite,
            },
            format: storage_format(format)
                .ok_or_else(|| PipelineError::StorageFormat { label: label.to_string(), format: format.clone() })?,
            view_dimension: view_dimension(*dim),
        },
    };
    Ok(wgpu::BindGroupLayoutEntry { binding: b.binding, visibility: b.visibility, ty, count: None })
}

/// The vertex buffers of `layout`, once every vertex input of `reflection` is checked to be
/// provided by an attribute of its size.
pub(super) fn vertex_buffers<'l>(
    label: &str,
    layout: &'l VertexLayout,
    reflection: &Reflection,
) -> Result<Vec<Option<wgpu::VertexBufferLayout<'l>>>, PipelineError> {
    let buffers: Vec<Option<wgpu::VertexBufferLayout<'l>>> = layout.buffers().iter().map(|b| Some(b.wgpu())).collect();
    for input in &reflection.vertex_inputs {
        let provided = buffers.iter().flatten().flat_map(|b| b.attributes.iter()).any(|a| {
            a.shader_location == input.location
                && a.format.size() == u64::from(input.ty.width) * u64::from(input.ty.components)
        });
        if !provided {
            return Err(PipelineError::VertexInput {
                label: label.to_string(),
                location: input.location,
                provided: layout.locations(),
            });
        }
    }
    Ok(buffers)
}
