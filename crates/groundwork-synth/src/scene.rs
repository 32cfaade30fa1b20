//! Procedural scenes: a terrain heightfield with a ground class at every place, objects
//! standing on it, and the circular path the vehicle drives.
//!
//! Every scene is laid out around a circle of radius `R` centred at (0, R): the vehicle
//! starts at the origin heading +x and turns left along it. A place is described by its
//! arc length `s` along that circle and its lateral offset `d` (positive toward the
//! centre, i.e. to the vehicle's left).

use std::f64::consts::{FRAC_PI_2, FRAC_PI_4, PI};

use glam::{DQuat, DVec2, DVec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::classes::*;
use crate::shapes::Shape;

/// The kinds of scene.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SceneKind {
    /// A curved two-lane street with cross streets, curbs and sidewalks, parked cars, poles,
    /// street trees, pedestrians and buildings; the road climbs and falls gently.
    Urban,
    /// Rolling hills (slopes up to about 20 %) with a dirt track, bushes, trees and boulders.
    Offroad,
    /// A parking lot with rows of cars, light poles and people, a ramp up to a raised deck,
    /// a curb and a building.
    Parking,
    /// A country road over hills: grades up to about 11 %, crests and dips a sensor looks
    /// over or into, a cut slope rising on the left and an embankment falling on the right,
    /// a guard rail, traffic, trees and bushes on the slopes.
    Hill,
    /// A steep city intersection, as on a Pandar64 city drive: the town street climbing and
    /// falling at up to 8 %, the whole block tilted 4 % across it (so the cross streets
    /// climb one way and fall the other), and cars parked nose to tail along both kerbs.
    City,
}

impl SceneKind {
    /// Every scene, in the order `groundwork synth` lists them.
    pub const ALL: [SceneKind; 5] = [
        SceneKind::Urban,
        SceneKind::Offroad,
        SceneKind::Parking,
        SceneKind::Hill,
        SceneKind::City,
    ];

    /// The scene's name on the command line.
    pub fn name(self) -> &'static str {
        match self {
            SceneKind::Urban => "urban",
            SceneKind::Offroad => "offroad",
            SceneKind::Parking => "parking",
            SceneKind::Hill => "hill",
            SceneKind::City => "city",
        }
    }

    /// The scene called `name` (any case).
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL
            .into_iter()
            .find(|k| k.name().eq_ignore_ascii_case(name))
    }

    /// Radius of the layout circle, metres.
    fn radius(self) -> f64 {
        match self {
            SceneKind::Urban => 80.0,
            SceneKind::Offroad => 60.0,
            SceneKind::Parking => 25.0,
            SceneKind::Hill => 400.0,
            SceneKind::City => 80.0,
        }
    }

    /// The vehicle's lateral offset (right-hand lane in town) and speed (m/s).
    pub(crate) fn drive(self) -> (f64, f64) {
        match self {
            SceneKind::Urban => (-1.75, 8.0),
            SceneKind::Offroad => (0.0, 5.0),
            SceneKind::Parking => (0.0, 4.0),
            SceneKind::Hill => (-1.75, 12.0),
            SceneKind::City => (-1.75, 6.0),
        }
    }
}

/// A solid of the scene with its labels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Object {
    /// Its geometry, world frame.
    pub shape: Shape,
    /// SemanticKITTI class id.
    pub class: u16,
    /// Instance id (unique per object in the scene, shared by an object's parts, e.g. a
    /// car's body and cabin or a tree's trunk and crown); 0 for buildings and fences.
    pub instance: u16,
    /// Foliage: beams penetrate it by a random depth.
    pub leafy: bool,
}

/// The ground at one place.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Surface {
    /// Height, metres (world z).
    pub height: f64,
    /// SemanticKITTI ground class.
    pub class: u16,
}

/// A laid-out scene.
#[derive(Debug, Clone)]
pub struct Scene {
    kind: SceneKind,
    radius: f64,
    objects: Vec<Object>,
}

fn smoothstep(x: f64) -> f64 {
    let x = x.clamp(0.0, 1.0);
    x * x * (3.0 - 2.0 * x)
}

/// Offroad terrain height: rolling hills with ruts.
fn offroad_height(x: f64, y: f64) -> f64 {
    1.4 * (0.045 * x + 0.7).sin() * (0.033 * y).cos()
        + 0.9 * (0.06 * (x + y) + 1.3).sin()
        + 0.35 * (0.11 * x - 0.09 * y).cos()
        // Ruts and clods: 3 cm at about 2 m.
        + 0.03 * (3.1 * x).sin() * (2.7 * y).sin()
}

/// Hill road: height of the road's centre line at arc length `s`, metres. Grades up to
/// 0.08 + 0.033 = 11 %; the vehicle starts on a climb toward a crest about 40 m ahead.
fn hill_profile(s: f64) -> f64 {
    3.2 * (s / 40.0 + 0.6).sin() + 0.5 * (s / 15.0 + 1.0).sin()
}

