//! InjectTranslucentVolume and FilterTranslucentVolume (`TranslucentLightingShaders.usf`):
//! two cascaded 64^3 translucency lighting volumes centred on the camera (cascade 0 small and
//! sharp, cascade 1 large), each a pair of RGBA16F volumes, Ambient (the light arriving at the
//! cell: SH band 0) and Dir (the luminance-weighted light direction: SH band 1). Each shadowed
//! light is injected by its own dispatch per cascade, reading the volumes the previous light
//! wrote and writing the other pair (ping-pong); then a 3x3x3 tent filter writes the volumes
//! translucent surfaces and particles read.

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use glam::{Mat4, Vec3, Vec4};

use crate::pipelines::{ComputePipeline, PipelineCache, PipelineError};

use super::frame_view::{perm, groups, uniform_buffer, view, volume_3d, DirectionalShadow};

pub const VOLUME_SIZE: u32 = 64;
pub const VOLUME_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba16Float;
/// Half extent of each cascade's box around the camera (meters).
pub const CASCADE_EXTENTS: [f32; 2] = [5.0, 20.0];

#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
struct VolumeParams {
    origin: Vec4,
    light_position: Vec4,
    light_color: Vec4,
    cascade_view_proj: [Mat4; 3],
    cascade_splits: Vec4,
    cascade_rects: [Vec4; 3],
}

/// A light injected into the volumes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum InjectedLight {
    /// Direction towards the light, colour * intensity; shadowed by the cascaded shadow map.
    Directional { direction: Vec3, color: Vec3 },
    Point { position: Vec3, radius: f32, color: Vec3 },
}

struct Cascade {
    /// [ambient, dir] x [zero, A, B, filtered]
    ambient: [wgpu::Texture; 4],
    dir: [wgpu::Texture; 4],
    /// one per light: (params, bind group, shadowed)
    injections: Vec<(wgpu::Buffer, wgpu::BindGroup, bool)>,
    filter_group: wgpu::BindGroup,
}

pub struct TranslucentVolumes {
    cascades: Vec<Cascade>,
    inject: [Arc<ComputePipeline>; 2],
    filter: Arc<ComputePipeline>,
    lights: Vec<InjectedLight>,
}

/// Which pair light `k` writes: 1 (A) or 2 (B); the first reads the zero pair 0.
fn written_pair(k: usize) -> usize {
    1 + k % 2
}

fn read_pair(k: usize) -> usize {
    if k == 0 { 0 } else { written_pair(k - 1) }
}

