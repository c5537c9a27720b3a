//! Shader modules, bind group layouts and pipelines from the archive.
//!
//! Takes permutation names and fixed-function state; gives modules, layouts and pipelines
//! from the runtime's one cache ([`PipelineCache`]), keyed by [`RenderKey`] (permutations,
//! vertex layout, primitive and cull, depth and stencil with the bias as bits, color targets
//! with blend and write masks, sample count) or [`ComputeKey`]. Guarantees: every field of a
//! permutation's reflection is checked against the device's limits before it is used
//! ([`check_limits`]); bind group layouts come from the reflection, merged across stages
//! (visibility is the set of stages that use a binding); modules are created lazily, from
//! SPIR-V passthrough where the device allows it and the archive is trusted (walked and
//! checked against the reflection, binding numbers rewritten to the layout's Vulkan ones:
//! [`crate::spirv`]), from WGSL otherwise; every wgpu error is a [`PipelineError`] naming
//! what failed. Bind groups are built by resource name: a pass hands over
//! `("View", buffer)`-style pairs and the reflection says where each goes.

use std::borrow::Cow;
use std::collections::HashMap;
use std::num::NonZeroU64;
use std::sync::{Arc, Mutex};

use kiln_archive::Stage;
use kiln_archive::{Binding, BindingKind, Reflection, SampleKind, StorageAccess, Target, TextureDim};

pub use crate::gpu::error_chain;
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
    #[error("permutation `{name}`: {what}")]
    Limit { name: String, what: String },
    #[error("{what}: wgpu rejected it: {message}")]
    Wgpu { what: String, message: String },
    #[error("pipeline `{label}`: binding @group({group}) @binding({binding}) is `{kind_a}` in one stage and `{kind_b}` in another")]
    StageConflict { label: String, group: u32, binding: u32, kind_a: String, kind_b: String },
    #[error("pipeline `{label}`: vertex input @location({location}) is not provided by its vertex layout (locations {provided:?})")]
    VertexInput { label: String, location: u32, provided: Vec<u32> },
    #[error("pipeline `{label}`: storage texture format `{format}` is not known to the runtime")]
    StorageFormat { label: String, format: String },
    #[error("bind group {group} of `{label}`: no resource given for binding {binding} `{name}`")]
    MissingResource { label: String, group: u32, binding: u32, name: String },
}

/// One vertex buffer of a [`VertexLayout`]: stride, step mode and attributes, in wgpu's terms
/// but owned and hashable, so that a pipeline key can hold it.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct VertexBuffer {
    pub stride: u64,
    pub step_mode: wgpu::VertexStepMode,
    pub attributes: Cow<'static, [wgpu::VertexAttribute]>,
}

impl VertexBuffer {
    /// A buffer described at compile time (`wgpu::vertex_attr_array!` in a `const`).
    pub const fn new(
        stride: u64,
        step_mode: wgpu::VertexStepMode,
        attributes: &'static [wgpu::VertexAttribute],
    ) -> VertexBuffer {
        VertexBuffer { stride, step_mode, attributes: Cow::Borrowed(attributes) }
    }

    /// The buffer a `wgpu::VertexBufferLayout` describes.
    pub fn from_wgpu(layout: &wgpu::VertexBufferLayout<'_>) -> VertexBuffer {
        VertexBuffer {
            stride: layout.array_stride,
            step_mode: layout.step_mode,
            attributes: Cow::Owned(layout.attributes.to_vec()),
        }
    }

    pub fn wgpu(&self) -> wgpu::VertexBufferLayout<'_> {
        wgpu::VertexBufferLayout { array_stride: self.stride, step_mode: self.step_mode, attributes: &self.attributes }
    }
}

/// The vertex buffers a render pipeline reads, in slot order, as the application describes
/// them (the runtime knows no vertex format of its own). Every vertex input of the vertex
/// shader's reflection must be provided by one attribute of the same size, or pipeline
/// creation is an error naming the location ([`PipelineError::VertexInput`]).
#[derive(Clone, Debug, Default, PartialEq, Eq, Hash)]
pub struct VertexLayout {
    buffers: Cow<'static, [VertexBuffer]>,
}

