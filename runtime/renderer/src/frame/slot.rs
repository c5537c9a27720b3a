//! Pipelines as the passes hold them: a key and the layout its bind groups are made for,
//! never the pipeline object. A pass asks for its pipeline when it records a draw or a
//! dispatch ([`RenderSlot::ready`], [`ComputeSlot::ready`]) and skips the draw when the answer
//! is "not ready", so a frame need not wait for a pipeline that is still being created.
//!
//! Both frames describe their render pipelines with one [`PipelineDesc`] and make their bind
//! groups by resource name with one [`bind_groups`]. Every record-time lookup goes through
//! [`ready_render`] and [`ready_compute`]: the one place that decides what a frame does
//! about a pipeline that is not created yet.

use std::sync::{Arc, Mutex};

use kiln_archive::Stage;

use crate::pipelines::{
    ComputeKey, ComputePipeline, PipelineCache, PipelineError, PipelineLayoutInfo, Ready, RenderKey, RenderPipeline,
    RenderState, VertexLayout,
};

/// The record-time lookup of a render pipeline: `Some` to draw with, `None` when it is not
/// ready (the draw is skipped). What "not ready" means is the cache's [`Missing`] setting:
/// under the default `Block` the cache creates the pipeline before answering, so every frame
/// draws with its exact pipeline; under `Background` the answer is the pipeline if it is
/// created, else the nearest ready permutation's (fallback `Nearest`) or none (`Skip`), and
/// the cache counts each such draw ([`PipelineCache::fallbacks`]).
///
/// [`Missing`]: crate::pipelines::Missing
pub fn ready_render(cache: &PipelineCache, key: &RenderKey) -> Result<Option<Arc<RenderPipeline>>, PipelineError> {
    Ok(match cache.render_ready(key)? {
        Ready::Exact(p) | Ready::Nearest(p) => Some(p),
        Ready::NotReady => None,
    })
}

/// [`ready_render`] for compute pipelines.
pub fn ready_compute(cache: &PipelineCache, key: &ComputeKey) -> Result<Option<Arc<ComputePipeline>>, PipelineError> {
    Ok(match cache.compute_ready(key)? {
        Ready::Exact(p) | Ready::Nearest(p) => Some(p),
        Ready::NotReady => None,
    })
}

/// When a renderer creates the pipelines of its passes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Creation {
    /// Each pipeline once when its pass is built, so a pipeline that cannot be created fails
    /// the renderer's construction, naming it.
    #[default]
    Eager,
    /// None when the passes are built: each when a frame first asks for it. For a cache
    /// that creates pipelines off the frame (a frame that never waits for one).
    Lazy,
}

/// How passes are given their slots while they are built: the cache and when to create.
#[derive(Clone, Copy)]
pub struct Slots<'a> {
    pub cache: &'a PipelineCache,
    pub creation: Creation,
}

impl<'a> Slots<'a> {
    pub fn new(cache: &'a PipelineCache, creation: Creation) -> Slots<'a> {
        Slots { cache, creation }
    }

    /// The slot of (vertex permutation, fragment permutation or none, state).
    pub fn render(
        &self,
        vertex: &str,
        fragment: Option<&str>,
        state: &RenderState,
    ) -> Result<Arc<RenderSlot>, PipelineError> {
        let key =
            RenderKey { vertex: vertex.to_string(), fragment: fragment.map(str::to_string), state: state.clone() };
        RenderSlot::new(self.cache, key, self.creation).map(Arc::new)
    }

    /// The slot of the pipeline `desc` describes.
    pub fn render_desc(&self, desc: &PipelineDesc) -> Result<Arc<RenderSlot>, PipelineError> {
        RenderSlot::new(self.cache, desc.key(), self.creation).map(Arc::new)
    }

    /// The slot of compute permutation `name`.
    pub fn compute(&self, name: &str) -> Result<Arc<ComputeSlot>, PipelineError> {
        ComputeSlot::new(self.cache, name, self.creation).map(Arc::new)
    }
}

/// Where a frame's passes get their pipelines while recording: the cache, and the first
/// lookup that failed (the frame skips that draw and reports the error when it finishes).
#[derive(Clone, Copy)]
pub struct FramePipelines<'a> {
    cache: &'a PipelineCache,
    failed: &'a Mutex<Option<PipelineError>>,
}

impl<'a> FramePipelines<'a> {
    pub fn new(cache: &'a PipelineCache, failed: &'a Mutex<Option<PipelineError>>) -> FramePipelines<'a> {
        FramePipelines { cache, failed }
    }

    pub fn cache(&self) -> &'a PipelineCache {
        self.cache
    }

    fn answer<T>(&self, result: Result<Option<T>, PipelineError>) -> Option<T> {
        match result {
            Ok(p) => p,
            Err(e) => {
                let mut failed = self.failed.lock().unwrap_or_else(|e| e.into_inner());
                failed.get_or_insert(e);
                None
            }
        }
    }
}

