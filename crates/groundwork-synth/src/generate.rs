//! Frames of a synthetic sequence: the vehicle's pose on the terrain, the sensor's rays cast
//! into the scene, and the sensor's error model applied to the hits.

use glam::{DAffine3, DQuat, DVec2, DVec3};
use groundwork_core::config::MountConfig;
use groundwork_core::{Point, mount_transform};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use rayon::prelude::*;

use crate::SynthError;
use crate::classes::{self, OUTLIER, UNLABELED};
use crate::pattern::BeamPattern;
use crate::scene::{Object, Scene, SceneKind};

/// What to generate.
#[derive(Debug, Clone, PartialEq)]
pub struct SynthConfig {
    /// The scene.
    pub scene: SceneKind,
    /// The sensor's beams and error model.
    pub pattern: BeamPattern,
    /// Where the sensor sits on the vehicle: the same transform as the segmenter's
    /// `sensor.mount` (ground-aligned vehicle frame from sensor frame).
    pub mount: MountConfig,
    /// Seed of the layout and of the sensor noise.
    pub seed: u64,
}

/// One generated scan.
#[derive(Debug, Clone, PartialEq)]
pub struct SynthScan {
    /// Points in the sensor frame, metres (placeholders at the origin where the sensor
    /// emits them).
    pub points: Vec<Point>,
    /// SemanticKITTI label per point: class id in the low 16 bits, instance id in the high.
    pub labels: Vec<u32>,
    /// World pose of the sensor (world from sensor).
    pub pose: DAffine3,
}

impl SynthScan {
    /// The pose as a row-major 4×4 matrix.
    pub fn pose_matrix(&self) -> [[f64; 4]; 4] {
        row_major(&self.pose)
    }

    /// The semantic class of point `i`.
    pub fn class(&self, i: usize) -> u16 {
        (self.labels[i] & 0xffff) as u16
    }
}

/// A seeded generator of one sequence.
#[derive(Debug, Clone)]
pub struct Generator {
    config: SynthConfig,
    frames: usize,
    scene: Scene,
    mount: DAffine3,
}

/// What a ray hit, before the sensor's errors.
#[derive(Debug, Clone, Copy)]
struct Hit {
    range: f64,
    class: u16,
    instance: u16,
    leafy: bool,
}

/// Horizontal bins by azimuth from the sensor, for culling objects per ray.
const BINS: usize = 360;

impl Generator {
    /// A generator of `frames` frames; lays the scene out along the stretch they drive.
    pub fn new(config: SynthConfig, frames: usize) -> Result<Self, SynthError> {
        if frames == 0 {
            return Err(SynthError::Invalid("frames must be at least 1".into()));
        }
        let period = config.pattern.period;
        if !(period.is_finite() && period > 0.0) {
            return Err(SynthError::Invalid(format!("frame period {period} s")));
        }
        let iso = mount_transform(&config.mount).map_err(|e| SynthError::Invalid(e.to_string()))?;
        let q = iso.rotation;
        let mount = DAffine3::from_rotation_translation(
            DQuat::from_xyzw(q.i, q.j, q.k, q.w),
            DVec3::new(iso.translation.x, iso.translation.y, iso.translation.z),
        );
        let (_, speed) = config.scene.drive();
        let length = speed * period * (frames - 1) as f64;
        let reach = config.pattern.max_range.min(120.0) + 10.0;
        let scene = Scene::new(config.scene, config.seed, 0.0, length, reach);
        Ok(Self {
            config,
            frames,
            scene,
            mount,
        })
    }

    /// Number of frames.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// The laid-out scene (its objects carry the instance ids of the labels).
    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// World pose of the vehicle's ground-aligned frame at frame `i`: on the terrain,
    /// heading along the path, tilted with the ground under its wheels.
    pub fn vehicle_pose(&self, i: usize) -> DAffine3 {
        let (lane, speed) = self.config.scene.drive();
        let s = speed * self.config.pattern.period * i as f64;
        let (p, heading) = self.scene.place(s, lane);
        // Wheelbase 2.8 m, track 1.6 m.
        let rotation = self.scene.on_wheels(p, heading, 2.8, 1.6);
        DAffine3::from_rotation_translation(rotation, p.extend(self.scene.height(p.x, p.y)))
    }

    /// World pose of the sensor (world from sensor) at frame `i`.
    pub fn sensor_pose(&self, i: usize) -> DAffine3 {
        self.vehicle_pose(i) * self.mount
    }

    /// [`Generator::sensor_pose`] as a row-major 4×4 matrix.
    pub fn scan_pose_matrix(&self, i: usize) -> [[f64; 4]; 4] {
        row_major(&self.sensor_pose(i))
    }

