//! Procedural scenes: shapes, materials, procedural textures and lights, in the robot's base
//! frame (`world`, z up, the table top at z = 0, the arm's base at the origin).
//!
//! A scene is plain data (serde), so the effective scene of a recording is attached to the log
//! as JSON. [`SceneKind`] builds the three built-in families: `toy` (the paper's textured toy
//! scene), `workpiece` (a reflective metal part on a metal table: the hard case), `random`
//! (varied scenes from the seed, the synthetic training set), `clutter` (what real captures have
//! and `random` lacks: tall stacks before a far floor, thin rods, natural and low textures;
//! trained on) and `bin` (parts in a tote: never trained on, the held-out check of how the
//! networks generalise).

use serde::{Deserialize, Serialize};

use crate::rng::SplitMix64;

/// Where the arm looks: the centre of the work area on the table (m, world frame).
pub const WORK_AREA_CENTER_M: [f64; 3] = [0.80, 0.0, 0.0];

/// The table as drawn by viewers (m): an infinite plane in the renderer, shown as a top of this
/// size centred on the work area.
pub const TABLE_DRAWN_SIZE_M: [f64; 2] = [1.6, 1.2];

/// An RGB colour, linear, components in [0, 1].
pub type Rgb = [f64; 3];

/// The scene families `record --scene` offers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum SceneKind {
    /// Textured toys, blocks, a ball, pencils and a textureless box on a wooden table.
    Toy,
    /// A mirror-like machined metal part and bolts on a brushed-metal table.
    Workpiece,
    /// Varied geometry (on a table tilted up to 25°), textures, materials and depth ranges drawn from the seed.
    Random,
    /// Stacks and towers up to half-way to the camera before a far, often plain floor, thin rods
    /// and wires, natural textures: large depth jumps and far surfaces, from the seed.
    Clutter,
    /// Bin picking: parts (some of metal) heaped in a tote whose walls hide much of them; never
    /// used for training (the held-out family).
    Bin,
    /// Thin structures before a far floor: rods, wires, lamp arms, slats and leaves 1–6 px wide
    /// at 640 px, 20+ px of disparity in front of it, and a near board whose occluded strip is
    /// wider than a training crop; never used for training (held out, as `bin`).
    Thin,
    /// Training's thin parts: grilles and lattices of bars 1–6 px wide with gaps of one to five
    /// widths, rods and wires, leaves and stacks before a far floor (3–37 px of disparity above
    /// it at 640 px and a 20 mm baseline); the
    /// `thin` family's kinds of parts drawn differently (several grilles, crossing bars, no
    /// lamps or board), so that `thin` stays a check of what training never saw.
    Fence,
    /// Training's lamps and boards: desk lamps of two to four jointed arms 1–6 px wide (posts,
    /// segments, joints, a shade), tripods of three legs, long sagging cables, and one or two
    /// matte slabs near the camera whose occluded strips on the floor are 20–50 px wide at 640
    /// px, before a far floor (plain in a third of the scenes). The `thin` family's lamp arms and
    /// near board drawn differently (more joints, shades, tripods, cables, no slats or leaves),
    /// so that `thin` stays a check of what training never saw.
    Lamps,
    /// One matte, finely textured plane tilted 5–35° under the camera, nothing else: disparity
    /// is exactly linear in the image, every pixel at a different sub-pixel offset. The
    /// sub-pixel precision benchmark (BadPix 0.07 against exact truth); never used for training.
    Slanted,
}

/// A texture: a function from surface coordinates (m) to albedo.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "type")]
pub enum Texture {
    /// One colour: a textureless surface.
    Solid {
        /// Albedo.
        rgb: Rgb,
    },
    /// A checkerboard.
    Checker {
        /// First colour.
        a: Rgb,
        /// Second colour.
        b: Rgb,
        /// Cell size (m).
        cell_m: f64,
    },
    /// Parallel stripes.
    Stripes {
        /// First colour.
        a: Rgb,
        /// Second colour.
        b: Rgb,
        /// Stripe period (m).
        period_m: f64,
        /// Stripe direction in the surface plane (degrees).
        angle_deg: f64,
    },
    /// Fractal value noise blending two colours (wood, stone, brushed metal).
    Noise {
        /// Colour at noise 0.
        a: Rgb,
        /// Colour at noise 1.
        b: Rgb,
        /// Feature size of the coarsest octave (m).
        scale_m: f64,
        /// Stretch along the surface u axis (1 = isotropic, > 1 = brushed or grain).
        anisotropy: f64,
        /// Noise seed.
        seed: u64,
    },
    /// Random coloured cells (a "patches" pattern like printed packaging).
    Patches {
        /// Colours drawn per cell.
        palette: Vec<Rgb>,
        /// Cell size (m).
        cell_m: f64,
        /// Pattern seed.
        seed: u64,
    },
}

/// Surface reflectance: diffuse albedo texture, Blinn-Phong highlight, mirror reflection.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Material {
    /// Human-readable name.
    pub name: String,
    /// Albedo texture.
    pub texture: Texture,
    /// Diffuse weight.
    pub diffuse: f64,
    /// Blinn-Phong specular weight.
    pub specular: f64,
    /// Blinn-Phong exponent.
    pub shininess: f64,
    /// Fraction of light mirrored (0 = matte, 1 = perfect mirror).
    pub mirror: f64,
    /// Colour of the mirrored light (metal tint).
    pub mirror_tint: Rgb,
    /// Amplitude of the fine surface grain that modulates the albedo (0 = perfectly uniform;
    /// 0.1 = ±10 %): the micro-texture of paper, wood or plastic at sub-millimetre scale.
    #[serde(default)]
    pub grain: f64,
}

/// Feature size of the surface grain (m).
pub const GRAIN_SCALE_M: f64 = 0.0006;
/// Grain of ordinary matte and glossy surfaces.
const DEFAULT_GRAIN: f64 = 0.12;

/// Specular weight above which a surface counts as glossy in the ground-truth mask.
pub const GLOSSY_SPECULAR_THRESHOLD: f64 = 0.25;
/// Mirror fraction above which a surface counts as a mirror in the ground-truth mask.
pub const MIRROR_THRESHOLD: f64 = 0.05;

/// Ground-truth surface class logged per pixel (`mono8`): view-dependent surfaces break the
/// photo-consistency that matching relies on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum SurfaceClass {
    /// Lambertian or weakly glossy: photo-consistent across views.
    Diffuse = 0,
    /// Strong Blinn-Phong highlights.
    Glossy = 128,
    /// Mirror-like metal: shows reflections of the scene.
    Mirror = 255,
    /// No surface hit (nothing visible along the ray).
    Empty = 64,
}

impl Material {
    /// The ground-truth class of this material.
    pub fn surface_class(&self) -> SurfaceClass {
        if self.mirror > MIRROR_THRESHOLD {
            SurfaceClass::Mirror
        } else if self.specular > GLOSSY_SPECULAR_THRESHOLD {
            SurfaceClass::Glossy
        } else {
            SurfaceClass::Diffuse
        }
    }

    fn matte(name: &str, texture: Texture) -> Self {
        Self {
            name: name.to_owned(),
            texture,
            diffuse: 0.9,
            specular: 0.05,
            shininess: 16.0,
            mirror: 0.0,
            mirror_tint: [1.0; 3],
            grain: DEFAULT_GRAIN,
        }
    }

    fn glossy(name: &str, texture: Texture) -> Self {
        Self {
            specular: 0.45,
            shininess: 60.0,
            diffuse: 0.8,
            ..Self::matte(name, texture)
        }
    }

    fn metal(name: &str, texture: Texture, mirror: f64) -> Self {
        Self {
            name: name.to_owned(),
            texture,
            diffuse: 0.35,
            specular: 0.8,
            shininess: 120.0,
            mirror,
            mirror_tint: [0.92, 0.93, 0.95],
            grain: DEFAULT_GRAIN / 2.0,
        }
    }
}

/// A geometric primitive in the world frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "type")]
pub enum Shape {
    /// An infinite plane.
    Plane {
        /// A point on the plane (m).
        point: [f64; 3],
        /// Unit normal.
        normal: [f64; 3],
    },
    /// An oriented box.
    Box {
        /// Centre (m).
        center: [f64; 3],
        /// Half sizes along the box's own axes (m).
        half_extents_m: [f64; 3],
        /// Rotation about world z (yaw, degrees), then about the box x axis (tilt, degrees).
        yaw_deg: f64,
        /// Tilt about the box's x axis (degrees).
        tilt_deg: f64,
    },
    /// A sphere.
    Sphere {
        /// Centre (m).
        center: [f64; 3],
        /// Radius (m).
        radius_m: f64,
    },
    /// A capped cylinder (thin ones make wires and pencils).
    Cylinder {
        /// Centre of the axis segment (m).
        center: [f64; 3],
        /// Axis direction (normalised on use).
        axis: [f64; 3],
        /// Radius (m).
        radius_m: f64,
        /// Half length along the axis (m).
        half_length_m: f64,
    },
}

