//! The live view stage: a Foxglove WebSocket server (Foxglove's own SDK) fed by the
//! pipeline's topics, so that the Foxglove app (desktop or web, or its open-source fork
//! Lichtblick) connects to `ws://host:8765` and shows the vehicle's ground live.
//!
//! Channels, each only encoded while some viewer subscribes to it:
//! - [`POINTS_TOPIC`]: each segmented scan (`foxglove.PointCloud` in the scan's frame) with
//!   its `ground_probability` and a colour from it (`red`, `green`, `blue`, `alpha`, which
//!   the app picks by default: green ground, orange non-ground, blends where unsure);
//! - [`BOXES_TOPIC`]: the proposals as boxes (`foxglove.SceneUpdate`, in `base_footprint`);
//! - [`TF_TOPIC`]: the mount, the scan frame in `base_footprint` (`foxglove.FrameTransforms`);
//! - [`STATS_TOPIC`]: per scan, the mask's figures and the view's counters (JSON).
//!
//! A viewer never slows the pipeline: this stage is one more subscriber, whose queue loses
//! its oldest messages when it falls behind (counted: `missed`); the server sends lossily
//! (a slow client loses its oldest queued messages, at most `backlog` per client, which the
//! SDK logs), and nothing is encoded for a channel nobody watches.

use std::collections::VecDeque;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::Context as _;
use foxglove::bytes::Bytes;
use foxglove::messages::packed_element_field::NumericType;
use foxglove::messages::{
    FrameTransform, FrameTransforms, PackedElementField, PointCloud, Pose, Quaternion, SceneUpdate,
    Vector3,
};
use foxglove::{Channel, ChannelBuilder, Context, PartialMetadata, RawChannel, Schema};
use groundwork_io::transform::{SENSOR_FRAME, StaticTransform};
use groundwork_msg::{
    MaskHeader, MaskStatus, ProposalsHeader, ScanHeader, ScanPoint, wall_clock_ns,
};
use groundwork_service::config::ServiceConfig;
use groundwork_service::scene::{self, timestamp};
use groundwork_service::stage::{self, Input, Inputs, Outbox, Stage, Topic, Wiring};
use serde::Serialize;
use tracing::info;

/// The scans with their ground probability.
pub const POINTS_TOPIC: &str = "/groundwork/points";
/// The proposals as boxes.
pub const BOXES_TOPIC: &str = "/groundwork/proposals";
/// The mount.
pub const TF_TOPIC: &str = "/tf";
/// Per scan, the mask's figures and the view's counters.
pub const STATS_TOPIC: &str = "/groundwork/stats";

/// Scans held for the masks that answer them: a mask comes a few milliseconds after its
/// scan, so a handful is plenty; older ones go.
const HELD_SCANS: usize = 8;

/// Bytes per point in [`POINTS_TOPIC`]: x, y, z, intensity, ground_probability (f32),
/// then red, green, blue, alpha (u8).
const POINT_STRIDE: usize = 24;

/// What the view is asked to do.
#[derive(Debug, Clone)]
pub struct ViewOptions {
    /// Where the server listens: `host:port` (port 0: any free port).
    pub addr: String,
    /// The sensor's mount, shown as the scan frame's transform; `None`: no transform.
    pub mount: Option<StaticTransform>,
    /// The segmenter's ground threshold (the colours' midpoint, shown with the counters).
    pub ground_threshold: f32,
    /// Messages queued per client before the oldest are dropped (a scan is a few MB).
    pub backlog: usize,
    /// Stop when set (a view running as a thread beside other stages).
    pub stop: Option<Arc<AtomicBool>>,
}

/// What the view did.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct ViewReport {
    /// Masks read.
    pub masks: u64,
    /// Scans sent to viewers with their probabilities.
    pub shown: u64,
    /// Masks this stage never read: it fell behind and its queue dropped them.
    pub missed: u64,
    /// Masks read while a viewer watched whose scan was no longer held (or did not fit).
    pub unmatched: u64,
    /// Proposal messages read.
    pub proposals: u64,
    /// Viewers connected at the end.
    pub clients: usize,
}

/// Splits `host:port` (IPv6 hosts in brackets).
pub fn parse_addr(addr: &str) -> anyhow::Result<(String, u16)> {
    let (host, port) = addr
        .rsplit_once(':')
        .with_context(|| format!("view address {addr:?}: expected host:port"))?;
    let port = port
        .parse()
        .with_context(|| format!("view address {addr:?}: {port:?} is not a port"))?;
    let host = host.trim_start_matches('[').trim_end_matches(']');
    anyhow::ensure!(!host.is_empty(), "view address {addr:?}: no host");
    Ok((host.to_string(), port))
}

