//! InjectTranslucentVolume and FilterTranslucentVolume (`TranslucentLightingShaders.usf`):
//! two cascaded 64^3 translucency lighting volumes centred on the camera (cascade 0 small and
//! sharp, cascade 1 large), each a pair of RGBA16F volumes, Ambient (the light arriving at the
//! cell: SH band 0) and Dir (the luminance-weighted light direction: SH band 1). Each shadowed
//! light is injected with its own shadow (the directional light with its cascades, a movable
//! point light with its cube shadow, a stationary point or spot light with its per-object
//! shadow tiles: `TranslucentVolumeInjectCS{DYNAMICALLY_SHADOWED=1, SHADOW_PROJECTION_TYPE}`,
//! looking them up as ShadowProjectionOnOpaque does) by its own dispatch per cascade, reading
//! the volumes the previous light wrote and writing the other pair (ping-pong); a local light
//! whose shadow work ShadowFrustumQueries skipped this frame, or one without shadow tiles, is
//! injected unshadowed. Then a 3x3x3 tent filter writes the volumes
//! translucent surfaces and particles read. The cascades' boxes of the frame are kept in a
//! uniform buffer (`TranslucencyLightingVolumeParams` of `BasePassPixelShader.usf`) for the
//! surfaces that read both cascades.

use crate::frame::{ComputeSlot, PassContext, PassDecl};
use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use glam::{Mat4, Vec3, Vec4};

use crate::keys;
use crate::pipelines::PipelineError;

use super::frame_view::{groups, uniform_buffer, volume, volume_view, DirectionalShadow, EffectPassInit};
use super::view::ShadowProjectionUniforms;

/// A step of Lighting; blends with the previous frame's volume (history).
pub const INJECT_STEP: PassDecl = PassDecl {
    name: "InjectTranslucentVolume",
    reads: &["Scene", "View", "ShadowDepths", "TranslucencyVolume"],
    writes: &["TranslucencyVolume"],
};

/// A step of Lighting, after the injection.
pub const FILTER_STEP: PassDecl =
    PassDecl { name: "FilterTranslucentVolume", reads: &["TranslucencyVolume"], writes: &["TranslucencyVolume"] };

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
    spot_direction: Vec4,
    spot_angles: Vec4,
}

/// A light injected into the volumes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum InjectedLight {
    /// Direction towards the light, colour * intensity; shadowed by the cascaded shadow map.
    Directional {
        direction: Vec3,
        color: Vec3,
    },
    Point {
        position: Vec3,
        radius: f32,
        color: Vec3,
    },
    /// A spot light: `direction` the way the cone points; the cone's half angles in radians.
    Spot {
        position: Vec3,
        radius: f32,
        color: Vec3,
        direction: Vec3,
        inner_angle: f32,
        outer_angle: f32,
    },
}

/// How a local light's own shadow is projected (`SHADOW_PROJECTION_TYPE`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LocalShadowProjection {
    /// A stationary light's per-object shadow tiles: `projection.params.w` of them, matrix and
    /// atlas rect `k` each.
    PerObject,
    /// A movable point light's cube shadow: six faces, side by side.
    OnePassPointLight,
}

impl LocalShadowProjection {
    fn label(self) -> &'static str {
        match self {
            LocalShadowProjection::PerObject => "PER_OBJECT",
            LocalShadowProjection::OnePassPointLight => "ONE_PASS_POINT_LIGHT",
        }
    }
}

/// A shadow-casting local light's shadow as InjectTranslucentVolume reads it: the shadow
/// depths ShadowDepths renders and the projection ShadowProjectionOnOpaque binds.
#[derive(Clone, Debug)]
pub struct LocalLightShadow<'a> {
    /// The light's index among the frame's local lights (point lights, then spot lights):
    /// what the ShadowFrustumQueries decide on.
    pub light: usize,
    pub kind: LocalShadowProjection,
    pub atlas: &'a wgpu::TextureView,
    pub projection: ShadowProjectionUniforms,
}

/// `TranslucencyLightingVolumeParams` of `BasePassPixelShader.usf`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct LookupParams {
    /// Per cascade: minimum corner, w the cell size.
    pub volume_min: [Vec4; 2],
    /// Per cascade: 1 / the box's size, w cells per side.
    pub volume_inv_size: [Vec4; 2],
}

impl LookupParams {
    /// The boxes of both cascades around `camera`.
    pub fn new(camera: Vec3) -> LookupParams {
        let mut p = LookupParams::default();
        for c in 0..2 {
            let (origin, cell) = TranslucentVolumes::cascade_box(camera, c);
            p.volume_min[c] = origin.extend(cell);
            p.volume_inv_size[c] = Vec3::splat(1.0 / (cell * VOLUME_SIZE as f32)).extend(VOLUME_SIZE as f32);
        }
        p
    }
}