impl Shape {
    /// A box standing on its base: turned `yaw_deg` about world z, not tilted.
    pub fn upright_box(center: [f64; 3], half_extents_m: [f64; 3], yaw_deg: f64) -> Self {
        Self::Box {
            center,
            half_extents_m,
            yaw_deg,
            tilt_deg: 0.0,
        }
    }

    /// A cylinder along `axis`.
    pub fn cylinder(center: [f64; 3], axis: [f64; 3], radius_m: f64, half_length_m: f64) -> Self {
        Self::Cylinder {
            center,
            axis,
            radius_m,
            half_length_m,
        }
    }

    /// A sphere.
    pub fn sphere(center: [f64; 3], radius_m: f64) -> Self {
        Self::Sphere { center, radius_m }
    }
}

/// A shape with a material.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneObject {
    /// Name (for humans and the attached scene description).
    pub name: String,
    /// Geometry.
    pub shape: Shape,
    /// Index into [`Scene::materials`].
    pub material: usize,
}

/// A point light with hard shadows.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Light {
    /// Position (m, world).
    pub position: [f64; 3],
    /// Radiance scale per channel.
    pub intensity: Rgb,
}

/// A complete scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Scene {
    /// Which family built it.
    pub kind: SceneKind,
    /// Seed it was built from.
    pub seed: u64,
    /// Materials referenced by index.
    pub materials: Vec<Material>,
    /// Objects.
    pub objects: Vec<SceneObject>,
    /// Lights.
    pub lights: Vec<Light>,
    /// Ambient light level.
    pub ambient: Rgb,
    /// Colour seen where a ray escapes.
    pub background: Rgb,
    /// Suggested distance from the camera to the table for this scene (m).
    pub camera_height_m: f64,
    /// Height (m above the table plane) that a tilted infinite plane reaches inside the view,
    /// which its shape cannot tell ([`Shape::top_m`] is `None` for planes); 0 for scenes without.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub surface_top_m: f64,
}

fn is_zero(x: &f64) -> bool {
    *x == 0.0
}

impl Shape {
    /// The highest point of the shape (m above the table plane, an upper bound for tilted
    /// boxes); `None` for an infinite plane.
    pub fn top_m(&self) -> Option<f64> {
        match self {
            Shape::Plane { .. } => None,
            Shape::Box {
                center, half_extents_m, ..
            } => Some(center[2] + half_extents_m.iter().map(|e| e * e).sum::<f64>().sqrt()),
            Shape::Sphere { center, radius_m } => Some(center[2] + radius_m),
            Shape::Cylinder {
                center,
                axis,
                radius_m,
                half_length_m,
            } => {
                let norm = axis.iter().map(|a| a * a).sum::<f64>().sqrt().max(f64::EPSILON);
                Some(center[2] + half_length_m * (axis[2] / norm).abs() + radius_m)
            }
        }
    }
}

impl Scene {
    /// The highest point of any object (m above the table plane, at least 0): with
    /// [`Scene::camera_height_m`], the working depth range of a capture looking down at it.
    pub fn highest_point_m(&self) -> f64 {
        self.objects
            .iter()
            .filter_map(|o| o.shape.top_m())
            .fold(self.surface_top_m, f64::max)
    }

    /// Builds the scene of a family for a seed.
    pub fn build(kind: SceneKind, seed: u64) -> Self {
        match kind {
            SceneKind::Toy => toy_scene(seed),
            SceneKind::Workpiece => workpiece_scene(seed),
            SceneKind::Random => random_scene(seed),
            SceneKind::Clutter => clutter_scene(seed),
            SceneKind::Bin => bin_scene(seed),
            SceneKind::Thin => thin_scene(seed),
            SceneKind::Fence => fence_scene(seed),
            SceneKind::Lamps => lamps_scene(seed),
            SceneKind::Slanted => slanted_scene(seed),
        }
    }

    fn add_material(&mut self, material: Material) -> usize {
        self.materials.push(material);
        self.materials.len() - 1
    }

    fn add(&mut self, name: &str, shape: Shape, material: usize) {
        self.objects.push(SceneObject {
            name: name.to_owned(),
            shape,
            material,
        });
    }

    fn empty(kind: SceneKind, seed: u64, camera_height_m: f64) -> Self {
        Self {
            kind,
            seed,
            materials: Vec::new(),
            objects: Vec::new(),
            lights: Vec::new(),
            ambient: [0.18; 3],
            background: [0.55, 0.6, 0.65],
            camera_height_m,
            surface_top_m: 0.0,
        }
    }

    /// Room around the table so that reflections and grazing rays see something.
    fn add_room(&mut self) {
        let wall = self.add_material(Material::matte(
            "wall",
            Texture::Noise {
                a: [0.55, 0.55, 0.52],
                b: [0.7, 0.68, 0.64],
                scale_m: 0.4,
                anisotropy: 1.0,
                seed: 7,
            },
        ));
        let c = WORK_AREA_CENTER_M;
        self.add(
            "back_wall",
            Shape::Plane {
                point: [c[0] + 1.6, 0.0, 0.0],
                normal: [-1.0, 0.0, 0.0],
            },
            wall,
        );
        // Ceiling panels and fittings: what mirror-like metal reflects.
        let ceiling = self.add_material(Material::matte(
            "ceiling_panels",
            Texture::Patches {
                palette: vec![
                    [0.75, 0.75, 0.72],
                    [0.35, 0.37, 0.4],
                    [0.95, 0.95, 0.9],
                    [0.2, 0.22, 0.25],
                    [0.6, 0.5, 0.4],
                ],
                cell_m: 0.08,
                seed: 11,
            },
        ));
        self.add(
            "ceiling",
            Shape::Plane {
                point: [0.0, 0.0, 2.6],
                normal: [0.0, 0.0, -1.0],
            },
            ceiling,
        );
    }

    fn add_lights(&mut self, rng: &mut SplitMix64) {
        let c = WORK_AREA_CENTER_M;
        self.lights.push(Light {
            position: [c[0] + rng.range(-0.6, 0.6), c[1] + rng.range(-1.0, -0.4), 1.9],
            intensity: [0.62, 0.6, 0.57],
        });
        self.lights.push(Light {
            position: [c[0] + rng.range(-0.6, 0.6), c[1] + rng.range(0.4, 1.0), 2.1],
            intensity: [0.3, 0.32, 0.35],
        });
    }
}

fn table(scene: &mut Scene, material: usize) {
    scene.add(
        "table",
        Shape::Plane {
            point: [0.0, 0.0, 0.0],
            normal: [0.0, 0.0, 1.0],
        },
        material,
    );
}

