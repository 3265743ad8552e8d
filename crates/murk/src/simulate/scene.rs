//! Seeded synthetic scenes for the simulators: a dark far wall plus a few Lambertian objects, and
//! the ray–primitive intersection the renderers need. Lengths are metres, camera frame (+z forward,
//! +x right, +y down).

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use nalgebra::Vector3;

use crate::camera::Intrinsics;

/// A point or direction of the simulators' scenes (metres for ToF, scene units for MVS); it
/// serialises as `[x, y, z]`.
pub(crate) type V3 = Vector3<f64>;

/// Geometry of one object.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Shape {
    /// Sphere with `centre` and `radius` (m).
    Sphere {
        /// Centre, m.
        centre: V3,
        /// Radius, m.
        radius: f64,
    },
    /// Axis-aligned box (camera frame) with corners `min` and `max` (m). Thin tall boxes model
    /// chair legs and poles.
    Box {
        /// Minimum corner, m.
        min: V3,
        /// Maximum corner, m.
        max: V3,
    },
    /// Box turned about the camera's vertical (y) axis: `half` are its half extents in its own
    /// frame (m), and `yaw_rad` turns its local +z (its thin side, for a panel) from the camera's
    /// +z towards +x. A panel at a yaw near ±90° is seen nearly edge-on: a narrow strip whose
    /// depth changes along it, lit at a grazing angle.
    TurnedBox {
        /// Centre, m.
        centre: V3,
        /// Half extents along the box's own x, y and z, m.
        half: V3,
        /// Rotation about the vertical axis, radians.
        yaw_rad: f64,
    },
}

/// A Lambertian object.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SceneObject {
    /// Geometry.
    pub shape: Shape,
    /// Diffuse albedo in [0, 1].
    pub albedo: f64,
}

/// How [`Scene::generate_layout`] places objects.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SceneLayout {
    /// 2–4 objects apart from each other, background visible around them, ≤ 35 % coverage
    /// ([`Scene::generate`]): the scene class the reference's method is meant for.
    #[default]
    Separated,
    /// A large bright sphere near the camera (front at 0.75–1.05 m) partly occluding a wide
    /// panel behind it, plus 1–2 further objects ([`Scene::generate_cluttered`]): the scenes on
    /// which the reference's saturated-scatter model breaks.
    Cluttered,
    /// The obstacles a robot must not lose ([`Scene::generate_obstacles`]): a near box or sphere,
    /// a thin panel seen nearly edge-on beside or partly behind it, so that the two touch in the
    /// image, a thin pole, and up to one further object.
    Obstacles,
}

impl std::fmt::Display for SceneLayout {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            SceneLayout::Separated => "separated",
            SceneLayout::Cluttered => "cluttered",
            SceneLayout::Obstacles => "obstacles",
        })
    }
}

impl std::str::FromStr for SceneLayout {
    type Err = crate::error::MurkError;
    fn from_str(s: &str) -> crate::error::Result<Self> {
        match s.trim().to_ascii_lowercase().as_str() {
            "separated" => Ok(SceneLayout::Separated),
            "cluttered" => Ok(SceneLayout::Cluttered),
            "obstacles" => Ok(SceneLayout::Obstacles),
            other => Err(crate::error::MurkError::invalid(
                "layout",
                format!(
                    "unknown scene layout {other:?}; expected separated, cluttered or obstacles"
                ),
            )),
        }
    }
}

/// A scene: a fronto-parallel wall at `wall_z_m` with albedo `wall_albedo` behind `objects`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Scene {
    /// Depth (z) of the background wall, m.
    pub wall_z_m: f64,
    /// Albedo of the background wall.
    pub wall_albedo: f64,
    /// Foreground objects.
    pub objects: Vec<SceneObject>,
}

/// A ray hit: distance along the ray, unit outward normal, albedo, and whether it is an object
/// (as opposed to the wall).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Hit {
    pub t: f64,
    pub normal: V3,
    pub albedo: f64,
    pub is_object: bool,
}

