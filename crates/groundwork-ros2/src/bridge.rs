//! The bridge: three stages in one process (one thread each), sharing the DDS participant
//! and the clouds in flight. `CloudsIn` is a source: it waits on the DDS subscription and
//! publishes each cloud as a scan. `AnswersOut` wakes on masks and publishes the answering
//! clouds (and, without a TF tree to read, the mount on `/tf_static`). `DetectionsOut`
//! wakes on proposals and publishes their boxes.

use std::collections::VecDeque;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use anyhow::Context as _;
use ros2_client::dds::rustdds::mio1::{Events, Interest, Poll, Token};
use ros2_client::dds::rustdds::{
    self, DomainParticipant, QosPolicies, QosPolicyBuilder, TopicKind, no_key, policy,
};
use ros2_client::{
    Context, MessageInfo, MessageTypeName, Name, Node, NodeName, NodeOptions, QosProfile,
    Subscription, qos,
};
use serde::Serialize;
use tracing::{info, warn};

use groundwork_detect::ProposalFlags;
use groundwork_io::Scan;
use groundwork_io::pointcloud2::{CloudPoints, select_records, with_probability};
use groundwork_io::transform::{GROUND_FRAME, SENSOR_FRAME, StaticTransform};
use groundwork_msg::{
    FrameId, MaskHeader, MaskStatus, ProposalRecord, ProposalsHeader, SCHEMA_VERSION, ScanHeader,
    ScanPoint, ScanSource, monotonic_ns, new_epoch, wall_clock_ns,
};
use groundwork_service::ServiceConfig;
use groundwork_service::producer::pose_matrix;
use groundwork_service::stage::{self, Input, Inputs, Outbox, Stage, Topic, Wiring};

use crate::msg::{
    BoundingBox3D, ColorRGBA, Covariance, Detection3D, Detection3DArray, Header, Marker,
    MarkerArray, ObjectHypothesis, ObjectHypothesisWithPose, Odometry, PointCloud2, Pose,
    PoseWithCovariance, Quaternion, TFMessage, Time, Transform, TransformStamped, Vector3,
};
use crate::odom::OdomTrack;
use crate::pose::Pose as Isometry;
use crate::tf::TfTree;

/// Reliability of the input subscription.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Qos {
    /// ROS 2's sensor-data profile: best effort, keep last 5 (drivers publish so).
    #[default]
    SensorData,
    /// Reliable, keep last 5 (for publishers that are reliable only).
    Reliable,
}

/// What the bridge subscribes to and publishes.
#[derive(Debug, Clone)]
pub struct BridgeOptions {
    /// DDS domain (`ROS_DOMAIN_ID`).
    pub domain_id: u16,
    /// The PointCloud2 topic, a ROS name (`/points`).
    pub input_topic: String,
    /// The input subscription's QoS.
    pub qos: Qos,
    /// The node's namespace (`/`).
    pub namespace: String,
    /// The node's name: outputs are `<namespace>/<node>/points`, `.../nonground`,
    /// `.../ground` (ROS's `~/points`).
    pub node: String,
    /// Also publish the ground points.
    pub publish_ground: bool,
    /// Points whose probability is at least this are ground (the segmenter's threshold).
    pub ground_threshold: f32,
    /// Stop after answering this many clouds.
    pub count: Option<u64>,
    /// The sensor's mount, published on `/tf_static` for each cloud frame seen (the
    /// detections' frame, `base_footprint`, to the cloud's).
    pub mount: Option<StaticTransform>,
    /// A `nav_msgs/Odometry` topic giving each scan its pose (the multi-frame history);
    /// `None`: scans carry no pose and are segmented on their own.
    pub odometry_topic: Option<String>,
    /// Read `/tf` and `/tf_static` instead: each scan's pose is its cloud frame's in this
    /// fixed frame (e.g. `odom`) at its stamp. The vehicle's tree then places the sensor:
    /// the mount is not published, and boxes are given in the cloud's frame.
    pub tf_fixed_frame: Option<String>,
}

impl Default for BridgeOptions {
    fn default() -> Self {
        Self {
            domain_id: 0,
            input_topic: "/points".into(),
            qos: Qos::SensorData,
            namespace: "/".into(),
            node: "groundwork".into(),
            publish_ground: false,
            ground_threshold: 0.5,
            count: None,
            mount: None,
            odometry_topic: None,
            tf_fixed_frame: None,
        }
    }
}

/// What the bridge did.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct BridgeReport {
    /// Clouds received from DDS.
    pub received: u64,
    /// Clouds published as scans.
    pub published: u64,
    /// Clouds skipped as malformed (missing fields, non-finite in a dense cloud, too many
    /// points, lying sizes), with the last reason.
    pub rejected: u64,
    /// The last rejection's reason.
    pub last_rejection: Option<String>,
    /// Clouds answered on `~/points`.
    pub answered: u64,
    /// Proposal messages answered on `~/detections` and `~/markers`.
    pub detections: u64,
    /// Masks the segmenter marked bad (no answer published for their cloud).
    pub bad_masks: u64,
    /// Masks whose cloud was no longer held (answered too late).
    pub unmatched_masks: u64,
    /// Clouds published and never answered (the segmenter skipped them, or more were in
    /// flight than the bridge holds).
    pub dropped: u64,
    /// DDS reads or writes that failed.
    pub dds_errors: u64,
    /// Clouds a publisher sent that the bridge never received: lost on the way, or
    /// overwritten in the subscription's history (the last 5) before they were taken.
    /// Counted from the gaps in each publisher's sequence numbers (a sample lost after a
    /// publisher's last received one cannot be seen).
    pub lost_before_received: u64,
    /// Odometry samples taken (with an odometry topic).
    pub odometry: u64,
    /// Odometry samples refused (no time, no pose) or unreadable.
    pub odometry_rejected: u64,
    /// Transforms taken from `/tf` and `/tf_static` (with a fixed frame).
    pub transforms: u64,
    /// Transforms refused (no time, no pose, a frame its own parent) or unreadable.
    pub transforms_rejected: u64,
    /// Clouds published without a pose although odometry or TF was to give one (no sample
    /// within 0.1 s of their stamp; with TF also a frame not connected to the fixed one).
    pub no_pose: u64,
    /// Why the last such cloud had none.
    pub last_no_pose: Option<String>,
}

