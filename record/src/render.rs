//! A deterministic CPU ray tracer (rayon over image rows) for the procedural scenes.
//!
//! Per pixel: `samples_per_pixel` primary rays (rotated-grid pattern for 4, stratified grid
//! otherwise), Blinn-Phong shading with hard shadows from every point light, mirror reflection
//! up to `max_bounces`, then exposure, a 2.2 display gamma and Gaussian sensor noise from a
//! counter-based hash (so the result does not depend on thread scheduling). Ground truth comes
//! from one extra ray through the pixel centre: z-depth (m, along the optical axis) and the
//! surface class of what it hits.

use nalgebra::{Isometry3, Matrix3, Rotation3, Vector3};
use rayon::prelude::*;

use crate::camera::PinholeCamera;
use crate::rng::{hash4, mix64};
use crate::scene::{Material, Scene, Shape, SurfaceClass, Texture};
use crate::sensor_noise::gaussians_from_bits;

type V3 = Vector3<f64>;

/// Offset along the normal that keeps secondary rays from re-hitting their own surface (m).
const SURFACE_EPSILON_M: f64 = 1e-6;
/// Texels per side of a baked noise tile.
const NOISE_TILE_TEXELS: usize = 512;
/// Lattice cells of the coarsest noise octave across one tile.
const NOISE_BASE_CELLS: usize = 8;
/// Octaves of fractal noise.
const NOISE_OCTAVES: usize = 4;
/// Rotated-grid supersampling pattern (4 samples), offsets from the pixel centre.
const RGSS_OFFSETS: [(f64, f64); 4] = [(-0.125, -0.375), (0.375, -0.125), (0.125, 0.375), (-0.375, 0.125)];

/// Rendering settings of one view.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderSettings {
    /// Primary rays per pixel (4 uses a rotated grid; other values a stratified n×n grid).
    pub samples_per_pixel: u32,
    /// Mirror bounces.
    pub max_bounces: u32,
    /// Exposure gain applied before the gamma (1 = nominal).
    pub exposure_gain: f64,
    /// Standard deviation of the sensor noise (8-bit levels).
    pub noise_sigma_levels: f64,
    /// Seed of the sensor noise of this view.
    pub noise_seed: u64,
}

impl Default for RenderSettings {
    fn default() -> Self {
        Self {
            samples_per_pixel: 4,
            max_bounces: 2,
            exposure_gain: 1.0,
            noise_sigma_levels: 1.0,
            noise_seed: 0,
        }
    }
}

/// One rendered view with its ground truth.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderedView {
    /// Width (pixels).
    pub width: u32,
    /// Height (pixels).
    pub height: u32,
    /// 8-bit RGB, row-major, 3 bytes per pixel.
    pub rgb: Vec<u8>,
    /// Ground-truth z-depth (m) along the optical axis; 0 where no surface is hit.
    pub depth_m: Vec<f32>,
    /// Ground-truth surface class per pixel ([`SurfaceClass`] as `u8`).
    pub surface_class: Vec<u8>,
}

enum Geometry {
    Plane {
        point: V3,
        normal: V3,
        u: V3,
        v: V3,
    },
    Box {
        center: V3,
        world_from_local: Matrix3<f64>,
        half: V3,
    },
    Sphere {
        center: V3,
        radius: f64,
    },
    Cylinder {
        center: V3,
        axis: V3,
        u: V3,
        v: V3,
        radius: f64,
        half_length: f64,
    },
}

struct Object {
    geometry: Geometry,
    material: usize,
    bound_center: V3,
    bound_radius: f64,
}

enum PreparedTexture {
    Solid(V3),
    Checker {
        a: V3,
        b: V3,
        inv_cell: f64,
    },
    Stripes {
        a: V3,
        b: V3,
        inv_period: f64,
        direction: (f64, f64),
    },
    Noise {
        a: V3,
        b: V3,
        texels: Vec<f32>,
        inv_tile_u: f64,
        inv_tile_v: f64,
    },
    Patches {
        palette: Vec<V3>,
        inv_cell: f64,
        seed: u64,
    },
}

struct PreparedMaterial {
    texture: PreparedTexture,
    material: Material,
    class: SurfaceClass,
    /// Seed of this material's grain.
    grain_seed: u64,
    /// `n·h` at or below which the highlight `(n·h)^shininess` is under 1e-12 (left out: the
    /// `powf` was an eighth of the renderer's time).
    highlight_cutoff: f64,
    /// The shininess when it is a whole number (every preset's): `powi`, a few multiplications,
    /// instead of `powf`.
    integer_shininess: Option<i32>,
}

struct Hit {
    t: f64,
    normal: V3,
    uv: (f64, f64),
    material: usize,
}

impl Hit {
    /// A hit at `t` whose normal and texture coordinates are not needed.
    fn at(t: f64, material: usize) -> Self {
        Self {
            t,
            normal: V3::zeros(),
            uv: (0.0, 0.0),
            material,
        }
    }
}

/// A scene prepared for tracing: textures baked, shapes in intersection form.
pub struct PreparedScene {
    objects: Vec<Object>,
    materials: Vec<PreparedMaterial>,
    lights: Vec<(V3, V3)>,
    /// Per light, which objects can shadow which rays ([`ShadowCasters`]).
    casters: Vec<ShadowCasters>,
    ambient: V3,
    background: V3,
}