impl VertexLayout {
    /// No vertex buffers (full-screen triangles from the vertex index, or vertices pulled
    /// from storage buffers).
    pub const NONE: VertexLayout = VertexLayout { buffers: Cow::Borrowed(&[]) };

    /// A layout described at compile time:
    /// `const BUFFERS: &[VertexBuffer] = &[...]; const MESH: VertexLayout = VertexLayout::from_static(BUFFERS);`.
    pub const fn from_static(buffers: &'static [VertexBuffer]) -> VertexLayout {
        VertexLayout { buffers: Cow::Borrowed(buffers) }
    }

    pub fn new(buffers: Vec<VertexBuffer>) -> VertexLayout {
        VertexLayout { buffers: Cow::Owned(buffers) }
    }

    /// The layout of these `wgpu::VertexBufferLayout`s (slot `i` is `layouts[i]`).
    pub fn from_wgpu(layouts: &[wgpu::VertexBufferLayout<'_>]) -> VertexLayout {
        VertexLayout::new(layouts.iter().map(VertexBuffer::from_wgpu).collect())
    }

    pub fn buffers(&self) -> &[VertexBuffer] {
        &self.buffers
    }

    /// The shader locations the layout provides, in slot order.
    pub fn locations(&self) -> Vec<u32> {
        self.buffers.iter().flat_map(|b| b.attributes.iter().map(|a| a.shader_location)).collect()
    }
}

/// How a color target blends.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Blend {
    Replace,
    /// dst + src (lights accumulating into SceneColor).
    Additive,
    /// dst * (1 - src.a) + src (premultiplied translucency).
    PremultipliedAlpha,
    /// Any other blend state.
    State(wgpu::BlendState),
}

impl Blend {
    pub fn state(self) -> Option<wgpu::BlendState> {
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
            Blend::State(state) => Some(state),
        }
    }
}

/// A color target: format, blending (`None`: replace) and the channels written.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct ColorTarget {
    pub format: wgpu::TextureFormat,
    pub blend: Option<wgpu::BlendState>,
    pub write_mask: wgpu::ColorWrites,
}

impl ColorTarget {
    /// A target writing every channel.
    pub fn new(format: wgpu::TextureFormat, blend: Blend) -> ColorTarget {
        ColorTarget { format, blend: blend.state(), write_mask: wgpu::ColorWrites::ALL }
    }

    pub fn with_write_mask(mut self, mask: wgpu::ColorWrites) -> ColorTarget {
        self.write_mask = mask;
        self
    }

    fn wgpu(&self) -> wgpu::ColorTargetState {
        wgpu::ColorTargetState { format: self.format, blend: self.blend, write_mask: self.write_mask }
    }
}

impl From<&wgpu::ColorTargetState> for ColorTarget {
    fn from(t: &wgpu::ColorTargetState) -> ColorTarget {
        ColorTarget { format: t.format, blend: t.blend, write_mask: t.write_mask }
    }
}

/// Depth test, writes and bias. The bias floats are stored as bits so the state hashes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct DepthState {
    pub format: wgpu::TextureFormat,
    pub write: bool,
    pub compare: wgpu::CompareFunction,
    /// Constant depth bias (shadow depths).
    pub bias: i32,
    /// Slope-scaled bias, as `f32::to_bits`.
    pub slope_scale_bits: u32,
    /// Bias clamp, as `f32::to_bits`.
    pub clamp_bits: u32,
}

impl DepthState {
    /// Reverse-Z depth test (near = 1, far = 0).
    pub fn reverse_z(format: wgpu::TextureFormat, write: bool) -> DepthState {
        DepthState {
            format,
            write,
            compare: wgpu::CompareFunction::GreaterEqual,
            bias: 0,
            slope_scale_bits: 0,
            clamp_bits: 0,
        }
    }
}

