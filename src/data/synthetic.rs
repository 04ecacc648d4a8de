//! Procedural dynamic scenes rendered by a small analytic ray tracer (it does not use the
//! rasterizer, so training on them tests the whole pipeline against an independent renderer).
//!
//! A textured floor and back wall, a banded sphere and a checkered box (static), one sphere in
//! fast large motion and one slowly drifting, spinning box; Lambert shading with hard shadows from
//! one directional light. Cameras sit on a forward-facing arc. The result is written in the N3DV
//! layout (`poses_bounds.npy`, `png/camXX/NNNNN.png`, `colmap_0/sparse/0/points3D.txt`) so the
//! same loader reads it. Everything is deterministic.

use std::path::Path;

use anyhow::{Context, Result, bail};
use glam::{DMat3, DVec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::cameras::{LlffPose, camera_from_c2w};
use super::colmap::write_points3d_txt;
use super::n3dv::frame_file_name;
use super::npy::write_npy_f64;
use super::scene::PointCloud;
use crate::raster::RasterCamera;

/// Motion regimes of the generated scenes: two everyday ones, one like users' fast-motion footage,
/// and four built to break methods (`acags stability`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum SyntheticPreset {
    /// MPEG-like: a sphere crosses the whole scene and bounces during the clip.
    Fast,
    /// N3DV-like: small motions on a mostly static scene.
    Slow,
    /// Fast large motion: the sphere crosses 7 units (twice the view) with high bounces, about
    /// its own radius per frame.
    LargeMotion,
    /// Motion leaving the initial point cloud: the sphere lifts off the floor and flies up and
    /// towards the cameras through empty air, where frame 0's cloud has no points.
    Leaving,
    /// A strong lighting change: the light dims to 40 % and swings 45° over the clip, so shading
    /// and shadows change everywhere, also on static geometry.
    Lighting,
    /// A long GOP: the `fast` motion over 120 frames instead of 40.
    LongGop,
    /// A textured cube flies across the view (3.6 units, ~7 px per frame at 320×240), rising 1.1
    /// units and spinning 180° about a tilted axis, while the sphere rolls slowly (0.65 units):
    /// what users' fast-motion footage does to a method.
    Crossing,
}

impl SyntheticPreset {
    /// The name in `synthetic:<name>`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Fast => "fast",
            Self::Slow => "slow",
            Self::LargeMotion => "large-motion",
            Self::Leaving => "leaving",
            Self::Lighting => "lighting",
            Self::LongGop => "long-gop",
            Self::Crossing => "crossing",
        }
    }

    pub fn spec(self) -> SyntheticSpec {
        let base = SyntheticSpec {
            cameras: 12,
            frames: 40,
            width: 320,
            height: 240,
            arc_degrees: 50.0,
            fast_travel: 4.0,
            fast_bounce: 0.8,
            fast_path: FastPath::Roll,
            slow_travel: 0.3,
            slow_spin_degrees: 60.0,
            light_swing_degrees: 0.0,
            light_dimming: 0.0,
            flying_cube: None,
        };
        match self {
            Self::Fast => base,
            Self::Slow => SyntheticSpec {
                fast_travel: 0.6,
                fast_bounce: 0.1,
                slow_travel: 0.1,
                slow_spin_degrees: 15.0,
                ..base
            },
            Self::LargeMotion => SyntheticSpec {
                fast_travel: 7.0,
                fast_bounce: 1.3,
                slow_travel: 0.8,
                slow_spin_degrees: 180.0,
                ..base
            },
            Self::Leaving => SyntheticSpec {
                fast_path: FastPath::Fly,
                ..base
            },
            Self::Lighting => SyntheticSpec {
                light_swing_degrees: 45.0,
                light_dimming: 0.6,
                ..base
            },
            Self::LongGop => SyntheticSpec {
                frames: 120,
                ..base
            },
            Self::Crossing => SyntheticSpec {
                fast_travel: 0.65,
                fast_bounce: 0.0,
                flying_cube: Some(CubeFlight {
                    travel: 3.6,
                    rise: 1.1,
                    spin_degrees: 180.0,
                }),
                ..base
            },
        }
    }
}

