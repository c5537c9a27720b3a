//! The bundled scene, after the seeds' test scene: a floor, walls and a window wall with an
//! opening, a movable noisy rock, two chairs and two statues drawn as instanced pairs, two
//! glass statues (translucent), a fire particle emitter, one directional light, stationary
//! and movable point lights, spot lights, height fog and a sky.
//!
//! Takes nothing (the scene is procedural); gives CPU-side descriptions ([`Scene`]) that
//! [`gpu::GpuScene`] uploads. Y is up, units are meters, front faces are counter-clockwise.

pub mod gpu;
pub mod mesh;
pub mod view;

use glam::camera::rh::proj::directx;
use glam::camera::rh::view::look_at_mat4;
use glam::{Mat4, Quat, Vec3};

pub use mesh::Mesh;

/// How a material is blended; a permutation dimension (`MATERIAL_BLEND_MODE`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum BlendMode {
    Opaque,
    Masked,
    Translucent,
}

impl BlendMode {
    /// The enum label in permutations.toml.
    pub fn label(self) -> &'static str {
        match self {
            BlendMode::Opaque => "OPAQUE",
            BlendMode::Masked => "MASKED",
            BlendMode::Translucent => "TRANSLUCENT",
        }
    }
}

/// A procedural pattern a material may use (`MaterialCommon.ush`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Pattern {
    None = 0,
    /// Tints the base color in an 8x8 checker per uv unit.
    Checker = 1,
    /// Vertical slats: the opacity mask of masked materials.
    Slats = 2,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Material {
    pub name: String,
    /// Linear base color.
    pub base_color: Vec3,
    pub metallic: f32,
    pub roughness: f32,
    pub specular: f32,
    pub emissive: Vec3,
    /// Selects the `FULLY_ROUGH` permutations on mobile: no specular, no reflections.
    pub fully_rough: bool,
    pub blend: BlendMode,
    /// Coverage of a translucent material.
    pub opacity: f32,
    /// Masked materials discard below this mask value.
    pub opacity_mask_clip: f32,
    pub pattern: Pattern,
    pub unlit: bool,
}

