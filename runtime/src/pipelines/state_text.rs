//! The render state's text (`state_text`, one word of a usage file and of an archive's
//! pipeline manifest) read back into a [`RenderState`], so that a recorded pipeline can be
//! created again without the frame that asked for it.
//!
//! wgpu's enums are read by comparing the text with the `compact(Debug)` text of each
//! candidate value, the way `state_text` writes them, so that reading and writing cannot
//! disagree on a name; structs (`BlendState`, `StencilState`) are split into their fields the
//! same way. Unknown text is a [`StateTextError`] naming the field, never a panic, and a text
//! that parses but does not write back to itself (a number with a leading zero, say) is one
//! too, so that a parsed state is the key the recording had.

use std::fmt::Debug;

use super::usage::{compact, state_text};
use super::{ColorTarget, DepthState, RenderState, VertexBuffer, VertexLayout};

/// Text that is not the state text of any render state.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("render state text `{text}`: field `{field}`: {message}")]
pub struct StateTextError {
    /// The field that could not be read (`topology`, `cull`, `depth`, `stencil`, `color`,
    /// `samples`, `vertex`, or a part of one such as `color.blend`).
    pub field: &'static str,
    /// What was wrong with it.
    pub message: String,
    /// The whole text.
    pub text: String,
}

type Parsed<T> = Result<T, (&'static str, String)>;

use wgpu::{
    BlendFactor as Bf, BlendOperation as Bo, CompareFunction as Cf, PrimitiveTopology as Pt, StencilOperation as So,
    TextureFormat as Tf, VertexFormat as Vf,
};

const TOPOLOGIES: &[Pt] = &[Pt::PointList, Pt::LineList, Pt::LineStrip, Pt::TriangleList, Pt::TriangleStrip];
const FACES: &[wgpu::Face] = &[wgpu::Face::Front, wgpu::Face::Back];
const COMPARES: &[Cf] =
    &[Cf::Never, Cf::Less, Cf::Equal, Cf::LessEqual, Cf::Greater, Cf::NotEqual, Cf::GreaterEqual, Cf::Always];
const STENCIL_OPS: &[So] = &[
    So::Keep,
    So::Zero,
    So::Replace,
    So::Invert,
    So::IncrementClamp,
    So::DecrementClamp,
    So::IncrementWrap,
    So::DecrementWrap,
];
const BLEND_FACTORS: &[Bf] = &[
    Bf::Zero,
    Bf::One,
    Bf::Src,
    Bf::OneMinusSrc,
    Bf::SrcAlpha,
    Bf::OneMinusSrcAlpha,
    Bf::Dst,
    Bf::OneMinusDst,
    Bf::DstAlpha,
    Bf::OneMinusDstAlpha,
    Bf::SrcAlphaSaturated,
    Bf::Constant,
    Bf::OneMinusConstant,
    Bf::Src1,
    Bf::OneMinusSrc1,
    Bf::Src1Alpha,
    Bf::OneMinusSrc1Alpha,
];
const BLEND_OPS: &[Bo] = &[Bo::Add, Bo::Subtract, Bo::ReverseSubtract, Bo::Min, Bo::Max];
const STEP_MODES: &[wgpu::VertexStepMode] = &[wgpu::VertexStepMode::Vertex, wgpu::VertexStepMode::Instance];
/// Every format a render pipeline can name as a color or depth target: the uncompressed
/// ones (block-compressed formats are never attachments).
const FORMATS: &[Tf] = &[
    Tf::R8Unorm,
    Tf::R8Snorm,
    Tf::R8Uint,
    Tf::R8Sint,
    Tf::R16Uint,
    Tf::R16Sint,
    Tf::R16Unorm,
    Tf::R16Snorm,
    Tf::R16Float,
    Tf::Rg8Unorm,
    Tf::Rg8Snorm,
    Tf::Rg8Uint,
    Tf::Rg8Sint,
    Tf::R32Uint,
    Tf::R32Sint,
    Tf::R32Float,
    Tf::Rg16Uint,
    Tf::Rg16Sint,
    Tf::Rg16Unorm,
    Tf::Rg16Snorm,
    Tf::Rg16Float,
    Tf::Rgba8Unorm,
    Tf::Rgba8UnormSrgb,
    Tf::Rgba8Snorm,
    Tf::Rgba8Uint,
    Tf::Rgba8Sint,
    Tf::Bgra8Unorm,
    Tf::Bgra8UnormSrgb,
    Tf::Rgb9e5Ufloat,
    Tf::Rgb10a2Uint,
    Tf::Rgb10a2Unorm,
    Tf::Rg11b10Ufloat,
    Tf::R64Uint,
    Tf::Rg32Uint,
    Tf::Rg32Sint,
    Tf::Rg32Float,
    Tf::Rgba16Uint,
    Tf::Rgba16Sint,
    Tf::Rgba16Unorm,
    Tf::Rgba16Snorm,
    Tf::Rgba16Float,
    Tf::Rgba32Uint,
    Tf::Rgba32Sint,
    Tf::Rgba32Float,
    Tf::Stencil8,
    Tf::Depth16Unorm,
    Tf::Depth24Plus,
    Tf::Depth24PlusStencil8,
    Tf::Depth32Float,
    Tf::Depth32FloatStencil8,
];
const VERTEX_FORMATS: &[Vf] = &[
    Vf::Uint8,
    Vf::Uint8x2,
    Vf::Uint8x4,
    Vf::Sint8,
    Vf::Sint8x2,
    Vf::Sint8x4,
    Vf::Unorm8,
    Vf::Unorm8x2,
    Vf::Unorm8x4,
    Vf::Snorm8,
    Vf::Snorm8x2,
    Vf::Snorm8x4,
    Vf::Uint16,
    Vf::Uint16x2,
    Vf::Uint16x4,
    Vf::Sint16,
    Vf::Sint16x2,
    Vf::Sint16x4,
    Vf::Unorm16,
    Vf::Unorm16x2,
    Vf::Unorm16x4,
    Vf::Snorm16,
    Vf::Snorm16x2,
    Vf::Snorm16x4,
    Vf::Float16,
    Vf::Float16x2,
    Vf::Float16x4,
    Vf::Float32,
    Vf::Float32x2,
    Vf::Float32x3,
    Vf::Float32x4,
    Vf::Uint32,
    Vf::Uint32x2,
    Vf::Uint32x3,
    Vf::Uint32x4,
    Vf::Sint32,
    Vf::Sint32x2,
    Vf::Sint32x3,
    Vf::Sint32x4,
    Vf::Float64,
    Vf::Float64x2,
    Vf::Float64x3,
    Vf::Float64x4,
    Vf::Unorm10_10_10_2,
    Vf::Unorm8x4Bgra,
];

/// The candidate whose `compact(Debug)` text is `text`.
fn pick<T: Debug + Copy>(field: &'static str, text: &str, candidates: &[T]) -> Parsed<T> {
    candidates.iter().copied().find(|c| compact(c) == text).ok_or_else(|| (field, format!("unknown value `{text}`")))
}

fn number<T: std::str::FromStr>(field: &'static str, text: &str) -> Parsed<T> {
    text.parse().map_err(|_| (field, format!("`{text}` is not a number")))
}

/// `text` split at each `sep` outside braces.
fn split_top(text: &str, sep: char) -> Vec<&str> {
    let (mut parts, mut depth, mut start) = (Vec::new(), 0i32, 0);
    for (i, c) in text.char_indices() {
        match c {
            '{' => depth += 1,
            '}' => depth -= 1,
            c if c == sep && depth == 0 => {
                parts.push(&text[start..i]);
                start = i + c.len_utf8();
            }
            _ => {}
        }
    }
    parts.push(&text[start..]);
    parts
}

/// The values of `Name{a:..,b:..}` (compact `Debug` of a struct), which must have exactly
/// the fields `names`, in order.
fn fields<'t, const N: usize>(
    field: &'static str,
    text: &'t str,
    name: &str,
    names: [&str; N],
) -> Parsed<[&'t str; N]> {
    let bad =
        || (field, format!("expected `{name}{{{}}}`, found `{text}`", names.map(|n| format!("{n}:..")).join(",")));
    let inner = text.strip_prefix(name).and_then(|t| t.strip_prefix('{')).and_then(|t| t.strip_suffix('}'));
    let parts = split_top(inner.ok_or_else(bad)?, ',');
    if parts.len() != N {
        return Err(bad());
    }
    let mut out = [""; N];
    for ((slot, part), want) in out.iter_mut().zip(parts).zip(names) {
        *slot = part.strip_prefix(want).and_then(|p| p.strip_prefix(':')).ok_or_else(bad)?;
    }
    Ok(out)
}