/// Runs the view until it is stopped (a signal, or `opts.stop`).
pub fn run(cfg: &ServiceConfig, opts: ViewOptions) -> anyhow::Result<ViewReport> {
    stage::run(cfg, || View::start(opts))
}

/// A scan held until its mask comes.
struct HeldScan {
    producer_epoch: u64,
    sequence: u64,
    points: Vec<ScanPoint>,
}

struct View {
    server: Option<foxglove::WebSocketServerHandle>,
    points: Channel<PointCloud>,
    boxes: Channel<SceneUpdate>,
    tf: Channel<FrameTransforms>,
    stats: Arc<RawChannel>,
    held: VecDeque<HeldScan>,
    /// The last mask read: (segmenter epoch, mask sequence).
    last_mask: Option<(u64, u64)>,
    report: ViewReport,
    opts: ViewOptions,
    /// Keeps the channels' context alive.
    _context: Arc<Context>,
}

impl std::fmt::Debug for View {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("View")
            .field("addr", &self.opts.addr)
            .field("report", &self.report)
            .finish()
    }
}

/// The JSON schema of [`STATS_TOPIC`]'s messages.
const STATS_SCHEMA: &str = r#"{
  "type": "object",
  "properties": {
    "stamp_ns": {"type": "integer"},
    "frame_id": {"type": "string"},
    "source_index": {"type": "integer"},
    "scan_sequence": {"type": "integer"},
    "points": {"type": "integer"},
    "ground_points": {"type": "integer"},
    "status": {"type": "string"},
    "fit_us": {"type": "integer"},
    "query_us": {"type": "integer"},
    "frames_queried": {"type": "integer"},
    "scan_to_mask_ms": {"type": "number"},
    "ground_threshold": {"type": "number"},
    "masks": {"type": "integer"},
    "shown": {"type": "integer"},
    "missed": {"type": "integer"},
    "unmatched": {"type": "integer"},
    "proposals": {"type": "integer"},
    "clients": {"type": "integer"}
  }
}"#;

/// One [`STATS_TOPIC`] message.
#[derive(Serialize)]
struct Stats<'a> {
    stamp_ns: u64,
    frame_id: &'a str,
    source_index: u64,
    scan_sequence: u64,
    points: u32,
    ground_points: u32,
    status: &'static str,
    fit_us: u32,
    query_us: u32,
    frames_queried: u32,
    /// From the scan's publication to its mask's.
    scan_to_mask_ms: f64,
    ground_threshold: f32,
    #[serde(flatten)]
    counters: &'a ViewReport,
}

impl View {
    fn start(opts: ViewOptions) -> anyhow::Result<Self> {
        anyhow::ensure!(opts.backlog > 0, "the view's backlog must be at least 1");
        let (host, port) = parse_addr(&opts.addr)?;
        let context = Context::new();
        let points = context.channel_builder(POINTS_TOPIC).build::<PointCloud>();
        let boxes = context.channel_builder(BOXES_TOPIC).build::<SceneUpdate>();
        let tf = context.channel_builder(TF_TOPIC).build::<FrameTransforms>();
        let stats = ChannelBuilder::new(STATS_TOPIC)
            .context(&context)
            .message_encoding("json")
            .schema(Schema::new(
                "groundwork.ViewStats",
                "jsonschema",
                STATS_SCHEMA.as_bytes(),
            ))
            .build_raw()
            .context("the stats channel")?;
        let server = context
            .websocket_server()
            .name("groundwork")
            .bind(&host, port)
            .message_backlog_size(opts.backlog)
            .start_blocking()
            .with_context(|| format!("cannot serve the view on {}", opts.addr))?;
        info!(
            url = %format!("ws://{host}:{}", server.port()),
            "live view: connect Foxglove to this address"
        );
        Ok(Self {
            server: Some(server),
            points,
            boxes,
            tf,
            stats,
            held: VecDeque::with_capacity(HELD_SCANS),
            last_mask: None,
            report: ViewReport::default(),
            opts,
            _context: context,
        })
    }

    fn on_scan(&mut self, h: &ScanHeader, points: &[ScanPoint]) {
        // A copy only for a viewer that watches the points.
        if !self.points.has_sinks() {
            self.held.clear();
            return;
        }
        if self.held.len() == HELD_SCANS {
            self.held.pop_front();
        }
        self.held.push_back(HeldScan {
            producer_epoch: h.producer_epoch,
            sequence: h.sequence,
            points: points.to_vec(),
        });
    }

