"""The Python package against the CLI on the bundled KITTI scans (bit for bit), and its
behaviour on bad input. Run by ``crates/groundwork-py/test.sh`` (which builds the wheel and
the CLI and sets GROUNDWORK_CLI)."""

import json
import os
import subprocess
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

import groundwork

ROOT = Path(__file__).resolve().parents[3]
SEQ = ROOT / "tests" / "data" / "semantickitti-00"
SCANS = sorted((SEQ / "velodyne").glob("*.bin"))
LABELED = [0, 1, 2]


def run(cli: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(cli), *args], check=True, capture_output=True, text=True
    )


def kitti(path: Path) -> np.ndarray:
    """A KITTI scan read by numpy alone: float32, C-contiguous, (N, 4)."""
    return np.fromfile(path, dtype=np.float32).reshape(-1, 4)


def bits(a: np.ndarray) -> np.ndarray:
    """Float32 values as their bit patterns: equality is bit-identity."""
    return np.ascontiguousarray(a, dtype=np.float32).view(np.uint32)


@pytest.fixture(scope="session")
def cli_single(cli: Path, tmp_path_factory) -> Path:
    """`groundwork segment` on frame 0 alone (a file: no poses, single frame)."""
    out = tmp_path_factory.mktemp("single")
    run(cli, "segment", "--out", str(out), str(SCANS[0]))
    return out


@pytest.fixture(scope="session")
def cli_sequence(cli: Path, tmp_path_factory) -> Path:
    """`groundwork segment` over the sequence folder (poses, default history)."""
    out = tmp_path_factory.mktemp("sequence")
    run(cli, "segment", "--out", str(out), str(SEQ))
    return out


def test_a_fresh_segmenter_equals_a_fresh_segment_process(cli_single: Path) -> None:
    expected = np.fromfile(cli_single / "000000.prob", dtype=np.float32)
    points = kitti(SCANS[0])
    probs = groundwork.Segmenter().segment(points)
    assert probs.dtype == np.float32 and probs.shape == (len(points),)
    assert np.array_equal(bits(probs), bits(expected))
    # The library's reader gives the same points, so the same answer.
    assert np.array_equal(groundwork.read_scan(SCANS[0]), points)


def test_one_segmenter_fed_the_sequence_equals_segment_over_it(cli_sequence: Path) -> None:
    poses = groundwork.read_poses(SEQ / "poses.txt", SEQ / "calib.txt")
    assert poses.shape == (len(SCANS), 4, 4) and poses.dtype == np.float64
    seg = groundwork.Segmenter()
    assert seg.frames > 1, "the default preset has a history"
    for scan, pose in zip(SCANS, poses):
        probs = seg.segment(kitti(scan), pose)
        expected = np.fromfile(cli_sequence / f"{scan.stem}.prob", dtype=np.float32)
        assert np.array_equal(bits(probs), bits(expected)), scan.name
    c = seg.counters
    assert c["scans"] == len(SCANS) and c["rejected"] == 0 and c["without_pose"] == 0
    assert 1 <= seg.history_len <= seg.frames
    hf = seg.height_filter
    assert hf["active_segments"] > 0 and len(hf["mean"]) == len(hf["frames"])
    assert seg.reset() is True and seg.history_len == 0


