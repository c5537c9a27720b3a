//! ShadowDepths: depth-only shadow maps, vertex shader only (`ShadowDepthVS`).
//!   Atlas0: the directional light's 3 cascades side by side (3x1), orthographic, casters in
//!     front of a cascade clamped onto its near plane.
//!   Atlas1: per-object shadows of stationary lights, one tile per (light, movable prop).
//!   `Cubemap_<light>`: a movable point light's six faces (6x1), whole scene.
//! A local light whose ShadowFrustumQuery came back with zero samples renders none of its
//! shadow views that frame (its `PerObject_<light>` step of Atlas1, its `Cubemap_<light>` step
//! and the copy of its cached static depth are absent; the cache itself stays valid).
//! The matrices are also what ShadowProjectionOnOpaque and the translucency read back.

use glam::camera::rh::proj::directx;
use glam::camera::rh::view::{look_at_mat4, look_to_mat4};
use glam::{Mat4, Vec3, Vec4};

use crate::frame::{FramePipelines, PassContext, PassDecl, PipelineDesc, RenderSlot, VertexInput, Visualize};
use crate::keys;

use super::pipelines::{BindGroups, DesktopLayout};
use super::resources::{begin, formats, LocalShadow, SceneBuffers, Texture};
use super::view::{FrameView, ShadowDepthPassUniforms, ShadowProjectionUniforms};
use super::{DesktopError, PassSetup};
use crate::gpu_types::uniform_buffer;
use std::sync::Arc;

/// Skips the lights whose ShadowFrustumQueries came back empty.
pub const PASS: PassDecl =
    PassDecl { name: "ShadowDepths", reads: &["Scene", "OcclusionQueries"], writes: &["ShadowDepths"] };

/// View depths where the cascades end (the first starts at the near plane).
pub const CASCADE_SPLITS: [f32; 3] = [6.0, 14.0, 32.0];
const CASCADES: usize = 3;

/// One shadow view rendered into a tile of an atlas.
struct ShadowView {
    viewport: [f32; 4],
    groups: BindGroups,
    /// Draws into this view (indices into `SceneBuffers::draws`).
    draws: Vec<usize>,
    /// The local light this view belongs to (`None`: the directional light's cascades).
    light: Option<usize>,
}

struct Atlas {
    step: String,
    texture: Texture,
    pipeline: Arc<RenderSlot>,
    views: Vec<ShadowView>,
    /// Cube shadows of movable lights: the static casters' depth, cached (effects).
    cache: Option<CubeCache>,
}

/// The cached static depth of a movable point light's cube shadow (CopyCachedShadowMap):
/// rendered once with the static casters, copied into the cube every frame, the movable
/// props drawn on top; rendered again only when invalidated (the light moved).
struct CubeCache {
    texture: Texture,
    /// CopyCachedShadowMap: a full-atlas draw writing the cached depth with frag_depth.
    copy: Arc<RenderSlot>,
    copy_groups: BindGroups,
    /// Per view (face): the static casters; `ShadowView::draws` keeps the movable ones.
    static_draws: Vec<Vec<usize>>,
    valid: std::sync::atomic::AtomicBool,
    rebuilds: std::sync::atomic::AtomicU32,
}

/// The projections lighting needs, per shadowed light.
#[derive(Clone, Debug, Default)]
pub struct ShadowSetup {
    /// The directional light's cascades.
    pub cascaded: Option<ShadowProjectionUniforms>,
    /// (light index, projection) per per-object shadow tile.
    pub per_object: Vec<(usize, ShadowProjectionUniforms)>,
    /// (light index, index into `ShadowDepths::cube_atlases`, projection).
    pub cubes: Vec<(usize, usize, ShadowProjectionUniforms)>,
}

pub struct ShadowDepths {
    atlases: Vec<Atlas>,
    /// The local lights' names (step names of their shadow views).
    light_names: Vec<String>,
    pub setup: ShadowSetup,
    /// Index of the cascade atlas in `atlases`.
    csm: Option<usize>,
    per_object: Option<usize>,
    cubes: Vec<usize>,
    /// The cascades' `ShadowDepthPass` buffers, refitted to the camera every frame.
    cascade_buffers: Vec<wgpu::Buffer>,
    sun_direction: Vec3,
    shadow_map_size: u32,
}

