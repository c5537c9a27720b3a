//! BeginOcclusionTests: hardware occlusion queries of the props' bounding boxes against the
//! prepass depth (`OcclusionQueryShaders.usf`, reverse-Z greater-or-equal, no depth write),
//! read back one or more frames later without waiting: each frame's results go to their own
//! read-back buffer, mapped after the frame was submitted and read by a later frame once the
//! map has completed. A prop found visible is drawn and tested again on its own
//! (IndividualQueries); a prop found occluded is culled and tested in a group of up to 8
//! occluded props, one query for all their boxes (GroupedQueries); when a group's query
//! turns visible the group is split and its props are tested individually again.
//! ShadowFrustumQueries test the local lights' bounds: a sphere for movable lights (their
//! cube shadow), the shadow frustum for stationary ones. A prop whose box holds the camera is
//! visible without a query, as in Unreal.
//!
//! A light whose ShadowFrustumQuery came back with zero samples (its shadow-casting volume is
//! hidden behind the depth buffer) casts no shadow that frame: [`ShadowFrustumVisibility`]
//! holds the decision, with the same latency as the props' (results applied a frame or more
//! after their query, never waited for; a light without a result yet counts as visible).

use crate::frame::{PassContext, PassDecl, RenderSlot};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use glam::{Mat4, Vec3, Vec4};

use crate::keys;
use crate::pipelines::{Blend, ColorTarget, DepthState, PipelineError, RenderPipeline, RenderState};

use super::frame_view::{target_2d, view, EffectPassInit};

/// Reads the prepass depth; its queries come back a frame or more later (ShadowDepths reads them).
pub const PASS: PassDecl =
    PassDecl { name: "BeginOcclusionTests", reads: &["View", "SceneDepth"], writes: &["OcclusionQueries"] };

/// Most queries of one frame.
pub const MAX_QUERIES: u32 = 128;
/// Most proxies (instances) of one frame.
pub const MAX_PROXIES: usize = 256;
/// Occluded props tested with one query.
pub const GROUP_SIZE: usize = 8;
/// Read-back buffers in flight.
const READBACK_SLOTS: usize = 4;
const CUBE_VERTICES: u32 = 36;
const SPHERE_VERTICES: u32 = 12 * 8 * 6;

/// `OcclusionProxy` of `OcclusionQueryShaders.usf`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
struct OcclusionProxy {
    unit_to_world: Mat4,
    color_shape: Vec4,
}

/// A prop's visibility as the queries last found it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PropVisibility {
    /// Drawn; tested individually.
    Visible,
    /// Culled; tested in a group.
    Occluded,
}

/// A light's bounds for ShadowFrustumQueries.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LightBounds {
    /// Movable light: its sphere of influence.
    Sphere { center: Vec3, radius: f32 },
    /// Stationary light: the frustum of its shadow projection (world -> clip).
    Frustum { view_proj: Mat4 },
}

#[derive(Clone, Debug, PartialEq)]
enum QueryKind {
    Individual(usize),
    Grouped(Vec<usize>),
    Light(usize),
}

struct Readback {
    buffer: wgpu::Buffer,
    queries: Vec<QueryKind>,
    /// Submitted with a frame, not yet asked to map.
    submitted: bool,
    /// map_async asked; the flag turns true when the map completed.
    mapping: Option<Arc<AtomicBool>>,
    in_use: bool,
}

/// What the last call found, for tests and the dump.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct OcclusionStats {
    pub individual_queries: usize,
    pub grouped_queries: usize,
    pub light_queries: usize,
    /// Query results applied this frame (from earlier frames).
    pub results_read: usize,
}

pub struct OcclusionCulling {
    pipeline: Arc<RenderSlot>,
    query_set: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    readbacks: Vec<Readback>,
    proxies: wgpu::Buffer,
    bind_group: wgpu::BindGroup,
    pub debug: wgpu::Texture,
    debug_view: wgpu::TextureView,
    bounds: Vec<(Vec3, Vec3)>,
    visibility: Vec<PropVisibility>,
    lights: ShadowFrustumVisibility,
    /// Readback slot written by the frame being recorded.
    pending_slot: Option<usize>,
    pub stats: OcclusionStats,
}