impl TranslucentVolumes {
    /// The lights are fixed when the volumes are built (one bind group per light and cascade).
    pub fn new(
        device: &wgpu::Device,
        cache: &PipelineCache,
        frame_view: &wgpu::Buffer,
        shadow_atlas: &wgpu::TextureView,
        shadow_compare: wgpu::CompareFunction,
        lights: Vec<InjectedLight>,
    ) -> Result<TranslucentVolumes, PipelineError> {
        let unshadowed = cache.compute(&perm(cache, "TranslucentVolumeInjectCS", &[("DYNAMICALLY_SHADOWED", "0")])?)?;
        let shadowed = cache.compute(&perm(cache, "TranslucentVolumeInjectCS", &[("DYNAMICALLY_SHADOWED", "1")])?)?;
        let inject = [unshadowed, shadowed];
        let filter = cache.compute(&perm(cache, "TranslucentVolumeFilterCS", &[])?)?;
        let shadow_sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("TranslucentVolume shadow sampler"),
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            compare: Some(shadow_compare),
            ..Default::default()
        });
        let size = [VOLUME_SIZE; 3];
        let mut cascades = Vec::new();
        for c in 0..2 {
            let names = ["Zero", "A", "B", ""];
            let ambient: [wgpu::Texture; 4] = std::array::from_fn(|i| volume_3d(device, &format!("TranslucentVolume{c}{}", names[i]), size, VOLUME_FORMAT));
            let dir: [wgpu::Texture; 4] = std::array::from_fn(|i| volume_3d(device, &format!("TranslucentVolumeDir{c}{}", names[i]), size, VOLUME_FORMAT));
            let ambient_views: Vec<wgpu::TextureView> = ambient.iter().map(view).collect();
            let dir_views: Vec<wgpu::TextureView> = dir.iter().map(view).collect();
            let tex = wgpu::BindingResource::TextureView;
            let mut injections = Vec::new();
            for (k, light) in lights.iter().enumerate() {
                let shadowed = matches!(light, InjectedLight::Directional { .. });
                let params = uniform_buffer(device, &format!("InjectTranslucentVolume {c} light {k}"), &VolumeParams::default());
                let (r, w) = (read_pair(k), written_pair(k));
                let mut resources = vec![
                    ("volume", params.as_entire_binding()),
                    ("prev_ambient", tex(&ambient_views[r])),
                    ("prev_dir", tex(&dir_views[r])),
                    ("out_ambient", tex(&ambient_views[w])),
                    ("out_dir", tex(&dir_views[w])),
                ];
                if shadowed {
                    resources.push(("view", frame_view.as_entire_binding()));
                    resources.push(("shadow_atlas", tex(shadow_atlas)));
                    resources.push(("shadow_sampler", wgpu::BindingResource::Sampler(&shadow_sampler)));
                }
                let group = inject[usize::from(shadowed)].layout.bind_group(device, 0, "InjectTranslucentVolume", &resources)?;
                injections.push((params, group, shadowed));
            }
            let last = if lights.is_empty() { 0 } else { written_pair(lights.len() - 1) };
            let filter_group = filter.layout.bind_group(device, 0, "FilterTranslucentVolume", &[
                ("in_ambient", tex(&ambient_views[last])),
                ("in_dir", tex(&dir_views[last])),
                ("out_ambient", tex(&ambient_views[3])),
                ("out_dir", tex(&dir_views[3])),
            ])?;
            cascades.push(Cascade { ambient, dir, injections, filter_group });
        }
        Ok(TranslucentVolumes { cascades, inject, filter, lights })
    }

    /// The filtered volumes of a cascade: (Ambient, Dir).
    pub fn volumes(&self, cascade: usize) -> (&wgpu::Texture, &wgpu::Texture) {
        (&self.cascades[cascade].ambient[3], &self.cascades[cascade].dir[3])
    }

    /// The volumes a cascade held after the last light was injected, before filtering.
    pub fn injected(&self, cascade: usize) -> (&wgpu::Texture, &wgpu::Texture) {
        let last = if self.lights.is_empty() { 0 } else { written_pair(self.lights.len() - 1) };
        (&self.cascades[cascade].ambient[last], &self.cascades[cascade].dir[last])
    }

    /// Box of cascade `c` around the camera: (min corner, cell size).
    pub fn cascade_box(camera: Vec3, c: usize) -> (Vec3, f32) {
        let extent = CASCADE_EXTENTS[c];
        let cell = 2.0 * extent / VOLUME_SIZE as f32;
        // snapped to whole cells so the volume does not swim as the camera moves
        let origin = ((camera - Vec3::splat(extent)) / cell).floor() * cell;
        (origin, cell)
    }

    /// InjectTranslucentVolume: every light into both cascades, the directional light
    /// shadowed by `shadow`.
    pub fn record_inject(&self, queue: &wgpu::Queue, encoder: &mut wgpu::CommandEncoder, camera: Vec3, shadow: Option<&DirectionalShadow>) {
        let (matrices, splits, rects) = DirectionalShadow::uniforms(shadow);
        let n = groups(VOLUME_SIZE, 4);
        for (c, cascade) in self.cascades.iter().enumerate() {
            let (origin, cell) = Self::cascade_box(camera, c);
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some(&format!("InjectTranslucentVolume cascade {c}")), timestamp_writes: None });
            for (k, light) in self.lights.iter().enumerate() {
                let (params, group, shadowed) = &cascade.injections[k];
                let (position, color) = match *light {
                    InjectedLight::Directional { direction, color } => (direction.normalize().extend(0.0), color.extend(0.0)),
                    InjectedLight::Point { position, radius, color } => (position.extend(radius), color.extend(1.0)),
                };
                let p = VolumeParams { origin: origin.extend(cell), light_position: position, light_color: color, cascade_view_proj: matrices, cascade_splits: splits, cascade_rects: rects };
                queue.write_buffer(params, 0, bytemuck::bytes_of(&p));
                pass.set_pipeline(&self.inject[usize::from(*shadowed)].pipeline);
                pass.set_bind_group(0, group, &[]);
                pass.dispatch_workgroups(n, n, n);
            }
        }
    }

    /// FilterTranslucentVolume: both cascades.
    pub fn record_filter(&self, encoder: &mut wgpu::CommandEncoder) {
        let n = groups(VOLUME_SIZE, 4);
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some("FilterTranslucentVolume"), timestamp_writes: None });
        pass.set_pipeline(&self.filter.pipeline);
        for cascade in &self.cascades {
            pass.set_bind_group(0, &cascade.filter_group, &[]);
            pass.dispatch_workgroups(n, n, n);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lights_ping_pong_between_two_pairs_after_the_zero_pair() {
        let reads: Vec<usize> = (0..4).map(read_pair).collect();
        let writes: Vec<usize> = (0..4).map(written_pair).collect();
        assert_eq!(reads, vec![0, 1, 2, 1]);
        assert_eq!(writes, vec![1, 2, 1, 2]);
    }

    #[test]
    fn cascades_cover_the_camera_with_whole_cells() {
        let camera = Vec3::new(1.3, 2.7, -4.1);
        for c in 0..2 {
            let (origin, cell) = TranslucentVolumes::cascade_box(camera, c);
            let local = (camera - origin) / cell;
            assert!(local.cmpge(Vec3::splat(31.0)).all() && local.cmple(Vec3::splat(33.0)).all(), "{local}");
            assert!(((origin / cell) - (origin / cell).round()).abs().max_element() < 1e-3);
        }
    }
}
