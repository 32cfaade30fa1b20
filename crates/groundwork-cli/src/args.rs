//! The command line: every command's arguments (clap).

use std::path::PathBuf;

use clap::{Parser, Subcommand, ValueEnum};

use crate::methods::MethodArg;

#[derive(Parser, Debug)]
#[command(name = "groundwork", version, about = "GMM LiDAR ground segmentation")]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(clap::Args, Debug)]
pub struct Common {
    /// Sensor preset (`groundwork sensors` lists them). Default: the service
    /// configuration's `sensor`, else hdl64e.
    #[arg(long)]
    pub sensor: Option<String>,
    /// Configuration file (TOML) laid over the sensor preset: every field it gives
    /// replaces the preset's.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Multi-frame history length N_f (1 = single frame); overrides the config.
    #[arg(long)]
    pub frames: Option<u32>,
    /// KITTI poses.txt (default: <sequence>/poses.txt if present).
    #[arg(long)]
    pub poses: Option<PathBuf>,
    /// KITTI calib.txt with Tr (default: <sequence>/calib.txt if present).
    #[arg(long)]
    pub calib: Option<PathBuf>,
    /// PointCloud2 topic of MCAP recordings (default: the first point cloud topic).
    #[arg(long)]
    pub topic: Option<String>,
}

/// The sensor and configuration alone, for commands that take one scan or scans one at a
/// time (no history, no poses, no recordings).
#[derive(clap::Args, Debug)]
pub struct SensorArgs {
    /// Sensor preset (`groundwork sensors` lists them). Default: hdl64e.
    #[arg(long)]
    pub sensor: Option<String>,
    /// Configuration file (TOML) laid over the sensor preset: every field it gives
    /// replaces the preset's.
    #[arg(long)]
    pub config: Option<PathBuf>,
}

impl From<SensorArgs> for Common {
    fn from(s: SensorArgs) -> Self {
        Self {
            sensor: s.sensor,
            config: s.config,
            frames: None,
            poses: None,
            calib: None,
            topic: None,
        }
    }
}