impl Material {
    pub fn opaque(name: &str, base_color: Vec3, metallic: f32, roughness: f32) -> Material {
        Material {
            name: name.to_string(),
            base_color,
            metallic,
            roughness,
            specular: 0.5,
            emissive: Vec3::ZERO,
            fully_rough: false,
            blend: BlendMode::Opaque,
            opacity: 1.0,
            opacity_mask_clip: 0.5,
            pattern: Pattern::None,
            unlit: false,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mobility {
    Static,
    Stationary,
    Movable,
}

/// A mesh drawn with one material at one or more transforms (one draw call).
#[derive(Clone, Debug)]
pub struct Object {
    pub name: String,
    pub mesh: usize,
    pub material: usize,
    pub instances: Vec<Mat4>,
    pub mobility: Mobility,
    pub casts_shadow: bool,
}

#[derive(Clone, Debug, PartialEq)]
pub struct DirectionalLight {
    /// The direction the light travels (normalized).
    pub direction: Vec3,
    pub color: Vec3,
    /// Illuminance scale (the frame is in relative units, exposure 1).
    pub intensity: f32,
    pub casts_shadows: bool,
    pub enabled: bool,
}

#[derive(Clone, Debug, PartialEq)]
pub struct PointLight {
    pub name: String,
    pub position: Vec3,
    pub color: Vec3,
    pub intensity: f32,
    pub radius: f32,
    pub mobility: Mobility,
    pub casts_shadows: bool,
}

#[derive(Clone, Debug, PartialEq)]
pub struct SpotLight {
    pub name: String,
    pub position: Vec3,
    /// The direction the cone points (normalized).
    pub direction: Vec3,
    pub color: Vec3,
    pub intensity: f32,
    pub radius: f32,
    pub inner_angle: f32,
    pub outer_angle: f32,
    pub mobility: Mobility,
    pub casts_shadows: bool,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    pub position: Vec3,
    pub target: Vec3,
    /// Vertical field of view in radians.
    pub fov_y: f32,
    pub near: f32,
}

impl Camera {
    pub fn view(&self) -> Mat4 {
        look_at_mat4(self.position, self.target, Vec3::Y)
    }

    /// Reverse-Z infinite perspective: the near plane maps to depth 1, infinity to 0.
    pub fn projection(&self, aspect: f32) -> Mat4 {
        directx::perspective_infinite_reverse(self.fov_y, aspect, self.near)
    }

    pub fn view_proj(&self, aspect: f32) -> Mat4 {
        self.projection(aspect) * self.view()
    }
}

/// A GPU particle emitter (ParticleSimulation): what it spawns and how particles move.
#[derive(Clone, Debug, PartialEq)]
pub struct ParticleEmitter {
    pub name: String,
    pub position: Vec3,
    /// Particles spawned per second.
    pub spawn_rate: f32,
    pub max_particles: u32,
    /// Lifetime range in seconds.
    pub lifetime: (f32, f32),
    /// Spawn disc radius.
    pub spawn_radius: f32,
    pub initial_velocity: Vec3,
    pub velocity_jitter: f32,
    /// Upward acceleration from buoyancy (m/s^2).
    pub buoyancy: f32,
    pub size: (f32, f32),
    /// Emissive color at birth and at death (HDR).
    pub color_start: Vec3,
    pub color_end: Vec3,
}

#[derive(Clone, Debug, PartialEq)]
pub struct HeightFog {
    pub color: Vec3,
    pub density: f32,
    pub height_falloff: f32,
    pub base_height: f32,
    pub start_distance: f32,
    pub max_opacity: f32,
}

/// Everything a frame draws.
#[derive(Clone, Debug)]
pub struct Scene {
    pub meshes: Vec<Mesh>,
    pub materials: Vec<Material>,
    pub objects: Vec<Object>,
    pub sun: DirectionalLight,
    pub point_lights: Vec<PointLight>,
    pub spot_lights: Vec<SpotLight>,
    pub camera: Camera,
    pub sky_color: Vec3,
    pub fog: HeightFog,
    pub emitters: Vec<ParticleEmitter>,
    pub exposure: f32,
}

/// The room: the floor spans x in [-ROOM_X, ROOM_X], z in [-ROOM_Z, ROOM_Z].
pub const ROOM_X: f32 = 8.0;
pub const ROOM_Z: f32 = 6.0;
pub const WALL_HEIGHT: f32 = 4.0;
const WALL: f32 = 0.2;

impl Scene {
    pub fn material_index(&self, name: &str) -> Option<usize> {
        self.materials.iter().position(|m| m.name == name)
    }

    pub fn object(&self, name: &str) -> Option<&Object> {
        self.objects.iter().find(|o| o.name == name)
    }

    /// The seeds' test scene.
    pub fn bundled() -> Scene {
        let mut meshes = room_meshes();
        meshes.extend(prop_meshes());
        let materials = bundled_materials();
        let objects = bundled_objects(&meshes, &materials);
        Scene {
            meshes,
            materials,
            objects,
            sun: DirectionalLight {
                direction: Vec3::new(-1.0, -0.75, -0.35).normalize(),
                color: Vec3::new(1.0, 0.95, 0.85),
                intensity: 2.5,
                casts_shadows: true,
                enabled: true,
            },
            point_lights: bundled_point_lights(),
            spot_lights: vec![statue_spot()],
            camera: Camera {
                position: Vec3::new(-3.0, 3.4, 9.5),
                target: Vec3::new(1.0, 0.6, -1.5),
                fov_y: 60f32.to_radians(),
                near: 0.1,
            },
            sky_color: Vec3::new(0.22, 0.28, 0.4),
            fog: HeightFog {
                color: Vec3::new(0.45, 0.5, 0.6),
                density: 0.02,
                height_falloff: 0.2,
                base_height: 0.0,
                start_distance: 2.0,
                max_opacity: 0.8,
            },
            emitters: vec![fire_emitter()],
            exposure: 0.8,
        }
    }

    /// The directional light's shadow view-projection: an orthographic, reverse-Z box
    /// around the room seen along the light.
    pub fn sun_shadow_view_proj(&self) -> Mat4 {
        let d = self.sun.direction;
        let center = Vec3::new(0.0, WALL_HEIGHT * 0.5, 0.0);
        let radius = Vec3::new(ROOM_X + 1.0, WALL_HEIGHT, ROOM_Z + 1.0).length();
        let up = if d.y.abs() > 0.99 { Vec3::Z } else { Vec3::Y };
        let view = look_at_mat4(center - d * radius * 2.0, center, up);
        // Reverse-Z: near maps to 1, far to 0 (orthographic_rh maps near -> 0, so swap).
        let proj = directx::orthographic(-radius, radius, -radius, radius, radius * 4.0, 0.01);
        proj * view
    }
}

/// The bundled room's floor, walls and window wall (in the scene's mesh order).
fn room_meshes() -> Vec<Mesh> {
    let mut meshes = Vec::new();
    let mut floor = Mesh::new("Floor");
    floor.add_quad(
        Vec3::new(-ROOM_X, 0.0, ROOM_Z),
        Vec3::X * 2.0 * ROOM_X,
        Vec3::NEG_Z * 2.0 * ROOM_Z,
        glam::Vec2::new(2.0 * ROOM_X, 2.0 * ROOM_Z) * 0.25,
    );
    meshes.push(floor);

    let mut walls = Mesh::new("Walls");
    walls.add_box(Vec3::new(-ROOM_X - WALL, 0.0, -ROOM_Z - WALL), Vec3::new(ROOM_X + WALL, WALL_HEIGHT, -ROOM_Z), 0.5);
    walls.add_box(Vec3::new(-ROOM_X - WALL, 0.0, -ROOM_Z), Vec3::new(-ROOM_X, WALL_HEIGHT, ROOM_Z), 0.5);
    meshes.push(walls);

    // The window wall at +x with an opening 4 m wide and 2 m high, 1 m above the floor.
    let (x0, x1) = (ROOM_X, ROOM_X + WALL);
    let mut window_wall = Mesh::new("WindowWall");
    window_wall.add_box(Vec3::new(x0, 0.0, -ROOM_Z), Vec3::new(x1, WALL_HEIGHT, -2.0), 0.5);
    window_wall.add_box(Vec3::new(x0, 0.0, 2.0), Vec3::new(x1, WALL_HEIGHT, ROOM_Z), 0.5);
    window_wall.add_box(Vec3::new(x0, 0.0, -2.0), Vec3::new(x1, 1.0, 2.0), 0.5);
    window_wall.add_box(Vec3::new(x0, 3.0, -2.0), Vec3::new(x1, WALL_HEIGHT, 2.0), 0.5);
    meshes.push(window_wall);
    meshes
}

/// The bundled scene's props: the rock, the chair and the statue.
fn prop_meshes() -> Vec<Mesh> {
    let mut meshes = Vec::new();
    let mut rock = Mesh::new("Rock");
    rock.add_sphere(Vec3::ZERO, 0.8, 16, 24, 0.35, 11);
    meshes.push(rock);

    let mut chair = Mesh::new("Chair");
    chair.add_box(Vec3::new(-0.45, 0.85, -0.45), Vec3::new(0.45, 0.95, 0.45), 1.0);
    for (x, z) in [(-0.4, -0.4), (0.32, -0.4), (-0.4, 0.32), (0.32, 0.32)] {
        chair.add_box(Vec3::new(x, 0.0, z), Vec3::new(x + 0.08, 0.85, z + 0.08), 1.0);
    }
    chair.add_box(Vec3::new(-0.45, 0.95, -0.45), Vec3::new(0.45, 1.9, -0.37), 1.0);
    meshes.push(chair);

    let mut statue = Mesh::new("Statue");
    statue.add_box(Vec3::new(-0.5, 0.0, -0.5), Vec3::new(0.5, 1.0, 0.5), 1.0);
    statue.add_sphere(Vec3::new(0.0, 1.6, 0.0), 0.45, 12, 16, 0.0, 0);
    statue.add_sphere(Vec3::new(0.0, 2.35, 0.0), 0.3, 10, 14, 0.0, 0);
    meshes.push(statue);
    meshes
}

/// The bundled scene's materials: one per surface kind, the glass translucent.
fn bundled_materials() -> Vec<Material> {
    let floor_mat =
        Material { pattern: Pattern::Checker, ..Material::opaque("Floor", Vec3::new(0.55, 0.5, 0.45), 0.0, 0.7) };
    let wall_mat = Material { fully_rough: true, ..Material::opaque("Plaster", Vec3::new(0.7, 0.68, 0.62), 0.0, 0.95) };
    let rock_mat = Material { fully_rough: true, ..Material::opaque("Rock", Vec3::new(0.25, 0.23, 0.21), 0.0, 0.9) };
    let wood_mat = Material {
        blend: BlendMode::Masked,
        pattern: Pattern::Slats,
        ..Material::opaque("ChairWood", Vec3::new(0.45, 0.26, 0.12), 0.0, 0.6)
    };
    let bronze_mat = Material::opaque("Bronze", Vec3::new(0.8, 0.5, 0.25), 1.0, 0.3);
    let glass_mat = Material {
        blend: BlendMode::Translucent,
        opacity: 0.35,
        specular: 1.0,
        ..Material::opaque("Glass", Vec3::new(0.6, 0.8, 0.9), 0.0, 0.05)
    };
    vec![floor_mat, wall_mat, rock_mat, wood_mat, bronze_mat, glass_mat]
}

/// The bundled scene's objects over `meshes` and `materials` (found by name).
fn bundled_objects(meshes: &[Mesh], materials: &[Material]) -> Vec<Object> {
    let mesh = |name: &str| meshes.iter().position(|m| m.name == name).unwrap();
    let mat = |name: &str| materials.iter().position(|m| m.name == name).unwrap();
    let (floor, walls, window_wall) = (mesh("Floor"), mesh("Walls"), mesh("WindowWall"));
    let (rock, chair, statue) = (mesh("Rock"), mesh("Chair"), mesh("Statue"));
    let at = |x: f32, z: f32, yaw_deg: f32| {
        Mat4::from_rotation_translation(Quat::from_rotation_y(yaw_deg.to_radians()), Vec3::new(x, 0.0, z))
    };
    let object = |name: &str, mesh: usize, material: usize, instances: Vec<Mat4>, mobility: Mobility| Object {
        name: name.to_string(),
        mesh,
        material,
        instances,
        mobility,
        casts_shadow: true,
    };
    vec![
        object("Floor", floor, mat("Floor"), vec![Mat4::IDENTITY], Mobility::Static),
        object("Walls", walls, mat("Plaster"), vec![Mat4::IDENTITY], Mobility::Static),
        object("WindowWall", window_wall, mat("Plaster"), vec![Mat4::IDENTITY], Mobility::Static),
        object(
            "Rock",
            rock,
            mat("Rock"),
            vec![Mat4::from_scale_rotation_translation(
                Vec3::splat(1.0),
                Quat::from_rotation_y(0.6),
                Vec3::new(1.5, 0.55, 1.0),
            )],
            Mobility::Movable,
        ),
        object("Chairs", chair, mat("ChairWood"), vec![at(-3.5, -1.5, 20.0), at(-1.8, -2.2, -15.0)], Mobility::Static),
        object("Statues", statue, mat("Bronze"), vec![at(-5.5, -4.2, 0.0), at(3.5, -4.2, 30.0)], Mobility::Static),
        object("GlassStatues", statue, mat("Glass"), vec![at(-1.0, -4.2, 10.0), at(0.5, 2.5, -20.0)], Mobility::Static),
    ]
}

/// The two ceiling lamps and the fire's light.
fn bundled_point_lights() -> Vec<PointLight> {
    vec![
        PointLight {
            name: "CeilingLampA".into(),
            position: Vec3::new(-4.0, 3.2, -3.0),
            color: Vec3::new(1.0, 0.8, 0.6),
            intensity: 6.0,
            radius: 6.0,
            mobility: Mobility::Stationary,
            casts_shadows: true,
        },
        PointLight {
            name: "CeilingLampB".into(),
            position: Vec3::new(0.0, 3.2, 3.0),
            color: Vec3::new(1.0, 0.85, 0.7),
            intensity: 5.0,
            radius: 6.0,
            mobility: Mobility::Stationary,
            casts_shadows: true,
        },
        PointLight {
            name: "FireLight".into(),
            position: Vec3::new(5.0, 0.8, -3.0),
            color: Vec3::new(1.0, 0.45, 0.1),
            intensity: 8.0,
            radius: 5.0,
            mobility: Mobility::Movable,
            casts_shadows: true,
        },
    ]
}

/// The spot light on the statue (casts no shadow).
fn statue_spot() -> SpotLight {
    SpotLight {
        name: "StatueSpot".into(),
        position: Vec3::new(3.5, 3.8, -1.5),
        direction: Vec3::new(0.0, -1.0, -0.9).normalize(),
        color: Vec3::new(0.7, 0.8, 1.0),
        intensity: 12.0,
        radius: 8.0,
        inner_angle: 15f32.to_radians(),
        outer_angle: 30f32.to_radians(),
        mobility: Mobility::Stationary,
        casts_shadows: false,
    }
}

/// The fire's particles (by the fire light).
fn fire_emitter() -> ParticleEmitter {
    ParticleEmitter {
        name: "Fire".into(),
        position: Vec3::new(5.0, 0.1, -3.0),
        spawn_rate: 400.0,
        max_particles: 2048,
        lifetime: (0.6, 1.4),
        spawn_radius: 0.35,
        initial_velocity: Vec3::new(0.0, 0.8, 0.0),
        velocity_jitter: 0.3,
        buoyancy: 1.5,
        size: (0.25, 0.05),
        color_start: Vec3::new(8.0, 3.0, 0.6),
        color_end: Vec3::new(0.6, 0.1, 0.02),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bundled_scene_has_what_the_seed_lists() {
        let s = Scene::bundled();
        for name in ["Floor", "Walls", "WindowWall", "Rock", "Chairs", "Statues", "GlassStatues"] {
            assert!(s.object(name).is_some(), "{name}");
        }
        assert_eq!(s.object("Chairs").unwrap().instances.len(), 2);
        assert_eq!(s.object("Statues").unwrap().instances.len(), 2);
        assert_eq!(s.object("Rock").unwrap().mobility, Mobility::Movable);
        let glass = &s.materials[s.object("GlassStatues").unwrap().material];
        assert_eq!(glass.blend, BlendMode::Translucent);
        assert!(s.point_lights.iter().any(|l| l.mobility == Mobility::Stationary));
        assert!(s.point_lights.iter().any(|l| l.mobility == Mobility::Movable));
        assert!(!s.spot_lights.is_empty());
        assert_eq!(s.emitters[0].name, "Fire");
    }

    #[test]
    fn bundled_objects_draw_their_own_meshes_and_materials() {
        let s = Scene::bundled();
        let expected = [
            ("Floor", "Floor", "Floor"),
            ("Walls", "Walls", "Plaster"),
            ("WindowWall", "WindowWall", "Plaster"),
            ("Rock", "Rock", "Rock"),
            ("Chairs", "Chair", "ChairWood"),
            ("Statues", "Statue", "Bronze"),
            ("GlassStatues", "Statue", "Glass"),
        ];
        let found: Vec<(&str, &str, &str)> = s
            .objects
            .iter()
            .map(|o| (o.name.as_str(), s.meshes[o.mesh].name.as_str(), s.materials[o.material].name.as_str()))
            .collect();
        assert_eq!(found, expected);
        let meshes: Vec<&str> = s.meshes.iter().map(|m| m.name.as_str()).collect();
        assert_eq!(meshes, ["Floor", "Walls", "WindowWall", "Rock", "Chair", "Statue"]);
    }

    #[test]
    fn reverse_z_maps_near_to_one_and_far_towards_zero() {
        let c = Scene::bundled().camera;
        let p = c.projection(16.0 / 9.0);
        let near = p.project_point3(Vec3::new(0.0, 0.0, -c.near));
        let far = p.project_point3(Vec3::new(0.0, 0.0, -1000.0));
        assert!((near.z - 1.0).abs() < 1e-5, "{near}");
        assert!(far.z > 0.0 && far.z < 0.001, "{far}");
    }

    #[test]
    fn shadow_projection_keeps_the_room_inside_and_reverse_z() {
        let s = Scene::bundled();
        let m = s.sun_shadow_view_proj();
        for corner in
            [Vec3::new(-ROOM_X, 0.0, -ROOM_Z), Vec3::new(ROOM_X, WALL_HEIGHT, ROOM_Z), Vec3::new(ROOM_X, 0.0, -ROOM_Z)]
        {
            let p = m.project_point3(corner);
            assert!(p.x.abs() <= 1.0 && p.y.abs() <= 1.0 && (0.0..=1.0).contains(&p.z), "{corner} -> {p}");
        }
        // A point nearer the light has a larger depth.
        let a = m.project_point3(Vec3::ZERO);
        let b = m.project_point3(-s.sun.direction);
        assert!(b.z > a.z);
    }
}
