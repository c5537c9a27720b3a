//! Distortion: the refracting surfaces are drawn a second time into an RG16F target of
//! screen-space offsets, accumulated additively and depth-tested against the scene
//! (DistortionAccum: the glass statues with `DistortAccumulatePS.usf`, the fire's heat haze
//! with the sprite shader's `distort_ps`); then SceneColor is copied and re-drawn where an
//! offset was accumulated, fetching the copy at the moved pixel (DistortionApply,
//! `DistortApplyScreenPS.usf`).

use crate::frame::{PassContext, PassDecl, RenderSlot};
use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use glam::{Mat4, Vec4};

use crate::keys;
use crate::pipelines::{Blend, ColorTarget, DepthState, PipelineError, RenderState};

use super::frame_view::{color_pass, linear_sampler, target_2d, uniform_buffer, view, EffectPassInit, InstancedMesh};
use super::resources::formats::DISTORTION as DISTORTION_FORMAT;
use crate::passes::particles::Particles;

/// The Distortion declaration.
pub const PASS: PassDecl = PassDecl {
    name: "Distortion",
    reads: &["Scene", "View", "SceneDepth", "ParticleState", "SceneColor"],
    writes: &["Distortion", "SceneColor"],
};

/// Index of refraction - 1 of the glass.
pub const GLASS_REFRACTION: f32 = 0.5;

#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
struct DistortionMaterial {
    refraction: Vec4,
}

pub struct Distortion {
    pub offsets: wgpu::Texture,
    offsets_view: wgpu::TextureView,
    pub scene_color_copy: wgpu::Texture,
    accumulate: Arc<RenderSlot>,
    apply: Arc<RenderSlot>,
    accumulate_group: wgpu::BindGroup,
    apply_group: wgpu::BindGroup,
    /// The refracting meshes.
    meshes: Vec<InstancedMesh>,
    _material: wgpu::Buffer,
}

impl Distortion {
    pub fn new(
        init: &EffectPassInit<'_>,
        size: [u32; 2],
        scene_color_format: wgpu::TextureFormat,
        depth_format: wgpu::TextureFormat,
        refracting: Vec<InstancedMesh>,
    ) -> Result<Distortion, PipelineError> {
        let EffectPassInit { device, cache, frame_view } = *init;
        let accumulate_state = RenderState::triangles(crate::gpu_types::layouts::MESH_INSTANCED)
            .with_cull(None)
            .with_targets(&[ColorTarget::new(DISTORTION_FORMAT, Blend::Additive)])
            .with_depth(DepthState::reverse_z(depth_format, false));
        let accumulate = cache.render(
            &keys::name(keys::distort_accumulate_vs::Key {}, keys::Level::Sm5)?,
            Some(&keys::name(keys::distort_accumulate_ps::Key {}, keys::Level::Sm5)?),
            &accumulate_state,
        )?;
        let apply = cache.render(
            &keys::name(keys::distort_apply_screen_vs::Key {}, keys::Level::Sm5)?,
            Some(&keys::name(keys::distort_apply_screen_ps::Key {}, keys::Level::Sm5)?),
            &RenderState::fullscreen(ColorTarget::new(scene_color_format, Blend::Replace)),
        )?;
        let offsets = target_2d(
            device,
            "Distortion",
            size,
            DISTORTION_FORMAT,
            wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING,
        );
        let offsets_view = view(&offsets);
        let scene_color_copy = target_2d(
            device,
            "SceneColor copy",
            size,
            scene_color_format,
            wgpu::TextureUsages::COPY_DST | wgpu::TextureUsages::TEXTURE_BINDING,
        );
        let copy_view = view(&scene_color_copy);
        let material = uniform_buffer(
            device,
            "Distortion glass",
            &DistortionMaterial { refraction: Vec4::new(GLASS_REFRACTION, 0.0, 0.0, 0.0) },
        );
        let accumulate_group = accumulate.layout.bind_group(
            device,
            0,
            "DistortionAccum",
            &[("View", frame_view.as_entire_binding()), ("material", material.as_entire_binding())],
        )?;
        let sampler = linear_sampler(device, "Distortion sampler");
        let apply_group = apply.layout.bind_group(
            device,
            0,
            "DistortionApply",
            &[
                ("scene_color_copy", wgpu::BindingResource::TextureView(&copy_view)),
                ("distortion", wgpu::BindingResource::TextureView(&offsets_view)),
                ("linear_sampler", wgpu::BindingResource::Sampler(&sampler)),
            ],
        )?;
        Ok(Distortion {
            offsets,
            offsets_view,
            scene_color_copy,
            accumulate,
            apply,
            accumulate_group,
            apply_group,
            meshes: refracting,
            _material: material,
        })
    }

    /// DistortionAccum: the offsets of the glass and the heat haze.
    /// `transforms[i]`: this frame's instances of refracting mesh `i`.
    pub fn record_accumulate(
        &mut self,
        queue: &wgpu::Queue,
        ctx: &mut PassContext<'_>,
        scene_depth: &wgpu::TextureView,
        transforms: &[Vec<Mat4>],
        particles: Option<&Particles>,
    ) {
        for (m, t) in self.meshes.iter_mut().zip(transforms) {
            m.set_transforms(queue, t);
        }
        let pl = ctx.pipelines();
        let mut pass = ctx.open_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("DistortionAccum"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: &self.offsets_view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT),
                    store: wgpu::StoreOp::Store,
                },
            })],
            depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                view: scene_depth,
                depth_ops: Some(wgpu::Operations { load: wgpu::LoadOp::Load, store: wgpu::StoreOp::Store }),
                stencil_ops: None,
            }),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        if let Some(p) = self.accumulate.ready(pl) {
            pass.set_pipeline(&p.pipeline);
            pass.set_bind_group(0, &self.accumulate_group, &[]);
            for m in &self.meshes {
                m.draw(&mut pass);
            }
        }
        if let Some(p) = particles {
            p.draw_distortion(pl, &mut pass);
        }
    }

    /// DistortionApply: copies SceneColor, then refracts it where offsets were accumulated.
    pub fn record_apply(
        &self,
        ctx: &mut PassContext<'_>,
        scene_color: &wgpu::Texture,
        scene_color_view: &wgpu::TextureView,
    ) {
        ctx.encoder().copy_texture_to_texture(
            scene_color.as_image_copy(),
            self.scene_color_copy.as_image_copy(),
            scene_color.size(),
        );
        let ready = self.apply.ready(ctx.pipelines());
        let mut pass = color_pass(ctx, "DistortionApply", scene_color_view, wgpu::LoadOp::Load);
        if let Some(p) = ready {
            pass.set_pipeline(&p.pipeline);
            pass.set_bind_group(0, &self.apply_group, &[]);
            pass.draw(0..3, 0..1);
        }
    }
}
