//! The resource limits and capabilities of a level, checked per entry point.
//!
//! `desktop` is wgpu's `Limits::defaults()` with WebGPU's core capabilities; `downlevel` is
//! `Limits::downlevel_defaults()` (4 color attachments, 4 storage buffers per stage, 16 KiB
//! uniform buffers, 16352 bytes of workgroup storage) with what GLES 3.1 lacks removed: no
//! cube array textures, no per-sample shading, no storage buffers or storage textures in
//! vertex shaders. A level's `limits` table ([`Limits::set`]) raises or lowers single
//! limits by their wgpu `Limits` field names.

use crate::archive::{BindingKind, Reflection, Stage};

use super::{Error, ErrorKind};

/// Per-stage and per-pipeline limits, named after wgpu's `Limits` fields.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct Limits {
    /// `"desktop"` or `"downlevel"`: shown in errors and part of the cache key.
    pub name: &'static str,
    pub max_bind_groups: u32,
    pub max_bindings_per_bind_group: u32,
    pub max_samplers_per_shader_stage: u32,
    pub max_sampled_textures_per_shader_stage: u32,
    pub max_storage_buffers_per_shader_stage: u32,
    pub max_storage_textures_per_shader_stage: u32,
    pub max_uniform_buffers_per_shader_stage: u32,
    pub max_uniform_buffer_binding_size: u64,
    pub max_vertex_attributes: u32,
    pub max_color_attachments: u32,
    pub max_compute_workgroup_storage_size: u64,
    pub max_compute_invocations_per_workgroup: u32,
    pub max_compute_workgroup_size: [u32; 3],
    /// GLES: vertex shaders may not use storage buffers or storage textures.
    pub vertex_storage: bool,
    /// GLES 3.1 core has neither cube array textures nor per-sample shading.
    pub gles: bool,
    /// The single limits a level's `limits` table sets, as written (part of the cache key;
    /// named in errors as set by the level).
    pub overrides: Vec<(String, u64)>,
}

/// Every field of wgpu 30's `Limits` ([`kiln_archive::limits::WGPU_LIMITS`]).
pub use crate::archive::limits::WGPU_LIMITS;

impl Default for Limits {
    fn default() -> Self {
        Limits::desktop()
    }
}

impl Limits {
    /// wgpu's `Limits::defaults()`.
    pub fn desktop() -> Limits {
        Limits {
            name: "desktop",
            max_bind_groups: 4,
            max_bindings_per_bind_group: 1000,
            max_samplers_per_shader_stage: 16,
            max_sampled_textures_per_shader_stage: 16,
            max_storage_buffers_per_shader_stage: 8,
            max_storage_textures_per_shader_stage: 4,
            max_uniform_buffers_per_shader_stage: 12,
            max_uniform_buffer_binding_size: 64 << 10,
            max_vertex_attributes: 16,
            max_color_attachments: 8,
            max_compute_workgroup_storage_size: 16384,
            max_compute_invocations_per_workgroup: 256,
            max_compute_workgroup_size: [256, 256, 64],
            vertex_storage: true,
            gles: false,
            overrides: Vec::new(),
        }
    }

    /// wgpu's `Limits::downlevel_defaults()`, GLES 3.1 capabilities, 4 color attachments.
    pub fn downlevel() -> Limits {
        Limits {
            name: "downlevel",
            max_storage_buffers_per_shader_stage: 4,
            max_uniform_buffer_binding_size: 16 << 10,
            max_color_attachments: 4,
            max_compute_workgroup_storage_size: 16352,
            vertex_storage: false,
            gles: true,
            ..Limits::desktop()
        }
    }

    /// The limits of `level`: its base (`default` or `downlevel`) with its overrides applied.
    pub fn for_level(level: &crate::permute::Level) -> Limits {
        let mut limits = match level.limits {
            crate::permute::Limits::Default => Limits::desktop(),
            crate::permute::Limits::Downlevel => Limits::downlevel(),
        };
        for (field, value) in &level.limit_overrides {
            limits.set(field, *value);
        }
        limits
    }

