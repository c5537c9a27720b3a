//! Shader modules, bind group layouts and pipelines from the archive.
//!
//! Modules are created lazily, once per permutation: SPIR-V passthrough when the device has
//! it (`Gpu::spirv_passthrough`), WGSL otherwise. Bind group layouts come from the archive's
//! reflection, merging the stages of a pipeline (visibility is the set of stages that use a
//! binding). Pipelines are cached per (permutations, fixed-function state). Bind groups are
//! built by resource name: a pass hands over `("View", buffer)`-style pairs and the
//! reflection says where each goes.

use std::borrow::Cow;
use std::collections::HashMap;
use std::num::NonZeroU64;
use std::sync::{Arc, Mutex};

use kiln::archive::{Binding, BindingKind, Reflection, SampleKind, StorageAccess, Target, TextureDim};
use kiln::Stage;

use crate::gpu::Gpu;
use crate::shaders::{LookupError, ShaderArchive};
use crate::spirv::{SpirvError, SpirvModule, VulkanBindings};

#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error(transparent)]
    Lookup(#[from] LookupError),
    #[error("permutation `{name}` is a {found} shader, used as a {wanted} shader")]
    WrongStage { name: String, found: Stage, wanted: Stage },
    #[error("permutation `{name}` has neither a WGSL nor a SPIR-V artifact (it has: {targets})")]
    NoArtifact { name: String, targets: String },
    #[error("permutation `{name}`: {message}")]
    BadArtifact { name: String, message: String },
    #[error("permutation `{name}`: {source}")]
    Spirv { name: String, source: SpirvError },
    #[error("{what}: wgpu rejected it: {message}")]
    Wgpu { what: String, message: String },
    #[error("pipeline `{label}`: binding @group({group}) @binding({binding}) is `{kind_a}` in one stage and `{kind_b}` in another")]
    StageConflict { label: String, group: u32, binding: u32, kind_a: String, kind_b: String },
    #[error("pipeline `{label}`: vertex input @location({location}) is not provided by the {layout:?} vertex layout")]
    VertexInput { label: String, location: u32, layout: VertexLayout },
    #[error("pipeline `{label}`: storage texture format `{format}` is not known to the runtime")]
    StorageFormat { label: String, format: String },
    #[error("bind group {group} of `{label}`: no resource given for binding {binding} `{name}`")]
    MissingResource { label: String, group: u32, binding: u32, name: String },
}

/// Vertex buffers a render pipeline reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum VertexLayout {
    /// No vertex buffers (full-screen triangles from the vertex index).
    None,
    /// [`crate::gpu_types::MeshVertex`] in buffer 0 and [`crate::gpu_types::InstanceData`]
    /// (one local-to-world matrix per instance) in buffer 1.
    MeshInstanced,
}

/// How a color target blends.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Blend {
    Replace,
    /// dst + src (lights accumulating into SceneColor).
    Additive,
    /// dst * (1 - src.a) + src (premultiplied translucency).
    PremultipliedAlpha,
}