    /// Frame `i`: the same for a given configuration and seed, on any number of threads.
    pub fn scan(&self, i: usize) -> SynthScan {
        let pattern = &self.config.pattern;
        let pose = self.sensor_pose(i);
        let rays = pattern.rays(i as u64);
        let origin = pose.translation;
        let bins = self.bin_objects(origin.truncate());
        let ego = pattern.ego.map(|e| e.boxes(self.mount.translation.z));
        let hits: Vec<Option<Hit>> = rays
            .par_iter()
            .with_min_len(512)
            .map(|&d| {
                // The body is fixed in the vehicle frame: cast there.
                let ego_hit = ego.as_ref().and_then(|boxes| {
                    let dv = self.mount.matrix3 * d;
                    boxes
                        .iter()
                        .filter_map(|b| b.hit(self.mount.translation, dv, 0.0, f64::INFINITY))
                        .reduce(f64::min)
                });
                self.cast(origin, pose.matrix3 * d, &bins, ego_hit)
            })
            .collect();
        self.sense(&rays, &hits, pose, i)
    }

    /// The objects within reach, binned by the azimuth range they cover from `origin`.
    fn bin_objects(&self, origin: DVec2) -> Vec<Vec<&Object>> {
        let mut bins: Vec<Vec<&Object>> = vec![Vec::new(); BINS];
        let reach = self.config.pattern.max_range;
        let width = std::f64::consts::TAU / BINS as f64;
        for o in self.scene.objects() {
            let (c, r) = o.shape.footprint();
            let dist = c.distance(origin);
            if dist - r > reach {
                continue;
            }
            if dist <= r + 0.5 {
                bins.iter_mut().for_each(|b| b.push(o));
                continue;
            }
            let half = (r / dist).asin() + width;
            let az = (c.y - origin.y).atan2(c.x - origin.x);
            let (lo, hi) = (
                ((az - half) / width).floor() as i64,
                ((az + half) / width).ceil() as i64,
            );
            for k in lo..=hi {
                bins[k.rem_euclid(BINS as i64) as usize].push(o);
            }
        }
        bins
    }

    /// The first surface the world ray from `o` along unit `d` meets.
    fn cast(&self, o: DVec3, d: DVec3, bins: &[Vec<&Object>], ego: Option<f64>) -> Option<Hit> {
        let pattern = &self.config.pattern;
        let mut best: Option<Hit> = ego.filter(|&t| t > pattern.min_range).map(|range| Hit {
            range,
            class: UNLABELED,
            instance: 0,
            leafy: false,
        });
        let mut limit = best.map_or(pattern.max_range, |h| h.range);
        let width = std::f64::consts::TAU / BINS as f64;
        let bin = (d.y.atan2(d.x) / width).floor() as i64;
        for obj in &bins[bin.rem_euclid(BINS as i64) as usize] {
            if let Some(t) = obj.shape.hit(o, d, pattern.min_range, limit) {
                limit = t;
                best = Some(Hit {
                    range: t,
                    class: obj.class,
                    instance: obj.instance,
                    leafy: obj.leafy,
                });
            }
        }
        if let Some(t) = self.march(o, d, pattern.min_range, limit) {
            let p = o + t * d;
            best = Some(Hit {
                range: t,
                class: self.scene.surface(p.x, p.y).class,
                instance: 0,
                leafy: false,
            });
        }
        best
    }

    /// Where the ray meets the terrain within (`t0`, `t1`): steps no longer than the height
    /// above the ground allows at the scene's slope bound, then bisection once below it
    /// (which also finds curbs, steeper than the bound but steps, not ridges).
    fn march(&self, o: DVec3, d: DVec3, t0: f64, t1: f64) -> Option<f64> {
        let scene = &self.scene;
        let above = |t: f64| {
            let p = o + t * d;
            p.z - scene.height(p.x, p.y)
        };
        let rate = (scene.slope_bound() * d.truncate().length() - d.z).max(1e-3);
        let top = scene.max_height();
        let (mut t, mut f) = (t0, above(t0));
        if f <= 0.0 {
            return None;
        }
        while t < t1 {
            if d.z >= 0.0 && o.z + t * d.z > top {
                return None;
            }
            let next = (t + (f / rate).clamp(0.01, 10.0)).min(t1);
            let fn_ = above(next);
            if fn_ <= 0.0 {
                let (mut lo, mut hi) = (t, next);
                while hi - lo > 1e-5 {
                    let mid = 0.5 * (lo + hi);
                    if above(mid) > 0.0 {
                        lo = mid;
                    } else {
                        hi = mid;
                    }
                }
                return Some(hi);
            }
            t = next;
            f = fn_;
        }
        None
    }

