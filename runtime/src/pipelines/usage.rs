//! What the frames asked the cache for: every render and compute pipeline asked for through
//! [`PipelineCache::render_key`] or [`PipelineCache::compute_key`] (and the calls built on
//! them), whether the cache created it or found it, with how many frames asked for it and the
//! first frame that did. Frames are counted by the caller: [`PipelineCache::next_frame`]
//! after each frame; what is asked before the first call (a renderer that creates its
//! pipelines when it is built) belongs to frame 0. [`PipelineCache::warm_up`] is no frame's
//! use and is not recorded.
//!
//! [`PipelineCache::usage`] gives a [`Usage`]: canonical permutation names and the whole
//! key, the render state written without spaces (`state_text`), saved with
//! [`Usage::to_text`] (the format is described in `kiln_archive::usage`).

use std::collections::HashMap;
use std::fmt::Write as _;

use super::{ComputeKey, PipelineCache, RenderKey, RenderState, Usage, UsageKey, UseCount};

/// One pipeline's asks.
#[derive(Clone, Copy, Debug)]
struct Seen {
    frames: u64,
    first: u64,
    last: u64,
}

/// The asks so far, by key, and the current frame.
#[derive(Clone, Debug, Default)]
pub(super) struct Recorder {
    frame: u64,
    render: HashMap<RenderKey, Seen>,
    compute: HashMap<ComputeKey, Seen>,
}

fn seen(entry: Option<&mut Seen>, frame: u64) -> Option<Seen> {
    match entry {
        Some(s) => {
            if s.last != frame {
                s.frames += 1;
                s.last = frame;
            }
            None
        }
        None => Some(Seen { frames: 1, first: frame, last: frame }),
    }
}

impl Recorder {
    pub(super) fn render(&mut self, key: &RenderKey) {
        if let Some(s) = seen(self.render.get_mut(key), self.frame) {
            self.render.insert(key.clone(), s);
        }
    }

    pub(super) fn compute(&mut self, key: &ComputeKey) {
        if let Some(s) = seen(self.compute.get_mut(key), self.frame) {
            self.compute.insert(key.clone(), s);
        }
    }
}

impl PipelineCache {
    /// Ends the current frame: asks from now on count for the next one. Returns the new
    /// frame's number (the first frame is 0).
    pub fn next_frame(&self) -> u64 {
        let mut inner = self.lock();
        inner.recorder.frame += 1;
        inner.recorder.frame
    }

    /// The current frame's number.
    pub fn frame(&self) -> u64 {
        self.lock().recorder.frame
    }

    /// Every pipeline asked for so far, with the archive's content hash: one run.
    pub fn usage(&self) -> Usage {
        let mut usage = Usage::new(self.archive.archive().content_hash());
        let inner = self.lock();
        let count = |s: &Seen| UseCount { frames: s.frames, first_frame: s.first };
        for (k, s) in &inner.recorder.render {
            let key = UsageKey::Render {
                vertex: k.vertex.clone(),
                fragment: k.fragment.clone(),
                state: state_text(&k.state),
            };
            usage.records.insert(key, count(s));
        }
        for (k, s) in &inner.recorder.compute {
            usage.records.insert(UsageKey::Compute { compute: k.compute.clone() }, count(s));
        }
        usage
    }
}

/// `{:?}` without spaces.
pub(super) fn compact(v: impl std::fmt::Debug) -> String {
    format!("{v:?}").replace(' ', "")
}

/// A render state as one word: every field of the key, `;`-separated, `-` for none.
pub fn state_text(s: &RenderState) -> String {
    let mut out = compact(s.topology);
    let _ = write!(out, ";cull={}", s.cull_mode.map_or("-".to_string(), compact));
    match &s.depth {
        Some(d) => {
            let _ = write!(
                out,
                ";depth={}/{}/{}/bias={},{},{}",
                compact(d.format),
                if d.write { "write" } else { "read" },
                compact(d.compare),
                d.bias,
                d.slope_scale_bits,
                d.clamp_bits
            );
        }
        None => out.push_str(";depth=-"),
    }
    if s.stencil != wgpu::StencilState::default() {
        let _ = write!(out, ";stencil={}", compact(&s.stencil));
    }
    out.push_str(";color=");
    for (i, t) in s.color_targets.iter().enumerate() {
        let blend = t.blend.map_or("-".to_string(), compact);
        let _ = write!(out, "{}{}/{blend}/{:#x}", if i > 0 { "," } else { "" }, compact(t.format), t.write_mask.bits());
    }
    let _ = write!(out, ";samples={};vertex=", s.sample_count);
    for (i, b) in s.vertex_layout.buffers().iter().enumerate() {
        let _ = write!(out, "{}{}/{}", if i > 0 { "," } else { "" }, b.stride, compact(b.step_mode));
        for a in b.attributes.iter() {
            let _ = write!(out, "/{}@{}+{}", compact(a.format), a.shader_location, a.offset);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::super::{Blend, ColorTarget, DepthState, VertexBuffer, VertexLayout};
    use super::*;

    #[test]
    fn a_render_state_is_one_word_naming_every_field() {
        const ATTRS: [wgpu::VertexAttribute; 1] =
            [wgpu::VertexAttribute { format: wgpu::VertexFormat::Float32x3, offset: 0, shader_location: 0 }];
        static BUFFERS: [VertexBuffer; 1] = [VertexBuffer::new(12, wgpu::VertexStepMode::Vertex, &ATTRS)];
        let state = RenderState::triangles(VertexLayout::from_static(&BUFFERS))
            .with_depth(DepthState::reverse_z(wgpu::TextureFormat::Depth32Float, true))
            .with_targets(&[ColorTarget::new(wgpu::TextureFormat::Rgba16Float, Blend::Replace)]);
        assert_eq!(
            state_text(&state),
            "TriangleList;cull=Back;depth=Depth32Float/write/GreaterEqual/bias=0,0,0;color=Rgba16Float/-/0xf;samples=1;vertex=12/Vertex/Float32x3@0+0"
        );
        let fullscreen = RenderState::fullscreen(ColorTarget::new(wgpu::TextureFormat::Rgba8Unorm, Blend::Additive));
        assert!(!state_text(&fullscreen).contains(' '));
    }
}
