"""groundwork: LiDAR ground segmentation and object proposals from numpy.

Points are (N, 3) or (N, 4) arrays of x, y, z[, intensity] in metres, in the sensor frame
(x forward, y left, z up). A C-contiguous float32 array is read in place; anything else
numpy can convert is converted once. Probabilities are float32 in [0, 1], one per point,
in input order. Poses are 4 x 4 float64 matrices, world from sensor.

Configuration, for every call that takes it: a sensor preset (``sensors()``; default
"hdl64e"), then a TOML file (``config=``) laid over it, then keyword arguments laid over
both — sections as dicts, e.g. ``history={"frames": 3}``, ``ground={"ground_threshold": 0.6}``.
Unknown keys are errors. Errors are ``ValueError`` (bad input, bad configuration) or
``OSError`` (a file that cannot be read), with the library's message.
"""

from collections.abc import Sequence
from os import PathLike
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

__version__: str

_Points = npt.ArrayLike
_Path = str | PathLike[str]

class Segmenter:
    """The GMM ground segmenter (a Gaussian mixture per polar segment, multi-frame history).

    Keeps state between calls: the last ``frames`` scans (queried when poses are given) and
    the zone-1 height filter. One instance per sensor stream, fed in time order; one per
    thread (the GIL is released while a scan is segmented, so threads run in parallel).
    """

    def __init__(
        self,
        sensor: str | None = None,
        config: _Path | None = None,
        frames: int | None = None,
        **overrides: Any,
    ) -> None:
        """``frames``: history length N_f (1 = single frame), as ``--frames``."""

    def segment(
        self, points: _Points, pose: npt.ArrayLike | None = None
    ) -> npt.NDArray[np.float32]:
        """Ground probability per point, in input order; ``pose`` (world from sensor) lets
        the scan be queried against the history, without it the scan is segmented
        single-frame and the history is left as it is. ``points`` is (N, 3) or (N, 4+):
        x, y, z[, intensity], further columns ignored; rows with a NaN or inf coordinate
        are "no return" placeholders and get probability 0 in place."""

    def ground(
        self,
        points: _Points,
        pose: npt.ArrayLike | None = None,
        threshold: float | None = None,
    ) -> npt.NDArray[np.bool_]:
        """Ground mask: probability >= ``threshold`` (default: the configuration's)."""

    def reset(self) -> bool:
        """Forgets the history and the height filter (a new sequence); whether frames were
        dropped."""

    @property
    def observed_mount(self) -> dict[str, float | bool] | None:
        """The mount observed in the ground fitted so far: height (m), roll_deg, pitch_deg,
        tilt_from_configured_deg, height_from_configured (m), scans; and the mount in use:
        applied_height (m), applied_roll_deg, applied_pitch_deg (the configured mount unless
        mount_check={"mode": "correct"} moved it), correcting, corrected_scans. None before a
        scan with enough ground, or with mount_check={"mode": "off"}."""
    @property
    def threshold(self) -> float:
        """Probability at or above which a point is ground: ``ground_threshold`` under the
        preset's probability map (``probability={"map": [...]}``, docs/accuracy.md)."""

    @property
    def frames(self) -> int:
        """Frames of history queried (1: single frame)."""

    @property
    def history_len(self) -> int:
        """Past frames held for multi-frame queries now."""

    @property
    def sensor(self) -> str:
        """The sensor preset it was built from."""

    @property
    def last_report(self) -> dict[str, Any] | None:
        """The last scan segmented: points, ground_points, frames_queried, posed,
        history_cleared, em_iterations, fit_ms and query_ms (the library's own time)."""

    @property
    def counters(self) -> dict[str, int]:
        """scans, rejected, without_pose, history_resets (resets_pose_jump,
        resets_time_gap, resets_requested), out_of_bounds_points, non_finite_outputs,
        placeholders (NaN/inf rows given probability 0)."""

    @property
    def height_filter(self) -> dict[str, Any]:
        """active_segments, mean_height (m), mean_std (m), and per zone-1 segment arrays
        mean (m, ground-aligned frame), variance (m²), frames."""

class Proposal:
    """An object proposal. Metres and radians, in the sensor's ground-aligned frame (x
    forward, y left, z up, origin on the ground below the sensor)."""

    id: int
    """1, 2, ... nearest first; the id its points carry in the cluster ids."""
    centroid: tuple[float, float, float]
    center: tuple[float, float]
    """Centre of the oriented box in the ground plane."""
    yaw: float
    """Heading of the box's long side from the x axis, in (-pi/2, pi/2]."""
    length: float
    width: float
    ground_z: float
    """Local ground height below the box centre."""
    bottom: float
    """Lowest point above the local ground."""
    height: float
    """Highest point above the local ground."""
    points: int
    flags: list[str]
    """Why it is plainly not an object: wall, large, tall, floating, many_points."""