/// Path of the fast sphere.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FastPath {
    /// Rolls along the floor across the scene and bounces.
    Roll,
    /// Lifts off the floor and flies up and towards the cameras (out of frame 0's cloud).
    Fly,
}

/// Sizes and motion amplitudes of a generated scene.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SyntheticSpec {
    pub cameras: usize,
    pub frames: usize,
    pub width: u32,
    pub height: u32,
    /// Angular span of the camera arc.
    pub arc_degrees: f64,
    /// Distance the fast sphere travels along x over the clip.
    pub fast_travel: f64,
    /// Height of its bounce.
    pub fast_bounce: f64,
    pub fast_path: FastPath,
    pub slow_travel: f64,
    pub slow_spin_degrees: f64,
    /// The light turns this far about the vertical axis over the clip.
    pub light_swing_degrees: f64,
    /// The light's intensity falls by this fraction over the clip.
    pub light_dimming: f64,
    /// A textured cube crossing the view, when present.
    #[serde(default)]
    pub flying_cube: Option<CubeFlight>,
}

/// The flight of the textured cube of the `crossing` scene.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CubeFlight {
    /// Distance along x over the clip (left to right).
    pub travel: f64,
    /// Height gained over the clip.
    pub rise: f64,
    /// Turn about its tilted axis over the clip.
    pub spin_degrees: f64,
}

/// Half edge of the flying cube.
pub const FLYING_CUBE_HALF: f64 = 0.3;

/// Centre and orientation (cube → world) of the flying cube at normalised time `time`.
pub fn flying_cube_pose(flight: &CubeFlight, time: f64) -> (DVec3, DMat3) {
    let center = DVec3::new(
        -flight.travel / 2.0 + flight.travel * time,
        FLOOR_Y - FLYING_CUBE_HALF - 0.6 - flight.rise * time,
        3.4,
    );
    // About an axis tilted 30° from the vertical towards the cameras, so the turn shows new faces
    // from every camera.
    let axis = DVec3::new(0.0, 30f64.to_radians().cos(), -30f64.to_radians().sin());
    let rotation =
        DMat3::from_axis_angle(axis, flight.spin_degrees.to_radians() * time) * rotation_y(0.4);
    (center, rotation)
}

/// World: OpenCV-like axes (y down); the floor is y = 1, the wall z = 7.
pub const FLOOR_Y: f64 = 1.0;
const WALL_Z: f64 = 7.0;
const TARGET: DVec3 = DVec3::new(0.0, 0.2, 4.0);
const SAMPLES_PER_AXIS: usize = 2;