#[derive(clap::Args, Debug, Clone)]
pub struct ServiceArgs {
    /// Service configuration (TOML). Default: the built-in config/service.toml.
    #[arg(long)]
    pub service: Option<PathBuf>,
    /// Service name prefix; overrides the configuration (run pipelines side by side).
    #[arg(long)]
    pub prefix: Option<String>,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Run producer, segmenter, detector and consumer as four processes (three with
    /// --no-detector) on the bundled scans or --data.
    /// Stops cleanly on Ctrl-C, or after --count scans.
    Pipeline(Box<PipelineArgs>),
    /// Stage: publish scans from a folder (looping) or synthetic scans.
    Producer(ProducerArgs),
    /// Stage: segment scans into masks, keeping the multi-frame history.
    Segmenter(SegmenterArgs),
    /// Stage: turn scans and masks into object proposals on <prefix>/proposals.
    Detector(DetectorArgs),
    /// Stage: read scans and masks, report latency, accuracy and counters.
    Consumer(ConsumerArgs),
    /// Stage: the ROS 2 bridge. Subscribes to a sensor_msgs/PointCloud2 topic over DDS
    /// (no ROS installation needed), publishes each cloud as a scan, and answers on
    /// /<node>/points (the cloud with a ground_probability field), /<node>/nonground and
    /// optionally /<node>/ground, stamped with the input's stamp and frame.
    Ros2(Ros2CmdArgs),
    /// Stage: the live view. A Foxglove WebSocket server (ws://127.0.0.1:8765 by default)
    /// that streams each scan with its ground probability, the proposals as boxes, the
    /// mount as a transform and the counters; `pipeline --view` starts it.
    View(ViewCmdArgs),
    /// List the sensor presets (`--sensor NAME`): mount, ranges, limits.
    Sensors,
    /// Generate a labeled synthetic sequence in the KITTI layout (velodyne/*.bin,
    /// labels/*.label with class and instance ids, poses.txt, calib.txt), which segment
    /// and eval read like the bundled one.
    Synth(SynthArgs),
    /// Print the shared memory (MiB) one pipeline with this service configuration may need
    /// at worst: the `/dev/shm` size a container must get (`docker run --shm-size`).
    ShmSize(ShmSizeArgs),
    /// Segment scans: writes <out>/<scan>.prob (f32 per point) and <out>/<scan>.ground (u8),
    /// or, for --out X.mcap, one recording with a ground_probability field.
    Segment(SegmentArgs),
    /// Object proposals (the fallback detector): segments each scan, removes the ground,
    /// clusters the rest. Writes <out>/<scan>.proposals.json and <out>/<scan>.clusters (u32
    /// proposal id per point, 0 = none); with instance labels beside the scans, reports the
    /// labeled objects found.
    Detect(DetectArgs),
    /// A bird's-eye PNG of one scan: ground by height or probability (or errors against
    /// labels with --compare), non-ground grey, proposals as boxes with ids, scale bar,
    /// sensor.
    Render(RenderArgs),
    /// Evaluate against SemanticKITTI labels: per scan and pooled metrics, plus speed.
    Eval(EvalArgs),
    /// Fit groundwork to a new sensor from raw scans, no labels: finds the mount (height,
    /// roll, pitch) by ground-plane consensus over the scans and writes it as a
    /// configuration to lay over the preset (`--sensor P --config OUT`), with a report.
    Calibrate(CalibrateArgs),
    /// Label a whole dataset offline (PseudoLabeler by default): <out>/<scan>.prob and
    /// .ground per scan, in parallel across scans, resumable, shardable across machines
    /// (`--shard i/n`), with a summary JSON.
    Label(LabelArgs),
}

/// Arguments of `groundwork pipeline`.
#[derive(clap::Args, Debug)]
pub struct PipelineArgs {
    #[command(flatten)]
    pub common: Common,
    #[command(flatten)]
    pub service: ServiceArgs,
    /// Scans to replay (looping): a folder of scans or an MCAP recording; default:
    /// $GROUNDWORK_DATA, else the sample KITTI scans installed beside the binary
    /// (<prefix>/share/groundwork/) or in the checkout it was built in.
    #[arg(long, conflicts_with = "packets")]
    pub data: Option<PathBuf>,
    /// Stop after this many scans (default: run until Ctrl-C).
    #[arg(long)]
    pub count: Option<u64>,
    /// Producer rate, scans per second (0 = as fast as possible), or `recorded`: a
    /// recording or capture at its recorded rate (their default).
    #[arg(long, value_parser = parse_rate)]
    pub rate: Option<Rate>,
    /// Consumer writes .prob/.ground files into this folder, or one recording
    /// (PointCloud2 with ground_probability) to a path ending in .mcap.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Start a stage that dies (killed, crashed) again, up to this many times per
    /// stage; each restart is logged and counted. Default 0: a dead stage stops the
    /// pipeline, which then exits non-zero.
    #[arg(long, default_value_t = 0)]
    pub restart: u32,
    /// Leave out the detector stage (object proposals on <prefix>/proposals).
    #[arg(long)]
    pub no_detector: bool,
    /// Take scans from ROS 2 instead of files: the ROS 2 bridge replaces the producer
    /// (the options below say where it listens and answers).
    #[arg(long, conflicts_with_all = ["data", "rate", "packets"])]
    pub ros2: bool,
    #[command(flatten)]
    pub packets: PacketArgs,
    #[command(flatten)]
    pub ros2_args: Ros2Args,
    #[command(flatten)]
    pub view: ViewArg,
}

/// Where a live view listens unless told.
pub const DEFAULT_VIEW_ADDR: &str = "127.0.0.1:8765";

/// The live view, as an option of a command that runs stages.
#[derive(clap::Args, Debug, Clone)]
pub struct ViewArg {
    /// Serve a live view for Foxglove (WebSocket) on ADDR, default 127.0.0.1:8765; give
    /// 0.0.0.0:8765 to let other machines connect.
    #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = DEFAULT_VIEW_ADDR)]
    pub view: Option<String>,
}

/// Arguments of `groundwork view`.
#[derive(clap::Args, Debug)]
pub struct ViewCmdArgs {
    /// The sensor and configuration the segmenter runs with (its mount and threshold).
    #[command(flatten)]
    pub sensor: SensorArgs,
    #[command(flatten)]
    pub service: ServiceArgs,
    /// Where the server listens, host:port (0.0.0.0 for other machines; port 0: any).
    #[arg(long, default_value = DEFAULT_VIEW_ADDR)]
    pub addr: String,
    /// Messages queued per viewer before its oldest are dropped (a scan is a few MB).
    #[arg(long, default_value_t = 8)]
    pub backlog: usize,
}

/// Where the ROS 2 bridge listens and answers.
#[derive(clap::Args, Debug, Clone)]
pub struct Ros2Args {
    /// The sensor_msgs/PointCloud2 topic to subscribe to.
    #[arg(long, default_value = "/points")]
    pub input_topic: String,
    /// DDS domain. Default: $ROS_DOMAIN_ID, else 0.
    #[arg(long)]
    pub domain_id: Option<u16>,
    /// Subscribe with reliable QoS (default: ROS 2's sensor-data profile, best effort,
    /// which matches both best-effort and reliable drivers).
    #[arg(long)]
    pub reliable: bool,
    /// The bridge's node name: it answers on /<namespace>/<node>/points etc.
    #[arg(long, default_value = "groundwork")]
    pub node: String,
    /// The node's namespace.
    #[arg(long, default_value = "/")]
    pub namespace: String,
    /// Also publish the ground points on /<namespace>/<node>/ground.
    #[arg(long)]
    pub publish_ground: bool,
    /// A nav_msgs/Odometry topic that gives each cloud its pose (at the cloud's stamp):
    /// the segmenter then keeps its multi-frame history. Its child frame is the vehicle's
    /// base (the sensor placed on it by the mount), or the cloud's own frame.
    #[arg(long, conflicts_with = "tf")]
    pub odom_topic: Option<String>,
    /// Read the TF tree (/tf and /tf_static): each cloud's pose is its frame's in this
    /// fixed frame at the cloud's stamp, and the segmenter keeps its multi-frame history.
    /// The tree places the sensor: the mount is not published on /tf_static, and boxes are
    /// given in the cloud's frame.
    #[arg(long, value_name = "FIXED_FRAME", num_args = 0..=1, default_missing_value = "odom")]
    pub tf: Option<String>,
}

/// Arguments of `groundwork ros2`.
#[derive(clap::Args, Debug)]
pub struct Ros2CmdArgs {
    /// The sensor and configuration the segmenter runs with (its ground threshold).
    #[command(flatten)]
    pub sensor: SensorArgs,
    #[command(flatten)]
    pub service: ServiceArgs,
    #[command(flatten)]
    pub ros2: Ros2Args,
    #[command(flatten)]
    pub view: ViewArg,
    /// Stop after answering this many clouds (default: run until stopped).
    #[arg(long)]
    pub count: Option<u64>,
}

/// A producer's pace: scans per second, or as recorded.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Rate {
    /// Scans per second (0: as fast as possible).
    Hz(f64),
    /// A recording's or capture's own pace.
    Recorded,
}