fn toy_scene(seed: u64) -> Scene {
    let mut rng = SplitMix64::new(seed ^ 0x0074_6f79);
    let mut scene = Scene::empty(SceneKind::Toy, seed, 0.62);
    let wood = scene.add_material(Material::matte(
        "wood",
        Texture::Noise {
            a: [0.45, 0.3, 0.17],
            b: [0.7, 0.5, 0.3],
            scale_m: 0.012,
            anisotropy: 5.0,
            seed: rng.next_u64(),
        },
    ));
    table(&mut scene, wood);
    scene.add_room();
    let checker = scene.add_material(Material::matte(
        "checker",
        Texture::Checker {
            a: [0.85, 0.2, 0.15],
            b: [0.95, 0.9, 0.8],
            cell_m: 0.02,
        },
    ));
    let patches = scene.add_material(Material::matte(
        "patches",
        Texture::Patches {
            palette: vec![
                [0.9, 0.75, 0.1],
                [0.1, 0.35, 0.8],
                [0.15, 0.6, 0.25],
                [0.85, 0.85, 0.85],
                [0.6, 0.1, 0.5],
            ],
            cell_m: 0.012,
            seed: rng.next_u64(),
        },
    ));
    let stripes = scene.add_material(Material::glossy(
        "stripes",
        Texture::Stripes {
            a: [0.1, 0.1, 0.12],
            b: [0.9, 0.8, 0.2],
            period_m: 0.015,
            angle_deg: 30.0,
        },
    ));
    let plain = scene.add_material(Material {
        grain: 0.0,
        ..Material::matte("textureless", Texture::Solid { rgb: [0.8, 0.8, 0.78] })
    });
    let stone = scene.add_material(Material::matte(
        "stone",
        Texture::Noise {
            a: [0.25, 0.3, 0.35],
            b: [0.75, 0.72, 0.65],
            scale_m: 0.015,
            anisotropy: 1.0,
            seed: rng.next_u64(),
        },
    ));
    let pencil = scene.add_material(Material::glossy("pencil", Texture::Solid { rgb: [0.9, 0.55, 0.05] }));
    let c = WORK_AREA_CENTER_M;
    scene.add(
        "checker_block",
        Shape::upright_box([c[0] - 0.05, c[1] - 0.12, 0.06], [0.05, 0.07, 0.06], 20.0),
        checker,
    );
    scene.add(
        "patch_box",
        Shape::upright_box([c[0] + 0.1, c[1] + 0.08, 0.04], [0.08, 0.05, 0.04], -15.0),
        patches,
    );
    scene.add("ball", Shape::sphere([c[0] - 0.09, c[1] + 0.12, 0.055], 0.055), stone);
    scene.add(
        "striped_can",
        Shape::cylinder([c[0] + 0.12, c[1] - 0.1, 0.07], [0.0, 0.0, 1.0], 0.035, 0.07),
        stripes,
    );
    scene.add(
        "textureless_box",
        Shape::upright_box([c[0] + 0.02, c[1] + 0.0, 0.025], [0.04, 0.04, 0.025], 40.0),
        plain,
    );
    for (i, (dx, dy, yaw)) in [(-0.16, -0.02, 10.0f64), (0.16, 0.14, 80.0), (-0.02, 0.2, -35.0)]
        .into_iter()
        .enumerate()
    {
        let yaw = yaw.to_radians();
        scene.add(
            &format!("pencil_{i}"),
            Shape::cylinder([c[0] + dx, c[1] + dy, 0.004], [yaw.cos(), yaw.sin(), 0.0], 0.004, 0.08),
            pencil,
        );
    }
    // A thin wire arch standing above the table: a thin structure in front of the background.
    scene.add(
        "wire",
        Shape::cylinder([c[0] - 0.02, c[1] - 0.02, 0.15], [0.3, 1.0, 0.0], 0.0025, 0.2),
        pencil,
    );
    scene.add_lights(&mut rng);
    scene
}

fn workpiece_scene(seed: u64) -> Scene {
    let mut rng = SplitMix64::new(seed ^ 0x776f_726b);
    let mut scene = Scene::empty(SceneKind::Workpiece, seed, 0.6);
    let brushed = scene.add_material(Material::metal(
        "brushed_steel_table",
        Texture::Noise {
            a: [0.3, 0.31, 0.33],
            b: [0.7, 0.71, 0.74],
            scale_m: 0.004,
            anisotropy: 8.0,
            seed: rng.next_u64(),
        },
        0.12,
    ));
    table(&mut scene, brushed);
    scene.add_room();
    let polished = scene.add_material(Material::metal(
        "polished_aluminium",
        Texture::Noise {
            a: [0.55, 0.56, 0.58],
            b: [0.7, 0.71, 0.73],
            scale_m: 0.02,
            anisotropy: 1.0,
            seed: rng.next_u64(),
        },
        0.75,
    ));
    let bolt = scene.add_material(Material::metal(
        "zinc_bolt",
        Texture::Solid { rgb: [0.6, 0.6, 0.55] },
        0.4,
    ));
    let cardboard = scene.add_material(Material::matte(
        "cardboard_label",
        Texture::Patches {
            palette: vec![
                [0.7, 0.55, 0.35],
                [0.15, 0.15, 0.15],
                [0.85, 0.8, 0.7],
                [0.75, 0.2, 0.1],
            ],
            cell_m: 0.01,
            seed: rng.next_u64(),
        },
    ));
    let rubber = scene.add_material(Material::matte(
        "rubber_mat",
        Texture::Checker {
            a: [0.12, 0.12, 0.12],
            b: [0.3, 0.3, 0.32],
            cell_m: 0.015,
        },
    ));
    let c = WORK_AREA_CENTER_M;
    scene.add(
        "rubber_mat",
        Shape::upright_box([c[0] - 0.14, c[1] + 0.1, 0.002], [0.09, 0.11, 0.002], 5.0),
        rubber,
    );
    // The machined part: a flange plate with a boss and a shaft.
    scene.add(
        "part_plate",
        Shape::upright_box([c[0] + 0.02, c[1] - 0.02, 0.015], [0.1, 0.07, 0.015], 12.0),
        polished,
    );
    scene.add(
        "part_boss",
        Shape::cylinder([c[0] + 0.03, c[1] - 0.02, 0.05], [0.0, 0.0, 1.0], 0.045, 0.02),
        polished,
    );
    scene.add(
        "part_shaft",
        Shape::cylinder([c[0] + 0.03, c[1] - 0.02, 0.1], [0.0, 0.0, 1.0], 0.015, 0.04),
        polished,
    );
    scene.add(
        "part_ball",
        Shape::sphere([c[0] - 0.1, c[1] - 0.13, 0.04], 0.04),
        polished,
    );
    for i in 0..5 {
        let angle = f64::from(i) * 0.9 + rng.range(0.0, 0.3);
        let x = c[0] + 0.13 + 0.04 * angle.cos();
        let y = c[1] + 0.12 + 0.05 * angle.sin();
        scene.add(
            &format!("bolt_{i}"),
            Shape::cylinder([x, y, 0.008], [angle.cos(), angle.sin(), 0.0], 0.006, 0.03),
            bolt,
        );
    }
    scene.add(
        "label_box",
        Shape::upright_box([c[0] - 0.16, c[1] - 0.02, 0.045], [0.035, 0.05, 0.045], -8.0),
        cardboard,
    );
    scene.add_lights(&mut rng);
    scene
}

fn random_color(rng: &mut SplitMix64) -> Rgb {
    [rng.range(0.05, 0.95), rng.range(0.05, 0.95), rng.range(0.05, 0.95)]
}

/// A texture drawn from the seed. Natural fractal noise (wood, stone, fabric, print) is the most
/// likely, as in real scenes; periodic checkers and stripes and grid-aligned patches, whose
/// repetition makes matching ambiguous along the baseline, are rarer. `natural` in 0..=10 weights
/// the noise further (a table fills most of the view, so a periodic table would dominate the data).
fn random_texture(rng: &mut SplitMix64, natural: u64) -> Texture {
    let draw = rng.below(10 + natural);
    match draw {
        0 | 1 => Texture::Solid { rgb: random_color(rng) },
        2 => Texture::Checker {
            a: random_color(rng),
            b: random_color(rng),
            cell_m: rng.range(0.004, 0.05),
        },
        3 => Texture::Stripes {
            a: random_color(rng),
            b: random_color(rng),
            period_m: rng.range(0.004, 0.04),
            angle_deg: rng.range(0.0, 180.0),
        },
        4 | 5 => Texture::Patches {
            palette: (0..rng.range_usize(2, 6)).map(|_| random_color(rng)).collect(),
            cell_m: rng.range(0.003, 0.03),
            seed: rng.next_u64(),
        },
        _ => Texture::Noise {
            a: random_color(rng),
            b: random_color(rng),
            // The noise tile repeats every 8 scales: at least 8 cm, wider than any searched
            // disparity range at these depths, so the repetition cannot fake a match.
            scale_m: rng.range(0.01, 0.08),
            anisotropy: if rng.below(3) == 0 { rng.range(2.0, 12.0) } else { 1.0 },
            seed: rng.next_u64(),
        },
    }
}

fn random_material(rng: &mut SplitMix64, name: &str, natural: u64) -> Material {
    let texture = random_texture(rng, natural);
    let textureless = matches!(texture, Texture::Solid { .. }) && rng.below(2) == 0;
    let material = match rng.below(10) {
        0..=5 => Material::matte(name, texture),
        6..=7 => Material::glossy(name, texture),
        _ => Material::metal(name, texture, rng.range(0.2, 0.85)),
    };
    if textureless {
        Material { grain: 0.0, ..material }
    } else {
        material
    }
}