#[derive(Clone, Copy, Debug)]
enum Texture {
    Checker { scale: f64, a: DVec3, b: DVec3 },
    Bands { a: DVec3, b: DVec3 },
    Wall,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Shape {
    Plane {
        axis: usize,
        value: f64,
        normal_sign: f64,
    },
    Sphere {
        center: DVec3,
        radius: f64,
    },
    /// Oriented box: centre, half extent, rotation (box → world).
    Cuboid {
        center: DVec3,
        half: f64,
        rotation: DMat3,
    },
}

#[derive(Clone, Copy, Debug)]
struct Object {
    /// What [`object_labels`] calls it.
    name: &'static str,
    shape: Shape,
    texture: Texture,
}

struct Hit {
    t: f64,
    normal: DVec3,
    /// Texture coordinates in object space.
    local: DVec3,
    texture: Texture,
}

fn hash_noise(p: DVec3) -> f64 {
    // Smooth value noise from a few sines: deterministic and cheap.
    let v = (p.x * 3.1).sin() * (p.y * 2.3 + 1.0).sin()
        + 0.5 * (p.z * 5.7 + p.x * 1.3).sin() * (p.y * 4.1).cos();
    0.5 + 0.25 * v
}

impl Texture {
    fn color(&self, local: DVec3) -> DVec3 {
        match *self {
            Texture::Checker { scale, a, b } => {
                let s = (local / scale).floor();
                if (s.x + s.y + s.z).rem_euclid(2.0) < 1.0 {
                    a
                } else {
                    b
                }
            }
            Texture::Bands { a, b } => {
                let lat = local.normalize_or_zero().y;
                let w = 0.5 + 0.5 * (lat * 9.0).sin();
                a * w + b * (1.0 - w)
            }
            Texture::Wall => {
                let n = hash_noise(local * 0.8);
                let stripe = if (local.x * 1.5).rem_euclid(2.0) < 1.0 {
                    0.15
                } else {
                    0.0
                };
                DVec3::new(0.45 + 0.3 * n, 0.35 + 0.25 * n + stripe, 0.55 - 0.2 * n)
            }
        }
    }
}

impl Object {
    fn intersect(&self, o: DVec3, d: DVec3) -> Option<Hit> {
        let texture = self.texture;
        match self.shape {
            Shape::Plane {
                axis,
                value,
                normal_sign,
            } => {
                let denom = d[axis];
                if denom.abs() < 1e-12 {
                    return None;
                }
                let t = (value - o[axis]) / denom;
                (t > 1e-6).then(|| {
                    let mut n = DVec3::ZERO;
                    n[axis] = normal_sign;
                    let mut local = o + d * t;
                    // Texture in the plane's own coordinates: the normal coordinate sits on a
                    // checker boundary and would flip cells from rounding alone.
                    local[axis] = 0.0;
                    Hit {
                        t,
                        normal: n,
                        local,
                        texture,
                    }
                })
            }
            Shape::Sphere { center, radius } => {
                let oc = o - center;
                let b = oc.dot(d);
                let c = oc.length_squared() - radius * radius;
                let disc = b * b - c;
                if disc < 0.0 {
                    return None;
                }
                let s = disc.sqrt();
                let t = if -b - s > 1e-6 { -b - s } else { -b + s };
                (t > 1e-6).then(|| {
                    let p = o + d * t;
                    Hit {
                        t,
                        normal: (p - center) / radius,
                        local: p - center,
                        texture,
                    }
                })
            }
            Shape::Cuboid {
                center,
                half,
                rotation,
            } => {
                let inv = rotation.transpose();
                let lo = inv * (o - center);
                let ld = inv * d;
                let (mut t0, mut t1, mut axis) = (f64::NEG_INFINITY, f64::INFINITY, 0);
                for a in 0..3 {
                    if ld[a].abs() < 1e-12 {
                        if lo[a].abs() > half {
                            return None;
                        }
                        continue;
                    }
                    let (mut near, mut far) = ((-half - lo[a]) / ld[a], (half - lo[a]) / ld[a]);
                    if near > far {
                        std::mem::swap(&mut near, &mut far);
                    }
                    if near > t0 {
                        t0 = near;
                        axis = a;
                    }
                    t1 = t1.min(far);
                }
                (t0 <= t1 && t0 > 1e-6).then(|| {
                    let mut local = lo + ld * t0 + DVec3::splat(half);
                    let mut n = DVec3::ZERO;
                    n[axis] = (local[axis] - half).signum();
                    local[axis] = 0.0; // face coordinates only (see the plane)
                    Hit {
                        t: t0,
                        normal: rotation * n,
                        local,
                        texture,
                    }
                })
            }
        }
    }
}

fn rotation_y(angle: f64) -> DMat3 {
    DMat3::from_rotation_y(angle)
}

/// Radius of the fast sphere.
pub const FAST_SPHERE_RADIUS: f64 = 0.35;

/// Centre of the fast sphere at normalised time `time` in [0, 1].
pub fn fast_sphere_center(spec: &SyntheticSpec, time: f64) -> DVec3 {
    match spec.fast_path {
        FastPath::Roll => {
            let bounce = spec.fast_bounce * (time * std::f64::consts::PI * 2.0).sin().abs();
            DVec3::new(
                -spec.fast_travel / 2.0 + spec.fast_travel * time,
                FLOOR_Y - FAST_SPHERE_RADIUS - bounce,
                3.2,
            )
        }
        // From the floor at the left up into the air (y down: up is −y) and towards the cameras;
        // smoothstep, so it starts at rest like a thrown ball leaving the hand.
        FastPath::Fly => {
            let s = time * time * (3.0 - 2.0 * time);
            DVec3::new(
                -1.0 + 2.2 * s,
                FLOOR_Y - FAST_SPHERE_RADIUS - 2.4 * s,
                3.2 - 1.0 * s,
            )
        }
    }
}

/// Half edge of the slow cube.
pub const SLOW_CUBE_HALF: f64 = 0.28;

/// Centre and orientation (cube → world) of the slow cube at normalised time `time`.
pub fn slow_cube_pose(spec: &SyntheticSpec, time: f64) -> (DVec3, DMat3) {
    (
        DVec3::new(0.1 + spec.slow_travel * time, 0.72, 5.4),
        rotation_y(spec.slow_spin_degrees.to_radians() * time),
    )
}

/// The objects at normalised time `time` in [0, 1].
fn objects(spec: &SyntheticSpec, time: f64) -> Vec<Object> {
    let fast_center = fast_sphere_center(spec, time);
    let (slow_center, slow_rotation) = slow_cube_pose(spec, time);
    let mut objects = vec![
        Object {
            name: "floor",
            shape: Shape::Plane {
                axis: 1,
                value: FLOOR_Y,
                normal_sign: -1.0,
            },
            texture: Texture::Checker {
                scale: 0.5,
                a: DVec3::new(0.85, 0.82, 0.75),
                b: DVec3::new(0.25, 0.28, 0.32),
            },
        },
        Object {
            name: "wall",
            shape: Shape::Plane {
                axis: 2,
                value: WALL_Z,
                normal_sign: -1.0,
            },
            texture: Texture::Wall,
        },
        Object {
            name: "static sphere",
            shape: Shape::Sphere {
                center: DVec3::new(-1.3, 0.4, 4.6),
                radius: 0.6,
            },
            texture: Texture::Bands {
                a: DVec3::new(0.9, 0.3, 0.2),
                b: DVec3::new(0.95, 0.85, 0.3),
            },
        },
        Object {
            name: "static cube",
            shape: Shape::Cuboid {
                center: DVec3::new(1.4, 0.6, 4.8),
                half: 0.4,
                rotation: rotation_y(0.5),
            },
            texture: Texture::Checker {
                scale: 0.2,
                a: DVec3::new(0.2, 0.5, 0.9),
                b: DVec3::new(0.9, 0.9, 0.95),
            },
        },
        // Fast: rolls across the front of the scene and bounces.
        Object {
            name: "fast sphere",
            shape: Shape::Sphere {
                center: fast_center,
                radius: FAST_SPHERE_RADIUS,
            },
            texture: Texture::Bands {
                a: DVec3::new(0.2, 0.8, 0.3),
                b: DVec3::new(0.1, 0.2, 0.6),
            },
        },
        // Slow: drifts and spins.
        Object {
            name: "slow cube",
            shape: Shape::Cuboid {
                center: slow_center,
                half: SLOW_CUBE_HALF,
                rotation: slow_rotation,
            },
            texture: Texture::Checker {
                scale: 0.14,
                a: DVec3::new(0.95, 0.5, 0.1),
                b: DVec3::new(0.3, 0.1, 0.05),
            },
        },
    ];
    if let Some(flight) = &spec.flying_cube {
        let (center, rotation) = flying_cube_pose(flight, time);
        objects.push(Object {
            name: "flying cube",
            shape: Shape::Cuboid {
                center,
                half: FLYING_CUBE_HALF,
                rotation,
            },
            texture: Texture::Checker {
                scale: 0.15,
                a: DVec3::new(0.95, 0.2, 0.6),
                b: DVec3::new(0.1, 0.75, 0.8),
            },
        });
    }
    objects
}

const LIGHT_DIR: DVec3 = DVec3::new(-0.4, -0.8, -0.45); // towards the light (up, left, towards the cameras)

/// The directional light at normalised time `time`: direction towards it and intensity.
#[derive(Clone, Copy, Debug)]
struct Light {
    towards: DVec3,
    intensity: f64,
}

fn light(spec: &SyntheticSpec, time: f64) -> Light {
    Light {
        towards: rotation_y(spec.light_swing_degrees.to_radians() * time) * LIGHT_DIR.normalize(),
        intensity: 1.0 - spec.light_dimming * time,
    }
}

/// The world direction of the ray through image point (`u`, `v`) in pixels (a pixel's centre
/// at +0.5).
fn pixel_ray(camera: &RasterCamera, c2w: DMat3, u: f64, v: f64) -> DVec3 {
    let dir = DVec3::new(
        (u - camera.cx as f64) / camera.fx as f64,
        (v - camera.cy as f64) / camera.fy as f64,
        1.0,
    );
    (c2w * dir).normalize()
}

/// The object the ray from `o` along `d` meets first beyond `min_t`: its index and the hit.
fn first_hit(objects: &[Object], o: DVec3, d: DVec3, min_t: f64) -> Option<(usize, Hit)> {
    objects
        .iter()
        .enumerate()
        .filter_map(|(i, obj)| obj.intersect(o, d).map(|h| (i, h)))
        .filter(|(_, h)| h.t > min_t)
        .min_by(|a, b| a.1.t.total_cmp(&b.1.t))
}

/// The side of `hit` that faces the ray along `d` (its normal), and the object whose shadow that
/// point lies in: the first one the ray from it towards the light meets, where that side faces
/// the light (`None` where it is lit or faces away).
fn shadow_caster(
    objects: &[Object],
    towards_light: DVec3,
    o: DVec3,
    d: DVec3,
    hit: &Hit,
) -> (DVec3, Option<usize>) {
    let n = if hit.normal.dot(d) > 0.0 {
        -hit.normal
    } else {
        hit.normal
    };
    let p = o + d * hit.t;
    let caster = (n.dot(towards_light) > 0.0)
        .then(|| first_hit(objects, p + n * 1e-6, towards_light, 1e-4).map(|(i, _)| i))
        .flatten();
    (n, caster)
}

fn trace(objects: &[Object], light: Light, o: DVec3, d: DVec3) -> DVec3 {
    let Some((_, hit)) = first_hit(objects, o, d, 0.0) else {
        return DVec3::new(0.6, 0.7, 0.85);
    };
    let (n, caster) = shadow_caster(objects, light.towards, o, d, &hit);
    let lit = n.dot(light.towards).max(0.0);
    let albedo = hit.texture.color(hit.local);
    albedo * light.intensity * (0.35 + 0.65 * if caster.is_some() { 0.0 } else { lit })
}

/// Position along the arc (0..1) of camera `i`. Camera 0, the test camera of the N3DV layout, sits
/// inside the rig (halfway between two training cameras near the middle, as N3DV's cam00 is a
/// central camera): evaluation interpolates between training views instead of extrapolating.
fn arc_position(i: usize, cameras: usize) -> f64 {
    if cameras <= 2 {
        return if cameras == 1 { 0.5 } else { i as f64 };
    }
    let spacing = 1.0 / (cameras - 2) as f64;
    if i == 0 {
        0.5 + 0.5 * spacing
    } else {
        (i - 1) as f64 * spacing
    }
}

/// The rig: `spec.cameras` cameras on an arc of radius 4.5 around the target, looking at it.
pub fn rig(spec: &SyntheticSpec) -> Vec<RasterCamera> {
    (0..spec.cameras)
        .map(|i| {
            let u = arc_position(i, spec.cameras);
            let angle = (u - 0.5) * spec.arc_degrees.to_radians();
            let center = TARGET
                + DVec3::new(
                    4.5 * angle.sin(),
                    -0.6 - 0.2 * (u * 6.0).sin(),
                    -4.5 * angle.cos(),
                );
            let forward = (TARGET - center).normalize();
            let right = DVec3::new(0.0, 1.0, 0.0).cross(forward).normalize(); // y down: right = down × forward
            let down = forward.cross(right);
            let f = 0.9 * spec.width as f64;
            camera_from_c2w(
                DMat3::from_cols(right, down, forward),
                center,
                spec.width,
                spec.height,
                f,
                f,
                (spec.width / 2) as f64,
                (spec.height / 2) as f64,
            )
        })
        .collect()
}

/// Renders one image as 8-bit RGB.
pub fn render(spec: &SyntheticSpec, camera: &RasterCamera, time: f64) -> image::RgbImage {
    let objects = objects(spec, time);
    let light = light(spec, time);
    let (c2w, center) = super::cameras::camera_to_c2w(camera);
    let mut img = image::RgbImage::new(camera.width, camera.height);
    for (x, y, px) in img.enumerate_pixels_mut() {
        let mut sum = DVec3::ZERO;
        for sy in 0..SAMPLES_PER_AXIS {
            for sx in 0..SAMPLES_PER_AXIS {
                let u = x as f64 + (sx as f64 + 0.5) / SAMPLES_PER_AXIS as f64;
                let v = y as f64 + (sy as f64 + 0.5) / SAMPLES_PER_AXIS as f64;
                sum += trace(&objects, light, center, pixel_ray(camera, c2w, u, v));
            }
        }
        let c = sum / (SAMPLES_PER_AXIS * SAMPLES_PER_AXIS) as f64;
        *px = image::Rgb(
            c.to_array()
                .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8),
        );
    }
    img
}