/// Clouds published and not yet answered, oldest first. Bounded: a segmenter that stops
/// answering does not grow the bridge.
#[derive(Debug, Default)]
struct InFlight {
    clouds: VecDeque<Held>,
    /// With boxes in the clouds' frames: the frame of each recent scan (epoch, sequence).
    frames: VecDeque<(u64, u64, String)>,
    report: BridgeReport,
    /// The answering stage has stopped (done, signalled or failed): so does the input.
    answers_stopped: bool,
    /// The input stage has stopped (done, signalled or failed): so do the answers.
    input_stopped: bool,
}

#[derive(Debug)]
struct Held {
    epoch: u64,
    sequence: u64,
    cloud: Arc<PointCloud2>,
    /// The scan's map from points back to records (without its points).
    scan: Scan,
    /// Points published.
    points: usize,
}

/// Clouds held for their answers.
const MAX_IN_FLIGHT: usize = 16;

impl InFlight {
    /// Holds a cloud for its answer; the oldest is dropped (and counted) when
    /// [`MAX_IN_FLIGHT`] are held.
    fn hold(&mut self, held: Held) {
        if self.clouds.len() == MAX_IN_FLIGHT {
            self.clouds.pop_front();
            self.report.dropped += 1;
        }
        self.clouds.push_back(held);
    }

    /// The cloud a mask of scan (`epoch`, `sequence`) answers. Older clouds will never be
    /// answered (the segmenter skipped them): dropped and counted. A mask for no held
    /// cloud is counted as unmatched.
    fn answered(&mut self, epoch: u64, sequence: u64) -> Option<Held> {
        let at = self
            .clouds
            .iter()
            .position(|c| c.epoch == epoch && c.sequence == sequence);
        match at {
            Some(i) => {
                self.report.dropped += i as u64;
                self.clouds.drain(..=i).next_back()
            }
            None => {
                self.report.unmatched_masks += 1;
                None
            }
        }
    }
}

type Shared = Arc<Mutex<InFlight>>;

fn lock(s: &Shared) -> std::sync::MutexGuard<'_, InFlight> {
    // A panic in the other stage ends the process anyway; the counters stay readable.
    s.lock().unwrap_or_else(PoisonError::into_inner)
}

/// A ROS topic name (`/a/b/points`) as ros2-client takes it.
pub fn ros_name(full: &str) -> anyhow::Result<Name> {
    let full = if full.starts_with('/') {
        full.to_string()
    } else {
        format!("/{full}")
    };
    let (ns, base) = full.rsplit_once('/').unwrap_or(("", &full));
    let ns = if ns.is_empty() { "/" } else { ns };
    Name::new(ns, base).map_err(|e| anyhow::anyhow!("{full:?} is not a ROS topic name: {e:?}"))
}

/// The cloud type's DDS name, as ROS 2 registers it.
pub fn cloud_type() -> MessageTypeName {
    MessageTypeName::new("sensor_msgs", "PointCloud2")
}

/// The source stage: DDS clouds into scans.
struct CloudsIn {
    subscription: no_key::SimpleDataReaderCdr<PointCloud2>,
    /// The input topic's name, for messages.
    topic: String,
    poll: Poll,
    events: Events,
    shared: Shared,
    epoch: u64,
    sequence: u64,
    max_points: usize,
    answers_wanted: Option<u64>,
    /// Polled this long for a cloud before the runner looks at signals again.
    wait: Duration,
    /// What gives scans their poses, if anything.
    poses: Option<PoseSource>,
    /// Remember each scan's frame (for boxes given in the clouds' frames).
    keep_frames: bool,
    /// Each publisher's last sequence number: the clouds lost before the bridge.
    gaps: SequenceGaps<ros2_client::Gid>,
    /// Set by SIGCONT: the process was stopped and resumed.
    resumed: Arc<AtomicBool>,
}

/// The samples each publisher sent and a subscriber never took, from the gaps in their
/// sequence numbers (DDS numbers a writer's samples 1, 2, 3, …).
#[derive(Debug)]
struct SequenceGaps<K>(std::collections::HashMap<K, i64>);

impl<K: std::hash::Hash + Eq> SequenceGaps<K> {
    fn new() -> Self {
        Self(std::collections::HashMap::new())
    }

    /// Samples missed between the publisher's last one seen and this one (0 for its
    /// first, and for one that comes late or twice).
    fn see(&mut self, publisher: K, sequence: i64) -> u64 {
        match self.0.get_mut(&publisher) {
            None => {
                self.0.insert(publisher, sequence);
                0
            }
            Some(last) if sequence > *last => {
                let missed = (sequence - *last - 1).unsigned_abs();
                *last = sequence;
                missed
            }
            // Late or repeated: the newest is kept.
            Some(_) => 0,
        }
    }
}

/// Where scans' poses come from.
// One per bridge: the variants' sizes do not matter.
#[allow(clippy::large_enum_variant)]
enum PoseSource {
    /// A `nav_msgs/Odometry` subscription and the samples it gave.
    Odometry {
        subscription: Subscription<Odometry>,
        track: OdomTrack,
    },
    /// `/tf` and `/tf_static`, the tree they gave, and the fixed frame.
    Tf {
        moving: Subscription<TFMessage>,
        statics: Subscription<TFMessage>,
        tree: TfTree,
        fixed: String,
    },
}

/// Counts one refused pose sample or transform, logging its reason now and then (a bad
/// source at 100 Hz would flood the log).
fn refuse(count: &mut u64, what: &str, reason: &str) {
    if (*count + 1).is_power_of_two() {
        warn!("skipped {what}: {reason}");
    }
    *count += 1;
}

impl PoseSource {
    /// Takes every sample that has arrived.
    fn take(&mut self, shared: &Shared) {
        match self {
            Self::Odometry {
                subscription,
                track,
            } => loop {
                let added = match subscription.take() {
                    Ok(Some((odom, _))) => track.add(&odom),
                    Ok(None) => return,
                    Err(e) => Err(format!("DDS read failed: {e:?}")),
                };
                let mut s = lock(shared);
                match added {
                    Ok(()) => s.report.odometry += 1,
                    Err(r) => refuse(&mut s.report.odometry_rejected, "an odometry sample", &r),
                }
            },
            Self::Tf {
                moving,
                statics,
                tree,
                ..
            } => {
                for (subscription, is_static) in [(statics, true), (moving, false)] {
                    loop {
                        let (taken, refused) = match subscription.take() {
                            Ok(Some((msg, _))) => tree.add(&msg, is_static),
                            Ok(None) => break,
                            Err(e) => (0, vec![format!("DDS read failed: {e:?}")]),
                        };
                        let mut s = lock(shared);
                        s.report.transforms += taken as u64;
                        for r in &refused {
                            refuse(&mut s.report.transforms_rejected, "a transform", r);
                        }
                    }
                }
            }
        }
    }