/// The highest camera (m above the table, over [`WORK_AREA_CENTER_M`]) from which the UR10 takes
/// every view of a 5 × 5 grid at the default 20 mm baseline (a cross reaches 0.95 m, a 5 × 5 grid
/// at 40 mm 0.89 m): the families draw their heights under it, so that their stations are
/// reachable by construction (`capture` tests every family on the five-view, 3 × 3 and line rigs).
pub const MAX_CAMERA_HEIGHT_M: f64 = 0.93;

/// A camera height drawn uniformly from `low..high` and kept within
/// [`MAX_CAMERA_HEIGHT_M`]: a draw above it is mapped linearly from `MAX..high` onto
/// `low..MAX`, so that the heights stay uniform over the reachable range and a draw that was
/// reachable keeps its value (and its seed its scene).
fn camera_height(rng: &mut SplitMix64, low: f64, high: f64) -> f64 {
    let h = rng.range(low, high);
    if h <= MAX_CAMERA_HEIGHT_M || high <= MAX_CAMERA_HEIGHT_M {
        return h;
    }
    low + (h - MAX_CAMERA_HEIGHT_M) / (high - MAX_CAMERA_HEIGHT_M) * (MAX_CAMERA_HEIGHT_M - low)
}

fn random_scene(seed: u64) -> Scene {
    let mut rng = SplitMix64::new(seed ^ 0x7261_6e64);
    let camera_height_m = camera_height(&mut rng, 0.4, 1.1);
    let mut scene = Scene::empty(SceneKind::Random, seed, camera_height_m);
    let table_material = random_material(&mut rng, "table", 20);
    let table_material = scene.add_material(table_material);
    // Most tables are tilted (up to 25°, any direction, about the work-area centre): a surface
    // slanted to the camera, whose disparity changes continuously across the view.
    let tilt = if rng.below(10) < 7 {
        rng.range(0.0, 25f64.to_radians())
    } else {
        0.0
    };
    let azimuth = rng.range(0.0, std::f64::consts::TAU);
    scene.add(
        "table",
        Shape::Plane {
            point: WORK_AREA_CENTER_M,
            normal: [tilt.sin() * azimuth.cos(), tilt.sin() * azimuth.sin(), tilt.cos()],
        },
        table_material,
    );
    scene.add_room();
    // Field of view at table height scales with the camera height; spread objects over it.
    let spread = 0.45 * camera_height_m;
    let object_count = rng.range_usize(8, 30);
    let c = WORK_AREA_CENTER_M;
    for index in 0..object_count {
        let material = random_material(&mut rng, &format!("material_{index}"), 0);
        let material = scene.add_material(material);
        let x = c[0] + rng.range(-spread, spread);
        let y = c[1] + rng.range(-spread, spread);
        let size = rng.range(0.008, 0.07) * camera_height_m / 0.6;
        // Some objects float at varied heights (shelves, hanging parts): depth variety.
        let lift = if rng.below(4) == 0 {
            rng.range(0.0, 0.35 * camera_height_m)
        } else {
            0.0
        };
        let shape = match rng.below(8) {
            0..=2 => Shape::Box {
                center: [x, y, lift + size],
                half_extents_m: [size * rng.range(0.4, 1.5), size * rng.range(0.4, 1.5), size],
                yaw_deg: rng.range(0.0, 90.0),
                tilt_deg: if lift > 0.0 { rng.range(-30.0, 30.0) } else { 0.0 },
            },
            3 | 4 => Shape::sphere([x, y, lift + size], size),
            5 | 6 => {
                let upright = rng.below(2) == 0;
                let yaw = rng.range(0.0, std::f64::consts::TAU);
                let radius = size * rng.range(0.3, 0.8);
                Shape::cylinder(
                    [x, y, lift + if upright { size } else { radius }],
                    if upright {
                        [0.0, 0.0, 1.0]
                    } else {
                        [yaw.cos(), yaw.sin(), 0.0]
                    },
                    radius,
                    size,
                )
            }
            _ => {
                // Thin structure: a rod or wire, possibly slanted and floating.
                let yaw = rng.range(0.0, std::f64::consts::TAU);
                let pitch = rng.range(-0.4, 0.4);
                Shape::cylinder(
                    [x, y, lift + 0.01],
                    [
                        yaw.cos() * pitch.cos(),
                        yaw.sin() * pitch.cos(),
                        pitch.sin().abs() * 0.2,
                    ],
                    rng.range(0.0015, 0.006),
                    rng.range(0.05, 0.25),
                )
            }
        };
        scene.add(&format!("object_{index}"), shape, material);
    }
    scene.ambient = [rng.range(0.1, 0.3); 3];
    scene.add_lights(&mut rng);
    scene
}

/// A far floor: in a third of the scenes plain (faint noise between `plain_a` and `plain_b`),
/// else a random material.
fn far_floor(rng: &mut SplitMix64, plain_a: Rgb, plain_b: Rgb) -> Material {
    if rng.below(3) == 0 {
        Material::matte(
            "plain_floor",
            Texture::Noise {
                a: plain_a,
                b: plain_b,
                scale_m: rng.range(0.02, 0.2),
                anisotropy: 1.0,
                seed: rng.next_u64(),
            },
        )
    } else {
        random_material(rng, "floor", 20)
    }
}

/// `clutter`: what real captures have and the `random` family rarely draws. A far floor (the
/// start of the range; plain or faintly textured in a third of the scenes), stacks of boxes and
/// upright cylinders reaching a quarter to a half of the way to the camera (depth jumps of many
/// disparities at their edges), thin rods and wires floating across them, and mostly natural
/// (fractal noise) textures with a few low-texture surfaces.
fn clutter_scene(seed: u64) -> Scene {
    let mut rng = SplitMix64::new(seed ^ 0x636c_7574);
    let camera_height_m = camera_height(&mut rng, 0.5, 1.2);
    let mut scene = Scene::empty(SceneKind::Clutter, seed, camera_height_m);
    let floor = far_floor(&mut rng, [0.5, 0.5, 0.48], [0.56, 0.55, 0.53]);
    let floor = scene.add_material(floor);
    table(&mut scene, floor);
    scene.add_room();
    let spread = 0.45 * camera_height_m;
    let c = WORK_AREA_CENTER_M;
    let stacks = rng.range_usize(3, 9);
    for index in 0..stacks {
        let material = random_material(&mut rng, &format!("stack_material_{index}"), 10);
        let material = scene.add_material(material);
        let (x, y) = (c[0] + rng.range(-spread, spread), c[1] + rng.range(-spread, spread));
        let height = camera_height_m * rng.range(0.1, 0.5);
        let width = camera_height_m * rng.range(0.03, 0.12);
        let shape = if rng.below(3) == 0 {
            Shape::cylinder([x, y, height / 2.0], [0.0, 0.0, 1.0], width, height / 2.0)
        } else {
            Shape::upright_box(
                [x, y, height / 2.0],
                [width, width * rng.range(0.5, 1.5), height / 2.0],
                rng.range(0.0, 90.0),
            )
        };
        scene.add(&format!("stack_{index}"), shape, material);
    }
    let small = rng.range_usize(4, 16);
    for index in 0..small {
        let material = random_material(&mut rng, &format!("part_material_{index}"), 10);
        let material = scene.add_material(material);
        let (x, y) = (c[0] + rng.range(-spread, spread), c[1] + rng.range(-spread, spread));
        let size = camera_height_m * rng.range(0.01, 0.05);
        let shape = if rng.below(2) == 0 {
            Shape::sphere([x, y, size], size)
        } else {
            Shape::upright_box(
                [x, y, size],
                [size, size * rng.range(0.5, 2.0), size],
                rng.range(0.0, 90.0),
            )
        };
        scene.add(&format!("part_{index}"), shape, material);
    }
    let rods = rng.range_usize(2, 8);
    for index in 0..rods {
        let material = random_material(&mut rng, &format!("rod_material_{index}"), 0);
        let material = scene.add_material(material);
        let (x, y) = (c[0] + rng.range(-spread, spread), c[1] + rng.range(-spread, spread));
        let yaw = rng.range(0.0, std::f64::consts::TAU);
        let pitch = rng.range(-0.3, 0.3);
        scene.add(
            &format!("rod_{index}"),
            Shape::cylinder(
                [x, y, camera_height_m * rng.range(0.02, 0.45)],
                [yaw.cos() * pitch.cos(), yaw.sin() * pitch.cos(), pitch.sin()],
                rng.range(0.001, 0.005),
                camera_height_m * rng.range(0.1, 0.4),
            ),
            material,
        );
    }
    scene.ambient = [rng.range(0.1, 0.3); 3];
    scene.add_lights(&mut rng);
    scene
}