fn blend_component(text: &str) -> Parsed<wgpu::BlendComponent> {
    let [src, dst, op] = fields("color.blend", text, "BlendComponent", ["src_factor", "dst_factor", "operation"])?;
    Ok(wgpu::BlendComponent {
        src_factor: pick("color.blend", src, BLEND_FACTORS)?,
        dst_factor: pick("color.blend", dst, BLEND_FACTORS)?,
        operation: pick("color.blend", op, BLEND_OPS)?,
    })
}

fn color_target(text: &str) -> Parsed<ColorTarget> {
    let [format, blend, mask] = split_top(text, '/')[..] else {
        return Err(("color", format!("expected `FORMAT/BLEND/MASK`, found `{text}`")));
    };
    let blend = match blend {
        "-" => None,
        b => {
            let [color, alpha] = fields("color.blend", b, "BlendState", ["color", "alpha"])?;
            Some(wgpu::BlendState { color: blend_component(color)?, alpha: blend_component(alpha)? })
        }
    };
    let bits = mask
        .strip_prefix("0x")
        .and_then(|m| u32::from_str_radix(m, 16).ok())
        .ok_or_else(|| ("color.write_mask", format!("`{mask}` is not a hexadecimal mask")))?;
    let write_mask =
        wgpu::ColorWrites::from_bits(bits).ok_or_else(|| ("color.write_mask", format!("`{mask}` has unknown bits")))?;
    Ok(ColorTarget { format: pick("color.format", format, FORMATS)?, blend, write_mask })
}