/// The objects that may block the light of one point light, for shadow rays: seen from the
/// light, a ray towards a point below it is the point `(dx, dy) / −dz` of its direction `d`, and
/// an object wholly below the light can only block the rays whose point lies in the box of its
/// projected bounding cube ([`bounding_cube_corners`]). A plane can only block the rays from
/// the far side of it, seen from the light. The rest (unbounded, or reaching up to the light) is
/// tested by every ray.
struct ShadowCasters {
    always: Vec<usize>,
    /// `(object, normal, offset, side)`: a plane `normal · x = offset` with the light on the
    /// `side` (signed distance) of it.
    planes: Vec<(usize, V3, f64, f64)>,
    /// `(object, [u_min, v_min, u_max, v_max])`.
    boxed: Vec<(usize, [f64; 4])>,
}

impl ShadowCasters {
    fn new(objects: &[Object], light: &V3) -> Self {
        let mut always = Vec::new();
        let mut planes = Vec::new();
        let mut boxed = Vec::new();
        for (index, object) in objects.iter().enumerate() {
            if let Geometry::Plane { point, normal, .. } = &object.geometry {
                let offset = normal.dot(point);
                let side = normal.dot(light) - offset;
                if side != 0.0 {
                    planes.push((index, *normal, offset, side));
                    continue;
                }
            }
            let mut bounds = [f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY];
            let mut below = object.bound_radius.is_finite();
            for corner in bounding_cube_corners(object) {
                if !below {
                    break;
                }
                let d = corner - light;
                below = d.z < -1e-6;
                let (u, v) = (d.x / -d.z, d.y / -d.z);
                bounds = [bounds[0].min(u), bounds[1].min(v), bounds[2].max(u), bounds[3].max(v)];
            }
            if below {
                // A margin for rounding: a ray grazing the box's edge is still tested.
                let m = 1e-6 * (1.0 + bounds.iter().map(|b| b.abs()).fold(0.0, f64::max));
                boxed.push((index, [bounds[0] - m, bounds[1] - m, bounds[2] + m, bounds[3] + m]));
            } else {
                always.push(index);
            }
        }
        Self { always, planes, boxed }
    }

    /// Whether any object blocks the segment from `point` to the light at `light`: the ray
    /// along `dir` (unit) up to `distance`. Each object that may block it is tested once, the
    /// planes and unbounded shapes first.
    fn blocked(&self, objects: &[Object], point: &V3, light: &V3, dir: &V3, distance: f64) -> bool {
        let blocks = |index: usize| {
            let object = &objects[index];
            bound_overlaps(object, point, dir, distance) && hit_distance(object, point, dir, distance).is_some()
        };
        if self.always.iter().any(|&i| blocks(i)) {
            return true;
        }
        // A point strictly on the light's side of a plane sees the light past it: the segment
        // between them does not meet the plane.
        for (index, normal, offset, side) in &self.planes {
            if (normal.dot(point) - offset) * side <= 0.0 && blocks(*index) {
                return true;
            }
        }
        let d = point - light;
        if d.z < -1e-9 {
            let (u, v) = (d.x / -d.z, d.y / -d.z);
            for (index, b) in &self.boxed {
                if b[0] <= u && u <= b[2] && b[1] <= v && v <= b[3] && blocks(*index) {
                    return true;
                }
            }
            false
        } else {
            self.boxed.iter().any(|(i, _)| blocks(*i))
        }
    }
}

/// The corners of the cube around an object's bounding sphere (its projection from any point
/// outside holds the sphere's).
fn bounding_cube_corners(object: &Object) -> impl Iterator<Item = V3> + '_ {
    (0..8).map(move |corner: usize| {
        let sign = |bit: usize| if corner >> bit & 1 == 1 { 1.0 } else { -1.0 };
        object.bound_center + V3::new(sign(0), sign(1), sign(2)) * object.bound_radius
    })
}

fn v3(a: [f64; 3]) -> V3 {
    V3::new(a[0], a[1], a[2])
}

/// Two unit vectors completing `n` to an orthonormal basis.
fn basis(n: &V3) -> (V3, V3) {
    let helper = if n.x.abs() < 0.9 { V3::x() } else { V3::y() };
    let u = n.cross(&helper).normalize();
    let v = n.cross(&u);
    (u, v)
}

fn bake_noise(seed: u64) -> Vec<f32> {
    let n = NOISE_TILE_TEXELS;
    let mut texels = vec![0f32; n * n];
    let mut total_weight = 0.0;
    let mut weight = 1.0;
    for octave in 0..NOISE_OCTAVES {
        let cells = NOISE_BASE_CELLS << octave;
        let lattice: Vec<f64> = (0..cells * cells)
            .map(|i| crate::rng::unit_from_bits(hash4(seed, octave as u64, i as u64, 0)))
            .collect();
        let scale = cells as f64 / n as f64;
        for (row, line) in texels.chunks_mut(n).enumerate() {
            let fy = row as f64 * scale;
            let y0 = fy.floor() as usize % cells;
            let y1 = (y0 + 1) % cells;
            let ty = smooth(fy.fract());
            for (col, texel) in line.iter_mut().enumerate() {
                let fx = col as f64 * scale;
                let x0 = fx.floor() as usize % cells;
                let x1 = (x0 + 1) % cells;
                let tx = smooth(fx.fract());
                let top = lerp(lattice[y0 * cells + x0], lattice[y0 * cells + x1], tx);
                let bottom = lerp(lattice[y1 * cells + x0], lattice[y1 * cells + x1], tx);
                *texel += (weight * lerp(top, bottom, ty)) as f32;
            }
        }
        total_weight += weight;
        weight *= 0.5;
    }
    for texel in &mut texels {
        // Stretch contrast: fractal sums cluster around 0.5.
        *texel = ((*texel / total_weight as f32 - 0.5) * 2.2 + 0.5).clamp(0.0, 1.0);
    }
    texels
}

