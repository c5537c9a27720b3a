//! Headless device setup: an instance restricted to one backend, its first adapter, and a
//! device with the optional features the runtime uses (SPIR-V passthrough, timestamps).

use std::fmt;

/// The graphics API to render with.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Backend {
    /// Vulkan (lavapipe on machines without a GPU).
    Vulkan,
    /// OpenGL ES through EGL (llvmpipe on machines without a GPU).
    Gl,
}

impl Backend {
    /// The backend's name, as `--backend` takes it.
    pub fn name(self) -> &'static str {
        match self {
            Backend::Vulkan => "vulkan",
            Backend::Gl => "gl",
        }
    }

    /// The backend named `name`, if any.
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

/// How to create a [`Gpu`].
#[derive(Clone, Debug)]
pub struct GpuOptions {
    /// The graphics API.
    pub backend: Backend,
    /// Where shader modules come from.
    pub module_source: ModuleSource,
    /// Ask for timestamp queries where the adapter has them.
    pub timestamps: bool,
    /// Create the device with the API's validation on: the instance flags that hand the
    /// Khronos validation layer's messages (Vulkan) or the driver's debug output (GL) to the
    /// `log` crate. Nothing global changes here: the layer itself and the logger that records
    /// the messages are the caller's to enable (`validation::enable`, with the `validation`
    /// feature).
    pub validation: bool,
}

impl Default for GpuOptions {
    fn default() -> Self {
        GpuOptions { backend: Backend::Vulkan, module_source: ModuleSource::Auto, timestamps: true, validation: false }
    }
}

/// Why a device could not be created.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// No adapter of the backend.
    #[error(
        "no {backend} adapter found ({detail}); on a machine without a GPU install Mesa's software drivers, \
         Debian package `mesa-vulkan-drivers` (lavapipe for Vulkan, llvmpipe for GL): apt-get install mesa-vulkan-drivers"
    )]
    NoAdapter {
        /// The backend asked for.
        backend: Backend,
        /// wgpu's error and the adapters seen.
        detail: String,
    },
    /// The Khronos validation layer is not installed.
    #[error(
        "validation was asked for, but the Khronos validation layer (VK_LAYER_KHRONOS_validation) is not \
         installed: Debian package `vulkan-validationlayers` (apt-get install vulkan-validationlayers)"
    )]
    NoValidationLayer,
    /// Another `log` logger is installed.
    #[error("validation was asked for, but another `log` logger is installed, so its messages cannot be recorded")]
    ValidationLogger,
    /// The adapter refused the device.
    #[error("cannot create a {backend} device on {adapter}: {source}")]
    Device {
        /// The backend.
        backend: Backend,
        /// The adapter's name.
        adapter: String,
        /// wgpu's error.
        source: wgpu::RequestDeviceError,
    },
}

/// Keeps Mesa's implicit `VK_LAYER_MESA_device_select` from probing for a Wayland display
/// where none can exist.
///
/// wgpu enables `VK_KHR_wayland_surface` on every Vulkan instance where the loader has it, and
/// the layer then calls `wl_display_connect` while listing devices; with no
/// `XDG_RUNTIME_DIR` that prints `error: XDG_RUNTIME_DIR is invalid or not set in the
/// environment.` (twice per instance) although nothing is wrong for a headless renderer. Where
/// `XDG_RUNTIME_DIR` is unset (so no Wayland display is reachable) and the user has not chosen
/// a device with `MESA_VK_DEVICE_SELECT` nor said anything through `NODEVICE_SELECT`, this
/// sets the layer's own switch `NODEVICE_SELECT=1` for the process, once, before the first
/// instance: wgpu picks the adapter itself. Any real error still prints.
fn skip_device_select_display_probe() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let unset = |name: &str| std::env::var_os(name).is_none_or(|v| v.is_empty());
        if unset("XDG_RUNTIME_DIR") && unset("MESA_VK_DEVICE_SELECT") && std::env::var_os("NODEVICE_SELECT").is_none() {
            std::env::set_var("NODEVICE_SELECT", "1");
        }
    });
}

