//! What the commands share: configuration loading, inputs and outputs of offline runs,
//! progress bars.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use groundwork_core::SegmenterConfig;
use groundwork_io::Sequence;
use groundwork_service::ServiceConfig;
use indicatif::{ProgressBar, ProgressStyle};
use tracing::{error, warn};

use crate::args::{Common, ServiceArgs};

/// The built-in service configuration (`config/service.toml`).
pub const DEFAULT_SERVICE: &str = include_str!("../../../config/service.toml");
/// Where the sample scans live below an installation prefix (`<prefix>/bin/groundwork`).
const SHARED_DATA: &str = "share/groundwork/semantickitti-00";
/// Where they live in a checkout of the repository.
const CHECKOUT_DATA: &str = "tests/data/semantickitti-00";

/// The scans a pipeline or producer replays when `--data` is not given: `$GROUNDWORK_DATA`,
/// else the samples installed beside the binary (`<prefix>/share/groundwork/`, as the
/// release tarball lays them out), else the checkout whose `target/` holds the binary (found
/// from where the binary is at run time, never from a path fixed at build time, so an
/// installed or copied binary does not depend on the build machine's files), else the
/// groundwork checkout the working directory is in.
pub fn sample_data() -> Result<PathBuf> {
    if let Some(d) = std::env::var_os("GROUNDWORK_DATA") {
        let d = PathBuf::from(d);
        anyhow::ensure!(
            d.exists(),
            "GROUNDWORK_DATA={}: no such folder or recording",
            d.display()
        );
        return Ok(d);
    }
    let exe = std::env::current_exe().context("cannot find this executable")?;
    let exe = exe.canonicalize().unwrap_or(exe);
    let cwd = std::env::current_dir().ok();
    sample_data_near(&exe)
        .or_else(|| cwd.as_deref().and_then(checkout_around))
        .ok_or_else(|| {
            anyhow::anyhow!(
                "no sample scans found: pass --data <folder of scans or .mcap>, or set \
                 GROUNDWORK_DATA, or unpack the release tarball's share/ beside bin/, or run \
                 from inside a groundwork checkout (looked for {SHARED_DATA} and \
                 {CHECKOUT_DATA} around {} and above the working directory)",
                exe.display()
            )
        })
}

/// The samples of the groundwork checkout `dir` is in (a binary installed by `cargo
/// install` and run from inside the clone it was built from).
fn checkout_around(dir: &Path) -> Option<PathBuf> {
    dir.ancestors()
        .find(|a| a.join("crates/groundwork-cli/Cargo.toml").is_file())
        .map(|root| root.join(CHECKOUT_DATA))
        .filter(|d| d.is_dir())
}

/// The samples beside an executable: `<prefix>/share/...` for `<prefix>/bin/<exe>`, or a
/// checkout's copy for a binary inside the checkout's `target/` folder.
fn sample_data_near(exe: &Path) -> Option<PathBuf> {
    let dir = exe.parent()?;
    let installed = dir.parent().map(|prefix| prefix.join(SHARED_DATA));
    let checkout = exe
        .ancestors()
        .find(|a| a.file_name().is_some_and(|n| n == "target"))
        .and_then(Path::parent)
        .map(|root| root.join(CHECKOUT_DATA));
    [installed, checkout]
        .into_iter()
        .flatten()
        .find(|d| d.is_dir())
}

pub fn load_service(args: &ServiceArgs) -> Result<ServiceConfig> {
    let mut cfg = match &args.service {
        Some(p) => ServiceConfig::load(p)?,
        None => toml::from_str(DEFAULT_SERVICE).context("built-in config/service.toml")?,
    };
    if let Some(p) = &args.prefix {
        cfg.prefix = p.clone();
    }
    cfg.validate()?;
    Ok(cfg)
}

/// The segmenter configuration: the named preset (`--sensor`, else the one the `--config`
/// file names, else the service's, else hdl64e), the `--config` file over it, then
/// `--frames`.
pub fn load(common: &Common, service_sensor: Option<&str>) -> Result<SegmenterConfig> {
    Ok(load_methods(common, service_sensor)?.segmenter)
}

/// The whole configuration (segmenter and method sections) the common options describe.
pub fn load_methods(
    common: &Common,
    service_sensor: Option<&str>,
) -> Result<groundwork_io::MethodsConfig> {
    Ok(load_named(common, service_sensor)?.1)
}

/// [`load_methods`], and the preset it was laid over: `--sensor`, else the one the
/// `--config` file names (another `--sensor` is refused, naming both), else the service's,
/// else hdl64e.
pub fn load_named(
    common: &Common,
    service_sensor: Option<&str>,
) -> Result<(String, groundwork_io::MethodsConfig)> {
    let (preset, mut cfg) = groundwork_io::load_methods_config_named(
        common.sensor.as_deref(),
        service_sensor.unwrap_or(groundwork_io::DEFAULT_SENSOR),
        common.config.as_deref(),
        None,
    )?;
    if let Some(n) = common.frames {
        cfg.segmenter.history.frames = n;
        cfg.segmenter.validate().context("--frames")?;
    }
    Ok((preset, cfg))
}