/// One light's injection into one cascade.
struct Injection {
    params: wgpu::Buffer,
    /// Through `TranslucentVolumeInjectCS{DYNAMICALLY_SHADOWED=0}`.
    unshadowed: wgpu::BindGroup,
    /// Through `{DYNAMICALLY_SHADOWED=1}`: the index of the pipeline (in
    /// `TranslucentVolumes::inject`) and its bind group with the light's shadow.
    shadowed: Option<(usize, wgpu::BindGroup)>,
}

/// Pipelines of `TranslucentVolumes::inject`: unshadowed, then shadowed by projection type.
const INJECT_UNSHADOWED: usize = 0;
const INJECT_CASCADED: usize = 1;
const INJECT_PER_OBJECT: usize = 2;
const INJECT_POINT: usize = 3;

struct Cascade {
    /// [ambient, dir] x [zero, A, B, filtered]
    ambient: [wgpu::Texture; 4],
    dir: [wgpu::Texture; 4],
    /// one per light
    injections: Vec<Injection>,
    filter_group: wgpu::BindGroup,
}

pub struct TranslucentVolumes {
    cascades: Vec<Cascade>,
    inject: [Arc<ComputeSlot>; 4],
    filter: Arc<ComputeSlot>,
    lights: Vec<InjectedLight>,
    /// Per light: the frame's local light index whose ShadowFrustumQuery gates its shadow.
    gates: Vec<Option<usize>>,
    /// The local lights' `ShadowProjection` buffers (kept alive with the bind groups).
    _projections: Vec<wgpu::Buffer>,
    /// This frame's [`LookupParams`], written by [`TranslucentVolumes::record_inject`].
    lookup: wgpu::Buffer,
}

/// Which pair light `k` writes: 1 (A) or 2 (B); the first reads the zero pair 0.
fn written_pair(k: usize) -> usize {
    1 + k % 2
}

fn read_pair(k: usize) -> usize {
    if k == 0 {
        0
    } else {
        written_pair(k - 1)
    }
}

/// What every cascade's volumes and bind groups are made from.
struct CascadeSetup<'a> {
    device: &'a wgpu::Device,
    frame_view: &'a wgpu::Buffer,
    /// The directional light's cascades.
    shadow_atlas: &'a wgpu::TextureView,
    shadow_sampler: wgpu::Sampler,
    inject: &'a [Arc<ComputeSlot>; 4],
    filter: &'a ComputeSlot,
    lights: &'a [InjectedLight],
    shadows: &'a [Option<LocalLightShadow<'a>>],
    /// Per light: its own shadow's `ShadowProjection` buffer.
    projections: &'a [Option<wgpu::Buffer>],
}