fn up_for(dir: Vec3) -> Vec3 {
    if dir.normalize().y.abs() > 0.99 {
        Vec3::X
    } else {
        Vec3::Y
    }
}

/// Ortho projections of the cascades: each fits the bounding sphere of its slice of the
/// camera frustum, seen along the light.
pub fn cascade_matrices(view: &FrameView, light_direction: Vec3) -> [Mat4; CASCADES] {
    let inv_view = view.view.inverse();
    let mut out = [Mat4::IDENTITY; CASCADES];
    let mut near = view.near;
    for (i, far) in CASCADE_SPLITS.iter().enumerate() {
        let mut corners = Vec::with_capacity(8);
        for d in [near, *far] {
            for (x, y) in [(-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0)] {
                let p = Vec3::new(x * d / view.proj.x_axis.x, y * d / view.proj.y_axis.y, -d);
                corners.push(inv_view.transform_point3(p));
            }
        }
        let center = corners.iter().copied().sum::<Vec3>() / corners.len() as f32;
        let radius = corners.iter().map(|c| c.distance(center)).fold(0.0, f32::max);
        let back = 20.0;
        let dir = light_direction.normalize();
        let light_view = look_at_mat4(center - dir * (radius + back), center, up_for(dir));
        let proj = directx::orthographic(-radius, radius, -radius, radius, 0.0, 2.0 * radius + back);
        out[i] = proj * light_view;
        near = *far;
    }
    out
}

/// The cascaded shadow's projection uniforms for `view` (and the cascades' matrices): what
/// ShadowProjectionOnOpaque, the forward-lit translucency and the effects read. `size`: one
/// cascade's side in texels.
pub fn cascaded_uniforms(
    view: &FrameView,
    light_direction: Vec3,
    size: u32,
) -> (ShadowProjectionUniforms, [Mat4; CASCADES]) {
    let matrices = cascade_matrices(view, light_direction);
    let mut u = ShadowProjectionUniforms {
        cascade_far_depths: Vec4::new(CASCADE_SPLITS[0], CASCADE_SPLITS[1], CASCADE_SPLITS[2], CASCADES as f32),
        params: Vec4::new(0.0005, 2.0, 0.0, 0.0),
        ..Default::default()
    };
    for (i, m) in matrices.iter().enumerate() {
        // World size of one shadow texel of this cascade (its box is 2r wide).
        u.light_position[i] = 2.0 / m.row(0).truncate().length() / size as f32;
        u.world_to_shadow[i] = *m;
        u.atlas_rects[i] = Vec4::new(i as f32 / CASCADES as f32, 0.0, 1.0 / CASCADES as f32, 1.0);
    }
    (u, matrices)
}

/// The six face projections of a point light (+x, -x, +y, -y, +z, -z).
pub fn cube_face_matrices(position: Vec3, radius: f32) -> [Mat4; 6] {
    let faces = [
        (Vec3::X, Vec3::NEG_Y),
        (Vec3::NEG_X, Vec3::NEG_Y),
        (Vec3::Y, Vec3::Z),
        (Vec3::NEG_Y, Vec3::NEG_Z),
        (Vec3::Z, Vec3::NEG_Y),
        (Vec3::NEG_Z, Vec3::NEG_Y),
    ];
    let proj = directx::perspective(std::f32::consts::FRAC_PI_2, 1.0, 0.05, radius.max(0.1));
    faces.map(|(dir, up)| proj * look_to_mat4(position, dir, up))
}

/// A perspective shadow frustum from a light position around a bounding sphere.
pub fn per_object_matrix(light: Vec3, light_radius: f32, center: Vec3, radius: f32) -> Option<Mat4> {
    let d = light.distance(center);
    if d <= radius * 1.05 {
        return None;
    }
    let half = (radius / d).asin() * 1.1;
    let near = ((d - radius) * 0.9).max(0.05);
    let far = light_radius.max(d + radius);
    Some(directx::perspective(2.0 * half, 1.0, near, far) * look_at_mat4(light, center, up_for(center - light)))
}

