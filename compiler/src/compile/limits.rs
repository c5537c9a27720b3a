//! The resource limits and capabilities of a level, checked per entry point.
//!
//! `desktop` is wgpu's `Limits::defaults()` with WebGPU's core capabilities; `downlevel` is
//! `Limits::downlevel_defaults()` (4 color attachments, 4 storage buffers per stage, 16 KiB
//! uniform buffers, 16352 bytes of workgroup storage) with what GLES 3.1 lacks removed: no
//! cube array textures, no per-sample shading, no storage buffers or storage textures in
//! vertex shaders. A level's `limits` table ([`Limits::set`]) raises or lowers single
//! limits by their wgpu `Limits` field names.

use crate::archive::limits::{violations, ResourceClass, StageLimits, Violation, Violation as V};
use crate::archive::Reflection;

use super::{Error, ErrorKind};

/// Per-stage and per-pipeline limits, named after wgpu's `Limits` fields.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct Limits {
    /// `"desktop"` or `"downlevel"`: shown in errors and part of the cache key.
    pub name: &'static str,
    /// wgpu's `max_bind_groups`.
    pub max_bind_groups: u32,
    /// wgpu's `max_bindings_per_bind_group`.
    pub max_bindings_per_bind_group: u32,
    /// wgpu's `max_samplers_per_shader_stage`.
    pub max_samplers_per_shader_stage: u32,
    /// wgpu's `max_sampled_textures_per_shader_stage`.
    pub max_sampled_textures_per_shader_stage: u32,
    /// wgpu's `max_storage_buffers_per_shader_stage`.
    pub max_storage_buffers_per_shader_stage: u32,
    /// wgpu's `max_storage_textures_per_shader_stage`.
    pub max_storage_textures_per_shader_stage: u32,
    /// wgpu's `max_uniform_buffers_per_shader_stage`.
    pub max_uniform_buffers_per_shader_stage: u32,
    /// wgpu's `max_uniform_buffer_binding_size`.
    pub max_uniform_buffer_binding_size: u64,
    /// wgpu's `max_vertex_attributes`.
    pub max_vertex_attributes: u32,
    /// wgpu's `max_color_attachments`.
    pub max_color_attachments: u32,
    /// wgpu's `max_compute_workgroup_storage_size`.
    pub max_compute_workgroup_storage_size: u64,
    /// wgpu's `max_compute_invocations_per_workgroup`.
    pub max_compute_invocations_per_workgroup: u32,
    /// wgpu's `max_compute_workgroup_size_x, _y and _z`.
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