impl CascadeSetup<'_> {
    /// Cascade `c`: its volumes, one injection per light and the filter.
    fn cascade(&self, c: usize) -> Result<Cascade, PipelineError> {
        let (device, size) = (self.device, [VOLUME_SIZE; 3]);
        let names = ["Zero", "A", "B", ""];
        let ambient: [wgpu::Texture; 4] =
            std::array::from_fn(|i| volume(device, &format!("TranslucentVolume{c}{}", names[i]), size, VOLUME_FORMAT));
        let dir: [wgpu::Texture; 4] = std::array::from_fn(|i| {
            volume(device, &format!("TranslucentVolumeDir{c}{}", names[i]), size, VOLUME_FORMAT)
        });
        let ambient_views: Vec<wgpu::TextureView> = ambient.iter().map(volume_view).collect();
        let dir_views: Vec<wgpu::TextureView> = dir.iter().map(volume_view).collect();
        let tex = wgpu::BindingResource::TextureView;
        let injections = (0..self.lights.len())
            .map(|k| self.injection(c, k, &ambient_views, &dir_views))
            .collect::<Result<Vec<_>, _>>()?;
        let last = if self.lights.is_empty() { 0 } else { written_pair(self.lights.len() - 1) };
        let filter_group = self.filter.layout.bind_group(
            device,
            0,
            "FilterTranslucentVolume",
            &[
                ("in_ambient", tex(&ambient_views[last])),
                ("in_dir", tex(&dir_views[last])),
                ("out_ambient", tex(&ambient_views[3])),
                ("out_dir", tex(&dir_views[3])),
            ],
        )?;
        Ok(Cascade { ambient, dir, injections, filter_group })
    }

    /// Light `k`'s injection into cascade `c`: unshadowed, and through its shadow where it
    /// has one.
    fn injection(
        &self,
        c: usize,
        k: usize,
        ambient_views: &[wgpu::TextureView],
        dir_views: &[wgpu::TextureView],
    ) -> Result<Injection, PipelineError> {
        let device = self.device;
        let tex = wgpu::BindingResource::TextureView;
        let params =
            uniform_buffer(device, &format!("InjectTranslucentVolume {c} light {k}"), &VolumeParams::default());
        let (r, w) = (read_pair(k), written_pair(k));
        let mut resources = vec![
            ("volume", params.as_entire_binding()),
            ("prev_ambient", tex(&ambient_views[r])),
            ("prev_dir", tex(&dir_views[r])),
            ("out_ambient", tex(&ambient_views[w])),
            ("out_dir", tex(&dir_views[w])),
        ];
        let inject = self.inject;
        let unshadowed =
            inject[INJECT_UNSHADOWED].layout.bind_group(device, 0, "InjectTranslucentVolume", &resources)?;
        let sampler = wgpu::BindingResource::Sampler(&self.shadow_sampler);
        let local_shadow = self.shadows.get(k).and_then(Option::as_ref);
        let shadowed = match (&self.lights[k], local_shadow, &self.projections[k]) {
            (InjectedLight::Directional { .. }, _, _) => {
                resources.push(("View", self.frame_view.as_entire_binding()));
                resources.push(("shadow_atlas", tex(self.shadow_atlas)));
                resources.push(("shadow_sampler", sampler));
                let label = "InjectTranslucentVolume (cascaded shadow)";
                Some((INJECT_CASCADED, inject[INJECT_CASCADED].layout.bind_group(device, 0, label, &resources)?))
            }
            (_, Some(s), Some(projection)) => {
                let pipeline = match s.kind {
                    LocalShadowProjection::PerObject => INJECT_PER_OBJECT,
                    LocalShadowProjection::OnePassPointLight => INJECT_POINT,
                };
                resources.push(("shadow_atlas", tex(s.atlas)));
                resources.push(("shadow_sampler", sampler));
                resources.push(("ShadowProjection", projection.as_entire_binding()));
                let label = format!("InjectTranslucentVolume ({} shadow)", s.kind.label());
                Some((pipeline, inject[pipeline].layout.bind_group(device, 0, &label, &resources)?))
            }
            _ => None,
        };
        Ok(Injection { params, unshadowed, shadowed })
    }
}