impl Shape {
    /// Nearest intersection with `t` in `(t_min, t_max)` of the ray `o + t·d`, with the outward
    /// normal. `d` need not be unit length for the box; the sphere assumes `|d| = 1`.
    pub(crate) fn intersect(&self, o: V3, d: V3, t_min: f64, t_max: f64) -> Option<(f64, V3)> {
        match *self {
            Shape::Sphere { centre, radius } => {
                let oc = o - centre;
                let b = oc.dot(&d);
                let c = oc.norm_squared() - radius * radius;
                let disc = b * b - c;
                if disc < 0.0 {
                    return None;
                }
                let sq = disc.sqrt();
                for t in [-b - sq, -b + sq] {
                    if t > t_min && t < t_max {
                        let p = o + d * t;
                        return Some((t, (p - centre) * (1.0 / radius)));
                    }
                }
                None
            }
            Shape::Box { min, max } => {
                // Slab method; remember which slab produced the entry/exit to get the normal.
                let mut t0 = f64::NEG_INFINITY;
                let mut t1 = f64::INFINITY;
                let mut axis0 = 0usize;
                let mut sign0 = -1.0;
                let mut axis1 = 0usize;
                let mut sign1 = 1.0;
                for a in 0..3 {
                    if d[a].abs() < 1e-300 {
                        if o[a] < min[a] || o[a] > max[a] {
                            return None;
                        }
                        continue;
                    }
                    let inv = 1.0 / d[a];
                    let (mut ta, mut tb) = ((min[a] - o[a]) * inv, (max[a] - o[a]) * inv);
                    // Entering through the min face means the outward normal points to −axis.
                    let (mut sa, mut sb) = (-1.0, 1.0);
                    if ta > tb {
                        std::mem::swap(&mut ta, &mut tb);
                        std::mem::swap(&mut sa, &mut sb);
                    }
                    if ta > t0 {
                        t0 = ta;
                        axis0 = a;
                        sign0 = sa;
                    }
                    if tb < t1 {
                        t1 = tb;
                        axis1 = a;
                        sign1 = sb;
                    }
                    if t0 > t1 {
                        return None;
                    }
                }
                let mut n = V3::zeros();
                if t0 > t_min && t0 < t_max {
                    n[axis0] = sign0;
                    Some((t0, n))
                } else if t1 > t_min && t1 < t_max {
                    n[axis1] = sign1;
                    Some((t1, n))
                } else {
                    None
                }
            }
            Shape::TurnedBox {
                centre,
                half,
                yaw_rad,
            } => {
                // Intersect in the box's own frame, where it is axis-aligned; a rotation keeps
                // the ray parameter t, and turns the normal back.
                let local = Shape::Box {
                    min: -half,
                    max: half,
                };
                let (t, n) = local.intersect(
                    yaw_to_local(o - centre, yaw_rad),
                    yaw_to_local(d, yaw_rad),
                    t_min,
                    t_max,
                )?;
                Some((t, yaw_to_local(n, -yaw_rad)))
            }
        }
    }

    /// The centre of the shape, m.
    pub fn centre(&self) -> V3 {
        match *self {
            Shape::Sphere { centre, .. } | Shape::TurnedBox { centre, .. } => centre,
            Shape::Box { min, max } => (min + max) * 0.5,
        }
    }

    /// The shape moved by `v` (m).
    pub fn translated(&self, v: V3) -> Shape {
        match *self {
            Shape::Sphere { centre, radius } => Shape::Sphere {
                centre: centre + v,
                radius,
            },
            Shape::Box { min, max } => Shape::Box {
                min: min + v,
                max: max + v,
            },
            Shape::TurnedBox {
                centre,
                half,
                yaw_rad,
            } => Shape::TurnedBox {
                centre: centre + v,
                half,
                yaw_rad,
            },
        }
    }

    /// Centre and radius of a bounding sphere (cheap rejection for shadow rays).
    pub(crate) fn bounding_sphere(&self) -> (V3, f64) {
        match *self {
            Shape::Sphere { centre, radius } => (centre, radius),
            Shape::Box { min, max } => {
                let c = (min + max) * 0.5;
                let h = max - c;
                (c, h.norm())
            }
            Shape::TurnedBox { centre, half, .. } => (centre, half.norm()),
        }
    }
}

