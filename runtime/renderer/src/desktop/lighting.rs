//! Lighting: direct light into SceneColor, as Unreal's deferred renderer does it.
//!   NonShadowedLights: each unshadowed local light drawn as a sphere around its attenuation
//!     radius (front faces with the depth test, or back faces when the camera is inside),
//!     pixels outside the sphere's depth range rejected (the seeds' depth bounds test); both
//!     the inside test and the depth range are the frame's camera's ([`Lighting::update`]),
//!     stencil limited to lit pixels. Above `DesktopOptions::tiled_threshold` lights, all of
//!     them in one `TiledDeferredLightingCS` dispatch instead.
//!   ShadowedLights, per light: ShadowProjectionOnOpaque (the screen-space shadow mask,
//!     cleared to 1, projections blended with Min), then StandardDeferredLighting reading it.
//!   A local light whose ShadowFrustumQuery came back with 0 samples has no shadow to project
//!     this frame: as in Unreal (a light is sorted among the shadowed ones only while it has a
//!     visible projected shadow, `CheckForProjectedShadows`), it is drawn with the
//!     NonShadowedLights, without a shadow mask, and its ShadowProjectionOnOpaque and
//!     StandardDeferredLighting steps are absent. Its draw shades no pixel then (the query
//!     proved every surface inside its bounds hidden), but the light is not dropped: the
//!     query's answer is a frame old, and Unreal does not cull lights on it either.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use glam::{UVec4, Vec3, Vec4};

use crate::frame::{
    blended, ComputeSlot, FramePipelines, PassContext, PassDecl, PipelineDesc, RenderSlot, VertexInput, Visualize,
};
use crate::keys;
use crate::keys::shadow_projection_ps::ShadowProjectionType;
use crate::keys::standard_deferred_lighting_ps::LightType;

use super::pipelines::{blend, BindGroups, DesktopLayout};
use super::resources::{
    begin, color_attachment, formats, read_only_depth, stencil_lit_only, FrameLight, LocalShadow, SceneBuffers,
    Targets, Texture,
};
use super::shadow_depths::ShadowDepths;
use super::view::{DeferredLightUniforms, FrameView, LocalLightGpu, ShadowProjectionUniforms, TiledLightingUniforms};
use super::{DesktopError, LightingPath, PassSetup};
use crate::gpu_types::uniform_buffer;

/// The Lighting declaration.
pub const PASS: PassDecl = PassDecl {
    name: "Lighting",
    reads: &["Scene", "View", "SceneDepth", "GBufferA", "GBufferB", "GBufferC", "ShadowDepths", "SceneColor"],
    writes: &["ShadowMask", "SceneColor"],
};

/// A light draw: its pipelines with their bind groups, and whether it is a sphere or the
/// full screen.
struct LightDraw {
    /// A local light: [camera outside the light volume, camera inside it]; the directional
    /// light: one, full screen.
    variants: Vec<(Arc<RenderSlot>, BindGroups)>,
    radial: bool,
    /// A local light's volume, which the camera of each frame is tested against.
    volume: Option<LightVolume>,
    /// Whether this frame's camera is inside the light volume (selects the variant).
    inside: AtomicBool,
}

/// A local light's sphere and its `DeferredLight` buffer, whose depth bounds depend on the
/// camera and are written every frame.
struct LightVolume {
    gpu: LocalLightGpu,
    buffer: wgpu::Buffer,
}

impl LightDraw {
    /// This frame's camera: the variant (inside or outside the volume) and the depth bounds.
    fn update(&self, queue: &wgpu::Queue, view: &FrameView) {
        let Some(v) = &self.volume else { return };
        let (center, radius) = (v.gpu.position_radius.truncate(), v.gpu.position_radius.w);
        self.inside.store(camera_inside(view, center, radius), Ordering::Relaxed);
        queue.write_buffer(
            &v.buffer,
            0,
            bytemuck::bytes_of(&DeferredLightUniforms {
                light: v.gpu,
                depth_bounds: depth_bounds(view, center, radius),
            }),
        );
    }

    fn variant(&self) -> &(Arc<RenderSlot>, BindGroups) {
        let i = usize::from(self.inside.load(Ordering::Relaxed)).min(self.variants.len() - 1);
        &self.variants[i]
    }
}