fn smooth(t: f64) -> f64 {
    t * t * (3.0 - 2.0 * t)
}

fn lerp(a: f64, b: f64, t: f64) -> f64 {
    a + (b - a) * t
}

impl PreparedTexture {
    fn new(texture: &Texture) -> Self {
        match texture {
            Texture::Solid { rgb } => Self::Solid(v3(*rgb)),
            Texture::Checker { a, b, cell_m } => Self::Checker {
                a: v3(*a),
                b: v3(*b),
                inv_cell: 1.0 / cell_m.max(1e-6),
            },
            Texture::Stripes {
                a,
                b,
                period_m,
                angle_deg,
            } => Self::Stripes {
                a: v3(*a),
                b: v3(*b),
                inv_period: 1.0 / period_m.max(1e-6),
                direction: (angle_deg.to_radians().cos(), angle_deg.to_radians().sin()),
            },
            Texture::Noise {
                a,
                b,
                scale_m,
                anisotropy,
                seed,
            } => {
                let tile_v = scale_m.max(1e-6) * NOISE_BASE_CELLS as f64;
                Self::Noise {
                    a: v3(*a),
                    b: v3(*b),
                    texels: bake_noise(*seed),
                    inv_tile_u: 1.0 / (tile_v * anisotropy.max(1e-3)),
                    inv_tile_v: 1.0 / tile_v,
                }
            }
            Texture::Patches { palette, cell_m, seed } => Self::Patches {
                palette: if palette.is_empty() {
                    vec![V3::repeat(0.5)]
                } else {
                    palette.iter().map(|c| v3(*c)).collect()
                },
                inv_cell: 1.0 / cell_m.max(1e-6),
                seed: *seed,
            },
        }
    }

    fn sample(&self, (u, v): (f64, f64)) -> V3 {
        match self {
            Self::Solid(c) => *c,
            Self::Checker { a, b, inv_cell } => {
                let parity = ((u * inv_cell).floor() as i64 + (v * inv_cell).floor() as i64) & 1;
                if parity == 0 { *a } else { *b }
            }
            Self::Stripes {
                a,
                b,
                inv_period,
                direction,
            } => {
                let s = (u * direction.0 + v * direction.1) * inv_period;
                if s - s.floor() < 0.5 { *a } else { *b }
            }
            Self::Noise {
                a,
                b,
                texels,
                inv_tile_u,
                inv_tile_v,
            } => {
                let n = NOISE_TILE_TEXELS;
                let fx = (u * inv_tile_u).rem_euclid(1.0) * n as f64;
                let fy = (v * inv_tile_v).rem_euclid(1.0) * n as f64;
                let x0 = (fx as usize).min(n - 1);
                let y0 = (fy as usize).min(n - 1);
                let x1 = (x0 + 1) % n;
                let y1 = (y0 + 1) % n;
                let tx = fx - x0 as f64;
                let ty = fy - y0 as f64;
                let top = lerp(f64::from(texels[y0 * n + x0]), f64::from(texels[y0 * n + x1]), tx);
                let bottom = lerp(f64::from(texels[y1 * n + x0]), f64::from(texels[y1 * n + x1]), tx);
                a.lerp(b, lerp(top, bottom, ty))
            }
            Self::Patches {
                palette,
                inv_cell,
                seed,
            } => {
                let cu = (u * inv_cell).floor() as i64 as u64;
                let cv = (v * inv_cell).floor() as i64 as u64;
                palette[(hash4(*seed, cu, cv, 1) % palette.len() as u64) as usize]
            }
        }
    }
}

impl PreparedScene {
    /// Bakes textures and converts shapes.
    pub fn new(scene: &Scene) -> Self {
        let materials = scene
            .materials
            .iter()
            .enumerate()
            .map(|(i, m)| PreparedMaterial {
                texture: PreparedTexture::new(&m.texture),
                material: m.clone(),
                class: m.surface_class(),
                grain_seed: hash4(0x6772, i as u64, 0, 0),
                integer_shininess: (m.shininess.fract() == 0.0 && (1.0..=1024.0).contains(&m.shininess))
                    .then_some(m.shininess as i32),
                highlight_cutoff: if m.shininess > 0.0 {
                    (-27.7 / m.shininess).exp()
                } else {
                    0.0
                },
            })
            .collect();
        let objects: Vec<Object> = scene
            .objects
            .iter()
            .map(|object| {
                let (geometry, bound_center, bound_radius) = match &object.shape {
                    Shape::Plane { point, normal } => {
                        let normal = v3(*normal).normalize();
                        let (u, v) = basis(&normal);
                        (
                            Geometry::Plane {
                                point: v3(*point),
                                normal,
                                u,
                                v,
                            },
                            V3::zeros(),
                            f64::INFINITY,
                        )
                    }
                    Shape::Box {
                        center,
                        half_extents_m,
                        yaw_deg,
                        tilt_deg,
                    } => {
                        let rotation = Rotation3::from_axis_angle(&V3::z_axis(), yaw_deg.to_radians())
                            * Rotation3::from_axis_angle(&V3::x_axis(), tilt_deg.to_radians());
                        let half = v3(*half_extents_m);
                        (
                            Geometry::Box {
                                center: v3(*center),
                                world_from_local: *rotation.matrix(),
                                half,
                            },
                            v3(*center),
                            half.norm(),
                        )
                    }
                    Shape::Sphere { center, radius_m } => (
                        Geometry::Sphere {
                            center: v3(*center),
                            radius: *radius_m,
                        },
                        v3(*center),
                        *radius_m,
                    ),
                    Shape::Cylinder {
                        center,
                        axis,
                        radius_m,
                        half_length_m,
                    } => {
                        let axis = v3(*axis).try_normalize(1e-12).unwrap_or_else(V3::z);
                        let (u, v) = basis(&axis);
                        (
                            Geometry::Cylinder {
                                center: v3(*center),
                                axis,
                                u,
                                v,
                                radius: *radius_m,
                                half_length: *half_length_m,
                            },
                            v3(*center),
                            radius_m.hypot(*half_length_m),
                        )
                    }
                };
                Object {
                    geometry,
                    material: object.material.min(scene.materials.len().saturating_sub(1)),
                    bound_center,
                    bound_radius,
                }
            })
            .collect();
        let casters = scene
            .lights
            .iter()
            .map(|l| ShadowCasters::new(&objects, &v3(l.position)))
            .collect();
        Self {
            objects,
            materials,
            casters,
            lights: scene.lights.iter().map(|l| (v3(l.position), v3(l.intensity))).collect(),
            ambient: v3(scene.ambient),
            background: v3(scene.background),
        }
    }

