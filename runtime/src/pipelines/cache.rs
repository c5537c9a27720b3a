//! The pipeline cache: modules, bind group layouts and pipelines created once per key.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use kiln_archive::Stage;
use kiln_archive::{Reflection, Target};

use super::disk_cache::DiskCache;
use super::layouts::{layout_entry, merge_bindings, vertex_buffers, vulkan_bindings};
use super::limits::check_limits;
use super::modules::{artifact, check_scope, create_spirv_module, create_wgsl_module, short_label, ErrorScopes};
use super::*;
use crate::gpu::Gpu;
use crate::shaders::ShaderArchive;
use crate::spirv::{SpirvModule, VulkanBindings};

/// A cached render pipeline with its layouts.
#[derive(Debug)]
pub struct RenderPipeline {
    /// The wgpu pipeline, to set in a render pass.
    pub pipeline: wgpu::RenderPipeline,
    /// Its bind group layouts, from the reflection of both stages.
    pub layout: PipelineLayoutInfo,
    /// The permutations it runs: the vertex one's canonical name.
    pub vertex: String,
    /// The fragment permutation's canonical name (`None`: depth only).
    pub fragment: Option<String>,
}

/// A cached compute pipeline with its layouts.
#[derive(Debug)]
pub struct ComputePipeline {
    /// The wgpu pipeline, to set in a compute pass.
    pub pipeline: wgpu::ComputePipeline,
    /// Its bind group layouts, from the permutation's reflection.
    pub layout: PipelineLayoutInfo,
    /// The compute permutation's canonical name.
    pub compute: String,
    /// Its `@workgroup_size`, to size dispatches by.
    pub workgroup_size: [u32; 3],
}

/// Counters of what the cache created (for tests and the warm-up check).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CacheStats {
    /// Shader modules created.
    pub modules: usize,
    /// Render pipelines created.
    pub render_pipelines: usize,
    /// Compute pipelines created.
    pub compute_pipelines: usize,
    /// Bind group layouts created (equal ones are shared).
    pub bind_group_layouts: usize,
}

#[derive(Default)]
pub(super) struct CacheInner {
    /// By the artifact blob the module was made from and, for SPIR-V passthrough, the Vulkan
    /// binding numbers of its resources: permutations that compiled to the same code share one
    /// module wherever their pipeline layouts number the bindings alike.
    modules: HashMap<(Target, kiln_archive::BlobId, Vec<u32>), wgpu::ShaderModule>,
    /// SPIR-V artifacts walked once ([`crate::spirv`]), by blob.
    spirv: HashMap<kiln_archive::BlobId, Arc<SpirvModule>>,
    used: std::collections::BTreeSet<String>,
    layouts: HashMap<Vec<wgpu::BindGroupLayoutEntry>, wgpu::BindGroupLayout>,
    pub(super) render: HashMap<RenderKey, Arc<RenderPipeline>>,
    pub(super) compute: HashMap<ComputeKey, Arc<ComputePipeline>>,
    stats: CacheStats,
    /// What was asked for, by frame ([`super::usage`]).
    pub(super) recorder: super::usage::Recorder,
}

/// Creates and caches modules, layouts and pipelines for one device and one archive.
pub struct PipelineCache {
    pub(super) archive: Arc<ShaderArchive>,
    pub(super) device: wgpu::Device,
    pub(super) passthrough: bool,
    pub(super) limits: wgpu::Limits,
    /// Shared with the worker views of [`super::missing`] and [`super::precache`]; never
    /// held across a wgpu call, so that workers create in parallel.
    pub(super) inner: Arc<Mutex<CacheInner>>,
    pub(super) disk: Option<DiskCache>,
    pub(super) background: Arc<super::inflight::Background>,
}

impl PipelineCache {
    /// A cache on the runtime's headless device (see [`Gpu::new`]).
    pub fn new(gpu: &Gpu, archive: Arc<ShaderArchive>) -> PipelineCache {
        PipelineCache::on(&gpu.device, gpu.spirv_passthrough, archive)
    }

    /// A cache on the application's own wgpu device, made from `adapter` however it likes
    /// (a window's surface, its own features and limits). Modules come from SPIR-V
    /// passthrough when the adapter is Vulkan, the device was created with
    /// `Features::PASSTHROUGH_SHADERS` and the archive is trusted; from WGSL otherwise.
    /// Reflection is checked against the device's own limits.
    pub fn for_device(adapter: &wgpu::Adapter, device: &wgpu::Device, archive: Arc<ShaderArchive>) -> PipelineCache {
        let passthrough = adapter.get_info().backend == wgpu::Backend::Vulkan
            && device.features().contains(wgpu::Features::PASSTHROUGH_SHADERS);
        PipelineCache::on(device, passthrough, archive)
    }

    fn on(device: &wgpu::Device, passthrough: bool, archive: Arc<ShaderArchive>) -> PipelineCache {
        PipelineCache {
            passthrough: passthrough && archive.trusted(),
            archive,
            device: device.clone(),
            limits: device.limits(),
            inner: Arc::default(),
            disk: None,
            background: Arc::default(),
        }
    }