/// Opens each input (a scan file, a folder or a recording; a folder may carry poses for
/// history) as a sequence. An input that cannot be used is reported and counted, and the
/// others still run: the sequences, and how many inputs were skipped. When none can be
/// used, nothing runs: an error (exit 2) before any output is created or replaced.
pub fn open_inputs(
    inputs: &[PathBuf],
    poses: Option<&Path>,
    calib: Option<&Path>,
    topic: Option<&str>,
) -> Result<(Vec<Sequence>, usize)> {
    let mut skipped = 0;
    let mut sequences = Vec::new();
    for path in inputs {
        match Sequence::open(path, poses, calib) {
            Ok(seq) => sequences.push(seq.with_topic(topic.map(str::to_owned))),
            Err(e) => {
                skipped += 1;
                error!("skipped: {e}");
            }
        }
    }
    anyhow::ensure!(
        !sequences.is_empty(),
        "no readable input among the {} given (each is named above): nothing was run",
        inputs.len()
    );
    Ok((sequences, skipped))
}

/// The output of an offline run, refused before anything is written where it would destroy
/// an input (`--out rec.mcap rec.mcap`) or where two inputs' scans would write the same
/// files of a folder (`000000.bin` in two folders): outputs are never overwritten in
/// silence. A re-run into the same place replaces what an earlier run wrote there (as a
/// build does), and says so first: `suffixes` are the file endings the command writes per
/// scan.
pub fn create_output(
    out: &Path,
    inputs: &[PathBuf],
    sequences: &[Sequence],
    suffixes: &[&str],
) -> Result<groundwork_io::OutputTarget> {
    let is_recording = out
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("mcap"));
    if is_recording {
        if out.is_file() {
            warn!(
                "{}: exists, and is replaced by this run's recording when it ends (if any scan is segmented)",
                out.display()
            );
        }
    } else {
        let sources: Vec<_> = sequences.iter().map(|s| &s.source).collect();
        groundwork_io::check_output_names(&sources)?;
        let earlier = groundwork_io::earlier_outputs(out, &sources, suffixes);
        groundwork_io::warn_replaced(out, &earlier);
    }
    Ok(groundwork_io::OutputTarget::create(
        out,
        &input_files(inputs, sequences),
    )?)
}

/// Every file a run over `inputs` reads: the inputs as given, and the scan files their
/// folders hold. An output is checked against these (see [`groundwork_io::OutputFiles`]).
pub fn input_files(inputs: &[PathBuf], sequences: &[Sequence]) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = inputs.to_vec();
    for s in sequences {
        if let groundwork_io::ScanSource::Files(f) = &s.source {
            files.extend(f.iter().cloned());
        }
    }
    files
}

/// Makes a recording output place every scan frame on the ground frame by `mount` (a
/// static transform on `/tf_static`); a folder output has nowhere to say it.
pub fn place_scans_by_mount(
    output: &mut groundwork_io::OutputTarget,
    mount: &groundwork_core::config::MountConfig,
) -> Result<()> {
    if let groundwork_io::OutputTarget::Recording(w) = output {
        w.set_mount(groundwork_io::transform::StaticTransform::of_mount(mount)?);
    }
    Ok(())
}

pub fn progress(len: usize, what: &str) -> ProgressBar {
    let pb = ProgressBar::new(len as u64);
    pb.set_style(progress_style(
        "{msg} [{bar:30}] {pos}/{len} scans, {rate}, eta {eta}",
    ));
    pb.set_message(what.to_string());
    pb
}

/// A progress bar style whose `{rate}` is scans per second to one decimal (indicatif's
/// `{per_sec}` prints four).
pub fn progress_style(template: &str) -> ProgressStyle {
    ProgressStyle::with_template(template)
        .unwrap_or_else(|_| ProgressStyle::default_bar())
        .with_key(
            "rate",
            |s: &indicatif::ProgressState, w: &mut dyn std::fmt::Write| {
                let _ = write!(w, "{:.1} scans/s", s.per_sec());
            },
        )
        .progress_chars("=> ")
}

/// The header a scan read from a file would carry in the service: its input is its
/// producer run, its place among all scans its sequence number.
pub fn offline_header(
    pose: Option<&groundwork_core::Pose>,
    input: usize,
    k: usize,
    points: usize,
) -> groundwork_msg::ScanHeader {
    let mut h = groundwork_msg::ScanHeader {
        point_count: u32::try_from(points).unwrap_or(u32::MAX),
        sequence: k as u64,
        producer_epoch: input as u64 + 1,
        source_index: k as u64,
        ..Default::default()
    };
    if let Some(p) = pose {
        h.has_pose = 1;
        h.pose = groundwork_service::producer::pose_matrix(p);
    }
    h
}
