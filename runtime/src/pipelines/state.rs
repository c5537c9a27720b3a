//! Fixed-function state and the keys of the pipeline cache: owned, hashable copies of
//! wgpu's descriptors.

use std::borrow::Cow;

/// One vertex buffer of a [`VertexLayout`]: stride, step mode and attributes, in wgpu's terms
/// but owned and hashable, so that a pipeline key can hold it.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct VertexBuffer {
    /// Bytes from one element to the next.
    pub stride: u64,
    /// Per vertex or per instance.
    pub step_mode: wgpu::VertexStepMode,
    /// The attributes read from each element, with their shader locations.
    pub attributes: Cow<'static, [wgpu::VertexAttribute]>,
}

impl VertexBuffer {
    /// A buffer described at compile time (`wgpu::vertex_attr_array!` in a `const`).
    pub const fn new(
        stride: u64,
        step_mode: wgpu::VertexStepMode,
        attributes: &'static [wgpu::VertexAttribute],
    ) -> VertexBuffer {
        VertexBuffer { stride, step_mode, attributes: Cow::Borrowed(attributes) }
    }

    /// The buffer a `wgpu::VertexBufferLayout` describes.
    pub fn from_wgpu(layout: &wgpu::VertexBufferLayout<'_>) -> VertexBuffer {
        VertexBuffer {
            stride: layout.array_stride,
            step_mode: layout.step_mode,
            attributes: Cow::Owned(layout.attributes.to_vec()),
        }
    }

    /// The same buffer as wgpu describes it.
    pub fn wgpu(&self) -> wgpu::VertexBufferLayout<'_> {
        wgpu::VertexBufferLayout { array_stride: self.stride, step_mode: self.step_mode, attributes: &self.attributes }
    }
}

/// The vertex buffers a render pipeline reads, in slot order, as the application describes
/// them (the runtime knows no vertex format of its own). Every vertex input of the vertex
/// shader's reflection must be provided by one attribute of the same size, or pipeline
/// creation is an error naming the location (`PipelineError::VertexInput`).
#[derive(Clone, Debug, Default, PartialEq, Eq, Hash)]
pub struct VertexLayout {
    buffers: Cow<'static, [VertexBuffer]>,
}

impl VertexLayout {
    /// No vertex buffers (full-screen triangles from the vertex index, or vertices pulled
    /// from storage buffers).
    pub const NONE: VertexLayout = VertexLayout { buffers: Cow::Borrowed(&[]) };

    /// A layout described at compile time:
    /// `const BUFFERS: &[VertexBuffer] = &[...]; const MESH: VertexLayout = VertexLayout::from_static(BUFFERS);`.
    pub const fn from_static(buffers: &'static [VertexBuffer]) -> VertexLayout {
        VertexLayout { buffers: Cow::Borrowed(buffers) }
    }

    /// A layout of these buffers (slot `i` is `buffers[i]`).
    pub fn new(buffers: Vec<VertexBuffer>) -> VertexLayout {
        VertexLayout { buffers: Cow::Owned(buffers) }
    }

    /// The layout of these `wgpu::VertexBufferLayout`s (slot `i` is `layouts[i]`).
    pub fn from_wgpu(layouts: &[wgpu::VertexBufferLayout<'_>]) -> VertexLayout {
        VertexLayout::new(layouts.iter().map(VertexBuffer::from_wgpu).collect())
    }

    /// The buffers, in slot order.
    pub fn buffers(&self) -> &[VertexBuffer] {
        &self.buffers
    }

    /// The shader locations the layout provides, in slot order.
    pub fn locations(&self) -> Vec<u32> {
        self.buffers.iter().flat_map(|b| b.attributes.iter().map(|a| a.shader_location)).collect()
    }
}

/// How a color target blends.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Blend {
    /// No blending: the source replaces what is there.
    Replace,
    /// dst + src (lights accumulating into SceneColor).
    Additive,
    /// dst * (1 - src.a) + src (premultiplied translucency).
    PremultipliedAlpha,
    /// Any other blend state.
    State(wgpu::BlendState),
}

