//! Render pipelines of the mobile passes. The mobile frames need fixed-function state the
//! shared [`RenderState`](crate::pipelines::RenderState) does not describe (stencil tests and
//! writes, color write masks, light volume vertex layouts), so they build their pipelines
//! here, from the same pieces: modules created lazily by the shared
//! [`PipelineCache`] (SPIR-V passthrough on Vulkan where allowed, WGSL otherwise) and bind
//! group layouts from the archive's reflection ([`PipelineCache::layout`]). Every pipeline is
//! built when its pass is built (the warm-up), and shared between passes by state.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use kiln::Stage;

use crate::gpu_types::{InstanceData, MeshVertex};
use crate::pipelines::{PipelineCache, PipelineError, PipelineLayoutInfo};

/// Vertex buffers a mobile pipeline reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum VertexInput {
    /// None: full-screen triangles from the vertex index.
    None,
    /// Scene meshes: [`MeshVertex`] in buffer 0, [`InstanceData`] in buffer 1 (locations 0-6).
    MeshInstanced,
    /// Light volumes: a `vec3<f32>` position in buffer 0 (location 0).
    Position,
}

/// Everything that makes a mobile render pipeline.
#[derive(Clone, Debug)]
pub struct PipelineDesc {
    /// The vertex permutation's canonical name.
    pub vertex: String,
    /// The fragment permutation's canonical name (`None`: depth only).
    pub fragment: Option<String>,
    pub vertex_input: VertexInput,
    pub cull_mode: Option<wgpu::Face>,
    pub depth_stencil: Option<wgpu::DepthStencilState>,
    pub targets: Vec<Option<wgpu::ColorTargetState>>,
    pub sample_count: u32,
}

impl PipelineDesc {
    pub fn new(vertex: String, fragment: Option<String>, vertex_input: VertexInput) -> PipelineDesc {
        PipelineDesc {
            vertex,
            fragment,
            vertex_input,
            cull_mode: None,
            depth_stencil: None,
            targets: Vec::new(),
            sample_count: 1,
        }
    }

    fn key(&self) -> String {
        format!("{self:?}")
    }
}

/// A built pipeline with its layouts (for bind groups by resource name).
#[derive(Debug)]
pub struct MobilePipeline {
    pub label: String,
    pub pipeline: wgpu::RenderPipeline,
    pub layout: PipelineLayoutInfo,
}

impl MobilePipeline {
    /// The bind groups of every group the pipeline uses, each from the named resources.
    pub fn bind_groups(
        &self,
        device: &wgpu::Device,
        resources: &[(&str, wgpu::BindingResource<'_>)],
    ) -> Result<Vec<Option<wgpu::BindGroup>>, PipelineError> {
        (0..self.layout.groups.len() as u32)
            .map(|g| {
                if self.layout.uses_group(g) {
                    self.layout.bind_group(device, g, &format!("{} group {g}", self.label), resources).map(Some)
                } else {
                    Ok(None)
                }
            })
            .collect()
    }
}

/// Mobile pipelines by state, over the shared module and layout cache.
pub struct MobilePipelines<'a> {
    pub cache: &'a PipelineCache,
    pub device: &'a wgpu::Device,
    built: Mutex<HashMap<String, Arc<MobilePipeline>>>,
}

const MESH_ATTRIBUTES: [wgpu::VertexAttribute; 3] =
    wgpu::vertex_attr_array![0 => Float32x3, 1 => Float32x3, 2 => Float32x2];
const INSTANCE_ATTRIBUTES: [wgpu::VertexAttribute; 4] =
    wgpu::vertex_attr_array![3 => Float32x4, 4 => Float32x4, 5 => Float32x4, 6 => Float32x4];
const POSITION_ATTRIBUTES: [wgpu::VertexAttribute; 1] = wgpu::vertex_attr_array![0 => Float32x3];

fn vertex_buffers(input: VertexInput) -> Vec<Option<wgpu::VertexBufferLayout<'static>>> {
    match input {
        VertexInput::None => Vec::new(),
        VertexInput::MeshInstanced => vec![
            Some(wgpu::VertexBufferLayout {
                array_stride: std::mem::size_of::<MeshVertex>() as u64,
                step_mode: wgpu::VertexStepMode::Vertex,
                attributes: &MESH_ATTRIBUTES,
            }),
            Some(wgpu::VertexBufferLayout {
                array_stride: std::mem::size_of::<InstanceData>() as u64,
                step_mode: wgpu::VertexStepMode::Instance,
                attributes: &INSTANCE_ATTRIBUTES,
            }),
        ],
        VertexInput::Position => vec![Some(wgpu::VertexBufferLayout {
            array_stride: 12,
            step_mode: wgpu::VertexStepMode::Vertex,
            attributes: &POSITION_ATTRIBUTES,
        })],
    }
}

