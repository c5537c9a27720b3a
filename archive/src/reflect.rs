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
    /// The entry point's stage.
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
    /// Its `@group`.
    pub group: u32,
    /// Its `@binding`.
    pub binding: u32,
    /// The global variable's name in the source, where it has one.
    pub name: Option<String>,
    /// What is bound there.
    pub kind: BindingKind,
}

/// What a binding holds, with what a bind group layout entry needs.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum BindingKind {
    /// `var<uniform>`; `min_size` is the size of the bound type in bytes.
    UniformBuffer {
        /// The size of the bound type in bytes.
        min_size: u64,
    },
    /// `var<storage, read>` or `var<storage, read_write>`; for a runtime-sized array the
    /// size of the fixed part plus one element.
    StorageBuffer {
        /// `var<storage, read>`.
        read_only: bool,
        /// The minimum binding size in bytes.
        min_size: u64,
    },
    /// A sampler.
    Sampler {
        /// A comparison sampler (`sampler_comparison`).
        comparison: bool,
    },
    /// A sampled texture (`texture_2d<f32>`, `texture_depth_2d`, ...).
    Texture {
        /// Its dimension.
        dim: TextureDim,
        /// What sampling it returns.
        sample: SampleKind,
        /// A multisampled texture.
        multisampled: bool,
    },
    /// A storage texture; `format` is the WGSL texel format name (`rgba16float`).
    StorageTexture {
        /// Its dimension.
        dim: TextureDim,
        /// The WGSL texel format name.
        format: String,
        /// How the shader accesses it.
        access: StorageAccess,
    },
}

/// A texture's dimension, as WGSL names them.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TextureDim {
    /// `texture_1d`.
    D1,
    /// `texture_2d`.
    D2,
    /// `texture_2d_array`.
    D2Array,
    /// `texture_cube`.
    Cube,
    /// `texture_cube_array`.
    CubeArray,
    /// `texture_3d`.
    D3,
}

/// What sampling a texture returns.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SampleKind {
    /// Floating point (`texture_2d<f32>`).
    Float,
    /// Depth (`texture_depth_2d`).
    Depth,
    /// Signed integers.
    Sint,
    /// Unsigned integers.
    Uint,
}

/// How a shader accesses a storage texture.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StorageAccess {
    /// `read`.
    ReadOnly,
    /// `write`.
    WriteOnly,
    /// `read_write`.
    ReadWrite,
}

/// The scalar of a numeric type.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ScalarKind {
    /// `f32` (or `f16`).
    Float,
    /// `i32`.
    Sint,
    /// `u32`.
    Uint,
    /// `bool`.
    Bool,
}

/// A scalar or vector type: `vec3<f32>` is `{ scalar: Float, width: 4, components: 3 }`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct NumericType {
    /// Its scalar kind.
    pub scalar: ScalarKind,
    /// Bytes per component.
    pub width: u8,
    /// 1 for a scalar, 2 to 4 for a vector.
    pub components: u8,
}

/// A vertex shader input.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct VertexInput {
    /// Its `@location`.
    pub location: u32,
    /// The argument's or member's name, where it has one.
    pub name: Option<String>,
    /// Its type.
    pub ty: NumericType,
}

/// A fragment shader output.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct ColorOutput {
    /// Its `@location`: the color attachment it writes.
    pub location: u32,
    /// Its type.
    pub ty: NumericType,
}
