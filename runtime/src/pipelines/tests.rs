//! Unit tests of layouts, vertex inputs and limits.

use kiln_archive::{NumericType, ScalarKind, VertexInput};

use super::layouts::{layout_entry, vertex_buffers};
use super::*;
use kiln_archive::{Binding, BindingKind, Reflection, SampleKind, Stage, StorageAccess, TextureDim};
use std::num::NonZeroU64;

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
        let b = MergedBinding { binding: 3, name: Some(name.into()), kind, visibility: wgpu::ShaderStages::FRAGMENT };
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
    const MESH: [wgpu::VertexAttribute; 3] = wgpu::vertex_attr_array![0 => Float32x3, 1 => Float32x3, 2 => Float32x2];
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
    assert_eq!(e, "pipeline `Screen`: vertex input @location(0) is not provided by its vertex layout (locations [])");
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
        e(&reflection(Stage::Fragment, vec![binding(0, 0, "S", sampler.clone()), binding(0, 0, "T", sampler.clone())])),
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
    assert_eq!(e(&cs), "workgroup invocations is 512, over the device's max_compute_invocations_per_workgroup (256)");
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