    /// Non-periodic value noise in [0, 1] at surface coordinates (m): hashed lattice, smooth
    /// interpolation, so the grain never repeats within a search range.
    fn grain_at(&self, (u, v): (f64, f64), seed: u64) -> f64 {
        let (fu, fv) = (u / crate::scene::GRAIN_SCALE_M, v / crate::scene::GRAIN_SCALE_M);
        let (iu, iv) = (fu.floor(), fv.floor());
        let (tu, tv) = (smooth(fu - iu), smooth(fv - iv));
        let (iu, iv) = (iu as i64 as u64, iv as i64 as u64);
        let lattice = |a: u64, b: u64| crate::rng::unit_from_bits(hash4(seed, a, b, 0x6772));
        let top = lerp(lattice(iu, iv), lattice(iu.wrapping_add(1), iv), tu);
        let bottom = lerp(
            lattice(iu, iv.wrapping_add(1)),
            lattice(iu.wrapping_add(1), iv.wrapping_add(1)),
            tu,
        );
        lerp(top, bottom, tv)
    }

    fn closest_hit(&self, origin: &V3, dir: &V3, t_max: f64) -> Option<Hit> {
        self.closest_hit_among(self.objects.iter(), origin, dir, t_max)
    }

    /// [`Self::closest_hit`] over some of the objects (in the scene's order, so that ties are
    /// broken as over all of them).
    fn closest_hit_among<'o>(
        &self,
        objects: impl Iterator<Item = &'o Object>,
        origin: &V3,
        dir: &V3,
        t_max: f64,
    ) -> Option<Hit> {
        // The normal and texture coordinates of the nearest object only: the same numbers, as
        // its intersection is computed again under the same range.
        let (object, _, limit) = Self::closest_among(objects, origin, dir, t_max)?;
        intersect(object, origin, dir, limit)
    }

    /// The nearest of `objects` along the ray: the object, its distance, and the range it was
    /// found under.
    fn closest_among<'o>(
        objects: impl Iterator<Item = &'o Object>,
        origin: &V3,
        dir: &V3,
        t_max: f64,
    ) -> Option<(&'o Object, f64, f64)> {
        let mut best = None;
        let mut limit = t_max;
        for object in objects {
            if !bound_overlaps(object, origin, dir, limit) {
                continue;
            }
            if let Some(t) = hit_distance(object, origin, dir, limit) {
                best = Some((object, t, limit));
                limit = t;
            }
        }
        best
    }

    fn trace(&self, origin: &V3, dir: &V3, bounces_left: u32) -> V3 {
        self.shade(self.closest_hit(origin, dir, f64::INFINITY), origin, dir, bounces_left)
    }

    /// The colour seen along a ray whose first hit (if any) is `hit`.
    fn shade(&self, hit: Option<Hit>, origin: &V3, dir: &V3, bounces_left: u32) -> V3 {
        let Some(hit) = hit else {
            return self.background;
        };
        let prepared = &self.materials[hit.material];
        let material = &prepared.material;
        let point = origin + dir * hit.t;
        let mut normal = hit.normal;
        if normal.dot(dir) > 0.0 {
            normal = -normal;
        }
        let mut albedo = prepared.texture.sample(hit.uv);
        if material.grain > 0.0 {
            albedo *= 1.0 + material.grain * (2.0 * self.grain_at(hit.uv, prepared.grain_seed) - 1.0);
        }
        let lifted = point + normal * SURFACE_EPSILON_M * (1.0 + point.norm());
        let mut diffuse = self.ambient;
        let mut specular = V3::zeros();
        for ((position, intensity), casters) in self.lights.iter().zip(&self.casters) {
            let to_light = position - point;
            let distance = to_light.norm();
            let l = to_light / distance;
            let n_dot_l = normal.dot(&l);
            if n_dot_l <= 0.0 || casters.blocked(&self.objects, &lifted, position, &l, distance) {
                continue;
            }
            diffuse += intensity * (material.diffuse * n_dot_l);
            if material.specular > 0.0 {
                let half = (l - dir).normalize();
                let n_dot_h = normal.dot(&half).max(0.0);
                if n_dot_h > prepared.highlight_cutoff {
                    let highlight = match prepared.integer_shininess {
                        Some(n) => n_dot_h.powi(n),
                        None => n_dot_h.powf(material.shininess),
                    };
                    specular += intensity * (material.specular * highlight);
                }
            }
        }
        let local = albedo.component_mul(&diffuse) + specular;
        if material.mirror > 0.0 && bounces_left > 0 {
            let reflected = dir - normal * (2.0 * dir.dot(&normal));
            let mirrored = self.trace(&lifted, &reflected, bounces_left - 1);
            local * (1.0 - material.mirror) + mirrored.component_mul(&v3(material.mirror_tint)) * material.mirror
        } else {
            local
        }
    }

    /// Renders one view seen from `world_from_camera`.
    pub fn render(
        &self,
        camera: &PinholeCamera,
        world_from_camera: &Isometry3<f64>,
        settings: &RenderSettings,
    ) -> RenderedView {
        let width = camera.width as usize;
        let height = camera.height as usize;
        let offsets = sample_offsets(settings.samples_per_pixel);
        let inv_samples = 1.0 / offsets.len() as f64;
        let rotation = world_from_camera.rotation.to_rotation_matrix();
        let origin = world_from_camera.translation.vector;
        let gamma_lut: Vec<f64> = (0..=GAMMA_LUT_SIZE)
            .map(|i| 255.0 * (i as f64 / GAMMA_LUT_SIZE as f64).powf(1.0 / 2.2))
            .collect();
        // Where each object can appear in the image (pixels, with a pixel of margin for the
        // sub-pixel samples): a primary ray only tests the objects whose box holds its pixel,
        // a few of the scene's dozens. The box is that of the projected corners of the cube
        // around the object's bounding sphere; an object reaching behind the camera, or
        // unbounded (a plane), may appear anywhere.
        let camera_from_world = world_from_camera.inverse();
        let everywhere = [f64::NEG_INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::INFINITY];
        let nowhere = [f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY];
        let boxes: Vec<[f64; 4]> = self
            .objects
            .iter()
            .map(|object| {
                if !object.bound_radius.is_finite() {
                    return if plane_behind(object, camera, &rotation, &origin) {
                        nowhere
                    } else {
                        everywhere
                    };
                }
                let mut bounds = [f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY];
                for corner in bounding_cube_corners(object) {
                    let point = camera_from_world * nalgebra::Point3::from(corner);
                    let Some((u, v)) = camera.project(&point.coords).filter(|_| point.z > 1e-9) else {
                        return everywhere;
                    };
                    bounds = [bounds[0].min(u), bounds[1].min(v), bounds[2].max(u), bounds[3].max(v)];
                }
                [bounds[0] - 1.0, bounds[1] - 1.0, bounds[2] + 1.0, bounds[3] + 1.0]
            })
            .collect();
        let mut rgb = vec![0u8; width * height * 3];
        let mut depth_m = vec![0f32; width * height];
        let mut surface_class = vec![0u8; width * height];
        rgb.par_chunks_mut(width * 3)
            .zip(depth_m.par_chunks_mut(width))
            .zip(surface_class.par_chunks_mut(width))
            .enumerate()
            // Rows in small tasks: the rows through the objects cost several times the table's,
            // and large tasks left a core idle at each view's end (0.1-0.2 s of a 1080p set).
            .with_max_len(4)
            .for_each(|(row, ((rgb_row, depth_row), class_row))| {
                let y = row as f64;
                let in_row: Vec<(&Object, [f64; 4])> = self
                    .objects
                    .iter()
                    .zip(&boxes)
                    .filter(|(_, b)| b[1] <= y && y <= b[3])
                    .map(|(o, b)| (o, *b))
                    .collect();
                let mut in_pixel: Vec<&Object> = Vec::with_capacity(in_row.len());
                let mut display_row = vec![0f64; width * 3];
                let (mut noise_a, mut noise_b) = (vec![0u64; width * 3], vec![0u64; width * 3]);
                let mut noise = vec![0f64; width * 3];
                for col in 0..width {
                    let x = col as f64;
                    in_pixel.clear();
                    in_pixel.extend(in_row.iter().filter(|(_, b)| b[0] <= x && x <= b[2]).map(|(o, _)| *o));
                    let candidates = || in_pixel.iter().copied();
                    let mut color = V3::zeros();
                    for (dx, dy) in &offsets {
                        let dir_camera = camera.ray_direction(col as f64 + dx, row as f64 + dy);
                        let dir = rotation * dir_camera;
                        let hit = self.closest_hit_among(candidates(), &origin, &dir, f64::INFINITY);
                        color += self.shade(hit, &origin, &dir, settings.max_bounces);
                    }
                    let dir_camera = camera.ray_direction(col as f64, row as f64);
                    let dir = rotation * dir_camera;
                    match Self::closest_among(candidates(), &origin, &dir, f64::INFINITY) {
                        Some((object, t, _)) => {
                            depth_row[col] = (t * dir_camera.z) as f32;
                            class_row[col] = self.materials[object.material].class as u8;
                        }
                        None => {
                            depth_row[col] = 0.0;
                            class_row[col] = SurfaceClass::Empty as u8;
                        }
                    }
                    for channel in 0..3 {
                        let linear = (color[channel] * inv_samples * settings.exposure_gain).clamp(0.0, 1.0);
                        display_row[col * 3 + channel] = gamma_lut[(linear * GAMMA_LUT_SIZE as f64) as usize];
                    }
                }
                // The sensor noise in passes of its own: the hashes, then the draws, four to a
                // vector (`sensor_noise`).
                if settings.noise_sigma_levels > 0.0 {
                    let first_pixel = (row * width) as u64;
                    for (i, (a, b)) in noise_a.iter_mut().zip(noise_b.iter_mut()).enumerate() {
                        *a = hash4(settings.noise_seed, first_pixel + (i / 3) as u64, (i % 3) as u64, 0);
                        *b = mix64(*a ^ 0x5851_F42D);
                    }
                    gaussians_from_bits(&noise_a, &noise_b, &mut noise);
                }
                for ((out, display), noise) in rgb_row.iter_mut().zip(&display_row).zip(&noise) {
                    *out = (display + settings.noise_sigma_levels * noise)
                        .round()
                        .clamp(0.0, 255.0) as u8;
                }
            });
        RenderedView {
            width: camera.width,
            height: camera.height,
            rgb,
            depth_m,
            surface_class,
        }
    }
}

