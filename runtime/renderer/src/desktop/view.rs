//! `#[repr(C)]` mirrors of the desktop shaders' uniform and storage structs
//! (`shader_src/Private/Desktop/*.ush`, member for member: vec4 and mat4 only), and the
//! per-frame view (camera and light grid) the frame's `SceneView` is filled from.

use bytemuck::{Pod, Zeroable};
use glam::{Mat4, UVec4, Vec3, Vec4};

use crate::scene::view::{CameraState, FrameTime, SceneView};
use crate::scene::{Camera, Scene};

/// Light grid tile size in pixels (Unreal's 64x64 px tiles).
pub const LIGHT_GRID_TILE: u32 = 64;
/// Light grid depth slices, exponentially distributed.
pub const LIGHT_GRID_SLICES: u32 = 32;
/// Far end of the light grid's last slice (meters).
pub const LIGHT_GRID_FAR: f32 = 100.0;

pub use crate::gpu_types::{InstanceGpu, MaterialGpu};

/// `LocalLight` of `DesktopCommon.ush`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct LocalLightGpu {
    pub position_radius: Vec4,
    pub color_falloff: Vec4,
    pub direction_type: Vec4,
    pub spot_angles: Vec4,
}

/// `DeferredLightUniforms` of `DeferredLightingParams.ush`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct DeferredLightUniforms {
    pub light: LocalLightGpu,
    pub depth_bounds: Vec4,
}

/// `ShadowProjectionUniforms` of `ShadowProjectionCommon.ush`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct ShadowProjectionUniforms {
    pub world_to_shadow: [Mat4; 6],
    pub atlas_rects: [Vec4; 6],
    pub cascade_far_depths: Vec4,
    pub light_position: Vec4,
    pub params: Vec4,
}

/// `ShadowDepthPassUniforms` of `ShadowDepthVertexShader.usf`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct ShadowDepthPassUniforms {
    pub view_proj: Mat4,
}

/// `AmbientOcclusionUniforms` of `PostProcessAmbientOcclusion.usf`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct AmbientOcclusionUniforms {
    pub params: Vec4,
    pub output_size: Vec4,
    pub jitter: Vec4,
}

/// `TiledLightingUniforms` of `TiledDeferredLightShaders.usf`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct TiledLightingUniforms {
    pub num_lights: UVec4,
}

/// `BloomUniforms` of `PostProcessBloom.usf`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct BloomUniforms {
    pub params: Vec4,
    pub source_texel: Vec4,
}

/// `TonemapUniforms` of `PostProcessTonemap.usf`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct TonemapUniforms {
    pub params: Vec4,
}

/// The camera of one frame: matrices (reverse-Z, infinite far plane) and the light grid's
/// shape, computed on the CPU once and shared by every pass and by the tests' references.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameView {
    pub width: u32,
    pub height: u32,
    pub position: Vec3,
    pub near: f32,
    pub view: Mat4,
    pub proj: Mat4,
    pub view_proj: Mat4,
    pub grid: [u32; 3],
    pub grid_z_params: Vec3,
}

impl FrameView {
    /// The view of the scene's own camera.
    pub fn new(scene: &Scene, width: u32, height: u32) -> FrameView {
        FrameView::from_camera(&scene.camera, width, height)
    }

    /// The view of `camera` (unjittered): what the frame computes every frame from the
    /// camera it renders with, so that nothing camera-dependent outlives a camera move.
    pub fn from_camera(camera: &Camera, width: u32, height: u32) -> FrameView {
        let aspect = width as f32 / height as f32;
        let view = camera.view();
        let proj = camera.projection(aspect);
        let grid = [width.div_ceil(LIGHT_GRID_TILE), height.div_ceil(LIGHT_GRID_TILE), LIGHT_GRID_SLICES];
        FrameView {
            width,
            height,
            position: camera.position,
            near: camera.near,
            view,
            proj,
            view_proj: proj * view,
            grid,
            grid_z_params: light_grid_z_params(camera.near, LIGHT_GRID_FAR, LIGHT_GRID_SLICES),
        }
    }

    /// Cells of the light grid.
    pub fn grid_cells(&self) -> u32 {
        self.grid[0] * self.grid[1] * self.grid[2]
    }

    /// Pixel (x right, y down) and view depth of a world position; `None` behind the camera.
    pub fn project(&self, world: Vec3) -> Option<(f32, f32, f32)> {
        let clip = self.view_proj * world.extend(1.0);
        if clip.w <= 0.0 {
            return None;
        }
        let ndc = clip.truncate() / clip.w;
        Some(((ndc.x * 0.5 + 0.5) * self.width as f32, (0.5 - ndc.y * 0.5) * self.height as f32, clip.w))
    }

    /// View depth at the near boundary of a light grid slice.
    pub fn slice_depth(&self, slice: f32) -> f32 {
        let p = self.grid_z_params;
        ((slice / p.z).exp2() - p.y) / p.x
    }

