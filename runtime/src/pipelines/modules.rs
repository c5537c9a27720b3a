//! Shader modules from an archive's artifacts (SPIR-V passthrough or WGSL) and the wgpu
//! error scopes every creation runs under.

use std::borrow::Cow;

use kiln_archive::{Reflection, Target};

use super::PipelineError;
use crate::gpu::error_chain;

/// A label GL accepts: shorter than `GL_MAX_LABEL_LENGTH`, which counts the nul (longer
/// labels are a GL error). Pipelines are labelled with their permutations' names,
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
/// words must have passed `SpirvModule::parse` and `SpirvModule::check` against
/// `reflection`, and come from a trusted archive (`ShaderArchive::trusted`); their binding
/// numbers must be the layout's Vulkan ones (`SpirvModule::remap_bindings`).
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
    /// Pushes a validation and an internal error scope on `device`.
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

pub(super) fn check_scope(scope: ErrorScopes, what: impl FnOnce() -> String) -> Result<(), PipelineError> {
    match scope.pop() {
        None => Ok(()),
        Some(message) => Err(PipelineError::Wgpu { what: what(), message }),
    }
}