/// The fixed-function state of a render pipeline: everything but the shaders. It is the
/// pipeline cache's key with the permutations ([`RenderKey`]), so it holds every piece of
/// state that changes the pipeline.
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
    /// Triangles from the vertex buffers of `vertex_layout`, back faces culled, no targets yet.
    pub fn triangles(vertex_layout: VertexLayout) -> RenderState {
        RenderState {
            vertex_layout,
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
            vertex_layout: VertexLayout::NONE,
            topology: wgpu::PrimitiveTopology::TriangleList,
            cull_mode: None,
            depth: None,
            stencil: wgpu::StencilState::default(),
            color_targets: vec![target],
            sample_count: 1,
        }
    }

    /// The state of triangles with this vertex layout, culling, wgpu depth-stencil state,
    /// targets and sample count (the frames describe their passes in wgpu's terms).
    pub fn from_wgpu(
        vertex_layout: VertexLayout,
        cull_mode: Option<wgpu::Face>,
        depth_stencil: Option<&wgpu::DepthStencilState>,
        targets: &[wgpu::ColorTargetState],
        sample_count: u32,
    ) -> RenderState {
        let depth = depth_stencil.map(|d| DepthState {
            format: d.format,
            write: d.depth_write_enabled.unwrap_or(false),
            compare: d.depth_compare.unwrap_or(wgpu::CompareFunction::Always),
            bias: d.bias.constant,
            slope_scale_bits: d.bias.slope_scale.to_bits(),
            clamp_bits: d.bias.clamp.to_bits(),
        });
        RenderState {
            vertex_layout,
            topology: wgpu::PrimitiveTopology::TriangleList,
            cull_mode,
            depth,
            stencil: depth_stencil.map(|d| d.stencil.clone()).unwrap_or_default(),
            color_targets: targets.iter().map(ColorTarget::from).collect(),
            sample_count,
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

    fn depth_stencil(&self) -> Option<wgpu::DepthStencilState> {
        self.depth.map(|d| wgpu::DepthStencilState {
            format: d.format,
            depth_write_enabled: Some(d.write),
            depth_compare: Some(d.compare),
            stencil: self.stencil.clone(),
            bias: wgpu::DepthBiasState {
                constant: d.bias,
                slope_scale: f32::from_bits(d.slope_scale_bits),
                clamp: f32::from_bits(d.clamp_bits),
            },
        })
    }
}

/// The key of a render pipeline in the cache: its permutations and its whole fixed-function
/// state.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct RenderKey {
    /// The vertex permutation's canonical name.
    pub vertex: String,
    /// The fragment permutation's canonical name (`None`: depth only).
    pub fragment: Option<String>,
    pub state: RenderState,
}

/// The key of a compute pipeline: its permutation (compute has no fixed-function state).
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct ComputeKey {
    pub compute: String,
}

/// A pipeline to create ahead of the first frame ([`PipelineCache::warm_up`]).
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub enum PipelineKey {
    Render(RenderKey),
    Compute(ComputeKey),
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
    modules: HashMap<(Target, kiln_archive::BlobId, Vec<u32>), wgpu::ShaderModule>,
    /// SPIR-V artifacts walked once ([`crate::spirv`]), by blob.
    spirv: HashMap<kiln_archive::BlobId, Arc<SpirvModule>>,
    used: std::collections::BTreeSet<String>,
    layouts: HashMap<Vec<wgpu::BindGroupLayoutEntry>, wgpu::BindGroupLayout>,
    render: HashMap<RenderKey, Arc<RenderPipeline>>,
    compute: HashMap<ComputeKey, Arc<ComputePipeline>>,
    stats: CacheStats,
}

/// Creates and caches modules, layouts and pipelines for one device and one archive.
/// The largest pipeline cache file read back: far more than a driver's cache of every
/// pipeline of the bundled renderer (a few MB).
const MAX_DISK_CACHE: u64 = 256 << 20;

pub struct PipelineCache {
    archive: Arc<ShaderArchive>,
    device: wgpu::Device,
    passthrough: bool,
    limits: wgpu::Limits,
    inner: Mutex<CacheInner>,
    disk: Option<DiskCache>,
}

/// wgpu's driver-level pipeline cache, loaded from and saved to one file per adapter and
/// driver.
struct DiskCache {
    cache: wgpu::PipelineCache,
    path: std::path::PathBuf,
}

/// The first bytes of a pipeline cache file Kiln wrote; a blake3 hash of the data follows.
const DISK_CACHE_MAGIC: &[u8; 8] = b"KILNPC1\0";