/// World-space box of a set of instances of a mesh with local bounds `local`.
pub fn world_bounds(local: (Vec3, Vec3), instances: &[Mat4]) -> (Vec3, Vec3) {
    let mut lo = Vec3::splat(f32::MAX);
    let mut hi = Vec3::splat(f32::MIN);
    for m in instances {
        for i in 0..8 {
            let c = Vec3::new(
                if i & 1 == 0 { local.0.x } else { local.1.x },
                if i & 2 == 0 { local.0.y } else { local.1.y },
                if i & 4 == 0 { local.0.z } else { local.1.z },
            );
            let p = m.transform_point3(c);
            lo = lo.min(p);
            hi = hi.max(p);
        }
    }
    (lo, hi)
}

fn box_proxy((lo, hi): (Vec3, Vec3), color: Vec3) -> OcclusionProxy {
    // a little larger than the prop, as Unreal's bounds are
    let center = (lo + hi) * 0.5;
    let half = (hi - lo) * 0.5 + Vec3::splat(0.02);
    OcclusionProxy {
        unit_to_world: Mat4::from_translation(center) * Mat4::from_scale(half),
        color_shape: color.extend(0.0),
    }
}

/// This frame's queries as they are gathered: the proxies to draw and, per query, (kind,
/// first proxy, proxy count, vertices per proxy).
#[derive(Default)]
struct QueryList {
    proxies: Vec<OcclusionProxy>,
    queries: Vec<(QueryKind, u32, u32, u32)>,
}

impl QueryList {
    /// Adds a query of `list`'s proxies, unless the frame's proxies or queries are full.
    fn push(&mut self, kind: QueryKind, list: Vec<OcclusionProxy>, vertices: u32) {
        if self.proxies.len() + list.len() > MAX_PROXIES || self.queries.len() >= MAX_QUERIES as usize {
            return;
        }
        self.queries.push((kind, self.proxies.len() as u32, list.len() as u32, vertices));
        self.proxies.extend(list);
    }
}