    /// The sensor's errors, drawn in ray order from a generator seeded by the seed and the
    /// frame: dropouts, range noise, foliage penetration, multipath below the ground.
    fn sense(
        &self,
        rays: &[DVec3],
        hits: &[Option<Hit>],
        pose: DAffine3,
        frame: usize,
    ) -> SynthScan {
        let pattern = &self.config.pattern;
        let mut rng = ChaCha8Rng::seed_from_u64(self.config.seed);
        rng.set_stream(frame as u64 + 1);
        let mut points = Vec::with_capacity(rays.len());
        let mut labels = Vec::with_capacity(rays.len());
        for (d, hit) in rays.iter().zip(hits) {
            // A fixed number of draws per ray keeps every ray's noise independent of the
            // others' outcomes.
            let drop = rng.random_bool(pattern.dropout);
            let noise: f64 = rng.sample::<f64, _>(StandardNormal) * pattern.range_noise;
            let depth: f64 = rng.random_range(0.0..0.3);
            let echo = rng.random_bool(pattern.multipath);
            let extra: f64 = rng.random_range(0.5..3.0);
            let shade: f32 = rng.random_range(-0.05..0.05);
            let Some(hit) = hit.filter(|_| !drop) else {
                if pattern.placeholders {
                    points.push(Point::default());
                    labels.push(u32::from(UNLABELED));
                }
                continue;
            };
            let mut range = hit.range + noise;
            let (mut class, mut instance) = (hit.class, hit.instance);
            if hit.leafy {
                range += depth;
            }
            if echo && classes::is_ground(class) {
                // A mirror path through a puddle or glossy road: the point lands along the
                // beam, at least 0.3 m below the surface.
                let sink = (pose.matrix3 * *d).z.abs().max(0.01);
                range += extra.max(0.3 / sink).min(30.0);
                (class, instance) = (OUTLIER, 0);
            }
            let p = *d * range;
            points.push(Point {
                x: p.x as f32,
                y: p.y as f32,
                z: p.z as f32,
                intensity: (classes::intensity(class) + shade).clamp(0.0, 1.0),
            });
            labels.push(u32::from(class) | (u32::from(instance) << 16));
        }
        SynthScan {
            points,
            labels,
            pose,
        }
    }
}

/// A rigid transform as a row-major 4×4 matrix.
fn row_major(a: &DAffine3) -> [[f64; 4]; 4] {
    let c = a.matrix3.to_cols_array_2d();
    let t = a.translation;
    let mut m = [[0.0; 4]; 4];
    for r in 0..3 {
        m[r] = [c[0][r], c[1][r], c[2][r], t[r]];
    }
    m[3][3] = 1.0;
    m
}

