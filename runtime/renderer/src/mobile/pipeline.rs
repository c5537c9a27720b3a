//! Render pipelines of the mobile passes, described in wgpu's terms ([`PipelineDesc`]) and
//! created by the runtime's one [`PipelineCache`], keyed by the permutations and the whole
//! fixed-function state. Every pipeline is requested when its pass is built (the warm-up),
//! and shared between passes by state.

use std::collections::HashSet;
use std::sync::{Arc, Mutex};

use crate::pipelines::{PipelineCache, PipelineError, PipelineLayoutInfo, RenderKey, RenderState, VertexLayout};

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

/// The mobile frames' view of the runtime's one pipeline cache.
pub struct MobilePipelines<'a> {
    pub cache: &'a PipelineCache,
    pub device: &'a wgpu::Device,
    /// The keys this frame asked for (how many distinct pipelines it uses).
    used: Mutex<HashSet<RenderKey>>,
}

impl<'a> MobilePipelines<'a> {
    pub fn new(cache: &'a PipelineCache, device: &'a wgpu::Device) -> MobilePipelines<'a> {
        MobilePipelines { cache, device, used: Mutex::default() }
    }

    /// The pipeline for `desc`, from the runtime's one pipeline cache.
    pub fn get(&self, desc: &PipelineDesc) -> Result<Arc<MobilePipeline>, PipelineError> {
        let layout = match desc.vertex_input {
            VertexInput::None => VertexLayout::NONE,
            VertexInput::MeshInstanced => crate::gpu_types::layouts::MESH_INSTANCED,
            VertexInput::Position => crate::gpu_types::layouts::POSITION,
        };
        // Every slot holds a target (`untouched` for one the pipeline does not write).
        let targets: Vec<wgpu::ColorTargetState> = desc.targets.iter().flatten().cloned().collect();
        if targets.len() != desc.targets.len() {
            return Err(PipelineError::Wgpu {
                what: format!("render pipeline `{}`", desc.vertex),
                message: "a color target slot is empty; use `untouched(format)`".into(),
            });
        }
        let state =
            RenderState::from_wgpu(layout, desc.cull_mode, desc.depth_stencil.as_ref(), &targets, desc.sample_count);
        let key = RenderKey { vertex: desc.vertex.clone(), fragment: desc.fragment.clone(), state };
        let built = self.cache.render_key(&key)?;
        self.used.lock().unwrap_or_else(|e| e.into_inner()).insert(key);
        let label = match &desc.fragment {
            Some(f) => format!("{} + {f}", desc.vertex),
            None => desc.vertex.clone(),
        };
        Ok(Arc::new(MobilePipeline { label, pipeline: built.pipeline.clone(), layout: built.layout.clone() }))
    }

    /// How many distinct pipelines were built.
    pub fn count(&self) -> usize {
        self.used.lock().unwrap_or_else(|e| e.into_inner()).len()
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