/// `v` (camera frame) in the frame of a box turned by `yaw_rad` about the vertical axis; a
/// negative angle maps back.
fn yaw_to_local(v: V3, yaw_rad: f64) -> V3 {
    let (s, c) = yaw_rad.sin_cos();
    V3::new(c * v[0] - s * v[2], v[1], s * v[0] + c * v[2])
}

impl Scene {
    /// Nearest surface along the camera ray `t·d` (`d` unit, from the origin). Rays that miss
    /// the wall (looking sideways or backwards) return `None`.
    pub(crate) fn cast(&self, d: V3) -> Option<Hit> {
        let mut best: Option<Hit> = None;
        if d[2] > 1e-9 {
            best = Some(Hit {
                t: self.wall_z_m / d[2],
                normal: V3::new(0.0, 0.0, -1.0),
                albedo: self.wall_albedo,
                is_object: false,
            });
        }
        for obj in &self.objects {
            let t_max = best.map_or(f64::INFINITY, |h| h.t);
            if let Some((t, normal)) = obj.shape.intersect(V3::zeros(), d, 1e-9, t_max) {
                best = Some(Hit {
                    t,
                    normal,
                    albedo: obj.albedo,
                    is_object: true,
                });
            }
        }
        best
    }

    /// True when an object blocks the open segment from `a` to `b` (the wall is behind
    /// everything and cannot shadow).
    pub(crate) fn occluded(&self, a: V3, b: V3) -> bool {
        let ab = b - a;
        let len = ab.norm();
        if len <= 0.0 {
            return false;
        }
        let d = ab * (1.0 / len);
        // Self-intersection guard: 1 µm is far below any feature size and far above f64 noise.
        let eps = 1e-6;
        self.objects.iter().any(|obj| {
            let (c, r) = obj.shape.bounding_sphere();
            // Distance from the bounding sphere's centre to the segment.
            let ac = c - a;
            let t = ac.dot(&d).clamp(0.0, len);
            let q = ac - d * t;
            if q.norm_squared() > r * r {
                return false;
            }
            obj.shape.intersect(a, d, eps, len - eps).is_some()
        })
    }

    /// A seeded scene: wall at 5–6.5 m (albedo 0.05) and 2–4 objects (spheres, boxes, a thin
    /// vertical bar) with albedo 0.3–0.9 whose centres lie 1–2 m from the camera inside the view.
    ///
    /// Placement is rejection-sampled on a coarse render so that no object spans the image from top
    /// to bottom, objects do not overlap, and together they cover at most 35 % of the image — the
    /// scene class the reference's method is meant for (background visible around objects, §5.4.2).
    pub fn generate(rng: &mut ChaCha8Rng, k: &Intrinsics, width: usize, height: usize) -> Scene {
        let wall_z_m = rng.random_range(5.0..6.5);
        let mut best: Option<(f64, Scene)> = None;
        for _attempt in 0..200 {
            let n = rng.random_range(2..=4usize);
            let mut objects: Vec<SceneObject> = Vec::with_capacity(n);
            add_clear_objects(&mut objects, n, rng, k, width, height);
            let scene = Scene {
                wall_z_m,
                wall_albedo: 0.05,
                objects,
            };
            let (coverage, spans) = scene.coarse_coverage(k, width, height);
            if scene.objects.len() >= 2 && coverage <= 0.35 && !spans {
                return scene;
            }
            // Keep the least-covering acceptable-looking fallback in case every attempt fails
            // (cannot happen with the ranges above, but never loop forever).
            if !spans && best.as_ref().is_none_or(|(c, _)| coverage < *c) {
                best = Some((coverage, scene));
            }
        }
        best.map(|(_, s)| s).unwrap_or(Scene {
            wall_z_m,
            wall_albedo: 0.05,
            objects: Vec::new(),
        })
    }

    /// A seeded scene of the given layout.
    pub fn generate_layout(
        layout: SceneLayout,
        rng: &mut ChaCha8Rng,
        k: &Intrinsics,
        width: usize,
        height: usize,
    ) -> Scene {
        match layout {
            SceneLayout::Separated => Scene::generate(rng, k, width, height),
            SceneLayout::Cluttered => Scene::generate_cluttered(rng, k, width, height),
            SceneLayout::Obstacles => Scene::generate_obstacles(rng, k, width, height),
        }
    }

