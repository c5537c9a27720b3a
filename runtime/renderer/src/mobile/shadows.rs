//! ShadowDepths: the directional light's cascaded shadow maps (2 cascades by default, up to
//! 4) and spot light shadows, all in one depth atlas that the base pass samples with one
//! comparison sampler (the seed: "spotlight shadow and CSM use the same shadow map atlas").
//!
//! The atlas is reverse-Z like the scene depth (cleared to 0, nearer the light is larger).
//! Cascades are 1024-texel tiles, two per row; spot lights get 512-texel tiles in a row
//! below. Each cascade bounds a slice of the camera frustum with a sphere, seen along the
//! light by an orthographic projection deep enough to catch casters behind the slice.

use crate::gpu::BufferInit;
use bytemuck::{Pod, Zeroable};
use glam::camera::rh::proj::directx::{orthographic, perspective};
use glam::camera::rh::view::look_at_mat4;
use glam::{Mat4, Vec3, Vec4};

use crate::frame::{PassContext, PassDecl, PipelineDesc, VertexInput, Visualize};
use crate::keys;
use crate::pipelines::PipelineError;
use crate::scene::gpu::GpuScene;
use crate::scene::view::MAX_CASCADES;
use crate::scene::{BlendMode, Camera, Scene};

use super::pipeline::{Draw, MobilePipelines};
use super::{MobileOptions, Target, SHADOW_ATLAS_FORMAT};

/// The ShadowDepths pass: CSM cascades and spot shadows into one atlas.
pub const PASS: PassDecl = PassDecl { name: "ShadowDepths", reads: &["Scene"], writes: &["ShadowAtlas"] };

pub const CASCADE_TILE: u32 = 1024;
pub const SPOT_TILE: u32 = 512;
/// Spot light shadows the atlas holds (the seed's default limit of visible spot shadows is 8).
pub const MAX_SPOT_SHADOWS: usize = 4;

/// One tile of the atlas: where it is and how the world projects into it.
#[derive(Clone, Debug, PartialEq)]
pub struct ShadowTile {
    /// x, y, width, height in atlas texels.
    pub viewport: [u32; 4],
    /// World to the tile's clip space (what the depth pass renders with).
    pub view_proj: Mat4,
    /// World to atlas uv (xy) and depth (z), what the lighting samples with.
    pub atlas_matrix: Mat4,
    /// Camera view depth where the cascade ends (cascades only).
    pub far: f32,
    /// World units the casters move along their normals (normal offset bias).
    pub normal_offset: f32,
}

/// `DepthPass` of `MobileShadowDepth.usf`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct DepthPassUniforms {
    pub view_proj: Mat4,
    /// x = normal offset (world units)
    pub params: Vec4,
}

/// Where every shadow of the frame lives in the atlas.
#[derive(Clone, Debug, PartialEq)]
pub struct ShadowLayout {
    pub atlas_width: u32,
    pub atlas_height: u32,
    pub cascades: Vec<ShadowTile>,
    /// (spot light index in the scene, tile)
    pub spots: Vec<(usize, ShadowTile)>,
}

impl ShadowLayout {
    pub fn new(scene: &Scene, options: &MobileOptions, aspect: f32) -> ShadowLayout {
        let num_cascades = if options.csm && scene.sun.enabled && scene.sun.casts_shadows {
            options.cascades.clamp(1, MAX_CASCADES as u32)
        } else {
            0
        };
        let cascade_rows = num_cascades.div_ceil(2);
        let spot_indices: Vec<usize> = if options.spot_shadows {
            scene
                .spot_lights
                .iter()
                .enumerate()
                .filter(|(_, l)| l.casts_shadows)
                .map(|(i, _)| i)
                .take(MAX_SPOT_SHADOWS)
                .collect()
        } else {
            Vec::new()
        };
        let atlas_width = 2 * CASCADE_TILE;
        let atlas_height =
            (cascade_rows * CASCADE_TILE + if spot_indices.is_empty() { 0 } else { SPOT_TILE }).max(SPOT_TILE);
        let size = (atlas_width as f32, atlas_height as f32);
        let splits = cascade_splits(scene.camera.near, options.shadow_distance, num_cascades as usize);
        let cascades = (0..num_cascades as usize)
            .map(|i| {
                let viewport =
                    [(i as u32 % 2) * CASCADE_TILE, (i as u32 / 2) * CASCADE_TILE, CASCADE_TILE, CASCADE_TILE];
                let (view_proj, radius) =
                    cascade_view_proj(&scene.camera, aspect, splits[i], splits[i + 1], scene.sun.direction);
                ShadowTile {
                    viewport,
                    view_proj,
                    atlas_matrix: tile_matrix(viewport, size) * view_proj,
                    far: splits[i + 1],
                    normal_offset: 2.0 * radius / CASCADE_TILE as f32,
                }
            })
            .collect();
        let spots = spot_indices
            .iter()
            .enumerate()
            .map(|(slot, &i)| {
                let l = &scene.spot_lights[i];
                let viewport = [slot as u32 * SPOT_TILE, cascade_rows * CASCADE_TILE, SPOT_TILE, SPOT_TILE];
                let dir = l.direction.normalize();
                let up = if dir.y.abs() > 0.99 { Vec3::Z } else { Vec3::Y };
                let view = look_at_mat4(l.position, l.position + dir, up);
                // Reverse-Z perspective: the far plane (the light's radius) maps to 0.
                let proj = perspective(2.0 * l.outer_angle.min(1.5), 1.0, l.radius, 0.05);
                let view_proj = proj * view;
                (
                    i,
                    ShadowTile {
                        viewport,
                        view_proj,
                        atlas_matrix: tile_matrix(viewport, size) * view_proj,
                        far: l.radius,
                        normal_offset: 0.02,
                    },
                )
            })
            .collect();
        ShadowLayout { atlas_width, atlas_height, cascades, spots }
    }

