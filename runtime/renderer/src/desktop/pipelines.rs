//! Pipelines of the desktop frame: the passes describe their fixed-function state in
//! wgpu's terms ([`RenderDesc`]); the pipelines come from the runtime's one
//! [`PipelineCache`], keyed by the permutations and that whole state.

use std::sync::Arc;

use crate::pipelines::{PipelineCache, PipelineError, PipelineLayoutInfo, RenderState, VertexLayout};

use super::DesktopError;

/// The bind group layouts of one pipeline (the runtime's [`PipelineLayoutInfo`]) and a
/// by-name way to fill them.
pub struct Layout(pub PipelineLayoutInfo);

impl Layout {
    /// A bind group for `group` from `(name in the shader, resource)` pairs, or `None` for a
    /// group the pipeline does not use: the runtime's [`PipelineLayoutInfo::bind_group`],
    /// its errors worded as the desktop frame's.
    pub fn bind_group(
        &self,
        device: &wgpu::Device,
        group: u32,
        resources: &[(&str, wgpu::BindingResource<'_>)],
    ) -> Result<Option<wgpu::BindGroup>, DesktopError> {
        let info = &self.0;
        if !info.uses_group(group) {
            return Ok(None);
        }
        let label = format!("{} group {group}", info.label);
        match info.bind_group(device, group, &label, resources) {
            Ok(bind_group) => Ok(Some(bind_group)),
            Err(PipelineError::MissingResource { label, group, binding, name }) => {
                Err(DesktopError::MissingResource { pipeline: label, group, binding, name })
            }
            Err(PipelineError::Wgpu { message, .. }) => {
                Err(DesktopError::Wgpu { what: format!("bind group {group} of `{}`", info.label), message })
            }
            Err(e) => Err(e.into()),
        }
    }

    /// Bind groups for every group the pipeline uses, from one resource list.
    pub fn bind_groups(
        &self,
        device: &wgpu::Device,
        resources: &[(&str, wgpu::BindingResource<'_>)],
    ) -> Result<BindGroups, DesktopError> {
        let mut groups = Vec::new();
        for g in 0..self.0.groups.len() as u32 {
            groups.push(self.bind_group(device, g, resources)?);
        }
        Ok(BindGroups { groups, keep: Vec::new() })
    }
}

/// The bind groups of one draw or dispatch, by group index (`None` for unused groups), and
/// the buffers made for them alone (kept alive as long as the groups).
pub struct BindGroups {
    pub groups: Vec<Option<wgpu::BindGroup>>,
    pub keep: Vec<wgpu::Buffer>,
}

impl BindGroups {
    /// Keeps `buffer` (a uniform made for these groups) alive with them.
    pub fn keeping(mut self, buffer: wgpu::Buffer) -> BindGroups {
        self.keep.push(buffer);
        self
    }

    pub fn set_render(&self, pass: &mut wgpu::RenderPass<'_>) {
        for (i, g) in self.groups.iter().enumerate() {
            if let Some(g) = g {
                pass.set_bind_group(i as u32, g, &[]);
            }
        }
    }

    pub fn set_compute(&self, pass: &mut wgpu::ComputePass<'_>) {
        for (i, g) in self.groups.iter().enumerate() {
            if let Some(g) = g {
                pass.set_bind_group(i as u32, g, &[]);
            }
        }
    }
}

/// Vertex buffers a desktop pipeline reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Vertices {
    /// None: a triangle from the vertex index.
    None,
    /// [`crate::gpu_types::MeshVertex`] in buffer 0 (locations 0 to 2); instances come from a
    /// storage buffer indexed by `instance_index`.
    Mesh,
}

/// The fixed-function state of a desktop render pipeline.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderDesc {
    pub vertices: Vertices,
    pub cull: Option<wgpu::Face>,
    pub depth_stencil: Option<wgpu::DepthStencilState>,
    pub targets: Vec<(wgpu::TextureFormat, Option<wgpu::BlendState>)>,
}

impl RenderDesc {
    pub fn fullscreen(format: wgpu::TextureFormat, blend: Option<wgpu::BlendState>) -> RenderDesc {
        RenderDesc { vertices: Vertices::None, cull: None, depth_stencil: None, targets: vec![(format, blend)] }
    }
}

/// A built render pipeline and its layout.
pub struct Render {
    pub pipeline: wgpu::RenderPipeline,
    pub layout: Layout,
}

pub struct Compute {
    pub pipeline: wgpu::ComputePipeline,
    pub layout: Layout,
    pub workgroup_size: [u32; 3],
}

/// The desktop frame's view of the runtime's one pipeline cache: its pipelines described
/// in wgpu's terms, at the frame's level.
pub struct Pipelines<'a> {
    pub cache: &'a PipelineCache,
    pub level: &'a str,
}

impl<'a> Pipelines<'a> {
    pub fn new(cache: &'a PipelineCache, level: &'a str) -> Pipelines<'a> {
        Pipelines { cache, level }
    }