    fn on_mask(&mut self, h: &MaskHeader, probabilities: &[f32]) {
        self.report.masks += 1;
        // Masks are numbered per segmenter run: a gap is masks our queue dropped.
        if let Some((epoch, last)) = self.last_mask
            && epoch == h.segmenter_epoch
            && h.mask_sequence > last + 1
        {
            self.report.missed += h.mask_sequence - last - 1;
        }
        self.last_mask = Some((h.segmenter_epoch, h.mask_sequence));
        let stamp = stamp_or_now(h.sensor_timestamp_ns);
        let frame = h.frame_id.get().unwrap_or(SENSOR_FRAME);
        if self.points.has_sinks() {
            // Scans older than the one answered will not be answered any more.
            let at = self.held.iter().position(|s| {
                s.producer_epoch == h.producer_epoch && s.sequence == h.scan_sequence
            });
            let scan = at.and_then(|i| {
                self.held.drain(..i);
                self.held.pop_front()
            });
            match scan {
                Some(s) if h.status == MaskStatus::OK && s.points.len() == probabilities.len() => {
                    self.points.log_with_time(
                        &cloud(
                            &s.points,
                            probabilities,
                            self.opts.ground_threshold,
                            stamp,
                            frame,
                        ),
                        stamp,
                    );
                    self.report.shown += 1;
                }
                _ => self.report.unmatched += 1,
            }
        }
        if let Some(m) = &self.opts.mount
            && self.tf.has_sinks()
        {
            // Every scan: a viewer that connects later gets the transform at once.
            self.tf.log_with_time(&transforms(m, frame, stamp), stamp);
        }
        if self.stats.has_sinks() {
            self.report.clients = self.server.as_ref().map_or(0, |s| s.client_count());
            let scan_to_mask_ms = h
                .stamps
                .segmenter_published_ns
                .saturating_sub(h.stamps.published_ns) as f64
                * 1e-6;
            let stats = Stats {
                stamp_ns: stamp,
                frame_id: frame,
                source_index: h.source_index,
                scan_sequence: h.scan_sequence,
                points: h.point_count,
                ground_points: h.ground_points,
                status: h.status.name(),
                fit_us: h.fit_us,
                query_us: h.query_us,
                frames_queried: h.frames_queried,
                scan_to_mask_ms,
                ground_threshold: self.opts.ground_threshold,
                counters: &self.report,
            };
            // Serializing plain numbers and strings cannot fail.
            if let Ok(json) = serde_json::to_vec(&stats) {
                self.stats.log_with_meta(
                    &json,
                    PartialMetadata {
                        log_time: Some(stamp),
                    },
                );
            }
        }
    }

    fn on_proposals(&mut self, h: &ProposalsHeader) {
        self.report.proposals += 1;
        if self.boxes.has_sinks() {
            let stamp = stamp_or_now(h.sensor_timestamp_ns);
            self.boxes.log_with_time(&scene::proposals(h, stamp), stamp);
        }
    }
}

impl Stage for View {
    const NAME: &'static str = "view";
    // Woken by masks like the consumer; the scans they answer and the proposals that came
    // since are read just before.
    const WIRING: Wiring = Wiring {
        wakes_on: Some(Topic::Masks),
        reads: &[Topic::Scans, Topic::Proposals],
        publishes: None,
        parallel: false,
        unique: false,
    };
    type Report = ViewReport;

    fn process(&mut self, input: Input<'_>, _: u64, _: &mut Outbox) -> anyhow::Result<()> {
        match input {
            Input::Scan(h, p) => self.on_scan(h, p),
            Input::Mask(h, p) => self.on_mask(h, p),
            Input::Proposals(h, _) => self.on_proposals(h),
            Input::Tick => {}
        }
        Ok(())
    }

    fn done(&self) -> bool {
        self.opts
            .stop
            .as_ref()
            .is_some_and(|s| s.load(Ordering::Relaxed))
    }

    fn log_state(&self) {
        self.log_counters("view");
    }

    fn stop(mut self, _: &Inputs) -> anyhow::Result<ViewReport> {
        if let Some(server) = self.server.take() {
            self.report.clients = server.client_count();
            drop(server.stop());
        }
        self.log_counters("view stopped");
        Ok(self.report.clone())
    }
}

impl View {
    fn log_counters(&self, what: &str) {
        let r = &self.report;
        let clients = self.server.as_ref().map_or(r.clients, |s| s.client_count());
        info!(
            masks = r.masks,
            shown = r.shown,
            missed = r.missed,
            unmatched = r.unmatched,
            proposals = r.proposals,
            clients,
            "{what}"
        );
    }
}

