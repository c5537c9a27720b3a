//! VolumetricFog (`VolumetricFog.usf`): a froxel volume fitted to the view, 8x8 px tiles and
//! 128 exponentially distributed depth slices (as the seeds' capture), computed in three
//! compute steps and applied over SceneColor with the height fog:
//! - InitializeVolumeAttributes: the height fog's scattering and extinction (VBufferA) and
//!   emissive (VBufferB) per froxel;
//! - LightScattering: light in-scattered at a jittered point of each froxel from the shadowed
//!   directional light, the sky light and the local lights, blended with the previous frame's
//!   result reprojected into this frame (the history volume);
//! - FinalIntegration: front-to-back accumulation of in-scattering and transmittance.

use crate::frame::{ComputeSlot, PassContext, PassDecl, RenderSlot};
use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use glam::{Mat4, UVec4, Vec3, Vec4};

use crate::keys;
use crate::pipelines::{Blend, ColorTarget, PipelineError, RenderState};

use super::frame_view::{
    groups, linear_sampler, uniform_buffer, volume, volume_view, DirectionalShadow, EffectPassInit,
};

/// Reprojects the previous frame's light scattering (history).
pub const PASS: PassDecl = PassDecl {
    name: "VolumetricFog",
    reads: &["View", "SceneDepth", "LightGrid", "ShadowDepths", "VolumetricFog"],
    writes: &["VolumetricFog"],
};

/// The step of ExponentialHeightFog that composites the fog over SceneColor.
pub const APPLY_STEP: PassDecl = PassDecl {
    name: "VolumetricFog",
    reads: &["View", "SceneDepth", "VolumetricFog", "SceneColor"],
    writes: &["SceneColor"],
};

pub const TILE_SIZE: u32 = 8;
pub const DEPTH_SLICES: u32 = 128;
pub const VOLUME_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba16Float;
/// Weight of the reprojected history in LightScattering.
pub const HISTORY_WEIGHT: f32 = 0.9;

/// `FogParams` of `VolumetricFog.usf`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct FogParams {
    pub grid_size: UVec4,
    pub depth_range: Vec4,
    pub height_fog: Vec4,
    pub albedo: Vec4,
    pub emissive: Vec4,
    pub intensities: Vec4,
    pub cascade_view_proj: [Mat4; 3],
    pub cascade_splits: Vec4,
    pub cascade_rects: [Vec4; 3],
    pub light_grid_size: UVec4,
    pub light_grid_z_params: Vec4,
}

/// ComputeLightGrid's output: the local lights the fog scatters, cell by cell.
pub struct LightGridInputs<'a> {
    /// `LocalLight`s (`GridLight` of `VolumetricFog.usf`).
    pub lights: &'a wgpu::Buffer,
    /// (count, first index) per cell.
    pub num_culled_lights: &'a wgpu::Buffer,
    /// Light indices, cell after cell.
    pub culled_light_data: &'a wgpu::Buffer,
    /// Cells in x, y, z and the tile size in pixels.
    pub size: UVec4,
    /// slice = log2(depth * x + y) * z.
    pub z_params: Vec4,
}

/// The directional light's cascaded shadow map as the fog reads it.
pub struct ShadowInputs<'a> {
    /// The 3x1 atlas, depth aspect.
    pub atlas: &'a wgpu::TextureView,
    /// How a receiver's depth compares with the stored depth where it is lit (reverse-Z
    /// shadow maps: `GreaterEqual`).
    pub compare: wgpu::CompareFunction,
}

/// The fog's settings for a frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FogSettings {
    /// Extinction at the fog height (per meter).
    pub density: f32,
    pub height_falloff: f32,
    pub fog_height: f32,
    pub start_distance: f32,
    pub albedo: Vec3,
    pub emissive: Vec3,
    /// Henyey-Greenstein anisotropy (forward scattering > 0).
    pub anisotropy: f32,
    pub sun_intensity: f32,
    pub sky_intensity: f32,
    pub local_intensity: f32,
    /// View distance of the first and last slices.
    pub near: f32,
    pub far: f32,
    /// The directional light's shadow; `None` when it casts none.
    pub shadow: Option<DirectionalShadow>,
}

pub struct VolumetricFog {
    pub grid: [u32; 3],
    pub vbuffer_a: wgpu::Texture,
    pub vbuffer_b: wgpu::Texture,
    /// Ping-pong: this frame's LightScattering and the previous frame's (the history).
    pub light_scattering: [wgpu::Texture; 2],
    pub integrated: wgpu::Texture,
    params: wgpu::Buffer,
    /// The light grid's size and depth distribution.
    light_grid: (UVec4, Vec4),
    init: Arc<ComputeSlot>,
    scattering: [Arc<ComputeSlot>; 2],
    integration: Arc<ComputeSlot>,
    apply: Arc<RenderSlot>,
    init_group: wgpu::BindGroup,
    /// [without history writing 0, with history: reads 1 - i writes i]
    scattering_groups: [wgpu::BindGroup; 3],
    integration_groups: [wgpu::BindGroup; 2],
    apply_group: wgpu::BindGroup,
    current: usize,
    history_valid: bool,
    use_history: bool,
    frame: u32,
}