def pseudo_label(
    points: _Points,
    seed: int = 0,
    sensor: str | None = None,
    config: _Path | None = None,
    **overrides: Any,
) -> npt.NDArray[np.float32]:
    """TerraSeg's PseudoLabeler on one scan: ground probability per point."""

def ransac(
    points: _Points,
    sensor: str | None = None,
    config: _Path | None = None,
    **overrides: Any,
) -> npt.NDArray[np.float32]:
    """The RANSAC plane baseline on one scan: ground probability per point."""

def detect(
    points: _Points,
    probabilities: npt.ArrayLike,
    sensor: str | None = None,
    config: _Path | None = None,
    **overrides: Any,
) -> tuple[list[Proposal], npt.NDArray[np.uint32]]:
    """The fallback detector: proposals (nearest first) and, per point, its proposal's id
    (0: ground or unclustered)."""

def read_scan(path: _Path, max_points: int = 10_000_000) -> npt.NDArray[np.float32]:
    """A scan file (KITTI .bin, nuScenes .pcd.bin, PCD, PLY) as an (N, 4) float32 array of
    x, y, z, intensity. Records with non-finite coordinates are left out."""

def read_recording(
    path: _Path, topic: str | None = None, max_points: int = 10_000_000
) -> list[tuple[int, npt.NDArray[np.float32]]]:
    """The point clouds of a ROS 2 recording (MCAP, sensor_msgs/msg/PointCloud2) on
    ``topic`` (default: the first point cloud topic), in log order: (log time in ns, (N, 4)
    float32 x, y, z, intensity)."""

def read_poses(poses: _Path, calib: _Path) -> npt.NDArray[np.float64]:
    """A KITTI sequence's sensor poses, (N, 4, 4), world from sensor (camera poses and the
    calibration's Tr, as ``groundwork segment`` uses them)."""

def read_labels(
    path: _Path, points: int, label_format: str = "semantickitti"
) -> npt.NDArray[np.uint32]:
    """A label file (SemanticKITTI: class in the low 16 bits, instance in the high 16),
    checked against the scan's point count."""

def evaluate(
    probabilities: npt.ArrayLike,
    labels: npt.ArrayLike,
    protocol: Literal["gmm", "terraseg"] = "gmm",
    threshold: float | None = None,
    label_format: str = "semantickitti",
) -> dict[str, float]:
    """Scores probabilities against raw labels as ``groundwork eval`` does (ground: at least
    ``threshold``, by default the default preset's, ``Segmenter().threshold``): precision,
    recall, f1, accuracy, iou_ground, iou_nonground, miou (percent) and tp, fp, fn, tn,
    ignored (points). "gmm" ignores vegetation, "terraseg" counts it as non-ground."""

def sensors() -> Sequence[str]:
    """The sensor presets."""

def calibrate(
    scans: Sequence[_Points],
    sensor: str | None = None,
    config: _Path | None = None,
    seed: int = 0,
    keep_zones: bool = False,
    keep_params: bool = False,
    param_scans: int = 48,
    param_trust: float = 90.0,
    param_min_gain: float = 2.5,
    fit_zones: bool = False,
    out: _Path | None = None,
    overwrite: bool = False,
    **overrides: Any,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """The sensor's mount from raw scans, no labels (`groundwork calibrate`): the
    configuration to lay over the preset ({"mount": {"height", "roll_deg", "pitch_deg",
    "yaw_deg"}}, and {"zones": {"min_range", "boundaries"}} where the zone model's near
    edge moved in to where the scans first see ground or its inner boundaries were scaled
    with the height found, unless keep_zones; usable as keyword arguments) and a report
    (median, spread and standard error of each over the scans; each scan's view or why it
    showed no usable ground; "near_edge": ground_from, scans, was, min_range;
    "height_scale": ratio, was, boundaries, where they were scaled; "one_sided_ground":
    leverage, nearest_m, caveat, where the scans saw the ground on one side of the sensor
    only). Then, unless keep_params, the likelihood parameters and ground threshold fitted to
    the PseudoLabeler's labels of up to param_scans of the scans (one in four held out; kept
    only if the held-out scans agree with the labels by more than param_min_gain points
    better, counted where the preset agrees with them on param_trust % or more), as
    `groundwork calibrate` does: {"ground": {...}} in the configuration where the fit was
    kept; report["parameters"]: kept_preset, changed [{name, old, new}], the agreement
    (both, segmenter_only, reference_only, iou) fitted and held out, before and after,
    trusted_range, trusted_points_per_scan and too_few_trusted_points (fewer than 500 points
    a scan ground there: no search, the preset kept); or report["parameters_refused"], the
    reason. fit_zones (not with
    keep_params): the inner zones' layout fitted with the parameters, {"zones": {"min_range",
    "boundaries", "rings", "sectors"}} where it changed (`--fit-zones`). report["summary"]
    is what the CLI prints. out: also write the configuration file `groundwork calibrate
    --out` writes (an existing file only with overwrite). Raises ValueError, with the
    reason, when the scans cannot determine the mount."""