    /// The pose of a scan in `frame` stamped `stamp_ns`, or why there is none.
    fn pose(&self, frame: &str, stamp_ns: u64) -> Result<Isometry, String> {
        match self {
            Self::Odometry { track, .. } => track.sensor_pose(frame, stamp_ns).ok_or_else(|| {
                format!(
                    "no odometry within {} ms of the stamp",
                    crate::pose::HOLD_NS / 1_000_000
                )
            }),
            Self::Tf { tree, fixed, .. } => tree.lookup(fixed, frame, stamp_ns),
        }
    }
}

impl CloudsIn {
    /// Holds a cloud until its answer (before it is published: the answer may come back
    /// at once).
    fn hold(&self, cloud: &Arc<PointCloud2>, points: &CloudPoints<'_>) {
        lock(&self.shared).hold(Held {
            epoch: self.epoch,
            sequence: self.sequence,
            cloud: Arc::clone(cloud),
            scan: points.records_map(),
            points: points.len(),
        });
    }

    /// Publishes one received cloud; a bad one is counted and skipped.
    fn publish(
        &mut self,
        cloud: PointCloud2,
        received_wall_ns: Option<u64>,
        out: &mut Outbox,
    ) -> anyhow::Result<()> {
        let taken = monotonic_ns();
        // The DDS receipt (the last fragment in), on the monotonic clock: the latency
        // tool's bridge row covers DDS's queue, deserialization and the copy.
        let produced = received_wall_ns.map_or(taken, |r| {
            taken.saturating_sub(wall_clock_ns().saturating_sub(r))
        });
        lock(&self.shared).report.received += 1;
        let label = format!(
            "{} (stamp {}.{:09})",
            self.topic, cloud.header.stamp.sec, cloud.header.stamp.nanosec
        );
        // Shared with the answering stage, which appends the probabilities to it.
        let cloud = Arc::new(cloud);
        let view = cloud.view();
        let reject = |e: groundwork_io::FormatError| {
            let reason = e.to_string();
            warn!("skipped a cloud: {reason}");
            let mut s = lock(&self.shared);
            s.report.rejected += 1;
            s.report.last_rejection = Some(reason);
        };
        // The layout first; the coordinates are checked as they are copied.
        let points = match CloudPoints::unsearched(Path::new(&label), &view, self.max_points) {
            Ok(p) => p,
            Err(e) => {
                reject(e);
                return Ok(());
            }
        };
        let mut header = ScanHeader {
            schema_version: SCHEMA_VERSION,
            point_count: points.len() as u32,
            sequence: self.sequence,
            producer_epoch: self.epoch,
            // A driver's stamp before 1970 is not a time: the wall clock stands in.
            sensor_timestamp_ns: view.stamp_ns().unwrap_or_else(wall_clock_ns),
            source_index: self.sequence,
            source: ScanSource::ROS2,
            frame_id: FrameId::new(&cloud.header.frame_id),
            ..ScanHeader::default()
        };
        header.stamps.produced_ns = produced;
        let frame = header.frame_id.get().unwrap_or(SENSOR_FRAME);
        if let Some(o) = &self.poses {
            match o.pose(frame, header.sensor_timestamp_ns) {
                Ok(p) => {
                    header.has_pose = 1;
                    header.pose = pose_matrix(&p);
                }
                Err(reason) => {
                    let mut s = lock(&self.shared);
                    refuse(&mut s.report.no_pose, "a cloud's pose", &reason);
                    s.report.last_no_pose = Some(reason);
                }
            }
        }
        if self.keep_frames {
            let mut s = lock(&self.shared);
            if s.frames.len() == 4 * MAX_IN_FLIGHT {
                s.frames.pop_front();
            }
            s.frames
                .push_back((self.epoch, self.sequence, frame.to_string()));
        }
        // The one copy, from the DDS sample's bytes straight into shared memory in one pass
        // over the records, taking every record for a point and checking that as it goes
        // (most clouds have no placeholder).
        self.hold(&cloud, &points);
        let copy = |sample: &mut [ScanPoint]| points.copy_into(sample, ScanPoint::from).1;
        if out.send_scan_filled(points.len(), copy, header)?.is_none() {
            // A record is no point: withdrawn, searched, and copied again without the
            // placeholders (or rejected, if the cloud said it was dense).
            lock(&self.shared).clouds.pop_back();
            let points = match points.search_placeholders(Path::new(&label)) {
                Ok(p) => p,
                Err(e) => {
                    reject(e);
                    return Ok(());
                }
            };
            header.point_count = points.len() as u32;
            self.hold(&cloud, &points);
            let copy = |sample: &mut [ScanPoint]| points.copy_into(sample, ScanPoint::from).1;
            out.send_scan_filled(points.len(), copy, header)?;
        }
        self.sequence += 1;
        lock(&self.shared).report.published += 1;
        Ok(())
    }
}

impl Stage for CloudsIn {
    const NAME: &'static str = "ros2";
    const WIRING: Wiring = Wiring {
        wakes_on: None,
        reads: &[],
        publishes: Some(Topic::Scans),
        parallel: false,
        unique: true,
    };
    type Report = ();

    fn start(&mut self) -> anyhow::Result<()> {
        // Here, after the stage's shared-memory node installed its signal handlers.
        signal_hook::flag::register(signal_hook::consts::SIGCONT, Arc::clone(&self.resumed))
            .context("watch for SIGCONT")?;
        Ok(())
    }

