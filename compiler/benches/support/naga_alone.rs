//! Naga alone on a set's distinct sources, as a tool calling naga directly would compile
//! them: the baseline Kiln's builds are measured against. Shared by the `compile` and
//! `scale` benches (`#[path = "support/naga_alone.rs"] mod naga_alone;`).

#![allow(dead_code)]

use std::collections::HashMap;

use kiln::archive::{Stage, Target};
use kiln::permute;
use kiln::preprocess::{self, SourceCache};
use naga::back::{glsl, hlsl, msl, spv, wgsl};

/// One distinct preprocessed source and what its level asks of naga.
pub struct Source {
    pub text: String,
    pub entry: String,
    pub stage: Stage,
    pub targets: Vec<Target>,
    pub gles: bool,
}

/// naga's name for a stage.
pub fn naga_stage(s: Stage) -> naga::ShaderStage {
    match s {
        Stage::Vertex => naga::ShaderStage::Vertex,
        Stage::Fragment => naga::ShaderStage::Fragment,
        Stage::Compute => naga::ShaderStage::Compute,
    }
}

/// parse, validate, every writer: what a tool calling naga directly does. With
/// `entry_only`, the module keeps only the entry point before validation, as Kiln does.
pub fn naga_alone(s: &Source, entry_only: bool) -> usize {
    naga_outputs(s, entry_only).iter().map(|(_, bytes)| bytes.len()).sum()
}

/// [`naga_alone`]'s outputs, by target (SPIR-V as its little-endian bytes).
pub fn naga_outputs(s: &Source, entry_only: bool) -> Vec<(Target, Vec<u8>)> {
    let mut module = naga::front::wgsl::parse_str(&s.text).expect("parses");
    if entry_only {
        module.entry_points.retain(|e| e.name == s.entry);
    }
    let caps = if s.gles {
        naga::valid::Capabilities::empty()
    } else {
        naga::valid::Capabilities::MULTISAMPLED_SHADING | naga::valid::Capabilities::CUBE_ARRAY_TEXTURES
    };
    let info =
        naga::valid::Validator::new(naga::valid::ValidationFlags::all(), caps).validate(&module).expect("validates");
    let stage = naga_stage(s.stage);
    s.targets.iter().map(|&t| (t, write_target(t, &module, &info, stage, &s.entry))).collect()
}

/// One writer's output.
fn write_target(
    t: Target,
    module: &naga::Module,
    info: &naga::valid::ModuleInfo,
    stage: naga::ShaderStage,
    entry: &str,
) -> Vec<u8> {
    match t {
        Target::Wgsl => wgsl::write_string(module, info, wgsl::WriterFlags::empty()).unwrap().into_bytes(),
        Target::Spirv => {
            let o = spv::Options {
                lang_version: (1, 0),
                flags: spv::WriterFlags::LABEL_VARYINGS | spv::WriterFlags::FORCE_POINT_SIZE,
                ..Default::default()
            };
            let p = spv::PipelineOptions { shader_stage: stage, entry_point: entry.to_string() };
            spv::write_vec(module, info, &o, Some(&p)).unwrap().iter().flat_map(|w| w.to_le_bytes()).collect()
        }
        Target::Msl => {
            let o = msl::Options { lang_version: (2, 4), ..Default::default() };
            let p = msl::PipelineOptions { entry_point: Some((stage, entry.to_string())), ..Default::default() };
            msl::write_string(module, info, &o, &p).unwrap().0.into_bytes()
        }
        Target::Glsl => {
            let o = glsl::Options { version: glsl::Version::new_gles(310), ..Default::default() };
            let p = glsl::PipelineOptions { shader_stage: stage, entry_point: entry.to_string(), multiview: None };
            let mut out = String::new();
            glsl::Writer::new(&mut out, module, info, &o, &p, Default::default()).unwrap().write().unwrap();
            out.into_bytes()
        }
        Target::Hlsl => {
            let o = hlsl::Options { shader_model: hlsl::ShaderModel::V5_1, ..Default::default() };
            let p = hlsl::PipelineOptions { entry_point: Some((stage, entry.to_string())) };
            let mut out = String::new();
            hlsl::Writer::new(&mut out, &o, &p).write(module, info, None).unwrap();
            out.into_bytes()
        }
    }
}

/// The distinct sources of a set, preprocessed by Kiln (untimed), as Kiln's dedup sees them,
/// and the number of kept permutations.
pub fn distinct_sources(config: &permute::Config) -> (Vec<Source>, usize) {
    let sources = SourceCache::new(config.dir.clone());
    let mut distinct: HashMap<(blake3::Hash, String, Stage, String), Source> = HashMap::new();
    let mut kept = 0;
    for p in config.permutations().filter(|p| p.is_kept()) {
        kept += 1;
        let out = preprocess::preprocess_file(&p.shader.source_path, &p.preprocess_options(config), &sources)
            .unwrap_or_else(|e| panic!("{}: {}", p.name(), e));
        let key = (out.token_hash(), p.shader.entry.clone(), p.shader.stage, p.level.name.clone());
        distinct.entry(key).or_insert_with(|| Source {
            text: out.text,
            entry: p.shader.entry.clone(),
            stage: p.shader.stage,
            targets: p.level.targets.clone(),
            gles: p.level.limits == permute::Limits::Downlevel,
        });
    }
    (distinct.into_values().collect(), kept)
}

/// A pool of `jobs` workers like `kiln build`'s.
pub fn pool(jobs: usize) -> rayon::ThreadPool {
    // The same workers as `kiln build`'s (the preprocessor's stack, so it runs in place).
    rayon::ThreadPoolBuilder::new()
        .num_threads(jobs)
        .stack_size(preprocess::STACK_BYTES)
        .start_handler(|_| preprocess::big_stack_thread())
        .build()
        .unwrap()
}