impl Rate {
    /// Scans per second, None for the recorded pace.
    pub fn hz(self) -> Option<f64> {
        match self {
            Self::Hz(r) => Some(r),
            Self::Recorded => None,
        }
    }
}

fn parse_rate(s: &str) -> Result<Rate, String> {
    if s == "recorded" {
        return Ok(Rate::Recorded);
    }
    s.parse()
        .map(Rate::Hz)
        .map_err(|_| format!("{s}: scans per second (a number) or `recorded`"))
}

/// A sensor's packets as the source of scans (producer and pipeline).
#[derive(clap::Args, Debug, Clone, Default)]
pub struct PacketArgs {
    /// Read the sensor's own packets: `velodyne` (VLP-16, Puck Hi-Res, VLP-32C, HDL-32E,
    /// HDL-64E) or `ouster` (OS0/OS1/OS2), from --pcap FILE or --udp ADDR, decoded straight
    /// into shared memory.
    #[arg(long, value_name = "FAMILY")]
    pub packets: Option<String>,
    /// Replay a pcap capture of the sensor's packets, once (at its recorded rate; with
    /// --rate 0 as fast as the scans are taken).
    #[arg(long, requires = "packets", conflicts_with = "udp")]
    pub pcap: Option<PathBuf>,
    /// Listen for the sensor's packets on this UDP address, e.g. 0.0.0.0:2368.
    #[arg(long, value_name = "ADDR", requires = "packets")]
    pub udp: Option<String>,
    /// The sensor's calibration file: Velodyne, the ROS driver's YAML (the HDL-64E needs
    /// its own, the others default to the manual's table); Ouster, the metadata JSON the
    /// sensor gives (required).
    #[arg(long, value_name = "FILE", requires = "packets")]
    pub sensor_config: Option<PathBuf>,
    /// The sensor model, where the preset does not say it: vlp16, vlp16-hires, vlp32c,
    /// hdl32e, hdl64e (S3), hdl64e-s2. Default: the sensor preset's name.
    #[arg(long, requires = "packets")]
    pub model: Option<String>,
    /// A capture's datagrams to this port only (default: the sensor's data port, 2368 for
    /// Velodyne, 7502 for Ouster; 0: every port).
    #[arg(long, requires = "pcap")]
    pub port: Option<u16>,
}