fn depth(text: &str) -> Parsed<Option<DepthState>> {
    if text == "-" {
        return Ok(None);
    }
    let [format, write, compare, bias] = split_top(text, '/')[..] else {
        return Err(("depth", format!("expected `FORMAT/write|read/COMPARE/bias=B,S,C` or `-`, found `{text}`")));
    };
    let write = match write {
        "write" => true,
        "read" => false,
        w => return Err(("depth", format!("expected `write` or `read`, found `{w}`"))),
    };
    let [b, s, c] = bias.strip_prefix("bias=").map(|b| split_top(b, ',')).unwrap_or_default()[..] else {
        return Err(("depth.bias", format!("expected `bias=CONSTANT,SLOPE_BITS,CLAMP_BITS`, found `{bias}`")));
    };
    Ok(Some(DepthState {
        format: pick("depth.format", format, FORMATS)?,
        write,
        compare: pick("depth.compare", compare, COMPARES)?,
        bias: number("depth.bias", b)?,
        slope_scale_bits: number("depth.bias", s)?,
        clamp_bits: number("depth.bias", c)?,
    }))
}

fn stencil_face(text: &str) -> Parsed<wgpu::StencilFaceState> {
    let names = ["compare", "fail_op", "depth_fail_op", "pass_op"];
    let [compare, fail, depth_fail, pass] = fields("stencil", text, "StencilFaceState", names)?;
    Ok(wgpu::StencilFaceState {
        compare: pick("stencil", compare, COMPARES)?,
        fail_op: pick("stencil", fail, STENCIL_OPS)?,
        depth_fail_op: pick("stencil", depth_fail, STENCIL_OPS)?,
        pass_op: pick("stencil", pass, STENCIL_OPS)?,
    })
}

fn stencil(text: &str) -> Parsed<wgpu::StencilState> {
    let [front, back, read, write] =
        fields("stencil", text, "StencilState", ["front", "back", "read_mask", "write_mask"])?;
    Ok(wgpu::StencilState {
        front: stencil_face(front)?,
        back: stencil_face(back)?,
        read_mask: number("stencil", read)?,
        write_mask: number("stencil", write)?,
    })
}