const GAMMA_LUT_SIZE: usize = 4096;

/// Whether every primary ray of the view (the image and a pixel around it) heads away from the
/// plane `object`, so that none can meet it: the ceiling, seen by a camera looking down. The
/// direction's component along the normal is linear in the pixel (before normalising), so its
/// sign at the four corners is its sign everywhere; a margin keeps rays near parallel tested.
fn plane_behind(object: &Object, camera: &PinholeCamera, rotation: &Rotation3<f64>, origin: &V3) -> bool {
    let Geometry::Plane { point, normal, .. } = &object.geometry else {
        return false;
    };
    let side = normal.dot(&(origin - point));
    let (right, bottom) = (f64::from(camera.width), f64::from(camera.height));
    side.abs() > 1e-9
        && [(-1.0, -1.0), (right, -1.0), (-1.0, bottom), (right, bottom)]
            .iter()
            .all(|&(x, y)| side * normal.dot(&(rotation * camera.ray_direction(x, y))) > 1e-6)
}

fn sample_offsets(samples_per_pixel: u32) -> Vec<(f64, f64)> {
    match samples_per_pixel {
        0 | 1 => vec![(0.0, 0.0)],
        4 => RGSS_OFFSETS.to_vec(),
        n => {
            let side = (f64::from(n).sqrt().ceil() as u32).max(1);
            let step = 1.0 / f64::from(side);
            (0..side * side)
                .map(|i| {
                    (
                        (f64::from(i % side) + 0.5) * step - 0.5,
                        (f64::from(i / side) + 0.5) * step - 0.5,
                    )
                })
                .collect()
        }
    }
}