/// `slanted`: one matte plane of natural texture (fractal noise of 1–3 cm scale) tilted 5–35° about a random horizontal axis, its
/// lowest point in the 60° 16:9 view on the table plane (z = 0) and its highest at
/// [`Scene::surface_top_m`]. No room, no other object: every pixel sees the plane, and its
/// disparity is exactly linear in the image.
fn slanted_scene(seed: u64) -> Scene {
    let mut rng = SplitMix64::new(seed ^ 0x736c_616e);
    let camera_height_m = camera_height(&mut rng, 0.5, 0.93);
    let mut scene = Scene::empty(SceneKind::Slanted, seed, camera_height_m);
    // A dark and a light colour: texture everywhere. The noise repeats every 8 scales, at least
    // 8 cm: wider than the searched range, so the repetition cannot fake a match.
    let dark = [rng.range(0.05, 0.35), rng.range(0.05, 0.35), rng.range(0.05, 0.35)];
    let light = [rng.range(0.55, 0.95), rng.range(0.55, 0.95), rng.range(0.55, 0.95)];
    let surface = scene.add_material(Material::matte(
        "slanted_surface",
        Texture::Noise {
            a: dark,
            b: light,
            scale_m: rng.range(0.01, 0.03),
            anisotropy: 1.0,
            seed: rng.next_u64(),
        },
    ));
    let (tilt, axis) = (
        rng.range(5.0f64, 35.0).to_radians(),
        rng.range(0.0, std::f64::consts::TAU),
    );
    // The plane rises along `up` (horizontal unit vector) by tan(tilt) per metre.
    let up = [axis.cos(), axis.sin()];
    let normal = [-tilt.sin() * up[0], -tilt.sin() * up[1], tilt.cos()];
    // Half the view's footprint on the table (m), with room for the rig's other views.
    let (half_x, half_y) = (0.62 * camera_height_m, 0.36 * camera_height_m);
    let rise = tilt.tan() * (up[0].abs() * half_x + up[1].abs() * half_y);
    let c = WORK_AREA_CENTER_M;
    scene.add(
        "slanted_plane",
        Shape::Plane {
            point: [c[0], c[1], rise],
            normal,
        },
        surface,
    );
    scene.surface_top_m = 2.0 * rise;
    scene.ambient = [rng.range(0.15, 0.3); 3];
    scene.add_lights(&mut rng);
    scene
}

/// The start of a thin-part family's scene (`thin`, `fence`, `lamps`): its generator seeded with
/// `salted_seed`, the camera 0.55–0.93 m up, a far floor (plain in `plain`'s colours a third of
/// the time), the table and the room.
fn far_floor_scene(kind: SceneKind, salted_seed: u64, seed: u64, plain: [Rgb; 2]) -> (Scene, SplitMix64) {
    let mut rng = SplitMix64::new(salted_seed);
    let camera_height_m = camera_height(&mut rng, 0.55, 0.93);
    let mut scene = Scene::empty(kind, seed, camera_height_m);
    let floor = far_floor(&mut rng, plain[0], plain[1]);
    let floor = scene.add_material(floor);
    table(&mut scene, floor);
    scene.add_room();
    (scene, rng)
}

/// A thin cylinder from `ends.0` to `ends.1`, its radius drawn by `radius_at(rng, z)` at its
/// middle's height; answers the radius.
fn add_segment(
    scene: &mut Scene,
    rng: &mut SplitMix64,
    name: &str,
    (a, b): ([f64; 3], [f64; 3]),
    material: usize,
    radius_at: &dyn Fn(&mut SplitMix64, f64) -> f64,
) -> f64 {
    let mid = [(a[0] + b[0]) / 2.0, (a[1] + b[1]) / 2.0, (a[2] + b[2]) / 2.0];
    let along = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    let half = 0.5 * (along[0] * along[0] + along[1] * along[1] + along[2] * along[2]).sqrt();
    let radius = radius_at(rng, mid[2]);
    scene.add(name, Shape::cylinder(mid, along, radius, half), material);
    radius
}

/// `thin`: what coarse levels and small crops lose. A far floor (plain in a third of the scenes),
/// and between it and the camera: rods and wires at any angle, two or three lamp arms (a post
/// and two jointed segments), a row of parallel slats, a handful of leaves (thin tilted plates)
/// and one matte board near the camera, whose occluded strip on the floor is 20–40 px wide at
/// 640 px. Each thin part's width is drawn as 1–6 px at its depth in a 640-px-wide 60° view
/// (0.7–4 px at 448, 3–18 px at 1920): `diameter = depth × U(1.8, 11) / 1000`. Never used for
/// training.
fn thin_scene(seed: u64) -> Scene {
    let (mut scene, mut rng) = far_floor_scene(
        SceneKind::Thin,
        seed ^ 0x7468_696e,
        seed,
        [[0.45, 0.46, 0.44], [0.52, 0.52, 0.5]],
    );
    let h = scene.camera_height_m;
    let c = WORK_AREA_CENTER_M;
    // A thin part's radius (m) at height `z` above the floor: 1–6 px wide at 640 px.
    let radius_at = |rng: &mut SplitMix64, z: f64| 0.5 * (h - z) * rng.range(0.0018, 0.011);
    // A place at height `z` within the middle of the 16:9 60° view (the camera looks down at
    // the work-area centre with its x along the world's x).
    let place = |rng: &mut SplitMix64, z: f64| {
        let depth = h - z;
        (
            c[0] + rng.range(-0.3, 0.3) * depth,
            c[1] + rng.range(-0.17, 0.17) * depth,
        )
    };
    let rods = rng.range_usize(4, 10);
    let thin_rods = ThinParts {
        count: rods,
        heights: (0.2, 0.65),
        place: &place,
        size_at: &radius_at,
    };
    add_rods(&mut scene, &mut rng, &thin_rods, (0.15, 0.45));
    let lamps = rng.range_usize(2, 4);
    for index in 0..lamps {
        let material = random_material(&mut rng, &format!("lamp_material_{index}"), 0);
        let material = scene.add_material(material);
        // A post from the floor, then two segments each turning at a joint.
        let post = h * rng.range(0.25, 0.5);
        let (x, y) = place(&mut rng, 0.0);
        let mut joint = [x, y, post];
        let radius = radius_at(&mut rng, post);
        scene.add(
            &format!("lamp_{index}_post"),
            Shape::cylinder([x, y, post / 2.0], [0.0, 0.0, 1.0], radius, post / 2.0),
            material,
        );
        for segment in 0..2 {
            let (yaw, rise) = (rng.range(0.0, std::f64::consts::TAU), rng.range(-0.3, 0.6));
            let length = h * rng.range(0.12, 0.25);
            let axis = [yaw.cos() * rise.cos(), yaw.sin() * rise.cos(), rise.sin()];
            let end = [
                joint[0] + axis[0] * length,
                joint[1] + axis[1] * length,
                (joint[2] + axis[2] * length).clamp(0.05 * h, 0.75 * h),
            ];
            let arm = (joint, end);
            let radius = add_segment(
                &mut scene,
                &mut rng,
                &format!("lamp_{index}_arm_{segment}"),
                arm,
                material,
                &radius_at,
            );
            scene.add(
                &format!("lamp_{index}_joint_{segment}"),
                Shape::sphere(joint, 1.5 * radius),
                material,
            );
            joint = end;
        }
    }
    // Slats: a row of parallel thin bars at one height, a gap of a few widths between them.
    let material = random_material(&mut rng, "slat_material", 5);
    let material = scene.add_material(material);
    let z = h * rng.range(0.3, 0.6);
    let (x, y) = place(&mut rng, z);
    let (yaw, width) = (rng.range(0.0, 180.0), 2.0 * radius_at(&mut rng, z));
    let (gap, length) = (width * rng.range(2.0, 6.0), h * rng.range(0.1, 0.25));
    for index in 0..rng.range_usize(5, 12) {
        let offset = index as f64 * (width + gap);
        let (dx, dy) = (offset * (yaw.to_radians()).cos(), offset * (yaw.to_radians()).sin());
        scene.add(
            &format!("slat_{index}"),
            Shape::Box {
                center: [x + dx, y + dy, z],
                half_extents_m: [width / 2.0, length, width / 2.0],
                yaw_deg: yaw,
                tilt_deg: 0.0,
            },
            material,
        );
    }
    // Leaves: thin plates a few pixels across, tilted, floating.
    let leaf_size = |rng: &mut SplitMix64, z: f64| 4.0 * radius_at(rng, z);
    let leaves = ThinParts {
        count: rng.range_usize(4, 10),
        heights: (0.15, 0.65),
        place: &place,
        size_at: &leaf_size,
    };
    add_leaves(&mut scene, &mut rng, &leaves, 0.5, 90.0);
    // One board near the camera, matte and textured: the floor strip it hides from one side is
    // its disparity jump wide (20–40 px at 640 px).
    let texture = random_texture(&mut rng, 10);
    let material = scene.add_material(Material::matte("board_material", texture));
    let z = h * rng.range(0.45, 0.6);
    let (x, y) = place(&mut rng, z);
    scene.add(
        "board",
        Shape::Box {
            center: [x, y, z],
            half_extents_m: [0.02 * h, 0.12 * h, 0.005 * h],
            yaw_deg: rng.range(0.0, 90.0),
            tilt_deg: 0.0,
        },
        material,
    );
    scene.ambient = [rng.range(0.1, 0.3); 3];
    scene.add_lights(&mut rng);
    scene
}