/// One buffer: `STRIDE/STEP[/FORMAT@LOCATION+OFFSET]...`.
fn vertex_buffer(text: &str) -> Parsed<VertexBuffer> {
    let mut parts = text.split('/');
    let stride = number("vertex.stride", parts.next().unwrap_or_default())?;
    let step = parts.next().ok_or_else(|| ("vertex", format!("expected `STRIDE/STEP...`, found `{text}`")))?;
    let mut attributes = Vec::new();
    for a in parts {
        let bad = || ("vertex.attribute", format!("expected `FORMAT@LOCATION+OFFSET`, found `{a}`"));
        let (format, rest) = a.split_once('@').ok_or_else(bad)?;
        let (location, offset) = rest.split_once('+').ok_or_else(bad)?;
        attributes.push(wgpu::VertexAttribute {
            format: pick("vertex.format", format, VERTEX_FORMATS)?,
            offset: number("vertex.attribute", offset)?,
            shader_location: number("vertex.attribute", location)?,
        });
    }
    Ok(VertexBuffer { stride, step_mode: pick("vertex.step_mode", step, STEP_MODES)?, attributes: attributes.into() })
}

/// `name=VALUE` of `part`, or an error naming `field`.
fn value<'t>(field: &'static str, part: Option<&'t str>) -> Parsed<&'t str> {
    let prefix = format!("{field}=");
    match part {
        Some(p) => {
            p.strip_prefix(prefix.as_str()).ok_or_else(|| (field, format!("expected `{prefix}...`, found `{p}`")))
        }
        None => Err((field, "missing".to_string())),
    }
}

/// Every field of `text`, in `state_text`'s order.
fn parse(text: &str) -> Parsed<RenderState> {
    let mut parts = text.split(';').peekable();
    let topology = pick("topology", parts.next().unwrap_or_default(), TOPOLOGIES)?;
    let cull_mode = match value("cull", parts.next())? {
        "-" => None,
        c => Some(pick("cull", c, FACES)?),
    };
    let depth = depth(value("depth", parts.next())?)?;
    let stencil = match parts.peek() {
        Some(p) if p.starts_with("stencil=") => stencil(value("stencil", parts.next())?)?,
        _ => wgpu::StencilState::default(),
    };
    let colors = value("color", parts.next())?;
    let color_targets = match colors {
        "" => Vec::new(),
        c => split_top(c, ',').into_iter().map(color_target).collect::<Parsed<_>>()?,
    };
    let sample_count = number("samples", value("samples", parts.next())?)?;
    let buffers = match value("vertex", parts.next())? {
        "" => Vec::new(),
        v => v.split(',').map(vertex_buffer).collect::<Parsed<_>>()?,
    };
    if let Some(rest) = parts.next() {
        return Err(("vertex", format!("unexpected `;{rest}` after the last field")));
    }
    let state = RenderState {
        vertex_layout: VertexLayout::new(buffers),
        topology,
        cull_mode,
        depth,
        stencil,
        color_targets,
        sample_count,
    };
    if state_text(&state) != text {
        return Err((
            "text",
            format!("reads as `{}`, not as itself (a number not in its shortest form?)", state_text(&state)),
        ));
    }
    Ok(state)
}

impl RenderState {
    /// The state whose `state_text` is `text`: the inverse of the text a usage file and an
    /// archive's pipeline manifest hold. Unknown or malformed text is an error naming the
    /// field.
    pub fn from_state_text(text: &str) -> Result<RenderState, StateTextError> {
        parse(text).map_err(|(field, message)| StateTextError { field, message, text: text.to_string() })
    }
}

#[cfg(test)]
mod tests {
    use super::super::Blend;
    use super::*;