/// Arguments of `groundwork producer`.
#[derive(clap::Args, Debug)]
pub struct ProducerArgs {
    #[command(flatten)]
    pub service: ServiceArgs,
    /// Stop after this many scans.
    #[arg(long)]
    pub count: Option<u64>,
    /// Scans per second (0 = as fast as possible; overrides the configuration), or
    /// `recorded`: a recording or capture at its recorded rate (their default).
    #[arg(long, value_parser = parse_rate)]
    pub rate: Option<Rate>,
    /// Publish generated scans of this many points instead of files.
    #[arg(long, conflicts_with = "data")]
    pub synthetic: Option<usize>,
    /// Fault testing: every N-th scan is malformed (NaN, empty, bad schema, bad count).
    #[arg(long)]
    pub malformed_every: Option<u64>,
    /// After --count scans, stay this many seconds (`inf`: until stopped) so that
    /// subscribers can still read the last ones (a leaving publisher takes its queued
    /// scans with it).
    #[arg(long, default_value_t = 0.0)]
    pub linger: f64,
    /// PointCloud2 topic of a recording (default: its first point cloud topic).
    #[arg(long)]
    pub topic: Option<String>,
    #[command(flatten)]
    pub packets: PacketArgs,
    /// Folder of scans or MCAP recording to replay (a recording at its recorded rate
    /// unless --rate is given); default: the sample scans, found as for `pipeline`.
    #[arg(conflicts_with = "packets")]
    pub data: Option<PathBuf>,
}

/// Arguments of `groundwork segmenter`.
#[derive(clap::Args, Debug)]
pub struct SegmenterArgs {
    #[command(flatten)]
    pub common: Common,
    #[command(flatten)]
    pub service: ServiceArgs,
    /// Stop after this many scans.
    #[arg(long)]
    pub count: Option<u64>,
    /// Transport benchmark: answer with masks of the right size without segmenting.
    #[arg(long)]
    pub echo: bool,
}

/// Arguments of `groundwork detector`.
#[derive(clap::Args, Debug)]
pub struct DetectorArgs {
    #[command(flatten)]
    pub common: Common,
    #[command(flatten)]
    pub service: ServiceArgs,
    /// Stop after this many masks.
    #[arg(long)]
    pub count: Option<u64>,
}