    fn process(&mut self, _: Input<'_>, _: u64, out: &mut Outbox) -> anyhow::Result<()> {
        if self.resumed.load(Ordering::Relaxed) {
            // Linux ends a blocking epoll_wait with EINTR after a stop and continue, and
            // RustDDS's event loops end on any poll error: the bridge would stay up and
            // receive nothing. Failing lets `pipeline --restart` start a new one.
            anyhow::bail!(
                "the bridge was stopped and resumed (SIGSTOP/SIGTSTP, then SIGCONT): its DDS \
                 event loop does not survive that, so it exits to be restarted"
            );
        }
        // Edge-triggered: after a wake-up, take everything that has arrived. A signal that
        // interrupts the wait (SIGCONT, SIGCHLD) only ends it early; a stop request is
        // seen by the runner when this returns.
        match self.poll.poll(&mut self.events, Some(self.wait)) {
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            r => r.context("poll the DDS subscription")?,
        }
        loop {
            // The poses first: a cloud takes the odometry or transforms that came before it.
            if let Some(o) = &mut self.poses {
                o.take(&self.shared);
            }
            self.subscription.drain_read_notifications();
            match self.subscription.try_take_one() {
                Ok(Some(sample)) => {
                    let info = MessageInfo::from(&sample);
                    let cloud = sample.into_value();
                    let missed = self.gaps.see(info.publisher_gid(), info.sequence_number());
                    if missed > 0 {
                        lock(&self.shared).report.lost_before_received += missed;
                    }
                    let received = info
                        .received_timestamp()
                        .and_then(|t| u64::try_from(t.to_nanos()).ok());
                    self.publish(cloud, received, out)?;
                }
                Ok(None) => return Ok(()),
                Err(e) => {
                    // A sample that does not deserialize as a PointCloud2 (another type
                    // under the same name, a truncated message): counted, skipped. RustDDS
                    // moves past it; the rest is taken at the next turn.
                    warn!("skipped a cloud: DDS read failed: {e:?}");
                    let mut s = lock(&self.shared);
                    s.report.dds_errors += 1;
                    s.report.rejected += 1;
                    s.report.last_rejection = Some(format!("DDS read failed: {e:?}"));
                    return Ok(());
                }
            }
        }
    }

    fn done(&self) -> bool {
        let s = lock(&self.shared);
        s.answers_stopped || self.answers_wanted.is_some_and(|n| s.report.answered >= n)
    }

    fn log_state(&self) {
        let s = lock(&self.shared);
        info!(
            received = s.report.received,
            published = s.report.published,
            rejected = s.report.rejected,
            lost_before_received = s.report.lost_before_received,
            "ros2 input state"
        );
    }

    fn stop(self, _: &Inputs) -> anyhow::Result<()> {
        Ok(())
    }
}

/// The answering stage: masks into ROS 2 clouds.
struct AnswersOut {
    /// `/tf_static`, and the frames published on it so far.
    tf: Option<(Writer<TFMessage>, StaticTransform, Vec<String>)>,
    points: Writer<PointCloud2>,
    nonground: Writer<PointCloud2>,
    ground: Option<Writer<PointCloud2>>,
    shared: Shared,
    threshold: f32,
    max_points: usize,
    count: Option<u64>,
}

impl AnswersOut {
    fn answer(&mut self, h: &MaskHeader, probs: &[f32]) -> anyhow::Result<()> {
        let held = lock(&self.shared).answered(h.producer_epoch, h.scan_sequence);
        let Some(held) = held else { return Ok(()) };
        if h.status != MaskStatus::OK || probs.len() != held.points {
            lock(&self.shared).report.bad_masks += 1;
            return Ok(());
        }
        self.place(&held.cloud.header);
        let answer = answer_clouds(
            &held,
            probs,
            self.threshold,
            self.max_points,
            self.ground.is_some(),
        )?;
        self.send(&self.points, answer.points);
        self.send(&self.nonground, answer.nonground);
        if let (Some(g), Some(cloud)) = (&self.ground, answer.ground) {
            self.send(g, cloud);
        }
        lock(&self.shared).report.answered += 1;
        Ok(())
    }

    fn send<M: Serialize>(&self, p: &Writer<M>, m: M) {
        send(&self.shared, p, m);
    }

    /// Publishes the mount on `/tf_static` when a cloud names a frame not seen before: as
    /// a static broadcaster does, one message with every frame's transform.
    fn place(&mut self, header: &Header) {
        let Some((publisher, mount, frames)) = &mut self.tf else {
            return;
        };
        if frames.contains(&header.frame_id) {
            return;
        }
        frames.push(header.frame_id.clone());
        send(
            &self.shared,
            publisher,
            static_transforms(mount, frames, header),
        );
    }
}

/// The answers to one cloud: the cloud with a `ground_probability` field (0 for a record
/// that is no point), its non-ground records, and with `with_ground` its ground records.
/// A placeholder record (no return) is in neither part.
struct Answer {
    points: PointCloud2,
    nonground: PointCloud2,
    ground: Option<PointCloud2>,
}

/// [`Answer`] to `held` from its points' probabilities (`probs`, one per point published).
fn answer_clouds(
    held: &Held,
    probs: &[f32],
    threshold: f32,
    max_points: usize,
    with_ground: bool,
) -> anyhow::Result<Answer> {
    let label = Path::new("ros2 answer");
    let per_record = held.scan.expand(probs, 0.0);
    // Each record's decision; none for a placeholder, which is neither ground nor not.
    let decisions: Vec<Option<bool>> = probs.iter().map(|&p| Some(p >= threshold)).collect();
    let decisions = held.scan.expand(&decisions, None);
    let cloud = held.cloud.view();
    let header = &held.cloud.header;
    let big = held.cloud.is_bigendian;
    let with = with_probability(label, &cloud, &per_record, max_points)?;
    let part = |ground: bool| -> anyhow::Result<PointCloud2> {
        let pick: Vec<bool> = decisions.iter().map(|&d| d == Some(ground)).collect();
        let mut records = select_records(label, &cloud, &pick, max_points)?;
        records.is_dense = true;
        Ok(PointCloud2::from_data(header.clone(), big, records))
    };
    Ok(Answer {
        points: PointCloud2::from_data(header.clone(), big, with),
        nonground: part(false)?,
        ground: with_ground.then(|| part(true)).transpose()?,
    })
}

/// The `/tf_static` message placing every frame in `frames` on the mount, as a static
/// broadcaster sends it: one message with every frame's transform.
fn static_transforms(mount: &StaticTransform, frames: &[String], header: &Header) -> TFMessage {
    let [x, y, z] = mount.translation;
    let [qx, qy, qz, qw] = mount.rotation;
    let transforms = frames
        .iter()
        .map(|child| TransformStamped {
            header: Header {
                stamp: header.stamp,
                frame_id: mount.parent.clone(),
            },
            child_frame_id: child.clone(),
            transform: Transform {
                translation: Vector3 { x, y, z },
                rotation: Quaternion {
                    x: qx,
                    y: qy,
                    z: qz,
                    w: qw,
                },
            },
        })
        .collect();
    TFMessage { transforms }
}

/// A leaving DDS writer takes its unacknowledged samples with it: the last answers get
/// this long to reach (and be repaired for) reliable subscribers.
fn linger() {
    std::thread::sleep(Duration::from_millis(500));
}

fn send<M: Serialize>(shared: &Shared, p: &Writer<M>, m: M) {
    if let Err(e) = p.write(m, Some(rustdds::Timestamp::now())) {
        warn!("DDS publish failed: {e}");
        lock(shared).report.dds_errors += 1;
    }
}