    /// The archive the cache creates modules from.
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
        let keep = |name: &str| !changed.contains(name) && matches!(archive.archive().get(name), Ok(Some(_)));
        let mut inner = CacheInner {
            layouts: old.layouts.clone(),
            stats: old.stats,
            recorder: old.recorder.clone(),
            ..CacheInner::default()
        };
        // The blobs of the kept permutations, old id to new id, per target.
        let mut blobs = HashMap::new();
        for name in old.used.iter().filter(|n| keep(n)) {
            inner.used.insert(name.clone());
            let (Ok(Some(o)), Ok(Some(n))) = (self.archive.archive().get(name), archive.archive().get(name)) else {
                continue;
            };
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
        for (ob, walked) in &old.spirv {
            if let Some(nb) = blobs.get(&(Target::Spirv, *ob)) {
                inner.spirv.insert(*nb, walked.clone());
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
        let passthrough = self.passthrough && archive.trusted();
        PipelineCache {
            archive,
            device: self.device.clone(),
            passthrough,
            limits: self.limits.clone(),
            inner: Arc::new(Mutex::new(inner)),
            disk: self.disk.as_ref().map(|d| DiskCache { cache: d.cache.clone(), path: d.path.clone() }),
            background: Arc::new(self.background.carried()),
        }
    }

    /// Whether modules come from SPIR-V passthrough: the device allows it and the archive is
    /// trusted ([`ShaderArchive::trusted`]); else from WGSL.
    pub fn uses_spirv_passthrough(&self) -> bool {
        self.passthrough
    }

    /// What the cache has created so far.
    pub fn stats(&self) -> CacheStats {
        self.lock().stats
    }

    /// Every permutation a module was created for, sorted.
    pub fn permutations_used(&self) -> Vec<String> {
        self.lock().used.iter().cloned().collect()
    }

    pub(super) fn lock(&self) -> std::sync::MutexGuard<'_, CacheInner> {
        self.inner.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The reflection of a permutation used as a `stage` shader.
    pub fn reflection(&self, name: &str, stage: Stage) -> Result<Reflection, PipelineError> {
        let perm = self.archive.get(name)?;
        let reflection = perm.reflection().clone();
        if reflection.stage != stage {
            return Err(PipelineError::WrongStage { name: name.to_string(), found: reflection.stage, wanted: stage });
        }
        check_limits(&reflection, &self.limits)
            .map_err(|what| PipelineError::Limit { name: name.to_string(), what })?;
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
                    let bytes = artifact(&perm, Target::Spirv)?.unwrap_or_default();
                    let parsed = SpirvModule::parse(&bytes)
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
            return Ok(self.keep_module(key, module));
        }
        let Some(blob) = perm.blob_id(Target::Wgsl) else {
            let targets = perm.targets().map(|t| t.name()).collect::<Vec<_>>().join(", ");
            return Err(PipelineError::NoArtifact { name: name.to_string(), targets });
        };
        let key = (Target::Wgsl, blob, Vec::new());
        if let Some(m) = self.lock().modules.get(&key) {
            return Ok(m.clone());
        }
        let wgsl = artifact(&perm, Target::Wgsl)?.unwrap_or_default();
        let module = create_wgsl_module(&self.device, name, &wgsl)?;
        Ok(self.keep_module(key, module))
    }

    /// Caches `module` unless another thread cached one of `key` meanwhile (that one is
    /// kept, so that every pipeline shares it).
    fn keep_module(
        &self,
        key: (Target, kiln_archive::BlobId, Vec<u32>),
        module: wgpu::ShaderModule,
    ) -> wgpu::ShaderModule {
        let mut inner = self.lock();
        if let Some(m) = inner.modules.get(&key) {
            return m.clone();
        }
        inner.stats.modules += 1;
        inner.modules.insert(key, module.clone());
        module
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
        self.render_key(&key)
    }

    /// The render pipeline of `key`, created on first use. This is the one place the runtime
    /// creates render pipelines.
    pub fn render_key(&self, key: &RenderKey) -> Result<Arc<RenderPipeline>, PipelineError> {
        let pipeline = self.create_render(key)?;
        self.lock().recorder.render(key);
        Ok(pipeline)
    }

    /// The render pipeline of `key`, found or created, not recorded as used by a frame.
    pub(super) fn create_render(&self, key: &RenderKey) -> Result<Arc<RenderPipeline>, PipelineError> {
        if let Some(p) = self.lock().render.get(key) {
            return Ok(p.clone());
        }
        // One thread creates a key; the others wait for it and find it.
        let _claim = self.background.claim(PipelineKey::Render(key.clone()));
        if let Some(p) = self.lock().render.get(key) {
            return Ok(p.clone());
        }
        let (vertex, fragment, state) = (key.vertex.as_str(), key.fragment.as_deref(), &key.state);
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
        let buffers = vertex_buffers(&label, &state.vertex_layout, &vs_reflection)?;
        let targets: Vec<Option<wgpu::ColorTargetState>> = state.color_targets.iter().map(|t| Some(t.wgpu())).collect();
        let scope = ErrorScopes::push(&self.device);
        let pipeline = self.device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some(short_label(&label)),
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
            depth_stencil: state.depth_stencil(),
            multisample: wgpu::MultisampleState { count: state.sample_count, ..Default::default() },
            fragment: fs.as_ref().map(|(module, r)| wgpu::FragmentState {
                module,
                entry_point: Some(&r.entry),
                compilation_options: Default::default(),
                targets: &targets,
            }),
            multiview_mask: None,
            cache: self.disk.as_ref().map(|d| &d.cache),
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
        inner.render.insert(key.clone(), handle.clone());
        Ok(handle)
    }

    /// A compute pipeline for a compute permutation, created on first use.
    pub fn compute(&self, name: &str) -> Result<Arc<ComputePipeline>, PipelineError> {
        self.compute_key(&ComputeKey { compute: name.to_string() })
    }

    /// The compute pipeline of `key`, created on first use: the one place the runtime creates
    /// compute pipelines.
    pub fn compute_key(&self, key: &ComputeKey) -> Result<Arc<ComputePipeline>, PipelineError> {
        let pipeline = self.create_compute(key)?;
        self.lock().recorder.compute(key);
        Ok(pipeline)
    }

    /// The compute pipeline of `key`, found or created, not recorded as used by a frame.
    pub(super) fn create_compute(&self, key: &ComputeKey) -> Result<Arc<ComputePipeline>, PipelineError> {
        if let Some(p) = self.lock().compute.get(key) {
            return Ok(p.clone());
        }
        let _claim = self.background.claim(PipelineKey::Compute(key.clone()));
        if let Some(p) = self.lock().compute.get(key) {
            return Ok(p.clone());
        }
        let name = key.compute.as_str();
        let reflection = self.reflection(name, Stage::Compute)?;
        let layout = self.layout(name, &[&reflection])?;
        let module = self.stage_module(name, &reflection, &layout.vulkan_bindings)?;
        let scope = ErrorScopes::push(&self.device);
        let pipeline = self.device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(short_label(name)),
            layout: Some(&layout.layout),
            module: &module,
            entry_point: Some(&reflection.entry),
            compilation_options: Default::default(),
            cache: self.disk.as_ref().map(|d| &d.cache),
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
        inner.compute.insert(key.clone(), handle.clone());
        Ok(handle)
    }

    /// Creates every pipeline of `keys` ahead of the first frame (those already made are
    /// found); the first failure is returned. Warming up is no frame's use: it is not
    /// recorded ([`PipelineCache::usage`]).
    pub fn warm_up<'k>(&self, keys: impl IntoIterator<Item = &'k PipelineKey>) -> Result<(), PipelineError> {
        for key in keys {
            match key {
                PipelineKey::Render(k) => drop(self.create_render(k)?),
                PipelineKey::Compute(k) => drop(self.create_compute(k)?),
            }
        }
        Ok(())
    }