/// How many thin parts of one kind [`add_rods`] and [`add_leaves`] place, and where: each at a
/// height drawn as a share of the camera's (`heights`), `place(rng, z)` its centre, `size_at(rng,
/// z)` a rod's radius or a leaf's half length (m).
struct ThinParts<'a> {
    count: usize,
    heights: (f64, f64),
    place: &'a dyn Fn(&mut SplitMix64, f64) -> (f64, f64),
    size_at: &'a dyn Fn(&mut SplitMix64, f64) -> f64,
}

/// Rods and wires at any angle (pitch within ±0.5 rad), each of a random material, their half
/// lengths a share of the camera's height drawn from `half_lengths`.
fn add_rods(scene: &mut Scene, rng: &mut SplitMix64, parts: &ThinParts<'_>, half_lengths: (f64, f64)) {
    let h = scene.camera_height_m;
    for index in 0..parts.count {
        let material = random_material(rng, &format!("rod_material_{index}"), 5);
        let material = scene.add_material(material);
        let z = h * rng.range(parts.heights.0, parts.heights.1);
        let (x, y) = (parts.place)(rng, z);
        let (yaw, pitch) = (rng.range(0.0, std::f64::consts::TAU), rng.range(-0.5, 0.5));
        let radius = (parts.size_at)(rng, z);
        scene.add(
            &format!("rod_{index}"),
            Shape::cylinder(
                [x, y, z],
                [yaw.cos() * pitch.cos(), yaw.sin() * pitch.cos(), pitch.sin()],
                radius,
                h * rng.range(half_lengths.0, half_lengths.1),
            ),
            material,
        );
    }
}

/// Leaves: thin plates (`aspect` as wide as long, a tenth as thick) turned up to `max_yaw_deg`
/// and tilted up to ±50°, floating.
fn add_leaves(scene: &mut Scene, rng: &mut SplitMix64, parts: &ThinParts<'_>, aspect: f64, max_yaw_deg: f64) {
    for index in 0..parts.count {
        let material = random_material(rng, &format!("leaf_material_{index}"), 10);
        let material = scene.add_material(material);
        let z = scene.camera_height_m * rng.range(parts.heights.0, parts.heights.1);
        let (x, y) = (parts.place)(rng, z);
        let size = (parts.size_at)(rng, z);
        scene.add(
            &format!("leaf_{index}"),
            Shape::Box {
                center: [x, y, z],
                half_extents_m: [size, aspect * size, 0.1 * size],
                yaw_deg: rng.range(0.0, max_yaw_deg),
                tilt_deg: rng.range(-50.0, 50.0),
            },
            material,
        );
    }
}

/// `fence`: what training needs to learn thin parts, drawn apart from the held-out `thin`
/// family. A far floor (plain in a third of the scenes), and between it and the camera two to
/// four grilles (rows of 4–14 parallel bars, each 1–6 px wide at 640 px, gaps of one to five
/// widths; a third of them crossed by a second row: a lattice), rods and wires at any angle,
/// leaves, and one to three stacks whose occluded strips on the floor are tens of pixels wide.
fn fence_scene(seed: u64) -> Scene {
    let (mut scene, mut rng) = far_floor_scene(
        SceneKind::Fence,
        seed ^ 0x6665_6e63,
        seed,
        [[0.44, 0.45, 0.47], [0.53, 0.52, 0.5]],
    );
    let h = scene.camera_height_m;
    let c = WORK_AREA_CENTER_M;
    // A bar's width (m) at height `z` above the floor: 1–6 px at 640 px.
    let width_at = |rng: &mut SplitMix64, z: f64| (h - z) * rng.range(0.0018, 0.011);
    // A place at height `z` within the 16:9 60° view.
    let place = |rng: &mut SplitMix64, z: f64| {
        let depth = h - z;
        (
            c[0] + rng.range(-0.32, 0.32) * depth,
            c[1] + rng.range(-0.18, 0.18) * depth,
        )
    };
    for grille in 0..rng.range_usize(2, 5) {
        let material = random_material(&mut rng, &format!("grille_{grille}_material"), 5);
        let material = scene.add_material(material);
        let z = h * rng.range(0.2, 0.65);
        let (x, y) = place(&mut rng, z);
        let width = width_at(&mut rng, z);
        let gap = width * rng.range(1.0, 5.0);
        let length = h * rng.range(0.06, 0.2);
        let bars = rng.range_usize(4, 15);
        let crossed = rng.below(3) == 0;
        let yaw = rng.range(0.0, 180.0);
        let layers = 1 + usize::from(crossed);
        for (layer, yaw) in [(0, yaw), (1, yaw + 90.0)].into_iter().take(layers) {
            // The crossing row lies on the first: one bar width higher.
            let z = z + layer as f64 * width;
            let (cos, sin) = (yaw.to_radians().cos(), yaw.to_radians().sin());
            for index in 0..bars {
                let offset = (index as f64 - bars as f64 / 2.0) * (width + gap);
                scene.add(
                    &format!("grille_{grille}_{layer}_bar_{index}"),
                    Shape::Box {
                        center: [x + offset * cos, y + offset * sin, z],
                        half_extents_m: [width / 2.0, length, width / 2.0],
                        yaw_deg: yaw,
                        tilt_deg: 0.0,
                    },
                    material,
                );
            }
        }
    }
    let rod_radius = |rng: &mut SplitMix64, z: f64| 0.5 * width_at(rng, z);
    let rods = ThinParts {
        count: rng.range_usize(3, 9),
        heights: (0.15, 0.65),
        place: &place,
        size_at: &rod_radius,
    };
    add_rods(&mut scene, &mut rng, &rods, (0.1, 0.4));
    let leaf_size = |rng: &mut SplitMix64, z: f64| 2.0 * width_at(rng, z);
    let leaves = ThinParts {
        count: rng.range_usize(2, 8),
        heights: (0.15, 0.65),
        place: &place,
        size_at: &leaf_size,
    };
    add_leaves(&mut scene, &mut rng, &leaves, 0.6, 180.0);
    for index in 0..rng.range_usize(1, 4) {
        let material = random_material(&mut rng, &format!("stack_material_{index}"), 10);
        let material = scene.add_material(material);
        let height = h * rng.range(0.2, 0.55);
        let (x, y) = place(&mut rng, 0.0);
        let width = h * rng.range(0.03, 0.1);
        scene.add(
            &format!("stack_{index}"),
            Shape::upright_box(
                [x, y, height / 2.0],
                [width, width * rng.range(0.5, 2.0), height / 2.0],
                rng.range(0.0, 90.0),
            ),
            material,
        );
    }
    scene.ambient = [rng.range(0.1, 0.3); 3];
    scene.add_lights(&mut rng);
    scene
}