    /// A seeded cluttered scene: wall at 5–6.5 m; a bright sphere (albedo 0.6–0.9, radius
    /// 0.2–0.3 m, nearest point 0.75–1.05 m from the camera); a wide, thin panel 0.5–1.0 m behind
    /// it, shifted sideways so the sphere hides 20–60 % of it; and 1–2 objects of
    /// [`Scene::generate`]'s kinds elsewhere. Objects may occlude each other and shadow each
    /// other from the light; no object spans the image from top to bottom, and objects cover at
    /// most 55 % of the image.
    pub fn generate_cluttered(
        rng: &mut ChaCha8Rng,
        k: &Intrinsics,
        width: usize,
        height: usize,
    ) -> Scene {
        let wall_z_m = rng.random_range(5.0..6.5);
        let accept = |coverage: f64, hidden: f64| coverage <= 0.55 && (0.2..=0.6).contains(&hidden);
        draw_until(wall_z_m, rng, k, width, height, accept, |rng| {
            let dir = central_ray(rng, k, width, height);
            let radius = rng.random_range(0.2..0.3);
            let front = rng.random_range(0.75..1.05);
            let centre = dir * (front + radius);
            let sphere = SceneObject {
                shape: Shape::Sphere { centre, radius },
                albedo: rng.random_range(0.6..0.9),
            };
            // The panel's centre sits behind the sphere, shifted sideways by 0.6–1.2 sphere
            // radii scaled to the panel's depth, so the sphere covers part of it.
            let panel_z = centre[2] + rng.random_range(0.5..1.0);
            let side = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
            let shift = rng.random_range(0.6..1.2) * radius * panel_z / centre[2];
            let half = V3::new(
                rng.random_range(0.25..0.4),
                rng.random_range(0.15..0.25),
                0.02,
            );
            let c = V3::new(
                centre[0] * panel_z / centre[2] + side * (shift + half[0] * 0.5),
                centre[1] * panel_z / centre[2] + rng.random_range(-0.5..0.5) * radius,
                panel_z,
            );
            let panel = SceneObject {
                shape: Shape::Box {
                    min: c - half,
                    max: c + half,
                },
                albedo: rng.random_range(0.3..0.8),
            };
            let mut objects = vec![sphere, panel];
            let extra = rng.random_range(1..=2usize);
            add_clear_objects(&mut objects, 2 + extra, rng, k, width, height);
            Some(objects)
        })
    }