/// The answering stage for proposals: boxes as `vision_msgs/Detection3DArray` and as
/// `visualization_msgs/MarkerArray` cubes, in the ground-aligned frame of the mount, or
/// in each cloud's own frame.
struct DetectionsOut {
    detections: Writer<Detection3DArray>,
    markers: Writer<MarkerArray>,
    shared: Shared,
    /// Boxes in the cloud's frame: the ground-aligned frame in the sensor's (the mount,
    /// inverted). `None`: boxes in [`GROUND_FRAME`], which the mount on `/tf_static` places.
    sensor_from_ground: Option<Isometry>,
}

/// The markers' namespace.
const MARKER_NS: &str = "groundwork_proposals";

impl DetectionsOut {
    /// The frame of the scan `h` answers (the latest one seen if it has gone).
    fn cloud_frame(&self, h: &ProposalsHeader) -> String {
        let s = lock(&self.shared);
        s.frames
            .iter()
            .rev()
            .find(|(e, q, _)| *e == h.producer_epoch && *q == h.scan_sequence)
            .or(s.frames.back())
            .map_or_else(|| SENSOR_FRAME.to_string(), |f| f.2.clone())
    }

    fn answer(&self, h: &ProposalsHeader) {
        let frame_id = match self.sensor_from_ground {
            Some(_) => self.cloud_frame(h),
            None => GROUND_FRAME.into(),
        };
        let (detections, markers) = detection_messages(h, frame_id, self.sensor_from_ground);
        send(&self.shared, &self.detections, detections);
        send(&self.shared, &self.markers, markers);
        lock(&self.shared).report.detections += 1;
    }
}

/// A scan's proposals as `vision_msgs/Detection3DArray` and as `MarkerArray` cubes (the
/// last scan's deleted first) in `frame_id`: the ground-aligned frame, or with
/// `sensor_from_ground` the cloud's own.
fn detection_messages(
    h: &ProposalsHeader,
    frame_id: String,
    sensor_from_ground: Option<Isometry>,
) -> (Detection3DArray, MarkerArray) {
    let header = Header {
        stamp: Time::from_ns(h.sensor_timestamp_ns),
        frame_id,
    };
    let n = (h.proposal_count as usize).min(h.records.len());
    let boxes: Vec<(&ProposalRecord, Pose, Vector3)> = h.records[..n]
        .iter()
        .map(|r| {
            let ([x, y, z], [qx, qy, qz, qw]) = match sensor_from_ground {
                None => (r.box_center(), r.box_rotation()),
                Some(m) => {
                    // A box is always finite (the detector's checks); the identity
                    // would only stand in for one that is not.
                    let in_ground = crate::pose::pose_of(r.box_center(), r.box_rotation())
                        .unwrap_or_else(|_| Isometry::identity());
                    let p = m * in_ground;
                    let (t, q) = (p.translation.vector, p.rotation.quaternion().coords);
                    ([t.x, t.y, t.z], [q.x, q.y, q.z, q.w])
                }
            };
            let pose = Pose {
                position: Vector3 { x, y, z },
                orientation: Quaternion {
                    x: qx,
                    y: qy,
                    z: qz,
                    w: qw,
                },
            };
            let [x, y, z] = r.box_size();
            let size = Vector3 { x, y, z };
            (r, pose, size)
        })
        .collect();
    let detections = boxes
        .iter()
        .map(|&(r, pose, size)| Detection3D {
            header: header.clone(),
            results: vec![ObjectHypothesisWithPose {
                hypothesis: ObjectHypothesis {
                    class_id: ProposalFlags(r.flags).class_name(),
                    score: 1.0,
                },
                pose: PoseWithCovariance {
                    pose,
                    covariance: Covariance([0.0; 36]),
                },
            }],
            bbox: BoundingBox3D { center: pose, size },
            id: r.id.to_string(),
        })
        .collect();
    let detections = Detection3DArray {
        header: header.clone(),
        detections,
    };
    // The last scan's boxes go, this scan's come.
    let mut markers = vec![Marker::new(
        header.clone(),
        MARKER_NS,
        0,
        Marker::CUBE,
        Marker::DELETE_ALL,
    )];
    markers.extend(boxes.iter().map(|&(r, pose, size)| {
        let mut m = Marker::new(
            header.clone(),
            MARKER_NS,
            r.id as i32,
            Marker::CUBE,
            Marker::ADD,
        );
        m.pose = pose;
        m.scale = size;
        // Object-like boxes green, flagged ones (walls, trees, ...) faint grey.
        m.color = if r.flags == 0 {
            ColorRGBA {
                r: 0.2,
                g: 0.85,
                b: 0.3,
                a: 0.5,
            }
        } else {
            ColorRGBA {
                r: 0.6,
                g: 0.6,
                b: 0.6,
                a: 0.25,
            }
        };
        m
    }));
    (detections, MarkerArray { markers })
}

impl Stage for DetectionsOut {
    const NAME: &'static str = "ros2-detections";
    const WIRING: Wiring = Wiring {
        wakes_on: Some(Topic::Proposals),
        reads: &[],
        publishes: None,
        parallel: false,
        unique: true,
    };
    type Report = ();

    fn process(&mut self, input: Input<'_>, _: u64, _: &mut Outbox) -> anyhow::Result<()> {
        if let Input::Proposals(h, _) = input {
            self.answer(h);
        }
        Ok(())
    }

    fn done(&self) -> bool {
        let s = lock(&self.shared);
        s.answers_stopped || s.input_stopped
    }

    fn log_state(&self) {}

    fn stop(self, rest: &Inputs) -> anyhow::Result<()> {
        rest.read(Topic::Proposals, |input, _| {
            if let Input::Proposals(h, _) = input {
                self.answer(h);
            }
            Ok(())
        })?;
        linger();
        Ok(())
    }
}

impl Stage for AnswersOut {
    const NAME: &'static str = "ros2-answers";
    const WIRING: Wiring = Wiring {
        wakes_on: Some(Topic::Masks),
        reads: &[],
        publishes: None,
        parallel: false,
        unique: true,
    };
    type Report = ();

    fn process(&mut self, input: Input<'_>, _: u64, _: &mut Outbox) -> anyhow::Result<()> {
        if let Input::Mask(h, probs) = input {
            self.answer(h, probs)?;
        }
        Ok(())
    }

    fn done(&self) -> bool {
        let s = lock(&self.shared);
        s.input_stopped || self.count.is_some_and(|n| s.report.answered >= n)
    }