/// The data of a pipeline cache file, or why it cannot be used.
fn read_disk_cache(bytes: &[u8]) -> Result<&[u8], &'static str> {
    let rest = bytes.strip_prefix(DISK_CACHE_MAGIC.as_slice()).ok_or("it is not a Kiln pipeline cache")?;
    if rest.len() < 32 {
        return Err("it is truncated");
    }
    let (hash, data) = rest.split_at(32);
    if blake3::hash(data).as_bytes() != hash {
        return Err("its checksum does not match (corrupt)");
    }
    Ok(data)
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
            inner: Mutex::default(),
            disk: None,
        }
    }

    /// A cache whose pipelines also go through wgpu's driver pipeline cache, loaded from
    /// `dir` (one file per adapter and driver) where the backend has one (Vulkan; lavapipe
    /// does). [`PipelineCache::save`] writes it back. A file that cannot be read or fails its
    /// checksum is ignored: the warning says why, and the cache starts empty.
    pub fn with_disk_cache(
        gpu: &Gpu,
        archive: Arc<ShaderArchive>,
        dir: &std::path::Path,
    ) -> (PipelineCache, Option<String>) {
        let key = gpu.pipeline_cache_key();
        PipelineCache::new(gpu, archive).load_disk_cache(key, dir)
    }

    /// As [`PipelineCache::with_disk_cache`], on the application's own device (see
    /// [`PipelineCache::for_device`]; the device needs `Features::PIPELINE_CACHE` for a disk
    /// cache).
    pub fn with_disk_cache_for_device(
        adapter: &wgpu::Adapter,
        device: &wgpu::Device,
        archive: Arc<ShaderArchive>,
        dir: &std::path::Path,
    ) -> (PipelineCache, Option<String>) {
        let key = crate::gpu::pipeline_cache_key(&adapter.get_info(), device);
        PipelineCache::for_device(adapter, device, archive).load_disk_cache(key, dir)
    }

    /// This cache with the driver's pipeline cache of file `key` in `dir` (none without a key;
    /// a file that is not regular, or larger than [`MAX_DISK_CACHE`], is a warning and
    /// ignored).
    fn load_disk_cache(self, key: Option<String>, dir: &std::path::Path) -> (PipelineCache, Option<String>) {
        let mut cache = self;
        let Some(key) = key else { return (cache, None) };
        let device = cache.device.clone();
        let path = dir.join(key);
        let mut warning = None;
        // Only a regular file, bounded: a FIFO or a link to a device is ignored (never waited
        // on or read without end).
        let bytes = match kiln_archive::input::read_regular(&path, MAX_DISK_CACHE) {
            Ok(b) => Some(b),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
            Err(e) => {
                warning = Some(format!("pipeline cache {} cannot be read ({e}); starting empty", path.display()));
                None
            }
        };
        let data = bytes.as_deref().and_then(|b| match read_disk_cache(b) {
            Ok(d) => Some(d),
            Err(why) => {
                warning = Some(format!("pipeline cache {} is ignored: {why}", path.display()));
                None
            }
        });
        let create = |data: Option<&[u8]>| {
            let scope = ErrorScopes::push(&device);
            // SAFETY: the data is either none or bytes this function wrote from
            // `PipelineCache::get_data` of a cache for the same adapter and driver (the file
            // name is wgpu's key for them), checked against their blake3 hash; wgpu checks its
            // own header (device, driver, version) again and the driver its own.
            let cache = unsafe {
                device.create_pipeline_cache(&wgpu::PipelineCacheDescriptor {
                    label: Some("kiln pipeline cache"),
                    data,
                    fallback: false,
                })
            };
            (cache, scope.pop())
        };
        let (wgpu_cache, error) = create(data);
        let wgpu_cache = match error {
            None => wgpu_cache,
            Some(e) => {
                warning = Some(format!("pipeline cache {} is ignored: {e}", path.display()));
                match create(None) {
                    (c, None) => c,
                    (_, Some(e)) => {
                        warning = Some(format!("no pipeline cache: {e}"));
                        return (cache, warning);
                    }
                }
            }
        };
        cache.disk = Some(DiskCache { cache: wgpu_cache, path });
        (cache, warning)
    }

    /// Writes the driver's pipeline cache back to its file (temp file + rename); the path,
    /// or `None` where there is no disk cache or the driver gives no data.
    pub fn save(&self) -> std::io::Result<Option<std::path::PathBuf>> {
        let Some(disk) = &self.disk else { return Ok(None) };
        let Some(data) = disk.cache.get_data() else { return Ok(None) };
        if let Some(dir) = disk.path.parent() {
            std::fs::create_dir_all(dir)?;
        }
        let mut bytes = Vec::with_capacity(data.len() + 40);
        bytes.extend_from_slice(DISK_CACHE_MAGIC);
        bytes.extend_from_slice(blake3::hash(&data).as_bytes());
        bytes.extend_from_slice(&data);
        kiln_archive::write_atomic(&disk.path, &bytes)?;
        Ok(Some(disk.path.clone()))
    }

    /// Whether pipelines go through a driver pipeline cache on disk.
    pub fn has_disk_cache(&self) -> bool {
        self.disk.is_some()
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
        let keep = |name: &str| !changed.contains(name) && matches!(archive.archive().get(name), Ok(Some(_)));
        let mut inner = CacheInner { layouts: old.layouts.clone(), stats: old.stats, ..CacheInner::default() };
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
            inner: Mutex::new(inner),
            disk: self.disk.as_ref().map(|d| DiskCache { cache: d.cache.clone(), path: d.path.clone() }),
        }
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
        let wgsl = artifact(&perm, Target::Wgsl)?.unwrap_or_default();
        let module = create_wgsl_module(&self.device, name, &wgsl)?;
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
        self.render_key(&key)
    }

    /// The render pipeline of `key`, created on first use. This is the one place the runtime
    /// creates render pipelines.
    pub fn render_key(&self, key: &RenderKey) -> Result<Arc<RenderPipeline>, PipelineError> {
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
    /// found); the first failure is returned.
    pub fn warm_up<'k>(&self, keys: impl IntoIterator<Item = &'k PipelineKey>) -> Result<(), PipelineError> {
        for key in keys {
            match key {
                PipelineKey::Render(k) => drop(self.render_key(k)?),
                PipelineKey::Compute(k) => drop(self.compute_key(k)?),
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
            let mut inner = self.lock();
            let layout = match inner.layouts.get(&entries) {
                Some(l) => l.clone(),
                None => {
                    let l = self.device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                        label: Some(short_label(&format!("{label} group {g}"))),
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
            label: Some(short_label(label)),
            bind_group_layouts: &refs,
            immediate_size: 0,
        });
        check_scope(scope, || format!("pipeline layout `{label}`"))?;
        let vulkan_bindings = vulkan_bindings(&groups);
        Ok(PipelineLayoutInfo { label: label.to_string(), groups, bind_group_layouts, layout, vulkan_bindings })
    }
}

/// A label GL accepts: at most 255 bytes (`GL_MAX_LABEL_LENGTH` is 256 with the nul;
/// longer labels are a GL error). Pipelines are labelled with their permutations' names,
/// which can be longer.
pub fn short_label(label: &str) -> &str {
    if label.len() <= 255 {
        return label;
    }
    let mut end = 255;
    while !label.is_char_boundary(end) {
        end -= 1;
    }
    &label[..end]
}

/// How wgpu-hal's Vulkan backend numbers the bindings of these groups.
fn vulkan_bindings(groups: &[Vec<MergedBinding>]) -> VulkanBindings {
    VulkanBindings::new(groups.iter().map(|g| g.iter().map(|b| b.binding).collect()).collect())
}

/// A permutation's artifact for `target`, read (decompressed, checked on first use) from the
/// archive; a damaged blob is an error naming the permutation.
pub(crate) fn artifact<'a>(
    perm: &kiln_archive::PermutationRef<'a>,
    target: Target,
) -> Result<Option<Cow<'a, [u8]>>, PipelineError> {
    perm.artifact(target)
        .map_err(|e| PipelineError::BadArtifact { name: perm.name().to_string(), message: e.to_string() })
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
            label: Some(short_label(name)),
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
        label: Some(short_label(name)),
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

