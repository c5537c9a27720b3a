//! The end-to-end tests across the compiler and the runtime, one binary (one link of wgpu and
//! naga): a module per area, over the support modules they share. Two suites run as binaries
//! of their own: `preprocess_linear` counts every allocation of its process, and
//! `remote_cache` sets the remote cache's environment variables, which every build reads.

mod build_support;
mod desktop_support;
mod mobile_support;
mod support;

mod build_archive;
mod build_cache;
mod build_errors;
mod build_report;
mod build_script;
mod compile_bundled;
mod compile_snapshots;
mod desktop_camera_move;
mod desktop_frame;
mod desktop_motion;
mod desktop_occlusion_hzb;
mod desktop_passes;
mod desktop_shadows_cached;
mod desktop_shadows_frustum;
mod desktop_smoke_cascades;
mod desktop_temporal;
mod desktop_translucency_volume;
mod desktop_volume_local_shadows;
mod desktop_volumes_gl;
mod docs;
mod example_hello;
mod mobile_compare;
mod mobile_features;
mod mobile_frames;
mod mobile_golden;
mod mobile_permutations;
mod permute_config_errors;
mod permute_enumerate;
mod permute_explain;
mod preprocess_cpp;
mod preprocess_errors;
mod preprocess_fuzz;
mod preprocess_map;
mod runtime_archive;
mod runtime_pipelines;
mod runtime_precache;
mod runtime_render;
mod usage;
