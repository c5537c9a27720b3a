//! Pipelines of the desktop frame: the passes describe their render pipelines with the
//! frames' one [`PipelineDesc`] and hold them as slots ([`RenderSlot`], [`ComputeSlot`]):
//! keys into the runtime's one [`PipelineCache`], asked for when a draw is recorded.

use std::sync::Arc;

use crate::frame::{ComputeSlot, Creation, PipelineDesc, RenderSlot, Slots};
use crate::pipelines::{PipelineCache, PipelineError, PipelineLayoutInfo};

use super::DesktopError;

/// Bind groups by resource name ([`crate::frame::bind_groups`]) for a desktop pass, their
/// errors worded as the desktop frame's.
pub trait DesktopLayout {
    /// Bind groups for every group the pipeline uses, from one resource list.
    fn bind_groups(
        &self,
        device: &wgpu::Device,
        resources: &[(&str, wgpu::BindingResource<'_>)],
    ) -> Result<BindGroups, DesktopError>;
}

impl DesktopLayout for PipelineLayoutInfo {
    fn bind_groups(
        &self,
        device: &wgpu::Device,
        resources: &[(&str, wgpu::BindingResource<'_>)],
    ) -> Result<BindGroups, DesktopError> {
        match crate::frame::bind_groups(device, self, resources) {
            Ok(groups) => Ok(BindGroups { groups, keep: Vec::new() }),
            Err(PipelineError::MissingResource { label, group, binding, name }) => {
                Err(DesktopError::MissingResource { pipeline: label, group, binding, name })
            }
            Err(PipelineError::Wgpu { what, message }) => Err(DesktopError::Wgpu { what, message }),
            Err(e) => Err(e.into()),
        }
    }
}

/// The bind groups of one draw or dispatch, by group index (`None` for unused groups), and
/// the buffers made for them alone (kept alive as long as the groups).
pub struct BindGroups {
    pub groups: Vec<Option<wgpu::BindGroup>>,
    pub keep: Vec<wgpu::Buffer>,
}

impl BindGroups {
    /// Keeps `buffer` (a uniform made for these groups) alive with them.
    pub fn keeping(mut self, buffer: wgpu::Buffer) -> BindGroups {
        self.keep.push(buffer);
        self
    }

    pub fn set_render(&self, pass: &mut wgpu::RenderPass<'_>) {
        for (i, g) in self.groups.iter().enumerate() {
            if let Some(g) = g {
                pass.set_bind_group(i as u32, g, &[]);
            }
        }
    }

    pub fn set_compute(&self, pass: &mut wgpu::ComputePass<'_>) {
        for (i, g) in self.groups.iter().enumerate() {
            if let Some(g) = g {
                pass.set_bind_group(i as u32, g, &[]);
            }
        }
    }
}

/// The desktop frame's view of the runtime's one pipeline cache while its passes are built:
/// slots at the frame's level, created as the frame's options say.
pub struct Pipelines<'a> {
    pub cache: &'a PipelineCache,
    pub level: &'a str,
    pub creation: Creation,
}

impl<'a> Pipelines<'a> {
    pub fn new(cache: &'a PipelineCache, level: &'a str, creation: Creation) -> Pipelines<'a> {
        Pipelines { cache, level, creation }
    }

    /// The cache and the frame's creation, for passes that describe their state in the
    /// runtime's terms.
    pub fn slots(&self) -> Slots<'a> {
        Slots::new(self.cache, self.creation)
    }

    /// The frame's level, for typed permutation keys ([`crate::keys`]).
    pub fn key_level(&self) -> Result<crate::keys::Level, crate::shaders::LookupError> {
        crate::keys::level(self.level)
    }

    /// The slot of the render pipeline `desc` describes.
    pub fn render(&self, desc: &PipelineDesc) -> Result<Arc<RenderSlot>, DesktopError> {
        Ok(self.slots().render_desc(desc)?)
    }

    /// The slot of compute permutation `name`.
    pub fn compute(&self, name: &str) -> Result<Arc<ComputeSlot>, DesktopError> {
        Ok(self.slots().compute(name)?)
    }
}

/// Blend states the desktop passes use beyond replace.
pub mod blend {
    use wgpu::{BlendComponent, BlendFactor as F, BlendOperation as Op, BlendState};

    const fn component(src: F, dst: F, operation: Op) -> BlendComponent {
        BlendComponent { src_factor: src, dst_factor: dst, operation }
    }

    /// dst + src: lights accumulating into SceneColor, bloom levels.
    pub const ADDITIVE: BlendState =
        BlendState { color: component(F::One, F::One, Op::Add), alpha: component(F::Zero, F::One, Op::Add) };
    /// min(dst, src): several shadow projections of one light into the shadow mask.
    pub const MIN: BlendState =
        BlendState { color: component(F::One, F::One, Op::Min), alpha: component(F::One, F::One, Op::Min) };
    /// dst * src: ambient occlusion applied to SceneColor.
    pub const MULTIPLY: BlendState =
        BlendState { color: component(F::Zero, F::Src, Op::Add), alpha: component(F::Zero, F::One, Op::Add) };
    /// dst * src.a + src.rgb: height fog (inscattering, transmittance) and the separate
    /// translucency composite (premultiplied color, transmittance).
    pub const TRANSMITTANCE: BlendState =
        BlendState { color: component(F::One, F::SrcAlpha, Op::Add), alpha: component(F::Zero, F::One, Op::Add) };
    /// Premultiplied "over" for color; alpha keeps the transmittance of what lies behind:
    /// a = dst.a * (1 - src.a). Translucent surfaces into the separate translucency target.
    pub const TRANSLUCENT: BlendState = BlendState {
        color: component(F::One, F::OneMinusSrcAlpha, Op::Add),
        alpha: component(F::Zero, F::OneMinusSrcAlpha, Op::Add),
    };
}