/// How `word` builds an error: message, the binding it points at, the label, the note.
type Fail<'a> = dyn Fn(String, Option<usize>, &str, String) -> Error + 'a;

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

    /// The limits [`kiln_archive::limits::violations`] checks a reflection against: this
    /// level's, with the sizes Kiln does not check at compile time unbounded.
    fn stage_limits(&self) -> StageLimits {
        StageLimits {
            max_bind_groups: self.max_bind_groups,
            max_bindings_per_bind_group: self.max_bindings_per_bind_group,
            max_uniform_buffers_per_shader_stage: self.max_uniform_buffers_per_shader_stage,
            max_storage_buffers_per_shader_stage: self.max_storage_buffers_per_shader_stage,
            max_samplers_per_shader_stage: self.max_samplers_per_shader_stage,
            max_sampled_textures_per_shader_stage: self.max_sampled_textures_per_shader_stage,
            max_storage_textures_per_shader_stage: self.max_storage_textures_per_shader_stage,
            max_uniform_buffer_binding_size: self.max_uniform_buffer_binding_size,
            max_storage_buffer_binding_size: u64::MAX,
            max_vertex_attributes: self.max_vertex_attributes,
            max_color_attachments: self.max_color_attachments,
            max_compute_workgroup_size: self.max_compute_workgroup_size,
            max_compute_invocations_per_workgroup: self.max_compute_invocations_per_workgroup,
            vertex_storage: self.vertex_storage,
        }
    }

    /// Checks the entry point's resources against the limits. `reflection` is the entry
    /// point's, from [`super::reflect()`]. The shared check ([`violations`]) finds what is over;
    /// this words the first of it with the source span of the binding, and adds the one
    /// check that needs naga's module: workgroup storage.
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
        let fail = |message: String, at: Option<usize>, label: &str, note: String| {
            let mut e = Error::new(ErrorKind::Limit, message);
            let at = at.map(|i| &reflection.bindings[i]);
            if let Some(range) = at.and_then(|b| span_of(b.group, b.binding)) {
                e.labels.push((range, label.to_string()));
            }
            e.notes.push(note);
            e
        };
        // The faults only the runtime checks (names, duplicates, zero sizes, vertex input
        // locations, the count of color outputs) never stop a compile.
        let first = violations(reflection, &self.stage_limits()).into_iter().find(|v| {
            !matches!(
                v,
                V::EntryName { .. }
                    | V::Duplicate { .. }
                    | V::StorageSize { .. }
                    | V::VertexLocation { .. }
                    | V::ColorOutputs { .. }
                    | V::WorkgroupZero { .. }
                    | V::NoWorkgroupSize
            )
        });
        if let Some(v) = first {
            return Err(self.word(reflection, v, fail));
        }
        if reflection.workgroup_size.is_some() {
            self.check_workgroup_storage(module, info)?;
        }
        Ok(())
    }

    /// A violation as a compile error: its message, the span it points at and the note that
    /// says where the limit comes from.
    fn word(
        &self,
        reflection: &Reflection,
        v: Violation,
        fail: impl Fn(String, Option<usize>, &str, String) -> Error,
    ) -> Error {
        match v {
            V::BindGroup { .. }
            | V::BindingNumber { .. }
            | V::VertexStorage { .. }
            | V::UniformSize { .. }
            | V::TooMany { .. } => self.word_binding(reflection, v, &fail),
            _ => self.word_stage(v, &fail),
        }
    }

    /// `word` for a violation of one binding: the error points at it.
    fn word_binding(&self, reflection: &Reflection, v: Violation, fail: &Fail<'_>) -> Error {
        let level = self.name;
        let stage = reflection.stage;
        let name = |i: usize| reflection.bindings[i].name.as_deref().unwrap_or("<unnamed>").to_string();
        match v {
            V::BindGroup { binding: i } => fail(
                format!(
                    "binding `{}` uses bind group {}, beyond the {level} limit of {} bind groups",
                    name(i),
                    reflection.bindings[i].group,
                    self.max_bind_groups
                ),
                Some(i),
                "declared here",
                self.note("max_bind_groups", self.max_bind_groups),
            ),
            V::BindingNumber { binding: i } => fail(
                format!(
                    "binding `{}` uses binding {}, beyond the {level} limit of {} bindings per group",
                    name(i),
                    reflection.bindings[i].binding,
                    self.max_bindings_per_bind_group
                ),
                Some(i),
                "declared here",
                self.note("max_bindings_per_bind_group", self.max_bindings_per_bind_group),
            ),
            V::VertexStorage { binding: i } => fail(
                format!(
                    "binding `{}` is a {} in a vertex shader, which the {level} limits do not allow",
                    name(i),
                    ResourceClass::of(&reflection.bindings[i].kind).singular()
                ),
                Some(i),
                "used by the vertex entry point",
                "GLES 3.1 has no storage buffers or storage textures in vertex shaders (wgpu's VERTEX_STORAGE downlevel flag)".to_string(),
            ),
            V::UniformSize { binding: i, size } => fail(
                format!(
                    "uniform buffer `{}` is {size} bytes, over the {level} limit of {} bytes",
                    name(i),
                    self.max_uniform_buffer_binding_size
                ),
                Some(i),
                "declared here",
                self.note("max_uniform_buffer_binding_size", self.max_uniform_buffer_binding_size),
            ),
            V::TooMany { binding: i, class, nth, .. } => {
                let max = self.stage_limits().per_stage(class);
                fail(
                    format!(
                        "binding `{}` is the {} {} of the {stage} stage, over the {level} limit of {max} {} per stage",
                        name(i),
                        ordinal(nth),
                        class.singular(),
                        class.plural()
                    ),
                    Some(i),
                    "one too many",
                    self.note(class.field(), max),
                )
            }
            _ => self.word_stage(v, fail),
        }
    }

    /// `word` for a violation of the stage as a whole: vertex inputs, color
    /// outputs, workgroup size.
    fn word_stage(&self, v: Violation, fail: &Fail<'_>) -> Error {
        let level = self.name;
        match v {
            V::VertexInputs { count } => fail(
                format!(
                    "the vertex shader has {count} inputs, over the {level} limit of {}",
                    self.max_vertex_attributes
                ),
                None,
                "",
                self.note("max_vertex_attributes", self.max_vertex_attributes),
            ),
            V::ColorLocation { location } => fail(
                format!(
                    "color output @location({location}) is beyond the {level} limit of {} color attachments",
                    self.max_color_attachments
                ),
                None,
                "",
                self.note("max_color_attachments", self.max_color_attachments),
            ),
            V::WorkgroupAxis { size, axis } => {
                let max = self.max_compute_workgroup_size[axis];
                fail(
                    format!(
                        "workgroup size {} is {} along {}, over the {level} limit of {max}",
                        fmt_size(size),
                        size[axis],
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
                )
            }
            V::WorkgroupInvocations { size, total } => fail(
                format!(
                    "workgroup size {} is {total} invocations, over the {level} limit of {}",
                    fmt_size(size),
                    self.max_compute_invocations_per_workgroup
                ),
                None,
                "",
                self.note("max_compute_invocations_per_workgroup", self.max_compute_invocations_per_workgroup),
            ),
            V::EntryName { .. }
            | V::Duplicate { .. }
            | V::StorageSize { .. }
            | V::VertexLocation { .. }
            | V::ColorOutputs { .. }
            | V::WorkgroupZero { .. }
            | V::NoWorkgroupSize
            | V::BindGroup { .. }
            | V::BindingNumber { .. }
            | V::VertexStorage { .. }
            | V::UniformSize { .. }
            | V::TooMany { .. } => unreachable!("filtered out by `check` or worded by `word_binding`"),
        }
    }

    /// The workgroup variables the compute entry point uses against
    /// `max_compute_workgroup_storage_size`, pointing at the variable that crosses it.
    fn check_workgroup_storage(&self, module: &naga::Module, info: &naga::valid::ModuleInfo) -> Result<(), Error> {
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
                    "workgroup variables take {total} bytes up to `{name}`, over the {} limit of {} bytes",
                    self.name, self.max_compute_workgroup_storage_size
                ),
            );
            if let Some(r) = module.global_variables.get_span(h).to_range() {
                e.labels.push((r, "the limit is crossed here".into()));
            }
            e.notes.push(self.note("max_compute_workgroup_storage_size", self.max_compute_workgroup_storage_size));
            return Err(e);
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