    /// The atlas slot and matrix of spot light `index` (in scene order), if it casts a shadow.
    pub fn spot_tile(&self, index: usize) -> Option<(usize, Mat4)> {
        self.spots.iter().position(|(i, _)| *i == index).map(|slot| (slot, self.spots[slot].1.atlas_matrix))
    }

    pub fn tiles(&self) -> impl Iterator<Item = &ShadowTile> {
        self.cascades.iter().chain(self.spots.iter().map(|(_, t)| t))
    }
}

/// View depths where cascades begin and end: Unreal's mix of logarithmic and uniform splits.
pub fn cascade_splits(near: f32, far: f32, count: usize) -> Vec<f32> {
    let lambda = 0.8;
    (0..=count)
        .map(|i| {
            if i == 0 {
                return near;
            }
            let t = i as f32 / count as f32;
            let log = near * (far / near).powf(t);
            let uniform = near + (far - near) * t;
            lambda * log + (1.0 - lambda) * uniform
        })
        .collect()
}

/// The light's view-projection for one slice of the camera frustum, and its bounding radius.
fn cascade_view_proj(camera: &Camera, aspect: f32, near: f32, far: f32, light_direction: Vec3) -> (Mat4, f32) {
    let inv_view = camera.view().inverse();
    let tan = (camera.fov_y * 0.5).tan();
    let mut corners = Vec::with_capacity(8);
    for z in [near, far] {
        let (h, w) = (z * tan, z * tan * aspect);
        for (x, y) in [(-w, -h), (w, -h), (-w, h), (w, h)] {
            corners.push(inv_view.transform_point3(Vec3::new(x, y, -z)));
        }
    }
    let center = corners.iter().copied().sum::<Vec3>() / corners.len() as f32;
    let radius = corners.iter().map(|c| c.distance(center)).fold(0.0, f32::max).max(0.5);
    let d = light_direction.normalize();
    let up = if d.y.abs() > 0.99 { Vec3::Z } else { Vec3::Y };
    // Casters up to this far behind the slice (towards the light) still land in the map.
    let caster_margin = 20.0;
    let eye = center - d * (radius + caster_margin);
    let view = look_at_mat4(eye, center, up);
    let depth = 2.0 * radius + caster_margin;
    let proj = orthographic(-radius, radius, -radius, radius, depth, 0.0);
    (proj * view, radius)
}

/// Clip space of a tile to atlas uv: x, y from [-1, 1] (y up) to the tile's texels.
fn tile_matrix(viewport: [u32; 4], size: (f32, f32)) -> Mat4 {
    let sx = viewport[2] as f32 / size.0;
    let sy = viewport[3] as f32 / size.1;
    let ox = viewport[0] as f32 / size.0;
    let oy = viewport[1] as f32 / size.1;
    Mat4::from_cols(
        Vec4::new(0.5 * sx, 0.0, 0.0, 0.0),
        Vec4::new(0.0, -0.5 * sy, 0.0, 0.0),
        Vec4::new(0.0, 0.0, 1.0, 0.0),
        Vec4::new(0.5 * sx + ox, 0.5 * sy + oy, 0.0, 1.0),
    )
}

/// The ShadowDepths pass: every shadow-casting opaque or masked mesh into every tile.
pub struct ShadowDepths {
    /// (tile viewport, draw with the tile's uniforms)
    tiles: Vec<([u32; 4], Draw)>,
    casters: Vec<usize>,
    _uniforms: Vec<wgpu::Buffer>,
}