fn stage_bits(stage: Stage) -> wgpu::ShaderStages {
    match stage {
        Stage::Vertex => wgpu::ShaderStages::VERTEX,
        Stage::Fragment => wgpu::ShaderStages::FRAGMENT,
        Stage::Compute => wgpu::ShaderStages::COMPUTE,
    }
}

/// Checks every field of a permutation's reflection against the device's limits (the
/// archive's manifest is input like any other: a checksum proves no origin): groups,
/// binding numbers, resources per stage and their sizes, vertex inputs, color outputs and
/// workgroup size. The message names the field, its value and the limit.
pub fn check_limits(r: &Reflection, limits: &wgpu::Limits) -> Result<(), String> {
    use kiln_archive::limits::{violations, ResourceClass, StageLimits, Violation as V};
    let stage_limits = StageLimits {
        max_bind_groups: limits.max_bind_groups,
        max_bindings_per_bind_group: limits.max_bindings_per_bind_group,
        max_uniform_buffers_per_shader_stage: limits.max_uniform_buffers_per_shader_stage,
        max_storage_buffers_per_shader_stage: limits.max_storage_buffers_per_shader_stage,
        max_samplers_per_shader_stage: limits.max_samplers_per_shader_stage,
        max_sampled_textures_per_shader_stage: limits.max_sampled_textures_per_shader_stage,
        max_storage_textures_per_shader_stage: limits.max_storage_textures_per_shader_stage,
        max_uniform_buffer_binding_size: limits.max_uniform_buffer_binding_size,
        max_storage_buffer_binding_size: limits.max_storage_buffer_binding_size,
        max_vertex_attributes: limits.max_vertex_attributes,
        max_color_attachments: limits.max_color_attachments,
        max_compute_workgroup_size: [
            limits.max_compute_workgroup_size_x,
            limits.max_compute_workgroup_size_y,
            limits.max_compute_workgroup_size_z,
        ],
        max_compute_invocations_per_workgroup: limits.max_compute_invocations_per_workgroup,
        vertex_storage: true,
    };
    let found = violations(r, &stage_limits);
    let at = |i: usize| format!("@group({}) @binding({})", r.bindings[i].group, r.bindings[i].binding);
    let over = |what: String, value: u64, field: &str, limit: u64| {
        format!("{what} is {value}, over the device's {field} ({limit})")
    };
    // The order of report: the entry point's name, then each binding's own faults (the
    // storage texture formats the runtime knows among them), then the counts per class,
    // then the rest as listed.
    if let Some(V::EntryName { len }) = found.first() {
        return Err(format!("entry point name of {len} bytes"));
    }
    let own = found.iter().find_map(|v| match *v {
        V::BindGroup { binding } | V::BindingNumber { binding } | V::Duplicate { binding } => Some((binding, v)),
        V::UniformSize { binding, .. } | V::StorageSize { binding, .. } => Some((binding, v)),
        _ => None,
    });
    let unknown_format = r.bindings.iter().position(|b| match &b.kind {
        BindingKind::StorageTexture { format, .. } => storage_format(format).is_none(),
        _ => false,
    });
    match (own, unknown_format) {
        (Some((i, v)), f) if f.is_none_or(|f| i <= f) => {
            let b = &r.bindings[i];
            return Err(match *v {
                V::BindGroup { .. } => {
                    format!(
                        "{}: group {} is past the device's max_bind_groups ({})",
                        at(i),
                        b.group,
                        limits.max_bind_groups
                    )
                }
                V::BindingNumber { .. } => format!(
                    "{}: binding {} is past the device's max_bindings_per_bind_group ({})",
                    at(i),
                    b.binding,
                    limits.max_bindings_per_bind_group
                ),
                V::Duplicate { .. } => format!("{} is listed twice", at(i)),
                V::UniformSize { size, .. } => over(
                    format!("{}: uniform buffer size", at(i)),
                    size,
                    "max_uniform_buffer_binding_size",
                    stage_limits.max_uniform_buffer_binding_size,
                ),
                V::StorageSize { size, .. } => over(
                    format!("{}: storage buffer size", at(i)),
                    size,
                    "max_storage_buffer_binding_size",
                    stage_limits.max_storage_buffer_binding_size,
                ),
                _ => unreachable!("only a binding's own faults are chosen above"),
            });
        }
        (_, Some(f)) => {
            let BindingKind::StorageTexture { format, .. } = &r.bindings[f].kind else { unreachable!() };
            return Err(format!("{}: storage texture format `{format}` is not known to the runtime", at(f)));
        }
        _ => {}
    }
    for class in ResourceClass::ALL {
        if let Some(V::TooMany { total, .. }) =
            found.iter().find(|v| matches!(v, V::TooMany { class: c, .. } if *c == class))
        {
            let limit = stage_limits.per_stage(class).into();
            return Err(over(format!("{} in the stage", class.plural()), (*total).into(), class.field(), limit));
        }
    }
    let xyz = ["x", "y", "z"];
    for v in &found {
        return Err(match *v {
            V::VertexInputs { count } => {
                over("vertex inputs".into(), count as u64, "max_vertex_attributes", limits.max_vertex_attributes.into())
            }
            V::VertexLocation { location } => format!(
                "vertex input @location({location}) is past the device's max_vertex_attributes ({})",
                limits.max_vertex_attributes
            ),
            V::ColorOutputs { count } => {
                over("color outputs".into(), count as u64, "max_color_attachments", limits.max_color_attachments.into())
            }
            V::ColorLocation { location } => format!(
                "color output @location({location}) is past the device's max_color_attachments ({})",
                limits.max_color_attachments
            ),
            V::WorkgroupZero { size: [x, y, z] } => format!("workgroup size {x}x{y}x{z} has a zero"),
            V::WorkgroupAxis { size, axis } => over(
                format!("workgroup size {}", xyz[axis]),
                size[axis].into(),
                ["max_compute_workgroup_size_x", "max_compute_workgroup_size_y", "max_compute_workgroup_size_z"][axis],
                stage_limits.max_compute_workgroup_size[axis].into(),
            ),
            V::WorkgroupInvocations { total, .. } => over(
                "workgroup invocations".into(),
                total,
                "max_compute_invocations_per_workgroup",
                limits.max_compute_invocations_per_workgroup.into(),
            ),
            V::NoWorkgroupSize => "compute shader without a workgroup size".into(),
            // A binding's faults and the counts are reported above; vertex storage is not a
            // device limit here.
            _ => continue,
        });
    }
    Ok(())
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

/// The vertex buffers of `layout`, once every vertex input of `reflection` is checked to be
/// provided by an attribute of its size.
fn vertex_buffers<'l>(
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

#[cfg(test)]
mod tests {
    use kiln_archive::{NumericType, ScalarKind, VertexInput};

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
    fn vertex_inputs_must_be_in_the_vertex_layout() {
        const MESH: [wgpu::VertexAttribute; 3] =
            wgpu::vertex_attr_array![0 => Float32x3, 1 => Float32x3, 2 => Float32x2];
        const INSTANCE: [wgpu::VertexAttribute; 4] =
            wgpu::vertex_attr_array![3 => Float32x4, 4 => Float32x4, 5 => Float32x4, 6 => Float32x4];
        const BUFFERS: &[VertexBuffer] = &[
            VertexBuffer::new(32, wgpu::VertexStepMode::Vertex, &MESH),
            VertexBuffer::new(64, wgpu::VertexStepMode::Instance, &INSTANCE),
        ];
        const MESH_INSTANCED: VertexLayout = VertexLayout::from_static(BUFFERS);
        let input = |location, components| VertexInput {
            location,
            name: None,
            ty: NumericType { scalar: ScalarKind::Float, width: 4, components },
        };
        let mut vs = reflection(Stage::Vertex, vec![]);
        vs.vertex_inputs = vec![input(0, 3), input(2, 2), input(6, 4)];
        assert_eq!(vertex_buffers("p", &MESH_INSTANCED, &vs).unwrap().len(), 2);
        vs.vertex_inputs = vec![input(2, 4)];
        let e = vertex_buffers("Depth", &MESH_INSTANCED, &vs).unwrap_err().to_string();
        assert_eq!(
            e,
            "pipeline `Depth`: vertex input @location(2) is not provided by its vertex layout (locations [0, 1, 2, 3, 4, 5, 6])"
        );
        vs.vertex_inputs = vec![input(0, 3)];
        let e = vertex_buffers("Screen", &VertexLayout::NONE, &vs).unwrap_err().to_string();
        assert_eq!(
            e,
            "pipeline `Screen`: vertex input @location(0) is not provided by its vertex layout (locations [])"
        );
    }

    #[test]
    fn a_user_described_vertex_layout_is_a_key_like_a_static_one() {
        use std::hash::{BuildHasher, RandomState};
        const ATTRIBUTES: [wgpu::VertexAttribute; 2] = wgpu::vertex_attr_array![0 => Float32x2, 1 => Unorm8x4];
        const BUFFERS: &[VertexBuffer] = &[VertexBuffer::new(12, wgpu::VertexStepMode::Vertex, &ATTRIBUTES)];
        const STATIC: VertexLayout = VertexLayout::from_static(BUFFERS);
        let described = VertexLayout::from_wgpu(&[wgpu::VertexBufferLayout {
            array_stride: 12,
            step_mode: wgpu::VertexStepMode::Vertex,
            attributes: &ATTRIBUTES,
        }]);
        let hasher = RandomState::new();
        assert_eq!(STATIC, described);
        assert_eq!(hasher.hash_one(&STATIC), hasher.hash_one(&described));
        let other = VertexLayout::new(vec![VertexBuffer::new(16, wgpu::VertexStepMode::Vertex, &ATTRIBUTES)]);
        assert_ne!(STATIC, other);
        let mut vs = reflection(Stage::Vertex, vec![]);
        vs.vertex_inputs = vec![VertexInput {
            location: 1,
            name: None,
            ty: NumericType { scalar: ScalarKind::Float, width: 1, components: 4 },
        }];
        assert_eq!(vertex_buffers("p", &described, &vs).unwrap()[0].as_ref().unwrap().array_stride, 12);
    }

    #[test]
    fn reflection_fields_are_checked_against_the_device_limits() {
        let limits = wgpu::Limits::downlevel_defaults();
        let sampler = BindingKind::Sampler { comparison: false };
        let ok = reflection(Stage::Fragment, vec![binding(0, 0, "S", sampler.clone())]);
        check_limits(&ok, &limits).unwrap();
        let e = |r: &Reflection| check_limits(r, &limits).unwrap_err();
        assert_eq!(
            e(&reflection(Stage::Fragment, vec![binding(4_000_000_000, 0, "S", sampler.clone())])),
            "@group(4000000000) @binding(0): group 4000000000 is past the device's max_bind_groups (4)"
        );
        assert_eq!(
            e(&reflection(
                Stage::Fragment,
                vec![binding(0, 0, "S", sampler.clone()), binding(0, 0, "T", sampler.clone())]
            )),
            "@group(0) @binding(0) is listed twice"
        );
        let many: Vec<Binding> = (0..17).map(|i| binding(0, i, "S", sampler.clone())).collect();
        assert_eq!(
            e(&reflection(Stage::Fragment, many)),
            "samplers in the stage is 17, over the device's max_samplers_per_shader_stage (16)"
        );
        let ub = BindingKind::UniformBuffer { min_size: 1 << 40 };
        assert_eq!(
            e(&reflection(Stage::Fragment, vec![binding(0, 0, "U", ub)])),
            "@group(0) @binding(0): uniform buffer size is 1099511627776, over the device's max_uniform_buffer_binding_size (16384)"
        );
        let mut cs = reflection(Stage::Compute, vec![]);
        assert_eq!(e(&cs), "compute shader without a workgroup size");
        cs.workgroup_size = Some([0, 1, 1]);
        assert_eq!(e(&cs), "workgroup size 0x1x1 has a zero");
        cs.workgroup_size = Some([16, 16, 2]);
        assert_eq!(
            e(&cs),
            "workgroup invocations is 512, over the device's max_compute_invocations_per_workgroup (256)"
        );
        let mut fs = reflection(Stage::Fragment, vec![]);
        fs.color_outputs = vec![kiln_archive::ColorOutput {
            location: 9,
            ty: NumericType { scalar: ScalarKind::Float, width: 4, components: 4 },
        }];
        assert_eq!(e(&fs), "color output @location(9) is past the device's max_color_attachments (4)");
        // merge_bindings refuses a huge group even unchecked, instead of allocating for it.
        let huge = reflection(Stage::Fragment, vec![binding(4_000_000_000, 0, "S", sampler)]);
        assert!(merge_bindings("p", &[&huge]).is_err());
    }
}
