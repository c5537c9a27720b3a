//! wgpu's driver pipeline cache, loaded from and saved to one file per adapter and driver.

use std::sync::Arc;

use super::modules::ErrorScopes;
use super::PipelineCache;
use crate::gpu::Gpu;
use crate::shaders::ShaderArchive;

/// The largest pipeline cache file read back: far more than a driver's cache of every
/// pipeline of the bundled renderer (a few MB).
const MAX_DISK_CACHE: u64 = 256 << 20;

/// wgpu's driver-level pipeline cache, loaded from and saved to one file per adapter and
/// driver.
pub(super) struct DiskCache {
    pub(super) cache: wgpu::PipelineCache,
    pub(super) path: std::path::PathBuf,
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
}