/// A scan's stamp; none (0): now.
fn stamp_or_now(stamp_ns: u64) -> u64 {
    if stamp_ns > 0 {
        stamp_ns
    } else {
        wall_clock_ns()
    }
}

/// The colour of a probability: orange non-ground, green ground, blended where unsure
/// (a probability at the threshold is half-way).
fn colour(p: f32, threshold: f32) -> [u8; 4] {
    const NON_GROUND: [f32; 3] = [240.0, 110.0, 40.0];
    const GROUND: [f32; 3] = [60.0, 200.0, 80.0];
    let t = if p >= threshold {
        0.5 + 0.5 * (p - threshold) / (1.0 - threshold).max(f32::EPSILON)
    } else {
        0.5 * p / threshold.max(f32::EPSILON)
    };
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let mix = |i: usize| (NON_GROUND[i] + t * (GROUND[i] - NON_GROUND[i])).round() as u8;
    [mix(0), mix(1), mix(2), 255]
}

/// A scan and its mask as a `foxglove.PointCloud` (little-endian, [`POINT_STRIDE`] bytes
/// a point).
fn cloud(
    points: &[ScanPoint],
    probabilities: &[f32],
    threshold: f32,
    stamp: u64,
    frame: &str,
) -> PointCloud {
    let mut data = Vec::with_capacity(points.len() * POINT_STRIDE);
    for (p, &prob) in points.iter().zip(probabilities) {
        for v in [p.x, p.y, p.z, p.intensity, prob] {
            data.extend_from_slice(&v.to_le_bytes());
        }
        data.extend_from_slice(&colour(prob, threshold));
    }
    let field = |name: &str, offset: u32, t: NumericType| PackedElementField {
        name: name.into(),
        offset,
        r#type: t as i32,
    };
    PointCloud {
        timestamp: Some(timestamp(stamp)),
        frame_id: frame.into(),
        pose: Some(identity()),
        point_stride: POINT_STRIDE as u32,
        fields: vec![
            field("x", 0, NumericType::Float32),
            field("y", 4, NumericType::Float32),
            field("z", 8, NumericType::Float32),
            field("intensity", 12, NumericType::Float32),
            field("ground_probability", 16, NumericType::Float32),
            field("red", 20, NumericType::Uint8),
            field("green", 21, NumericType::Uint8),
            field("blue", 22, NumericType::Uint8),
            field("alpha", 23, NumericType::Uint8),
        ],
        data: Bytes::from(data),
    }
}

fn identity() -> Pose {
    Pose {
        position: Some(Vector3 {
            x: 0.0,
            y: 0.0,
            z: 0.0,
        }),
        orientation: Some(Quaternion {
            x: 0.0,
            y: 0.0,
            z: 0.0,
            w: 1.0,
        }),
    }
}