fn bound_overlaps(object: &Object, origin: &V3, dir: &V3, t_max: f64) -> bool {
    if !object.bound_radius.is_finite() {
        return true;
    }
    let oc = object.bound_center - origin;
    let along = oc.dot(dir);
    let r2 = object.bound_radius * object.bound_radius;
    let perpendicular2 = oc.norm_squared() - along * along;
    perpendicular2 <= r2 && along + object.bound_radius > 0.0 && along - object.bound_radius < t_max
}

fn intersect(object: &Object, origin: &V3, dir: &V3, t_max: f64) -> Option<Hit> {
    intersect_with::<true>(object, origin, dir, t_max)
}

/// The distance along the ray to `object`'s surface (the `t` of [`intersect`], the same number).
fn hit_distance(object: &Object, origin: &V3, dir: &V3, t_max: f64) -> Option<f64> {
    intersect_with::<false>(object, origin, dir, t_max).map(|hit| hit.t)
}

/// [`intersect`]; without `DETAILS` the hit's normal and texture coordinates are left zero (the
/// tests of shadow rays and of candidates that a nearer object may yet hide need only `t`).
#[inline(always)]
fn intersect_with<const DETAILS: bool>(object: &Object, origin: &V3, dir: &V3, t_max: f64) -> Option<Hit> {
    let t_min = SURFACE_EPSILON_M * 0.5;
    let material = object.material;
    match &object.geometry {
        Geometry::Plane { point, normal, u, v } => {
            let denom = normal.dot(dir);
            if denom.abs() < 1e-12 {
                return None;
            }
            let t = (point - origin).dot(normal) / denom;
            if t <= t_min || t >= t_max {
                return None;
            }
            if !DETAILS {
                return Some(Hit::at(t, material));
            }
            let p = origin + dir * t - point;
            Some(Hit {
                t,
                normal: *normal,
                uv: (p.dot(u), p.dot(v)),
                material,
            })
        }
        Geometry::Sphere { center, radius } => {
            let oc = origin - center;
            let b = oc.dot(dir);
            let c = oc.norm_squared() - radius * radius;
            let disc = b * b - c;
            if disc < 0.0 {
                return None;
            }
            let sq = disc.sqrt();
            let t = if -b - sq > t_min { -b - sq } else { -b + sq };
            if t <= t_min || t >= t_max {
                return None;
            }
            if !DETAILS {
                return Some(Hit::at(t, material));
            }
            let local = origin + dir * t - center;
            let normal = local / *radius;
            Some(Hit {
                t,
                normal,
                uv: planar_uv(&local, &normal),
                material,
            })
        }
        Geometry::Box {
            center,
            world_from_local,
            half,
        } => {
            let o = world_from_local.tr_mul(&(origin - center));
            let d = world_from_local.tr_mul(dir);
            let mut t_near = f64::NEG_INFINITY;
            let mut t_far = f64::INFINITY;
            let mut near_axis = 0;
            let mut far_axis = 0;
            for axis in 0..3 {
                if d[axis].abs() < 1e-15 {
                    if o[axis].abs() > half[axis] {
                        return None;
                    }
                    continue;
                }
                let inv = 1.0 / d[axis];
                let mut t0 = (-half[axis] - o[axis]) * inv;
                let mut t1 = (half[axis] - o[axis]) * inv;
                if t0 > t1 {
                    std::mem::swap(&mut t0, &mut t1);
                }
                if t0 > t_near {
                    t_near = t0;
                    near_axis = axis;
                }
                if t1 < t_far {
                    t_far = t1;
                    far_axis = axis;
                }
                if t_near > t_far {
                    return None;
                }
            }
            let (t, axis) = if t_near > t_min {
                (t_near, near_axis)
            } else {
                (t_far, far_axis)
            };
            if t <= t_min || t >= t_max {
                return None;
            }
            if !DETAILS {
                return Some(Hit::at(t, material));
            }
            let local = o + d * t;
            let mut local_normal = V3::zeros();
            local_normal[axis] = local[axis].signum();
            let uv = match axis {
                0 => (local.y, local.z),
                1 => (local.x, local.z),
                _ => (local.x, local.y),
            };
            Some(Hit {
                t,
                normal: world_from_local * local_normal,
                uv,
                material,
            })
        }
        Geometry::Cylinder {
            center,
            axis,
            u,
            v,
            radius,
            half_length,
        } => {
            let oc = origin - center;
            let o_axial = oc.dot(axis);
            let d_axial = dir.dot(axis);
            let o_perp = oc - axis * o_axial;
            let d_perp = dir - axis * d_axial;
            let mut best: Option<(f64, V3, (f64, f64))> = None;
            let a = d_perp.norm_squared();
            if a > 1e-15 {
                let b = o_perp.dot(&d_perp);
                let c = o_perp.norm_squared() - radius * radius;
                let disc = b * b - a * c;
                if disc >= 0.0 {
                    let sq = disc.sqrt();
                    for t in [(-b - sq) / a, (-b + sq) / a] {
                        if t > t_min && t < t_max {
                            let h = o_axial + d_axial * t;
                            if h.abs() <= *half_length {
                                if DETAILS {
                                    let radial = o_perp + d_perp * t;
                                    let angle = radial.dot(v).atan2(radial.dot(u));
                                    best = Some((t, radial / *radius, (angle * radius, h)));
                                } else {
                                    best = Some((t, V3::zeros(), (0.0, 0.0)));
                                }
                                break;
                            }
                        }
                    }
                }
            }
            if d_axial.abs() > 1e-15 {
                for cap in [-*half_length, *half_length] {
                    let t = (cap - o_axial) / d_axial;
                    if t > t_min && t < t_max && best.as_ref().is_none_or(|(bt, _, _)| t < *bt) {
                        let radial = o_perp + d_perp * t;
                        if radial.norm_squared() <= radius * radius {
                            best = Some(if DETAILS {
                                (t, axis * cap.signum(), (radial.dot(u), radial.dot(v)))
                            } else {
                                (t, V3::zeros(), (0.0, 0.0))
                            });
                        }
                    }
                }
            }
            best.map(|(t, normal, uv)| Hit {
                t,
                normal,
                uv,
                material,
            })
        }
    }
}