/// `lamps`: what training needs to keep lamp arms, tripods and the floor beside near boards
/// (see [`SceneKind::Lamps`]). Each thin part is 1–6 px wide at its depth in a 640-px-wide 60°
/// view, as in `thin` and `fence`.
fn lamps_scene(seed: u64) -> Scene {
    let (mut scene, mut rng) = far_floor_scene(
        SceneKind::Lamps,
        seed ^ 0x6c61_6d70,
        seed,
        [[0.47, 0.45, 0.43], [0.5, 0.52, 0.53]],
    );
    let h = scene.camera_height_m;
    let c = WORK_AREA_CENTER_M;
    // A thin part's radius (m) at height `z` above the floor: 1–6 px wide at 640 px.
    let radius_at = |rng: &mut SplitMix64, z: f64| 0.5 * (h - z) * rng.range(0.0018, 0.011);
    let place = |rng: &mut SplitMix64, z: f64| {
        let depth = h - z;
        (
            c[0] + rng.range(-0.32, 0.32) * depth,
            c[1] + rng.range(-0.18, 0.18) * depth,
        )
    };
    let segment = |scene: &mut Scene, rng: &mut SplitMix64, name: &str, a: [f64; 3], b: [f64; 3], material: usize| {
        add_segment(scene, rng, name, (a, b), material, &radius_at)
    };
    for index in 0..rng.range_usize(2, 5) {
        let material = random_material(&mut rng, &format!("lamp_{index}_material"), 5);
        let material = scene.add_material(material);
        let (x, y) = place(&mut rng, 0.0);
        let top = h * rng.range(0.2, 0.55);
        let mut joint = [x, y, top];
        segment(
            &mut scene,
            &mut rng,
            &format!("lamp_{index}_post"),
            [x, y, 0.0],
            joint,
            material,
        );
        for arm in 0..rng.range_usize(2, 5) {
            let (yaw, rise) = (rng.range(0.0, std::f64::consts::TAU), rng.range(-0.6, 0.7));
            let length = h * rng.range(0.08, 0.22);
            let end = [
                joint[0] + yaw.cos() * rise.cos() * length,
                joint[1] + yaw.sin() * rise.cos() * length,
                (joint[2] + rise.sin() * length).clamp(0.05 * h, 0.72 * h),
            ];
            let radius = segment(
                &mut scene,
                &mut rng,
                &format!("lamp_{index}_arm_{arm}"),
                joint,
                end,
                material,
            );
            scene.add(
                &format!("lamp_{index}_joint_{arm}"),
                Shape::sphere(joint, rng.range(1.2, 2.0) * radius),
                material,
            );
            joint = end;
        }
        // The shade: a small sphere or box at the last joint, a few times the arm's width.
        let size = 2.0 * radius_at(&mut rng, joint[2]) * rng.range(2.0, 5.0);
        let shade = if rng.below(2) == 0 {
            Shape::sphere(joint, size)
        } else {
            Shape::Box {
                center: joint,
                half_extents_m: [size, 0.6 * size, 0.8 * size],
                yaw_deg: rng.range(0.0, 180.0),
                tilt_deg: rng.range(-40.0, 40.0),
            }
        };
        scene.add(&format!("lamp_{index}_shade"), shade, material);
    }
    for index in 0..rng.range_usize(1, 3) {
        let material = random_material(&mut rng, &format!("tripod_{index}_material"), 5);
        let material = scene.add_material(material);
        let head_z = h * rng.range(0.25, 0.6);
        let (x, y) = place(&mut rng, head_z);
        let head = [x, y, head_z];
        let spread = head_z * rng.range(0.25, 0.6);
        let turn = rng.range(0.0, std::f64::consts::TAU);
        for leg in 0..3 {
            let angle = turn + leg as f64 * std::f64::consts::TAU / 3.0 + rng.range(-0.3, 0.3);
            let foot = [x + spread * angle.cos(), y + spread * angle.sin(), 0.0];
            segment(
                &mut scene,
                &mut rng,
                &format!("tripod_{index}_leg_{leg}"),
                head,
                foot,
                material,
            );
        }
        let size = 2.0 * radius_at(&mut rng, head_z) * rng.range(2.0, 4.0);
        scene.add(
            &format!("tripod_{index}_head"),
            Shape::Box {
                center: [x, y, head_z + size],
                half_extents_m: [size, size, size],
                yaw_deg: rng.range(0.0, 90.0),
                tilt_deg: 0.0,
            },
            material,
        );
    }
    // Cables: three to six short straight pieces sagging between two high points.
    for index in 0..rng.range_usize(1, 4) {
        let material = random_material(&mut rng, &format!("cable_{index}_material"), 3);
        let material = scene.add_material(material);
        let z = h * rng.range(0.3, 0.65);
        let (x, y) = place(&mut rng, z);
        let yaw = rng.range(0.0, std::f64::consts::TAU);
        let (length, sag) = (h * rng.range(0.2, 0.5), h * rng.range(0.02, 0.15));
        let pieces = rng.range_usize(3, 7);
        let point = |t: f64| {
            [
                x + (t - 0.5) * length * yaw.cos(),
                y + (t - 0.5) * length * yaw.sin(),
                z - sag * 4.0 * t * (1.0 - t),
            ]
        };
        for piece in 0..pieces {
            let (a, b) = (
                point(piece as f64 / pieces as f64),
                point((piece + 1) as f64 / pieces as f64),
            );
            segment(&mut scene, &mut rng, &format!("cable_{index}_{piece}"), a, b, material);
        }
    }
    // One or two matte slabs near the camera: the floor strip each hides from one side is its
    // disparity jump wide (20–50 px at 640 px).
    for index in 0..rng.range_usize(1, 3) {
        let texture = random_texture(&mut rng, 10);
        let material = scene.add_material(Material::matte(&format!("slab_{index}_material"), texture));
        let z = h * rng.range(0.45, 0.65);
        let (x, y) = place(&mut rng, z);
        scene.add(
            &format!("slab_{index}"),
            Shape::Box {
                center: [x, y, z],
                half_extents_m: [h * rng.range(0.01, 0.03), h * rng.range(0.05, 0.12), 0.005 * h],
                yaw_deg: rng.range(0.0, 180.0),
                tilt_deg: rng.range(-15.0, 15.0),
            },
            material,
        );
    }
    scene.ambient = [rng.range(0.1, 0.3); 3];
    scene.add_lights(&mut rng);
    scene
}