    fn log_state(&self) {
        let s = lock(&self.shared);
        info!(
            answered = s.report.answered,
            bad_masks = s.report.bad_masks,
            unmatched = s.report.unmatched_masks,
            "ros2 output state"
        );
    }

    fn stop(mut self, rest: &Inputs) -> anyhow::Result<()> {
        // Masks already queued when the stop came are answered, not lost.
        rest.read(Topic::Masks, |input, _| match input {
            Input::Mask(h, probs) => self.answer(h, probs),
            _ => Ok(()),
        })?;
        linger();
        Ok(())
    }
}

/// A writer of `M` on a ROS topic.
type Writer<M> = no_key::DataWriterCdr<M>;

/// The bridge's DDS readers and writers of clouds and answers, each holding at most its
/// history depth of samples. They are made on the DDS participant rather than through
/// ros2-client, whose QoS profile cannot carry the resource limit that bounds them:
/// without one RustDDS keeps the last 64 samples of a topic it reads, and up to 8,192
/// samples a reliable subscriber has not acknowledged, whatever the depth (measured: 2 MB
/// clouds at 55 Hz held 185 MB in the reader; a subscriber that took nothing, 600 MB).
struct Bounded<'a> {
    participant: DomainParticipant,
    node: &'a NodeName,
}

impl Bounded<'_> {
    /// The topic `name` of type `ty`, and `qos` with its depth as the resource limit.
    fn topic(
        &self,
        name: &str,
        ty: &MessageTypeName,
        qos: &QosProfile,
    ) -> anyhow::Result<(rustdds::Topic, QosPolicies)> {
        let depth = match qos.history {
            qos::History::KeepLast { depth } => depth as i32,
            qos::History::KeepAll => anyhow::bail!("{name}: keep-all has no bound"),
        };
        let limits = QosPolicyBuilder::new()
            .resource_limits(policy::ResourceLimits {
                max_samples: depth,
                max_instances: 1,
                max_samples_per_instance: depth,
            })
            .build();
        let qos = QosPolicies::from(qos).modify_by(&limits);
        let topic = self
            .participant
            .create_topic(
                ros_name(name)?.to_dds_name("rt", self.node, ""),
                ty.dds_msg_type(),
                &qos,
                TopicKind::NoKey,
            )
            .with_context(|| format!("topic {name}"))?;
        Ok((topic, qos))
    }

    fn reader<M: 'static>(
        &self,
        name: &str,
        ty: &MessageTypeName,
        qos: &QosProfile,
    ) -> anyhow::Result<no_key::SimpleDataReaderCdr<M>> {
        let (topic, qos) = self.topic(name, ty, qos)?;
        self.participant
            .create_subscriber(&qos)
            .with_context(|| format!("subscriber to {name}"))?
            .create_simple_datareader_no_key(&topic, Some(qos))
            .with_context(|| format!("subscription to {name}"))
    }

    fn writer<M: Serialize>(
        &self,
        name: &str,
        ty: &MessageTypeName,
        qos: &QosProfile,
    ) -> anyhow::Result<Writer<M>> {
        let (topic, qos) = self.topic(name, ty, qos)?;
        self.participant
            .create_publisher(&qos)
            .with_context(|| format!("publisher on {name}"))?
            .create_datawriter_no_key(&topic, Some(qos))
            .with_context(|| format!("publisher on {name}"))
    }
}

/// The QoS profile of a subscription or publication.
pub fn profile(q: Qos) -> QosProfile {
    let base = QosProfile::subscription_default().history(qos::History::KeepLast { depth: 5 });
    match q {
        Qos::SensorData => base.reliability_best_effort(),
        Qos::Reliable => base.reliability_reliable(qos::WhenFull::DEFAULT),
    }
}

