//! Headless device setup: an instance restricted to one backend, its first adapter, and a
//! device with the optional features the runtime uses (SPIR-V passthrough, timestamps).

use std::fmt;

/// The graphics API to render with.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Backend {
    Vulkan,
    Gl,
}

impl Backend {
    pub fn name(self) -> &'static str {
        match self {
            Backend::Vulkan => "vulkan",
            Backend::Gl => "gl",
        }
    }

    pub fn from_name(name: &str) -> Option<Backend> {
        match name {
            "vulkan" => Some(Backend::Vulkan),
            "gl" => Some(Backend::Gl),
            _ => None,
        }
    }

    fn wgpu(self) -> wgpu::Backends {
        match self {
            Backend::Vulkan => wgpu::Backends::VULKAN,
            Backend::Gl => wgpu::Backends::GL,
        }
    }
}

impl fmt::Display for Backend {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// How shader modules are made from the archive.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default)]
pub enum ModuleSource {
    /// SPIR-V passthrough where the device allows it (Vulkan with `PASSTHROUGH_SHADERS`),
    /// WGSL otherwise.
    #[default]
    Auto,
    /// Always WGSL (wgpu parses and validates it with its own naga).
    Wgsl,
}

#[derive(Clone, Debug)]
pub struct GpuOptions {
    pub backend: Backend,
    pub module_source: ModuleSource,
    /// Ask for timestamp queries where the adapter has them.
    pub timestamps: bool,
}

impl Default for GpuOptions {
    fn default() -> Self {
        GpuOptions { backend: Backend::Vulkan, module_source: ModuleSource::Auto, timestamps: true }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    #[error(
        "no {backend} adapter found ({detail}); on a machine without a GPU install Mesa's software drivers, \
         Debian package `mesa-vulkan-drivers` (lavapipe for Vulkan, llvmpipe for GL): apt-get install mesa-vulkan-drivers"
    )]
    NoAdapter { backend: Backend, detail: String },
    #[error("cannot create a {backend} device on {adapter}: {source}")]
    Device { backend: Backend, adapter: String, source: wgpu::RequestDeviceError },
}

/// A device ready to render offscreen.
pub struct Gpu {
    pub instance: wgpu::Instance,
    pub adapter: wgpu::Adapter,
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub backend: Backend,
    pub info: wgpu::AdapterInfo,
    /// Modules come from SPIR-V passthrough (else WGSL).
    pub spirv_passthrough: bool,
    /// Timestamps can be written between passes (`TIMESTAMP_QUERY_INSIDE_ENCODERS`).
    pub timestamps: bool,
    /// Depth textures can be copied to buffers (not on GL).
    pub depth_copies: bool,
}

impl fmt::Debug for Gpu {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Gpu")
            .field("backend", &self.backend)
            .field("adapter", &self.info.name)
            .field("spirv_passthrough", &self.spirv_passthrough)
            .field("timestamps", &self.timestamps)
            .finish()
    }
}

impl Gpu {
    pub fn new(options: &GpuOptions) -> Result<Gpu, GpuError> {
        pollster::block_on(Gpu::new_async(options))
    }

    async fn new_async(options: &GpuOptions) -> Result<Gpu, GpuError> {
        let backend = options.backend;
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
        desc.backends = backend.wgpu();
        let instance = wgpu::Instance::new(desc);
        let adapter = match instance
            .request_adapter(&wgpu::RequestAdapterOptions {
                power_preference: wgpu::PowerPreference::HighPerformance,
                force_fallback_adapter: false,
                compatible_surface: None,
                apply_limit_buckets: false,
            })
            .await
        {
            Ok(a) => a,
            Err(e) => {
                let all = instance.enumerate_adapters(backend.wgpu()).await;
                let detail = if all.is_empty() {
                    format!("{e}; the {backend} backend lists no adapters")
                } else {
                    let names: Vec<String> = all.iter().map(|a| a.get_info().name).collect();
                    format!("{e}; adapters seen: {}", names.join(", "))
                };
                return Err(GpuError::NoAdapter { backend, detail });
            }
        };
        let info = adapter.get_info();
        let available = adapter.features();
        let mut features = wgpu::Features::empty();
        let passthrough = backend == Backend::Vulkan
            && options.module_source == ModuleSource::Auto
            && available.contains(wgpu::Features::PASSTHROUGH_SHADERS);
        if passthrough {
            features |= wgpu::Features::PASSTHROUGH_SHADERS;
        }
        let timestamp_features = wgpu::Features::TIMESTAMP_QUERY | wgpu::Features::TIMESTAMP_QUERY_INSIDE_ENCODERS;
        let timestamps = options.timestamps && available.contains(timestamp_features);
        if timestamps {
            features |= timestamp_features;
        }
        // The desktop frame's scene depth with stencil, copyable for --dump-passes.
        features |= available & wgpu::Features::DEPTH32FLOAT_STENCIL8;
        let (device, queue) = adapter
            .request_device(&wgpu::DeviceDescriptor {
                label: Some("kiln-runtime device"),
                required_features: features,
                required_limits: adapter.limits(),
                experimental_features: wgpu::ExperimentalFeatures::disabled(),
                memory_hints: wgpu::MemoryHints::Performance,
                trace: wgpu::Trace::Off,
            })
            .await
            .map_err(|source| GpuError::Device { backend, adapter: info.name.clone(), source })?;
        // Errors outside an error scope are reported, not panicked on: every frame and
        // pipeline creation runs in a scope that turns them into results.
        device.on_uncaptured_error(std::sync::Arc::new(|e: wgpu::Error| {
            eprintln!("wgpu error: {}", crate::pipelines::error_chain(&e));
        }));
        let depth_copies =
            adapter.get_downlevel_capabilities().flags.contains(wgpu::DownlevelFlags::DEPTH_TEXTURE_AND_BUFFER_COPIES);
        Ok(Gpu {
            instance,
            adapter,
            device,
            queue,
            backend,
            info,
            spirv_passthrough: passthrough,
            timestamps,
            depth_copies,
        })
    }

    /// Waits until the GPU has finished everything submitted.
    pub fn wait(&self) {
        let _ = self.device.poll(wgpu::PollType::wait_indefinitely());
    }
}