    /// Sets one limit by its wgpu `Limits` field name (the config loader has checked the name
    /// against [`WGPU_LIMITS`] and the value's range). A field Kiln does not check is only recorded.
    pub fn set(&mut self, field: &str, value: u64) {
        let v32 = u32::try_from(value).unwrap_or(u32::MAX);
        match field {
            "max_bind_groups" => self.max_bind_groups = v32,
            "max_bindings_per_bind_group" => self.max_bindings_per_bind_group = v32,
            "max_samplers_per_shader_stage" => self.max_samplers_per_shader_stage = v32,
            "max_sampled_textures_per_shader_stage" => self.max_sampled_textures_per_shader_stage = v32,
            "max_storage_buffers_per_shader_stage" => self.max_storage_buffers_per_shader_stage = v32,
            "max_storage_textures_per_shader_stage" => self.max_storage_textures_per_shader_stage = v32,
            "max_uniform_buffers_per_shader_stage" => self.max_uniform_buffers_per_shader_stage = v32,
            "max_uniform_buffer_binding_size" => self.max_uniform_buffer_binding_size = value,
            "max_vertex_attributes" => self.max_vertex_attributes = v32,
            "max_color_attachments" => self.max_color_attachments = v32,
            "max_compute_workgroup_storage_size" => self.max_compute_workgroup_storage_size = value,
            "max_compute_invocations_per_workgroup" => self.max_compute_invocations_per_workgroup = v32,
            "max_compute_workgroup_size_x" => self.max_compute_workgroup_size[0] = v32,
            "max_compute_workgroup_size_y" => self.max_compute_workgroup_size[1] = v32,
            "max_compute_workgroup_size_z" => self.max_compute_workgroup_size[2] = v32,
            _ => {}
        }
        self.overrides.retain(|(f, _)| f != field);
        self.overrides.push((field.to_string(), value));
    }

    /// The note under a limit error: where the limit's value comes from.
    fn note(&self, field: &str, value: impl std::fmt::Display) -> String {
        if self.overrides.iter().any(|(f, _)| f == field) {
            format!("{field} = {value}, as the level's `limits` table sets it")
        } else {
            format!("{field} = {value} at the {} limits", self.name)
        }
    }

    /// What naga's validator may accept at this level.
    pub fn capabilities(&self) -> naga::valid::Capabilities {
        use naga::valid::Capabilities as C;
        if self.gles {
            C::empty()
        } else {
            C::MULTISAMPLED_SHADING | C::CUBE_ARRAY_TEXTURES
        }
    }