/// `bin`: bin picking. A plastic tote (floor and four walls 12–25 cm high) on a table, 10–30
/// parts heaped in it (boxes, cylinders, balls; some of metal), the camera 0.5–0.9 m above the
/// table: the walls hide much of the floor from one view or another. Never used for training.
fn bin_scene(seed: u64) -> Scene {
    let mut rng = SplitMix64::new(seed ^ 0x0062_696e);
    let camera_height_m = camera_height(&mut rng, 0.5, 0.9);
    let mut scene = Scene::empty(SceneKind::Bin, seed, camera_height_m);
    let concrete = scene.add_material(Material::matte(
        "concrete",
        Texture::Noise {
            a: [0.4, 0.4, 0.38],
            b: [0.62, 0.6, 0.57],
            scale_m: 0.03,
            anisotropy: 1.0,
            seed: rng.next_u64(),
        },
    ));
    table(&mut scene, concrete);
    scene.add_room();
    let tote_colour = [
        [0.15, 0.3, 0.65],
        [0.75, 0.2, 0.12],
        [0.2, 0.2, 0.22],
        [0.85, 0.65, 0.1],
    ][rng.below(4) as usize];
    let tote = scene.add_material(Material::glossy("tote_plastic", Texture::Solid { rgb: tote_colour }));
    let c = WORK_AREA_CENTER_M;
    let (half_x, half_y) = (
        camera_height_m * rng.range(0.22, 0.32),
        camera_height_m * rng.range(0.16, 0.24),
    );
    let wall_height = rng.range(0.12, 0.25);
    let thickness = 0.008;
    scene.add(
        "tote_floor",
        Shape::upright_box([c[0], c[1], thickness / 2.0], [half_x, half_y, thickness / 2.0], 0.0),
        tote,
    );
    for (name, center, half) in [
        ("tote_wall_near", [c[0] - half_x, c[1]], [thickness, half_y]),
        ("tote_wall_far", [c[0] + half_x, c[1]], [thickness, half_y]),
        ("tote_wall_left", [c[0], c[1] - half_y], [half_x, thickness]),
        ("tote_wall_right", [c[0], c[1] + half_y], [half_x, thickness]),
    ] {
        scene.add(
            name,
            Shape::upright_box(
                [center[0], center[1], wall_height / 2.0],
                [half[0], half[1], wall_height / 2.0],
                0.0,
            ),
            tote,
        );
    }
    let parts = rng.range_usize(10, 30);
    for index in 0..parts {
        let material = random_material(&mut rng, &format!("part_material_{index}"), 5);
        let material = scene.add_material(material);
        let x = c[0] + rng.range(-0.85, 0.85) * half_x;
        let y = c[1] + rng.range(-0.85, 0.85) * half_y;
        let size = rng.range(0.012, 0.045);
        // Heaped: later parts lie higher.
        let z = thickness + size + rng.range(0.0, 0.6) * wall_height * index as f64 / parts as f64;
        let shape = match rng.below(3) {
            0 => Shape::Box {
                center: [x, y, z],
                half_extents_m: [size * rng.range(0.5, 2.0), size * rng.range(0.5, 1.5), size],
                yaw_deg: rng.range(0.0, 90.0),
                tilt_deg: rng.range(-25.0, 25.0),
            },
            1 => {
                let yaw = rng.range(0.0, std::f64::consts::TAU);
                Shape::cylinder(
                    [x, y, z],
                    [yaw.cos(), yaw.sin(), rng.range(-0.3, 0.3)],
                    size * rng.range(0.3, 0.7),
                    size * rng.range(1.0, 2.5),
                )
            }
            _ => Shape::sphere([x, y, z], size),
        };
        scene.add(&format!("part_{index}"), shape, material);
    }
    scene.ambient = [rng.range(0.12, 0.25); 3];
    scene.add_lights(&mut rng);
    scene
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn camera_heights_stay_uniform_within_reach_and_keep_reachable_draws() {
        let mut rng = SplitMix64::new(1);
        let heights: Vec<f64> = (0..20_000).map(|_| camera_height(&mut rng, 0.5, 1.2)).collect();
        assert!(heights.iter().all(|h| (0.5..=MAX_CAMERA_HEIGHT_M).contains(h)));
        // Uniform over 0.5 … MAX: each tenth of the range holds a tenth of the draws.
        let tenth_m = (MAX_CAMERA_HEIGHT_M - 0.5) / 10.0;
        for tenth in 0..10 {
            let lo = 0.5 + tenth_m * f64::from(tenth);
            let share = heights.iter().filter(|h| (lo..lo + tenth_m).contains(*h)).count() as f64 / 20_000.0;
            assert!((share - 0.1).abs() < 0.01, "{lo:.2}: {share}");
        }
        // A reachable draw is the draw itself.
        let (mut a, mut b) = (SplitMix64::new(7), SplitMix64::new(7));
        for _ in 0..100 {
            let (h, drawn) = (camera_height(&mut a, 0.4, 1.1), b.range(0.4, 1.1));
            if drawn <= MAX_CAMERA_HEIGHT_M {
                assert_eq!(h, drawn);
            }
        }
    }

    #[test]
    fn random_scenes_vary_with_the_seed() {
        let a = Scene::build(SceneKind::Random, 1);
        let b = Scene::build(SceneKind::Random, 2);
        assert_ne!(a, b);
        assert_eq!(a, Scene::build(SceneKind::Random, 1));
        let heights: Vec<f64> = (0..20)
            .map(|s| Scene::build(SceneKind::Random, s).camera_height_m)
            .collect();
        let (min, max) = heights
            .iter()
            .fold((f64::MAX, f64::MIN), |(lo, hi), h| (lo.min(*h), hi.max(*h)));
        assert!(
            max - min > 0.3,
            "camera heights {min}..{max} do not vary the depth range"
        );
        let counts: Vec<usize> = (0..20)
            .map(|s| Scene::build(SceneKind::Random, s).objects.len())
            .collect();
        assert!(counts.iter().max() > counts.iter().min());
    }

    #[test]
    fn clutter_scenes_reach_half_way_to_the_camera_and_bins_have_four_walls() {
        for seed in 0..10 {
            let clutter = Scene::build(SceneKind::Clutter, seed);
            let ratio = clutter.highest_point_m() / clutter.camera_height_m;
            assert!(
                (0.1..=0.7).contains(&ratio),
                "seed {seed}: stacks reach {ratio:.2} of the way"
            );
            assert!(clutter.objects.iter().any(|o| o.name.starts_with("rod_")));
            let bin = Scene::build(SceneKind::Bin, seed);
            let walls = bin.objects.iter().filter(|o| o.name.starts_with("tote_wall")).count();
            assert_eq!(walls, 4, "seed {seed}");
            assert!(bin.objects.iter().filter(|o| o.name.starts_with("part_")).count() >= 10);
        }
        assert_ne!(Scene::build(SceneKind::Bin, 1), Scene::build(SceneKind::Bin, 2));
    }

    #[test]
    fn thin_scenes_hold_parts_one_to_six_pixels_wide_far_above_their_floor() {
        // fx of a 640-px-wide 60° view.
        let fx = 320.0 / 30f64.to_radians().tan();
        for seed in 0..10 {
            let scene = Scene::build(SceneKind::Thin, seed);
            let h = scene.camera_height_m;
            let mut thin = 0;
            for o in &scene.objects {
                let Shape::Cylinder { center, radius_m, .. } = &o.shape else {
                    continue;
                };
                if o.name.starts_with("rod_") || o.name.contains("_arm_") {
                    let width_px = fx * 2.0 * radius_m / (h - center[2]);
                    assert!(
                        (0.9..=6.1).contains(&width_px),
                        "seed {seed} {}: {width_px:.2} px",
                        o.name
                    );
                    thin += 1;
                }
            }
            assert!(thin >= 8, "seed {seed}: {thin} thin parts");
            for prefix in ["slat_", "leaf_", "board", "lamp_"] {
                assert!(
                    scene.objects.iter().any(|o| o.name.starts_with(prefix)),
                    "seed {seed}: no {prefix}"
                );
            }
        }
        assert_ne!(Scene::build(SceneKind::Thin, 1), Scene::build(SceneKind::Thin, 2));
    }

    #[test]
    fn fence_scenes_hold_grilles_of_bars_one_to_six_pixels_wide_far_above_their_floor() {
        // fx of a 640-px-wide 60° view.
        let fx = 320.0 / 30f64.to_radians().tan();
        for seed in 0..10 {
            let scene = Scene::build(SceneKind::Fence, seed);
            let h = scene.camera_height_m;
            let mut bars = 0;
            for o in &scene.objects {
                let Shape::Box {
                    center, half_extents_m, ..
                } = &o.shape
                else {
                    continue;
                };
                if o.name.contains("_bar_") {
                    let width_px = fx * 2.0 * half_extents_m[0] / (h - center[2]);
                    assert!(
                        (0.9..=6.2).contains(&width_px),
                        "seed {seed} {}: {width_px:.2} px",
                        o.name
                    );
                    // Clear of the floor: 3–37 px of disparity above it at a 20 mm baseline.
                    let jump_px = fx * 0.02 * (1.0 / (h - center[2]) - 1.0 / h);
                    assert!(
                        (2.5..=40.0).contains(&jump_px),
                        "seed {seed} {}: {jump_px:.1} px",
                        o.name
                    );
                    bars += 1;
                }
            }
            assert!(bars >= 8, "seed {seed}: {bars} bars");
            for prefix in ["rod_", "leaf_", "stack_"] {
                assert!(
                    scene.objects.iter().any(|o| o.name.starts_with(prefix)),
                    "seed {seed}: no {prefix}"
                );
            }
        }
        assert_ne!(Scene::build(SceneKind::Fence, 1), Scene::build(SceneKind::Fence, 2));
    }

    #[test]
    fn lamps_scenes_hold_arms_legs_and_cables_one_to_six_pixels_wide_and_near_slabs() {
        // fx of a 640-px-wide 60° view.
        let fx = 320.0 / 30f64.to_radians().tan();
        for seed in 0..10 {
            let scene = Scene::build(SceneKind::Lamps, seed);
            let h = scene.camera_height_m;
            let mut thin = 0;
            for o in &scene.objects {
                let Shape::Cylinder { center, radius_m, .. } = &o.shape else {
                    continue;
                };
                let width_px = fx * 2.0 * radius_m / (h - center[2]);
                assert!(
                    (0.9..=6.1).contains(&width_px),
                    "seed {seed} {}: {width_px:.2} px",
                    o.name
                );
                thin += 1;
            }
            assert!(thin >= 8, "seed {seed}: {thin} thin parts");
            for prefix in ["lamp_", "tripod_", "cable_", "slab_"] {
                assert!(
                    scene.objects.iter().any(|o| o.name.starts_with(prefix)),
                    "seed {seed}: no {prefix}"
                );
            }
            assert!(
                !scene
                    .objects
                    .iter()
                    .any(|o| o.name.starts_with("slat_") || o.name.starts_with("leaf_"))
            );
        }
        assert_ne!(Scene::build(SceneKind::Lamps, 1), Scene::build(SceneKind::Lamps, 2));
    }

    #[test]
    fn workpiece_has_mirror_metal() {
        let scene = Scene::build(SceneKind::Workpiece, 0);
        assert!(
            scene
                .materials
                .iter()
                .any(|m| m.surface_class() == SurfaceClass::Mirror)
        );
    }
}