    #[test]
    fn every_field_round_trips() {
        const ATTRS: [wgpu::VertexAttribute; 2] = wgpu::vertex_attr_array![0 => Float32x3, 1 => Unorm8x4Bgra];
        let layout = VertexLayout::new(vec![
            VertexBuffer::new(16, wgpu::VertexStepMode::Vertex, &ATTRS),
            VertexBuffer::new(0, wgpu::VertexStepMode::Instance, &[]),
        ]);
        let face = wgpu::StencilFaceState {
            compare: Cf::NotEqual,
            fail_op: So::IncrementWrap,
            depth_fail_op: So::Zero,
            pass_op: So::Replace,
        };
        let mut state = RenderState::triangles(layout)
            .with_depth(DepthState {
                bias: -3,
                slope_scale_bits: 1.5f32.to_bits(),
                ..DepthState::reverse_z(Tf::Depth24PlusStencil8, false)
            })
            .with_stencil(wgpu::StencilState { front: face, back: Default::default(), read_mask: 0xff, write_mask: 7 })
            .with_targets(&[
                ColorTarget::new(Tf::Rgba16Float, Blend::Additive),
                ColorTarget::new(Tf::Bgra8UnormSrgb, Blend::PremultipliedAlpha).with_write_mask(wgpu::ColorWrites::RED),
                ColorTarget::new(Tf::R32Uint, Blend::Replace),
            ])
            .with_cull(Some(wgpu::Face::Front))
            .with_samples(4);
        state.topology = Pt::LineStrip;
        let text = state_text(&state);
        assert_eq!(RenderState::from_state_text(&text).unwrap(), state, "{text}");
        let plain = RenderState::fullscreen(ColorTarget::new(Tf::Rgba8Unorm, Blend::Replace)).with_targets(&[]);
        assert_eq!(RenderState::from_state_text(&state_text(&plain)).unwrap(), plain);
    }

    #[test]
    fn malformed_text_is_an_error_naming_the_field() {
        let good = "TriangleList;cull=Back;depth=Depth32Float/write/GreaterEqual/bias=0,0,0;color=Rgba16Float/-/0xf;samples=1;vertex=12/Vertex/Float32x3@0+0";
        assert!(RenderState::from_state_text(good).is_ok());
        for (text, field) in [
            ("", "topology"),
            ("Triangles;cull=Back", "topology"),
            ("TriangleList", "cull"),
            ("TriangleList;cull=Sideways;depth=-;color=;samples=1;vertex=", "cull"),
            ("TriangleList;cull=-;depth=Depth99/write/Less/bias=0,0,0;color=;samples=1;vertex=", "depth.format"),
            ("TriangleList;cull=-;depth=Depth32Float/rw/Less/bias=0,0,0;color=;samples=1;vertex=", "depth"),
            ("TriangleList;cull=-;depth=Depth32Float/write/Less/bias=0,0;color=;samples=1;vertex=", "depth.bias"),
            ("TriangleList;cull=-;depth=-;stencil=StencilState{};color=;samples=1;vertex=", "stencil"),
            ("TriangleList;cull=-;depth=-;color=Rgba8Unorm/-/0x100;samples=1;vertex=", "color.write_mask"),
            ("TriangleList;cull=-;depth=-;color=Rgba8Unorm/BlendState{color:x}/0xf;samples=1;vertex=", "color.blend"),
            ("TriangleList;cull=-;depth=-;color=Rgba8Unorm/-;samples=1;vertex=", "color"),
            ("TriangleList;cull=-;depth=-;color=;samples=x;vertex=", "samples"),
            ("TriangleList;cull=-;depth=-;color=;samples=01;vertex=", "text"),
            ("TriangleList;cull=-;depth=-;color=;samples=1;vertex=12/Sideways", "vertex.step_mode"),
            ("TriangleList;cull=-;depth=-;color=;samples=1;vertex=12/Vertex/Float32x3@0", "vertex.attribute"),
            ("TriangleList;cull=-;depth=-;color=;samples=1;vertex=;more", "vertex"),
            ("TriangleList;cull=-;depth=-;color=;samples=1", "vertex"),
        ] {
            let e = RenderState::from_state_text(text).unwrap_err();
            assert_eq!(e.field, field, "{text}: {e}");
            assert!(e.to_string().contains(&format!("field `{field}`")), "{e}");
        }
    }
}