/// What a pixel of a synthetic image shows, by the ray through its centre.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PixelLabel {
    /// The object the ray meets first (an index into [`object_names`]), `None` for the sky.
    pub object: Option<u8>,
    /// The object whose shadow that point lies in (the first one the ray from it towards the
    /// light meets, as the renderer shades it), `None` where it is lit or faces away.
    pub shadow_of: Option<u8>,
}

/// What each pixel of `camera`'s image at `time` shows (row-major). The renders average 2×2 rays
/// per pixel, so a pixel on an outline shows a blend of its label and a neighbour. For
/// diagnostics that split the moving pixels by what moves there
/// (`examples/motion_diagnostics.rs`).
pub fn object_labels(spec: &SyntheticSpec, camera: &RasterCamera, time: f64) -> Vec<PixelLabel> {
    let objects = objects(spec, time);
    let towards_light = light(spec, time).towards;
    let (c2w, center) = super::cameras::camera_to_c2w(camera);
    let mut labels = Vec::with_capacity((camera.width * camera.height) as usize);
    for y in 0..camera.height {
        for x in 0..camera.width {
            let d = pixel_ray(camera, c2w, x as f64 + 0.5, y as f64 + 0.5);
            let label = match first_hit(&objects, center, d, 0.0) {
                None => PixelLabel {
                    object: None,
                    shadow_of: None,
                },
                Some((i, hit)) => PixelLabel {
                    object: Some(i as u8),
                    // The renderer's own shadow test (`trace`).
                    shadow_of: shadow_caster(&objects, towards_light, center, d, &hit)
                        .1
                        .map(|j| j as u8),
                },
            };
            labels.push(label);
        }
    }
    labels
}

