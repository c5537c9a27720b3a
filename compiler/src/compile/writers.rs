//! One naga writer per target, with options that work on real shaders, each run under
//! `catch_unwind`: a writer that panics becomes an error of the permutation.
//!
//! - WGSL: naga's WGSL writer (the module holds only the entry point).
//! - SPIR-V 1.0 with the flags wgpu's Vulkan backend uses (no coordinate-space flip: wgpu
//!   flips the viewport), so the runtime can pass it through unchanged.
//! - MSL 2.4 (naga's default 1.0 rejects common shaders).
//! - GLSL ES 3.10, one output for the entry point's stage.
//! - HLSL shader model 5.1.

use std::panic::{catch_unwind, AssertUnwindSafe};

use naga::back::{glsl, hlsl, msl, spv, wgsl};

use super::{naga_stage, Error, ErrorKind};
use crate::archive::{Stage, Target};

pub const MSL_VERSION: (u8, u8) = (2, 4);
pub const SPIRV_VERSION: (u8, u8) = (1, 0);
pub const GLSL_ES_VERSION: u16 = 310;

pub fn write(
    target: Target,
    module: &naga::Module,
    info: &naga::valid::ModuleInfo,
    entry: &str,
    stage: Stage,
) -> Result<Vec<u8>, Error> {
    let run = || -> Result<Vec<u8>, String> {
        match target {
            Target::Wgsl => wgsl::write_string(module, info, wgsl::WriterFlags::empty())
                .map(String::into_bytes)
                .map_err(|e| e.to_string()),
            Target::Spirv => {
                let options = spv::Options {
                    lang_version: SPIRV_VERSION,
                    flags: spv::WriterFlags::LABEL_VARYINGS | spv::WriterFlags::FORCE_POINT_SIZE,
                    ..spv::Options::default()
                };
                let pipeline = spv::PipelineOptions { shader_stage: naga_stage(stage), entry_point: entry.to_string() };
                let words = spv::write_vec(module, info, &options, Some(&pipeline)).map_err(|e| e.to_string())?;
                Ok(words_to_bytes(&words))
            }
            Target::Msl => {
                let options = msl::Options { lang_version: MSL_VERSION, ..msl::Options::default() };
                let pipeline = msl::PipelineOptions {
                    entry_point: Some((naga_stage(stage), entry.to_string())),
                    ..msl::PipelineOptions::default()
                };
                msl::write_string(module, info, &options, &pipeline)
                    .map(|(s, _)| s.into_bytes())
                    .map_err(|e| e.to_string())
            }
            Target::Glsl => {
                let options =
                    glsl::Options { version: glsl::Version::new_gles(GLSL_ES_VERSION), ..glsl::Options::default() };
                let pipeline = glsl::PipelineOptions {
                    shader_stage: naga_stage(stage),
                    entry_point: entry.to_string(),
                    multiview: None,
                };
                let mut out = String::new();
                let mut w = glsl::Writer::new(&mut out, module, info, &options, &pipeline, Default::default())
                    .map_err(|e| e.to_string())?;
                w.write().map_err(|e| e.to_string())?;
                Ok(out.into_bytes())
            }
            Target::Hlsl => {
                let options = hlsl::Options { shader_model: hlsl::ShaderModel::V5_1, ..hlsl::Options::default() };
                let pipeline = hlsl::PipelineOptions { entry_point: Some((naga_stage(stage), entry.to_string())) };
                let mut out = String::new();
                hlsl::Writer::new(&mut out, &options, &pipeline)
                    .write(module, info, None)
                    .map_err(|e| e.to_string())?;
                Ok(out.into_bytes())
            }
        }
    };
    guarded(target, run)
}

/// SPIR-V words as little-endian bytes, in one allocation of the final size (a `flat_map`
/// over the words showed up in a cold build's profile).
fn words_to_bytes(words: &[u32]) -> Vec<u8> {
    let mut bytes = Vec::with_capacity(words.len() * 4);
    for w in words {
        bytes.extend_from_slice(&w.to_le_bytes());
    }
    bytes
}

thread_local! {
    /// Set while a writer runs: its panics are reported as errors, not printed.
    static IN_WRITER: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Installs (once per process) a panic hook that stays quiet for panics inside a writer,
/// which [`guarded`] turns into errors, and defers to the previous hook for all others.
fn quiet_writer_panics() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if !IN_WRITER.with(|w| w.get()) {
                previous(info);
            }
        }));
    });
}

/// Runs a writer, turning an `Err` or a panic into the permutation's [`Error`].
pub(crate) fn guarded(target: Target, run: impl FnOnce() -> Result<Vec<u8>, String>) -> Result<Vec<u8>, Error> {
    quiet_writer_panics();
    IN_WRITER.with(|w| w.set(true));
    let result = catch_unwind(AssertUnwindSafe(run));
    IN_WRITER.with(|w| w.set(false));
    match result {
        Ok(Ok(bytes)) => Ok(bytes),
        Ok(Err(message)) => {
            Err(Error::new(ErrorKind::Writer(target), format!("the {target} writer failed: {message}")))
        }
        Err(panic) => {
            let what = panic
                .downcast_ref::<String>()
                .map(String::as_str)
                .or_else(|| panic.downcast_ref::<&str>().copied())
                .unwrap_or("no message");
            let mut e = Error::new(ErrorKind::Writer(target), format!("the {target} writer panicked: {what}"));
            e.notes.push(format!("naga {} cannot write this shader as {target}", super::NAGA_VERSION));
            Err(e)
        }
    }
}
