//! Validation messages of the graphics API, caught for tests.
//!
//! With [`crate::GpuOptions::validation`] the device is created with the Khronos validation
//! layer on Vulkan (Debian package `vulkan-validationlayers`) or GL debug output on GL. wgpu
//! hands the layer's and the GL driver's messages to the `log` crate (targets
//! `wgpu_hal::vulkan::*` and `wgpu_hal::gles::*`, errors and warnings at those levels); the
//! logger here records them, so that a test can fail on any, with the message in the
//! failure. It is installed once per process, and only if no other logger is.
//!
//! Nothing here runs unless called: [`enable`] (or [`CheckedGpu::new`], which calls it) is
//! what installs the logger and adds the layer to the process's environment.

use std::path::{Path, PathBuf};
use std::sync::Mutex;

static MESSAGES: Mutex<Vec<String>> = Mutex::new(Vec::new());

struct Recorder;

impl log::Log for Recorder {
    fn enabled(&self, metadata: &log::Metadata<'_>) -> bool {
        metadata.level() <= log::Level::Warn && metadata.target().starts_with("wgpu_hal::")
    }

    fn log(&self, record: &log::Record<'_>) {
        if !self.enabled(record.metadata()) {
            return;
        }
        let message = format!("[{} {}] {}", record.level(), record.target(), record.args());
        // GL: only the driver's debug output (wgpu prefixes it `GLES: `); EGL's display probing
        // reports through the same target without being about the API's use.
        let gl_other =
            record.target().starts_with("wgpu_hal::gles") && !record.args().to_string().starts_with("GLES: ");
        if gl_other || known_not_invalid_usage(&message) {
            return;
        }
        eprintln!("{message}");
        MESSAGES.lock().unwrap_or_else(|e| e.into_inner()).push(message);
    }

    fn flush(&self) {}
}

static RECORDER: Recorder = Recorder;

/// Messages that say nothing about invalid usage by the runtime:
/// - performance hints (a vertex attribute or stage output nothing reads);
/// - the loader's note that `VK_INSTANCE_LAYERS` added the layer, and the object lists
///   wgpu prints after each message (the message itself is recorded);
/// - `Invalid source language operand: 10` on modules wgpu made from WGSL: with
///   `InstanceFlags::DEBUG` (which the debug-utils messenger needs) wgpu writes `OpSource WGSL`,
///   language 10 of SPIR-V's registry, which the SPIR-V tools in Debian 12's layer predate.
fn known_not_invalid_usage(message: &str) -> bool {
    message.contains("Performance Warning")
        || message.contains("SPIR-V module not valid: Invalid source language operand: 10")
        || message.contains("[Loader Message")
        || message.contains("env var 'VK_INSTANCE_LAYERS' defined")
        || message.trim_start_matches(|c| c != ']').starts_with("] \tobjects:")
}

/// Installs the recording logger; `false` where another logger was installed first (then
/// nothing is recorded).
pub fn install() -> bool {
    static INSTALLED: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *INSTALLED.get_or_init(|| {
        let ok = log::set_logger(&RECORDER).is_ok();
        if ok {
            log::set_max_level(log::LevelFilter::Warn);
        }
        ok
    })
}

/// Enables the Khronos validation layer for every Vulkan instance this process creates from
/// now on, as `VK_INSTANCE_LAYERS=VK_LAYER_KHRONOS_validation` does (added to the variable's
/// layers, once).
pub fn enable_layer_for_process() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        const LAYER: &str = "VK_LAYER_KHRONOS_validation";
        let current = std::env::var("VK_INSTANCE_LAYERS").unwrap_or_default();
        if !current.split(':').any(|l| l == LAYER) {
            let value = if current.is_empty() { LAYER.to_string() } else { format!("{current}:{LAYER}") };
            std::env::set_var("VK_INSTANCE_LAYERS", value);
        }
    });
}