    /// The view-space box of a light grid cell, as `ComputeCellViewAABB` in
    /// `LightGridInjection.usf` computes it (the tests' reference).
    pub fn cell_view_aabb(&self, x: u32, y: u32, z: u32) -> (Vec3, Vec3) {
        let tile = LIGHT_GRID_TILE as f32;
        let (w, h) = (self.width as f32, self.height as f32);
        let px_min = glam::Vec2::new(x as f32 * tile, y as f32 * tile);
        let px_max = (px_min + glam::Vec2::splat(tile)).min(glam::Vec2::new(w, h));
        let ndc_min = glam::Vec2::new(px_min.x / w * 2.0 - 1.0, 1.0 - px_max.y / h * 2.0);
        let ndc_max = glam::Vec2::new(px_max.x / w * 2.0 - 1.0, 1.0 - px_min.y / h * 2.0);
        let near_depth = if z == 0 { self.near } else { self.slice_depth(z as f32) };
        let far_depth = self.slice_depth(z as f32 + 1.0);
        let corner =
            |ndc: glam::Vec2, d: f32| glam::Vec2::new(ndc.x * d / self.proj.x_axis.x, ndc.y * d / self.proj.y_axis.y);
        let pts = [
            corner(ndc_min, near_depth),
            corner(ndc_max, near_depth),
            corner(ndc_min, far_depth),
            corner(ndc_max, far_depth),
        ];
        let lo = pts.iter().fold(glam::Vec2::splat(f32::MAX), |a, p| a.min(*p));
        let hi = pts.iter().fold(glam::Vec2::splat(f32::MIN), |a, p| a.max(*p));
        (lo.extend(-far_depth), hi.extend(-near_depth))
    }

    /// The frame's `SceneView` for this (unjittered) view of `scene`, with what the desktop
    /// frame adds: the light grid and `View.frame` (frame index, local lights, flags: bit 0 a
    /// flat sky).
    pub fn scene_view(&self, scene: &Scene, num_local_lights: u32, frame_index: u32, flags: u32) -> SceneView {
        let camera = CameraState::new(self.view, self.proj, self.near, glam::Vec2::ZERO);
        let mut v = SceneView::new(scene, &camera, &camera, self.width, self.height, FrameTime::default());
        v.frame = UVec4::new(frame_index, num_local_lights, 0, flags);
        v.light_grid_size = UVec4::new(self.grid[0], self.grid[1], self.grid[2], LIGHT_GRID_TILE);
        v.light_grid_z_params = self.grid_z_params.extend(0.0);
        v
    }
}

/// Unreal's `GetLightGridZParams`: slices are exponential in view depth, slice 0 starting a
/// little beyond the near plane; `slice = log2(depth * B + O) * S`.
pub fn light_grid_z_params(near: f32, far: f32, slices: u32) -> Vec3 {
    let near_offset = 0.095;
    let s = 4.05f32;
    let n = near + near_offset;
    let f = far;
    let o = (f - n * ((slices as f32 - 1.0) / s).exp2()) / (f - n);
    let b = (1.0 - o) / n;
    Vec3::new(b, o, s)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn struct_sizes_match_the_wgsl_structs() {
        assert_eq!(std::mem::size_of::<InstanceGpu>(), 2 * 64 + 2 * 16);
        assert_eq!(std::mem::size_of::<MaterialGpu>(), 64);
        assert_eq!(std::mem::size_of::<LocalLightGpu>(), 64);
        assert_eq!(std::mem::size_of::<DeferredLightUniforms>(), 80);
        assert_eq!(std::mem::size_of::<ShadowProjectionUniforms>(), 6 * 64 + 9 * 16);
    }

    #[test]
    fn light_grid_slices_cover_near_to_far_exponentially() {
        let p = light_grid_z_params(0.1, 100.0, 32);
        let slice = |d: f32| (d * p.x + p.y).log2() * p.z;
        assert!(slice(0.195).abs() < 1e-3, "slice 0 starts at near + offset: {}", slice(0.195));
        assert!((slice(100.0) - 31.0).abs() < 1e-2, "{}", slice(100.0));
        // Exponential: later slices are thicker.
        let v = FrameView { grid_z_params: p, ..FrameView::new(&Scene::bundled(), 320, 180) };
        let t1 = v.slice_depth(2.0) - v.slice_depth(1.0);
        let t20 = v.slice_depth(21.0) - v.slice_depth(20.0);
        assert!(t20 > 5.0 * t1, "{t1} {t20}");
    }

    #[test]
    fn projection_is_reverse_z() {
        let v = FrameView::new(&Scene::bundled(), 320, 180);
        let near = v.proj.project_point3(Vec3::new(0.0, 0.0, -v.near));
        assert!((near.z - 1.0).abs() < 1e-5);
    }
}