impl Blend {
    fn state(self) -> Option<wgpu::BlendState> {
        match self {
            Blend::Replace => None,
            Blend::Additive => Some(wgpu::BlendState {
                color: wgpu::BlendComponent {
                    src_factor: wgpu::BlendFactor::One,
                    dst_factor: wgpu::BlendFactor::One,
                    operation: wgpu::BlendOperation::Add,
                },
                alpha: wgpu::BlendComponent {
                    src_factor: wgpu::BlendFactor::Zero,
                    dst_factor: wgpu::BlendFactor::One,
                    operation: wgpu::BlendOperation::Add,
                },
            }),
            Blend::PremultipliedAlpha => Some(wgpu::BlendState::PREMULTIPLIED_ALPHA_BLENDING),
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct ColorTarget {
    pub format: wgpu::TextureFormat,
    pub blend: Blend,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct DepthState {
    pub format: wgpu::TextureFormat,
    pub write: bool,
    pub compare: wgpu::CompareFunction,
    /// Constant depth bias (shadow depths).
    pub bias: i32,
    /// Slope-scaled bias, as `f32::to_bits` so the state hashes.
    pub slope_scale_bits: u32,
}

impl DepthState {
    /// Reverse-Z depth test (near = 1, far = 0).
    pub fn reverse_z(format: wgpu::TextureFormat, write: bool) -> DepthState {
        DepthState { format, write, compare: wgpu::CompareFunction::GreaterEqual, bias: 0, slope_scale_bits: 0 }
    }
}

/// The fixed-function state of a render pipeline: everything but the shaders.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct RenderState {
    pub vertex_layout: VertexLayout,
    pub topology: wgpu::PrimitiveTopology,
    pub cull_mode: Option<wgpu::Face>,
    pub depth: Option<DepthState>,
    /// Stencil test and writes (needs a depth format with stencil).
    pub stencil: wgpu::StencilState,
    pub color_targets: Vec<ColorTarget>,
    pub sample_count: u32,
}

impl RenderState {
    /// Triangles from mesh vertex buffers, back faces culled, no targets yet.
    pub fn mesh() -> RenderState {
        RenderState {
            vertex_layout: VertexLayout::MeshInstanced,
            topology: wgpu::PrimitiveTopology::TriangleList,
            cull_mode: Some(wgpu::Face::Back),
            depth: None,
            stencil: wgpu::StencilState::default(),
            color_targets: Vec::new(),
            sample_count: 1,
        }
    }

    /// A full-screen triangle (no vertex buffers, no culling, no depth).
    pub fn fullscreen(target: ColorTarget) -> RenderState {
        RenderState {
            vertex_layout: VertexLayout::None,
            topology: wgpu::PrimitiveTopology::TriangleList,
            cull_mode: None,
            depth: None,
            stencil: wgpu::StencilState::default(),
            color_targets: vec![target],
            sample_count: 1,
        }
    }

    pub fn with_depth(mut self, depth: DepthState) -> RenderState {
        self.depth = Some(depth);
        self
    }

    pub fn with_targets(mut self, targets: &[ColorTarget]) -> RenderState {
        self.color_targets = targets.to_vec();
        self
    }

    pub fn with_cull(mut self, cull: Option<wgpu::Face>) -> RenderState {
        self.cull_mode = cull;
        self
    }

    pub fn with_stencil(mut self, stencil: wgpu::StencilState) -> RenderState {
        self.stencil = stencil;
        self
    }

    /// MSAA sample count of every attachment.
    pub fn with_samples(mut self, count: u32) -> RenderState {
        self.sample_count = count;
        self
    }
}

/// One resource binding of a pipeline, merged over its stages.
#[derive(Clone, Debug)]
pub struct MergedBinding {
    pub binding: u32,
    pub name: Option<String>,
    pub kind: BindingKind,
    pub visibility: wgpu::ShaderStages,
}

/// The bind group layouts of a pipeline, one per group index from 0 to the highest used.
#[derive(Clone, Debug)]
pub struct PipelineLayoutInfo {
    pub label: String,
    pub groups: Vec<Vec<MergedBinding>>,
    pub bind_group_layouts: Vec<wgpu::BindGroupLayout>,
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
        let bind_group =
            device.create_bind_group(&wgpu::BindGroupDescriptor { label: Some(label), layout, entries: &entries });
        check_scope(scope, || format!("bind group `{label}`"))?;
        Ok(bind_group)
    }

    /// Whether the pipeline uses group `group` at all.
    pub fn uses_group(&self, group: u32) -> bool {
        self.groups.get(group as usize).is_some_and(|g| !g.is_empty())
    }
}

/// A cached render pipeline with its layouts.
#[derive(Debug)]
pub struct RenderPipeline {
    pub pipeline: wgpu::RenderPipeline,
    pub layout: PipelineLayoutInfo,
    /// The permutations it runs.
    pub vertex: String,
    pub fragment: Option<String>,
}

#[derive(Debug)]
pub struct ComputePipeline {
    pub pipeline: wgpu::ComputePipeline,
    pub layout: PipelineLayoutInfo,
    pub compute: String,
    pub workgroup_size: [u32; 3],
}

#[derive(Clone, Debug, PartialEq, Eq, Hash)]
struct RenderKey {
    vertex: String,
    fragment: Option<String>,
    state: RenderState,
}

/// Counters of what the cache created (for tests and the warm-up check).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CacheStats {
    pub modules: usize,
    pub render_pipelines: usize,
    pub compute_pipelines: usize,
    pub bind_group_layouts: usize,
}

#[derive(Default)]
struct CacheInner {
    /// By the artifact blob the module was made from and, for SPIR-V passthrough, the Vulkan
    /// binding numbers of its resources: permutations that compiled to the same code share one
    /// module wherever their pipeline layouts number the bindings alike.
    modules: HashMap<(Target, kiln::archive::BlobId, Vec<u32>), wgpu::ShaderModule>,
    /// SPIR-V artifacts walked once ([`crate::spirv`]), by blob.
    spirv: HashMap<kiln::archive::BlobId, Arc<SpirvModule>>,
    used: std::collections::BTreeSet<String>,
    layouts: HashMap<Vec<wgpu::BindGroupLayoutEntry>, wgpu::BindGroupLayout>,
    render: HashMap<RenderKey, Arc<RenderPipeline>>,
    compute: HashMap<String, Arc<ComputePipeline>>,
    /// Pipelines a pass builds itself ([`PipelineCache::external`]), with the permutations
    /// each uses.
    external: HashMap<String, (Vec<String>, Arc<dyn std::any::Any + Send + Sync>)>,
    stats: CacheStats,
}

/// Creates and caches modules, layouts and pipelines for one device and one archive.
pub struct PipelineCache {
    archive: Arc<ShaderArchive>,
    device: wgpu::Device,
    passthrough: bool,
    inner: Mutex<CacheInner>,
}

impl PipelineCache {
    pub fn new(gpu: &Gpu, archive: Arc<ShaderArchive>) -> PipelineCache {
        PipelineCache {
            passthrough: gpu.spirv_passthrough && archive.trusted(),
            archive,
            device: gpu.device.clone(),
            inner: Mutex::default(),
        }
    }