/// The depth-only pipeline of the shadow views (`perspective`: point and spot lights).
fn depth_pipeline(b: &PassSetup<'_>, perspective: bool) -> Result<Arc<RenderSlot>, DesktopError> {
    let p = b.pipelines;
    let name = keys::name(keys::shadow_depth_vs::Key { perspective_correct_depth: perspective }, p.key_level()?)?;
    p.render(&PipelineDesc {
        depth_stencil: Some(wgpu::DepthStencilState {
            format: formats::SHADOW_DEPTH,
            depth_write_enabled: Some(true),
            depth_compare: Some(wgpu::CompareFunction::LessEqual),
            stencil: wgpu::StencilState::default(),
            bias: wgpu::DepthBiasState { constant: 0, slope_scale: 1.0, clamp: 0.0 },
        }),
        ..PipelineDesc::new(&name, None, VertexInput::Mesh)
    })
}

/// The bind groups of one shadow view (its `ShadowDepthPass` matrix `m`), and that buffer.
fn view_groups(
    b: &PassSetup<'_>,
    pipeline: &RenderSlot,
    m: Mat4,
    label: &str,
) -> Result<(BindGroups, wgpu::Buffer), DesktopError> {
    let buffer = uniform_buffer(b.device, label, &ShadowDepthPassUniforms { view_proj: m });
    let groups = pipeline.layout.bind_groups(
        b.device,
        &[("ShadowDepthPass", buffer.as_entire_binding()), ("Instances", b.buffers.instances.as_entire_binding())],
    )?;
    Ok((groups.keeping(buffer.clone()), buffer))
}

/// The directional light's cascades side by side, with their projection uniforms and the
/// `ShadowDepthPass` buffers that follow the camera.
fn cascade_atlas(
    b: &PassSetup<'_>,
    ortho: &Arc<RenderSlot>,
    casters: &[usize],
    size: u32,
) -> Result<(Atlas, ShadowProjectionUniforms, Vec<wgpu::Buffer>), DesktopError> {
    let (u, matrices) = cascaded_uniforms(b.view, b.scene.sun.direction, size);
    let mut views = Vec::new();
    let mut buffers = Vec::new();
    for (i, m) in matrices.iter().enumerate() {
        let (groups, buffer) = view_groups(b, ortho, *m, &format!("Cascade{i}"))?;
        buffers.push(buffer);
        views.push(ShadowView {
            viewport: [(i as u32 * size) as f32, 0.0, size as f32, size as f32],
            groups,
            draws: casters.to_vec(),
            light: None,
        });
    }
    let atlas = Atlas {
        step: "Atlas0".into(),
        texture: shadow_texture(b.device, "ShadowDepthAtlas0", size * CASCADES as u32, size),
        pipeline: ortho.clone(),
        views,
        cache: None,
    };
    Ok((atlas, u, buffers))
}

/// One tile per (stationary light, movable caster in its reach); their projections go to
/// `projections`. `None` without such a pair.
fn per_object_atlas(
    b: &PassSetup<'_>,
    perspective: &Arc<RenderSlot>,
    casters: &[usize],
    tile: u32,
    projections: &mut Vec<(usize, ShadowProjectionUniforms)>,
) -> Result<Option<Atlas>, DesktopError> {
    let movable: Vec<usize> = casters.iter().copied().filter(|i| b.buffers.draws[*i].movable).collect();
    let mut tiles = Vec::new();
    for (li, light) in b.lights.iter().enumerate().filter(|(_, l)| l.shadow == LocalShadow::PerObject) {
        for &di in &movable {
            let (center, radius) = b.buffers.draws[di].bounds;
            if light.position().distance(center) > light.radius() + radius {
                continue;
            }
            if let Some(m) = per_object_matrix(light.position(), light.radius(), center, radius) {
                tiles.push((li, di, m));
            }
        }
    }
    if tiles.is_empty() {
        return Ok(None);
    }
    let n = tiles.len() as u32;
    let mut views = Vec::new();
    for (k, (li, di, m)) in tiles.iter().enumerate() {
        let mut u = ShadowProjectionUniforms {
            light_position: b.lights[*li].position().extend(1.0),
            params: Vec4::new(0.0003, 0.02, 0.0, 0.0),
            ..Default::default()
        };
        u.world_to_shadow[0] = *m;
        u.atlas_rects[0] = Vec4::new(k as f32 / n as f32, 0.0, 1.0 / n as f32, 1.0);
        projections.push((*li, u));
        views.push(ShadowView {
            viewport: [(k as u32 * tile) as f32, 0.0, tile as f32, tile as f32],
            groups: view_groups(b, perspective, *m, &format!("PerObject{k}"))?.0,
            draws: vec![*di],
            light: Some(*li),
        });
    }
    Ok(Some(Atlas {
        step: "Atlas1".into(),
        texture: shadow_texture(b.device, "ShadowDepthAtlas1", tile * n, tile),
        pipeline: perspective.clone(),
        views,
        cache: None,
    }))
}