/// Vertex buffers a render pipeline reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum VertexInput {
    /// None: full-screen triangles from the vertex index.
    None,
    /// [`crate::gpu_types::MeshVertex`] in buffer 0 (locations 0 to 2); instances come from a
    /// storage buffer indexed by `instance_index` (the desktop frame).
    Mesh,
    /// Scene meshes: `MeshVertex` in buffer 0, `InstanceData` in buffer 1 (locations 0-6).
    MeshInstanced,
    /// Light volumes: a `vec3<f32>` position in buffer 0 (location 0).
    Position,
}

impl VertexInput {
    fn layout(self) -> VertexLayout {
        match self {
            VertexInput::None => VertexLayout::NONE,
            VertexInput::Mesh => crate::gpu_types::layouts::MESH,
            VertexInput::MeshInstanced => crate::gpu_types::layouts::MESH_INSTANCED,
            VertexInput::Position => crate::gpu_types::layouts::POSITION,
        }
    }
}

/// Everything that makes a render pipeline, in wgpu's terms: both frames describe theirs
/// with it.
#[derive(Clone, Debug, PartialEq)]
pub struct PipelineDesc {
    /// The vertex permutation's canonical name.
    pub vertex: String,
    /// The fragment permutation's canonical name (`None`: depth only).
    pub fragment: Option<String>,
    pub vertex_input: VertexInput,
    pub cull_mode: Option<wgpu::Face>,
    pub depth_stencil: Option<wgpu::DepthStencilState>,
    /// One per color attachment ([`untouched`] for one the pipeline does not write).
    pub targets: Vec<wgpu::ColorTargetState>,
    pub sample_count: u32,
}

impl PipelineDesc {
    /// No culling, depth or targets, one sample.
    pub fn new(vertex: &str, fragment: Option<&str>, vertex_input: VertexInput) -> PipelineDesc {
        PipelineDesc {
            vertex: vertex.to_string(),
            fragment: fragment.map(str::to_string),
            vertex_input,
            cull_mode: None,
            depth_stencil: None,
            targets: Vec::new(),
            sample_count: 1,
        }
    }

    /// A full-screen triangle into one target.
    pub fn fullscreen(vertex: &str, fragment: &str, target: wgpu::ColorTargetState) -> PipelineDesc {
        PipelineDesc { targets: vec![target], ..PipelineDesc::new(vertex, Some(fragment), VertexInput::None) }
    }

    /// The key of the pipeline in the runtime's cache.
    pub fn key(&self) -> RenderKey {
        let state = RenderState::from_wgpu(
            self.vertex_input.layout(),
            self.cull_mode,
            self.depth_stencil.as_ref(),
            &self.targets,
            self.sample_count,
        );
        RenderKey { vertex: self.vertex.clone(), fragment: self.fragment.clone(), state }
    }
}

/// A color target that replaces (no blending) and writes every channel.
pub fn replace(format: wgpu::TextureFormat) -> wgpu::ColorTargetState {
    blended(format, None)
}

/// A color target with `blend` (none: replace), writing every channel.
pub fn blended(format: wgpu::TextureFormat, blend: Option<wgpu::BlendState>) -> wgpu::ColorTargetState {
    wgpu::ColorTargetState { format, blend, write_mask: wgpu::ColorWrites::ALL }
}

/// A color target the shader does not write in this pipeline.
pub fn untouched(format: wgpu::TextureFormat) -> wgpu::ColorTargetState {
    wgpu::ColorTargetState { format, blend: None, write_mask: wgpu::ColorWrites::empty() }
}

/// Lights accumulating into SceneColor: `dst + src`, rgb only (CW_RGB, BF_One, BF_One).
pub fn additive(format: wgpu::TextureFormat) -> wgpu::ColorTargetState {
    let add = wgpu::BlendComponent {
        src_factor: wgpu::BlendFactor::One,
        dst_factor: wgpu::BlendFactor::One,
        operation: wgpu::BlendOperation::Add,
    };
    wgpu::ColorTargetState {
        format,
        blend: Some(wgpu::BlendState { color: add, alpha: add }),
        write_mask: wgpu::ColorWrites::COLOR,
    }
}

/// Premultiplied translucency: `dst * (1 - src.a) + src`.
pub fn premultiplied(format: wgpu::TextureFormat) -> wgpu::ColorTargetState {
    wgpu::ColorTargetState {
        format,
        blend: Some(wgpu::BlendState::PREMULTIPLIED_ALPHA_BLENDING),
        write_mask: wgpu::ColorWrites::COLOR,
    }
}