impl<'a> MobilePipelines<'a> {
    pub fn new(cache: &'a PipelineCache, device: &'a wgpu::Device) -> MobilePipelines<'a> {
        MobilePipelines { cache, device, built: Mutex::default() }
    }

    /// Builds (or finds) the pipeline for `desc`.
    pub fn get(&self, desc: &PipelineDesc) -> Result<Arc<MobilePipeline>, PipelineError> {
        let key = desc.key();
        if let Some(p) = self.built.lock().unwrap_or_else(|e| e.into_inner()).get(&key) {
            return Ok(p.clone());
        }
        let permutations: Vec<&str> = std::iter::once(desc.vertex.as_str()).chain(desc.fragment.as_deref()).collect();
        let built = self.cache.external(&key, &permutations, || self.create(desc))?;
        self.built.lock().unwrap_or_else(|e| e.into_inner()).insert(key, built.clone());
        Ok(built)
    }

    fn create(&self, desc: &PipelineDesc) -> Result<MobilePipeline, PipelineError> {
        let label = match &desc.fragment {
            Some(f) => format!("{} + {f}", desc.vertex),
            None => desc.vertex.clone(),
        };
        let vs_reflection = self.cache.reflection(&desc.vertex, Stage::Vertex)?;
        let fs_reflection = match &desc.fragment {
            Some(f) => Some(self.cache.reflection(f, Stage::Fragment)?),
            None => None,
        };
        let mut reflections = vec![&vs_reflection];
        reflections.extend(fs_reflection.as_ref());
        let layout = self.cache.layout(&label, &reflections)?;
        let vs = self.cache.stage_module(&desc.vertex, &vs_reflection, &layout.vulkan_bindings)?;
        let fs = match (&desc.fragment, fs_reflection) {
            (Some(f), Some(r)) => Some((self.cache.stage_module(f, &r, &layout.vulkan_bindings)?, r)),
            _ => None,
        };
        let buffers = vertex_buffers(desc.vertex_input);
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let pipeline = self.device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some(&label),
            layout: Some(&layout.layout),
            vertex: wgpu::VertexState {
                module: &vs,
                entry_point: Some(&vs_reflection.entry),
                compilation_options: Default::default(),
                buffers: &buffers,
            },
            primitive: wgpu::PrimitiveState {
                topology: wgpu::PrimitiveTopology::TriangleList,
                cull_mode: desc.cull_mode,
                front_face: wgpu::FrontFace::Ccw,
                ..Default::default()
            },
            depth_stencil: desc.depth_stencil.clone(),
            multisample: wgpu::MultisampleState { count: desc.sample_count, ..Default::default() },
            fragment: fs.as_ref().map(|(module, r)| wgpu::FragmentState {
                module,
                entry_point: Some(&r.entry),
                compilation_options: Default::default(),
                targets: &desc.targets,
            }),
            multiview_mask: None,
            cache: None,
        });
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(PipelineError::Wgpu { what: format!("render pipeline `{label}`"), message: e.to_string() });
        }
        self.cache.count_external_render_pipeline();
        Ok(MobilePipeline { label, pipeline, layout })
    }

    /// How many distinct pipelines were built.
    pub fn count(&self) -> usize {
        self.built.lock().unwrap_or_else(|e| e.into_inner()).len()
    }
}

/// A pipeline with its bind groups, ready to draw.
pub struct Draw {
    pub pipeline: Arc<MobilePipeline>,
    pub groups: Vec<Option<wgpu::BindGroup>>,
}

impl Draw {
    pub fn new(
        device: &wgpu::Device,
        pipeline: Arc<MobilePipeline>,
        resources: &[(&str, wgpu::BindingResource<'_>)],
    ) -> Result<Draw, PipelineError> {
        let groups = pipeline.bind_groups(device, resources)?;
        Ok(Draw { pipeline, groups })
    }

    pub fn bind(&self, pass: &mut wgpu::RenderPass<'_>) {
        pass.set_pipeline(&self.pipeline.pipeline);
        for (i, g) in self.groups.iter().enumerate() {
            if let Some(g) = g {
                pass.set_bind_group(i as u32, g, &[]);
            }
        }
    }
}

/// A color target that replaces (no blending) and writes every channel.
pub fn replace(format: wgpu::TextureFormat) -> Option<wgpu::ColorTargetState> {
    Some(wgpu::ColorTargetState { format, blend: None, write_mask: wgpu::ColorWrites::ALL })
}

/// A color target the shader does not write in this pipeline.
pub fn untouched(format: wgpu::TextureFormat) -> Option<wgpu::ColorTargetState> {
    Some(wgpu::ColorTargetState { format, blend: None, write_mask: wgpu::ColorWrites::empty() })
}

/// Lights accumulating into SceneColor: `dst + src`, rgb only (CW_RGB, BF_One, BF_One).
pub fn additive(format: wgpu::TextureFormat) -> Option<wgpu::ColorTargetState> {
    let add = wgpu::BlendComponent {
        src_factor: wgpu::BlendFactor::One,
        dst_factor: wgpu::BlendFactor::One,
        operation: wgpu::BlendOperation::Add,
    };
    Some(wgpu::ColorTargetState {
        format,
        blend: Some(wgpu::BlendState { color: add, alpha: add }),
        write_mask: wgpu::ColorWrites::COLOR,
    })
}

/// Premultiplied translucency: `dst * (1 - src.a) + src`.
pub fn premultiplied(format: wgpu::TextureFormat) -> Option<wgpu::ColorTargetState> {
    Some(wgpu::ColorTargetState {
        format,
        blend: Some(wgpu::BlendState::PREMULTIPLIED_ALPHA_BLENDING),
        write_mask: wgpu::ColorWrites::COLOR,
    })
}
