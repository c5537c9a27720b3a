//! Pipelines of the desktop frame. Modules and reflection come from the runtime's
//! [`PipelineCache`] (lazy, SPIR-V passthrough or WGSL); the desktop passes need
//! fixed-function state the shared cache does not describe (stencil, min and multiply
//! blending, vertex layouts of light volumes), so their pipelines are built here, from the
//! same reflection, once per (permutations, state) when the frame is built.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use kiln::Stage;

use crate::pipelines::{ErrorScopes, MergedBinding, PipelineCache};

use super::DesktopError;

/// The bind group layouts of one pipeline and a by-name way to fill them.
pub struct Layout {
    pub label: String,
    pub groups: Vec<Vec<MergedBinding>>,
    pub bind_group_layouts: Vec<wgpu::BindGroupLayout>,
    pub pipeline_layout: wgpu::PipelineLayout,
}

impl Layout {
    /// A bind group for `group` from `(name in the shader, resource)` pairs. Resources the
    /// permutation does not use are left out; a binding it uses without a resource is an error.
    pub fn bind_group(
        &self,
        device: &wgpu::Device,
        group: u32,
        resources: &[(&str, wgpu::BindingResource<'_>)],
    ) -> Result<Option<wgpu::BindGroup>, DesktopError> {
        let Some(bindings) = self.groups.get(group as usize) else { return Ok(None) };
        if bindings.is_empty() {
            return Ok(None);
        }
        let mut entries = Vec::with_capacity(bindings.len());
        for b in bindings {
            let name = b.name.clone().unwrap_or_default();
            let resource = resources.iter().find(|(n, _)| *n == name).map(|(_, r)| r.clone()).ok_or_else(|| {
                DesktopError::MissingResource {
                    pipeline: self.label.clone(),
                    group,
                    binding: b.binding,
                    name: name.clone(),
                }
            })?;
            entries.push(wgpu::BindGroupEntry { binding: b.binding, resource });
        }
        let scope = ErrorScopes::push(device);
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(&format!("{} group {group}", self.label)),
            layout: &self.bind_group_layouts[group as usize],
            entries: &entries,
        });
        if let Some(message) = scope.pop() {
            return Err(DesktopError::Wgpu { what: format!("bind group {group} of `{}`", self.label), message });
        }
        Ok(Some(bind_group))
    }