impl VolumetricFog {
    pub fn new(
        init: &EffectPassInit<'_>,
        size: [u32; 2],
        scene_depth: &wgpu::TextureView,
        shadow: &ShadowInputs<'_>,
        light_grid: &LightGridInputs<'_>,
        scene_color_format: wgpu::TextureFormat,
    ) -> Result<VolumetricFog, PipelineError> {
        let EffectPassInit { device, cache, frame_view } = *init;
        let grid = [size[0].div_ceil(TILE_SIZE), size[1].div_ceil(TILE_SIZE), DEPTH_SLICES];
        let init = cache.compute(&keys::name(keys::volumetric_fog_initialize_cs::Key {}, keys::Level::Sm5)?)?;
        let scattering = [
            cache.compute(&keys::name(
                keys::volumetric_fog_light_scattering_cs::Key { use_temporal_reprojection: false },
                keys::Level::Sm5,
            )?)?,
            cache.compute(&keys::name(
                keys::volumetric_fog_light_scattering_cs::Key { use_temporal_reprojection: true },
                keys::Level::Sm5,
            )?)?,
        ];
        let integration =
            cache.compute(&keys::name(keys::volumetric_fog_final_integration_cs::Key {}, keys::Level::Sm5)?)?;
        let apply = cache.render(
            &keys::name(keys::volumetric_fog_apply_vs::Key {}, keys::Level::Sm5)?,
            Some(&keys::name(keys::volumetric_fog_apply_ps::Key {}, keys::Level::Sm5)?),
            &RenderState::fullscreen(ColorTarget::new(scene_color_format, Blend::PremultipliedAlpha)),
        )?;
        let vbuffer_a = volume(device, "VBufferA", grid, VOLUME_FORMAT);
        let vbuffer_b = volume(device, "VBufferB", grid, VOLUME_FORMAT);
        let light_scattering = [
            volume(device, "LightScattering0", grid, VOLUME_FORMAT),
            volume(device, "LightScattering1", grid, VOLUME_FORMAT),
        ];
        let integrated = volume(device, "IntegratedLightScattering", grid, VOLUME_FORMAT);
        let params = uniform_buffer(device, "VolumetricFog params", &FogParams::default());
        let shadow_sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("VolumetricFog shadow sampler"),
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            compare: Some(shadow.compare),
            ..Default::default()
        });
        let sampler = linear_sampler(device, "VolumetricFog volume sampler");
        let (a, b) = (volume_view(&vbuffer_a), volume_view(&vbuffer_b));
        let ls = [volume_view(&light_scattering[0]), volume_view(&light_scattering[1])];
        let integrated_view = volume_view(&integrated);
        let tex = wgpu::BindingResource::TextureView;
        let init_group = init.layout.bind_group(
            device,
            0,
            "InitializeVolumeAttributes",
            &[
                ("View", frame_view.as_entire_binding()),
                ("fog", params.as_entire_binding()),
                ("vbuffer_a", tex(&a)),
                ("vbuffer_b", tex(&b)),
            ],
        )?;
        let scatter_group = |history: Option<usize>, out: usize| {
            let mut r = vec![
                ("View", frame_view.as_entire_binding()),
                ("fog", params.as_entire_binding()),
                ("vbuffer_a", tex(&a)),
                ("vbuffer_b", tex(&b)),
                ("light_scattering", tex(&ls[out])),
                ("shadow_atlas", tex(shadow.atlas)),
                ("shadow_sampler", wgpu::BindingResource::Sampler(&shadow_sampler)),
                ("LocalLights", light_grid.lights.as_entire_binding()),
                ("NumCulledLightsGrid", light_grid.num_culled_lights.as_entire_binding()),
                ("CulledLightDataGrid", light_grid.culled_light_data.as_entire_binding()),
            ];
            let pipeline = match history {
                Some(h) => {
                    r.push(("history", tex(&ls[h])));
                    r.push(("history_sampler", wgpu::BindingResource::Sampler(&sampler)));
                    &scattering[1]
                }
                None => &scattering[0],
            };
            pipeline.layout.bind_group(device, 0, "LightScattering", &r)
        };
        let scattering_groups = [scatter_group(None, 0)?, scatter_group(Some(1), 0)?, scatter_group(Some(0), 1)?];
        let integration_group = |i: usize| {
            integration.layout.bind_group(
                device,
                0,
                "FinalIntegration",
                &[
                    ("View", frame_view.as_entire_binding()),
                    ("fog", params.as_entire_binding()),
                    ("light_scattering", tex(&ls[i])),
                    ("integrated", tex(&integrated_view)),
                ],
            )
        };
        let integration_groups = [integration_group(0)?, integration_group(1)?];
        let apply_group = apply.layout.bind_group(
            device,
            0,
            "VolumetricFog apply",
            &[
                ("View", frame_view.as_entire_binding()),
                ("fog", params.as_entire_binding()),
                ("integrated_volume", tex(&integrated_view)),
                ("volume_sampler", wgpu::BindingResource::Sampler(&sampler)),
                ("SceneDepthTexture", tex(scene_depth)),
            ],
        )?;
        Ok(VolumetricFog {
            grid,
            vbuffer_a,
            vbuffer_b,
            light_scattering,
            integrated,
            params,
            light_grid: (light_grid.size, light_grid.z_params),
            init,
            scattering,
            integration,
            apply,
            init_group,
            scattering_groups,
            integration_groups,
            apply_group,
            current: 0,
            history_valid: false,
            use_history: false,
            frame: 0,
        })
    }

    /// Forgets the history (camera cut, or a test that wants one frame without it).
    pub fn reset_history(&mut self) {
        self.history_valid = false;
    }

    /// The LightScattering volume this frame wrote.
    pub fn current_light_scattering(&self) -> &wgpu::Texture {
        &self.light_scattering[self.current]
    }

    /// Which LightScattering volume holds this frame's (0 or 1).
    pub fn current_index(&self) -> usize {
        self.current
    }

    /// The light grid's depth slicing this frame (it follows the camera's near plane).
    pub fn set_light_grid_z_params(&mut self, z_params: Vec4) {
        self.light_grid.1 = z_params;
    }

    /// InitializeVolumeAttributes (and this frame's parameters).
    pub fn record_initialize(&mut self, queue: &wgpu::Queue, ctx: &mut PassContext<'_>, settings: &FogSettings) {
        let (cascades, splits, rects) = DirectionalShadow::uniforms(settings.shadow.as_ref());
        let use_history = self.history_valid;
        let params = FogParams {
            grid_size: UVec4::new(self.grid[0], self.grid[1], self.grid[2], self.frame),
            depth_range: Vec4::new(
                settings.near,
                settings.far,
                TILE_SIZE as f32,
                if use_history { HISTORY_WEIGHT } else { 0.0 },
            ),
            height_fog: Vec4::new(
                settings.density,
                settings.height_falloff,
                settings.fog_height,
                settings.start_distance,
            ),
            albedo: settings.albedo.extend(1.0),
            emissive: settings.emissive.extend(settings.anisotropy),
            intensities: Vec4::new(settings.sun_intensity, settings.sky_intensity, settings.local_intensity, 0.0),
            cascade_view_proj: cascades,
            cascade_splits: splits,
            cascade_rects: rects,
            light_grid_size: self.light_grid.0,
            light_grid_z_params: self.light_grid.1,
        };
        queue.write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
        self.frame = self.frame.wrapping_add(1);
        let [gx, gy, gz] = self.grid;

        let ready = self.init.ready(ctx.pipelines());
        let mut pass = ctx.open_compute_pass("InitializeVolumeAttributes");
        if let Some(p) = ready {
            pass.set_pipeline(&p.pipeline);
            pass.set_bind_group(0, &self.init_group, &[]);
            pass.dispatch_workgroups(groups(gx, 4), groups(gy, 4), groups(gz, 4));
        }
        self.use_history = use_history;
    }

    /// LightScattering, with the history when there is one.
    pub fn record_light_scattering(&mut self, ctx: &mut PassContext<'_>) {
        let [gx, gy, gz] = self.grid;
        let use_history = self.use_history;
        // this frame writes `out`; the history is the other volume
        let out = if use_history { 1 - self.current } else { 0 };
        let (pipeline, group) = if use_history {
            (&self.scattering[1], &self.scattering_groups[1 + out])
        } else {
            (&self.scattering[0], &self.scattering_groups[0])
        };
        let ready = pipeline.ready(ctx.pipelines());
        let mut pass = ctx.open_compute_pass("LightScattering");
        // a frame that could not scatter leaves the volumes (and the history) as they were
        let Some(p) = ready else { return };
        pass.set_pipeline(&p.pipeline);
        pass.set_bind_group(0, group, &[]);
        pass.dispatch_workgroups(groups(gx, 4), groups(gy, 4), groups(gz, 4));
        drop(pass);
        self.current = out;
        self.history_valid = true;
    }

    /// FinalIntegration of this frame's LightScattering.
    pub fn record_final_integration(&mut self, ctx: &mut PassContext<'_>) {
        let [gx, gy, _] = self.grid;
        let out = self.current;
        let ready = self.integration.ready(ctx.pipelines());
        let mut pass = ctx.open_compute_pass("FinalIntegration");
        if let Some(p) = ready {
            pass.set_pipeline(&p.pipeline);
            pass.set_bind_group(0, &self.integration_groups[out], &[]);
            pass.dispatch_workgroups(groups(gx, 8), groups(gy, 8), 1);
        }
    }

    /// Composites the integrated volume over SceneColor (after the height fog).
    pub fn apply(&self, ctx: &mut PassContext<'_>, scene_color: &wgpu::TextureView) {
        let ready = self.apply.ready(ctx.pipelines());
        let mut pass = super::frame_view::color_pass(ctx, "VolumetricFog apply", scene_color, wgpu::LoadOp::Load);
        if let Some(p) = ready {
            pass.set_pipeline(&p.pipeline);
            pass.set_bind_group(0, &self.apply_group, &[]);
            pass.draw(0..3, 0..1);
        }
    }
}
