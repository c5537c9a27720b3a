//! The one view uniform block of the bundled renderer: `SceneView` of
//! `shader_src/Private/SceneView.ush`, member for member (vec4, arrays of them and mat4 only, so
//! no padding rules apply), and the camera of one frame it is computed from. The desktop frame
//! and the mobile frames each fill one per frame with [`SceneView::new`] (plus their own parts:
//! the desktop light grid, the mobile CSM and forward lights) and write it into their one View
//! buffer, which every pass binds.

use bytemuck::{Pod, Zeroable};
use glam::{Mat4, UVec4, Vec2, Vec3, Vec4};

use super::Scene;

/// Most local lights the mobile forward base pass shades (`MAX_LOCAL_LIGHTS` of SceneView.ush).
pub const MAX_LOCAL_LIGHTS: usize = 4;
/// Mobile CSM cascades (`MAX_CASCADES`).
pub const MAX_CASCADES: usize = 4;
/// Reflection captures the mobile frames blend (`NUM_CAPTURES`).
pub const NUM_CAPTURES: usize = 3;

/// `ForwardLocalLight` of `SceneView.ush`: a local light of the mobile forward base pass (and of
/// one mobile deferred light volume).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct ForwardLocalLight {
    /// xyz position, w = 1 / radius
    pub position_inv_radius: Vec4,
    /// rgb color times intensity, w = specular scale
    pub color: Vec4,
    /// xyz the direction the spot points, w = 1 for a spot light
    pub direction: Vec4,
    /// cos(outer), 1 / (cos(inner) - cos(outer)), shadow slot (-1: none), shadow bias
    pub spot_angles: Vec4,
    /// world -> shadow atlas
    pub shadow_matrix: Mat4,
}

/// `SceneView` of `SceneView.ush` (the comments there say what each member holds).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct SceneView {
    pub view_proj: Mat4,
    pub inv_view_proj: Mat4,
    pub view: Mat4,
    pub proj: Mat4,
    pub prev_view_proj: Mat4,
    pub clip_to_prev_clip: Mat4,
    pub camera_position: Vec4,
    pub camera_forward: Vec4,
    pub prev_camera_position: Vec4,
    pub prev_camera_forward: Vec4,
    pub viewport_size: Vec4,
    pub jitter: Vec4,
    pub time: Vec4,
    pub frame: UVec4,
    pub light_grid_size: UVec4,
    pub light_grid_z_params: Vec4,
    pub directional_light_direction: Vec4,
    pub directional_light_color: Vec4,
    pub sky_color: Vec4,
    pub ground_color: Vec4,
    pub sky_sh: [Vec4; 4],
    pub fog_color: Vec4,
    pub fog_params: Vec4,
    pub fog_directional: Vec4,
    pub csm_splits: Vec4,
    pub csm_view_proj: [Mat4; MAX_CASCADES],
    pub csm_rects: [Vec4; MAX_CASCADES],
    pub shadow_params: Vec4,
    pub counts: Vec4,
    pub local_lights: [ForwardLocalLight; MAX_LOCAL_LIGHTS],
    pub capture_positions: [Vec4; NUM_CAPTURES],
    pub capture_brightness: [Vec4; NUM_CAPTURES],
}

/// One frame's camera: what the view of this frame, and the next frame's reprojection, need.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraState {
    pub view: Mat4,
    /// The projection without jitter (reverse-Z).
    pub proj: Mat4,
    pub position: Vec3,
    pub forward: Vec3,
    pub near: f32,
    /// The sub-pixel offset of this frame in NDC units (0 without TAA).
    pub jitter: Vec2,
}

impl CameraState {
    pub fn new(view: Mat4, proj: Mat4, near: f32, jitter: Vec2) -> CameraState {
        let inv = view.inverse();
        CameraState {
            view,
            proj,
            position: inv.w_axis.truncate(),
            forward: -inv.z_axis.truncate().normalize(),
            near,
            jitter,
        }
    }

    /// The scene's camera for a `width` x `height` target, without jitter.
    pub fn of_scene(scene: &Scene, width: u32, height: u32) -> CameraState {
        let camera = &scene.camera;
        let aspect = width.max(1) as f32 / height.max(1) as f32;
        CameraState::new(camera.view(), camera.projection(aspect), camera.near, Vec2::ZERO)
    }

    /// The projection the frame is rasterised with: shifted by the jitter in clip space.
    pub fn jittered_proj(&self) -> Mat4 {
        jitter_projection(self.proj, self.jitter)
    }

    pub fn unjittered_view_proj(&self) -> Mat4 {
        self.proj * self.view
    }
}

/// Shifts a projection by `jitter` NDC units: clip.xy += jitter * clip.w.
pub fn jitter_projection(proj: Mat4, jitter: Vec2) -> Mat4 {
    Mat4::from_translation(Vec3::new(jitter.x, jitter.y, 0.0)) * proj
}

/// When a frame is: seconds since the start, the step to the previous frame, its index.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FrameTime {
    pub time: f32,
    pub delta: f32,
    pub index: u64,
}