    /// The frame's level, for typed permutation keys ([`crate::keys`]).
    pub fn key_level(&self) -> Result<crate::keys::Level, crate::shaders::LookupError> {
        crate::keys::level(self.level)
    }

    /// A render pipeline of (vertex permutation, fragment permutation or none, state), from
    /// the runtime's one pipeline cache.
    pub fn render(&self, vertex: &str, fragment: Option<&str>, desc: &RenderDesc) -> Result<Arc<Render>, DesktopError> {
        let layout = match desc.vertices {
            Vertices::None => VertexLayout::NONE,
            Vertices::Mesh => crate::gpu_types::layouts::MESH,
        };
        let targets: Vec<wgpu::ColorTargetState> = desc
            .targets
            .iter()
            .map(|(format, blend)| wgpu::ColorTargetState {
                format: *format,
                blend: *blend,
                write_mask: wgpu::ColorWrites::ALL,
            })
            .collect();
        let state = RenderState::from_wgpu(layout, desc.cull, desc.depth_stencil.as_ref(), &targets, 1);
        let built = self.cache.render(vertex, fragment, &state)?;
        Ok(Arc::new(Render { pipeline: built.pipeline.clone(), layout: Layout::from(&built.layout) }))
    }

    pub fn compute(&self, name: &str) -> Result<Arc<Compute>, DesktopError> {
        let built = self.cache.compute(name)?;
        Ok(Arc::new(Compute {
            pipeline: built.pipeline.clone(),
            layout: Layout::from(&built.layout),
            workgroup_size: built.workgroup_size,
        }))
    }
}

impl From<&PipelineLayoutInfo> for Layout {
    fn from(info: &PipelineLayoutInfo) -> Layout {
        Layout(info.clone())
    }
}

/// Blend states the desktop passes use beyond replace.
pub mod blend {
    use wgpu::{BlendComponent, BlendFactor as F, BlendOperation as Op, BlendState};

    const fn component(src: F, dst: F, operation: Op) -> BlendComponent {
        BlendComponent { src_factor: src, dst_factor: dst, operation }
    }

    /// dst + src: lights accumulating into SceneColor, bloom levels.
    pub const ADDITIVE: BlendState =
        BlendState { color: component(F::One, F::One, Op::Add), alpha: component(F::Zero, F::One, Op::Add) };
    /// min(dst, src): several shadow projections of one light into the shadow mask.
    pub const MIN: BlendState =
        BlendState { color: component(F::One, F::One, Op::Min), alpha: component(F::One, F::One, Op::Min) };
    /// dst * src: ambient occlusion applied to SceneColor.
    pub const MULTIPLY: BlendState =
        BlendState { color: component(F::Zero, F::Src, Op::Add), alpha: component(F::Zero, F::One, Op::Add) };
    /// dst * src.a + src.rgb: height fog (inscattering, transmittance) and the separate
    /// translucency composite (premultiplied color, transmittance).
    pub const TRANSMITTANCE: BlendState =
        BlendState { color: component(F::One, F::SrcAlpha, Op::Add), alpha: component(F::Zero, F::One, Op::Add) };
    /// Premultiplied "over" for color; alpha keeps the transmittance of what lies behind:
    /// a = dst.a * (1 - src.a). Translucent surfaces into the separate translucency target.
    pub const TRANSLUCENT: BlendState = BlendState {
        color: component(F::One, F::OneMinusSrcAlpha, Op::Add),
        alpha: component(F::Zero, F::OneMinusSrcAlpha, Op::Add),
    };
}