impl SynthConfig {
    /// A sequence of `scene` seen by the built-in pattern of `sensor` (a preset name) on
    /// `mount`.
    pub fn new(
        sensor: &str,
        mount: MountConfig,
        scene: SceneKind,
        seed: u64,
    ) -> Result<Self, SynthError> {
        let pattern = BeamPattern::for_sensor(sensor)
            .ok_or_else(|| SynthError::UnknownSensor(sensor.to_string()))?;
        Ok(Self {
            scene,
            pattern,
            mount,
            seed,
        })
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::classes::{CAR, PERSON, is_ground};
    use crate::pattern::Scanning;
    use proptest::prelude::*;

    fn generator(sensor: &str, scene: SceneKind, frames: usize, mount: MountConfig) -> Generator {
        Generator::new(SynthConfig::new(sensor, mount, scene, 3).unwrap(), frames).unwrap()
    }

    fn level(height: f64) -> MountConfig {
        MountConfig {
            height,
            ..Default::default()
        }
    }

    #[test]
    fn the_same_frames_on_one_thread_and_on_many() {
        let g = generator("hdl64e", SceneKind::Urban, 3, level(1.73));
        let many = g.scan(2);
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let one = pool.install(|| g.scan(2));
        assert_eq!(many, one);
        assert_ne!(g.scan(1).points, many.points);
    }

    #[test]
    fn labels_are_exact_ground_points_lie_on_the_terrain_and_objects_above_it() {
        // A tilted, turned sensor: the labels must hold through mount and pose.
        let mount = MountConfig {
            height: 1.6,
            roll: 0.05,
            pitch: -0.07,
            yaw: 0.4,
            matrix: None,
        };
        for scene in SceneKind::ALL {
            let g = generator("os1-64", scene, 6, mount.clone());
            let scan = g.scan(5);
            let (mut ground, mut things) = (0, 0);
            for (i, p) in scan.points.iter().enumerate() {
                let w = scan
                    .pose
                    .transform_point3(DVec3::new(p.x.into(), p.y.into(), p.z.into()));
                let above = w.z - g.scene().height(w.x, w.y);
                let class = scan.class(i);
                if is_ground(class) {
                    // Range noise is 1.5 cm (σ): 10 σ along any beam.
                    assert!(
                        above.abs() < 0.15,
                        "{scene:?}: class {class} {above} m off the ground"
                    );
                    ground += 1;
                } else if class == CAR || class == PERSON {
                    // On the ground or above it, never in it (feet stand on slopes).
                    assert!(
                        above > -0.1,
                        "{scene:?}: a {class} point {above} m above ground"
                    );
                    assert!(scan.labels[i] >> 16 > 0, "things carry an instance id");
                    things += 1;
                } else if class == OUTLIER && scene != SceneKind::Hill {
                    // (On the hill an echo may land over the embankment, which falls away
                    // faster than the mirrored beam sinks.)
                    assert!(above < -0.1, "{scene:?}: multipath echo {above} m");
                }
            }
            assert!(
                ground > 10_000 && things > 100,
                "{scene:?}: {ground} ground, {things} things"
            );
        }
    }

    #[test]
    fn instance_ids_name_objects_of_the_scene() {
        let g = generator("hdl64e", SceneKind::Parking, 1, level(1.73));
        let scan = g.scan(0);
        for (i, l) in scan.labels.iter().enumerate() {
            let id = (l >> 16) as u16;
            if id > 0 {
                let obj = g
                    .scene()
                    .objects()
                    .iter()
                    .find(|o| o.instance == id)
                    .unwrap();
                // A tree's trunk and crown share an id and differ in class.
                assert!(
                    obj.class == scan.class(i)
                        || g.scene()
                            .objects()
                            .iter()
                            .any(|o| o.instance == id && o.class == scan.class(i))
                );
            }
        }
    }

    #[test]
    fn placeholders_only_where_the_driver_sends_them() {
        let ouster = generator("os1-64", SceneKind::Urban, 1, level(1.5)).scan(0);
        assert_eq!(ouster.points.len(), 64 * 1024, "an organized image");
        let velodyne = generator("hdl64e", SceneKind::Urban, 1, level(1.73)).scan(0);
        assert!(velodyne.points.len() < 64 * 2000);
        assert!(
            !velodyne
                .points
                .iter()
                .any(|p| p.x == 0.0 && p.y == 0.0 && p.z == 0.0)
        );
    }

    #[test]
    fn the_vehicle_follows_the_path_and_the_terrain() {
        let g = generator("hdl64e", SceneKind::Offroad, 20, level(1.73));
        for i in [0, 10, 19] {
            let v = g.vehicle_pose(i);
            let p = v.translation;
            assert!((p.z - g.scene().height(p.x, p.y)).abs() < 1e-9);
            let s = g.sensor_pose(i).translation;
            // The sensor is 1.73 m up along the vehicle's tilted z.
            assert!((s - p).length() - 1.73 < 1e-9);
        }
        // Turning left: the heading grows.
        let yaw = |i| {
            let x = g.vehicle_pose(i).matrix3.x_axis;
            x.y.atan2(x.x)
        };
        assert!(yaw(19) > yaw(0) + 0.1);
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 24, ..ProptestConfig::default() })]
        /// Any seed, scene and mount: one label per point, finite points within the range
        /// limits, and placeholders only at the origin.
        #[test]
        fn every_point_is_finite_in_range_and_labelled(
            seed in 0u64..1000,
            scene in 0usize..SceneKind::ALL.len(),
            height in 0.4f64..2.5,
            roll in -0.2f64..0.2,
            pitch in -0.2f64..0.2,
            yaw in -3.2f64..3.2,
            frame in 0usize..5,
        ) {
            let mut pattern = BeamPattern::for_sensor("os1-64").unwrap();
            // A coarse image keeps the property fast.
            pattern.scanning = Scanning::Spinning { elevations_deg: (0..16).map(|i| 20.0 - 3.0 * f64::from(i)).collect(), columns: 128 };
            let mount = MountConfig { height, roll, pitch, yaw, matrix: None };
            let cfg = SynthConfig { scene: SceneKind::ALL[scene], pattern, mount, seed };
            let g = Generator::new(cfg, 5).unwrap();
            let scan = g.scan(frame);
            prop_assert_eq!(scan.points.len(), 16 * 128);
            prop_assert_eq!(scan.labels.len(), scan.points.len());
            for p in &scan.points {
                let r = (p.x * p.x + p.y * p.y + p.z * p.z).sqrt();
                prop_assert!(r.is_finite());
                // Multipath echoes may land up to 30 m beyond the hit.
                prop_assert!(r == 0.0 || (0.4..151.0).contains(&r), "range {}", r);
            }
        }
    }
}