    /// A seeded scene of thin and touching obstacles: wall at 4–6 m (albedo 0.05) and
    /// - a near box or sphere (albedo 0.4–0.9, nearest point 0.8–1.3 m from the camera);
    /// - a thin panel (1.6–2.4 cm thick, 0.4–0.7 m wide, 0.3–0.6 m tall, albedo 0.3–0.8)
    ///   0.2–0.8 m behind it, turned 70–88° from facing the camera, so that it is seen nearly
    ///   edge-on, lit at a grazing angle, and placed at the near object's outline in the image
    ///   (beside it or partly behind it, at most 70 % hidden);
    /// - a pole 2–4 cm wide and 0.4–0.8 m tall at 1–2 m;
    /// - up to one further object of [`Scene::generate`]'s kinds.
    ///
    /// No object spans the image from top to bottom, and objects cover at most 50 % of it.
    pub fn generate_obstacles(
        rng: &mut ChaCha8Rng,
        k: &Intrinsics,
        width: usize,
        height: usize,
    ) -> Scene {
        let wall_z_m = rng.random_range(4.0..6.0);
        let accept = |coverage: f64, hidden: f64| coverage <= 0.5 && hidden <= 0.7;
        draw_until(wall_z_m, rng, k, width, height, accept, |rng| {
            let dir = central_ray(rng, k, width, height);
            let front = rng.random_range(0.8..1.3);
            let (near, near_half_width) = if rng.random_bool(0.5) {
                let radius = rng.random_range(0.12..0.22);
                let shape = Shape::Sphere {
                    centre: dir * (front + radius),
                    radius,
                };
                (shape, radius)
            } else {
                let half = V3::new(
                    rng.random_range(0.1..0.2),
                    rng.random_range(0.1..0.25),
                    rng.random_range(0.08..0.15),
                );
                let c = dir * (front + half[2]);
                (
                    Shape::Box {
                        min: c - half,
                        max: c + half,
                    },
                    half[0],
                )
            };
            let near_centre = near.centre();
            // The panel's centre: behind the near object, sideways by 0.8–1.3 of its half
            // width scaled to the panel's depth, so its outline meets the near object's.
            let panel_z = near_centre[2] + rng.random_range(0.2..0.8);
            let side = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
            let scale = panel_z / near_centre[2];
            let centre = V3::new(
                (near_centre[0] + side * rng.random_range(0.8..1.3) * near_half_width) * scale,
                (near_centre[1] + rng.random_range(-0.6..0.6) * near_half_width) * scale,
                panel_z,
            );
            let half = V3::new(
                rng.random_range(0.2..0.35),
                rng.random_range(0.15..0.3),
                rng.random_range(0.008..0.012),
            );
            // Turned 70–88° from facing the camera along the ray to its centre.
            let facing = centre[0].atan2(centre[2]);
            let grazing = rng.random_range(70.0f64..88.0).to_radians();
            let turn = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
            let panel = Shape::TurnedBox {
                centre,
                half,
                yaw_rad: facing + turn * grazing,
            };
            let mut objects = vec![
                SceneObject {
                    shape: near,
                    albedo: rng.random_range(0.4..0.9),
                },
                SceneObject {
                    shape: panel,
                    albedo: rng.random_range(0.3..0.8),
                },
            ];
            let pole = (0..20)
                .map(|_| random_pole(rng, k, width, height))
                .find(|pole| clear_of(&objects, &pole.shape))?;
            objects.push(pole);
            let target = objects.len() + rng.random_range(0..=1usize);
            add_clear_objects(&mut objects, target, rng, k, width, height);
            Some(objects)
        })
    }

    /// Share of object `index`'s pixels (from a coarse render) that another object hides.
    fn hidden_share(&self, index: usize, k: &Intrinsics, width: usize, height: usize) -> f64 {
        let step = (width.max(height) / 96).max(1);
        let (mut seen, mut hidden) = (0usize, 0usize);
        let obj = &self.objects[index];
        for y in (0..height).step_by(step) {
            for x in (0..width).step_by(step) {
                let d = k.ray(x as f64, y as f64);
                let Some((t, _)) = obj.shape.intersect(V3::zeros(), d, 1e-9, f64::INFINITY) else {
                    continue;
                };
                let in_front = self.objects.iter().enumerate().any(|(j, o)| {
                    j != index && o.shape.intersect(V3::zeros(), d, 1e-9, t).is_some()
                });
                if in_front {
                    hidden += 1;
                } else {
                    seen += 1;
                }
            }
        }
        hidden as f64 / (seen + hidden).max(1) as f64
    }

    /// Object coverage fraction and whether any object's rows span the full image height, from
    /// a render at most 96 pixels wide.
    fn coarse_coverage(&self, k: &Intrinsics, width: usize, height: usize) -> (f64, bool) {
        let step = (width.max(height) / 96).max(1);
        let mut covered = 0usize;
        let mut total = 0usize;
        let mut first_row_hit = vec![false; self.objects.len()];
        let mut last_row_hit = vec![false; self.objects.len()];
        let last_y = ((height - 1) / step) * step;
        for y in (0..height).step_by(step) {
            for x in (0..width).step_by(step) {
                total += 1;
                let d = k.ray(x as f64, y as f64);
                let mut nearest: Option<(usize, f64)> = None;
                for (i, o) in self.objects.iter().enumerate() {
                    let t_max = nearest.map_or(f64::INFINITY, |(_, t)| t);
                    if let Some((t, _)) = o.shape.intersect(V3::zeros(), d, 1e-9, t_max) {
                        nearest = Some((i, t));
                    }
                }
                if let Some((i, _)) = nearest {
                    covered += 1;
                    if y == 0 {
                        first_row_hit[i] = true;
                    }
                    if y == last_y {
                        last_row_hit[i] = true;
                    }
                }
            }
        }
        let spans = first_row_hit
            .iter()
            .zip(&last_row_hit)
            .any(|(a, b)| *a && *b);
        (covered as f64 / total.max(1) as f64, spans)
    }
}