/// Runs the bridge until `count` clouds are answered or a termination signal arrives.
pub fn run(cfg: &ServiceConfig, opts: &BridgeOptions) -> anyhow::Result<BridgeReport> {
    let context = Context::from_domain_participant(
        ros2_client::dds::rustdds::DomainParticipant::new(opts.domain_id)
            .with_context(|| format!("cannot join DDS domain {}", opts.domain_id))?,
    )
    .context("ROS 2 context")?;
    let node_name = NodeName::new(&opts.namespace, &opts.node)
        .map_err(|e| anyhow::anyhow!("node {:?}: {e:?}", opts.node))?;
    let mut node: Node = context
        .new_node(node_name.clone(), NodeOptions::new().enable_rosout(false))
        .context("ROS 2 node")?;
    let in_qos = profile(opts.qos);
    let dds = Bounded {
        participant: context.domain_participant(),
        node: &node_name,
    };
    let mut subscription = dds.reader::<PointCloud2>(&opts.input_topic, &cloud_type(), &in_qos)?;
    // Outputs are reliable (which best-effort subscribers match too), keep last 5.
    let out_qos = profile(Qos::Reliable);
    let base = format!("{}/{}", opts.namespace.trim_end_matches('/'), opts.node);
    let cloud =
        |leaf: &str| dds.writer::<PointCloud2>(&format!("{base}/{leaf}"), &cloud_type(), &out_qos);
    let points = cloud("points")?;
    let nonground = cloud("nonground")?;
    let ground = opts.publish_ground.then(|| cloud("ground")).transpose()?;
    let detections = dds.writer::<Detection3DArray>(
        &format!("{base}/detections"),
        &MessageTypeName::new("vision_msgs", "Detection3DArray"),
        &out_qos,
    )?;
    let markers = dds.writer::<MarkerArray>(
        &format!("{base}/markers"),
        &MessageTypeName::new("visualization_msgs", "MarkerArray"),
        &out_qos,
    )?;
    // tf2's static broadcaster QoS: reliable, transient local, the last message.
    let tf_qos = profile(Qos::Reliable)
        .durability(qos::Durability::TransientLocal)
        .history(qos::History::KeepLast { depth: 1 });
    // With a TF tree to read, the vehicle's tree places the sensor: publishing the mount
    // would give the cloud frame a second parent.
    let reads_tf = opts.tf_fixed_frame.is_some();
    let tf = match &opts.mount {
        Some(m) if !reads_tf => Some((
            dds.writer::<TFMessage>(
                "/tf_static",
                &MessageTypeName::new("tf2_msgs", "TFMessage"),
                &tf_qos,
            )?,
            m.clone(),
            Vec::new(),
        )),
        _ => None,
    };
    let poll = Poll::new().context("poll")?;
    poll.registry()
        .register(&mut subscription, Token(0), Interest::READABLE)
        .context("register the DDS subscription")?;
    let mount_pose = opts.mount.as_ref().map(|m| {
        let ([x, y, z], [qx, qy, qz, qw]) = (m.translation, m.rotation);
        Isometry::from_parts(
            nalgebra::Translation3::new(x, y, z),
            nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(qw, qx, qy, qz)),
        )
    });
    let poses = match (&opts.odometry_topic, &opts.tf_fixed_frame) {
        (Some(_), Some(_)) => anyhow::bail!("poses come from odometry or from TF, not both"),
        (None, Some(fixed)) => {
            let tf_type = || MessageTypeName::new("tf2_msgs", "TFMessage");
            // tf2's listeners: reliable, the last 100 of /tf; /tf_static transient local
            // (a static broadcaster sends once, to those present and those who come later).
            let moving_qos = profile(Qos::Reliable).history(qos::History::KeepLast { depth: 100 });
            let static_qos = moving_qos
                .clone()
                .durability(qos::Durability::TransientLocal);
            let mut subscribe = |name: &str, q: &QosProfile, token: usize| {
                let topic = node
                    .create_topic(&ros_name(name)?, tf_type(), q)
                    .with_context(|| format!("topic {name}"))?;
                let mut sub = node
                    .create_subscription::<TFMessage>(&topic, Some(q.clone()))
                    .with_context(|| format!("subscription to {name}"))?;
                poll.registry()
                    .register(&mut sub, Token(token), Interest::READABLE)
                    .with_context(|| format!("register the subscription to {name}"))?;
                anyhow::Ok(sub)
            };
            Some(PoseSource::Tf {
                moving: subscribe("/tf", &moving_qos, 1)?,
                statics: subscribe("/tf_static", &static_qos, 2)?,
                tree: TfTree::default(),
                fixed: fixed.clone(),
            })
        }
        (Some(name), None) => {
            let topic = node
                .create_topic(
                    &ros_name(name)?,
                    MessageTypeName::new("nav_msgs", "Odometry"),
                    &in_qos,
                )
                .context("odometry topic")?;
            let mut subscription = node
                // Odometry comes at up to 100 Hz: room for a few polls' worth.
                .create_subscription::<Odometry>(
                    &topic,
                    Some(in_qos.clone().history(qos::History::KeepLast { depth: 50 })),
                )
                .context("odometry subscription")?;
            poll.registry()
                .register(&mut subscription, Token(1), Interest::READABLE)
                .context("register the odometry subscription")?;
            Some(PoseSource::Odometry {
                subscription,
                track: OdomTrack::new(mount_pose),
            })
        }
        (None, None) => None,
    };
    info!(
        domain = opts.domain_id,
        input = %opts.input_topic,
        qos = ?opts.qos,
        outputs = %format!("{base}/{{points,nonground{}}}", if opts.publish_ground { ",ground" } else { "" }),
        "ROS 2 bridge ready"
    );
    let shared: Shared = Arc::default();
    let answers = AnswersOut {
        tf,
        points,
        nonground,
        ground,
        shared: Arc::clone(&shared),
        threshold: opts.ground_threshold,
        max_points: cfg.max_points,
        count: opts.count,
    };
    let boxes = DetectionsOut {
        detections,
        markers,
        shared: Arc::clone(&shared),
        sensor_from_ground: if reads_tf {
            Some(mount_pose.unwrap_or_else(Isometry::identity).inverse())
        } else {
            None
        },
    };
    let boxes_cfg = cfg.clone();
    let boxing = std::thread::Builder::new()
        .name("ros2-detections".into())
        .spawn(move || stage::run(&boxes_cfg, || Ok(boxes)))
        .context("start the detections thread")?;
    let out_cfg = cfg.clone();
    let answering = std::thread::Builder::new()
        .name("ros2-answers".into())
        .spawn(move || {
            let shared = Arc::clone(&answers.shared);
            let r = stage::run(&out_cfg, || Ok(answers));
            lock(&shared).answers_stopped = true;
            r
        })
        .context("start the answering thread")?;
    let clouds = CloudsIn {
        subscription,
        poll,
        events: Events::with_capacity(8),
        shared: Arc::clone(&shared),
        topic: opts.input_topic.clone(),
        epoch: new_epoch(),
        sequence: 0,
        max_points: cfg.max_points,
        answers_wanted: opts.count,
        wait: Duration::from_millis(50),
        poses,
        keep_frames: reads_tf,
        gaps: SequenceGaps::new(),
        resumed: Arc::default(),
    };
    let input_result = stage::run(cfg, || Ok(clouds));
    lock(&shared).input_stopped = true;
    let output_result = answering
        .join()
        .map_err(|_| anyhow::anyhow!("the answering thread panicked"))?;
    let boxes_result = boxing
        .join()
        .map_err(|_| anyhow::anyhow!("the detections thread panicked"))?;
    input_result?;
    output_result?;
    boxes_result?;
    let report = lock(&shared).report.clone();
    info!(
        received = report.received,
        published = report.published,
        rejected = report.rejected,
        answered = report.answered,
        detections = report.detections,
        bad_masks = report.bad_masks,
        unmatched = report.unmatched_masks,
        dropped = report.dropped,
        dds_errors = report.dds_errors,
        lost_before_received = report.lost_before_received,
        odometry = report.odometry,
        odometry_rejected = report.odometry_rejected,
        transforms = report.transforms,
        transforms_rejected = report.transforms_rejected,
        no_pose = report.no_pose,
        "ROS 2 bridge stopped"
    );
    Ok(report)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

    use super::*;
    use groundwork_io::pointcloud2::{decode_cloud, probabilities};

    /// A cloud of `n` records as a driver sends it, record 2 a placeholder (NaN: no return),
    /// held as the input stage holds it (the placeholders searched).
    fn held(sequence: u64, n: usize) -> Held {
        let field = |name: &str, offset| groundwork_io::pointcloud2::PointField {
            name: name.into(),
            offset,
            datatype: 7, // FLOAT32
            count: 1,
        };
        let data: Vec<u8> = (0..n)
            .flat_map(|i| {
                let v = if i == 2 { f32::NAN } else { i as f32 };
                [v, 1.0, -1.7 + 0.1 * v]
            })
            .flat_map(f32::to_le_bytes)
            .collect();
        let cloud = PointCloud2 {
            header: Header {
                stamp: Time::from_ns(1_700_000_000_000_000_000),
                frame_id: "lidar".into(),
            },
            height: 1,
            width: n as u32,
            fields: vec![field("x", 0), field("y", 4), field("z", 8)],
            is_bigendian: false,
            point_step: 12,
            row_step: 12 * n as u32,
            data,
            is_dense: false,
        };
        let view = cloud.view();
        let points = CloudPoints::new(Path::new("test"), &view, 1000).unwrap();
        let (scan, count) = (points.records_map(), points.len());
        Held {
            epoch: 7,
            sequence,
            cloud: Arc::new(cloud),
            scan,
            points: count,
        }
    }

    #[test]
    fn in_flight_clouds_are_bounded_and_an_answer_drops_the_older_ones() {
        let mut f = InFlight::default();
        for q in 0..MAX_IN_FLIGHT as u64 + 3 {
            f.hold(held(q, 4));
        }
        assert_eq!(f.clouds.len(), MAX_IN_FLIGHT);
        assert_eq!(f.report.dropped, 3, "the three oldest, to keep the bound");
        // Scan 5 answered: 3 and 4 were skipped by the segmenter and never will be.
        assert_eq!(f.answered(7, 5).map(|h| h.sequence), Some(5));
        assert_eq!(f.report.dropped, 5);
        assert_eq!(f.clouds.front().map(|h| h.sequence), Some(6));
        // Another producer run's scan, or one answered already: unmatched, nothing taken.
        assert!(f.answered(8, 6).is_none() && f.answered(7, 5).is_none());
        assert_eq!(f.report.unmatched_masks, 2);
        assert_eq!(f.clouds.len(), MAX_IN_FLIGHT - 3);
    }

    #[test]
    fn an_answer_keeps_every_record_and_splits_the_points_by_the_threshold() {
        let h = held(0, 6);
        assert_eq!(h.points, 5, "the placeholder is no point");
        let probs = [0.9, 0.1, 0.7, 0.2, 0.5];
        let a = answer_clouds(&h, &probs, 0.5, 1000, true).unwrap();
        let label = Path::new("answer");
        // Every record, in order, with its point's probability; 0 for the placeholder.
        let with = probabilities(label, &a.points.view(), 1000).unwrap();
        assert_eq!(with, vec![0.9, 0.1, 0.0, 0.7, 0.2, 0.5]);
        assert_eq!(a.points.header, h.cloud.header);
        let xs = |c: &PointCloud2| -> Vec<f32> {
            let scan = decode_cloud(label, &c.view(), 1000).unwrap();
            scan.points.iter().map(|p| p.x).collect()
        };
        // Records 0, 3, 5 (at or above 0.5) are ground; 1 and 4 are not; 2 neither.
        assert_eq!(xs(a.ground.as_ref().unwrap()), vec![0.0, 3.0, 5.0]);
        assert_eq!(xs(&a.nonground), vec![1.0, 4.0]);
        assert!(a.nonground.is_dense && a.ground.as_ref().unwrap().is_dense);
        assert!(
            answer_clouds(&h, &probs, 0.5, 1000, false)
                .unwrap()
                .ground
                .is_none()
        );
    }

    #[test]
    fn the_static_transform_places_every_frame_seen_on_the_mount() {
        let mount = StaticTransform {
            parent: "base_footprint".into(),
            translation: [0.0, 0.0, 1.73],
            rotation: [0.0, 0.0, 0.0, 1.0],
        };
        let header = Header {
            stamp: Time::from_ns(5_000_000_001),
            frame_id: "lidar_top".into(),
        };
        let frames = ["lidar_front".to_string(), "lidar_top".to_string()];
        let tf = static_transforms(&mount, &frames, &header);
        let children: Vec<&str> = tf
            .transforms
            .iter()
            .map(|t| t.child_frame_id.as_str())
            .collect();
        assert_eq!(children, ["lidar_front", "lidar_top"]);
        for t in &tf.transforms {
            assert_eq!(t.header.frame_id, "base_footprint");
            assert_eq!(t.header.stamp, header.stamp);
            assert_eq!(t.transform.translation.z, 1.73);
        }
    }

    #[test]
    fn proposals_become_detections_and_markers_in_the_frame_asked() {
        let mut h = ProposalsHeader {
            proposal_count: 2,
            sensor_timestamp_ns: 3_000_000_000,
            ..ProposalsHeader::default()
        };
        h.records[0] = ProposalRecord {
            id: 1,
            center: [5.0, 1.0],
            length: 4.0,
            width: 1.8,
            height: 1.5,
            ..ProposalRecord::default()
        };
        h.records[1] = ProposalRecord {
            id: 2,
            flags: 1,
            center: [9.0, -2.0],
            length: 1.0,
            width: 1.0,
            height: 3.0,
            ..ProposalRecord::default()
        };
        // In the ground-aligned frame: the boxes as the detector gave them.
        let (d, m) = detection_messages(&h, GROUND_FRAME.into(), None);
        assert_eq!(d.header.frame_id, GROUND_FRAME);
        assert_eq!(d.detections.len(), 2);
        assert_eq!(d.detections[0].id, "1");
        assert_eq!(d.detections[0].bbox.size.x, 4.0);
        assert_eq!(d.detections[0].bbox.center.position.x, 5.0);
        // The last scan's markers deleted first, then one cube per box; flagged ones faint.
        assert_eq!(m.markers.len(), 3);
        assert_eq!(m.markers[0].action, Marker::DELETE_ALL);
        assert!(m.markers[2].color.a < m.markers[1].color.a);
        // In the sensor's frame 1.73 m above the ground: every box 1.73 m higher.
        let up = Isometry::from_parts(
            nalgebra::Translation3::new(0.0, 0.0, 1.73),
            nalgebra::UnitQuaternion::identity(),
        );
        let (s, _) = detection_messages(&h, "lidar".into(), Some(up));
        assert_eq!(s.header.frame_id, "lidar");
        let dz = s.detections[1].bbox.center.position.z - d.detections[1].bbox.center.position.z;
        assert!((dz - 1.73).abs() < 1e-9, "{dz}");
    }

    #[test]
    fn gaps_in_each_publishers_sequence_are_the_samples_missed() {
        let mut g = SequenceGaps::new();
        assert_eq!(g.see('a', 1), 0, "a publisher's first sample");
        assert_eq!(g.see('a', 2), 0);
        assert_eq!(g.see('a', 6), 3, "3, 4 and 5 never came");
        assert_eq!(g.see('b', 40), 0, "another publisher, its own numbers");
        assert_eq!(g.see('a', 5), 0, "late: counted as missed already");
        assert_eq!(g.see('a', 6), 0, "repeated");
        assert_eq!(g.see('a', 7), 0);
        assert_eq!(g.see('b', 42), 1);
    }
}