/// Arguments of `groundwork consumer`.
#[derive(clap::Args, Debug)]
pub struct ConsumerArgs {
    /// The sensor whose mount a recording (`--out X.mcap`) places the scans by.
    #[command(flatten)]
    pub sensor: SensorArgs,
    #[command(flatten)]
    pub service: ServiceArgs,
    /// Stop after this many masks.
    #[arg(long)]
    pub count: Option<u64>,
    /// Stop when no mask arrived for this many seconds (after the first).
    #[arg(long)]
    pub idle_timeout: Option<f64>,
    /// Sequence folder with labels/ for live accuracy.
    #[arg(long)]
    pub labels: Option<PathBuf>,
    /// Write .prob/.ground files into this folder, or one recording (PointCloud2 with
    /// ground_probability, topic /points) to a path ending in .mcap.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Write the final report as JSON here.
    #[arg(long)]
    pub report_json: Option<PathBuf>,
    /// Fault testing: after this many masks stop reading for --stall-secs.
    #[arg(long)]
    pub stall_after: Option<u64>,
    /// Seconds to stall.
    #[arg(long, default_value_t = 0.0)]
    pub stall_secs: f64,
    /// Leave the first N segmented masks out of the latency figures (first touches of
    /// shared memory, cold caches).
    #[arg(long, default_value_t = 0)]
    pub warmup: u64,
}

/// Arguments of `groundwork synth`.
#[derive(clap::Args, Debug)]
pub struct SynthArgs {
    /// Sensor preset whose beam pattern and mount the scans are taken with.
    #[arg(long, default_value = "hdl64e")]
    pub sensor: String,
    /// Configuration laid over the preset: its sensor.mount is the mount the scans are
    /// taken with (a tilted or low sensor).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Scene: urban, offroad, parking, hill or city.
    #[arg(long, default_value = "urban")]
    pub scene: String,
    /// Frames to generate.
    #[arg(long, default_value_t = 10)]
    pub frames: usize,
    /// Seed of the layout and the sensor noise.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Output folder (created if missing).
    #[arg(long)]
    pub out: PathBuf,
}

/// Arguments of `groundwork shm-size`.
#[derive(clap::Args, Debug)]
pub struct ShmSizeArgs {
    #[command(flatten)]
    pub service: ServiceArgs,
}

/// Arguments of `groundwork segment`.
#[derive(clap::Args, Debug)]
pub struct SegmentArgs {
    #[command(flatten)]
    pub common: Common,
    /// Method: gmm (online, history), pseudolabeler (offline, slow, accurate) or ransac.
    #[arg(long, value_enum, default_value_t = MethodArg::Gmm)]
    pub method: MethodArg,
    /// Output folder of .prob/.ground files (created if missing), or a path ending in
    /// .mcap: one recording with a ground_probability field per point.
    #[arg(long)]
    pub out: PathBuf,
    /// Scan files, folders of scans (a sequence folder with velodyne/ works too), or
    /// MCAP recordings.
    #[arg(required = true)]
    pub inputs: Vec<PathBuf>,
}

/// Arguments of `groundwork detect`.
#[derive(clap::Args, Debug)]
pub struct DetectArgs {
    #[command(flatten)]
    pub common: Common,
    /// Ground segmentation method.
    #[arg(long, value_enum, default_value_t = MethodArg::Gmm)]
    pub method: MethodArg,
    /// Output folder (created if missing).
    #[arg(long)]
    pub out: PathBuf,
    /// Scan files, or folders of scans (a sequence folder with velodyne/ works too).
    #[arg(required = true)]
    pub inputs: Vec<PathBuf>,
}