    pub fn archive(&self) -> &ShaderArchive {
        &self.archive
    }

    /// Hot reload: a cache on `archive` holding this cache's layouts, modules and pipelines,
    /// except those of the `changed` permutations (and of permutations `archive` lacks), which
    /// are created again on first use. Its counters go on from this cache's.
    pub fn carry_over(
        &self,
        archive: Arc<ShaderArchive>,
        changed: &std::collections::HashSet<String>,
    ) -> PipelineCache {
        let old = self.lock();
        let keep = |name: &str| !changed.contains(name) && archive.archive().get(name).is_some();
        let mut inner = CacheInner { layouts: old.layouts.clone(), stats: old.stats, ..CacheInner::default() };
        // The blobs of the kept permutations, old id to new id, per target.
        let mut blobs = HashMap::new();
        for name in old.used.iter().filter(|n| keep(n)) {
            inner.used.insert(name.clone());
            let (Some(o), Some(n)) = (self.archive.archive().get(name), archive.archive().get(name)) else { continue };
            for target in [Target::Spirv, Target::Wgsl] {
                if let (Some(ob), Some(nb)) = (o.blob_id(target), n.blob_id(target)) {
                    blobs.insert((target, ob), nb);
                }
            }
        }
        for ((target, ob, numbering), m) in &old.modules {
            if let Some(nb) = blobs.get(&(*target, *ob)) {
                inner.modules.insert((*target, *nb, numbering.clone()), m.clone());
            }
        }
        for (k, p) in &old.render {
            if keep(&k.vertex) && k.fragment.as_deref().is_none_or(keep) {
                inner.render.insert(k.clone(), p.clone());
            }
        }
        for (k, p) in &old.compute {
            if keep(&p.compute) {
                inner.compute.insert(k.clone(), p.clone());
            }
        }
        for (k, (names, p)) in &old.external {
            if names.iter().all(|n| keep(n)) {
                inner.external.insert(k.clone(), (names.clone(), p.clone()));
            }
        }
        let passthrough = self.passthrough && archive.trusted();
        PipelineCache { archive, device: self.device.clone(), passthrough, inner: Mutex::new(inner) }
    }

    /// Whether modules come from SPIR-V passthrough: the device allows it and the archive is
    /// trusted ([`ShaderArchive::trusted`]); else from WGSL.
    pub fn uses_spirv_passthrough(&self) -> bool {
        self.passthrough
    }

    pub fn stats(&self) -> CacheStats {
        self.lock().stats
    }