def test_every_format_reads_the_points_independent_writers_wrote() -> None:
    """The I/O crate's fixtures, written by pypcd4, plyfile and mcap-ros2-support from every
    97th point of frame 0 (crates/groundwork-io/tests/fixtures/README.md)."""
    fixtures = ROOT / "crates" / "groundwork-io" / "tests" / "fixtures"
    want = kitti(SCANS[0])[::97]
    for name in ("kitti_binary.pcd", "kitti_binary_compressed.pcd", "kitti_binary_le.ply",
                 "kitti_ascii.ply"):
        got = groundwork.read_scan(fixtures / name)
        assert got.shape == want.shape and got.dtype == np.float32, name
        assert np.array_equal(got[:, :3], want[:, :3]), name
    ascii_pcd = groundwork.read_scan(fixtures / "kitti_ascii.pcd")
    assert np.allclose(ascii_pcd[:, :3], want[:, :3], rtol=1e-7, atol=1e-10)
    scans = groundwork.read_recording(fixtures / "kitti_pointcloud2.mcap")
    assert len(scans) == 3, "the /chatter messages are not scans"
    times = [t for t, _ in scans]
    assert times == sorted(times) and times[1] - times[0] == 100_000_000
    assert np.array_equal(scans[0][1][:, :3], want[:, :3])
    # Message 1 is organised with two NaN placeholders: left out.
    assert len(scans[1][1]) == 2 * (len(want) // 2) - 2
    with pytest.raises(ValueError, match="nosuch"):
        groundwork.read_recording(fixtures / "kitti_pointcloud2.mcap", topic="/nosuch")


def test_other_layouts_and_dtypes_give_the_same_probabilities() -> None:
    points = kitti(SCANS[1])
    reference = groundwork.Segmenter().segment(points)
    for variant in (
        points[:, :3],  # (N, 3), not contiguous: converted
        np.ascontiguousarray(points[:, :3]),  # (N, 3) contiguous
        points.astype(np.float64),  # converted to float32 exactly
        np.asfortranarray(points),
    ):
        assert np.array_equal(bits(groundwork.Segmenter().segment(variant)), bits(reference))
    # A list of lists converts too.
    few = points[:2000]
    assert np.array_equal(
        groundwork.Segmenter().segment(few.tolist()), groundwork.Segmenter().segment(few)
    )


def test_ground_is_the_probability_at_the_threshold() -> None:
    points = kitti(SCANS[0])
    seg = groundwork.Segmenter()
    probs = groundwork.Segmenter().segment(points)
    mask = seg.ground(points)
    assert mask.dtype == np.bool_ and np.array_equal(mask, probs >= seg.threshold)
    strict = groundwork.Segmenter().ground(points, threshold=0.9)
    assert np.array_equal(strict, probs >= 0.9)
    assert 0.3 < mask.mean() < 0.8


def test_evaluate_matches_groundwork_eval(cli: Path) -> None:
    for protocol in ("gmm", "terraseg"):
        report = json.loads(
            run(
                cli,
                "eval",
                "--frames",
                "1",
                "--protocol",
                protocol,
                "--json",
                str(SCANS[0]),
                "--labels",
                str(SEQ / "labels"),
            ).stdout
        )
        points = kitti(SCANS[0])
        probs = groundwork.Segmenter(frames=1).segment(points)
        labels = groundwork.read_labels(SEQ / "labels" / "000000.label", len(points))
        assert np.array_equal(labels, np.fromfile(SEQ / "labels" / "000000.label", np.uint32))
        got = groundwork.evaluate(probs, labels, protocol=protocol)
        assert got == groundwork.evaluate(probs, labels, protocol, groundwork.Segmenter().threshold)
        scan = report["scans"][0]
        for k, v in scan["metrics"].items():
            assert got[k] == v, (protocol, k)
        for k in ("tp", "fp", "tn", "ignored"):
            assert got[k] == scan["confusion"][k]
        assert got["fn"] == scan["confusion"]["fn_"]


def test_offline_methods_and_the_detector_match_the_cli(cli: Path, tmp_path: Path) -> None:
    points = kitti(SCANS[0])
    for method, call in (
        ("ransac", lambda: groundwork.ransac(points)),
        ("pseudolabeler", lambda: groundwork.pseudo_label(points, seed=0)),
    ):
        out = tmp_path / method
        run(cli, "segment", "--method", method, "--out", str(out), str(SCANS[0]))
        expected = np.fromfile(out / "000000.prob", dtype=np.float32)
        assert np.array_equal(bits(call()), bits(expected)), method

    out = tmp_path / "detect"
    run(cli, "detect", "--out", str(out), str(SCANS[0]))
    probs = groundwork.Segmenter().segment(points)
    proposals, clusters = groundwork.detect(points, probs)
    assert np.array_equal(clusters, np.fromfile(out / "000000.clusters", np.uint32))
    saved = json.loads((out / "000000.proposals.json").read_text())["proposals"]
    assert [p.id for p in proposals] == [p["id"] for p in saved] == list(
        range(1, len(proposals) + 1)
    )
    for p, q in zip(proposals, saved):
        assert p.points == q["points"] == np.count_nonzero(clusters == p.id)
        assert p.flags == q["flags"]
        assert p.length == pytest.approx(q["length"]) and p.yaw == pytest.approx(q["yaw"])
    assert any(not p.flags for p in proposals)


def test_a_thread_pool_gives_the_serial_results() -> None:
    scans = [kitti(s) for s in SCANS]
    serial = [groundwork.Segmenter().segment(s) for s in scans]
    with ThreadPoolExecutor(2) as pool:
        parallel = list(pool.map(lambda s: groundwork.Segmenter().segment(s), scans))
    for a, b in zip(serial, parallel):
        assert np.array_equal(bits(a), bits(b))


def test_bad_points_are_value_errors_naming_the_problem() -> None:
    seg = groundwork.Segmenter()
    good = kitti(SCANS[0])
    with pytest.raises(ValueError, match=r"\(N, 3\) or \(N, 4\+\)"):
        seg.segment(np.zeros((10, 2), np.float32))
    with pytest.raises(ValueError, match=r"\(N, 3\) or \(N, 4\+\)"):
        seg.segment(np.zeros(12, np.float32))
    with pytest.raises(ValueError):
        seg.segment(np.array([["a", "b", "c"]]))
    with pytest.raises(ValueError, match="4 × 4"):
        seg.segment(good, np.eye(3))
    tilted = np.eye(4)
    tilted[0, 0] = 2.0
    with pytest.raises(ValueError, match="rotation"):
        seg.segment(good, tilted)
    # Nothing was segmented or rejected: shapes and poses are refused before.
    assert seg.counters["rejected"] == 0 and seg.counters["scans"] == 0
    assert np.array_equal(bits(seg.segment(good)), bits(groundwork.Segmenter().segment(good)))


def test_placeholders_and_extra_columns_are_read_as_the_cli_reads_them() -> None:
    good = kitti(SCANS[0])
    alone = groundwork.Segmenter().segment(np.delete(good, [7, 9], axis=0))
    # NaN or inf rows are "no return" placeholders: probability 0 in place, the rest as
    # if they were not there (an organized PCD through the CLI gets the same).
    bad = good.copy()
    bad[7, 2] = np.nan
    bad[9, 0] = np.inf
    seg = groundwork.Segmenter()
    p = seg.segment(bad)
    assert p.shape == (len(good),) and p[7] == 0.0 and p[9] == 0.0
    assert np.array_equal(bits(np.delete(p, [7, 9])), bits(alone))
    assert seg.counters["placeholders"] == 2 and seg.counters["rejected"] == 0
    # Columns after intensity (nuScenes' ring index) are ignored, as in a .pcd.bin.
    five = np.hstack([good, np.arange(len(good), dtype=np.float32)[:, None]])
    assert np.array_equal(
        bits(groundwork.Segmenter().segment(five)), bits(groundwork.Segmenter().segment(good))
    )
    # The offline methods alike.
    r = groundwork.ransac(bad)
    assert r[7] == 0.0 and r[9] == 0.0
    with pytest.raises(ValueError, match="none of its 5 points"):
        groundwork.Segmenter().segment(np.full((5, 3), np.nan, np.float32))


def test_bad_arguments_elsewhere_are_value_errors() -> None:
    good = kitti(SCANS[0])
    # An empty scan is no error.
    assert groundwork.Segmenter().segment(np.zeros((0, 3), np.float32)).shape == (0,)
    with pytest.raises(ValueError, match="probabilities"):
        groundwork.detect(good, np.zeros(len(good) - 1, np.float32))
    with pytest.raises(ValueError, match="not in"):
        groundwork.detect(good, np.full(len(good), 1.5, np.float32))
    with pytest.raises(ValueError, match="labels for"):
        groundwork.evaluate(np.zeros(3, np.float32), np.zeros(4, np.uint32))
    with pytest.raises(ValueError, match="protocol"):
        groundwork.evaluate(np.zeros(3, np.float32), np.zeros(3, np.uint32), protocol="x")


def test_bad_configuration_and_files_are_errors_naming_them(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="no such sensor preset"):
        groundwork.Segmenter(sensor="hdl65")
    with pytest.raises(ValueError, match="keyword arguments.*unknown field"):
        groundwork.Segmenter(history={"framez": 3})
    with pytest.raises(ValueError, match="frames"):
        groundwork.Segmenter(frames=0)
    bad = tmp_path / "bad.toml"
    bad.write_text("[ground]\nground_treshold = 0.4\n")
    with pytest.raises(ValueError, match="bad.toml"):
        groundwork.Segmenter(config=bad)
    with pytest.raises(OSError, match="missing.bin"):
        groundwork.read_scan(tmp_path / "missing.bin")
    truncated = tmp_path / "truncated.bin"
    truncated.write_bytes(SCANS[0].read_bytes()[:100])
    with pytest.raises(ValueError, match="truncated.bin"):
        groundwork.read_scan(truncated)
    with pytest.raises(ValueError, match="label"):
        groundwork.read_labels(SEQ / "labels" / "000000.label", 10)


def test_keyword_arguments_configure_like_a_file(tmp_path: Path) -> None:
    points = kitti(SCANS[0])
    cfg = tmp_path / "strict.toml"
    cfg.write_text("[ground]\nground_threshold = 0.8\n")
    by_file = groundwork.Segmenter(config=cfg)
    by_kwargs = groundwork.Segmenter(ground={"ground_threshold": 0.8})
    # The threshold on the output: the preset's probability map at ground_threshold.
    assert by_file.threshold == by_kwargs.threshold > groundwork.Segmenter().threshold
    unmapped = groundwork.Segmenter(ground={"ground_threshold": 0.8}, probability={"map": []})
    assert unmapped.threshold == pytest.approx(0.8)
    assert np.array_equal(by_file.ground(points), by_kwargs.ground(points))
    assert groundwork.Segmenter(frames=3).frames == 3
    assert "vlp16" in groundwork.sensors()
    assert groundwork.Segmenter(sensor="vlp16").sensor == "vlp16"


def test_layouts_are_a_keyword_away_and_score_higher(cli: Path, tmp_path: Path) -> None:
    """`zones.layouts` by keyword gives the CLI's bits with the same setting in a file, and on
    the labeled frames a better pooled IoU than one layout (98.99 against 98.66 measured)."""
    cfg = tmp_path / "layouts.toml"
    cfg.write_text("[zones]\nlayouts = 3\n")
    out = tmp_path / "out"
    run(cli, "segment", "--config", str(cfg), "--out", str(out), str(SCANS[0]))
    three = groundwork.Segmenter(frames=1, zones={"layouts": 3})
    probs = three.segment(kitti(SCANS[0]))
    assert np.array_equal(bits(probs), bits(np.fromfile(out / "000000.prob", np.float32)))
    assert probs.min() >= 0.0 and probs.max() <= 1.0
    pooled = {}
    for layouts in (1, 3):
        seg = groundwork.Segmenter(frames=1, zones={"layouts": layouts})
        counts = np.zeros(3)
        for i in LABELED:
            points = kitti(SCANS[i])
            labels = groundwork.read_labels(SEQ / "labels" / f"{i:06}.label", len(points))
            r = groundwork.evaluate(seg.segment(points), labels, protocol="gmm")
            counts += [r["tp"], r["fp"], r["fn"]]
        pooled[layouts] = counts[0] / counts.sum()
    assert pooled[3] >= pooled[1] + 0.0025, pooled
    with pytest.raises(ValueError, match="zones.layouts"):
        groundwork.Segmenter(zones={"layouts": 9})


def test_an_ascii_pcd_of_a_scan_gives_the_decisions_of_its_bin(cli: Path, tmp_path: Path) -> None:
    """A scan converted to text by an independent writer (pypcd4: ten decimals, i.e. the f32
    coordinates rounded) gives the ground of the original: the fit points are chosen by the
    geometry, not by the coordinates' last bits (docs/algorithm.md)."""
    from pypcd4 import Encoding, PointCloud

    threshold = groundwork.Segmenter().threshold
    for i in LABELED:
        points = kitti(SCANS[i])
        pcd = tmp_path / f"{SCANS[i].stem}.pcd"
        PointCloud.from_xyzi_points(points).save(pcd, encoding=Encoding.ASCII)
        assert pcd.read_bytes().count(b"DATA ascii") == 1
        for src, name in ((SCANS[i], "bin"), (pcd, "pcd")):
            run(cli, "segment", "--out", str(tmp_path / name), str(src))
        want = np.fromfile(tmp_path / "bin" / f"{SCANS[i].stem}.prob", dtype=np.float32)
        got = np.fromfile(tmp_path / "pcd" / f"{SCANS[i].stem}.prob", dtype=np.float32)
        assert got.shape == want.shape
        flipped = int(np.count_nonzero((got >= threshold) != (want >= threshold)))
        largest = float(np.max(np.abs(got - want)))
        print(f"frame {i}: ASCII PCD vs .bin: {flipped} decisions differ, largest change {largest:.4f}")
        # The bound: at most 0.05 % of the decisions differ.
        assert flipped <= 0.0005 * len(want), (i, flipped, largest)


def test_the_label_folder_example_writes_what_label_writes_and_resumes(
    cli: Path, tmp_path: Path
) -> None:
    """examples/label_folder.py (a process pool over groundwork.pseudo_label) gives the
    bytes `groundwork label` gives, and a rerun keeps what is complete."""
    import sys

    scans = tmp_path / "scans"
    scans.mkdir()
    for s in SCANS[:3]:
        (scans / s.name).write_bytes(s.read_bytes())
    run(cli, "label", "--out", str(tmp_path / "cli"), str(scans))
    example = ROOT / "examples" / "label_folder.py"
    out = tmp_path / "py"
    done = subprocess.run(
        [sys.executable, str(example), str(scans), str(out), "--workers", "2"],
        check=True, capture_output=True, text=True,
    )
    assert "3 scans, 0 already complete" in done.stderr, done.stderr
    for s in SCANS[:3]:
        for ext in ("prob", "ground"):
            name = f"{s.stem}.{ext}"
            assert (out / name).read_bytes() == (tmp_path / "cli" / name).read_bytes(), name
    # A scan whose .ground is missing (killed before its last rename) is done again.
    (out / f"{SCANS[1].stem}.ground").unlink()
    again = subprocess.run(
        [sys.executable, str(example), str(scans), str(out), "--workers", "1"],
        check=True, capture_output=True, text=True,
    )
    assert "3 scans, 2 already complete" in again.stderr and "1 labelled" in again.stderr
    name = f"{SCANS[1].stem}.ground"
    assert (out / name).read_bytes() == (tmp_path / "cli" / name).read_bytes()


def test_an_older_cpu_gets_an_import_error_not_sigill() -> None:
    """On a CPU below the wheel's level (x86-64-v3), `import groundwork` raises an
    ImportError naming the missing features: run under qemu-x86_64 as a Nehalem (no AVX)."""
    import platform
    import shutil
    import sys

    qemu = shutil.which("qemu-x86_64")
    if platform.machine() != "x86_64":
        pytest.skip("the x86-64 level's check")
    if qemu is None:
        assert not os.environ.get("GROUNDWORK_REQUIRE_QEMU"), "qemu-x86_64 is required"
        pytest.skip("qemu-x86_64 not installed")
    r = subprocess.run(
        [qemu, "-cpu", "Nehalem", sys.executable, "-c", "import groundwork"],
        capture_output=True, text=True, timeout=600,
    )
    assert r.returncode == 1, (r.returncode, r.stderr[-2000:])
    assert "ImportError: groundwork: this CPU lacks avx" in r.stderr, r.stderr[-2000:]
    assert "x86-64-v3" in r.stderr


def test_calibrate_moves_the_zones_for_a_low_mount_as_the_cli_does(cli: Path, tmp_path: Path) -> None:
    """An HDL-32E 0.8 m up, pitched 6°: Python's calibrate moves the near edge in and, the
    preset's layout following its beams (`scale_with_height`), scales the inner boundaries
    by the height found over the preset's 1.84 m, to the same zones as the CLI's file."""
    low = tmp_path / "low.toml"
    low.write_text("[sensor]\nmount = { height = 0.8, pitch_deg = 6.0 }\n")
    seq = tmp_path / "seq"
    run(cli, "synth", "--sensor", "hdl32e", "--scene", "urban", "--frames", "6",
        "--config", str(low), "--out", str(seq))
    scans = [kitti(p) for p in sorted((seq / "velodyne").glob("*.bin"))]
    preset, report = groundwork.calibrate(scans, sensor="hdl32e")
    scale = report["height_scale"]
    assert abs(scale["ratio"] - preset["mount"]["height"] / 1.84) < 1e-9, scale
    assert abs(scale["ratio"] - 0.8 / 1.84) < 0.05, scale
    zones = preset["zones"]
    assert zones["boundaries"] == scale["boundaries"]
    assert zones["boundaries"][0] == zones["min_range"] == report["near_edge"]["min_range"]
    assert zones["boundaries"][3:] == scale["was"][3:], zones
    out = tmp_path / "low-cal.toml"
    run(cli, "calibrate", "--sensor", "hdl32e", "--out", str(out), str(seq))
    text = out.read_text()
    assert f"boundaries = {zones['boundaries']!r}".replace("'", "") in text, (zones, text)
    _, kept = groundwork.calibrate(scans, sensor="hdl32e", keep_zones=True)
    assert "height_scale" not in kept and "near_edge" not in kept
    # The file names its preset: alone it is laid over hdl32e, as with sensor="hdl32e";
    # another preset is refused, naming both.
    alone = groundwork.Segmenter(frames=1, config=out).segment(scans[0])
    named = groundwork.Segmenter(sensor="hdl32e", frames=1, config=out).segment(scans[0])
    assert np.array_equal(alone, named)
    with pytest.raises(ValueError, match='"hdl32e".*"vlp16"|"vlp16".*"hdl32e"'):
        groundwork.Segmenter(sensor="vlp16", config=out)


def test_calibrate_finds_the_mount_and_segmenter_takes_it_in_degrees(cli: Path, tmp_path: Path) -> None:
    """The mount from the six bundled scans, as `groundwork calibrate` finds it (the CLI
    file's values), usable as keyword arguments; too few scans are refused."""
    scans = [kitti(s) for s in SCANS]
    preset, report = groundwork.calibrate(scans, sensor="hdl64e")
    mount = preset["mount"]
    assert report["frames_used"] == report["frames"] == len(SCANS)
    assert abs(mount["height"] - 1.707) < 0.02
    assert report["height"]["spread"] < 0.05
    # KITTI's road starts beyond the preset's 2.7 m near edge: the zones stay.
    near = report["near_edge"]
    assert near["ground_from"] > 3.0 and near["min_range"] is None, near
    assert "zones" not in preset and near["was"] == 2.7
    # KITTI's height is the preset's: the inner boundaries stay.
    assert "height_scale" not in report
    # A spinning sensor sees ground all around; the same scans cut to a forward sensor's
    # 90° window from 5 m on see it ahead only, and the report says what the mount assumes.
    assert "one_sided_ground" not in report
    ahead = [s[(s[:, 0] > 5.0) & (np.abs(s[:, 1]) < s[:, 0])] for s in scans]
    _, forward = groundwork.calibrate(ahead, sensor="hdl64e")
    one_sided = forward["one_sided_ground"]
    assert one_sided["leverage"] > 1.5 and 5.0 < one_sided["nearest_m"] < 8.0, one_sided
    assert "one side of the sensor only" in one_sided["caveat"]
    assert "near_edge" not in groundwork.calibrate(scans, sensor="hdl64e", keep_zones=True)[1]
    out = tmp_path / "mine.toml"
    subprocess.run(
        [str(cli), "calibrate", "--sensor", "hdl64e", "--out", str(out), str(SEQ)],
        check=True,
        capture_output=True,
    )
    text = out.read_text()
    for key, digits in [("height", 4), ("roll_deg", 3), ("pitch_deg", 3)]:
        assert f"{key} = {mount[key]:.{digits}f}" in text, (key, text)
    # The file keeps 0.1 mm and 0.001°: the same mount, rounded the same, segments the same.
    digits = {"height": 4, "roll_deg": 3, "pitch_deg": 3, "yaw_deg": 3}
    rounded = {k: round(v, digits[k]) for k, v in mount.items()}
    by_kwargs = groundwork.Segmenter(frames=1, mount=rounded)
    by_file = groundwork.Segmenter(frames=1, config=out)
    assert np.array_equal(by_kwargs.segment(scans[0]), by_file.segment(scans[0]))
    # Python writes the CLI's file: the same library call and writer, only the first line
    # (where the scans came from) differs.
    mine = tmp_path / "py" / "mine.toml"
    mine.parent.mkdir()
    groundwork.calibrate(scans, sensor="hdl64e", out=mine)
    ours, theirs = mine.read_text().splitlines(), text.splitlines()
    assert ours[1:] == theirs[1:] and len(ours) > 10, (ours, theirs)
    assert "scans given from Python" in ours[0] and str(SEQ) in theirs[0]
    with pytest.raises(ValueError, match="exists; pass overwrite=True"):
        groundwork.calibrate(scans, sensor="hdl64e", out=mine)
    groundwork.calibrate(scans, sensor="hdl64e", out=mine, overwrite=True)
    assert "summary" in report and "mount from 6 of 6 scans" in report["summary"]
    # Degrees and radians: the same mount, and not both at once.
    deg = groundwork.Segmenter(frames=1, mount={"height": 1.8, "pitch_deg": 2.0})
    rad = groundwork.Segmenter(frames=1, mount={"height": 1.8, "pitch": np.radians(2.0)})
    assert np.array_equal(deg.segment(scans[0]), rad.segment(scans[0]))
    with pytest.raises(ValueError, match="pitch_deg"):
        groundwork.Segmenter(mount={"pitch": 0.1, "pitch_deg": 2.0})
    with pytest.raises(ValueError, match="2 of 2 scans"):
        groundwork.calibrate(scans[:2])
    # The segmenter observes the mount too: told 5° of pitch, it sees the ground's.
    seg = groundwork.Segmenter(mount={"height": 1.73, "pitch_deg": 5.0})
    assert seg.observed_mount is None
    for s in scans:
        seg.segment(s)
    seen = seg.observed_mount
    assert seen["scans"] == len(scans)
    assert abs(seen["pitch_deg"] - mount["pitch_deg"]) < 1.0, seen
    assert seen["tilt_from_configured_deg"] > 3.0, seen
    # `warn` keeps the mount it was told; `correct` turns it towards the observed one.
    assert abs(seen["applied_pitch_deg"] - 5.0) < 1e-9 and seen["corrected_scans"] == 0, seen
    fast = {"mode": "correct", "warmup_scans": 1, "correct_rate_deg": 2.0}
    seg = groundwork.Segmenter(mount={"height": 1.73, "pitch_deg": 5.0}, mount_check=fast)
    for s in scans:
        seg.segment(s)
    moved = seg.observed_mount
    assert moved["corrected_scans"] >= 2, moved
    # Two degrees a scan from the second scan on: at least two of the five taken.
    before, after = 5.0 - moved["pitch_deg"], moved["applied_pitch_deg"] - moved["pitch_deg"]
    assert abs(after) < abs(before) - 2.0, moved
    assert groundwork.Segmenter(mount_check={"mode": "off"}).observed_mount is None


def as_written(mount: dict[str, float]) -> dict[str, float]:
    """A mount from `calibrate` as the CLI's file keeps it: to 0.1 mm and 0.001°."""
    digits = {"height": 4, "roll_deg": 3, "pitch_deg": 3, "yaw_deg": 3}
    return {k: round(v, digits[k]) for k, v in mount.items()}


def test_calibrate_fits_the_parameters_as_the_cli_does(cli: Path, tmp_path: Path) -> None:
    """After the mount, the likelihood parameters fitted to the PseudoLabeler's labels, as
    `groundwork calibrate` does by default: kept only on a clear held-out gain (on KITTI
    the preset already agrees on 98 %: kept), and, with the labels trusted everywhere and no
    bar (any held-out gain: 93.65 -> 93.71 measured), changed to exactly what the CLI
    writes: the two segment the same bits."""
    scans = [kitti(s) for s in SCANS]
    preset, report = groundwork.calibrate(scans, sensor="hdl64e")
    fit = report["parameters"]
    assert fit["kept_preset"] and not fit["changed"] and "ground" not in preset, fit
    assert (fit["fitted_scans"], fit["held_out_scans"]) == (5, 1), fit
    assert 95.0 < fit["held_out_before"]["iou"] == fit["held_out_after"]["iou"], fit
    assert "parameters" not in groundwork.calibrate(scans, sensor="hdl64e", keep_params=True)[1]
    # Three scans tell the mount but cannot hold one in four out: the preset's parameters.
    preset, report = groundwork.calibrate(scans[:3], sensor="hdl64e")
    assert "mount" in preset and "ground" not in preset and "parameters" not in report
    assert report["parameters_refused"].startswith("3 scans are too few"), report

    low_bar = {"param_trust": 0.0, "param_min_gain": 0.0}
    preset, report = groundwork.calibrate(scans, sensor="hdl64e", **low_bar)
    fit = report["parameters"]
    assert not fit["kept_preset"] and fit["changed"], fit
    assert fit["held_out_after"]["iou"] > fit["held_out_before"]["iou"], fit
    ground = preset["ground"]
    for change in fit["changed"]:
        section, _, key = change["name"].partition(".")
        assert section == "ground", change
        value = ground[key] if "." not in key else ground[key.split(".")[0]][key.split(".")[1]]
        # `ground_threshold` is an f32: the dict gives its exact value (0.6 is
        # 0.6000000238...), the change record the decimal the CLI writes.
        assert value == pytest.approx(change["new"], rel=1e-7), (change, ground)
    out = tmp_path / "fitted.toml"
    run(cli, "calibrate", "--sensor", "hdl64e", "--param-trust", "0", "--param-min-gain", "0",
        "--out", str(out), str(SEQ))
    assert "[ground]" in out.read_text()
    rounded = as_written(preset["mount"])
    by_kwargs = groundwork.Segmenter(sensor="hdl64e", frames=1, mount=rounded, ground=ground)
    by_file = groundwork.Segmenter(sensor="hdl64e", frames=1, config=out)
    mount_only = groundwork.Segmenter(sensor="hdl64e", frames=1, mount=rounded)
    for s in scans[:2]:
        assert np.array_equal(by_kwargs.segment(s), by_file.segment(s))
    assert not np.array_equal(mount_only.segment(scans[2]), by_kwargs.segment(scans[2]))
    with pytest.raises(ValueError, match="param_min_gain"):
        groundwork.calibrate(scans, param_min_gain=-1.0)
    with pytest.raises(ValueError, match="param_scans"):
        groundwork.calibrate(scans, param_scans=0)


def test_calibrate_fits_the_zones_as_the_cli_does(cli: Path, tmp_path: Path) -> None:
    """fit_zones, as `--fit-zones`: the inner zones' layout fitted with the parameters. On
    KITTI with the labels trusted everywhere and no bar it changes a zone's sectors (32 -> 26
    measured); the configuration holds the whole layout, and a Segmenter made from it gives
    the bits of one made from the CLI's file. Not with keep_params."""
    scans = [kitti(s) for s in SCANS]
    opts = {"param_trust": 0.0, "param_min_gain": 0.0}
    preset, report = groundwork.calibrate(scans, sensor="hdl64e", fit_zones=True, **opts)
    zones = preset["zones"]
    assert set(zones) == {"min_range", "boundaries", "rings", "sectors"}, zones
    changed = [c["name"] for c in report["parameters"]["changed"]]
    assert any(n.startswith("zones.") for n in changed), changed
    # Without fit_zones the layout is the preset's: KITTI's near edge does not move either.
    assert "zones" not in groundwork.calibrate(scans, sensor="hdl64e", **opts)[0]
    out = tmp_path / "zones.toml"
    run(cli, "calibrate", "--sensor", "hdl64e", "--fit-zones", "--param-trust", "0",
        "--param-min-gain", "0", "--out", str(out), str(SEQ))
    assert "sectors = " in out.read_text()
    mount = as_written(preset["mount"])
    by_kwargs = groundwork.Segmenter(
        sensor="hdl64e", frames=1, mount=mount, ground=preset["ground"], zones=zones
    )
    by_file = groundwork.Segmenter(sensor="hdl64e", frames=1, config=out)
    for s in scans[:2]:
        assert np.array_equal(by_kwargs.segment(s), by_file.segment(s))
    with pytest.raises(ValueError, match="fit_zones"):
        groundwork.calibrate(scans, keep_params=True, fit_zones=True)


def read_clouds(path: Path) -> list[tuple[int, int, str]]:
    """(log time, header stamp, frame id) of every PointCloud2 in a recording, read by the
    `mcap` package and decoded by `mcap-ros2-support`: readers groundwork did not write."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out = []
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, _channel, message, cloud in reader.iter_decoded_messages():
            if schema.name != "sensor_msgs/msg/PointCloud2":
                continue
            stamp = cloud.header.stamp.sec * 10**9 + cloud.header.stamp.nanosec
            out.append((message.log_time, stamp, cloud.header.frame_id))
    return out


def test_recordings_keep_the_input_stamps_and_frames(cli: Path, tmp_path: Path) -> None:
    # Written by mcap-ros2-support: three clouds at 10 Hz from 1700000000 s, frame os_lidar.
    fixture = ROOT / "crates/groundwork-io/tests/fixtures/kitti_pointcloud2.mcap"
    want = read_clouds(fixture)
    assert [t for t, _, _ in want] == [1_700_000_000_000_000_000 + k * 10**8 for k in range(3)]

    seg = tmp_path / "segment.mcap"
    run(cli, "segment", "--out", str(seg), str(fixture))
    assert read_clouds(seg) == want

    # Through the four processes: producer, segmenter, consumer over shared memory.
    piped = tmp_path / "pipeline.mcap"
    run(cli, "pipeline", "--count", "3", "--no-detector", "--prefix", f"gw-py-stamps-{os.getpid()}",
        "--data", str(fixture), "--out", str(piped))
    assert read_clouds(piped) == want

    # A KITTI-layout folder with a times.txt (synth writes one): its times, frame "lidar".
    synth = tmp_path / "synth"
    run(cli, "synth", "--sensor", "vlp16", "--frames", "3", "--out", str(synth))
    times = [round(float(t) * 1e9) for t in (synth / "times.txt").read_text().split()]
    assert times == [0, 10**8, 2 * 10**8]
    seg = tmp_path / "synth.mcap"
    run(cli, "segment", "--sensor", "vlp16", "--out", str(seg), str(synth))
    assert read_clouds(seg) == [(t, t, "lidar") for t in times]


def test_a_recording_from_a_recording_keeps_every_field_and_topic(cli: Path, tmp_path: Path) -> None:
    """Written by mcap-ros2-support: clouds with a `ring` field and padding, one organized
    with placeholders, one big-endian, and a `/chatter` topic. Read back by `mcap`."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    def messages(path: Path) -> list:
        with open(path, "rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            return [(ch.topic, msg.log_time, msg.data, decoded)
                    for _, ch, msg, decoded in reader.iter_decoded_messages(log_time_order=True)]

    fixture = ROOT / "crates/groundwork-io/tests/fixtures/kitti_pointcloud2.mcap"
    out = tmp_path / "out.mcap"
    run(cli, "segment", "--out", str(out), str(fixture))
    before, after = messages(fixture), messages(out)
    # Every other topic passed through as it was (same bytes, same times).
    chatter = lambda ms: [(t, d) for topic, t, d, _ in ms if topic == "/chatter"]  # noqa: E731
    assert chatter(after) == chatter(before) and len(chatter(before)) == 3
    clouds = lambda ms: [c for topic, _, _, c in ms if topic == "/points"]  # noqa: E731
    assert len(clouds(after)) == 3
    for src, dst in zip(clouds(before), clouds(after)):
        names = [f.name for f in src.fields]
        assert [f.name for f in dst.fields] == names + ["ground_probability"]
        assert (dst.height, dst.width, dst.is_bigendian) == (src.height, src.width, src.is_bigendian)
        n = src.height * src.width
        for r in range(n):
            row, col = divmod(r, src.width)
            a = src.data[row * src.row_step + col * src.point_step:][: src.point_step]
            b = dst.data[r * dst.point_step:][: dst.point_step]
            assert bytes(b[: src.point_step]) == bytes(a), f"record {r}: every input byte kept"
        order = ">" if src.is_bigendian else "<"
        offset = dst.fields[-1].offset
        probs = [np.frombuffer(bytes(dst.data[r * dst.point_step + offset:][:4]), dtype=order + "f4")[0]
                 for r in range(n)]
        assert all(0.0 <= p <= 1.0 for p in probs)
        assert sum(p >= 0.5 for p in probs) > n // 4


def test_recordings_place_the_scan_frame_by_the_mount(cli: Path, tmp_path: Path) -> None:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    fixture = ROOT / "crates/groundwork-io/tests/fixtures/kitti_pointcloud2.mcap"
    segmented, piped = tmp_path / "segment.mcap", tmp_path / "pipeline.mcap"
    # The hdl32e preset: 1.84 m up, turned −90° about z on its mount.
    run(cli, "segment", "--sensor", "hdl32e", "--out", str(segmented), str(fixture))
    run(cli, "pipeline", "--sensor", "hdl32e", "--count", "3", "--no-detector", "--prefix",
        f"gw-py-tf-{os.getpid()}", "--data", str(fixture), "--out", str(piped))
    for out in (segmented, piped):
        with open(out, "rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            found = [(msg.log_time, tf) for _, ch, msg, tf in reader.iter_decoded_messages()
                     if ch.topic == "/tf_static"]
        assert len(found) == 1, f"{out.name}: one transform for the one frame"
        log_time, tf = found[0]
        assert log_time == 1_700_000_000_000_000_000, "written with the first scan"
        (t,) = tf.transforms
        assert (t.header.frame_id, t.child_frame_id) == ("base_footprint", "os_lidar")
        v, q = t.transform.translation, t.transform.rotation
        assert (v.x, v.y, v.z) == pytest.approx((0.0, 0.0, 1.84), abs=1e-12)
        s = 0.5 ** 0.5
        assert (q.x, q.y, q.z, q.w) == pytest.approx((0.0, 0.0, -s, s), abs=1e-12)