struct Projection {
    pipeline: Arc<RenderSlot>,
    groups: BindGroups,
}

/// Whether the camera is inside a light's sphere: the sphere mesh encloses the unit sphere,
/// so within its radius (plus the near plane) the front faces may be clipped away.
fn camera_inside(view: &FrameView, center: Vec3, radius: f32) -> bool {
    view.position.distance(center) < radius * 1.03 + view.near * 2.0
}

struct ShadowedLight {
    name: String,
    projections: Vec<Projection>,
    light: LightDraw,
    /// Local lights: the index into the frame's lights, and the same light without a shadow
    /// mask, drawn with the NonShadowedLights while its shadow is occluded.
    local: Option<(usize, LightDraw)>,
}

pub struct Lighting {
    non_shadowed: Vec<LightDraw>,
    tiled: Option<(Arc<ComputeSlot>, BindGroups)>,
    shadowed: Vec<ShadowedLight>,
    /// Whether the tiled path runs this frame.
    pub tiled_path: bool,
    /// The directional light's `ShadowProjection` buffer (its cascades follow the camera).
    cascaded_projection: Option<wgpu::Buffer>,
}

/// `LIGHT_TYPE` of `StandardDeferredLightingPS` for a local light.
fn light_type(l: &FrameLight) -> LightType {
    if l.spot {
        LightType::Spot
    } else {
        LightType::Point
    }
}

/// Depth bounds (device z, farthest and nearest) of a light sphere, reverse-Z.
fn depth_bounds(view: &FrameView, center: Vec3, radius: f32) -> Vec4 {
    let depth = -(view.view.transform_point3(center)).z;
    let near = (depth - radius).max(view.near);
    let far = depth + radius;
    if far <= view.near {
        return Vec4::new(2.0, 2.0, 0.0, 0.0);
    }
    Vec4::new(view.near / far, view.near / near, 0.0, 0.0)
}

/// The scene depth bound read-only for a light draw with `compare` (none where the frame
/// cannot attach it read-only).
fn read_only(t: &Targets, compare: wgpu::CompareFunction) -> Option<wgpu::DepthStencilState> {
    if !t.scene_depth.read_only_attachment {
        return None;
    }
    Some(wgpu::DepthStencilState {
        format: t.scene_depth.format,
        depth_write_enabled: Some(false),
        depth_compare: Some(compare),
        stencil: stencil_lit_only(),
        bias: wgpu::DepthBiasState::default(),
    })
}

/// One pipeline per (light permutation, inside-the-volume or not).
fn light_draw(
    b: &PassSetup<'_>,
    light_type: LightType,
    shadowed: bool,
    inverse_squared: bool,
    gpu: LocalLightGpu,
    label: &str,
) -> Result<LightDraw, DesktopError> {
    let p = b.pipelines;
    let t = b.targets;
    let radial = light_type != LightType::Directional;
    let vs = keys::name(keys::deferred_light_vs::Key { radial_light: radial }, p.key_level()?)?;
    let key = keys::standard_deferred_lighting_ps::Key {
        light_type,
        use_shadow_mask: shadowed,
        inverse_squared_falloff: radial && inverse_squared,
    };
    let ps = keys::name(key, p.key_level()?)?;
    let (center, radius) = (gpu.position_radius.truncate(), gpu.position_radius.w);
    // a local light: both ways of drawing its sphere, chosen every frame by where the
    // camera is (front faces depth tested from outside, back faces from inside)
    let targets = vec![blended(formats::SCENE_COLOR, Some(blend::ADDITIVE))];
    let descs = if !radial {
        let base = PipelineDesc { targets, ..PipelineDesc::new(&vs, Some(&ps), VertexInput::None) };
        vec![PipelineDesc { depth_stencil: read_only(t, wgpu::CompareFunction::Always), ..base }]
    } else {
        let base = PipelineDesc { targets, ..PipelineDesc::new(&vs, Some(&ps), VertexInput::Mesh) };
        vec![
            PipelineDesc {
                cull_mode: Some(wgpu::Face::Back),
                depth_stencil: read_only(t, wgpu::CompareFunction::GreaterEqual),
                ..base.clone()
            },
            PipelineDesc {
                cull_mode: Some(wgpu::Face::Front),
                depth_stencil: read_only(t, wgpu::CompareFunction::Always),
                ..base
            },
        ]
    };
    let bounds = if radial { depth_bounds(b.view, center, radius) } else { Vec4::new(0.0, 1.0, 0.0, 0.0) };
    let buffer = uniform_buffer(
        b.device,
        &format!("DeferredLight {label}"),
        &DeferredLightUniforms { light: gpu, depth_bounds: bounds },
    );
    let mut variants = Vec::new();
    for desc in &descs {
        let pipeline = p.render(desc)?;
        let groups = pipeline.layout.bind_groups(b.device, &light_resources(b, &buffer))?.keeping(buffer.clone());
        variants.push((pipeline, groups));
    }
    let inside = AtomicBool::new(radial && camera_inside(b.view, center, radius));
    Ok(LightDraw { variants, radial, volume: radial.then_some(LightVolume { gpu, buffer }), inside })
}

