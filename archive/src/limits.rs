//! The vocabulary of resource limits that the compiler and the runtime share: the names of
//! wgpu's `Limits` fields, which a level's `limits` table in `permutations.toml` sets, and the
//! one check of an entry point's reflection against them ([`violations`]), which the compiler
//! words with source spans and the runtime with its device's limits.

use crate::{BindingKind, Reflection, Stage};

/// Every field of wgpu 30's `Limits`, and whether it is a `u64` (else a `u32`). The ones
/// Kiln checks are fields of the compiler's `Limits`; the others are accepted and recorded.
pub const WGPU_LIMITS: &[(&str, bool)] = &[
    ("max_texture_dimension_1d", false),
    ("max_texture_dimension_2d", false),
    ("max_texture_dimension_3d", false),
    ("max_texture_array_layers", false),
    ("max_bind_groups", false),
    ("max_bind_groups_plus_vertex_buffers", false),
    ("max_bindings_per_bind_group", false),
    ("max_dynamic_uniform_buffers_per_pipeline_layout", false),
    ("max_dynamic_storage_buffers_per_pipeline_layout", false),
    ("max_sampled_textures_per_shader_stage", false),
    ("max_samplers_per_shader_stage", false),
    ("max_storage_buffers_per_shader_stage", false),
    ("max_storage_textures_per_shader_stage", false),
    ("max_uniform_buffers_per_shader_stage", false),
    ("max_binding_array_elements_per_shader_stage", false),
    ("max_binding_array_acceleration_structure_elements_per_shader_stage", false),
    ("max_binding_array_sampler_elements_per_shader_stage", false),
    ("max_uniform_buffer_binding_size", true),
    ("max_storage_buffer_binding_size", true),
    ("max_vertex_buffers", false),
    ("max_buffer_size", true),
    ("max_vertex_attributes", false),
    ("max_vertex_buffer_array_stride", false),
    ("max_inter_stage_shader_variables", false),
    ("min_uniform_buffer_offset_alignment", false),
    ("min_storage_buffer_offset_alignment", false),
    ("max_color_attachments", false),
    ("max_color_attachment_bytes_per_sample", false),
    ("max_compute_workgroup_storage_size", false),
    ("max_compute_invocations_per_workgroup", false),
    ("max_compute_workgroup_size_x", false),
    ("max_compute_workgroup_size_y", false),
    ("max_compute_workgroup_size_z", false),
    ("max_compute_workgroups_per_dimension", false),
    ("max_immediate_size", false),
    ("max_non_sampler_bindings", false),
    ("max_task_workgroup_total_count", false),
    ("max_task_workgroups_per_dimension", false),
    ("max_mesh_workgroup_total_count", false),
    ("max_mesh_workgroups_per_dimension", false),
    ("max_task_invocations_per_workgroup", false),
    ("max_task_invocations_per_dimension", false),
    ("max_mesh_invocations_per_workgroup", false),
    ("max_mesh_invocations_per_dimension", false),
    ("max_task_payload_size", false),
    ("max_mesh_output_vertices", false),
    ("max_mesh_output_primitives", false),
    ("max_mesh_output_layers", false),
    ("max_mesh_multiview_view_count", false),
    ("max_blas_primitive_count", false),
    ("max_blas_geometry_count", false),
    ("max_tlas_instance_count", false),
    ("max_acceleration_structures_per_shader_stage", false),
    ("max_buffers_and_acceleration_structures_per_shader_stage", false),
    ("max_multiview_view_count", false),
    ("max_ray_dispatch_count", false),
];

/// The classes of resources counted per shader stage, each with its own limit.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ResourceClass {
    /// `var<uniform>` buffers.
    UniformBuffer,
    /// `var<storage>` buffers.
    StorageBuffer,
    /// Samplers, comparison or not.
    Sampler,
    /// Sampled textures.
    SampledTexture,
    /// Storage textures.
    StorageTexture,
}

impl ResourceClass {
    /// Every class, in the order the runtime reports their counts.
    pub const ALL: [ResourceClass; 5] = [
        ResourceClass::UniformBuffer,
        ResourceClass::StorageBuffer,
        ResourceClass::Sampler,
        ResourceClass::SampledTexture,
        ResourceClass::StorageTexture,
    ];

    /// The class a binding counts in.
    pub fn of(kind: &BindingKind) -> ResourceClass {
        match kind {
            BindingKind::UniformBuffer { .. } => ResourceClass::UniformBuffer,
            BindingKind::StorageBuffer { .. } => ResourceClass::StorageBuffer,
            BindingKind::Sampler { .. } => ResourceClass::Sampler,
            BindingKind::Texture { .. } => ResourceClass::SampledTexture,
            BindingKind::StorageTexture { .. } => ResourceClass::StorageTexture,
        }
    }