/// The names of `spec`'s objects, indexed as [`object_labels`] labels them.
pub fn object_names(spec: &SyntheticSpec) -> Vec<&'static str> {
    objects(spec, 0.0).iter().map(|o| o.name).collect()
}

/// Whether each of `spec`'s objects (indexed as [`object_names`]) moves during the clip: its
/// shape or pose at a quarter, half, three quarters or the end of the clip differs from frame 0's.
pub fn object_moves(spec: &SyntheticSpec) -> Vec<bool> {
    let start = objects(spec, 0.0);
    let later: Vec<Vec<Object>> = [0.25, 0.5, 0.75, 1.0]
        .iter()
        .map(|&t| objects(spec, t))
        .collect();
    (0..start.len())
        .map(|i| later.iter().any(|objs| objs[i].shape != start[i].shape))
        .collect()
}

/// Pixel stride of the rays that make the initial cloud: sparse like an SfM reconstruction
/// (~10k points for the rig), so densification has work to do and a CPU step stays cheap.
const POINT_SAMPLING_STEP: usize = 10;

/// Surface points as an SfM reconstruction would give at frame 0: the first hit of rays through
/// a grid of pixels of every camera, lightly deduplicated.
pub fn points(spec: &SyntheticSpec, cameras: &[RasterCamera]) -> PointCloud {
    let objects = objects(spec, 0.0);
    let light = light(spec, 0.0);
    let mut cloud = PointCloud::default();
    let mut seen = std::collections::HashSet::new();
    for camera in cameras {
        let (c2w, center) = super::cameras::camera_to_c2w(camera);
        for y in (0..camera.height).step_by(POINT_SAMPLING_STEP) {
            for x in (0..camera.width).step_by(POINT_SAMPLING_STEP) {
                let d = pixel_ray(camera, c2w, x as f64 + 0.5, y as f64 + 0.5);
                let Some((_, hit)) = first_hit(&objects, center, d, 0.0) else {
                    continue;
                };
                let p = center + d * hit.t;
                if !seen.insert((p / 0.02).round().as_ivec3().to_array()) {
                    continue;
                }
                cloud.positions.push(p.as_vec3().to_array());
                cloud
                    .colors
                    .push(trace(&objects, light, center, d).as_vec3().to_array());
            }
        }
    }
    cloud
}