/// Arguments of `groundwork render`.
#[derive(clap::Args, Debug)]
pub struct RenderArgs {
    #[command(flatten)]
    pub sensor: SensorArgs,
    /// The scan.
    pub scan: PathBuf,
    /// Its .prob file (default: segment it with --method).
    #[arg(long)]
    pub mask: Option<PathBuf>,
    /// Method when no mask is given.
    #[arg(long, value_enum, default_value_t = MethodArg::Gmm)]
    pub method: MethodArg,
    /// Its .proposals.json, drawn as boxes.
    #[arg(long, conflicts_with = "detect")]
    pub proposals: Option<PathBuf>,
    /// Run the detector and draw its proposals.
    #[arg(long)]
    pub detect: bool,
    /// Colour true/false ground and missed ground against labels (gmm protocol).
    #[arg(long)]
    pub compare: bool,
    /// Label file for --compare (default: labels/<stem>.label beside velodyne/).
    #[arg(long)]
    pub labels: Option<PathBuf>,
    /// Ground colouring.
    #[arg(long, value_enum, default_value_t = ColourArg::Height)]
    pub colour: ColourArg,
    /// Half the picture's side, metres.
    #[arg(long, default_value_t = 40.0)]
    pub range: f32,
    /// Metres per pixel.
    #[arg(long, default_value_t = 0.08)]
    pub resolution: f32,
    /// The PNG to write.
    #[arg(long)]
    pub out: PathBuf,
}

/// Arguments of `groundwork eval`.
#[derive(clap::Args, Debug)]
pub struct EvalArgs {
    #[command(flatten)]
    pub common: Common,
    /// Methods to score on the same scans (comma-separated or repeated): gmm,
    /// pseudolabeler, ransac; several are printed side by side.
    #[arg(long, value_enum, value_delimiter = ',', default_value = "gmm")]
    pub method: Vec<MethodArg>,
    /// Sequence folder with velodyne/ and labels/ (poses.txt, calib.txt optional), a
    /// folder of scans, or an MCAP recording.
    pub sequence: PathBuf,
    /// Folder of .label files (default: <sequence>/labels). For a recording, the
    /// index-th message's labels are <index:06>.label.
    #[arg(long)]
    pub labels: Option<PathBuf>,
    /// Label layout and ground classes: semantickitti, nuscenes, rellis (built-in maps,
    /// config/labels/) or the path of a map file for another dataset.
    #[arg(long, default_value = "semantickitti")]
    pub labels_format: String,
    /// Label protocol: gmm (vegetation ignored) or terraseg (vegetation is non-ground).
    #[arg(long, value_enum, default_value_t = ProtocolArg::Gmm)]
    pub protocol: ProtocolArg,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

/// Arguments of `groundwork label`.
#[derive(clap::Args, Debug)]
pub struct LabelArgs {
    #[command(flatten)]
    pub sensor: SensorArgs,
    /// Per-scan method (the GMM keeps a history over scans in order: use `segment`).
    #[arg(long, value_enum, default_value_t = LabelMethod::Pseudolabeler)]
    pub method: LabelMethod,
    /// Output folder (created if missing).
    #[arg(long)]
    pub out: PathBuf,
    /// Label only shard i of n (0-based): scans whose place in the sorted list is i
    /// modulo n. Every scan is in exactly one shard.
    #[arg(long, value_parser = parse_shard)]
    pub shard: Option<Shard>,
    /// Label again even scans whose outputs are complete.
    #[arg(long)]
    pub overwrite: bool,
    /// Scan files or folders of scans (a sequence folder with velodyne/ works too).
    #[arg(required = true)]
    pub inputs: Vec<PathBuf>,
}

/// Arguments of `groundwork calibrate`.
#[derive(clap::Args, Debug)]
pub struct CalibrateArgs {
    /// The preset to start from (its mount is the prior; the output holds what differs
    /// from it), and a configuration over it (a better prior).
    #[command(flatten)]
    pub sensor: SensorArgs,
    /// PointCloud2 topic of MCAP recordings (default: the first point cloud topic).
    #[arg(long)]
    pub topic: Option<String>,
    /// The configuration to write (TOML).
    #[arg(long)]
    pub out: PathBuf,
    /// Also write the whole report (per-scan planes, spreads) as JSON here.
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// Replace --out and --report if they exist (otherwise an existing file is an error).
    #[arg(long)]
    pub overwrite: bool,
    /// Look at no more than this many scans, spread evenly over the inputs where their
    /// length is known.
    #[arg(long, default_value_t = 400)]
    pub max_scans: usize,
    /// Seed of the plane hypotheses: the same scans and seed give the same file.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Keep the preset's likelihood parameters and ground threshold. By default, with the
    /// mount found, they are fitted to the PseudoLabeler's labels of a sample of the scans
    /// (one in four held out to judge the fit) and kept only where the held-out scans agree
    /// with those labels clearly better (docs/calibration.md).
    #[arg(long)]
    pub keep_params: bool,
    /// The parameter fit, which is the default now (accepted for scripts written before).
    #[arg(long, hide = true, conflicts_with = "keep_params")]
    pub fit_params: bool,
    /// Scans in that sample, at most (spread over the scans looked at).
    #[arg(long, default_value_t = 48)]
    pub param_scans: usize,
    /// The labels count only out to where the preset agrees with them on at least this much
    /// (ground IoU, %, in 10 m rings from the sensor): beyond, neither can be taken as truth.
    #[arg(long, default_value_t = 90.0)]
    pub param_trust: f64,
    /// The fitted parameters are kept only if the held-out scans agree with the labels
    /// better than with the preset's by more than this (ground IoU points); smaller gains
    /// were as often losses against the truth (docs/calibration.md).
    #[arg(long, default_value_t = 2.5)]
    pub param_min_gain: f64,
    /// Also fit the layout of the two inner zones (their boundary, rings and sectors) to
    /// the labels. Off by default: it can fit the labeler's own mistakes
    /// (docs/calibration.md).
    #[arg(long, conflicts_with = "keep_params")]
    pub fit_zones: bool,
    /// Keep the preset's zone model as it is. By default its near edge (`zones.min_range`)
    /// moves in to where the scans first see ground on the mount found, if that is nearer
    /// (a lower or pitched mount), and its inner boundaries scale with the height found
    /// over the preset's, if more than 5 % apart (docs/calibration.md).
    #[arg(long)]
    pub keep_zones: bool,
    /// Scan files, folders of scans or recordings of one sensor on one mount.
    #[arg(required = true)]
    pub inputs: Vec<PathBuf>,
}

#[derive(Copy, Clone, Debug, ValueEnum)]
pub enum ProtocolArg {
    Gmm,
    Terraseg,
}

/// How ground points are coloured.
#[derive(Copy, Clone, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum ColourArg {
    /// Ground by height.
    Height,
    /// Ground by probability.
    Probability,
}