/// TiledDeferredLighting of the unshadowed lights. With the light grid the pass reads every
/// light (and skips the shadowed ones); culling per tile, it gets the unshadowed ones only.
fn tiled_lighting(
    b: &PassSetup<'_>,
    unshadowed: &[&FrameLight],
    grid: &super::light_grid::LightGrid,
) -> Result<(Arc<ComputeSlot>, BindGroups), DesktopError> {
    let (p, t, device) = (b.pipelines, b.targets, b.device);
    let use_grid = b.options.tiled_uses_light_grid;
    let gpu: Vec<LocalLightGpu> = unshadowed.iter().map(|l| l.gpu).collect();
    let lights = super::resources::storage(device, "TiledLights", &gpu, wgpu::BufferUsages::empty());
    let params = uniform_buffer(
        device,
        "TiledLighting",
        &TiledLightingUniforms { num_lights: UVec4::new(gpu.len() as u32, 0, 0, 0) },
    );
    let cs = p.compute(&keys::name(
        keys::tiled_deferred_lighting_cs::Key { use_light_grid: use_grid, visualize_light_culling: false },
        p.key_level()?,
    )?)?;
    let lights_binding = if use_grid { b.lights_buffer.as_entire_binding() } else { lights.as_entire_binding() };
    let groups = cs
        .layout
        .bind_groups(
            device,
            &[
                ("View", b.view_buffer.as_entire_binding()),
                ("SceneDepthTexture", wgpu::BindingResource::TextureView(t.scene_depth.sampled_view())),
                ("GBufferATexture", wgpu::BindingResource::TextureView(&t.gbuffer_a.view)),
                ("GBufferBTexture", wgpu::BindingResource::TextureView(&t.gbuffer_b.view)),
                ("GBufferCTexture", wgpu::BindingResource::TextureView(&t.gbuffer_c.view)),
                ("SceneColorTexture", wgpu::BindingResource::TextureView(&t.scene_color.view)),
                ("OutSceneColor", wgpu::BindingResource::TextureView(&t.scene_color_tiled.view)),
                ("LocalLights", lights_binding),
                ("TiledLighting", params.as_entire_binding()),
                ("NumCulledLightsGrid", grid.num_culled_lights.as_entire_binding()),
                ("CulledLightDataGrid", grid.culled_light_data.as_entire_binding()),
            ],
        )?
        .keeping(lights)
        .keeping(params);
    Ok((cs, groups))
}

/// A ShadowProjection of one light into the shadow mask, with its `ShadowProjection` buffer.
fn projection(
    b: &PassSetup<'_>,
    kind: ShadowProjectionType,
    texture: &Texture,
    u: &ShadowProjectionUniforms,
    label: &str,
) -> Result<(Projection, wgpu::Buffer), DesktopError> {
    let (p, t, device) = (b.pipelines, b.targets, b.device);
    let quality = i64::from(b.options.shadow_quality.clamp(1, 3));
    let vs = keys::name(keys::post_process_vs::Key {}, p.key_level()?)?;
    let key = keys::shadow_projection_ps::Key { shadow_projection_type: kind, shadow_quality: quality };
    let ps = keys::name(key, p.key_level()?)?;
    let pipeline = p.render(&PipelineDesc {
        depth_stencil: read_only(t, wgpu::CompareFunction::Always),
        targets: vec![blended(formats::SHADOW_MASK, Some(blend::MIN))],
        ..PipelineDesc::new(&vs, Some(&ps), VertexInput::None)
    })?;
    let buffer = uniform_buffer(device, &format!("ShadowProjection {label}"), u);
    let groups = pipeline
        .layout
        .bind_groups(
            device,
            &[
                ("View", b.view_buffer.as_entire_binding()),
                ("SceneDepthTexture", wgpu::BindingResource::TextureView(t.scene_depth.sampled_view())),
                ("GBufferATexture", wgpu::BindingResource::TextureView(&t.gbuffer_a.view)),
                ("ShadowDepthTexture", wgpu::BindingResource::TextureView(&texture.view)),
                ("ShadowDepthSampler", wgpu::BindingResource::Sampler(&b.samplers.shadow)),
                ("ShadowProjection", buffer.as_entire_binding()),
            ],
        )?
        .keeping(buffer.clone());
    Ok((Projection { pipeline, groups }, buffer))
}