impl Blend {
    /// The wgpu blend state (`None` for [`Blend::Replace`]).
    pub fn state(self) -> Option<wgpu::BlendState> {
        match self {
            Blend::Replace => None,
            Blend::Additive => Some(wgpu::BlendState {
                color: wgpu::BlendComponent {
                    src_factor: wgpu::BlendFactor::One,
                    dst_factor: wgpu::BlendFactor::One,
                    operation: wgpu::BlendOperation::Add,
                },
                alpha: wgpu::BlendComponent {
                    src_factor: wgpu::BlendFactor::Zero,
                    dst_factor: wgpu::BlendFactor::One,
                    operation: wgpu::BlendOperation::Add,
                },
            }),
            Blend::PremultipliedAlpha => Some(wgpu::BlendState::PREMULTIPLIED_ALPHA_BLENDING),
            Blend::State(state) => Some(state),
        }
    }
}

/// A color target: format, blending (`None`: replace) and the channels written.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct ColorTarget {
    /// The attachment's format.
    pub format: wgpu::TextureFormat,
    /// How it blends (`None`: replace).
    pub blend: Option<wgpu::BlendState>,
    /// The channels written.
    pub write_mask: wgpu::ColorWrites,
}

impl ColorTarget {
    /// A target writing every channel.
    pub fn new(format: wgpu::TextureFormat, blend: Blend) -> ColorTarget {
        ColorTarget { format, blend: blend.state(), write_mask: wgpu::ColorWrites::ALL }
    }

    /// The same target writing only the channels of `mask`.
    pub fn with_write_mask(mut self, mask: wgpu::ColorWrites) -> ColorTarget {
        self.write_mask = mask;
        self
    }

    pub(super) fn wgpu(&self) -> wgpu::ColorTargetState {
        wgpu::ColorTargetState { format: self.format, blend: self.blend, write_mask: self.write_mask }
    }
}

impl From<&wgpu::ColorTargetState> for ColorTarget {
    fn from(t: &wgpu::ColorTargetState) -> ColorTarget {
        ColorTarget { format: t.format, blend: t.blend, write_mask: t.write_mask }
    }
}

/// Depth test, writes and bias. The bias floats are stored as bits so the state hashes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct DepthState {
    /// The depth attachment's format.
    pub format: wgpu::TextureFormat,
    /// Whether depth is written.
    pub write: bool,
    /// The depth test.
    pub compare: wgpu::CompareFunction,
    /// Constant depth bias (shadow depths).
    pub bias: i32,
    /// Slope-scaled bias, as `f32::to_bits`.
    pub slope_scale_bits: u32,
    /// Bias clamp, as `f32::to_bits`.
    pub clamp_bits: u32,
}

impl DepthState {
    /// Reverse-Z depth test (near = 1, far = 0).
    pub fn reverse_z(format: wgpu::TextureFormat, write: bool) -> DepthState {
        DepthState {
            format,
            write,
            compare: wgpu::CompareFunction::GreaterEqual,
            bias: 0,
            slope_scale_bits: 0,
            clamp_bits: 0,
        }
    }
}

/// The fixed-function state of a render pipeline: everything but the shaders. It is the
/// pipeline cache's key with the permutations ([`RenderKey`]), so it holds every piece of
/// state that changes the pipeline.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct RenderState {
    /// The vertex buffers read.
    pub vertex_layout: VertexLayout,
    /// How vertices make primitives.
    pub topology: wgpu::PrimitiveTopology,
    /// The faces culled (`None`: none).
    pub cull_mode: Option<wgpu::Face>,
    /// Depth test, writes and bias (`None`: no depth attachment).
    pub depth: Option<DepthState>,
    /// Stencil test and writes (needs a depth format with stencil).
    pub stencil: wgpu::StencilState,
    /// The color attachments, in order.
    pub color_targets: Vec<ColorTarget>,
    /// MSAA sample count of every attachment.
    pub sample_count: u32,
}