/// Hill road: half width of the asphalt, and where the slopes beside it begin, metres.
const HILL_ROAD_HALF: f64 = 4.5;
const HILL_SHOULDER: f64 = 7.0;

/// Parking lot height, and how much of it is the ramp and the sidewalk (their classes).
fn parking_parts(x: f64, y: f64) -> (f64, f64, f64) {
    // 1 % fall for drainage.
    let mut height = 0.01 * x.clamp(-60.0, 100.0);
    let (rx0, rx1, rx2) = RAMP_X;
    let (ry0, ry1) = RAMP_Y;
    let edge = 0.1;
    let across = smoothstep((y - ry0) / edge) * (1.0 - smoothstep((y - ry1) / edge));
    let along = smoothstep((x - rx0) / (rx1 - rx0)) * (1.0 - smoothstep((x - rx2) / edge));
    let ramp = DECK * along * across;
    height += ramp;
    let walk =
        smoothstep((y - WALK_Y.0) / CURB_WIDTH) * (1.0 - smoothstep((y - WALK_Y.1) / CURB_WIDTH));
    height += CURB * walk;
    (height, ramp, walk)
}

/// City: the amplitude of the street's climbs and falls (1.6 m over an eighth of the
/// circle: 8 % at the steepest) and the block's tilt across the street (4 %).
const CITY_CLIMB: f64 = 1.6;
const CITY_TILT: f64 = 0.04;

/// Parked cars along a kerb: the gap to the next car (metres, from..to) and the chance a
/// space holds one. In town every other space or so; in the city nose to tail.
const URBAN_PARKING: ((f64, f64), f64) = ((5.5, 9.0), 0.6);
const CITY_PARKING: ((f64, f64), f64) = ((4.9, 5.6), 0.92);

/// Height of urban curbs and the parking lot's sidewalk, metres.
const CURB: f64 = 0.15;
/// Width over which a curb rises, metres.
const CURB_WIDTH: f64 = 0.06;
/// Half width of the urban road, metres.
const ROAD_HALF: f64 = 6.0;
/// Half width of the urban cross streets, metres.
const CROSS_HALF: f64 = 6.0;

/// Parking: ramp footprint (x from, x top, x end of the deck; y band) and deck height.
const RAMP_X: (f64, f64, f64) = (30.0, 50.0, 70.0);
const RAMP_Y: (f64, f64) = (8.0, 20.0);
const DECK: f64 = 3.0;
/// Parking: the sidewalk in front of the building (y band).
const WALK_Y: (f64, f64) = (-12.0, -10.0);

impl Scene {
    /// Lays out a scene of `kind` covering the path from arc length `s_from` to `s_to` and
    /// everything a sensor sees from it (objects within `reach` metres), from `seed`.
    pub fn new(kind: SceneKind, seed: u64, s_from: f64, s_to: f64, reach: f64) -> Self {
        let mut scene = Scene {
            kind,
            radius: kind.radius(),
            objects: Vec::new(),
        };
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut layout = Layout {
            scene: &scene,
            rng: &mut rng,
            objects: Vec::new(),
            next_instance: 1,
        };
        match kind {
            SceneKind::Urban => layout.urban(s_from - reach, s_to + reach, URBAN_PARKING),
            SceneKind::City => layout.urban(s_from - reach, s_to + reach, CITY_PARKING),
            SceneKind::Offroad => layout.offroad(s_from, s_to, reach),
            SceneKind::Parking => layout.parking(),
            SceneKind::Hill => layout.hill(s_from - reach, s_to + reach),
        }
        scene.objects = layout.objects;
        scene
    }

    /// The scene's kind.
    pub fn kind(&self) -> SceneKind {
        self.kind
    }

    /// The objects standing in the scene.
    pub fn objects(&self) -> &[Object] {
        &self.objects
    }

    /// Arc length and lateral offset of a place (see the module documentation).
    pub fn path_coordinates(&self, p: DVec2) -> (f64, f64) {
        let v = p - DVec2::new(0.0, self.radius);
        let angle = v.x.atan2(-v.y);
        (self.radius * angle, self.radius - v.length())
    }

    /// The place at arc length `s` and lateral offset `d`, and the path's heading there.
    pub fn place(&self, s: f64, d: f64) -> (DVec2, f64) {
        let a = s / self.radius;
        let p = DVec2::new(0.0, self.radius) + (self.radius - d) * DVec2::new(a.sin(), -a.cos());
        (p, a)
    }

    /// Upper bound of the terrain's slope away from curbs and ramp edges (which are steps
    /// the ray marcher finds by a change of sign).
    pub(crate) fn slope_bound(&self) -> f64 {
        match self.kind {
            SceneKind::Urban => 0.12,
            SceneKind::Offroad => 0.42,
            SceneKind::Parking => 0.25,
            SceneKind::Hill => 0.4,
            SceneKind::City => 0.14,
        }
    }