impl OcclusionCulling {
    /// `bounds`: each prop's world-space box (a prop is an object of the scene, by index).
    pub fn new(
        init: &EffectPassInit<'_>,
        size: [u32; 2],
        depth_format: wgpu::TextureFormat,
        bounds: Vec<(Vec3, Vec3)>,
        lights: usize,
    ) -> Result<OcclusionCulling, PipelineError> {
        let EffectPassInit { device, cache, frame_view } = *init;
        let state = RenderState::fullscreen(ColorTarget::new(wgpu::TextureFormat::Rgba8Unorm, Blend::Additive))
            .with_depth(DepthState::reverse_z(depth_format, false));
        let pipeline = cache.render(
            &keys::name(keys::occlusion_query_vs::Key {}, keys::Level::Sm5)?,
            Some(&keys::name(keys::occlusion_query_ps::Key {}, keys::Level::Sm5)?),
            &state,
        )?;
        let query_set = device.create_query_set(&wgpu::QuerySetDescriptor {
            label: Some("occlusion queries"),
            ty: wgpu::QueryType::Occlusion,
            count: MAX_QUERIES,
        });
        let resolve = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("occlusion resolve"),
            size: u64::from(MAX_QUERIES) * 8,
            usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        let readbacks = (0..READBACK_SLOTS)
            .map(|i| Readback {
                buffer: device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some(&format!("occlusion readback {i}")),
                    size: u64::from(MAX_QUERIES) * 8,
                    usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                }),
                queries: Vec::new(),
                submitted: false,
                mapping: None,
                in_use: false,
            })
            .collect();
        let proxies = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("occlusion proxies"),
            size: (MAX_PROXIES * std::mem::size_of::<OcclusionProxy>()) as u64,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let bind_group = pipeline.layout.bind_group(
            device,
            0,
            "BeginOcclusionTests",
            &[("View", frame_view.as_entire_binding()), ("proxies", proxies.as_entire_binding())],
        )?;
        let debug = target_2d(
            device,
            "BeginOcclusionTests",
            size,
            wgpu::TextureFormat::Rgba8Unorm,
            wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING,
        );
        let debug_view = view(&debug);
        let count = bounds.len();
        Ok(OcclusionCulling {
            pipeline,
            query_set,
            resolve,
            readbacks,
            proxies,
            bind_group,
            debug,
            debug_view,
            bounds,
            visibility: vec![PropVisibility::Visible; count],
            lights: ShadowFrustumVisibility::new(lights),
            pending_slot: None,
            stats: OcclusionStats::default(),
        })
    }

    /// Whether prop `index` should be drawn this frame.
    pub fn is_visible(&self, index: usize) -> bool {
        self.visibility.get(index).is_none_or(|v| *v == PropVisibility::Visible)
    }

    pub fn visibility(&self, index: usize) -> Option<PropVisibility> {
        self.visibility.get(index).copied()
    }

    /// Whether local light `index` was found visible (its bounds pass the depth test), or
    /// has no result yet: whether its shadow depths and projection run this frame.
    pub fn is_light_visible(&self, index: usize) -> bool {
        self.lights.casts_shadow(index)
    }

    /// A camera cut: the results of queries issued from the old camera no longer say what
    /// the new one sees. Every prop and light counts as visible again, and the results
    /// still in flight are dropped when they come back (Unreal ignores the existing queries
    /// of a view on a camera cut); the next frame's queries decide again.
    pub fn camera_cut(&mut self) {
        self.visibility.iter_mut().for_each(|v| *v = PropVisibility::Visible);
        self.lights = ShadowFrustumVisibility::new(self.lights.visible.len());
        for slot in &mut self.readbacks {
            slot.queries.clear();
        }
    }

    /// Moves a prop (its box changed).
    pub fn set_bounds(&mut self, index: usize, bounds: (Vec3, Vec3)) {
        if let Some(b) = self.bounds.get_mut(index) {
            *b = bounds;
        }
    }

    /// Applies every read-back whose map completed; asks to map those submitted earlier.
    fn collect(&mut self, device: &wgpu::Device) {
        for slot in &mut self.readbacks {
            if slot.in_use && slot.submitted && slot.mapping.is_none() {
                let flag = Arc::new(AtomicBool::new(false));
                let f = flag.clone();
                slot.buffer.slice(..).map_async(wgpu::MapMode::Read, move |r| f.store(r.is_ok(), Ordering::Release));
                slot.mapping = Some(flag);
            }
        }
        // never waits: results not there yet are read by a later frame
        let _ = device.poll(wgpu::PollType::Poll);
        let mut read = 0;
        for i in 0..self.readbacks.len() {
            let ready = self.readbacks[i].mapping.as_ref().is_some_and(|f| f.load(Ordering::Acquire));
            if !ready {
                continue;
            }
            let counts: Vec<u64> = match self.readbacks[i].buffer.slice(..).get_mapped_range() {
                Ok(view) => bytemuck::pod_collect_to_vec(&view),
                Err(_) => Vec::new(),
            };
            self.readbacks[i].buffer.unmap();
            let queries = std::mem::take(&mut self.readbacks[i].queries);
            for (q, kind) in queries.iter().enumerate() {
                // a count that did not come back counts as visible
                let passed = counts.get(q).copied().unwrap_or(1) > 0;
                read += 1;
                match kind {
                    QueryKind::Individual(p) => {
                        self.visibility[*p] = if passed { PropVisibility::Visible } else { PropVisibility::Occluded };
                    }
                    QueryKind::Grouped(members) => {
                        // a group that turns visible is split: its props are drawn and
                        // tested individually again
                        if passed {
                            for p in members {
                                self.visibility[*p] = PropVisibility::Visible;
                            }
                        }
                    }
                    QueryKind::Light(l) => self.lights.apply(*l, counts.get(q).copied()),
                }
            }
            let slot = &mut self.readbacks[i];
            slot.in_use = false;
            slot.submitted = false;
            slot.mapping = None;
        }
        self.stats.results_read = read;
    }

    /// Records this frame's queries. `camera`: the camera position (props around it are
    /// visible without a query); `lights`: ShadowFrustumQueries bounds.
    pub fn record(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        ctx: &mut PassContext<'_>,
        scene_depth: &wgpu::TextureView,
        camera: Vec3,
        lights: &[LightBounds],
    ) {
        // frames are submitted in order: the queries of the last frame recorded are on the
        // GPU now, and their read-back may be mapped
        self.frame_submitted();
        self.collect(device);
        let Some(slot) = self.readbacks.iter().position(|r| !r.in_use) else {
            // every read-back still in flight: skip the queries this frame (nothing waits)
            self.pending_slot = None;
            return;
        };
        let mut list = QueryList::default();
        self.light_queries(camera, lights, &mut list);
        self.prop_queries(camera, &mut list);
        let QueryList { proxies, mut queries } = list;
        self.stats.individual_queries = queries.iter().filter(|q| matches!(q.0, QueryKind::Individual(_))).count();
        self.stats.grouped_queries = queries.iter().filter(|q| matches!(q.0, QueryKind::Grouped(_))).count();
        self.stats.light_queries = queries.iter().filter(|q| matches!(q.0, QueryKind::Light(_))).count();
        if !proxies.is_empty() {
            queue.write_buffer(&self.proxies, 0, bytemuck::cast_slice(&proxies));
        }
        let ready = self.pipeline.ready(ctx.pipelines());
        if ready.is_none() {
            // nothing can be tested this frame: the last verdicts stand
            queries.clear();
        }
        self.draw_queries(ctx, scene_depth, ready.as_deref(), &queries);
        if !queries.is_empty() {
            let n = queries.len() as u32;
            ctx.encoder().resolve_query_set(&self.query_set, 0..n, &self.resolve, 0);
            ctx.encoder().copy_buffer_to_buffer(&self.resolve, 0, &self.readbacks[slot].buffer, 0, u64::from(n) * 8);
            let r = &mut self.readbacks[slot];
            r.queries = queries.into_iter().map(|q| q.0).collect();
            r.in_use = true;
            r.submitted = false;
            self.pending_slot = Some(slot);
        } else {
            self.pending_slot = None;
        }
    }

    /// ShadowFrustumQueries: each light's bounds, unless the camera is inside them.
    fn light_queries(&mut self, camera: Vec3, lights: &[LightBounds], list: &mut QueryList) {
        for (i, light) in lights.iter().enumerate() {
            match *light {
                LightBounds::Sphere { center, radius } => {
                    if camera.distance(center) <= radius * 1.1 {
                        self.lights.camera_inside(i);
                        continue;
                    }
                    let p = OcclusionProxy {
                        unit_to_world: Mat4::from_translation(center) * Mat4::from_scale(Vec3::splat(radius)),
                        color_shape: Vec4::new(0.5, 0.45, 0.0, 1.0),
                    };
                    list.push(QueryKind::Light(i), vec![p], SPHERE_VERTICES);
                }
                LightBounds::Frustum { view_proj } => {
                    // the unit cube in the light's clip space, z in [0, 1]
                    let clip_cube =
                        Mat4::from_translation(Vec3::new(0.0, 0.0, 0.5)) * Mat4::from_scale(Vec3::new(1.0, 1.0, 0.5));
                    let p = OcclusionProxy {
                        unit_to_world: view_proj.inverse() * clip_cube,
                        color_shape: Vec4::new(0.45, 0.4, 0.0, 0.0),
                    };
                    list.push(QueryKind::Light(i), vec![p], CUBE_VERTICES);
                }
            }
        }
    }

    /// The props: visible ones one query each, occluded ones in groups; those around the
    /// camera are visible without a query.
    fn prop_queries(&mut self, camera: Vec3, list: &mut QueryList) {
        let contains = |(lo, hi): (Vec3, Vec3)| {
            camera.cmpge(lo - Vec3::splat(0.2)).all() && camera.cmple(hi + Vec3::splat(0.2)).all()
        };
        let mut occluded = Vec::new();
        for (p, &bounds) in self.bounds.iter().enumerate() {
            if contains(bounds) {
                self.visibility[p] = PropVisibility::Visible;
                continue;
            }
            match self.visibility[p] {
                PropVisibility::Visible => list.push(
                    QueryKind::Individual(p),
                    vec![box_proxy(bounds, Vec3::new(0.0, 0.6, 0.1))],
                    CUBE_VERTICES,
                ),
                PropVisibility::Occluded => occluded.push(p),
            }
        }
        for group in occluded.chunks(GROUP_SIZE) {
            let proxies = group.iter().map(|&p| box_proxy(self.bounds[p], Vec3::new(0.7, 0.05, 0.05))).collect();
            list.push(QueryKind::Grouped(group.to_vec()), proxies, CUBE_VERTICES);
        }
    }

    /// BeginOcclusionTests: each query's proxies against the depth (and into the debug view).
    fn draw_queries(
        &self,
        ctx: &mut PassContext<'_>,
        scene_depth: &wgpu::TextureView,
        pipeline: Option<&RenderPipeline>,
        queries: &[(QueryKind, u32, u32, u32)],
    ) {
        let mut pass = ctx.open_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("BeginOcclusionTests"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: &self.debug_view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations { load: wgpu::LoadOp::Clear(wgpu::Color::BLACK), store: wgpu::StoreOp::Store },
            })],
            depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                view: scene_depth,
                depth_ops: Some(wgpu::Operations { load: wgpu::LoadOp::Load, store: wgpu::StoreOp::Store }),
                stencil_ops: None,
            }),
            timestamp_writes: None,
            occlusion_query_set: Some(&self.query_set),
            multiview_mask: None,
        });
        if let Some(p) = pipeline {
            pass.set_pipeline(&p.pipeline);
            pass.set_bind_group(0, &self.bind_group, &[]);
        }
        for (i, (_, first, count, vertices)) in queries.iter().enumerate() {
            pass.begin_occlusion_query(i as u32);
            pass.draw(0..*vertices, *first..*first + *count);
            pass.end_occlusion_query();
        }
    }

    /// Marks the queries of the last frame recorded as submitted: their read-back may be
    /// mapped (by the next `record`, which calls this itself).
    pub fn frame_submitted(&mut self) {
        if let Some(slot) = self.pending_slot.take() {
            self.readbacks[slot].submitted = true;
        }
    }
}