/// Version of the generator's output; cached scenes of another version are regenerated.
pub const GENERATOR_VERSION: u32 = 2;

/// Writes a synthetic dataset in the N3DV layout under `out` (created; must not hold one yet).
pub fn write_dataset(preset: SyntheticPreset, out: &Path) -> Result<()> {
    write_spec_dataset(&preset.spec(), preset.name(), out)
}

/// [`write_dataset`] of any spec (tests build scenes of their own); `name` is recorded in
/// `synthetic.json`.
pub fn write_spec_dataset(spec: &SyntheticSpec, name: &str, out: &Path) -> Result<()> {
    let spec = *spec;
    if out.join("poses_bounds.npy").exists() {
        bail!("{} already holds a dataset", out.display());
    }
    let cameras = rig(&spec);
    let rows: Vec<f64> = cameras
        .iter()
        .flat_map(|c| LlffPose::from_camera(c, 1.0, 12.0).to_row())
        .collect();
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let jobs: Vec<(usize, usize)> = (0..cameras.len())
        .flat_map(|c| (0..spec.frames).map(move |f| (c, f)))
        .collect();
    for c in 0..cameras.len() {
        std::fs::create_dir_all(out.join(format!("png/cam{c:02}")))?;
    }
    jobs.par_iter().try_for_each(|&(c, f)| -> Result<()> {
        let time = if spec.frames > 1 {
            f as f64 / (spec.frames - 1) as f64
        } else {
            0.0
        };
        let path = out.join(format!("png/cam{c:02}")).join(frame_file_name(f));
        render(&spec, &cameras[c], time)
            .save(&path)
            .with_context(|| format!("cannot write {}", path.display()))
    })?;
    let sparse = out.join("colmap_0/sparse/0");
    std::fs::create_dir_all(&sparse)?;
    write_points3d_txt(&sparse.join("points3D.txt"), &points(&spec, &cameras))?;
    std::fs::write(
        out.join("synthetic.json"),
        serde_json::to_string_pretty(&serde_json::json!({
            "preset": name,
            "generator_version": GENERATOR_VERSION,
            "spec": spec
        }))?,
    )?;
    // Written last: its presence marks a complete dataset.
    write_npy_f64(&out.join("poses_bounds.npy"), &[cameras.len(), 17], &rows)
}
