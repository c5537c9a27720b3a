//! A permutation's reflection against the device's limits.

use super::layouts::storage_format;
use kiln_archive::limits::{violations, ResourceClass, StageLimits, Violation as V};
use kiln_archive::{BindingKind, Reflection};

/// Checks every field of a permutation's reflection against the device's limits (the
/// archive's manifest is input like any other: a checksum proves no origin): groups,
/// binding numbers, resources per stage and their sizes, vertex inputs, color outputs and
/// workgroup size. The message names the field, its value and the limit.
pub fn check_limits(r: &Reflection, limits: &wgpu::Limits) -> Result<(), String> {
    let stage_limits = stage_limits(limits);
    let found = violations(r, &stage_limits);
    // The order of report: the entry point's name, then each binding's own faults (the
    // storage texture formats the runtime knows among them), then the counts per class,
    // then the rest as listed.
    if let Some(V::EntryName { len }) = found.first() {
        return Err(format!("entry point name of {len} bytes"));
    }
    let fault = binding_fault(r, limits, &stage_limits, &found)
        .or_else(|| count_fault(&stage_limits, &found))
        .or_else(|| stage_fault(limits, &stage_limits, &found));
    match fault {
        Some(message) => Err(message),
        None => Ok(()),
    }
}

/// The limits `kiln_archive`'s checker reads, from the device's.
fn stage_limits(limits: &wgpu::Limits) -> StageLimits {
    StageLimits {
        max_bind_groups: limits.max_bind_groups,
        max_bindings_per_bind_group: limits.max_bindings_per_bind_group,
        max_uniform_buffers_per_shader_stage: limits.max_uniform_buffers_per_shader_stage,
        max_storage_buffers_per_shader_stage: limits.max_storage_buffers_per_shader_stage,
        max_samplers_per_shader_stage: limits.max_samplers_per_shader_stage,
        max_sampled_textures_per_shader_stage: limits.max_sampled_textures_per_shader_stage,
        max_storage_textures_per_shader_stage: limits.max_storage_textures_per_shader_stage,
        max_uniform_buffer_binding_size: limits.max_uniform_buffer_binding_size,
        max_storage_buffer_binding_size: limits.max_storage_buffer_binding_size,
        max_vertex_attributes: limits.max_vertex_attributes,
        max_color_attachments: limits.max_color_attachments,
        max_compute_workgroup_size: [
            limits.max_compute_workgroup_size_x,
            limits.max_compute_workgroup_size_y,
            limits.max_compute_workgroup_size_z,
        ],
        max_compute_invocations_per_workgroup: limits.max_compute_invocations_per_workgroup,
        vertex_storage: true,
    }
}

/// `@group(g) @binding(b)` of the reflection's binding `i`.
fn at(r: &Reflection, i: usize) -> String {
    format!("@group({}) @binding({})", r.bindings[i].group, r.bindings[i].binding)
}

/// "`what` is `value`, over the device's `field` (`limit`)".
fn over(what: String, value: u64, field: &str, limit: u64) -> String {
    format!("{what} is {value}, over the device's {field} ({limit})")
}