/// ShadowFrustumQueries' verdict per local light, as Unreal keeps it: a light's shadow work
/// (its shadow depths and ShadowProjection) is skipped only while the last result that came
/// back for it counted zero samples. Before any result, for a result that could not be read,
/// and while the camera is inside the light's bounds (no query is issued then), the light
/// counts as visible: a hidden light may cost a frame of shadow work, a visible one never
/// loses its shadow.
#[derive(Clone, Debug, PartialEq)]
pub struct ShadowFrustumVisibility {
    visible: Vec<bool>,
}

impl ShadowFrustumVisibility {
    /// `lights` local lights, none with a result yet (all visible).
    pub fn new(lights: usize) -> ShadowFrustumVisibility {
        ShadowFrustumVisibility { visible: vec![true; lights] }
    }

    /// A query result read back for light `index`: its sample count, `None` if unreadable.
    pub fn apply(&mut self, index: usize, samples: Option<u64>) {
        if let Some(v) = self.visible.get_mut(index) {
            *v = samples.is_none_or(|n| n > 0);
        }
    }

    /// The camera is inside light `index`'s bounds: visible without a query.
    pub fn camera_inside(&mut self, index: usize) {
        if let Some(v) = self.visible.get_mut(index) {
            *v = true;
        }
    }

    /// Whether light `index` renders its shadow depths and projection this frame (a light
    /// the queries do not know is visible).
    pub fn casts_shadow(&self, index: usize) -> bool {
        self.visible.get(index).copied().unwrap_or(true)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shadow_frustum_results_gate_shadows_unknown_counts_as_visible() {
        let mut v = ShadowFrustumVisibility::new(3);
        // no result yet: every light casts its shadow (and an index the queries never saw)
        assert!((0..4).all(|i| v.casts_shadow(i)));
        // light 1's volume hidden (0 samples), light 0's seen (12 samples), light 2's result
        // lost (unreadable): only light 1 skips its shadow work
        v.apply(0, Some(12));
        v.apply(1, Some(0));
        v.apply(2, None);
        assert_eq!((0..3).map(|i| v.casts_shadow(i)).collect::<Vec<_>>(), [true, false, true]);
        // the skip lasts until a later result says otherwise: results for other lights, or
        // none at all (frames whose read-back is still in flight), leave it skipped
        v.apply(0, Some(0));
        assert!(!v.casts_shadow(1));
        // one sample is enough to bring it back
        v.apply(1, Some(1));
        assert!(v.casts_shadow(1));
        // the camera walks into a hidden light's sphere: visible without waiting for a query
        v.apply(2, Some(0));
        v.camera_inside(2);
        assert!(v.casts_shadow(2));
        // out-of-range indices are ignored, not a panic
        v.apply(7, Some(0));
        assert!(v.casts_shadow(7));
    }

    #[test]
    fn world_bounds_cover_every_instance() {
        let local = (Vec3::splat(-1.0), Vec3::splat(1.0));
        let (lo, hi) = world_bounds(
            local,
            &[Mat4::from_translation(Vec3::new(5.0, 0.0, 0.0)), Mat4::from_translation(Vec3::new(-5.0, 1.0, 0.0))],
        );
        assert_eq!(lo, Vec3::new(-6.0, -1.0, -1.0));
        assert_eq!(hi, Vec3::new(6.0, 2.0, 1.0));
    }

    #[test]
    fn box_proxy_maps_the_unit_cube_onto_the_bounds() {
        let p = box_proxy((Vec3::new(1.0, 2.0, 3.0), Vec3::new(3.0, 4.0, 7.0)), Vec3::ONE);
        let a = p.unit_to_world.transform_point3(Vec3::splat(-1.0));
        let b = p.unit_to_world.transform_point3(Vec3::splat(1.0));
        assert!((a - Vec3::new(0.98, 1.98, 2.98)).length() < 1e-5, "{a}");
        assert!((b - Vec3::new(3.02, 4.02, 7.02)).length() < 1e-5, "{b}");
    }
}