    /// Upper bound of the terrain's height anywhere, metres.
    pub(crate) fn max_height(&self) -> f64 {
        match self.kind {
            SceneKind::Urban => 1.0 + CURB + 0.5,
            SceneKind::Offroad => 1.4 + 0.9 + 0.35 + 0.03,
            SceneKind::Parking => 0.01 * 100.0 + DECK + CURB,
            SceneKind::Hill => 3.2 + 0.5 + 3.0,
            SceneKind::City => CITY_CLIMB + CITY_TILT * 80.0 + CURB + 0.5,
        }
    }

    /// The ground at (x, y).
    pub fn surface(&self, x: f64, y: f64) -> Surface {
        match self.kind {
            SceneKind::Urban => self.urban_surface(x, y),
            SceneKind::Offroad => self.offroad_surface(x, y),
            SceneKind::Parking => self.parking_surface(x, y),
            SceneKind::Hill => self.hill_surface(x, y),
            SceneKind::City => self.urban_surface(x, y),
        }
    }

    /// World from vehicle of a vehicle standing at `p` heading `heading` (radians): turned
    /// about z, and tilted with the ground under its wheels, the slopes between its axles
    /// (`wheelbase` apart) and between its wheels (`track` apart).
    pub fn on_wheels(&self, p: DVec2, heading: f64, wheelbase: f64, track: f64) -> DQuat {
        let fwd = DVec2::new(heading.cos(), heading.sin());
        let left = fwd.perp();
        let h = |q: DVec2| self.height(q.x, q.y);
        let pitch = (h(p + 0.5 * wheelbase * fwd) - h(p - 0.5 * wheelbase * fwd)) / wheelbase;
        let roll = (h(p + 0.5 * track * left) - h(p - 0.5 * track * left)) / track;
        let normal = (DVec3::Z - pitch * fwd.extend(0.0) - roll * left.extend(0.0)).normalize();
        DQuat::from_rotation_arc(DVec3::Z, normal) * DQuat::from_rotation_z(heading)
    }

    /// Terrain height at (x, y).
    pub fn height(&self, x: f64, y: f64) -> f64 {
        // The ray marcher's inner loop: offroad and parking heights do not need the
        // path coordinates (an atan2 and a square root) that only their classes use.
        match self.kind {
            SceneKind::Urban => self.urban_surface(x, y).height,
            SceneKind::Offroad => offroad_height(x, y),
            SceneKind::Parking => parking_parts(x, y).0,
            SceneKind::Hill => self.hill_surface(x, y).height,
            SceneKind::City => self.urban_surface(x, y).height,
        }
    }

    /// Arc length to the nearest cross street's centre line (cross streets every 45° of the
    /// circle, the first 22.5° ahead of the start).
    fn cross_offset(&self, s: f64) -> f64 {
        let a = s / self.radius - FRAC_PI_4 / 2.0;
        let k = (a / FRAC_PI_4).round();
        self.radius * (a - k * FRAC_PI_4)
    }

    fn urban_surface(&self, x: f64, y: f64) -> Surface {
        let (s, d) = self.path_coordinates(DVec2::new(x, y));
        let cross = self.cross_offset(s);
        // Four climbs and descents per circle: at most 5 % grade along the road. Toward the
        // circle's centre the amplitude shrinks with the radius, so that the grade does not
        // steepen where the circles of equal height crowd together.
        let rho = self.radius - d;
        let (climb, tilt) = match self.kind {
            SceneKind::City => (CITY_CLIMB, CITY_TILT * d),
            _ => (1.0, 0.0),
        };
        let grade = climb * (rho / self.radius).min(1.0) * (4.0 * s / self.radius).sin() + tilt;
        // The road is crowned: 1 % down toward the curbs.
        let crown = -0.01 * d.abs().min(ROAD_HALF);
        // How far outside both roads (negative: on a road).
        let outside = (d.abs() - ROAD_HALF).min(cross.abs() - CROSS_HALF);
        let curb = CURB * smoothstep(outside / CURB_WIDTH);
        // Lawns behind the sidewalk rise gently.
        let lawn = (0.02 * (d.abs() - 10.0)).clamp(0.0, 0.5);
        let class = if outside <= 0.0 {
            ROAD
        } else if d.abs() < 10.0 || cross.abs() < CROSS_HALF + 3.5 {
            SIDEWALK
        } else {
            TERRAIN
        };
        Surface {
            height: grade + crown + curb + lawn,
            class,
        }
    }

    fn offroad_surface(&self, x: f64, y: f64) -> Surface {
        let (_, d) = self.path_coordinates(DVec2::new(x, y));
        let class = if d.abs() < 1.8 { OTHER_GROUND } else { TERRAIN };
        Surface {
            height: offroad_height(x, y),
            class,
        }
    }