/// The first binding's own fault: its group or number past the limits, listed twice, a
/// buffer too large, or a storage texture format the runtime does not know (whichever
/// binding comes first).
fn binding_fault(r: &Reflection, limits: &wgpu::Limits, stage_limits: &StageLimits, found: &[V]) -> Option<String> {
    let own = found.iter().find_map(|v| match *v {
        V::BindGroup { binding } | V::BindingNumber { binding } | V::Duplicate { binding } => Some((binding, v)),
        V::UniformSize { binding, .. } | V::StorageSize { binding, .. } => Some((binding, v)),
        _ => None,
    });
    let unknown_format = r.bindings.iter().position(|b| match &b.kind {
        BindingKind::StorageTexture { format, .. } => storage_format(format).is_none(),
        _ => false,
    });
    match (own, unknown_format) {
        (Some((i, v)), f) if f.is_none_or(|f| i <= f) => {
            let b = &r.bindings[i];
            Some(match *v {
                V::BindGroup { .. } => format!(
                    "{}: group {} is past the device's max_bind_groups ({})",
                    at(r, i),
                    b.group,
                    limits.max_bind_groups
                ),
                V::BindingNumber { .. } => format!(
                    "{}: binding {} is past the device's max_bindings_per_bind_group ({})",
                    at(r, i),
                    b.binding,
                    limits.max_bindings_per_bind_group
                ),
                V::Duplicate { .. } => format!("{} is listed twice", at(r, i)),
                V::UniformSize { size, .. } => over(
                    format!("{}: uniform buffer size", at(r, i)),
                    size,
                    "max_uniform_buffer_binding_size",
                    stage_limits.max_uniform_buffer_binding_size,
                ),
                V::StorageSize { size, .. } => over(
                    format!("{}: storage buffer size", at(r, i)),
                    size,
                    "max_storage_buffer_binding_size",
                    stage_limits.max_storage_buffer_binding_size,
                ),
                _ => unreachable!("only a binding's own faults are chosen above"),
            })
        }
        (_, Some(f)) => {
            let BindingKind::StorageTexture { format, .. } = &r.bindings[f].kind else { unreachable!() };
            Some(format!("{}: storage texture format `{format}` is not known to the runtime", at(r, f)))
        }
        _ => None,
    }
}

/// The first resource class with more bindings in the stage than the device allows.
fn count_fault(stage_limits: &StageLimits, found: &[V]) -> Option<String> {
    ResourceClass::ALL.into_iter().find_map(|class| {
        let Some(V::TooMany { total, .. }) =
            found.iter().find(|v| matches!(v, V::TooMany { class: c, .. } if *c == class))
        else {
            return None;
        };
        let limit = stage_limits.per_stage(class).into();
        Some(over(format!("{} in the stage", class.plural()), (*total).into(), class.field(), limit))
    })
}

/// The first fault of the stage's interface: vertex inputs, color outputs, workgroup size.
fn stage_fault(limits: &wgpu::Limits, stage_limits: &StageLimits, found: &[V]) -> Option<String> {
    let xyz = ["x", "y", "z"];
    found.iter().find_map(|v| {
        Some(match *v {
            V::VertexInputs { count } => {
                over("vertex inputs".into(), count as u64, "max_vertex_attributes", limits.max_vertex_attributes.into())
            }
            V::VertexLocation { location } => format!(
                "vertex input @location({location}) is past the device's max_vertex_attributes ({})",
                limits.max_vertex_attributes
            ),
            V::ColorOutputs { count } => {
                over("color outputs".into(), count as u64, "max_color_attachments", limits.max_color_attachments.into())
            }
            V::ColorLocation { location } => format!(
                "color output @location({location}) is past the device's max_color_attachments ({})",
                limits.max_color_attachments
            ),
            V::WorkgroupZero { size: [x, y, z] } => format!("workgroup size {x}x{y}x{z} has a zero"),
            V::WorkgroupAxis { size, axis } => over(
                format!("workgroup size {}", xyz[axis]),
                size[axis].into(),
                ["max_compute_workgroup_size_x", "max_compute_workgroup_size_y", "max_compute_workgroup_size_z"][axis],
                stage_limits.max_compute_workgroup_size[axis].into(),
            ),
            V::WorkgroupInvocations { total, .. } => over(
                "workgroup invocations".into(),
                total,
                "max_compute_invocations_per_workgroup",
                limits.max_compute_invocations_per_workgroup.into(),
            ),
            V::NoWorkgroupSize => "compute shader without a workgroup size".into(),
            // A binding's faults and the counts are reported above; vertex storage is not a
            // device limit here.
            _ => return None,
        })
    })
}