/// How the directional light is drawn.
enum Sun {
    /// With its cascades, and their `ShadowProjection` buffer (which follows the camera).
    Shadowed(Box<ShadowedLight>, wgpu::Buffer),
    /// Without a shadow: one of the NonShadowedLights.
    Unshadowed(LightDraw),
}

/// The directional light: shadowed by its cascades where it has them, else a plain light
/// draw.
fn sun_light(b: &PassSetup<'_>, shadows: &ShadowDepths) -> Result<Option<Sun>, DesktopError> {
    let sun = &b.scene.sun;
    if !sun.enabled {
        return Ok(None);
    }
    let gpu = LocalLightGpu {
        position_radius: Vec4::ZERO,
        color_falloff: (sun.color * sun.intensity).extend(0.0),
        direction_type: (-sun.direction).normalize().extend(0.0),
        spot_angles: Vec4::ZERO,
    };
    let cascaded = match (&shadows.setup.cascaded, shadows.csm_texture()) {
        (Some(u), Some(texture)) => {
            Some(projection(b, ShadowProjectionType::Cascaded, texture, u, "DirectionalLight")?)
        }
        _ => None,
    };
    let light = light_draw(b, LightType::Directional, cascaded.is_some(), false, gpu, "DirectionalLight")?;
    Ok(Some(match cascaded {
        Some((p, buffer)) => Sun::Shadowed(
            Box::new(ShadowedLight { name: "DirectionalLight".into(), projections: vec![p], light, local: None }),
            buffer,
        ),
        None => Sun::Unshadowed(light),
    }))
}

/// A local light that casts a shadow: its projections (per-object tiles, a cube), its
/// shadowed draw, and the same light unshadowed for frames where its shadow is occluded.
fn shadowed_local_light(
    b: &PassSetup<'_>,
    shadows: &ShadowDepths,
    dummy_shadow: &Texture,
    li: usize,
    l: &FrameLight,
) -> Result<ShadowedLight, DesktopError> {
    let mut projections = Vec::new();
    for (_, u) in shadows.setup.per_object.iter().filter(|(i, _)| *i == li) {
        let texture = shadows.per_object_texture().unwrap_or(dummy_shadow);
        projections.push(projection(b, ShadowProjectionType::PerObject, texture, u, &l.name)?.0);
    }
    for (_, cube, u) in shadows.setup.cubes.iter().filter(|(i, _, _)| *i == li) {
        let texture = shadows.cube_texture(*cube);
        projections.push(projection(b, ShadowProjectionType::OnePassPointLight, texture, u, &l.name)?.0);
    }
    let light = light_draw(b, light_type(l), true, l.inverse_squared, l.gpu, &l.name)?;
    let unshadowed = light_draw(b, light_type(l), false, l.inverse_squared, l.gpu, &format!("{} unshadowed", l.name))?;
    Ok(ShadowedLight { name: l.name.clone(), projections, light, local: Some((li, unshadowed)) })
}