impl ShadowDepths {
    pub fn new(
        pipelines: &MobilePipelines<'_>,
        scene: &GpuScene,
        layout: &ShadowLayout,
    ) -> Result<ShadowDepths, PipelineError> {
        let vs = keys::name(keys::mobile_shadow_depth_vs::Key {}, keys::Level::Es31)?;
        let mut desc = PipelineDesc::new(&vs, None, VertexInput::MeshInstanced);
        desc.depth_stencil = Some(wgpu::DepthStencilState {
            format: SHADOW_ATLAS_FORMAT,
            depth_write_enabled: Some(true),
            depth_compare: Some(wgpu::CompareFunction::GreaterEqual),
            stencil: Default::default(),
            // Reverse-Z: sloped casters move away from the light (smaller depth).
            bias: wgpu::DepthBiasState { constant: 0, slope_scale: -1.5, clamp: 0.0 },
        });
        let pipeline = pipelines.get(&desc)?;
        let mut tiles = Vec::new();
        let mut uniforms = Vec::new();
        for (i, tile) in layout.tiles().enumerate() {
            let u =
                DepthPassUniforms { view_proj: tile.view_proj, params: Vec4::new(tile.normal_offset, 0.0, 0.0, 0.0) };
            let buffer = pipelines.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(&format!("ShadowDepths tile {i}")),
                contents: bytemuck::bytes_of(&u),
                usage: wgpu::BufferUsages::UNIFORM,
            });
            tiles.push((
                tile.viewport,
                Draw::new(pipelines.device, pipeline.clone(), &[("Pass", buffer.as_entire_binding())])?,
            ));
            uniforms.push(buffer);
        }
        let casters = scene
            .objects
            .iter()
            .enumerate()
            .filter(|(_, o)| o.casts_shadow && scene.material(o).blend != BlendMode::Translucent)
            .map(|(i, _)| i)
            .collect();
        Ok(ShadowDepths { tiles, casters, _uniforms: uniforms })
    }

    /// Writes (clears) the atlas.
    pub fn record(&self, ctx: &mut PassContext<'_>, scene: &GpuScene, atlas: &Target) {
        let pl = ctx.pipelines();
        {
            ctx.render_pass(
                &wgpu::RenderPassDescriptor {
                    label: Some("ShadowDepths"),
                    color_attachments: &[],
                    depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                        view: &atlas.view,
                        depth_ops: Some(wgpu::Operations {
                            load: wgpu::LoadOp::Clear(0.0),
                            store: wgpu::StoreOp::Store,
                        }),
                        stencil_ops: None,
                    }),
                    timestamp_writes: None,
                    occlusion_query_set: None,
                    multiview_mask: None,
                },
                |pass| {
                    for (viewport, draw) in &self.tiles {
                        pass.set_viewport(
                            viewport[0] as f32,
                            viewport[1] as f32,
                            viewport[2] as f32,
                            viewport[3] as f32,
                            0.0,
                            1.0,
                        );
                        if !draw.bind(pl, pass) {
                            continue;
                        }
                        for &i in &self.casters {
                            scene.draw(pass, &scene.objects[i]);
                        }
                    }
                },
            );
        }
        ctx.output(&atlas.texture, Visualize::Depth);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_pass_uniforms_match_the_wgsl_struct() {
        assert_eq!(std::mem::size_of::<DepthPassUniforms>(), 80);
    }

    #[test]
    fn splits_cover_near_to_far_and_grow() {
        let s = cascade_splits(0.1, 30.0, 2);
        assert_eq!(s.len(), 3);
        assert_eq!(s[0], 0.1);
        assert!((s[2] - 30.0).abs() < 1e-3);
        assert!(s[1] > s[0] && s[1] < s[2]);
        // Logarithmic weighting: the first cascade is much shorter than half the range.
        assert!(s[1] < 15.0, "{s:?}");
    }

    #[test]
    fn tile_matrix_maps_clip_corners_to_the_tile() {
        let m = tile_matrix([1024, 0, 1024, 1024], (2048.0, 1536.0));
        let tl = m.project_point3(Vec3::new(-1.0, 1.0, 0.5));
        let br = m.project_point3(Vec3::new(1.0, -1.0, 0.5));
        assert!((tl.x - 0.5).abs() < 1e-6 && tl.y.abs() < 1e-6 && (tl.z - 0.5).abs() < 1e-6, "{tl}");
        assert!((br.x - 1.0).abs() < 1e-6 && (br.y - 1024.0 / 1536.0).abs() < 1e-6, "{br}");
    }

    #[test]
    fn cascades_see_the_camera_slice_in_reverse_z() {
        let scene = Scene::bundled();
        let options = MobileOptions::default();
        let layout = ShadowLayout::new(&scene, &options, 16.0 / 9.0);
        assert_eq!(layout.cascades.len(), 2);
        // A point in the middle of each cascade's slice of the view is inside its box, and
        // a point nearer the light has a larger depth.
        let camera = &scene.camera;
        let forward = (camera.target - camera.position).normalize();
        let splits = cascade_splits(camera.near, options.shadow_distance, 2);
        for (i, c) in layout.cascades.iter().enumerate() {
            let inside = camera.position + forward * (splits[i] + splits[i + 1]) * 0.5;
            let p = c.view_proj.project_point3(inside);
            assert!(p.x.abs() <= 1.0 && p.y.abs() <= 1.0 && (0.0..=1.0).contains(&p.z), "cascade {i}: {p}");
            let towards_light = c.view_proj.project_point3(inside - scene.sun.direction);
            assert!(towards_light.z > p.z, "cascade {i}: reverse-Z");
            assert_eq!(c.far, splits[i + 1]);
        }
    }
}