/// A movable point light's six faces (its movable casters) over a cached depth of the static
/// ones, with the light's projection uniforms.
fn cube_atlas(
    b: &PassSetup<'_>,
    perspective: &Arc<RenderSlot>,
    casters: &[usize],
    tile: u32,
    (li, light): (usize, &super::resources::FrameLight),
) -> Result<(Atlas, ShadowProjectionUniforms), DesktopError> {
    let matrices = cube_face_matrices(light.position(), light.radius());
    let mut u = ShadowProjectionUniforms {
        light_position: light.position().extend(1.0),
        params: Vec4::new(0.0002, 0.03, 0.0, 0.0),
        ..Default::default()
    };
    let mut views = Vec::new();
    let (movable_casters, static_casters): (Vec<usize>, Vec<usize>) =
        casters.iter().partition(|&&d| b.buffers.draws[d].movable);
    for (f, m) in matrices.iter().enumerate() {
        u.world_to_shadow[f] = *m;
        u.atlas_rects[f] = Vec4::new(f as f32 / 6.0, 0.0, 1.0 / 6.0, 1.0);
        views.push(ShadowView {
            viewport: [(f as u32 * tile) as f32, 0.0, tile as f32, tile as f32],
            groups: view_groups(b, perspective, *m, &format!("{} face {f}", light.name))?.0,
            draws: movable_casters.clone(),
            light: Some(li),
        });
    }
    let cache = cube_cache(b, light, static_casters, tile)?;
    let usage = wgpu::TextureUsages::RENDER_ATTACHMENT
        | wgpu::TextureUsages::TEXTURE_BINDING
        | wgpu::TextureUsages::COPY_SRC
        | wgpu::TextureUsages::COPY_DST;
    let texture = Texture::new(
        b.device,
        &format!("ShadowDepthCube {}", light.name),
        formats::SHADOW_DEPTH,
        tile * 6,
        tile,
        usage,
    );
    let atlas = Atlas {
        step: format!("Cubemap_{}", light.name),
        texture,
        pipeline: perspective.clone(),
        views,
        cache: Some(cache),
    };
    Ok((atlas, u))
}

/// The static casters' depth of a cube, rendered once, and the draw that copies it into the
/// cube each frame.
fn cube_cache(
    b: &PassSetup<'_>,
    light: &super::resources::FrameLight,
    static_casters: Vec<usize>,
    tile: u32,
) -> Result<CubeCache, DesktopError> {
    let p = b.pipelines;
    let cached = shadow_texture(b.device, &format!("CachedShadowDepthCube {}", light.name), tile * 6, tile);
    let copy = p.render(&PipelineDesc {
        depth_stencil: Some(wgpu::DepthStencilState {
            format: formats::SHADOW_DEPTH,
            depth_write_enabled: Some(true),
            depth_compare: Some(wgpu::CompareFunction::Always),
            stencil: Default::default(),
            bias: Default::default(),
        }),
        ..PipelineDesc::new(
            &keys::name(keys::copy_cached_shadow_map_vs::Key {}, p.key_level()?)?,
            Some(&keys::name(keys::copy_cached_shadow_map_ps::Key {}, p.key_level()?)?),
            VertexInput::None,
        )
    })?;
    let copy_groups = copy
        .layout
        .bind_groups(b.device, &[("CachedShadowDepthTexture", wgpu::BindingResource::TextureView(&cached.view))])?;
    Ok(CubeCache {
        texture: cached,
        copy,
        copy_groups,
        static_draws: vec![static_casters; 6],
        valid: std::sync::atomic::AtomicBool::new(false),
        rebuilds: std::sync::atomic::AtomicU32::new(0),
    })
}

