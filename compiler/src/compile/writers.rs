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
                Ok(words.iter().flat_map(|w| w.to_le_bytes()).collect())
            }
            Target::Msl => {
                let options = msl::Options { lang_version: MSL_VERSION, ..msl::Options::default() };
                let pipeline = msl::PipelineOptions {
                    entry_point: Some((naga_stage(stage), entry.to_string())),
                    ..msl::PipelineOptions::default()
                };
                msl::write_string(module, info, &options, &pipeline).map(|(s, _)| s.into_bytes()).map_err(|e| e.to_string())
            }
            Target::Glsl => {
                let options = glsl::Options {
                    version: glsl::Version::new_gles(GLSL_ES_VERSION),
                    ..glsl::Options::default()
                };
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
                let pipeline =
                    hlsl::PipelineOptions { entry_point: Some((naga_stage(stage), entry.to_string())) };
                let mut out = String::new();
                hlsl::Writer::new(&mut out, &options, &pipeline).write(module, info, None).map_err(|e| e.to_string())?;
                Ok(out.into_bytes())
            }
        }
    };
    match catch_unwind(AssertUnwindSafe(run)) {
        Ok(Ok(bytes)) => Ok(bytes),
        Ok(Err(message)) => Err(Error::new(ErrorKind::Writer(target), format!("the {target} writer failed: {message}"))),
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