impl RenderState {
    /// Triangles from the vertex buffers of `vertex_layout`, back faces culled, no targets yet.
    pub fn triangles(vertex_layout: VertexLayout) -> RenderState {
        RenderState {
            vertex_layout,
            topology: wgpu::PrimitiveTopology::TriangleList,
            cull_mode: Some(wgpu::Face::Back),
            depth: None,
            stencil: wgpu::StencilState::default(),
            color_targets: Vec::new(),
            sample_count: 1,
        }
    }

    /// A full-screen triangle (no vertex buffers, no culling, no depth).
    pub fn fullscreen(target: ColorTarget) -> RenderState {
        RenderState {
            vertex_layout: VertexLayout::NONE,
            topology: wgpu::PrimitiveTopology::TriangleList,
            cull_mode: None,
            depth: None,
            stencil: wgpu::StencilState::default(),
            color_targets: vec![target],
            sample_count: 1,
        }
    }

    /// The state of triangles with this vertex layout, culling, wgpu depth-stencil state,
    /// targets and sample count (the frames describe their passes in wgpu's terms).
    pub fn from_wgpu(
        vertex_layout: VertexLayout,
        cull_mode: Option<wgpu::Face>,
        depth_stencil: Option<&wgpu::DepthStencilState>,
        targets: &[wgpu::ColorTargetState],
        sample_count: u32,
    ) -> RenderState {
        let depth = depth_stencil.map(|d| DepthState {
            format: d.format,
            write: d.depth_write_enabled.unwrap_or(false),
            compare: d.depth_compare.unwrap_or(wgpu::CompareFunction::Always),
            bias: d.bias.constant,
            slope_scale_bits: d.bias.slope_scale.to_bits(),
            clamp_bits: d.bias.clamp.to_bits(),
        });
        RenderState {
            vertex_layout,
            topology: wgpu::PrimitiveTopology::TriangleList,
            cull_mode,
            depth,
            stencil: depth_stencil.map(|d| d.stencil.clone()).unwrap_or_default(),
            color_targets: targets.iter().map(ColorTarget::from).collect(),
            sample_count,
        }
    }

    /// The same state with this depth test.
    pub fn with_depth(mut self, depth: DepthState) -> RenderState {
        self.depth = Some(depth);
        self
    }

    /// The same state with these color targets.
    pub fn with_targets(mut self, targets: &[ColorTarget]) -> RenderState {
        self.color_targets = targets.to_vec();
        self
    }

    /// The same state culling `cull` (`None`: no culling).
    pub fn with_cull(mut self, cull: Option<wgpu::Face>) -> RenderState {
        self.cull_mode = cull;
        self
    }

    /// The same state with this stencil test and writes.
    pub fn with_stencil(mut self, stencil: wgpu::StencilState) -> RenderState {
        self.stencil = stencil;
        self
    }

    /// MSAA sample count of every attachment.
    pub fn with_samples(mut self, count: u32) -> RenderState {
        self.sample_count = count;
        self
    }

    pub(super) fn depth_stencil(&self) -> Option<wgpu::DepthStencilState> {
        self.depth.map(|d| wgpu::DepthStencilState {
            format: d.format,
            depth_write_enabled: Some(d.write),
            depth_compare: Some(d.compare),
            stencil: self.stencil.clone(),
            bias: wgpu::DepthBiasState {
                constant: d.bias,
                slope_scale: f32::from_bits(d.slope_scale_bits),
                clamp: f32::from_bits(d.clamp_bits),
            },
        })
    }
}

/// The key of a render pipeline in the cache: its permutations and its whole fixed-function
/// state.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct RenderKey {
    /// The vertex permutation's canonical name.
    pub vertex: String,
    /// The fragment permutation's canonical name (`None`: depth only).
    pub fragment: Option<String>,
    /// Its fixed-function state.
    pub state: RenderState,
}

/// The key of a compute pipeline: its permutation (compute has no fixed-function state).
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct ComputeKey {
    /// The compute permutation's canonical name.
    pub compute: String,
}

/// A pipeline to create ahead of the first frame (`PipelineCache::warm_up`).
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub enum PipelineKey {
    /// A render pipeline.
    Render(RenderKey),
    /// A compute pipeline.
    Compute(ComputeKey),
}