impl ShadowDepths {
    pub fn new(b: &PassSetup<'_>) -> Result<ShadowDepths, DesktopError> {
        let ortho = depth_pipeline(b, false)?;
        let perspective = depth_pipeline(b, true)?;
        let casters: Vec<usize> =
            b.buffers.draws.iter().enumerate().filter(|(_, d)| d.casts_shadow).map(|(i, _)| i).collect();
        let size = b.options.shadow_map_size;
        let tile = (size / 2).max(64);
        let mut atlases = Vec::new();
        let mut setup = ShadowSetup::default();
        let (mut csm, mut per_object, mut cubes) = (None, None, Vec::new());
        let mut cascade_buffers = Vec::new();
        if b.scene.sun.enabled && b.scene.sun.casts_shadows {
            let (atlas, u, buffers) = cascade_atlas(b, &ortho, &casters, size)?;
            setup.cascaded = Some(u);
            cascade_buffers = buffers;
            csm = Some(atlases.len());
            atlases.push(atlas);
        }
        if let Some(atlas) = per_object_atlas(b, &perspective, &casters, tile, &mut setup.per_object)? {
            per_object = Some(atlases.len());
            atlases.push(atlas);
        }
        for (li, light) in b.lights.iter().enumerate().filter(|(_, l)| l.shadow == LocalShadow::Cube) {
            let (atlas, u) = cube_atlas(b, &perspective, &casters, tile, (li, light))?;
            setup.cubes.push((li, cubes.len(), u));
            cubes.push(atlases.len());
            atlases.push(atlas);
        }
        Ok(ShadowDepths {
            atlases,
            light_names: b.lights.iter().map(|l| l.name.clone()).collect(),
            setup,
            csm,
            per_object,
            cubes,
            cascade_buffers,
            sun_direction: b.scene.sun.direction,
            shadow_map_size: size,
        })
    }

    /// Refits the cascades to this frame's camera: rewrites their `ShadowDepthPass`
    /// matrices and returns the projection uniforms the readers of the cascades bind this
    /// frame (`None` without cascades). The local lights' shadows do not depend on the camera.
    pub fn update_cascades(&self, queue: &wgpu::Queue, view: &FrameView) -> Option<ShadowProjectionUniforms> {
        self.csm?;
        let (u, matrices) = cascaded_uniforms(view, self.sun_direction, self.shadow_map_size);
        for (buffer, m) in self.cascade_buffers.iter().zip(matrices) {
            queue.write_buffer(buffer, 0, bytemuck::bytes_of(&ShadowDepthPassUniforms { view_proj: m }));
        }
        Some(u)
    }

    /// The cascade atlas (a 1x1 cleared map when the directional light casts none).
    pub fn csm_texture(&self) -> Option<&Texture> {
        self.csm.map(|i| &self.atlases[i].texture)
    }

    pub fn per_object_texture(&self) -> Option<&Texture> {
        self.per_object.map(|i| &self.atlases[i].texture)
    }

    pub fn cube_texture(&self, cube: usize) -> &Texture {
        &self.atlases[self.cubes[cube]].texture
    }

    /// How many times the cube shadows' cached static depth was rendered (all cubes).
    pub fn cached_shadow_rebuilds(&self) -> u32 {
        self.atlases
            .iter()
            .filter_map(|a| a.cache.as_ref())
            .map(|c| c.rebuilds.load(std::sync::atomic::Ordering::Relaxed))
            .sum()
    }