/// The mount: `frame` in the ground frame.
fn transforms(m: &StaticTransform, frame: &str, stamp: u64) -> FrameTransforms {
    let ([x, y, z], [qx, qy, qz, qw]) = (m.translation, m.rotation);
    FrameTransforms {
        transforms: vec![FrameTransform {
            timestamp: Some(timestamp(stamp)),
            parent_frame_id: m.parent.clone(),
            child_frame_id: frame.into(),
            translation: Some(Vector3 { x, y, z }),
            rotation: Some(Quaternion {
                x: qx,
                y: qy,
                z: qz,
                w: qw,
            }),
        }],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn addresses_split_into_host_and_port() {
        assert_eq!(
            parse_addr("127.0.0.1:8765").ok(),
            Some(("127.0.0.1".into(), 8765))
        );
        assert_eq!(parse_addr("[::1]:0").ok(), Some(("::1".into(), 0)));
        assert!(parse_addr("8765").is_err());
        assert!(parse_addr(":8765").is_err());
        assert!(parse_addr("host:99999").is_err());
    }

    #[test]
    fn colours_run_from_non_ground_through_the_threshold_to_ground() {
        let (lo, mid, hi) = (colour(0.0, 0.5), colour(0.5, 0.5), colour(1.0, 0.5));
        assert_eq!(lo, [240, 110, 40, 255]);
        assert_eq!(hi, [60, 200, 80, 255]);
        assert_eq!(mid, [150, 155, 60, 255]);
        // A threshold away from 0.5 still puts its own value half-way.
        assert_eq!(colour(0.8, 0.8), mid);
        assert_eq!(colour(f32::NAN, 0.5), lo);
    }

    #[test]
    fn a_cloud_carries_every_point_and_its_probability() {
        let points = [
            ScanPoint {
                x: 1.0,
                y: -2.0,
                z: 0.5,
                intensity: 0.25,
            },
            ScanPoint {
                x: 3.0,
                y: 4.0,
                z: -1.5,
                intensity: 0.0,
            },
        ];
        let c = cloud(
            &points,
            &[0.9, 0.1],
            0.5,
            1_500_000_000_000_000_001,
            "velodyne",
        );
        assert_eq!(c.data.len(), 2 * POINT_STRIDE);
        assert_eq!(c.frame_id, "velodyne");
        let ts = c.timestamp.unwrap_or_default();
        assert_eq!((ts.sec(), ts.nsec()), (1_500_000_000, 1));
        let f32_at = |o: usize| {
            let mut b = [0; 4];
            b.copy_from_slice(&c.data[o..o + 4]);
            f32::from_le_bytes(b)
        };
        assert_eq!(f32_at(POINT_STRIDE + 8), -1.5);
        assert_eq!(f32_at(16), 0.9);
        assert_eq!(f32_at(POINT_STRIDE + 16), 0.1);
        assert_eq!(&c.data[20..24], &colour(0.9, 0.5));
        let names: Vec<_> = c.fields.iter().map(|f| f.name.as_str()).collect();
        assert!(names.contains(&"ground_probability"));
        // Every field lies inside the stride.
        assert!(c.fields.iter().all(|f| (f.offset as usize) < POINT_STRIDE));
    }

    /// docs/foxglove-layout.json, the layout users import: a 3D panel following the
    /// ground frame that colours the view's cloud by a field it carries over the
    /// probabilities' range, the boxes shown, and plots of fields the stats schema has.
    #[test]
    fn the_shipped_foxglove_layout_names_what_the_view_serves() {
        let text = include_str!("../../../docs/foxglove-layout.json");
        let layout: serde_json::Value = serde_json::from_str(text).expect("the layout is JSON");
        let panels = layout["configById"].as_object().expect("configById");

        // The layout tree places only panels that are configured, and each once.
        fn leaves<'a>(node: &'a serde_json::Value, out: &mut Vec<&'a str>) {
            match node {
                serde_json::Value::String(id) => out.push(id),
                _ => {
                    leaves(&node["first"], out);
                    leaves(&node["second"], out);
                }
            }
        }
        let mut placed = Vec::new();
        leaves(&layout["layout"], &mut placed);
        placed.sort_unstable();
        let mut configured: Vec<&str> = panels.keys().map(String::as_str).collect();
        configured.sort_unstable();
        assert_eq!(placed, configured);

        let scene = &panels["3D!groundwork"];
        assert_eq!(scene["followTf"], groundwork_io::transform::GROUND_FRAME);
        let cloud_settings = &scene["topics"][POINTS_TOPIC];
        let points = [ScanPoint {
            x: 1.0,
            y: 0.0,
            z: 0.0,
            intensity: 0.0,
        }];
        let served = cloud(&points, &[1.0], 0.5, 0, "velodyne");
        let field = cloud_settings["colorField"].as_str().expect("colorField");
        assert!(served.fields.iter().any(|f| f.name == field), "{field}");
        assert_eq!(field, "ground_probability");
        assert_eq!(cloud_settings["colorMode"], "colormap");
        assert_eq!(
            (
                cloud_settings["minValue"].as_f64(),
                cloud_settings["maxValue"].as_f64()
            ),
            (Some(0.0), Some(1.0))
        );
        assert_eq!(scene["topics"][BOXES_TOPIC]["visible"], true);

        let schema: serde_json::Value = serde_json::from_str(STATS_SCHEMA).expect("schema");
        let mut plotted = 0;
        for (id, panel) in panels.iter().filter(|(id, _)| id.starts_with("Plot!")) {
            for path in panel["paths"].as_array().expect("paths") {
                let value = path["value"].as_str().expect("path value");
                let name = value
                    .strip_prefix(STATS_TOPIC)
                    .and_then(|rest| rest.strip_prefix('.'))
                    .unwrap_or_else(|| panic!("{id}: {value} is not a stats field"));
                assert!(
                    schema["properties"][name]["type"] == "integer"
                        || schema["properties"][name]["type"] == "number",
                    "{id}: {name} is not a numeric stats field"
                );
                plotted += 1;
            }
        }
        assert!(plotted >= 3);
    }
}