    /// Every permutation a module was created for, sorted.
    pub fn permutations_used(&self) -> Vec<String> {
        self.lock().used.iter().cloned().collect()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, CacheInner> {
        self.inner.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The reflection of a permutation used as a `stage` shader.
    pub fn reflection(&self, name: &str, stage: Stage) -> Result<Reflection, PipelineError> {
        let perm = self.archive.get(name)?;
        let reflection = perm.reflection().clone();
        if reflection.stage != stage {
            return Err(PipelineError::WrongStage { name: name.to_string(), found: reflection.stage, wanted: stage });
        }
        self.lock().used.insert(name.to_string());
        Ok(reflection)
    }

    /// The shader module of a permutation alone (a pipeline of that one stage), created on
    /// first use.
    pub fn module(&self, name: &str, stage: Stage) -> Result<(wgpu::ShaderModule, Reflection), PipelineError> {
        let reflection = self.reflection(name, stage)?;
        let groups = merge_bindings(name, &[&reflection])?;
        let module = self.stage_module(name, &reflection, &vulkan_bindings(&groups))?;
        Ok((module, reflection))
    }

    /// The module of a permutation for a pipeline whose layout numbers bindings as
    /// `bindings` says, created on first use and shared with every permutation whose
    /// artifact is the same blob (and numbered alike).
    pub fn stage_module(
        &self,
        name: &str,
        reflection: &Reflection,
        bindings: &VulkanBindings,
    ) -> Result<wgpu::ShaderModule, PipelineError> {
        let perm = self.archive.get(name)?;
        let spirv_blob = perm.blob_id(Target::Spirv).filter(|_| self.passthrough);
        if let Some(blob) = spirv_blob {
            let parsed = self.lock().spirv.get(&blob).cloned();
            let parsed = match parsed {
                Some(p) => p,
                None => {
                    let bytes = perm.artifact(Target::Spirv).unwrap_or_default();
                    let parsed = SpirvModule::parse(bytes)
                        .and_then(|m| m.check(reflection).map(|()| m))
                        .map_err(|source| PipelineError::Spirv { name: name.to_string(), source })?;
                    let parsed = Arc::new(parsed);
                    self.lock().spirv.insert(blob, parsed.clone());
                    parsed
                }
            };
            let numbering: Vec<u32> = parsed.resources.iter().map(|r| bindings.get(r.group, r.binding)).collect();
            let key = (Target::Spirv, blob, numbering);
            if let Some(m) = self.lock().modules.get(&key) {
                return Ok(m.clone());
            }
            let words = parsed.remap_bindings(|g, b| bindings.get(g, b)).unwrap_or_else(|| parsed.words.clone());
            let module = create_spirv_module(&self.device, name, words, reflection)?;
            let mut inner = self.lock();
            inner.stats.modules += 1;
            inner.modules.insert(key, module.clone());
            return Ok(module);
        }
        let Some(blob) = perm.blob_id(Target::Wgsl) else {
            let targets = perm.targets().map(|t| t.name()).collect::<Vec<_>>().join(", ");
            return Err(PipelineError::NoArtifact { name: name.to_string(), targets });
        };
        let key = (Target::Wgsl, blob, Vec::new());
        if let Some(m) = self.lock().modules.get(&key) {
            return Ok(m.clone());
        }
        let module = create_wgsl_module(&self.device, name, perm.artifact(Target::Wgsl).unwrap_or_default())?;
        let mut inner = self.lock();
        inner.stats.modules += 1;
        inner.modules.insert(key, module.clone());
        Ok(module)
    }

    /// A render pipeline for (vertex permutation, fragment permutation, state), created on
    /// first use. `fragment` is `None` for depth-only pipelines.
    pub fn render(
        &self,
        vertex: &str,
        fragment: Option<&str>,
        state: &RenderState,
    ) -> Result<Arc<RenderPipeline>, PipelineError> {
        let key =
            RenderKey { vertex: vertex.to_string(), fragment: fragment.map(str::to_string), state: state.clone() };
        if let Some(p) = self.lock().render.get(&key) {
            return Ok(p.clone());
        }
        let label = match fragment {
            Some(f) => format!("{vertex} + {f}"),
            None => vertex.to_string(),
        };
        let vs_reflection = self.reflection(vertex, Stage::Vertex)?;
        let fs_reflection = match fragment {
            Some(f) => Some(self.reflection(f, Stage::Fragment)?),
            None => None,
        };
        let mut reflections = vec![&vs_reflection];
        reflections.extend(fs_reflection.as_ref());
        let layout = self.layout(&label, &reflections)?;
        let vs = self.stage_module(vertex, &vs_reflection, &layout.vulkan_bindings)?;
        let fs = match (fragment, fs_reflection) {
            (Some(f), Some(r)) => Some((self.stage_module(f, &r, &layout.vulkan_bindings)?, r)),
            _ => None,
        };
        let buffers = vertex_buffers(&label, state.vertex_layout, &vs_reflection)?;
        let targets: Vec<Option<wgpu::ColorTargetState>> = state
            .color_targets
            .iter()
            .map(|t| {
                Some(wgpu::ColorTargetState {
                    format: t.format,
                    blend: t.blend.state(),
                    write_mask: wgpu::ColorWrites::ALL,
                })
            })
            .collect();
        let scope = ErrorScopes::push(&self.device);
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
                topology: state.topology,
                cull_mode: state.cull_mode,
                front_face: wgpu::FrontFace::Ccw,
                ..Default::default()
            },
            depth_stencil: state.depth.map(|d| wgpu::DepthStencilState {
                format: d.format,
                depth_write_enabled: Some(d.write),
                depth_compare: Some(d.compare),
                stencil: state.stencil.clone(),
                bias: wgpu::DepthBiasState {
                    constant: d.bias,
                    slope_scale: f32::from_bits(d.slope_scale_bits),
                    clamp: 0.0,
                },
            }),
            multisample: wgpu::MultisampleState { count: state.sample_count, ..Default::default() },
            fragment: fs.as_ref().map(|(module, r)| wgpu::FragmentState {
                module,
                entry_point: Some(&r.entry),
                compilation_options: Default::default(),
                targets: &targets,
            }),
            multiview_mask: None,
            cache: None,
        });
        check_scope(scope, || format!("render pipeline `{label}`"))?;
        let handle = Arc::new(RenderPipeline {
            pipeline,
            layout,
            vertex: vertex.to_string(),
            fragment: fragment.map(str::to_string),
        });
        let mut inner = self.lock();
        inner.stats.render_pipelines += 1;
        inner.render.insert(key, handle.clone());
        Ok(handle)
    }