/// A device ready to render offscreen.
pub struct Gpu {
    /// The wgpu instance.
    pub instance: wgpu::Instance,
    /// The adapter the device is on.
    pub adapter: wgpu::Adapter,
    /// The device.
    pub device: wgpu::Device,
    /// Its queue.
    pub queue: wgpu::Queue,
    /// The backend.
    pub backend: Backend,
    /// The adapter's name, driver and kind.
    pub info: wgpu::AdapterInfo,
    /// Modules come from SPIR-V passthrough (else WGSL).
    pub spirv_passthrough: bool,
    /// Timestamps can be written between passes (`TIMESTAMP_QUERY_INSIDE_ENCODERS`).
    pub timestamps: bool,
    /// Depth textures can be copied to buffers (not on GL).
    pub depth_copies: bool,
    /// Why the device was lost, once it is.
    pub lost: DeviceLost,
}

/// Why a device was lost, shared with whatever renders on it.
#[derive(Clone, Debug, Default)]
pub struct DeviceLost(std::sync::Arc<std::sync::Mutex<Option<String>>>);

impl DeviceLost {
    /// The reason, once the device is lost.
    pub fn reason(&self) -> Option<String> {
        self.0.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }
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
    /// Creates an instance, an adapter and a device with `options`, blocking.
    pub fn new(options: &GpuOptions) -> Result<Gpu, GpuError> {
        pollster::block_on(Gpu::new_async(options))
    }

    async fn new_async(options: &GpuOptions) -> Result<Gpu, GpuError> {
        let backend = options.backend;
        let instance = instance(options);
        let adapter = adapter(&instance, backend).await?;
        let info = adapter.get_info();
        let Features { features, passthrough, timestamps } = Features::of(&adapter, options);
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
        let lost = watch(&device);
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
            lost,
        })
    }

    /// The file name of this adapter's and driver's pipeline cache, where the device has one
    /// (`Features::PIPELINE_CACHE`: Vulkan).
    pub fn pipeline_cache_key(&self) -> Option<String> {
        pipeline_cache_key(&self.info, &self.device)
    }

    /// Waits until the GPU has finished everything submitted.
    pub fn wait(&self) {
        let _ = self.device.poll(wgpu::PollType::wait_indefinitely());
    }
}

/// An instance of `options.backend`, with the debug flags validation wants.
fn instance(options: &GpuOptions) -> wgpu::Instance {
    let backend = options.backend;
    if backend == Backend::Vulkan {
        skip_device_select_display_probe();
    }
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = backend.wgpu();
    if options.validation {
        // Vulkan: the layer comes from `VK_INSTANCE_LAYERS` (`validation::enable`; its core
        // checks: wgpu's own VALIDATION flag adds synchronization validation, which flags
        // wgpu's store of read-only depth attachments), and DEBUG is for the debug-utils
        // messenger that hands its messages to wgpu's log. GL: VALIDATION turns debug
        // output on.
        if backend == Backend::Gl {
            desc.flags |= wgpu::InstanceFlags::VALIDATION;
        }
        desc.flags |= wgpu::InstanceFlags::DEBUG;
    }
    wgpu::Instance::new(desc)
}

/// The high-performance adapter of `backend`; where there is none, the error names the
/// adapters the backend lists (or says it lists none).
async fn adapter(instance: &wgpu::Instance, backend: Backend) -> Result<wgpu::Adapter, GpuError> {
    let request = instance.request_adapter(&wgpu::RequestAdapterOptions {
        power_preference: wgpu::PowerPreference::HighPerformance,
        force_fallback_adapter: false,
        compatible_surface: None,
        apply_limit_buckets: false,
    });
    match request.await {
        Ok(a) => Ok(a),
        Err(e) => {
            let all = instance.enumerate_adapters(backend.wgpu()).await;
            let detail = if all.is_empty() {
                format!("{e}; the {backend} backend lists no adapters")
            } else {
                let names: Vec<String> = all.iter().map(|a| a.get_info().name).collect();
                format!("{e}; adapters seen: {}", names.join(", "))
            };
            Err(GpuError::NoAdapter { backend, detail })
        }
    }
}