    /// The movable lights moved: their cached static depth is rendered again next frame.
    pub fn invalidate_cached_shadows(&self) {
        for c in self.atlases.iter().filter_map(|a| a.cache.as_ref()) {
            c.valid.store(false, std::sync::atomic::Ordering::Relaxed);
        }
    }

    /// Records every atlas. `casts_shadow(light)`: whether local light `light` renders its
    /// shadow views this frame (ShadowFrustumQueries); the cascades always render.
    pub fn record(&self, ctx: &mut PassContext<'_>, scene: &SceneBuffers, casts_shadow: &dyn Fn(usize) -> bool) {
        for (index, atlas) in self.atlases.iter().enumerate() {
            if Some(index) == self.per_object {
                ctx.step(&atlas.step, |ctx| self.record_per_object(ctx, scene, atlas, casts_shadow));
                continue;
            }
            // a cube shadow whose light is occluded: no step at all (its cache stays valid)
            if atlas.views.first().and_then(|v| v.light).is_some_and(|l| !casts_shadow(l)) {
                continue;
            }
            ctx.step(&atlas.step, |ctx| Self::record_atlas(ctx, scene, atlas));
        }
    }

    /// One tile per (stationary light, movable prop): one step per light whose shadow is not
    /// occluded, the first clearing the atlas.
    fn record_per_object(
        &self,
        ctx: &mut PassContext<'_>,
        scene: &SceneBuffers,
        atlas: &Atlas,
        casts_shadow: &dyn Fn(usize) -> bool,
    ) {
        let pl = ctx.pipelines();
        let mut lights: Vec<usize> = atlas.views.iter().filter_map(|v| v.light).collect();
        lights.dedup();
        let mut cleared = false;
        for light in lights.into_iter().filter(|l| casts_shadow(*l)) {
            let name = self.light_names.get(light).map_or("", String::as_str);
            let load = if cleared { wgpu::LoadOp::Load } else { wgpu::LoadOp::Clear(1.0) };
            ctx.step(&format!("PerObject_{name}"), |ctx| {
                let mut pass = begin(ctx, &format!("PerObject {name}"), &[], depth(&atlas.texture.view, load));
                draw_views(pl, scene, &mut pass, atlas, &|v| v.light == Some(light), &|_, v| v.draws.clone());
            });
            cleared = true;
        }
        if !cleared {
            // every light occluded: the atlas is only cleared
            begin(ctx, &atlas.step, &[], depth(&atlas.texture.view, wgpu::LoadOp::Clear(1.0)));
        }
        ctx.output(&atlas.texture.texture, Visualize::Depth);
    }

    /// The cascades, or a cube: over its cached static depth where it has one.
    fn record_atlas(ctx: &mut PassContext<'_>, scene: &SceneBuffers, atlas: &Atlas) {
        let pl = ctx.pipelines();
        let mut load = wgpu::LoadOp::Clear(1.0);
        if let Some(cache) = &atlas.cache {
            if !cache.valid.load(std::sync::atomic::Ordering::Relaxed) {
                // the static casters, rendered once into the cache
                let mut pass =
                    begin(ctx, "CachedShadowDepth", &[], depth(&cache.texture.view, wgpu::LoadOp::Clear(1.0)));
                if draw_views(pl, scene, &mut pass, atlas, &|_| true, &|i, _| cache.static_draws[i].clone()) {
                    cache.valid.store(true, std::sync::atomic::Ordering::Relaxed);
                    cache.rebuilds.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                }
            }
            ctx.step("CopyCachedShadowMap", |ctx| {
                {
                    let mut pass =
                        begin(ctx, "CopyCachedShadowMap", &[], depth(&atlas.texture.view, wgpu::LoadOp::Clear(1.0)));
                    if let Some(p) = cache.copy.ready(pl) {
                        pass.set_pipeline(&p.pipeline);
                        cache.copy_groups.set_render(&mut pass);
                        pass.draw(0..3, 0..1);
                    }
                }
                ctx.output(&atlas.texture.texture, Visualize::Depth);
            });
            load = wgpu::LoadOp::Load;
        }
        {
            let mut pass = begin(ctx, &atlas.step, &[], depth(&atlas.texture.view, load));
            draw_views(pl, scene, &mut pass, atlas, &|_| true, &|_, v| v.draws.clone());
        }
        ctx.output(&atlas.texture.texture, Visualize::Depth);
    }
}