    /// Bind groups for every group the pipeline uses, from one resource list.
    pub fn bind_groups(
        &self,
        device: &wgpu::Device,
        resources: &[(&str, wgpu::BindingResource<'_>)],
    ) -> Result<BindGroups, DesktopError> {
        let mut groups = Vec::new();
        for g in 0..self.groups.len() as u32 {
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

/// A cached render pipeline with its key (vertex, fragment, state).
type RenderEntry = (String, Option<String>, RenderDesc, Arc<Render>);

/// Builds and caches the desktop pipelines of one frame.
pub struct Pipelines<'a> {
    pub cache: &'a PipelineCache,
    pub device: &'a wgpu::Device,
    pub level: &'a str,
    render: Mutex<Vec<RenderEntry>>,
    compute: Mutex<HashMap<String, Arc<Compute>>>,
}

impl<'a> Pipelines<'a> {
    pub fn new(cache: &'a PipelineCache, device: &'a wgpu::Device, level: &'a str) -> Pipelines<'a> {
        Pipelines { cache, device, level, render: Mutex::new(Vec::new()), compute: Mutex::new(HashMap::new()) }
    }

    /// The frame's level, for typed permutation keys ([`crate::keys`]).
    pub fn key_level(&self) -> Result<crate::keys::Level, crate::shaders::LookupError> {
        crate::keys::level(self.level)
    }

    /// The pipeline layout from the runtime's cache (one layout rule for every frame; bind
    /// group layouts shared with the other pipelines).
    fn layout(
        &self,
        label: &str,
        reflections: &[&kiln::archive::Reflection],
    ) -> Result<(Layout, crate::spirv::VulkanBindings), DesktopError> {
        let info = self.cache.layout(label, reflections)?;
        let layout = Layout {
            label: info.label,
            groups: info.groups,
            bind_group_layouts: info.bind_group_layouts,
            pipeline_layout: info.layout,
        };
        Ok((layout, info.vulkan_bindings))
    }

    /// A render pipeline of (vertex permutation, fragment permutation or none, state).
    pub fn render(&self, vertex: &str, fragment: Option<&str>, desc: &RenderDesc) -> Result<Arc<Render>, DesktopError> {
        {
            let cached = self.render.lock().unwrap_or_else(|e| e.into_inner());
            if let Some((_, _, _, r)) =
                cached.iter().find(|(v, f, d, _)| v == vertex && f.as_deref() == fragment && d == desc)
            {
                return Ok(r.clone());
            }
        }
        let label = match fragment {
            Some(f) => format!("{vertex} + {f}"),
            None => vertex.to_string(),
        };
        let vs_reflection = self.cache.reflection(vertex, Stage::Vertex)?;
        let fs_reflection = match fragment {
            Some(f) => Some(self.cache.reflection(f, Stage::Fragment)?),
            None => None,
        };
        let mut reflections = vec![&vs_reflection];
        reflections.extend(fs_reflection.as_ref());
        let (layout, numbering) = self.layout(&label, &reflections)?;
        let vs = self.cache.stage_module(vertex, &vs_reflection, &numbering)?;
        let fs = match (fragment, fs_reflection) {
            (Some(f), Some(r)) => Some((self.cache.stage_module(f, &r, &numbering)?, r)),
            _ => None,
        };
        let buffers: Vec<Option<wgpu::VertexBufferLayout<'static>>> = match desc.vertices {
            Vertices::None => Vec::new(),
            Vertices::Mesh => vec![Some(wgpu::VertexBufferLayout {
                array_stride: std::mem::size_of::<crate::gpu_types::MeshVertex>() as u64,
                step_mode: wgpu::VertexStepMode::Vertex,
                attributes: &MESH_ATTRIBUTES,
            })],
        };
        let targets: Vec<Option<wgpu::ColorTargetState>> = desc
            .targets
            .iter()
            .map(|(format, blend)| {
                Some(wgpu::ColorTargetState { format: *format, blend: *blend, write_mask: wgpu::ColorWrites::ALL })
            })
            .collect();
        let scope = ErrorScopes::push(self.device);
        let pipeline = self.device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some(&label),
            layout: Some(&layout.pipeline_layout),
            vertex: wgpu::VertexState {
                module: &vs,
                entry_point: Some(&vs_reflection.entry),
                compilation_options: Default::default(),
                buffers: &buffers,
            },
            primitive: wgpu::PrimitiveState {
                topology: wgpu::PrimitiveTopology::TriangleList,
                cull_mode: desc.cull,
                front_face: wgpu::FrontFace::Ccw,
                ..Default::default()
            },
            depth_stencil: desc.depth_stencil.clone(),
            multisample: wgpu::MultisampleState::default(),
            fragment: fs.as_ref().map(|(module, r)| wgpu::FragmentState {
                module,
                entry_point: Some(&r.entry),
                compilation_options: Default::default(),
                targets: &targets,
            }),
            multiview_mask: None,
            cache: None,
        });
        if let Some(message) = scope.pop() {
            return Err(DesktopError::Wgpu { what: format!("render pipeline `{label}`"), message });
        }
        let handle = Arc::new(Render { pipeline, layout });
        self.render.lock().unwrap_or_else(|e| e.into_inner()).push((
            vertex.to_string(),
            fragment.map(str::to_string),
            desc.clone(),
            handle.clone(),
        ));
        Ok(handle)
    }

    pub fn compute(&self, name: &str) -> Result<Arc<Compute>, DesktopError> {
        if let Some(c) = self.compute.lock().unwrap_or_else(|e| e.into_inner()).get(name) {
            return Ok(c.clone());
        }
        let reflection = self.cache.reflection(name, Stage::Compute)?;
        let (layout, numbering) = self.layout(name, &[&reflection])?;
        let module = self.cache.stage_module(name, &reflection, &numbering)?;
        let scope = ErrorScopes::push(self.device);
        let pipeline = self.device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(name),
            layout: Some(&layout.pipeline_layout),
            module: &module,
            entry_point: Some(&reflection.entry),
            compilation_options: Default::default(),
            cache: None,
        });
        if let Some(message) = scope.pop() {
            return Err(DesktopError::Wgpu { what: format!("compute pipeline `{name}`"), message });
        }
        let handle =
            Arc::new(Compute { pipeline, layout, workgroup_size: reflection.workgroup_size.unwrap_or([1, 1, 1]) });
        self.compute.lock().unwrap_or_else(|e| e.into_inner()).insert(name.to_string(), handle.clone());
        Ok(handle)
    }
}

const MESH_ATTRIBUTES: [wgpu::VertexAttribute; 3] =
    wgpu::vertex_attr_array![0 => Float32x3, 1 => Float32x3, 2 => Float32x2];

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