    /// The plural noun, as messages say it (`"storage buffers"`).
    pub fn plural(self) -> &'static str {
        match self {
            ResourceClass::UniformBuffer => "uniform buffers",
            ResourceClass::StorageBuffer => "storage buffers",
            ResourceClass::Sampler => "samplers",
            ResourceClass::SampledTexture => "sampled textures",
            ResourceClass::StorageTexture => "storage textures",
        }
    }

    /// The singular noun (`"storage buffer"`).
    pub fn singular(self) -> &'static str {
        let plural = self.plural();
        &plural[..plural.len() - 1]
    }

    /// The wgpu `Limits` field that bounds the class per stage.
    pub fn field(self) -> &'static str {
        match self {
            ResourceClass::UniformBuffer => "max_uniform_buffers_per_shader_stage",
            ResourceClass::StorageBuffer => "max_storage_buffers_per_shader_stage",
            ResourceClass::Sampler => "max_samplers_per_shader_stage",
            ResourceClass::SampledTexture => "max_sampled_textures_per_shader_stage",
            ResourceClass::StorageTexture => "max_storage_textures_per_shader_stage",
        }
    }
}

/// The limits one entry point's reflection is checked against, named after wgpu's `Limits`
/// fields: the compiler fills it from a level, the runtime from its device.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct StageLimits {
    /// `max_bind_groups`.
    pub max_bind_groups: u32,
    /// `max_bindings_per_bind_group`.
    pub max_bindings_per_bind_group: u32,
    /// `max_uniform_buffers_per_shader_stage`.
    pub max_uniform_buffers_per_shader_stage: u32,
    /// `max_storage_buffers_per_shader_stage`.
    pub max_storage_buffers_per_shader_stage: u32,
    /// `max_samplers_per_shader_stage`.
    pub max_samplers_per_shader_stage: u32,
    /// `max_sampled_textures_per_shader_stage`.
    pub max_sampled_textures_per_shader_stage: u32,
    /// `max_storage_textures_per_shader_stage`.
    pub max_storage_textures_per_shader_stage: u32,
    /// `max_uniform_buffer_binding_size`.
    pub max_uniform_buffer_binding_size: u64,
    /// `max_storage_buffer_binding_size`.
    pub max_storage_buffer_binding_size: u64,
    /// `max_vertex_attributes`.
    pub max_vertex_attributes: u32,
    /// `max_color_attachments`.
    pub max_color_attachments: u32,
    /// `max_compute_workgroup_size_x`, `_y` and `_z`.
    pub max_compute_workgroup_size: [u32; 3],
    /// `max_compute_invocations_per_workgroup`.
    pub max_compute_invocations_per_workgroup: u32,
    /// Whether vertex shaders may use storage buffers and storage textures (wgpu's
    /// `VERTEX_STORAGE` downlevel flag; GLES 3.1 has not).
    pub vertex_storage: bool,
}

impl StageLimits {
    /// The per-stage limit of `class`.
    pub fn per_stage(&self, class: ResourceClass) -> u32 {
        match class {
            ResourceClass::UniformBuffer => self.max_uniform_buffers_per_shader_stage,
            ResourceClass::StorageBuffer => self.max_storage_buffers_per_shader_stage,
            ResourceClass::Sampler => self.max_samplers_per_shader_stage,
            ResourceClass::SampledTexture => self.max_sampled_textures_per_shader_stage,
            ResourceClass::StorageTexture => self.max_storage_textures_per_shader_stage,
        }
    }
}

/// One way a reflection breaks a [`StageLimits`]. `binding` is an index into the
/// reflection's `bindings`; each side words the violation in its own terms.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Violation {
    /// The entry point's name is empty or over 1024 bytes long.
    EntryName {
        /// The name's length in bytes.
        len: usize,
    },
    /// A binding's group is at or past `max_bind_groups`.
    BindGroup {
        /// The binding's index in the reflection.
        binding: usize,
    },
    /// A binding's number is at or past `max_bindings_per_bind_group`.
    BindingNumber {
        /// The binding's index in the reflection.
        binding: usize,
    },
    /// A (group, binding) is listed twice.
    Duplicate {
        /// The binding's index in the reflection.
        binding: usize,
    },
    /// A storage buffer or storage texture in a vertex shader without `vertex_storage`.
    VertexStorage {
        /// The binding's index in the reflection.
        binding: usize,
    },
    /// A uniform buffer over `max_uniform_buffer_binding_size`.
    UniformSize {
        /// The binding's index in the reflection.
        binding: usize,
        /// The buffer's size in bytes.
        size: u64,
    },
    /// A storage buffer over `max_storage_buffer_binding_size`.
    StorageSize {
        /// The binding's index in the reflection.
        binding: usize,
        /// The buffer's size in bytes.
        size: u64,
    },
    /// `binding` is the `nth` of its class, one over the class's per-stage limit; the stage
    /// has `total` of them in all.
    TooMany {
        /// The binding's index in the reflection.
        binding: usize,
        /// Its class.
        class: ResourceClass,
        /// Its rank among the stage's bindings of the class.
        nth: u32,
        /// How many of the class the stage has.
        total: u32,
    },
    /// More vertex inputs than `max_vertex_attributes`.
    VertexInputs {
        /// How many inputs the shader has.
        count: usize,
    },
    /// A vertex input's location at or past `max_vertex_attributes`.
    VertexLocation {
        /// The input's `@location`.
        location: u32,
    },
    /// More color outputs than `max_color_attachments`.
    ColorOutputs {
        /// How many outputs the shader has.
        count: usize,
    },
    /// A color output's location at or past `max_color_attachments`.
    ColorLocation {
        /// The output's `@location`.
        location: u32,
    },
    /// A workgroup size with a zero along some axis.
    WorkgroupZero {
        /// The workgroup size.
        size: [u32; 3],
    },
    /// A workgroup size over `max_compute_workgroup_size` along `axis` (0 to 2).
    WorkgroupAxis {
        /// The workgroup size.
        size: [u32; 3],
        /// The axis over the limit: 0, 1 or 2.
        axis: usize,
    },
    /// A workgroup of more than `max_compute_invocations_per_workgroup` invocations.
    WorkgroupInvocations {
        /// The workgroup size.
        size: [u32; 3],
        /// Its invocations: x times y times z.
        total: u64,
    },
    /// A compute entry point without a workgroup size.
    NoWorkgroupSize,
}