/// The unit ray of a pixel drawn in the central part of the view (30–70 % of the width,
/// 35–65 % of the height).
fn central_ray(rng: &mut ChaCha8Rng, k: &Intrinsics, width: usize, height: usize) -> V3 {
    let u = rng.random_range(0.3..0.7) * (width as f64 - 1.0);
    let v = rng.random_range(0.35..0.65) * (height as f64 - 1.0);
    k.ray(u, v)
}

/// Draws the objects of a scene in front of a wall at `wall_z_m` (albedo 0.05) until a draw
/// spans no image from top to bottom and `accept(coverage, hidden)` holds, with `hidden` the
/// share of the second object that others hide; at most 200 draws. `draw` returns `None` for a
/// draw it could not complete. Every attempt failing is practically impossible with the
/// layouts' ranges; the last complete draw is then still a valid scene.
fn draw_until(
    wall_z_m: f64,
    rng: &mut ChaCha8Rng,
    k: &Intrinsics,
    width: usize,
    height: usize,
    accept: impl Fn(f64, f64) -> bool,
    mut draw: impl FnMut(&mut ChaCha8Rng) -> Option<Vec<SceneObject>>,
) -> Scene {
    let mut last = None;
    for _attempt in 0..200 {
        let Some(objects) = draw(rng) else {
            continue;
        };
        let scene = Scene {
            wall_z_m,
            wall_albedo: 0.05,
            objects,
        };
        let (coverage, spans) = scene.coarse_coverage(k, width, height);
        if !spans && accept(coverage, scene.hidden_share(1, k, width, height)) {
            return scene;
        }
        last = Some(scene);
    }
    last.unwrap_or(Scene {
        wall_z_m,
        wall_albedo: 0.05,
        objects: Vec::new(),
    })
}

/// Adds [`random_object`]s whose bounding spheres keep 5 cm from every object already placed,
/// until `objects` holds `target` (at most 100 draws).
fn add_clear_objects(
    objects: &mut Vec<SceneObject>,
    target: usize,
    rng: &mut ChaCha8Rng,
    k: &Intrinsics,
    width: usize,
    height: usize,
) {
    let mut tries = 0;
    while objects.len() < target && tries < 100 {
        tries += 1;
        let obj = random_object(rng, k, width, height);
        if clear_of(objects, &obj.shape) {
            objects.push(obj);
        }
    }
}

/// Whether `shape`'s bounding sphere keeps 5 cm from those of all `objects`.
fn clear_of(objects: &[SceneObject], shape: &Shape) -> bool {
    let (c, r) = shape.bounding_sphere();
    objects.iter().all(|o| {
        let (c2, r2) = o.shape.bounding_sphere();
        (c - c2).norm() > r + r2 + 0.05
    })
}

/// A vertical pole 2–4 cm wide and 0.4–0.8 m tall, 1–2 m from the camera, inside the central
/// part of the view; albedo 0.3–0.9.
fn random_pole(rng: &mut ChaCha8Rng, k: &Intrinsics, width: usize, height: usize) -> SceneObject {
    let u = rng.random_range(0.15..0.85) * (width as f64 - 1.0);
    let v = rng.random_range(0.3..0.7) * (height as f64 - 1.0);
    let hw = rng.random_range(0.01..0.02);
    let hh = rng.random_range(0.2..0.4);
    let c = k.ray(u, v) * rng.random_range(1.0..2.0);
    let h = V3::new(hw, hh, hw);
    SceneObject {
        shape: Shape::Box {
            min: c - h,
            max: c + h,
        },
        albedo: rng.random_range(0.3..0.9),
    }
}

