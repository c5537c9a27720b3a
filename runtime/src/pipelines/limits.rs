//! A permutation's reflection against the device's limits.

use super::layouts::storage_format;
use kiln_archive::Stage;
use kiln_archive::{BindingKind, Reflection};

/// Checks every field of a permutation's reflection against the device's limits (the
/// archive's manifest is input like any other: a checksum proves no origin): groups,
/// binding numbers, resources per stage and their sizes, vertex inputs, color outputs and
/// workgroup size. The message names the field, its value and the limit.
pub fn check_limits(r: &Reflection, limits: &wgpu::Limits) -> Result<(), String> {
    fn over(what: String, value: u64, field: &str, limit: impl Into<u64>) -> Result<(), String> {
        let limit = limit.into();
        if value > limit {
            Err(format!("{what} is {value}, over the device's {field} ({limit})"))
        } else {
            Ok(())
        }
    }
    if r.entry.is_empty() || r.entry.len() > 1024 {
        return Err(format!("entry point name of {} bytes", r.entry.len()));
    }
    let mut counts = [0u64; 5];
    let mut seen = std::collections::HashSet::new();
    for b in &r.bindings {
        let at = format!("@group({}) @binding({})", b.group, b.binding);
        if u64::from(b.group) >= u64::from(limits.max_bind_groups) {
            return Err(format!(
                "{at}: group {} is past the device's max_bind_groups ({})",
                b.group, limits.max_bind_groups
            ));
        }
        if u64::from(b.binding) >= u64::from(limits.max_bindings_per_bind_group) {
            return Err(format!(
                "{at}: binding {} is past the device's max_bindings_per_bind_group ({})",
                b.binding, limits.max_bindings_per_bind_group
            ));
        }
        if !seen.insert((b.group, b.binding)) {
            return Err(format!("{at} is listed twice"));
        }
        match &b.kind {
            BindingKind::UniformBuffer { min_size } => {
                counts[0] += 1;
                over(
                    format!("{at}: uniform buffer size"),
                    *min_size,
                    "max_uniform_buffer_binding_size",
                    limits.max_uniform_buffer_binding_size,
                )?;
            }
            BindingKind::StorageBuffer { min_size, .. } => {
                counts[1] += 1;
                over(
                    format!("{at}: storage buffer size"),
                    *min_size,
                    "max_storage_buffer_binding_size",
                    limits.max_storage_buffer_binding_size,
                )?;
            }
            BindingKind::Sampler { .. } => counts[2] += 1,
            BindingKind::Texture { .. } => counts[3] += 1,
            BindingKind::StorageTexture { format, .. } => {
                counts[4] += 1;
                if storage_format(format).is_none() {
                    return Err(format!("{at}: storage texture format `{format}` is not known to the runtime"));
                }
            }
        }
    }
    over(
        "uniform buffers in the stage".into(),
        counts[0],
        "max_uniform_buffers_per_shader_stage",
        limits.max_uniform_buffers_per_shader_stage,
    )?;
    over(
        "storage buffers in the stage".into(),
        counts[1],
        "max_storage_buffers_per_shader_stage",
        limits.max_storage_buffers_per_shader_stage,
    )?;
    over(
        "samplers in the stage".into(),
        counts[2],
        "max_samplers_per_shader_stage",
        limits.max_samplers_per_shader_stage,
    )?;
    over(
        "sampled textures in the stage".into(),
        counts[3],
        "max_sampled_textures_per_shader_stage",
        limits.max_sampled_textures_per_shader_stage,
    )?;
    over(
        "storage textures in the stage".into(),
        counts[4],
        "max_storage_textures_per_shader_stage",
        limits.max_storage_textures_per_shader_stage,
    )?;
    over("vertex inputs".into(), r.vertex_inputs.len() as u64, "max_vertex_attributes", limits.max_vertex_attributes)?;
    for v in &r.vertex_inputs {
        if v.location >= limits.max_vertex_attributes {
            return Err(format!(
                "vertex input @location({}) is past the device's max_vertex_attributes ({})",
                v.location, limits.max_vertex_attributes
            ));
        }
    }
    over("color outputs".into(), r.color_outputs.len() as u64, "max_color_attachments", limits.max_color_attachments)?;
    for o in &r.color_outputs {
        if o.location >= limits.max_color_attachments {
            return Err(format!(
                "color output @location({}) is past the device's max_color_attachments ({})",
                o.location, limits.max_color_attachments
            ));
        }
    }
    if let Some([x, y, z]) = r.workgroup_size {
        if x == 0 || y == 0 || z == 0 {
            return Err(format!("workgroup size {x}x{y}x{z} has a zero"));
        }
        over("workgroup size x".into(), x.into(), "max_compute_workgroup_size_x", limits.max_compute_workgroup_size_x)?;
        over("workgroup size y".into(), y.into(), "max_compute_workgroup_size_y", limits.max_compute_workgroup_size_y)?;
        over("workgroup size z".into(), z.into(), "max_compute_workgroup_size_z", limits.max_compute_workgroup_size_z)?;
        let invocations = u64::from(x) * u64::from(y) * u64::from(z);
        over(
            "workgroup invocations".into(),
            invocations,
            "max_compute_invocations_per_workgroup",
            limits.max_compute_invocations_per_workgroup,
        )?;
    } else if r.stage == Stage::Compute {
        return Err("compute shader without a workgroup size".into());
    }
    Ok(())
}