/// Draws the views of `atlas` that `keep` selects, each its `draws`; `false` (nothing drawn)
/// while the atlas's pipeline is not ready.
fn draw_views(
    pl: FramePipelines<'_>,
    scene: &SceneBuffers,
    pass: &mut wgpu::RenderPass<'_>,
    atlas: &Atlas,
    keep: &dyn Fn(&ShadowView) -> bool,
    draws: &dyn Fn(usize, &ShadowView) -> Vec<usize>,
) -> bool {
    let Some(pipeline) = atlas.pipeline.ready(pl) else { return false };
    pass.set_pipeline(&pipeline.pipeline);
    for (i, v) in atlas.views.iter().enumerate().filter(|(_, v)| keep(v)) {
        let [x, y, w, h] = v.viewport;
        pass.set_viewport(x, y, w, h, 0.0, 1.0);
        v.groups.set_render(pass);
        for d in draws(i, v) {
            scene.draw(pass, &scene.draws[d]);
        }
    }
    true
}

/// A shadow map as the pass's depth target, stored.
fn depth(view: &wgpu::TextureView, load: wgpu::LoadOp<f32>) -> Option<wgpu::RenderPassDepthStencilAttachment<'_>> {
    Some(wgpu::RenderPassDepthStencilAttachment {
        view,
        depth_ops: Some(wgpu::Operations { load, store: wgpu::StoreOp::Store }),
        stencil_ops: None,
    })
}

fn shadow_texture(device: &wgpu::Device, label: &str, width: u32, height: u32) -> Texture {
    Texture::target(device, label, formats::SHADOW_DEPTH, width, height)
}

/// A 1x1 shadow map cleared to "unshadowed" for bindings without a real one.
pub fn dummy_shadow_texture(device: &wgpu::Device, queue: &wgpu::Queue) -> Texture {
    let t = shadow_texture(device, "NoShadowDepth", 1, 1);
    let mut encoder =
        device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("clear NoShadowDepth") });
    // made once with the renderer, outside any frame: no pass context to record through
    encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
        label: Some("clear NoShadowDepth"),
        color_attachments: &[],
        depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
            view: &t.view,
            depth_ops: Some(wgpu::Operations { load: wgpu::LoadOp::Clear(1.0), store: wgpu::StoreOp::Store }),
            stencil_ops: None,
        }),
        timestamp_writes: None,
        occlusion_query_set: None,
        multiview_mask: None,
    });
    queue.submit([encoder.finish()]);
    t
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cube_faces_see_their_own_axis() {
        let m = cube_face_matrices(Vec3::ZERO, 10.0);
        for (f, dir) in [Vec3::X, Vec3::NEG_X, Vec3::Y, Vec3::NEG_Y, Vec3::Z, Vec3::NEG_Z].iter().enumerate() {
            let p = m[f].project_point3(*dir * 3.0);
            assert!(p.x.abs() < 1e-4 && p.y.abs() < 1e-4 && p.z > 0.0 && p.z < 1.0, "face {f}: {p}");
        }
    }

    #[test]
    fn cascades_cover_their_slice_of_the_view() {
        let scene = crate::scene::Scene::bundled();
        let view = FrameView::new(&scene, 320, 180);
        let m = cascade_matrices(&view, scene.sun.direction);
        // The point the camera looks at, 10 m away or so, lies inside cascade 1's box.
        let target = scene.camera.target;
        let depth = -(view.view.transform_point3(target)).z;
        let c = CASCADE_SPLITS.iter().position(|s| depth < *s).unwrap();
        let p = m[c].project_point3(target);
        assert!(p.x.abs() <= 1.0 && p.y.abs() <= 1.0 && (0.0..=1.0).contains(&p.z), "cascade {c}: {p}");
    }
}