    fn hill_surface(&self, x: f64, y: f64) -> Surface {
        let (s, d) = self.path_coordinates(DVec2::new(x, y));
        // As in town, the profile's amplitude shrinks toward the circle's centre so that
        // grades do not steepen where lines of equal arc length crowd together.
        let rho = self.radius - d;
        let road = (rho / self.radius).min(1.0) * hill_profile(s);
        // Crowned 2 %; the shoulder carries on at the asphalt's edge height.
        let crown = -0.02 * d.abs().min(HILL_ROAD_HALF);
        // Left: a cut slope rising at 20 % up to 3 m; right: an embankment falling at 18 %
        // down to 2.5 m, each easing in over a metre.
        let beyond = (d.abs() - HILL_SHOULDER).max(0.0);
        let ease = smoothstep(beyond);
        let side = if d > 0.0 {
            (0.2 * beyond * ease).min(3.0)
        } else {
            -(0.18 * beyond * ease).min(2.5)
        };
        let class = if d.abs() < HILL_ROAD_HALF {
            ROAD
        } else {
            TERRAIN
        };
        Surface {
            height: road + crown + side,
            class,
        }
    }

    fn parking_surface(&self, x: f64, y: f64) -> Surface {
        let (height, ramp, walk) = parking_parts(x, y);
        let (_, d) = self.path_coordinates(DVec2::new(x, y));
        let class = if ramp > 0.0 || d.abs() < 3.5 {
            ROAD
        } else if walk > 0.0 {
            SIDEWALK
        } else {
            PARKING
        };
        Surface { height, class }
    }
}

/// Places objects with a seeded generator.
struct Layout<'a> {
    scene: &'a Scene,
    rng: &'a mut ChaCha8Rng,
    objects: Vec<Object>,
    next_instance: u16,
}