    /// A compute pipeline for a compute permutation, created on first use.
    pub fn compute(&self, name: &str) -> Result<Arc<ComputePipeline>, PipelineError> {
        let key = name.to_string();
        if let Some(p) = self.lock().compute.get(&key) {
            return Ok(p.clone());
        }
        let reflection = self.reflection(name, Stage::Compute)?;
        let layout = self.layout(name, &[&reflection])?;
        let module = self.stage_module(name, &reflection, &layout.vulkan_bindings)?;
        let scope = ErrorScopes::push(&self.device);
        let pipeline = self.device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(name),
            layout: Some(&layout.layout),
            module: &module,
            entry_point: Some(&reflection.entry),
            compilation_options: Default::default(),
            cache: None,
        });
        check_scope(scope, || format!("compute pipeline `{name}`"))?;
        let handle = Arc::new(ComputePipeline {
            pipeline,
            layout,
            compute: name.to_string(),
            workgroup_size: reflection.workgroup_size.unwrap_or([1, 1, 1]),
        });
        let mut inner = self.lock();
        inner.stats.compute_pipelines += 1;
        inner.compute.insert(key, handle.clone());
        Ok(handle)
    }

    /// A pipeline (or anything else made from permutations) that a pass builds itself, kept
    /// under `key` with the `permutations` it uses: created by `create` on first use, then
    /// shared, and carried over by hot reload unless one of its permutations changed.
    pub fn external<T: std::any::Any + Send + Sync>(
        &self,
        key: &str,
        permutations: &[&str],
        create: impl FnOnce() -> Result<T, PipelineError>,
    ) -> Result<Arc<T>, PipelineError> {
        if let Some(found) = self.lock().external.get(key).and_then(|(_, p)| p.clone().downcast::<T>().ok()) {
            return Ok(found);
        }
        let made = Arc::new(create()?);
        let names = permutations.iter().map(|n| n.to_string()).collect();
        self.lock().external.insert(key.to_string(), (names, made.clone()));
        Ok(made)
    }

    /// Counts a render pipeline a pass built itself from this cache's modules and layouts
    /// (the mobile frames, whose stencil and write-mask state `RenderState` does not hold).
    pub fn count_external_render_pipeline(&self) {
        self.lock().stats.render_pipelines += 1;
    }

    /// The pipeline layout of a set of stages, from their reflection (bind group layouts
    /// shared through the cache).
    pub fn layout(&self, label: &str, reflections: &[&Reflection]) -> Result<PipelineLayoutInfo, PipelineError> {
        let groups = merge_bindings(label, reflections)?;
        let mut bind_group_layouts = Vec::with_capacity(groups.len());
        for (g, bindings) in groups.iter().enumerate() {
            let entries = bindings.iter().map(|b| layout_entry(label, b)).collect::<Result<Vec<_>, _>>()?;
            let mut inner = self.lock();
            let layout = match inner.layouts.get(&entries) {
                Some(l) => l.clone(),
                None => {
                    let l = self.device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                        label: Some(&format!("{label} group {g}")),
                        entries: &entries,
                    });
                    inner.stats.bind_group_layouts += 1;
                    inner.layouts.insert(entries, l.clone());
                    l
                }
            };
            bind_group_layouts.push(layout);
        }
        let refs: Vec<Option<&wgpu::BindGroupLayout>> = bind_group_layouts.iter().map(Some).collect();
        let scope = ErrorScopes::push(&self.device);
        let layout = self.device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some(label),
            bind_group_layouts: &refs,
            immediate_size: 0,
        });
        check_scope(scope, || format!("pipeline layout `{label}`"))?;
        let vulkan_bindings = vulkan_bindings(&groups);
        Ok(PipelineLayoutInfo { label: label.to_string(), groups, bind_group_layouts, layout, vulkan_bindings })
    }
}

