//! ComputeLightGrid: local lights culled into a frustum grid of 64x64 px tiles and 32
//! exponential depth slices (`LightGridInjection.usf`). CullLights pushes each light onto a
//! linked list per cell it touches; Compact turns the lists into one contiguous index array
//! with (count, offset) per cell, which translucency (and volumetric fog) read.

use std::sync::Arc;

use crate::frame::{blended, ComputeSlot, PassContext, PassDecl, PipelineDesc, RenderSlot, Visualize};
use crate::keys;

use super::pipelines::{BindGroups, DesktopLayout};
use super::resources::{begin, color_attachment, formats, Targets};
use super::{DesktopError, PassSetup};

/// The ComputeLightGrid declaration.
pub const PASS: PassDecl = PassDecl { name: "ComputeLightGrid", reads: &["Scene", "View"], writes: &["LightGrid"] };

/// Links each cell may hold on average before culling truncates (per light, up to this).
const LINKS_PER_CELL: u32 = 64;

pub struct LightGrid {
    inject: Arc<ComputeSlot>,
    compact: Arc<ComputeSlot>,
    visualize: Arc<RenderSlot>,
    inject_groups: BindGroups,
    compact_groups: BindGroups,
    visualize_groups: BindGroups,
    start_offsets: wgpu::Buffer,
    counters: wgpu::Buffer,
    /// (count, offset) per cell.
    pub num_culled_lights: wgpu::Buffer,
    /// Light indices, cell after cell.
    pub culled_light_data: wgpu::Buffer,
    pub grid: [u32; 3],
}

impl LightGrid {
    pub fn new(b: &PassSetup<'_>) -> Result<LightGrid, DesktopError> {
        let device = b.device;
        let cells = u64::from(b.view.grid_cells());
        let capacity = cells * u64::from(LINKS_PER_CELL.min(b.lights.len().max(1) as u32));
        let buffer = |label: &str, size: u64, usage: wgpu::BufferUsages| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: size.max(16),
                usage,
                mapped_at_creation: false,
            })
        };
        let rw = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::COPY_SRC;
        let start_offsets = buffer("StartOffsetGrid", cells * 4, rw);
        let links = buffer("CulledLightLinks", capacity * 8, rw);
        let counters = buffer("LightGridCounters", 16, rw);
        let num_culled_lights = buffer("NumCulledLightsGrid", cells * 8, rw);
        let culled_light_data = buffer("CulledLightDataGrid", capacity * 4, rw);
        let p = b.pipelines;
        let inject = p.compute(&keys::name(keys::light_grid_injection_cs::Key {}, p.key_level()?)?)?;
        let compact = p.compute(&keys::name(keys::light_grid_compact_cs::Key {}, p.key_level()?)?)?;
        let visualize = p.render(&PipelineDesc::fullscreen(
            &keys::name(keys::post_process_vs::Key {}, p.key_level()?)?,
            &keys::name(keys::visualize_light_grid_ps::Key {}, p.key_level()?)?,
            blended(formats::VISUALIZE, None),
        ))?;
        let resources = [
            ("View", b.view_buffer.as_entire_binding()),
            ("LocalLights", b.lights_buffer.as_entire_binding()),
            ("StartOffsetGrid", start_offsets.as_entire_binding()),
            ("CulledLightLinks", links.as_entire_binding()),
            ("Counters", counters.as_entire_binding()),
            ("NumCulledLightsGrid", num_culled_lights.as_entire_binding()),
            ("CulledLightDataGrid", culled_light_data.as_entire_binding()),
            ("SceneDepthTexture", wgpu::BindingResource::TextureView(&b.targets.scene_depth.depth_view)),
        ];
        Ok(LightGrid {
            inject_groups: inject.layout.bind_groups(device, &resources)?,
            compact_groups: compact.layout.bind_groups(device, &resources)?,
            visualize_groups: visualize.layout.bind_groups(device, &resources)?,
            inject,
            compact,
            visualize,
            start_offsets,
            counters,
            num_culled_lights,
            culled_light_data,
            grid: b.view.grid,
        })
    }

    fn dispatch(&self, ctx: &mut PassContext<'_>, label: &str, pipeline: &ComputeSlot, groups: &BindGroups) {
        let [wx, wy, wz] = pipeline.workgroup_size;
        let ready = pipeline.ready(ctx.pipelines());
        let mut pass = ctx.open_compute_pass(label);
        let Some(p) = ready else { return };
        pass.set_pipeline(&p.pipeline);
        groups.set_compute(&mut pass);
        pass.dispatch_workgroups(self.grid[0].div_ceil(wx), self.grid[1].div_ceil(wy), self.grid[2].div_ceil(wz));
    }

    pub fn record(&self, ctx: &mut PassContext<'_>, targets: &Targets) {
        ctx.step("CullLights", |ctx| {
            // Unreal clears large list heads with a compute shader; a buffer clear is the
            // same on every backend wgpu has.
            ctx.encoder().clear_buffer(&self.start_offsets, 0, None);
            ctx.encoder().clear_buffer(&self.counters, 0, None);
            self.dispatch(ctx, "CullLights", &self.inject, &self.inject_groups);
        });
        ctx.step("Compact", |ctx| {
            self.dispatch(ctx, "Compact", &self.compact, &self.compact_groups);
        });
        {
            let ready = self.visualize.ready(ctx.pipelines());
            let mut pass = begin(
                ctx,
                "VisualizeLightGrid",
                &[color_attachment(&targets.light_grid_visualize.view, Some(wgpu::Color::BLACK))],
                None,
            );
            if let Some(p) = ready {
                pass.set_pipeline(&p.pipeline);
                self.visualize_groups.set_render(&mut pass);
                pass.draw(0..3, 0..1);
            }
        }
        ctx.output(&targets.light_grid_visualize.texture, Visualize::Direct);
    }
}