/// The bind groups of every group `layout` has, each from the named resources (`None` for
/// a group the pipeline does not use). The one bind-group-by-name of the renderer.
pub fn bind_groups(
    device: &wgpu::Device,
    layout: &PipelineLayoutInfo,
    resources: &[(&str, wgpu::BindingResource<'_>)],
) -> Result<Vec<Option<wgpu::BindGroup>>, PipelineError> {
    (0..layout.groups.len() as u32)
        .map(|g| {
            if layout.uses_group(g) {
                layout.bind_group(device, g, &format!("{} group {g}", layout.label), resources).map(Some)
            } else {
                Ok(None)
            }
        })
        .collect()
}

/// A render pipeline as a pass holds it: its key and its layout. The layout comes from the
/// stages' reflection through the cache (whose bind group layouts every pipeline of the same
/// bindings shares), so bind groups can be made before the pipeline exists.
#[derive(Clone, Debug)]
pub struct RenderSlot {
    key: RenderKey,
    /// The bind group layouts the pipeline will have.
    pub layout: PipelineLayoutInfo,
}

impl RenderSlot {
    /// The slot of `key`; with [`Creation::Eager`], its pipeline is created now.
    pub fn new(cache: &PipelineCache, key: RenderKey, creation: Creation) -> Result<RenderSlot, PipelineError> {
        let label = match &key.fragment {
            Some(f) => format!("{} + {f}", key.vertex),
            None => key.vertex.clone(),
        };
        let vertex = cache.reflection(&key.vertex, Stage::Vertex)?;
        let fragment = match &key.fragment {
            Some(f) => Some(cache.reflection(f, Stage::Fragment)?),
            None => None,
        };
        let mut reflections = vec![&vertex];
        reflections.extend(fragment.as_ref());
        let layout = cache.layout(&label, &reflections)?;
        if creation == Creation::Eager {
            ready_render(cache, &key)?;
        }
        Ok(RenderSlot { key, layout })
    }

    /// The slot of the pipeline `desc` describes.
    pub fn from_desc(
        cache: &PipelineCache,
        desc: &PipelineDesc,
        creation: Creation,
    ) -> Result<RenderSlot, PipelineError> {
        RenderSlot::new(cache, desc.key(), creation)
    }

    pub fn key(&self) -> &RenderKey {
        &self.key
    }

    /// `"vertex + fragment"`, as the cache labels the pipeline.
    pub fn label(&self) -> &str {
        &self.layout.label
    }

    /// The pipeline to draw with now, or `None`: skip the draw.
    pub fn ready(&self, pipelines: FramePipelines<'_>) -> Option<Arc<RenderPipeline>> {
        pipelines.answer(ready_render(pipelines.cache, &self.key))
    }

    /// See [`bind_groups`].
    pub fn bind_groups(
        &self,
        device: &wgpu::Device,
        resources: &[(&str, wgpu::BindingResource<'_>)],
    ) -> Result<Vec<Option<wgpu::BindGroup>>, PipelineError> {
        bind_groups(device, &self.layout, resources)
    }
}

/// A compute pipeline as a pass holds it (see [`RenderSlot`]).
#[derive(Clone, Debug)]
pub struct ComputeSlot {
    key: ComputeKey,
    /// The bind group layouts the pipeline will have.
    pub layout: PipelineLayoutInfo,
    /// The shader's workgroup size, from its reflection.
    pub workgroup_size: [u32; 3],
}

impl ComputeSlot {
    /// The slot of compute permutation `name`; with [`Creation::Eager`], its pipeline is
    /// created now.
    pub fn new(cache: &PipelineCache, name: &str, creation: Creation) -> Result<ComputeSlot, PipelineError> {
        let key = ComputeKey { compute: name.to_string() };
        let reflection = cache.reflection(name, Stage::Compute)?;
        let layout = cache.layout(name, &[&reflection])?;
        if creation == Creation::Eager {
            ready_compute(cache, &key)?;
        }
        Ok(ComputeSlot { key, layout, workgroup_size: reflection.workgroup_size.unwrap_or([1, 1, 1]) })
    }

    pub fn key(&self) -> &ComputeKey {
        &self.key
    }

    /// The pipeline to dispatch with now, or `None`: skip the dispatch.
    pub fn ready(&self, pipelines: FramePipelines<'_>) -> Option<Arc<ComputePipeline>> {
        pipelines.answer(ready_compute(pipelines.cache, &self.key))
    }

    /// See [`bind_groups`].
    pub fn bind_groups(
        &self,
        device: &wgpu::Device,
        resources: &[(&str, wgpu::BindingResource<'_>)],
    ) -> Result<Vec<Option<wgpu::BindGroup>>, PipelineError> {
        bind_groups(device, &self.layout, resources)
    }
}