/// How wgpu-hal's Vulkan backend numbers the bindings of these groups.
fn vulkan_bindings(groups: &[Vec<MergedBinding>]) -> VulkanBindings {
    VulkanBindings::new(groups.iter().map(|g| g.iter().map(|b| b.binding).collect()).collect())
}

/// Creates a module from SPIR-V words as they are (passthrough), bypassing the cache. The
/// words must have passed [`SpirvModule::parse`] and [`SpirvModule::check`] against
/// `reflection`, and come from a trusted archive ([`ShaderArchive::trusted`]); their binding
/// numbers must be the layout's Vulkan ones ([`SpirvModule::remap_bindings`]).
pub fn create_spirv_module(
    device: &wgpu::Device,
    name: &str,
    words: Vec<u32>,
    reflection: &Reflection,
) -> Result<wgpu::ShaderModule, PipelineError> {
    let entry = wgpu::PassthroughShaderEntryPoint {
        name: Cow::Borrowed(&reflection.entry),
        workgroup_size: reflection.workgroup_size.map(|[x, y, z]| (x, y, z)).unwrap_or((1, 1, 1)),
    };
    let scope = ErrorScopes::push(device);
    // SAFETY: the SPIR-V comes from a trusted archive (embedded at build time: produced by
    // naga from a module naga validated, for the same wgpu/naga major version, and checked
    // by spirv-val in Kiln's tests); it passed the structural walk of `crate::spirv` and its
    // resources were checked against the reflection the pipeline layout is built from, with
    // binding numbers rewritten to the layout's Vulkan ones.
    let module = unsafe {
        device.create_shader_module_passthrough(wgpu::ShaderModuleDescriptorPassthrough {
            label: Some(name),
            entry_points: Cow::Owned(vec![entry]),
            spirv: Some(Cow::Owned(words)),
            ..Default::default()
        })
    };
    check_scope(scope, || format!("SPIR-V module `{name}`"))?;
    Ok(module)
}

/// Creates a module from a WGSL artifact (wgpu's naga parses and validates it), bypassing
/// the cache.
pub fn create_wgsl_module(
    device: &wgpu::Device,
    name: &str,
    bytes: &[u8],
) -> Result<wgpu::ShaderModule, PipelineError> {
    let bad = |message: String| PipelineError::BadArtifact { name: name.to_string(), message };
    let text = std::str::from_utf8(bytes).map_err(|e| bad(format!("WGSL artifact is not UTF-8: {e}")))?;
    let scope = ErrorScopes::push(device);
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(name),
        source: wgpu::ShaderSource::Wgsl(Cow::Borrowed(text)),
    });
    check_scope(scope, || format!("WGSL module `{name}`"))?;
    Ok(module)
}

/// Validation and internal errors (a backend's shader translation failing) of what runs
/// while they are pushed.
pub struct ErrorScopes {
    // Dropped in declaration order: the reverse of the order pushed.
    memory: wgpu::ErrorScopeGuard,
    internal: wgpu::ErrorScopeGuard,
    validation: wgpu::ErrorScopeGuard,
}

impl ErrorScopes {
    pub fn push(device: &wgpu::Device) -> ErrorScopes {
        let validation = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let internal = device.push_error_scope(wgpu::ErrorFilter::Internal);
        let memory = device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        ErrorScopes { memory, internal, validation }
    }

    /// The first error caught, with its sources.
    pub fn pop(self) -> Option<String> {
        let errors = [
            pollster::block_on(self.memory.pop()),
            pollster::block_on(self.internal.pop()),
            pollster::block_on(self.validation.pop()),
        ];
        errors.into_iter().flatten().next().map(|e| error_chain(&e))
    }
}

fn check_scope(scope: ErrorScopes, what: impl FnOnce() -> String) -> Result<(), PipelineError> {
    match scope.pop() {
        None => Ok(()),
        Some(message) => Err(PipelineError::Wgpu { what: what(), message }),
    }
}