    /// The key of every pipeline created so far, render then compute, in no set order: a
    /// list to warm another cache up with.
    pub fn keys(&self) -> Vec<PipelineKey> {
        let inner = self.lock();
        let render = inner.render.keys().cloned().map(PipelineKey::Render);
        let compute = inner.compute.keys().cloned().map(PipelineKey::Compute);
        render.chain(compute).collect()
    }

    /// The pipeline layout of a set of stages, from their reflection (bind group layouts
    /// shared through the cache).
    pub fn layout(&self, label: &str, reflections: &[&Reflection]) -> Result<PipelineLayoutInfo, PipelineError> {
        let groups = merge_bindings(label, reflections)?;
        let mut bind_group_layouts = Vec::with_capacity(groups.len());
        for (g, bindings) in groups.iter().enumerate() {
            let entries = bindings.iter().map(|b| layout_entry(label, b)).collect::<Result<Vec<_>, _>>()?;
            let found = self.lock().layouts.get(&entries).cloned();
            let layout = match found {
                Some(l) => l,
                None => {
                    let l = self.device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                        label: Some(short_label(&format!("{label} group {g}"))),
                        entries: &entries,
                    });
                    // Another thread may have made the same one meanwhile: keep the first.
                    let mut inner = self.lock();
                    match inner.layouts.get(&entries) {
                        Some(first) => first.clone(),
                        None => {
                            inner.stats.bind_group_layouts += 1;
                            inner.layouts.insert(entries, l.clone());
                            l
                        }
                    }
                }
            };
            bind_group_layouts.push(layout);
        }
        let refs: Vec<Option<&wgpu::BindGroupLayout>> = bind_group_layouts.iter().map(Some).collect();
        let scope = ErrorScopes::push(&self.device);
        let layout = self.device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some(short_label(label)),
            bind_group_layouts: &refs,
            immediate_size: 0,
        });
        check_scope(scope, || format!("pipeline layout `{label}`"))?;
        let vulkan_bindings = vulkan_bindings(&groups);
        Ok(PipelineLayoutInfo { label: label.to_string(), groups, bind_group_layouts, layout, vulkan_bindings })
    }
}