impl Lighting {
    pub fn new(
        b: &PassSetup<'_>,
        shadows: &ShadowDepths,
        dummy_shadow: &Texture,
        grid: &super::light_grid::LightGrid,
    ) -> Result<Lighting, DesktopError> {
        let unshadowed: Vec<&FrameLight> = b.lights.iter().filter(|l| l.shadow == LocalShadow::None).collect();
        let tiled_path = match b.options.lighting_path {
            LightingPath::Auto => unshadowed.len() > b.options.tiled_threshold,
            LightingPath::PerLight => false,
            LightingPath::Tiled => true,
        };
        let mut non_shadowed = Vec::new();
        let mut tiled = None;
        if tiled_path {
            tiled = Some(tiled_lighting(b, &unshadowed, grid)?);
        } else {
            for l in &unshadowed {
                non_shadowed.push(light_draw(b, light_type(l), false, l.inverse_squared, l.gpu, &l.name)?);
            }
        }
        let mut shadowed = Vec::new();
        let mut cascaded_projection = None;
        match sun_light(b, shadows)? {
            Some(Sun::Shadowed(light, buffer)) => {
                shadowed.push(*light);
                cascaded_projection = Some(buffer);
            }
            Some(Sun::Unshadowed(light)) => non_shadowed.insert(0, light),
            None => {}
        }
        for (li, l) in b.lights.iter().enumerate().filter(|(_, l)| l.shadow != LocalShadow::None) {
            shadowed.push(shadowed_local_light(b, shadows, dummy_shadow, li, l)?);
        }
        Ok(Lighting { non_shadowed, tiled, shadowed, tiled_path, cascaded_projection })
    }

    /// What depends on the camera, for this frame's `view`: each local light's depth bounds
    /// and whether the camera is inside its volume, and the directional light's cascades
    /// (`cascaded`, as ShadowDepths refitted them).
    pub fn update(&self, queue: &wgpu::Queue, view: &FrameView, cascaded: Option<&ShadowProjectionUniforms>) {
        for d in self
            .non_shadowed
            .iter()
            .chain(self.shadowed.iter().flat_map(|l| std::iter::once(&l.light).chain(l.local.as_ref().map(|(_, d)| d))))
        {
            d.update(queue, view);
        }
        if let (Some(buffer), Some(u)) = (&self.cascaded_projection, cascaded) {
            queue.write_buffer(buffer, 0, bytemuck::bytes_of(u));
        }
    }

    fn draw_light(pl: FramePipelines<'_>, pass: &mut wgpu::RenderPass<'_>, scene: &SceneBuffers, d: &LightDraw) {
        let (pipeline, groups) = d.variant();
        let Some(pipeline) = pipeline.ready(pl) else { return };
        pass.set_pipeline(&pipeline.pipeline);
        groups.set_render(pass);
        if d.radial {
            pass.set_vertex_buffer(0, scene.sphere.vertices.slice(..));
            pass.set_index_buffer(scene.sphere.indices.slice(..), wgpu::IndexFormat::Uint32);
            pass.draw_indexed(0..scene.sphere.index_count, 0, 0..1);
        } else {
            pass.draw(0..3, 0..1);
        }
    }

    /// Records the lights. `casts_shadow(light)`: whether local light `light` (an index into
    /// the frame's lights) projects its shadow this frame (ShadowFrustumQueries).
    pub fn record(
        &self,
        ctx: &mut PassContext<'_>,
        scene: &SceneBuffers,
        t: &Targets,
        casts_shadow: &dyn Fn(usize) -> bool,
    ) {
        // The depth is final: the lights sample its copy while testing against it.
        t.scene_depth.copy_for_sampling(ctx.encoder());
        ctx.step("NonShadowedLights", |ctx| self.record_non_shadowed(ctx, scene, t, casts_shadow));
        if let Some((cs, groups)) = &self.tiled {
            ctx.step("TiledDeferredLighting", |ctx| Self::record_tiled(ctx, t, cs, groups));
        }
        ctx.step("ShadowedLights", |ctx| {
            for light in self.shadowed.iter().filter(|l| occluded_draw(l, casts_shadow).is_none()) {
                Self::record_shadowed(ctx, scene, t, light);
            }
        });
    }

    /// The unshadowed lights, and the shadowed ones whose shadow is occluded this frame.
    fn record_non_shadowed(
        &self,
        ctx: &mut PassContext<'_>,
        scene: &SceneBuffers,
        t: &Targets,
        casts_shadow: &dyn Fn(usize) -> bool,
    ) {
        let pl = ctx.pipelines();
        {
            let mut pass = begin(
                ctx,
                "NonShadowedLights",
                &[color_attachment(&t.scene_color.view, None)],
                read_only_depth(&t.scene_depth),
            );
            pass.set_stencil_reference(super::resources::STENCIL_LIT);
            let occluded = self.shadowed.iter().filter_map(|l| occluded_draw(l, casts_shadow));
            for d in self.non_shadowed.iter().chain(occluded) {
                Self::draw_light(pl, &mut pass, scene, d);
            }
        }
        ctx.output(&t.scene_color.texture, Visualize::Hdr);
    }