/// The per-scan methods `label` runs.
#[derive(Copy, Clone, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum LabelMethod {
    /// TerraSeg's PseudoLabeler (per-scan MLP elevation map).
    Pseudolabeler,
    /// The RANSAC plane baseline.
    Ransac,
}

/// Shard i of n.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Shard {
    /// 0-based index.
    pub index: u64,
    /// Number of shards.
    pub count: u64,
}

impl Default for Shard {
    fn default() -> Self {
        Self { index: 0, count: 1 }
    }
}

impl Shard {
    /// Whether the k-th scan of the sorted list is in this shard.
    pub fn contains(&self, k: usize) -> bool {
        k as u64 % self.count == self.index
    }
}

impl std::fmt::Display for Shard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

/// Parses `i/n` with 0 ≤ i < n (a Slurm array's `$SLURM_ARRAY_TASK_ID/$SLURM_ARRAY_TASK_COUNT`).
pub fn parse_shard(s: &str) -> Result<Shard, String> {
    let (i, n) = s
        .split_once('/')
        .ok_or_else(|| format!("{s:?}: expected i/n, e.g. 0/8"))?;
    let parse = |v: &str| {
        v.trim()
            .parse::<u64>()
            .map_err(|e| format!("{s:?}: {v:?} is not a count ({e})"))
    };
    let (index, count) = (parse(i)?, parse(n)?);
    if count == 0 || index >= count {
        return Err(format!("{s:?}: need 0 ≤ i < n"));
    }
    Ok(Shard { index, count })
}
