//! The desktop deferred frame's passes, part 2 (issue 7): particles, occlusion queries, the
//! HZB, volumetric fog, velocity, translucency lighting volumes, reflections, distortion and
//! temporal post-processing, driven by [`part2::Part2`] one call per pass from the frame
//! function.

pub mod distortion;
pub mod eye_adaptation;
pub mod frame_view;
pub mod hzb;
pub mod motion_blur;
pub mod occlusion;
pub mod part2;
pub mod particles;
pub mod reflections;
pub mod taa;
pub mod translucent_volume;
pub mod velocity;
pub mod volumetric_fog;