impl TranslucentVolumes {
    /// The lights are fixed when the volumes are built (one bind group per light and cascade).
    /// `shadows[k]`: light `k`'s own shadow where it is a local light with one (the directional
    /// light is shadowed by `shadow_atlas`, its cascades).
    pub fn new(
        init: &EffectPassInit<'_>,
        shadow_atlas: &wgpu::TextureView,
        shadow_compare: wgpu::CompareFunction,
        lights: Vec<InjectedLight>,
        shadows: &[Option<LocalLightShadow<'_>>],
    ) -> Result<TranslucentVolumes, PipelineError> {
        let EffectPassInit { device, cache, frame_view } = *init;
        use keys::translucent_volume_inject_cs::{Key, ShadowProjectionType};
        let name = |dynamically_shadowed: bool, shadow_projection_type: ShadowProjectionType| {
            keys::name(Key { dynamically_shadowed, shadow_projection_type }, keys::Level::Sm5)
        };
        let inject = [
            cache.compute(&name(false, ShadowProjectionType::Cascaded)?)?,
            cache.compute(&name(true, ShadowProjectionType::Cascaded)?)?,
            cache.compute(&name(true, ShadowProjectionType::PerObject)?)?,
            cache.compute(&name(true, ShadowProjectionType::OnePassPointLight)?)?,
        ];
        let local_shadow = |k: usize| shadows.get(k).and_then(Option::as_ref);
        let projections: Vec<Option<wgpu::Buffer>> = (0..lights.len())
            .map(|k| {
                local_shadow(k).map(|s| {
                    uniform_buffer(device, &format!("InjectTranslucentVolume shadow {}", s.kind.label()), &s.projection)
                })
            })
            .collect();
        let gates = (0..lights.len()).map(|k| local_shadow(k).map(|s| s.light)).collect();
        let filter = cache.compute(&keys::name(keys::translucent_volume_filter_cs::Key {}, keys::Level::Sm5)?)?;
        let setup = CascadeSetup {
            device,
            frame_view,
            shadow_atlas,
            shadow_sampler: device.create_sampler(&wgpu::SamplerDescriptor {
                label: Some("TranslucentVolume shadow sampler"),
                mag_filter: wgpu::FilterMode::Linear,
                min_filter: wgpu::FilterMode::Linear,
                compare: Some(shadow_compare),
                ..Default::default()
            }),
            inject: &inject,
            filter: &filter,
            lights: &lights,
            shadows,
            projections: &projections,
        };
        let cascades = vec![setup.cascade(0)?, setup.cascade(1)?];
        let lookup = uniform_buffer(device, "TranslucencyLightingVolume", &LookupParams::default());
        Ok(TranslucentVolumes {
            cascades,
            inject,
            filter,
            lights,
            gates,
            _projections: projections.into_iter().flatten().collect(),
            lookup,
        })
    }

    /// The cascades' boxes this frame ([`LookupParams`]), for the surfaces that read the volumes.
    pub fn lookup_buffer(&self) -> &wgpu::Buffer {
        &self.lookup
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

    /// InjectTranslucentVolume: every light into both cascades, each shadowed by its own
    /// shadow when `shadows` (else unshadowed, as if nothing occluded it): the directional
    /// light by `shadow` (this frame's cascades), a local light by its shadow depths where
    /// `casts_shadow(local light index)` says they were rendered this frame.
    pub fn record_inject(
        &self,
        queue: &wgpu::Queue,
        ctx: &mut PassContext<'_>,
        camera: Vec3,
        shadow: Option<&DirectionalShadow>,
        shadows: bool,
        casts_shadow: &dyn Fn(usize) -> bool,
    ) {
        let (matrices, splits, rects) = DirectionalShadow::uniforms(shadow);
        queue.write_buffer(&self.lookup, 0, bytemuck::bytes_of(&LookupParams::new(camera)));
        let n = groups(VOLUME_SIZE, 4);
        let pl = ctx.pipelines();
        for (c, cascade) in self.cascades.iter().enumerate() {
            let (origin, cell) = Self::cascade_box(camera, c);
            let mut pass = ctx.open_compute_pass(&format!("InjectTranslucentVolume cascade {c}"));
            for (k, light) in self.lights.iter().enumerate() {
                let injection = &cascade.injections[k];
                let rendered = self.gates[k].is_none_or(casts_shadow);
                let (pipeline, group) = match &injection.shadowed {
                    Some((pipeline, g)) if shadows && rendered => (*pipeline, g),
                    _ => (INJECT_UNSHADOWED, &injection.unshadowed),
                };
                let (position, color, spot_direction, spot_angles) = match *light {
                    InjectedLight::Directional { direction, color } => {
                        (direction.normalize().extend(0.0), color.extend(0.0), Vec4::ZERO, Vec4::ZERO)
                    }
                    InjectedLight::Point { position, radius, color } => {
                        (position.extend(radius), color.extend(1.0), Vec4::ZERO, Vec4::ZERO)
                    }
                    InjectedLight::Spot { position, radius, color, direction, inner_angle, outer_angle } => {
                        let (cos_outer, cos_inner) = (outer_angle.cos(), inner_angle.cos());
                        let cone = direction.normalize().extend(cos_outer);
                        (
                            position.extend(radius),
                            color.extend(1.0),
                            cone,
                            Vec4::new(1.0 / (cos_inner - cos_outer).max(1e-4), 1.0, 0.0, 0.0),
                        )
                    }
                };
                let p = VolumeParams {
                    origin: origin.extend(cell),
                    light_position: position,
                    light_color: color,
                    cascade_view_proj: matrices,
                    cascade_splits: splits,
                    cascade_rects: rects,
                    spot_direction,
                    spot_angles,
                };
                queue.write_buffer(&injection.params, 0, bytemuck::bytes_of(&p));
                let Some(p) = self.inject[pipeline].ready(pl) else { continue };
                pass.set_pipeline(&p.pipeline);
                pass.set_bind_group(0, group, &[]);
                pass.dispatch_workgroups(n, n, n);
            }
        }
    }

    /// FilterTranslucentVolume: both cascades.
    pub fn record_filter(&self, ctx: &mut PassContext<'_>) {
        let n = groups(VOLUME_SIZE, 4);
        let ready = self.filter.ready(ctx.pipelines());
        let mut pass = ctx.open_compute_pass("FilterTranslucentVolume");
        let Some(p) = ready else { return };
        pass.set_pipeline(&p.pipeline);
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

    #[test]
    fn lookup_maps_each_cascade_box_to_the_unit_cube() {
        let camera = Vec3::new(-3.0, 3.4, 9.5);
        let p = LookupParams::new(camera);
        for c in 0..2 {
            let (origin, cell) = TranslucentVolumes::cascade_box(camera, c);
            let far_corner = origin + Vec3::splat(cell * VOLUME_SIZE as f32);
            let uvw = (far_corner - p.volume_min[c].truncate()) * p.volume_inv_size[c].truncate();
            assert!((uvw - Vec3::ONE).abs().max_element() < 1e-5, "{uvw}");
            let at_camera = (camera - p.volume_min[c].truncate()) * p.volume_inv_size[c].truncate();
            assert!((at_camera - Vec3::splat(0.5)).abs().max_element() <= 1.0 / VOLUME_SIZE as f32, "{at_camera}");
        }
        assert_eq!(std::mem::size_of::<LookupParams>(), 64);
    }
}