/// An error and its sources on one line each (wgpu's own Display says only "Validation Error").
pub fn error_chain(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        let line = s.to_string();
        if !text.contains(&line) {
            text.push_str(": ");
            text.push_str(&line);
        }
        source = s.source();
    }
    text
}

fn stage_bits(stage: Stage) -> wgpu::ShaderStages {
    match stage {
        Stage::Vertex => wgpu::ShaderStages::VERTEX,
        Stage::Fragment => wgpu::ShaderStages::FRAGMENT,
        Stage::Compute => wgpu::ShaderStages::COMPUTE,
    }
}

/// Merges the bindings of a pipeline's stages into groups (index = group number).
pub fn merge_bindings(label: &str, reflections: &[&Reflection]) -> Result<Vec<Vec<MergedBinding>>, PipelineError> {
    let mut groups: Vec<Vec<MergedBinding>> = Vec::new();
    for r in reflections {
        for Binding { group, binding, name, kind } in &r.bindings {
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

fn view_dimension(dim: TextureDim) -> wgpu::TextureViewDimension {
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
fn layout_entry(label: &str, b: &MergedBinding) -> Result<wgpu::BindGroupLayoutEntry, PipelineError> {
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

const MESH_ATTRIBUTES: [wgpu::VertexAttribute; 3] =
    wgpu::vertex_attr_array![0 => Float32x3, 1 => Float32x3, 2 => Float32x2];
const INSTANCE_ATTRIBUTES: [wgpu::VertexAttribute; 4] =
    wgpu::vertex_attr_array![3 => Float32x4, 4 => Float32x4, 5 => Float32x4, 6 => Float32x4];

fn vertex_buffers(
    label: &str,
    layout: VertexLayout,
    reflection: &Reflection,
) -> Result<Vec<Option<wgpu::VertexBufferLayout<'static>>>, PipelineError> {
    let buffers = match layout {
        VertexLayout::None => Vec::new(),
        VertexLayout::MeshInstanced => vec![
            Some(wgpu::VertexBufferLayout {
                array_stride: std::mem::size_of::<crate::gpu_types::MeshVertex>() as u64,
                step_mode: wgpu::VertexStepMode::Vertex,
                attributes: &MESH_ATTRIBUTES,
            }),
            Some(wgpu::VertexBufferLayout {
                array_stride: std::mem::size_of::<crate::gpu_types::InstanceData>() as u64,
                step_mode: wgpu::VertexStepMode::Instance,
                attributes: &INSTANCE_ATTRIBUTES,
            }),
        ],
    };
    for input in &reflection.vertex_inputs {
        let provided = buffers.iter().flatten().flat_map(|b| b.attributes.iter()).any(|a| {
            a.shader_location == input.location
                && a.format.size() == u64::from(input.ty.width) * u64::from(input.ty.components)
        });
        if !provided {
            return Err(PipelineError::VertexInput { label: label.to_string(), location: input.location, layout });
        }
    }
    Ok(buffers)
}

#[cfg(test)]
mod tests {
    use kiln::archive::{NumericType, ScalarKind, VertexInput};

    use super::*;

    fn binding(group: u32, binding: u32, name: &str, kind: BindingKind) -> Binding {
        Binding { group, binding, name: Some(name.into()), kind }
    }

    fn reflection(stage: Stage, bindings: Vec<Binding>) -> Reflection {
        Reflection {
            entry: "main".into(),
            stage,
            bindings,
            vertex_inputs: vec![],
            color_outputs: vec![],
            workgroup_size: None,
        }
    }

    #[test]
    fn stages_merge_into_groups_with_the_union_of_visibilities() {
        let view = BindingKind::UniformBuffer { min_size: 320 };
        let vs = reflection(Stage::Vertex, vec![binding(0, 0, "View", view.clone())]);
        let fs = reflection(
            Stage::Fragment,
            vec![
                binding(0, 0, "View", view.clone()),
                binding(0, 2, "ShadowDepthSampler", BindingKind::Sampler { comparison: true }),
                binding(2, 0, "Light", BindingKind::UniformBuffer { min_size: 64 }),
            ],
        );
        let groups = merge_bindings("p", &[&vs, &fs]).unwrap();
        assert_eq!(groups.len(), 3, "group 1 is empty but present");
        assert!(groups[1].is_empty());
        let summary: Vec<(u32, &str, wgpu::ShaderStages)> =
            groups[0].iter().map(|b| (b.binding, b.name.as_deref().unwrap(), b.visibility)).collect();
        assert_eq!(
            summary,
            [(0, "View", wgpu::ShaderStages::VERTEX_FRAGMENT), (2, "ShadowDepthSampler", wgpu::ShaderStages::FRAGMENT)]
        );
    }

    #[test]
    fn a_binding_of_two_kinds_is_an_error() {
        let vs = reflection(Stage::Vertex, vec![binding(0, 1, "A", BindingKind::UniformBuffer { min_size: 16 })]);
        let fs = reflection(Stage::Fragment, vec![binding(0, 1, "B", BindingKind::Sampler { comparison: false })]);
        let e = merge_bindings("Pipe", &[&vs, &fs]).unwrap_err().to_string();
        assert_eq!(
            e,
            "pipeline `Pipe`: binding @group(0) @binding(1) is `UniformBuffer { min_size: 16 }` in one stage and `Sampler { comparison: false }` in another"
        );
    }

    #[test]
    fn layout_entries_follow_reflection() {
        let entry = |name: &str, kind: BindingKind| {
            let b =
                MergedBinding { binding: 3, name: Some(name.into()), kind, visibility: wgpu::ShaderStages::FRAGMENT };
            layout_entry("p", &b).unwrap().ty
        };
        let tex = |sample| BindingKind::Texture { dim: TextureDim::D2, sample, multisampled: false };
        assert_eq!(
            entry("GBufferATexture", tex(SampleKind::Float)),
            wgpu::BindingType::Texture {
                sample_type: wgpu::TextureSampleType::Float { filterable: true },
                view_dimension: wgpu::TextureViewDimension::D2,
                multisampled: false
            }
        );
        // Depth read as a float texture is unfilterable (GLES path).
        assert_eq!(
            entry("SceneDepthTexture", tex(SampleKind::Float)),
            wgpu::BindingType::Texture {
                sample_type: wgpu::TextureSampleType::Float { filterable: false },
                view_dimension: wgpu::TextureViewDimension::D2,
                multisampled: false
            }
        );
        assert_eq!(
            entry("ShadowDepthTexture", tex(SampleKind::Depth)),
            wgpu::BindingType::Texture {
                sample_type: wgpu::TextureSampleType::Depth,
                view_dimension: wgpu::TextureViewDimension::D2,
                multisampled: false
            }
        );
        assert_eq!(
            entry("Grid", BindingKind::StorageBuffer { read_only: true, min_size: 8 }),
            wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Storage { read_only: true },
                has_dynamic_offset: false,
                min_binding_size: NonZeroU64::new(8)
            }
        );
        assert_eq!(
            entry(
                "Out",
                BindingKind::StorageTexture {
                    dim: TextureDim::D2,
                    format: "rgba16float".into(),
                    access: StorageAccess::WriteOnly
                }
            ),
            wgpu::BindingType::StorageTexture {
                access: wgpu::StorageTextureAccess::WriteOnly,
                format: wgpu::TextureFormat::Rgba16Float,
                view_dimension: wgpu::TextureViewDimension::D2
            }
        );
        let b = MergedBinding {
            binding: 0,
            name: None,
            kind: BindingKind::StorageTexture {
                dim: TextureDim::D2,
                format: "bgra4".into(),
                access: StorageAccess::ReadOnly,
            },
            visibility: wgpu::ShaderStages::COMPUTE,
        };
        assert_eq!(
            layout_entry("Pipe", &b).unwrap_err().to_string(),
            "pipeline `Pipe`: storage texture format `bgra4` is not known to the runtime"
        );
    }

    #[test]
    fn vertex_inputs_must_be_in_the_mesh_layout() {
        let input = |location, components| VertexInput {
            location,
            name: None,
            ty: NumericType { scalar: ScalarKind::Float, width: 4, components },
        };
        let mut vs = reflection(Stage::Vertex, vec![]);
        vs.vertex_inputs = vec![input(0, 3), input(2, 2), input(6, 4)];
        assert_eq!(vertex_buffers("p", VertexLayout::MeshInstanced, &vs).unwrap().len(), 2);
        vs.vertex_inputs = vec![input(2, 4)];
        let e = vertex_buffers("Depth", VertexLayout::MeshInstanced, &vs).unwrap_err().to_string();
        assert_eq!(e, "pipeline `Depth`: vertex input @location(2) is not provided by the MeshInstanced vertex layout");
        vs.vertex_inputs = vec![input(0, 3)];
        let e = vertex_buffers("Screen", VertexLayout::None, &vs).unwrap_err().to_string();
        assert_eq!(e, "pipeline `Screen`: vertex input @location(0) is not provided by the None vertex layout");
    }
}
