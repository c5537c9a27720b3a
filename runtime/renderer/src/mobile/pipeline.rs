//! Render pipelines of the mobile passes, described with the frames' one
//! [`PipelineDesc`] and held as [`RenderSlot`]s: keys into the runtime's one
//! [`PipelineCache`], asked for when a draw is recorded. Unless the frame is built with
//! [`Creation::Lazy`], every pipeline is created when its pass is built (the warm-up).

use std::collections::HashSet;
use std::sync::{Arc, Mutex};

use crate::frame::{Creation, FramePipelines, PipelineDesc, RenderSlot};
use crate::pipelines::{PipelineCache, PipelineError, RenderKey};

/// The mobile frames' view of the runtime's one pipeline cache while the passes are built.
pub struct MobilePipelines<'a> {
    pub cache: &'a PipelineCache,
    pub device: &'a wgpu::Device,
    creation: Creation,
    /// The keys this frame asked for (how many distinct pipelines it uses).
    used: Mutex<HashSet<RenderKey>>,
}

impl<'a> MobilePipelines<'a> {
    pub fn new(cache: &'a PipelineCache, device: &'a wgpu::Device, creation: Creation) -> MobilePipelines<'a> {
        MobilePipelines { cache, device, creation, used: Mutex::default() }
    }

    /// The slot of the pipeline `desc` describes.
    pub fn get(&self, desc: &PipelineDesc) -> Result<Arc<RenderSlot>, PipelineError> {
        let slot = RenderSlot::from_desc(self.cache, desc, self.creation)?;
        self.used.lock().unwrap_or_else(|e| e.into_inner()).insert(slot.key().clone());
        Ok(Arc::new(slot))
    }

    /// How many distinct pipelines the frame uses.
    pub fn count(&self) -> usize {
        self.used.lock().unwrap_or_else(|e| e.into_inner()).len()
    }
}

/// A pipeline with its bind groups, ready to draw.
pub struct Draw {
    pub pipeline: Arc<RenderSlot>,
    pub groups: Vec<Option<wgpu::BindGroup>>,
}

impl Draw {
    pub fn new(
        device: &wgpu::Device,
        pipeline: Arc<RenderSlot>,
        resources: &[(&str, wgpu::BindingResource<'_>)],
    ) -> Result<Draw, PipelineError> {
        let groups = pipeline.bind_groups(device, resources)?;
        Ok(Draw { pipeline, groups })
    }

    /// Sets the pipeline and its bind groups; `false` (nothing set) when the pipeline is not
    /// ready, and the caller skips the draw.
    #[must_use]
    pub fn bind(&self, pipelines: FramePipelines<'_>, pass: &mut wgpu::RenderPass<'_>) -> bool {
        let Some(pipeline) = self.pipeline.ready(pipelines) else {
            return false;
        };
        pass.set_pipeline(&pipeline.pipeline);
        for (i, g) in self.groups.iter().enumerate() {
            if let Some(g) = g {
                pass.set_bind_group(i as u32, g, &[]);
            }
        }
        true
    }
}