fn random_object(rng: &mut ChaCha8Rng, k: &Intrinsics, width: usize, height: usize) -> SceneObject {
    let albedo = rng.random_range(0.3..0.9);
    // Centre direction inside the central part of the view, so the object is mostly visible.
    let u = rng.random_range(0.15..0.85) * (width as f64 - 1.0);
    let v = rng.random_range(0.25..0.75) * (height as f64 - 1.0);
    let dir = k.ray(u, v);
    let kind = rng.random_range(0..3u32);
    let shape = match kind {
        0 => {
            let radius = rng.random_range(0.12..0.25);
            let range = rng.random_range(1.0 + radius..2.0);
            Shape::Sphere {
                centre: dir * range,
                radius,
            }
        }
        1 => {
            let h = V3::new(
                rng.random_range(0.08..0.22),
                rng.random_range(0.08..0.22),
                rng.random_range(0.08..0.2),
            );
            let range = rng.random_range(1.0 + h[2]..2.0);
            let c = dir * range;
            Shape::Box {
                min: c - h,
                max: c + h,
            }
        }
        _ => {
            // Thin vertical bar (chair leg, pole): 3–6 cm wide, 40–70 cm tall.
            let hw = rng.random_range(0.015..0.03);
            let hh = rng.random_range(0.2..0.35);
            let range = rng.random_range(1.0 + hw..2.0);
            let c = dir * range;
            let h = V3::new(hw, hh, hw);
            Shape::Box {
                min: c - h,
                max: c + h,
            }
        }
    };
    SceneObject { shape, albedo }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn sphere_and_box_hits_have_outward_normals() {
        let s = Shape::Sphere {
            centre: V3::new(0.0, 0.0, 2.0),
            radius: 0.5,
        };
        let (t, n) = s
            .intersect(V3::zeros(), V3::new(0.0, 0.0, 1.0), 0.0, 10.0)
            .unwrap();
        assert!((t - 1.5).abs() < 1e-12 && (n[2] + 1.0).abs() < 1e-12);
        let b = Shape::Box {
            min: V3::new(-0.5, -0.5, 1.0),
            max: V3::new(0.5, 0.5, 2.0),
        };
        let (t, n) = b
            .intersect(V3::zeros(), V3::new(0.0, 0.0, 1.0), 0.0, 10.0)
            .unwrap();
        assert!((t - 1.0).abs() < 1e-12 && n == V3::new(0.0, 0.0, -1.0));
        // Exit through the far face from inside.
        let (t, n) = b
            .intersect(V3::new(0.0, 0.0, 1.5), V3::new(0.0, 0.0, 1.0), 0.0, 10.0)
            .unwrap();
        assert!((t - 0.5).abs() < 1e-12 && n == V3::new(0.0, 0.0, 1.0));
        assert!(b
            .intersect(V3::new(2.0, 0.0, 0.0), V3::new(0.0, 0.0, 1.0), 0.0, 10.0)
            .is_none());
    }

    #[test]
    fn generated_scenes_respect_placement_rules() {
        let k = Intrinsics::new(365.0, 365.0, 255.5, 211.5);
        for seed in 0..20 {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let s = Scene::generate(&mut rng, &k, 512, 424);
            assert!((2..=4).contains(&s.objects.len()), "seed {seed}");
            let (cov, spans) = s.coarse_coverage(&k, 512, 424);
            assert!(cov <= 0.35 && !spans, "seed {seed}: {cov}");
            for o in &s.objects {
                assert!((0.3..=0.9).contains(&o.albedo));
            }
        }
    }

    #[test]
    fn cluttered_scenes_have_a_near_sphere_occluding_a_panel() {
        let k = Intrinsics::new(365.0, 365.0, 255.5, 211.5);
        for seed in 0..20 {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let s = Scene::generate_cluttered(&mut rng, &k, 512, 424);
            assert!((3..=4).contains(&s.objects.len()), "seed {seed}");
            let Shape::Sphere { centre, radius } = s.objects[0].shape else {
                panic!("seed {seed}: the first object is the near sphere");
            };
            let front = centre.norm() - radius;
            assert!((0.75..=1.05).contains(&front), "seed {seed}: {front}");
            let hidden = s.hidden_share(1, &k, 512, 424);
            assert!(
                (0.2..=0.6).contains(&hidden),
                "seed {seed}: panel hidden {hidden}"
            );
            let (cov, spans) = s.coarse_coverage(&k, 512, 424);
            assert!(cov <= 0.55 && !spans, "seed {seed}: {cov}");
        }
    }

    #[test]
    fn a_turned_box_is_hit_on_its_faces_with_turned_normals() {
        // A 1 cm thick panel 2 m ahead, turned 90°: its face normal is the camera's ±x, so the
        // camera sees it exactly edge-on.
        let panel = Shape::TurnedBox {
            centre: V3::new(0.0, 0.0, 2.0),
            half: V3::new(0.3, 0.2, 0.005),
            yaw_rad: std::f64::consts::FRAC_PI_2,
        };
        // Its local x (the 0.6 m width) now runs along the camera's −z: the ray enters the
        // panel's end at z = 2 − 0.3.
        let (t, n) = panel
            .intersect(V3::zeros(), V3::new(0.0, 0.0, 1.0), 0.0, 10.0)
            .unwrap();
        assert!((t - 1.7).abs() < 1e-12, "{t}");
        assert!((n - V3::new(0.0, 0.0, -1.0)).norm() < 1e-12, "{n:?}");
        // A ray 1 cm to the side misses the 1 cm thick panel.
        let d = V3::new(0.01, 0.0, 2.0).normalize();
        assert!(panel.intersect(V3::zeros(), d, 0.0, 10.0).is_none());
        // A ray from the side hits its broad face, with the normal pointing back at it.
        let (t, n) = panel
            .intersect(V3::new(1.0, 0.0, 2.0), V3::new(-1.0, 0.0, 0.0), 0.0, 10.0)
            .unwrap();
        assert!((t - 0.995).abs() < 1e-12, "{t}");
        assert!((n - V3::new(1.0, 0.0, 0.0)).norm() < 1e-12, "{n:?}");
        // Unturned, it is the axis-aligned box.
        let flat = Shape::TurnedBox {
            centre: V3::new(0.0, 0.0, 2.0),
            half: V3::new(0.3, 0.2, 0.005),
            yaw_rad: 0.0,
        };
        let (t, _) = flat
            .intersect(V3::zeros(), V3::new(0.0, 0.0, 1.0), 0.0, 10.0)
            .unwrap();
        assert!((t - 1.995).abs() < 1e-12);
    }

    #[test]
    fn obstacle_scenes_hold_a_near_object_an_edge_on_panel_and_a_pole() {
        let k = Intrinsics::new(365.0, 365.0, 255.5, 211.5);
        for seed in 0..20 {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let s = Scene::generate_obstacles(&mut rng, &k, 512, 424);
            assert!((3..=4).contains(&s.objects.len()), "seed {seed}");
            assert!((4.0..6.0).contains(&s.wall_z_m));
            let Shape::TurnedBox {
                centre, yaw_rad, ..
            } = s.objects[1].shape
            else {
                panic!("seed {seed}: the second object is the panel");
            };
            // 70–88° between its face normal and the ray to its centre.
            let grazing = (yaw_rad - centre[0].atan2(centre[2])).abs().to_degrees();
            assert!((69.9..88.1).contains(&grazing), "seed {seed}: {grazing}");
            assert!(s.hidden_share(1, &k, 512, 424) <= 0.7, "seed {seed}");
            let Shape::Box { min, max } = s.objects[2].shape else {
                panic!("seed {seed}: the third object is the pole");
            };
            let width = max[0] - min[0];
            assert!((0.02..=0.04).contains(&width), "seed {seed}: {width}");
            let (cov, spans) = s.coarse_coverage(&k, 512, 424);
            assert!(cov <= 0.5 && !spans, "seed {seed}: {cov}");
        }
    }

    #[test]
    fn occlusion_blocks_segment_through_object() {
        let scene = Scene {
            wall_z_m: 5.0,
            wall_albedo: 0.05,
            objects: vec![SceneObject {
                shape: Shape::Sphere {
                    centre: V3::new(0.0, 0.0, 2.0),
                    radius: 0.3,
                },
                albedo: 0.5,
            }],
        };
        assert!(scene.occluded(V3::zeros(), V3::new(0.0, 0.0, 4.0)));
        assert!(!scene.occluded(V3::zeros(), V3::new(0.0, 0.0, 1.0)));
        assert!(!scene.occluded(V3::new(1.0, 0.0, 0.0), V3::new(1.0, 0.0, 4.0)));
    }
}