/// The optional features the device is asked for, of those the adapter has.
struct Features {
    features: wgpu::Features,
    /// SPIR-V passthrough (Vulkan, where the options leave the module source to the runtime).
    passthrough: bool,
    /// Timestamps between passes, where the options ask for them.
    timestamps: bool,
}

impl Features {
    fn of(adapter: &wgpu::Adapter, options: &GpuOptions) -> Features {
        let available = adapter.features();
        let mut features = wgpu::Features::empty();
        let passthrough = options.backend == Backend::Vulkan
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
        // The driver's pipeline cache, persisted by `PipelineCache::with_disk_cache`.
        features |= available & wgpu::Features::PIPELINE_CACHE;
        Features { features, passthrough, timestamps }
    }
}

/// Reports `device`'s uncaptured errors and records why it is lost, once it is.
fn watch(device: &wgpu::Device) -> DeviceLost {
    // Errors outside an error scope are reported, not panicked on: every frame and
    // pipeline creation runs in a scope that turns them into results.
    device.on_uncaptured_error(std::sync::Arc::new(|e: wgpu::Error| {
        eprintln!("wgpu error: {}", error_chain(&e));
    }));
    // A lost device (a driver reset, or one that gave up) is an error of the next frame.
    let lost = DeviceLost::default();
    let record = lost.clone();
    device.set_device_lost_callback(move |reason, message| {
        *record.0.lock().unwrap_or_else(|e| e.into_inner()) = Some(format!("{reason:?}: {message}"));
    });
    lost
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

/// The file name of the pipeline cache of `device` on the adapter `info` describes, where the
/// device has one (`Features::PIPELINE_CACHE`: Vulkan): one per adapter and driver.
pub fn pipeline_cache_key(info: &wgpu::AdapterInfo, device: &wgpu::Device) -> Option<String> {
    if !device.features().contains(wgpu::Features::PIPELINE_CACHE) {
        return None;
    }
    wgpu::util::pipeline_cache_key(info)
        .map(|k| format!("{k}_{}.kpc", info.driver_info.replace(|c: char| !c.is_ascii_alphanumeric(), "_")))
}

/// `create_buffer_init` that never panics: `wgpu::util::DeviceExt::create_buffer_init`
/// panics when the buffer cannot be mapped at creation (a lost device, memory exhausted).
/// Here such a buffer is left unfilled: the device has reported the error (to the error
/// scope around the setup, or as lost), which the caller turns into its own error before
/// the buffer is ever used ([`DeviceLost::reason`]). Import it instead of `DeviceExt`.
pub trait BufferInit {
    /// Creates the buffer of `descriptor` with its contents, or unfilled where it cannot be
    /// mapped (the device has reported why).
    fn create_buffer_init(&self, descriptor: &wgpu::util::BufferInitDescriptor<'_>) -> wgpu::Buffer;
}

impl BufferInit for wgpu::Device {
    fn create_buffer_init(&self, descriptor: &wgpu::util::BufferInitDescriptor<'_>) -> wgpu::Buffer {
        let unpadded = descriptor.contents.len() as wgpu::BufferAddress;
        // As wgpu's: a size that is a positive multiple of COPY_BUFFER_ALIGNMENT.
        let align = wgpu::COPY_BUFFER_ALIGNMENT - 1;
        let padded = ((unpadded + align) & !align).max(wgpu::COPY_BUFFER_ALIGNMENT);
        let empty = descriptor.contents.is_empty();
        let buffer = self.create_buffer(&wgpu::BufferDescriptor {
            label: descriptor.label,
            size: if empty { 0 } else { padded },
            usage: descriptor.usage,
            mapped_at_creation: !empty,
        });
        if !empty {
            if let Ok(mut range) = buffer.get_mapped_range_mut(..) {
                range.slice(..unpadded as usize).copy_from_slice(descriptor.contents);
            }
            buffer.unmap();
        }
        buffer
    }
}