/// Every violation of `limits` by `r`, in one fixed order: the entry point's name; then
/// binding by binding its group, number, uniqueness, stage, size, and whether it is one too
/// many of its class; then vertex inputs, color outputs and the workgroup size. Each caller
/// reports the first one it cares about, in its own order.
pub fn violations(r: &Reflection, limits: &StageLimits) -> Vec<Violation> {
    let mut out = Vec::new();
    if r.entry.is_empty() || r.entry.len() > 1024 {
        out.push(Violation::EntryName { len: r.entry.len() });
    }
    let mut totals = [0u32; 5];
    for b in &r.bindings {
        totals[class_index(ResourceClass::of(&b.kind))] += 1;
    }
    let mut counts = [0u32; 5];
    let mut seen = std::collections::HashSet::new();
    for (i, b) in r.bindings.iter().enumerate() {
        if b.group >= limits.max_bind_groups {
            out.push(Violation::BindGroup { binding: i });
        }
        if b.binding >= limits.max_bindings_per_bind_group {
            out.push(Violation::BindingNumber { binding: i });
        }
        if !seen.insert((b.group, b.binding)) {
            out.push(Violation::Duplicate { binding: i });
        }
        let class = ResourceClass::of(&b.kind);
        let storage = matches!(class, ResourceClass::StorageBuffer | ResourceClass::StorageTexture);
        if r.stage == Stage::Vertex && !limits.vertex_storage && storage {
            out.push(Violation::VertexStorage { binding: i });
        }
        match b.kind {
            BindingKind::UniformBuffer { min_size } if min_size > limits.max_uniform_buffer_binding_size => {
                out.push(Violation::UniformSize { binding: i, size: min_size });
            }
            BindingKind::StorageBuffer { min_size, .. } if min_size > limits.max_storage_buffer_binding_size => {
                out.push(Violation::StorageSize { binding: i, size: min_size });
            }
            _ => {}
        }
        let c = class_index(class);
        counts[c] += 1;
        if u64::from(counts[c]) == u64::from(limits.per_stage(class)) + 1 {
            out.push(Violation::TooMany { binding: i, class, nth: counts[c], total: totals[c] });
        }
    }
    if r.vertex_inputs.len() as u64 > u64::from(limits.max_vertex_attributes) {
        out.push(Violation::VertexInputs { count: r.vertex_inputs.len() });
    }
    for v in &r.vertex_inputs {
        if v.location >= limits.max_vertex_attributes {
            out.push(Violation::VertexLocation { location: v.location });
        }
    }
    if r.color_outputs.len() as u64 > u64::from(limits.max_color_attachments) {
        out.push(Violation::ColorOutputs { count: r.color_outputs.len() });
    }
    for o in &r.color_outputs {
        if o.location >= limits.max_color_attachments {
            out.push(Violation::ColorLocation { location: o.location });
        }
    }
    match r.workgroup_size {
        Some(size) => {
            if size.contains(&0) {
                out.push(Violation::WorkgroupZero { size });
            }
            for axis in 0..3 {
                if size[axis] > limits.max_compute_workgroup_size[axis] {
                    out.push(Violation::WorkgroupAxis { size, axis });
                }
            }
            let total = size.iter().map(|&n| u64::from(n)).product::<u64>();
            if total > u64::from(limits.max_compute_invocations_per_workgroup) {
                out.push(Violation::WorkgroupInvocations { size, total });
            }
        }
        None if r.stage == Stage::Compute => out.push(Violation::NoWorkgroupSize),
        None => {}
    }
    out
}

fn class_index(class: ResourceClass) -> usize {
    ResourceClass::ALL.iter().position(|c| *c == class).expect("every class is listed")
}