impl SceneView {
    /// The view of `scene` through `current` (this frame's camera) after `previous` (the
    /// previous frame's: the same camera on a first frame) for a `width` x `height` target.
    /// The frames fill what only they read (the desktop light grid, the mobile CSM and forward
    /// lights) on top.
    pub fn new(
        scene: &Scene,
        current: &CameraState,
        previous: &CameraState,
        width: u32,
        height: u32,
        time: FrameTime,
    ) -> SceneView {
        let mut v = SceneView::of_scene(scene);
        v.set_camera(current, previous, width, height, time);
        v
    }

    /// What the scene alone decides: the directional light, the sky and the height fog
    /// (pre-exposure 1, no camera yet).
    pub fn of_scene(scene: &Scene) -> SceneView {
        let sun = &scene.sun;
        let to_sun = (-sun.direction).normalize();
        let sun_color = if sun.enabled { sun.color * sun.intensity } else { Vec3::ZERO };
        let fog = &scene.fog;
        SceneView {
            time: Vec4::new(0.0, 0.0, 0.0, 1.0),
            directional_light_direction: to_sun.extend(if sun.enabled { 1.0 } else { 0.0 }),
            directional_light_color: sun_color.extend(1.0),
            sky_color: scene.sky_color.extend(1.0),
            ground_color: (Vec3::new(0.4, 0.36, 0.3) * scene.sky_color.length() * 0.5).extend(0.0),
            fog_color: fog.color.extend(fog.density),
            fog_params: Vec4::new(fog.height_falloff, fog.base_height, fog.start_distance, fog.max_opacity),
            fog_directional: (sun.color * sun.intensity * 0.15).extend(8.0),
            ..Default::default()
        }
    }

    /// Every camera-dependent member, for `current` after `previous` on a `width` x `height`
    /// target at `time` (the pre-exposure, `time.w`, is kept).
    pub fn set_camera(
        &mut self,
        current: &CameraState,
        previous: &CameraState,
        width: u32,
        height: u32,
        time: FrameTime,
    ) {
        let (w, h) = (width.max(1) as f32, height.max(1) as f32);
        let proj = current.jittered_proj();
        let view_proj = proj * current.view;
        let prev_view_proj = previous.unjittered_view_proj();
        self.view_proj = view_proj;
        self.inv_view_proj = view_proj.inverse();
        self.view = current.view;
        self.proj = proj;
        self.prev_view_proj = prev_view_proj;
        self.clip_to_prev_clip = prev_view_proj * current.unjittered_view_proj().inverse();
        self.camera_position = current.position.extend(current.near);
        self.camera_forward = current.forward.extend(0.0);
        self.prev_camera_position = previous.position.extend(0.0);
        self.prev_camera_forward = previous.forward.extend(0.0);
        self.viewport_size = Vec4::new(w, h, 1.0 / w, 1.0 / h);
        self.jitter = Vec4::new(current.jitter.x, current.jitter.y, previous.jitter.x, previous.jitter.y);
        self.time = Vec4::new(time.time, time.delta, time.index as f32, self.time.w);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn size_matches_the_wgsl_struct() {
        assert_eq!(std::mem::size_of::<ForwardLocalLight>(), 128);
        // 6 mat4; 7 camera vec4; frame, grid size, grid z; 2 light; 2 sky + 4 SH; 3 fog;
        // splits, 4 mat4, 4 rects, shadow params; counts, 4 lights, 6 captures
        let vec4 = 16;
        let mat4 = 64;
        assert_eq!(
            std::mem::size_of::<SceneView>(),
            6 * mat4
                + 7 * vec4
                + 3 * vec4
                + 2 * vec4
                + 6 * vec4
                + 3 * vec4
                + vec4
                + 4 * mat4
                + 4 * vec4
                + vec4
                + vec4
                + 4 * 128
                + 6 * vec4
        );
    }

    #[test]
    fn still_camera_reprojects_onto_itself() {
        let scene = Scene::bundled();
        let view = glam::camera::rh::view::look_at_mat4(Vec3::new(1.0, 2.0, 5.0), Vec3::ZERO, Vec3::Y);
        let proj = glam::camera::rh::proj::directx::perspective_infinite_reverse(1.0, 1.5, 0.1);
        let cam = CameraState::new(view, proj, 0.1, Vec2::new(0.001, 0.002));
        let v = SceneView::new(&scene, &cam, &cam, 300, 200, FrameTime { time: 0.0, delta: 1.0 / 30.0, index: 3 });
        let clip = Vec4::new(0.25, -0.5, 0.01, 1.0);
        let prev = v.clip_to_prev_clip * clip;
        assert!((prev.truncate() / prev.w - clip.truncate()).length() < 1e-4, "{prev}");
        assert!((cam.position - Vec3::new(1.0, 2.0, 5.0)).length() < 1e-5);
        assert!((cam.forward - (-Vec3::new(1.0, 2.0, 5.0)).normalize()).length() < 1e-5);
        // the jittered matrices are what the frame rasterises with
        assert!(v.view_proj.abs_diff_eq(cam.jittered_proj() * cam.view, 1e-6));
        assert_eq!(v.camera_position.w, 0.1);
        assert_eq!(v.time, Vec4::new(0.0, 1.0 / 30.0, 3.0, 1.0));
    }
}