impl Layout<'_> {
    fn instance(&mut self) -> u16 {
        let id = self.next_instance;
        self.next_instance = self.next_instance.saturating_add(1);
        id
    }

    fn push(&mut self, shape: Shape, class: u16, instance: u16) {
        self.objects.push(Object {
            shape,
            class,
            instance,
            leafy: class == VEGETATION,
        });
    }

    fn ground(&self, p: DVec2) -> f64 {
        self.scene.height(p.x, p.y)
    }

    /// A car (body and cabin) or now and then a van, centred at `p` heading `yaw`, tilted
    /// with the ground under its wheels.
    fn car(&mut self, p: DVec2, yaw: f64) {
        let id = self.instance();
        let van = self.rng.random_bool(0.15);
        let (l, w) = if van {
            (5.0, 2.0)
        } else {
            (
                self.rng.random_range(3.9..4.8),
                self.rng.random_range(1.7..1.9),
            )
        };
        let rotation = self.scene.on_wheels(p, yaw, 0.6 * l, w - 0.2);
        let foot = p.extend(self.ground(p));
        // A part: half extents, and its centre in the car's frame (x forward, z up from the
        // ground under the car's centre).
        let part = |this: &mut Self, half: DVec3, at: DVec3| {
            let shape = Shape::TiltedBox {
                center: foot + rotation * at,
                half,
                rotation,
            };
            this.push(shape, CAR, id);
        };
        if van {
            let half = DVec3::new(2.5, 1.0, 1.05);
            part(self, half, DVec3::new(0.0, 0.0, 0.15 + half.z));
            return;
        }
        let top = self.rng.random_range(0.85..1.0);
        let roof = self.rng.random_range(1.4..1.6);
        let body = DVec3::new(l / 2.0, w / 2.0, (top - 0.2) / 2.0);
        part(self, body, DVec3::new(0.0, 0.0, 0.2 + body.z));
        let cabin = DVec3::new(0.27 * l, w / 2.0 - 0.1, (roof - top) / 2.0);
        part(self, cabin, DVec3::new(-0.08 * l, 0.0, top + cabin.z));
    }

    fn person(&mut self, p: DVec2) {
        let id = self.instance();
        let shape = Shape::Cylinder {
            base: p.extend(self.ground(p)),
            radius: self.rng.random_range(0.22..0.3),
            height: self.rng.random_range(1.55..1.9),
        };
        self.push(shape, PERSON, id);
    }

    fn pole(&mut self, p: DVec2, sign: bool) {
        let id = self.instance();
        let height = self.rng.random_range(5.0..8.0);
        let base = p.extend(self.ground(p));
        let radius = self.rng.random_range(0.08..0.15);
        self.push(
            Shape::Cylinder {
                base,
                radius,
                height,
            },
            POLE,
            id,
        );
        if sign {
            let sign_id = self.instance();
            let shape = Shape::Box {
                center: base + DVec3::new(0.0, 0.0, height - 1.0),
                half: DVec3::new(0.05, 0.35, 0.35),
                yaw: self.rng.random_range(0.0..PI),
            };
            self.push(shape, TRAFFIC_SIGN, sign_id);
        }
    }

    fn tree(&mut self, p: DVec2) {
        let id = self.instance();
        let base = p.extend(self.ground(p));
        let trunk = self.rng.random_range(2.0..3.0);
        let radius = self.rng.random_range(0.12..0.25);
        self.push(
            Shape::Cylinder {
                base,
                radius,
                height: trunk + 0.5,
            },
            TRUNK,
            id,
        );
        let r = self.rng.random_range(1.3..2.2);
        let radii = DVec3::new(
            r,
            r * self.rng.random_range(0.85..1.15),
            self.rng.random_range(1.2..2.0),
        );
        self.push(
            Shape::Ellipsoid {
                center: base + DVec3::new(0.0, 0.0, trunk + 0.8 * radii.z),
                radii,
            },
            VEGETATION,
            id,
        );
    }

    /// A bush (or, as `class`, a boulder) half sunk into the ground.
    fn mound(&mut self, p: DVec2, class: u16) {
        let id = self.instance();
        let (lo, hi) = if class == VEGETATION {
            (0.6, 1.8)
        } else {
            (0.4, 1.2)
        };
        let radii = DVec3::new(
            self.rng.random_range(lo..hi),
            self.rng.random_range(lo..hi),
            self.rng.random_range(0.4..1.1),
        );
        let sunk = if class == VEGETATION { 0.5 } else { 0.3 };
        let shape = Shape::Ellipsoid {
            center: p.extend(self.ground(p) + (1.0 - 2.0 * sunk) * radii.z),
            radii,
        };
        self.push(shape, class, id);
    }

    /// A building or a wall: a straight box between arc lengths `s0` and `s1`, beside the
    /// path (`side` = ±1), its face toward it `face` metres away, `size` = (depth, height).
    fn block(&mut self, (s0, s1): (f64, f64), side: f64, face: f64, size: (f64, f64), class: u16) {
        let (depth, height) = size;
        let len = s1 - s0;
        // A straight face bends away from the circle; on the inner side its ends come
        // closer to the path by the sagitta, which is added so that no end does.
        let sag = if side > 0.0 {
            len * len / (8.0 * self.scene.radius)
        } else {
            0.0
        };
        let (p, heading) = self
            .scene
            .place(0.5 * (s0 + s1), side * (face + sag + depth / 2.0));
        let z = self.ground(p) - 0.5;
        let half = DVec3::new(len / 2.0, depth / 2.0, (height + 0.5) / 2.0);
        self.push(
            Shape::Box {
                center: p.extend(z + half.z),
                half,
                yaw: heading,
            },
            class,
            0,
        );
    }

    fn urban(&mut self, s_from: f64, s_to: f64, parking: ((f64, f64), f64)) {
        let scene = self.scene;
        let near_cross = |s: f64, margin: f64| scene.cross_offset(s).abs() < CROSS_HALF + margin;
        let ((gap_from, gap_to), parked) = parking;
        for side in [-1.0, 1.0] {
            // Parked cars in the parking lanes along the curbs.
            let mut s = s_from;
            while s < s_to {
                s += self.rng.random_range(gap_from..gap_to);
                if !near_cross(s, 3.0) && self.rng.random_bool(parked) {
                    let (p, heading) = scene.place(s, side * 4.75);
                    let yaw = heading + self.rng.random_range(-0.05..0.05);
                    self.car(p, yaw);
                }
            }
            // Poles just behind the curb, a third with a sign.
            let mut s = s_from;
            while s < s_to {
                s += self.rng.random_range(18.0..30.0);
                if !near_cross(s, 0.5) {
                    let sign = self.rng.random_bool(0.35);
                    self.pole(scene.place(s, side * 6.4).0, sign);
                }
            }
            // Street trees.
            let mut s = s_from;
            while s < s_to {
                s += self.rng.random_range(8.0..16.0);
                if !near_cross(s, 2.5) && self.rng.random_bool(0.5) {
                    self.tree(scene.place(s, side * 8.1).0);
                }
            }
            // Pedestrians on the sidewalk.
            let mut s = s_from;
            while s < s_to {
                s += self.rng.random_range(6.0..20.0);
                let d = self.rng.random_range(6.9..9.6);
                self.person(scene.place(s, side * d).0);
            }
            // Buildings behind the sidewalk, walls in some gaps; cross streets stay open.
            let mut s = s_from;
            while s < s_to {
                if near_cross(s, 3.0) {
                    s += 0.5;
                    continue;
                }
                // Up to the next cross street.
                let want = self.rng.random_range(12.0..30.0);
                let mut end = s;
                while end < s + want && !near_cross(end + 0.5, 3.0) {
                    end += 0.5;
                }
                let gap = if self.rng.random_bool(0.3) {
                    self.rng.random_range(8.0..15.0)
                } else {
                    self.rng.random_range(0.5..4.0)
                };
                if end - s >= 6.0 {
                    let face = self.rng.random_range(11.0..12.5);
                    let depth = self.rng.random_range(8.0..15.0);
                    let height = self.rng.random_range(6.0..20.0);
                    self.block((s, end), side, face, (depth, height), BUILDING);
                }
                if gap > 6.0 && !near_cross(end + gap, 3.0) {
                    let h = self.rng.random_range(1.0..1.5);
                    self.block((end + 0.5, end + gap - 0.5), side, 10.5, (0.2, h), FENCE);
                }
                s = end + gap;
            }
        }
        // Oncoming traffic in the other lane.
        let mut s = s_from;
        while s < s_to {
            s += self.rng.random_range(25.0..50.0);
            if self.rng.random_bool(0.5) {
                let (p, heading) = scene.place(s, 1.75);
                self.car(p, heading + PI);
            }
        }
    }

    fn offroad(&mut self, s_from: f64, s_to: f64, reach: f64) {
        let scene = self.scene;
        // Everything within `reach` of the driven stretch, on a jittered 8 m grid.
        let (p0, p1) = (scene.place(s_from, 0.0).0, scene.place(s_to, 0.0).0);
        let mut lo = p0.min(p1) - DVec2::splat(reach);
        let mut hi = p0.max(p1) + DVec2::splat(reach);
        // The stretch may bend past its end points' box.
        let steps = ((s_to - s_from) / 5.0).ceil().max(1.0) as usize;
        for k in 0..=steps {
            let p = scene
                .place(s_from + (s_to - s_from) * k as f64 / steps as f64, 0.0)
                .0;
            lo = lo.min(p - DVec2::splat(reach));
            hi = hi.max(p + DVec2::splat(reach));
        }
        let cell = 8.0;
        let mut y = lo.y;
        while y < hi.y {
            let mut x = lo.x;
            while x < hi.x {
                let p = DVec2::new(x, y)
                    + DVec2::new(
                        self.rng.random_range(0.0..cell),
                        self.rng.random_range(0.0..cell),
                    );
                let (s, d) = scene.path_coordinates(p);
                let on_stretch = s > s_from - reach && s < s_to + reach;
                let roll: f64 = self.rng.random_range(0.0..1.0);
                if d.abs() > 3.5 || !on_stretch {
                    if roll < 0.55 {
                        self.mound(p, VEGETATION);
                    } else if roll < 0.7 {
                        self.tree(p);
                    } else if roll < 0.8 {
                        self.mound(p, OTHER_OBJECT);
                    }
                }
                x += cell;
            }
            y += cell;
        }
        // Vehicles parked beside the track, hikers on its edge.
        let mut s = s_from - reach;
        while s < s_to + reach {
            s += self.rng.random_range(25.0..60.0);
            let side = if self.rng.random_bool(0.5) { 1.0 } else { -1.0 };
            let (p, heading) = scene.place(s, side * 4.5);
            self.car(p, heading);
            let p = scene
                .place(
                    s + self.rng.random_range(8.0..15.0),
                    side * self.rng.random_range(2.2..3.0),
                )
                .0;
            self.person(p);
        }
    }

    fn hill(&mut self, s_from: f64, s_to: f64) {
        let scene = self.scene;
        // Traffic: parked on the shoulder, and in both lanes.
        let mut s = s_from;
        while s < s_to {
            s += self.rng.random_range(20.0..45.0);
            let roll: f64 = self.rng.random_range(0.0..1.0);
            let (d, turn) = if roll < 0.3 {
                (-5.6, 0.0)
            } else if roll < 0.65 {
                (1.9, PI)
            } else {
                (-1.9, 0.0)
            };
            // Nothing in the ego lane within 15 m of the start.
            if d < 0.0 && d > -3.0 && s.abs() < 15.0 {
                continue;
            }
            let (p, heading) = scene.place(s, d);
            let yaw = heading + turn + self.rng.random_range(-0.04..0.04);
            self.car(p, yaw);
        }
        // A guard rail along the embankment, posts every 4 m.
        let mut s = s_from;
        while s < s_to {
            let len = self.rng.random_range(30.0..60.0);
            self.block((s, s + len), -1.0, HILL_SHOULDER - 0.4, (0.15, 0.75), FENCE);
            s += len + self.rng.random_range(10.0..40.0);
        }
        // Poles now and then on the right, trees and bushes on both slopes.
        let mut s = s_from;
        while s < s_to {
            s += self.rng.random_range(30.0..50.0);
            let sign = self.rng.random_bool(0.3);
            self.pole(scene.place(s, -(HILL_SHOULDER - 1.0)).0, sign);
        }
        for side in [-1.0, 1.0] {
            let mut s = s_from;
            while s < s_to {
                s += self.rng.random_range(4.0..10.0);
                let d = side
                    * self
                        .rng
                        .random_range(HILL_SHOULDER + 2.0..HILL_SHOULDER + 35.0);
                let p = scene.place(s, d).0;
                if self.rng.random_bool(0.4) {
                    self.tree(p);
                } else {
                    self.mound(p, VEGETATION);
                }
            }
        }
        // Walkers on the shoulder.
        let mut s = s_from;
        while s < s_to {
            s += self.rng.random_range(25.0..70.0);
            let d = self.rng.random_range(4.8..6.2);
            self.person(scene.place(s, d).0);
        }
    }

    fn parking(&mut self) {
        let scene = self.scene;
        let in_aisle = |p: DVec2, margin: f64| scene.path_coordinates(p).1.abs() < 3.5 + margin;
        let on_ramp =
            |p: DVec2| p.x > RAMP_X.0 - 3.0 && p.y > RAMP_Y.0 - 3.0 && p.y < RAMP_Y.1 + 3.0;
        // Rows of stalls along x, nose-in: a row every 6 m, a stall every 2.7 m.
        let mut cars: Vec<DVec2> = Vec::new();
        for row in 0..12 {
            let y = -7.0 + 6.0 * f64::from(row);
            for col in 0..28 {
                let p = DVec2::new(-45.0 + 2.7 * f64::from(col), y);
                if p.x > RAMP_X.2 || in_aisle(p, 2.6) || on_ramp(p) || !self.rng.random_bool(0.7) {
                    continue;
                }
                let yaw = FRAC_PI_2 + self.rng.random_range(-0.06..0.06);
                self.car(p, yaw);
                cars.push(p);
            }
        }
        // Light poles on an 18 m grid, off the aisle.
        for i in 0..6 {
            for j in 0..5 {
                let p = DVec2::new(-42.0 + 18.0 * f64::from(i), -4.0 + 18.0 * f64::from(j));
                if !in_aisle(p, 1.0) && !on_ramp(p) && cars.iter().all(|c| c.distance(p) > 2.6) {
                    self.pole(p, false);
                }
            }
        }
        // People walking between the rows and in the aisle.
        let mut placed = 0;
        while placed < 16 {
            let p = DVec2::new(
                self.rng.random_range(-40.0..28.0),
                self.rng.random_range(-9.0..55.0),
            );
            if on_ramp(p) || cars.iter().any(|c| c.distance(p) < 2.8) {
                continue;
            }
            // Nobody stands where the vehicle drives.
            if scene.path_coordinates(p).1.abs() < 1.5 {
                continue;
            }
            self.person(p);
            placed += 1;
        }
        // The ramp's side walls and the deck's end wall.
        let walls = [
            (
                DVec2::new(0.5 * (RAMP_X.0 + RAMP_X.2), RAMP_Y.0 - 0.15),
                DVec3::new(0.5 * (RAMP_X.2 - RAMP_X.0), 0.15, 0.0),
                0.0,
            ),
            (
                DVec2::new(0.5 * (RAMP_X.0 + RAMP_X.2), RAMP_Y.1 + 0.15),
                DVec3::new(0.5 * (RAMP_X.2 - RAMP_X.0), 0.15, 0.0),
                0.0,
            ),
            (
                DVec2::new(RAMP_X.2 + 0.15, 0.5 * (RAMP_Y.0 + RAMP_Y.1)),
                DVec3::new(0.15, 0.5 * (RAMP_Y.1 - RAMP_Y.0) + 0.3, 0.0),
                0.0,
            ),
        ];
        for (c, half, yaw) in walls {
            let top = DECK + 1.1;
            self.push(
                Shape::Box {
                    center: c.extend(top / 2.0 - 0.25),
                    half: DVec3::new(half.x, half.y, top / 2.0 + 0.25),
                    yaw,
                },
                BUILDING,
                0,
            );
        }
        // The building behind the sidewalk.
        self.push(
            Shape::Box {
                center: DVec3::new(-10.0, WALK_Y.0 - 6.0, 6.0),
                half: DVec3::new(40.0, 6.0, 7.0),
                yaw: 0.0,
            },
            BUILDING,
            0,
        );
        // A few trees along the sidewalk.
        for k in 0..6 {
            self.tree(DVec2::new(
                -40.0 + 14.0 * f64::from(k),
                0.5 * (WALK_Y.0 + WALK_Y.1),
            ));
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn path_coordinates_invert_place() {
        for kind in SceneKind::ALL {
            let scene = Scene::new(kind, 1, 0.0, 10.0, 40.0);
            for (s, d) in [(0.0, 0.0), (17.0, -4.0), (-30.0, 6.5), (60.0, 2.0)] {
                let (p, _) = scene.place(s, d);
                let (s2, d2) = scene.path_coordinates(p);
                assert!(
                    (s - s2).abs() < 1e-9 && (d - d2).abs() < 1e-9,
                    "{kind:?} {s} {d}"
                );
            }
        }
    }

    #[test]
    fn urban_curbs_lift_the_sidewalk_by_15_cm() {
        let scene = Scene::new(SceneKind::Urban, 1, 0.0, 10.0, 40.0);
        let (road, _) = scene.place(0.0, ROAD_HALF - 0.2);
        let (walk, _) = scene.place(0.0, ROAD_HALF + 0.2);
        let (a, b) = (scene.surface(road.x, road.y), scene.surface(walk.x, walk.y));
        assert_eq!((a.class, b.class), (ROAD, SIDEWALK));
        assert!(
            (b.height - a.height - CURB).abs() < 0.01,
            "{} {}",
            a.height,
            b.height
        );
    }

    #[test]
    fn cars_stand_on_their_wheels_on_the_steep_street() {
        // Every corner of a car's body clears the ground under it (0.2 m under the centre;
        // less at a corner where the street curves): an upright box sinks its uphill end
        // into an 8 % street, and its points at the road's height were labelled car.
        for kind in [SceneKind::City, SceneKind::Hill] {
            for seed in 0..3 {
                let scene = Scene::new(kind, seed, 0.0, 10.0, 60.0);
                let mut lowest = f64::INFINITY;
                for o in scene.objects().iter().filter(|o| o.class == CAR) {
                    let Shape::TiltedBox {
                        center,
                        half,
                        rotation,
                    } = o.shape
                    else {
                        panic!("a car is a tilted box: {:?}", o.shape);
                    };
                    for (sx, sy) in [(-1.0, -1.0), (-1.0, 1.0), (1.0, -1.0), (1.0, 1.0)] {
                        let c = center + rotation * (half * DVec3::new(sx, sy, -1.0));
                        lowest = lowest.min(c.z - scene.height(c.x, c.y));
                    }
                }
                assert!(
                    lowest > 0.1 && lowest < 0.25,
                    "{kind:?} seed {seed}: {lowest}"
                );
            }
        }
    }

    #[test]
    fn the_city_is_steep_and_parked_full() {
        let city = Scene::new(SceneKind::City, 1, 0.0, 10.0, 60.0);
        let town = Scene::new(SceneKind::Urban, 1, 0.0, 10.0, 60.0);
        let cars = |scene: &Scene| {
            let mut ids: Vec<u16> = scene
                .objects()
                .iter()
                .filter(|o| o.class == CAR)
                .map(|o| o.instance)
                .collect();
            ids.dedup();
            ids.len()
        };
        assert!(
            cars(&city) > cars(&town) * 3 / 2,
            "{} {}",
            cars(&city),
            cars(&town)
        );
        // The street climbs ahead and falls behind, metres within 40 m of the start, and the
        // block tilts across it.
        let h = |scene: &Scene, s: f64, d: f64| {
            let (p, _) = scene.place(s, d);
            scene.height(p.x, p.y)
        };
        let along = || (-40..=40).map(|s| h(&city, f64::from(s), -1.75));
        let (fall, rise) = (
            along().fold(f64::NAN, f64::min),
            along().fold(f64::NAN, f64::max),
        );
        assert!(rise - fall > 2.5, "{fall} {rise}");
        assert!((h(&city, 0.0, 30.0) - h(&city, 0.0, -30.0)).abs() > 2.0);
    }

    #[test]
    fn layouts_are_deterministic_and_differ_by_seed() {
        for kind in SceneKind::ALL {
            let a = Scene::new(kind, 7, 0.0, 20.0, 60.0);
            let b = Scene::new(kind, 7, 0.0, 20.0, 60.0);
            let c = Scene::new(kind, 8, 0.0, 20.0, 60.0);
            assert_eq!(a.objects, b.objects, "{kind:?}");
            assert_ne!(a.objects, c.objects, "{kind:?}");
            assert!(a.objects.len() > 20, "{kind:?}: {}", a.objects.len());
        }
    }

    #[test]
    fn the_slope_bound_holds_away_from_steps() {
        // Finite differences on a grid avoiding curbs and ramp edges.
        for kind in SceneKind::ALL {
            let scene = Scene::new(kind, 1, 0.0, 10.0, 40.0);
            let mut worst: f64 = 0.0;
            for i in -60..60 {
                for j in -60..60 {
                    let (x, y) = (f64::from(i) * 0.73, f64::from(j) * 0.91);
                    let h = 0.01;
                    let gx = (scene.height(x + h, y) - scene.height(x - h, y)) / (2.0 * h);
                    let gy = (scene.height(x, y + h) - scene.height(x, y - h)) / (2.0 * h);
                    // Steps (curbs, the ramp's edges) are where the class changes.
                    let class = scene.surface(x, y).class;
                    let step = [(0.3, 0.0), (-0.3, 0.0), (0.0, 0.3), (0.0, -0.3)]
                        .iter()
                        .any(|(dx, dy)| scene.surface(x + dx, y + dy).class != class);
                    if !step {
                        worst = worst.max(gx.hypot(gy));
                    }
                    assert!(scene.height(x, y) <= scene.max_height(), "{kind:?}");
                }
            }
            assert!(worst <= scene.slope_bound(), "{kind:?}: {worst}");
        }
    }
}