/// Texture coordinates from the two axes least aligned with the normal.
fn planar_uv(local: &V3, normal: &V3) -> (f64, f64) {
    let n = normal.abs();
    if n.z >= n.x && n.z >= n.y {
        (local.x, local.y)
    } else if n.y >= n.x {
        (local.x, local.z)
    } else {
        (local.y, local.z)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{Light, SceneKind, SceneObject};

    fn plane_scene(distance_m: f64) -> Scene {
        Scene {
            kind: SceneKind::Toy,
            seed: 0,
            materials: vec![Material {
                name: "grey".into(),
                texture: Texture::Checker {
                    a: [0.2; 3],
                    b: [0.8; 3],
                    cell_m: 0.05,
                },
                diffuse: 1.0,
                specular: 0.0,
                shininess: 1.0,
                mirror: 0.0,
                mirror_tint: [1.0; 3],
                grain: 0.0,
            }],
            objects: vec![SceneObject {
                name: "wall".into(),
                shape: Shape::Plane {
                    point: [0.0, 0.0, distance_m],
                    normal: [0.0, 0.0, -1.0],
                },
                material: 0,
            }],
            lights: vec![Light {
                position: [0.0, 0.0, 0.0],
                intensity: [0.5; 3],
            }],
            ambient: [0.2; 3],
            background: [0.0; 3],
            camera_height_m: distance_m,
            surface_top_m: 0.0,
        }
    }

    #[test]
    fn fronto_parallel_plane_has_constant_z_depth() {
        let scene = PreparedScene::new(&plane_scene(0.75));
        let camera = PinholeCamera::from_horizontal_fov(64, 48, 60.0);
        let view = scene.render(&camera, &Isometry3::identity(), &RenderSettings::default());
        assert!(view.depth_m.iter().all(|d| (d - 0.75).abs() < 1e-6));
        assert!(view.surface_class.iter().all(|c| *c == SurfaceClass::Diffuse as u8));
    }

    #[test]
    fn rendering_is_deterministic_and_noise_is_seeded() {
        let scene = PreparedScene::new(&Scene::build(SceneKind::Toy, 3));
        let camera = PinholeCamera::from_horizontal_fov(48, 32, 60.0);
        let pose = Isometry3::face_towards(
            &nalgebra::Point3::new(0.8, 0.0, 0.6),
            &nalgebra::Point3::new(0.8, 0.0, 0.0),
            &V3::x(),
        );
        let settings = RenderSettings::default();
        let a = scene.render(&camera, &pose, &settings);
        let b = scene.render(&camera, &pose, &settings);
        assert_eq!(a, b);
        let c = scene.render(
            &camera,
            &pose,
            &RenderSettings {
                noise_seed: 99,
                ..settings
            },
        );
        assert_ne!(a.rgb, c.rgb);
        assert_eq!(a.depth_m, c.depth_m);
    }

    /// The shadow test with its shortcuts (planes from the light's side, boxes seen from the
    /// light) against every object tested, for points all over the toy scene's room.
    #[test]
    fn shadow_shortcuts_agree_with_testing_every_object() {
        let scene = PreparedScene::new(&Scene::build(SceneKind::Toy, 5));
        let mut rng = crate::rng::SplitMix64::new(17);
        let (mut blocked, mut tested) = (0, 0);
        for ((light, _), casters) in scene.lights.iter().zip(&scene.casters) {
            for _ in 0..20_000 {
                let point = V3::new(rng.range(-0.5, 2.5), rng.range(-1.5, 1.5), rng.range(-0.3, 2.8));
                let to_light = light - point;
                let distance = to_light.norm();
                let dir = to_light / distance;
                let every = scene
                    .objects
                    .iter()
                    .any(|o| hit_distance(o, &point, &dir, distance).is_some());
                assert_eq!(
                    casters.blocked(&scene.objects, &point, light, &dir, distance),
                    every,
                    "{point:?}"
                );
                blocked += usize::from(every);
                tested += 1;
            }
        }
        // Both answers occur: the points include ones under the table and behind the walls.
        assert!(
            blocked > tested / 20 && blocked < tested - tested / 20,
            "{blocked} of {tested}"
        );
    }

    /// A plane every primary ray heads away from is met by none: the ceiling seen from above
    /// the table; the table itself is kept.
    #[test]
    fn planes_behind_the_view_are_met_by_no_ray() {
        let scene = PreparedScene::new(&Scene::build(SceneKind::Toy, 5));
        let camera = PinholeCamera::from_horizontal_fov(64, 36, 60.0);
        let pose = Isometry3::face_towards(
            &nalgebra::Point3::new(0.8, 0.0, 0.7),
            &nalgebra::Point3::new(0.85, 0.05, 0.0),
            &V3::x(),
        );
        let rotation = pose.rotation.to_rotation_matrix();
        let origin = pose.translation.vector;
        let planes: Vec<&Object> = scene
            .objects
            .iter()
            .filter(|o| matches!(o.geometry, Geometry::Plane { .. }))
            .collect();
        let behind: Vec<bool> = planes
            .iter()
            .map(|o| plane_behind(o, &camera, &rotation, &origin))
            .collect();
        assert_eq!(behind.iter().filter(|b| **b).count(), 1, "only the ceiling: {behind:?}");
        for (plane, behind) in planes.iter().zip(&behind) {
            let met = (0..36 * 4).any(|y| {
                (0..64 * 4).any(|x| {
                    let dir = rotation * camera.ray_direction(f64::from(x) / 4.0 - 0.5, f64::from(y) / 4.0 - 0.5);
                    hit_distance(plane, &origin, &dir, f64::INFINITY).is_some()
                })
            });
            assert!(!(met && *behind), "a plane taken as behind the view is met");
        }
        assert!(!behind[0], "the table is in view");
    }

    #[test]
    fn shapes_report_correct_distances() {
        let origin = V3::zeros();
        let dir = V3::z();
        let sphere = Object {
            geometry: Geometry::Sphere {
                center: V3::new(0.0, 0.0, 2.0),
                radius: 0.5,
            },
            material: 0,
            bound_center: V3::new(0.0, 0.0, 2.0),
            bound_radius: 0.5,
        };
        assert!((intersect(&sphere, &origin, &dir, 10.0).unwrap().t - 1.5).abs() < 1e-12);
        let cube = Object {
            geometry: Geometry::Box {
                center: V3::new(0.0, 0.0, 3.0),
                world_from_local: Matrix3::identity(),
                half: V3::repeat(0.25),
            },
            material: 0,
            bound_center: V3::new(0.0, 0.0, 3.0),
            bound_radius: 0.5,
        };
        let hit = intersect(&cube, &origin, &dir, 10.0).unwrap();
        assert!((hit.t - 2.75).abs() < 1e-12 && (hit.normal + V3::z()).norm() < 1e-12);
        let rod = Object {
            geometry: Geometry::Cylinder {
                center: V3::new(0.0, 0.0, 1.0),
                axis: V3::x(),
                u: V3::y(),
                v: V3::z(),
                radius: 0.1,
                half_length: 1.0,
            },
            material: 0,
            bound_center: V3::new(0.0, 0.0, 1.0),
            bound_radius: 1.01,
        };
        assert!((intersect(&rod, &origin, &dir, 10.0).unwrap().t - 0.9).abs() < 1e-12);
        let can = Object {
            geometry: Geometry::Cylinder {
                center: V3::new(0.0, 0.0, 1.0),
                axis: V3::z(),
                u: V3::x(),
                v: V3::y(),
                radius: 0.1,
                half_length: 0.2,
            },
            material: 0,
            bound_center: V3::new(0.0, 0.0, 1.0),
            bound_radius: 0.3,
        };
        let cap = intersect(&can, &origin, &dir, 10.0).unwrap();
        assert!((cap.t - 0.8).abs() < 1e-12 && (cap.normal + V3::z()).norm() < 1e-12);
    }
}