/// Everything a device created with [`crate::GpuOptions::validation`] needs for its messages to
/// be recorded, for this process: the recording logger ([`install`]) and, on Vulkan, the
/// Khronos layer ([`enable_layer_for_process`], after checking that it is installed).
pub fn enable(backend: crate::Backend) -> Result<(), crate::GpuError> {
    if !install() {
        return Err(crate::GpuError::ValidationLogger);
    }
    if backend == crate::Backend::Vulkan {
        if khronos_layer_manifest().is_none() {
            return Err(crate::GpuError::NoValidationLayer);
        }
        enable_layer_for_process();
    }
    Ok(())
}

/// The messages recorded since the last call, oldest first.
pub fn take() -> Vec<String> {
    std::mem::take(&mut *MESSAGES.lock().unwrap_or_else(|e| e.into_inner()))
}

/// The manifest of the Khronos validation layer, searched where the Vulkan loader looks for
/// explicit layers (`VK_LAYER_PATH`, `VK_ADD_LAYER_PATH`, then `vulkan/explicit_layer.d` under
/// the XDG config and data folders, `/etc` and `/usr/share`).
pub fn khronos_layer_manifest() -> Option<PathBuf> {
    let mut dirs: Vec<PathBuf> = Vec::new();
    for var in ["VK_LAYER_PATH", "VK_ADD_LAYER_PATH"] {
        if let Some(v) = std::env::var_os(var) {
            dirs.extend(std::env::split_paths(&v));
        }
    }
    let xdg = |var: &str, default: &str| {
        let v = std::env::var(var).ok().filter(|v| !v.is_empty()).unwrap_or_else(|| default.to_string());
        v.split(':').map(|d| Path::new(d).join("vulkan/explicit_layer.d")).collect::<Vec<_>>()
    };
    dirs.extend(xdg("XDG_CONFIG_DIRS", "/etc/xdg"));
    dirs.push(PathBuf::from("/etc/vulkan/explicit_layer.d"));
    dirs.extend(xdg("XDG_DATA_DIRS", "/usr/local/share:/usr/share"));
    if let Some(home) = std::env::var_os("HOME") {
        dirs.push(Path::new(&home).join(".local/share/vulkan/explicit_layer.d"));
    }
    dirs.into_iter().find_map(|d| {
        let entries = std::fs::read_dir(&d).ok()?;
        entries.flatten().map(|e| e.path()).find(|p| {
            p.extension().is_some_and(|x| x == "json")
                && std::fs::read_to_string(p).is_ok_and(|t| t.contains("\"VK_LAYER_KHRONOS_validation\""))
        })
    })
}

/// A device created with validation on ([`crate::GpuOptions::validation`]) that fails the
/// test holding it when it goes out of scope if any validation message was recorded in the
/// process meanwhile: it panics with every message (unless the thread is already panicking).
/// For render tests: any validation message is a failure, never a log line.
pub struct CheckedGpu {
    gpu: crate::Gpu,
}

impl CheckedGpu {
    /// A device with validation on ([`enable`]d for its backend); the options' `validation`
    /// is ignored.
    pub fn new(options: &crate::GpuOptions) -> Result<CheckedGpu, crate::GpuError> {
        enable(options.backend)?;
        let options = crate::GpuOptions { validation: true, ..options.clone() };
        Ok(CheckedGpu { gpu: crate::Gpu::new(&options)? })
    }

    /// Fails now if any validation message was recorded.
    pub fn check(&self) {
        self.gpu.wait();
        let messages = take();
        if !messages.is_empty() && !std::thread::panicking() {
            panic!("{} validation message(s) on {}:\n{}", messages.len(), self.gpu.info.name, messages.join("\n"));
        }
    }
}

impl std::ops::Deref for CheckedGpu {
    type Target = crate::Gpu;

    fn deref(&self) -> &crate::Gpu {
        &self.gpu
    }
}

impl Drop for CheckedGpu {
    fn drop(&mut self) {
        self.check();
    }
}
