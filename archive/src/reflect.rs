//! Reflection: what a compiled entry point expects from the pipeline that runs it, taken
//! from the validated naga module and stored in the archive so the runtime builds bind group
//! layouts and vertex layouts without parsing any shader.

use serde::{Deserialize, Serialize};

use super::Stage;

/// The interface of one entry point.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Reflection {
    /// The entry point's name.
    pub entry: String,
    pub stage: Stage,
    /// Every resource the entry point uses, sorted by (group, binding).
    pub bindings: Vec<Binding>,
    /// Vertex shader inputs with a `@location`, sorted by location (empty for other stages).
    pub vertex_inputs: Vec<VertexInput>,
    /// Fragment shader outputs with a `@location`, sorted by location.
    pub color_outputs: Vec<ColorOutput>,
    /// `@workgroup_size` of a compute entry point.
    pub workgroup_size: Option<[u32; 3]>,
}

/// One `@group(g) @binding(b)` resource.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Binding {
    pub group: u32,
    pub binding: u32,
    /// The global variable's name in the source, where it has one.
    pub name: Option<String>,
    pub kind: BindingKind,
}

#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum BindingKind {
    /// `var<uniform>`; `min_size` is the size of the bound type in bytes.
    UniformBuffer {
        min_size: u64,
    },
    /// `var<storage, read>` or `var<storage, read_write>`; for a runtime-sized array the
    /// size of the fixed part plus one element.
    StorageBuffer {
        read_only: bool,
        min_size: u64,
    },
    Sampler {
        comparison: bool,
    },
    /// A sampled texture (`texture_2d<f32>`, `texture_depth_2d`, ...).
    Texture {
        dim: TextureDim,
        sample: SampleKind,
        multisampled: bool,
    },
    /// A storage texture; `format` is the WGSL texel format name (`rgba16float`).
    StorageTexture {
        dim: TextureDim,
        format: String,
        access: StorageAccess,
    },
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TextureDim {
    D1,
    D2,
    D2Array,
    Cube,
    CubeArray,
    D3,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SampleKind {
    Float,
    Depth,
    Sint,
    Uint,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StorageAccess {
    ReadOnly,
    WriteOnly,
    ReadWrite,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ScalarKind {
    Float,
    Sint,
    Uint,
    Bool,
}

/// A scalar or vector type: `vec3<f32>` is `{ scalar: Float, width: 4, components: 3 }`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct NumericType {
    pub scalar: ScalarKind,
    /// Bytes per component.
    pub width: u8,
    /// 1 for a scalar, 2 to 4 for a vector.
    pub components: u8,
}

#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct VertexInput {
    pub location: u32,
    pub name: Option<String>,
    pub ty: NumericType,
}

#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct ColorOutput {
    pub location: u32,
    pub ty: NumericType,
}