    /// The unshadowed lights in one dispatch, into a copy of SceneColor copied back.
    fn record_tiled(ctx: &mut PassContext<'_>, t: &Targets, cs: &ComputeSlot, groups: &BindGroups) {
        let ready = cs.ready(ctx.pipelines());
        {
            let mut pass = ctx.open_compute_pass("TiledDeferredLighting");
            if let Some(p) = ready {
                pass.set_pipeline(&p.pipeline);
                groups.set_compute(&mut pass);
                let [wx, wy, _] = cs.workgroup_size;
                pass.dispatch_workgroups(t.width.div_ceil(wx), t.height.div_ceil(wy), 1);
            }
        }
        ctx.encoder().copy_texture_to_texture(
            t.scene_color_tiled.texture.as_image_copy(),
            t.scene_color.texture.as_image_copy(),
            wgpu::Extent3d { width: t.width, height: t.height, depth_or_array_layers: 1 },
        );
        ctx.output(&t.scene_color.texture, Visualize::Hdr);
    }

    /// One shadowed light: its shadow projections into the shadow mask, then the light.
    fn record_shadowed(ctx: &mut PassContext<'_>, scene: &SceneBuffers, t: &Targets, light: &ShadowedLight) {
        let pl = ctx.pipelines();
        {
            let mut pass = begin(
                ctx,
                "ShadowProjectionOnOpaque",
                &[color_attachment(&t.shadow_mask.view, Some(wgpu::Color::WHITE))],
                read_only_depth(&t.scene_depth),
            );
            pass.set_stencil_reference(super::resources::STENCIL_LIT);
            for p in &light.projections {
                let Some(pipeline) = p.pipeline.ready(pl) else { continue };
                pass.set_pipeline(&pipeline.pipeline);
                p.groups.set_render(&mut pass);
                pass.draw(0..3, 0..1);
            }
        }
        ctx.output_named(
            &format!("ShadowProjectionOnOpaque_{}", light.name),
            &t.shadow_mask.texture,
            Visualize::Direct,
        );
        {
            let mut pass = begin(
                ctx,
                "StandardDeferredLighting",
                &[color_attachment(&t.scene_color.view, None)],
                read_only_depth(&t.scene_depth),
            );
            pass.set_stencil_reference(super::resources::STENCIL_LIT);
            Self::draw_light(pl, &mut pass, scene, &light.light);
        }
        ctx.output_named(&format!("StandardDeferredLighting_{}", light.name), &t.scene_color.texture, Visualize::Hdr);
    }

    /// Names of the shadowed lights, in the order they are drawn.
    pub fn shadowed_light_names(&self) -> Vec<String> {
        self.shadowed.iter().map(|l| l.name.clone()).collect()
    }
}

/// A local light whose shadow is occluded this frame: its draw without a shadow mask.
fn occluded_draw<'l>(light: &'l ShadowedLight, casts_shadow: &dyn Fn(usize) -> bool) -> Option<&'l LightDraw> {
    light.local.as_ref().and_then(|(i, d)| (!casts_shadow(*i)).then_some(d))
}

fn light_resources<'r>(
    b: &'r PassSetup<'_>,
    light: &'r wgpu::Buffer,
) -> Vec<(&'static str, wgpu::BindingResource<'r>)> {
    let t = b.targets;
    vec![
        ("View", b.view_buffer.as_entire_binding()),
        ("SceneDepthTexture", wgpu::BindingResource::TextureView(t.scene_depth.sampled_view())),
        ("GBufferATexture", wgpu::BindingResource::TextureView(&t.gbuffer_a.view)),
        ("GBufferBTexture", wgpu::BindingResource::TextureView(&t.gbuffer_b.view)),
        ("GBufferCTexture", wgpu::BindingResource::TextureView(&t.gbuffer_c.view)),
        ("ShadowMaskTexture", wgpu::BindingResource::TextureView(&t.shadow_mask.view)),
        ("DeferredLight", light.as_entire_binding()),
    ]
}