    /// Checks the entry point's resources against the limits. `reflection` is the entry
    /// point's, from [`super::reflect`].
    pub(crate) fn check(
        &self,
        module: &naga::Module,
        info: &naga::valid::ModuleInfo,
        reflection: &Reflection,
    ) -> Result<(), Error> {
        let span_of = |group: u32, binding: u32| {
            module
                .global_variables
                .iter()
                .find(|(_, g)| g.binding.as_ref().is_some_and(|b| b.group == group && b.binding == binding))
                .and_then(|(h, _)| module.global_variables.get_span(h).to_range())
        };
        let fail = |message: String, at: Option<(u32, u32)>, label: &str, note: String| {
            let mut e = Error::new(ErrorKind::Limit, message);
            if let Some(range) = at.and_then(|(g, b)| span_of(g, b)) {
                e.labels.push((range, label.to_string()));
            }
            e.notes.push(note);
            e
        };
        let level = self.name;
        let stage = reflection.stage;

        let mut counts = [0u32; 5];
        let names = [
            ("samplers", "max_samplers_per_shader_stage", self.max_samplers_per_shader_stage),
            ("sampled textures", "max_sampled_textures_per_shader_stage", self.max_sampled_textures_per_shader_stage),
            ("storage buffers", "max_storage_buffers_per_shader_stage", self.max_storage_buffers_per_shader_stage),
            ("storage textures", "max_storage_textures_per_shader_stage", self.max_storage_textures_per_shader_stage),
            ("uniform buffers", "max_uniform_buffers_per_shader_stage", self.max_uniform_buffers_per_shader_stage),
        ];
        for b in &reflection.bindings {
            let name = b.name.as_deref().unwrap_or("<unnamed>");
            let at = Some((b.group, b.binding));
            if b.group >= self.max_bind_groups {
                return Err(fail(
                    format!(
                        "binding `{name}` uses bind group {}, beyond the {level} limit of {} bind groups",
                        b.group, self.max_bind_groups
                    ),
                    at,
                    "declared here",
                    self.note("max_bind_groups", self.max_bind_groups),
                ));
            }
            if b.binding >= self.max_bindings_per_bind_group {
                return Err(fail(
                    format!(
                        "binding `{name}` uses binding {}, beyond the {level} limit of {} bindings per group",
                        b.binding, self.max_bindings_per_bind_group
                    ),
                    at,
                    "declared here",
                    self.note("max_bindings_per_bind_group", self.max_bindings_per_bind_group),
                ));
            }
            let slot = match &b.kind {
                BindingKind::Sampler { .. } => 0,
                BindingKind::Texture { .. } => 1,
                BindingKind::StorageBuffer { .. } => 2,
                BindingKind::StorageTexture { .. } => 3,
                BindingKind::UniformBuffer { .. } => 4,
            };
            if stage == Stage::Vertex && !self.vertex_storage && (slot == 2 || slot == 3) {
                return Err(fail(
                    format!("binding `{name}` is a {} in a vertex shader, which the {level} limits do not allow", &names[slot].0[..names[slot].0.len() - 1]),
                    at,
                    "used by the vertex entry point",
                    "GLES 3.1 has no storage buffers or storage textures in vertex shaders (wgpu's VERTEX_STORAGE downlevel flag)".to_string(),
                ));
            }
            if let BindingKind::UniformBuffer { min_size } = b.kind {
                if min_size > self.max_uniform_buffer_binding_size {
                    return Err(fail(
                        format!(
                            "uniform buffer `{name}` is {min_size} bytes, over the {level} limit of {} bytes",
                            self.max_uniform_buffer_binding_size
                        ),
                        at,
                        "declared here",
                        self.note("max_uniform_buffer_binding_size", self.max_uniform_buffer_binding_size),
                    ));
                }
            }
            counts[slot] += 1;
            let (what, field, max) = names[slot];
            if counts[slot] > max {
                return Err(fail(
                    format!("binding `{name}` is the {} of the {stage} stage, over the {level} limit of {max} {what} per stage", ordinal(counts[slot]) + " " + &what[..what.len() - 1]),
                    at,
                    "one too many",
                    self.note(field, max),
                ));
            }
        }
        if reflection.vertex_inputs.len() as u32 > self.max_vertex_attributes {
            return Err(fail(
                format!(
                    "the vertex shader has {} inputs, over the {level} limit of {}",
                    reflection.vertex_inputs.len(),
                    self.max_vertex_attributes
                ),
                None,
                "",
                self.note("max_vertex_attributes", self.max_vertex_attributes),
            ));
        }
        if let Some(c) = reflection.color_outputs.iter().find(|c| c.location >= self.max_color_attachments) {
            return Err(fail(
                format!(
                    "color output @location({}) is beyond the {level} limit of {} color attachments",
                    c.location, self.max_color_attachments
                ),
                None,
                "",
                self.note("max_color_attachments", self.max_color_attachments),
            ));
        }
        if let Some(size) = reflection.workgroup_size {
            for (axis, (&n, &max)) in size.iter().zip(&self.max_compute_workgroup_size).enumerate() {
                if n > max {
                    return Err(fail(
                        format!(
                            "workgroup size {} is {n} along {}, over the {level} limit of {max}",
                            fmt_size(size),
                            ["x", "y", "z"][axis]
                        ),
                        None,
                        "",
                        self.note(
                            [
                                "max_compute_workgroup_size_x",
                                "max_compute_workgroup_size_y",
                                "max_compute_workgroup_size_z",
                            ][axis],
                            max,
                        ),
                    ));
                }
            }
            let total = size.iter().map(|&n| n as u64).product::<u64>();
            if total > self.max_compute_invocations_per_workgroup as u64 {
                return Err(fail(
                    format!(
                        "workgroup size {} is {total} invocations, over the {level} limit of {}",
                        fmt_size(size),
                        self.max_compute_invocations_per_workgroup
                    ),
                    None,
                    "",
                    self.note("max_compute_invocations_per_workgroup", self.max_compute_invocations_per_workgroup),
                ));
            }
            let ep_info = info.get_entry_point(0);
            let mut total = 0u64;
            let mut last = None;
            for (h, g) in module.global_variables.iter() {
                if g.space == naga::AddressSpace::WorkGroup && !ep_info[h].is_empty() {
                    total += module.types[g.ty].inner.try_size(module.to_ctx()).unwrap_or(0) as u64;
                    last = Some(h);
                    if total > self.max_compute_workgroup_storage_size {
                        break;
                    }
                }
            }
            if total > self.max_compute_workgroup_storage_size {
                let h = last.expect("some workgroup variable");
                let name = module.global_variables[h].name.as_deref().unwrap_or("<unnamed>");
                let mut e = Error::new(
                    ErrorKind::Limit,
                    format!(
                        "workgroup variables take {total} bytes up to `{name}`, over the {level} limit of {} bytes",
                        self.max_compute_workgroup_storage_size
                    ),
                );
                if let Some(r) = module.global_variables.get_span(h).to_range() {
                    e.labels.push((r, "the limit is crossed here".into()));
                }
                e.notes.push(self.note("max_compute_workgroup_storage_size", self.max_compute_workgroup_storage_size));
                return Err(e);
            }
        }
        Ok(())
    }
}

fn fmt_size(s: [u32; 3]) -> String {
    format!("({}, {}, {})", s[0], s[1], s[2])
}

fn ordinal(n: u32) -> String {
    let suffix = match (n % 10, n % 100) {
        (1, x) if x != 11 => "st",
        (2, x) if x != 12 => "nd",
        (3, x) if x != 13 => "rd",
        _ => "th",
    };
    format!("{n}{suffix}")
}
