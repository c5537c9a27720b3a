//! A permutation's reflection against the device's limits.

use super::layouts::storage_format;
use kiln_archive::{BindingKind, Reflection};

/// Checks every field of a permutation's reflection against the device's limits (the
/// archive's manifest is input like any other: a checksum proves no origin): groups,
/// binding numbers, resources per stage and their sizes, vertex inputs, color outputs and
/// workgroup size. The message names the field, its value and the limit.
pub fn check_limits(r: &Reflection, limits: &wgpu::Limits) -> Result<(), String> {
    use kiln_archive::limits::{violations, ResourceClass, StageLimits, Violation as V};
    let stage_limits = StageLimits {
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
    };
    let found = violations(r, &stage_limits);
    let at = |i: usize| format!("@group({}) @binding({})", r.bindings[i].group, r.bindings[i].binding);
    let over = |what: String, value: u64, field: &str, limit: u64| {
        format!("{what} is {value}, over the device's {field} ({limit})")
    };
    // The order of report: the entry point's name, then each binding's own faults (the
    // storage texture formats the runtime knows among them), then the counts per class,
    // then the rest as listed.
    if let Some(V::EntryName { len }) = found.first() {
        return Err(format!("entry point name of {len} bytes"));
    }
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
            return Err(match *v {
                V::BindGroup { .. } => {
                    format!(
                        "{}: group {} is past the device's max_bind_groups ({})",
                        at(i),
                        b.group,
                        limits.max_bind_groups
                    )
                }
                V::BindingNumber { .. } => format!(
                    "{}: binding {} is past the device's max_bindings_per_bind_group ({})",
                    at(i),
                    b.binding,
                    limits.max_bindings_per_bind_group
                ),
                V::Duplicate { .. } => format!("{} is listed twice", at(i)),
                V::UniformSize { size, .. } => over(
                    format!("{}: uniform buffer size", at(i)),
                    size,
                    "max_uniform_buffer_binding_size",
                    stage_limits.max_uniform_buffer_binding_size,
                ),
                V::StorageSize { size, .. } => over(
                    format!("{}: storage buffer size", at(i)),
                    size,
                    "max_storage_buffer_binding_size",
                    stage_limits.max_storage_buffer_binding_size,
                ),
                _ => unreachable!("only a binding's own faults are chosen above"),
            });
        }
        (_, Some(f)) => {
            let BindingKind::StorageTexture { format, .. } = &r.bindings[f].kind else { unreachable!() };
            return Err(format!("{}: storage texture format `{format}` is not known to the runtime", at(f)));
        }
        _ => {}
    }
    for class in ResourceClass::ALL {
        if let Some(V::TooMany { total, .. }) =
            found.iter().find(|v| matches!(v, V::TooMany { class: c, .. } if *c == class))
        {
            let limit = stage_limits.per_stage(class).into();
            return Err(over(format!("{} in the stage", class.plural()), (*total).into(), class.field(), limit));
        }
    }
    let xyz = ["x", "y", "z"];
    for v in &found {
        return Err(match *v {
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
            _ => continue,
        });
    }
    Ok(())
}
