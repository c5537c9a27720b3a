//! Reflection of the (only) entry point of a validated module into the archive's types.

use crate::archive::{
    Binding, BindingKind, ColorOutput, NumericType, Reflection, SampleKind, ScalarKind, Stage, StorageAccess,
    TextureDim, VertexInput,
};

/// The interface of entry point 0 of `module`: the resources it uses (and only those),
/// its vertex inputs, color outputs and workgroup size.
pub fn reflect(module: &naga::Module, info: &naga::valid::ModuleInfo) -> Reflection {
    let ep = &module.entry_points[0];
    let uses = info.get_entry_point(0);
    let stage = match ep.stage {
        naga::ShaderStage::Vertex => Stage::Vertex,
        naga::ShaderStage::Fragment => Stage::Fragment,
        _ => Stage::Compute,
    };
    let mut bindings = Vec::new();
    for (h, g) in module.global_variables.iter() {
        let Some(rb) = &g.binding else { continue };
        if uses[h].is_empty() {
            continue;
        }
        if let Some(kind) = binding_kind(module, g) {
            bindings.push(Binding { group: rb.group, binding: rb.binding, name: g.name.clone(), kind });
        }
    }
    bindings.sort_by_key(|b| (b.group, b.binding));

    let mut vertex_inputs = Vec::new();
    if stage == Stage::Vertex {
        for arg in &ep.function.arguments {
            locations(module, arg.ty, arg.binding.as_ref(), arg.name.as_deref(), &mut |location, name, ty| {
                vertex_inputs.push(VertexInput { location, name, ty });
            });
        }
        vertex_inputs.sort_by_key(|v| v.location);
    }
    let mut color_outputs = Vec::new();
    if stage == Stage::Fragment {
        if let Some(result) = &ep.function.result {
            locations(module, result.ty, result.binding.as_ref(), None, &mut |location, _, ty| {
                color_outputs.push(ColorOutput { location, ty });
            });
        }
        color_outputs.sort_by_key(|c| c.location);
        color_outputs.dedup_by_key(|c| c.location); // dual-source blending: two outputs at 0
    }
    let workgroup_size = (stage == Stage::Compute).then_some(ep.workgroup_size);
    Reflection { entry: ep.name.clone(), stage, bindings, vertex_inputs, color_outputs, workgroup_size }
}

/// Calls `f` for every `@location` of a value of type `ty` with binding `binding`, looking
/// into struct members.
fn locations(
    module: &naga::Module,
    ty: naga::Handle<naga::Type>,
    binding: Option<&naga::Binding>,
    name: Option<&str>,
    f: &mut dyn FnMut(u32, Option<String>, NumericType),
) {
    match binding {
        Some(naga::Binding::Location { location, .. }) => {
            if let Some(t) = numeric(&module.types[ty].inner) {
                f(*location, name.map(str::to_string), t);
            }
        }
        Some(naga::Binding::BuiltIn(_)) => {}
        None => {
            if let naga::TypeInner::Struct { members, .. } = &module.types[ty].inner {
                for m in members {
                    locations(module, m.ty, m.binding.as_ref(), m.name.as_deref(), f);
                }
            }
        }
    }
}

fn numeric(inner: &naga::TypeInner) -> Option<NumericType> {
    let (scalar, components) = match *inner {
        naga::TypeInner::Scalar(s) => (s, 1),
        naga::TypeInner::Vector { size, scalar } => (scalar, size as u8),
        _ => return None,
    };
    let kind = match scalar.kind {
        naga::ScalarKind::Sint | naga::ScalarKind::AbstractInt => ScalarKind::Sint,
        naga::ScalarKind::Uint => ScalarKind::Uint,
        naga::ScalarKind::Float | naga::ScalarKind::AbstractFloat => ScalarKind::Float,
        naga::ScalarKind::Bool => ScalarKind::Bool,
    };
    Some(NumericType { scalar: kind, width: scalar.width, components })
}

fn binding_kind(module: &naga::Module, g: &naga::GlobalVariable) -> Option<BindingKind> {
    let size = || module.types[g.ty].inner.try_size(module.to_ctx()).unwrap_or(0) as u64;
    match g.space {
        naga::AddressSpace::Uniform => Some(BindingKind::UniformBuffer { min_size: size() }),
        naga::AddressSpace::Storage { access } => Some(BindingKind::StorageBuffer {
            read_only: !access.contains(naga::StorageAccess::STORE),
            min_size: size(),
        }),
        naga::AddressSpace::Handle => {
            let mut inner = &module.types[g.ty].inner;
            if let naga::TypeInner::BindingArray { base, .. } = *inner {
                inner = &module.types[base].inner;
            }
            match *inner {
                naga::TypeInner::Sampler { comparison } => Some(BindingKind::Sampler { comparison }),
                naga::TypeInner::Image { dim, arrayed, class } => {
                    let dim = match (dim, arrayed) {
                        (naga::ImageDimension::D1, _) => TextureDim::D1,
                        (naga::ImageDimension::D2, false) => TextureDim::D2,
                        (naga::ImageDimension::D2, true) => TextureDim::D2Array,
                        (naga::ImageDimension::Cube, false) => TextureDim::Cube,
                        (naga::ImageDimension::Cube, true) => TextureDim::CubeArray,
                        (naga::ImageDimension::D3, _) => TextureDim::D3,
                    };
                    match class {
                        naga::ImageClass::Sampled { kind, multi } => Some(BindingKind::Texture {
                            dim,
                            sample: match kind {
                                naga::ScalarKind::Sint => SampleKind::Sint,
                                naga::ScalarKind::Uint => SampleKind::Uint,
                                _ => SampleKind::Float,
                            },
                            multisampled: multi,
                        }),
                        naga::ImageClass::Depth { multi } => {
                            Some(BindingKind::Texture { dim, sample: SampleKind::Depth, multisampled: multi })
                        }
                        naga::ImageClass::Storage { format, access } => Some(BindingKind::StorageTexture {
                            dim,
                            format: format!("{format:?}").to_ascii_lowercase(),
                            access: match (
                                access.contains(naga::StorageAccess::LOAD),
                                access.contains(naga::StorageAccess::STORE),
                            ) {
                                (true, true) => StorageAccess::ReadWrite,
                                (true, false) => StorageAccess::ReadOnly,
                                _ => StorageAccess::WriteOnly,
                            },
                        }),
                        naga::ImageClass::External => {
                            Some(BindingKind::Texture { dim, sample: SampleKind::Float, multisampled: false })
                        }
                    }
                }
                _ => None,
            }
        }
        _ => None,
    }
}
