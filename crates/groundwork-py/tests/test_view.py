"""The live view against an independent client: a WebSocket client (the `websockets`
package) speaks Foxglove's protocol to `pipeline --view`, subscribes to every channel,
and decodes one message of each with Google's protobuf runtime from the schemas the server
advertises. The points must be the bundled scan's, the probabilities its mask's, the boxes
and the mount where they belong; a viewer that never reads and one that comes and goes
must not slow the pipeline."""

import asyncio
import base64
import json
import re
import signal
import socket
import struct
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import websockets
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

ROOT = Path(__file__).resolve().parents[3]
SCANS = sorted((ROOT / "tests/data/semantickitti-00/velodyne").glob("*.bin"))
PROTOCOL = "foxglove.sdk.v1"
TOPICS = ("/groundwork/points", "/groundwork/proposals", "/tf", "/groundwork/stats")
MOUNT_HEIGHT = 1.73  # config/sensors/hdl64e.toml, the default sensor


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def message_class(channel: dict):
    """The protobuf class of a channel, built from the FileDescriptorSet it advertises."""
    files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"])).file
    pool, pending = descriptor_pool.DescriptorPool(), list(files)
    while pending:  # dependencies first, whatever order the set lists them in
        added = [f for f in pending if all(d in {g.name for g in files if g not in pending}
                                           for d in f.dependency)]
        assert added, "a schema whose dependencies are missing"
        for f in added:
            pool.Add(f)
            pending.remove(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))


async def connect(url: str, timeout: float = 30):
    end = time.time() + timeout
    while True:
        try:
            return await websockets.connect(url, subprotocols=[PROTOCOL], max_size=None)
        except OSError:
            if time.time() > end:
                raise
            await asyncio.sleep(0.2)


async def take(url: str, topics: tuple, want: int = 1, timeout: float = 40) -> dict:
    """Subscribes to `topics` and returns, per topic, `want` decoded (log time, message)."""
    ws = await connect(url)
    try:
        assert ws.subprotocol == PROTOCOL
        channels, got, end = {}, {t: [] for t in topics}, time.time() + timeout
        while any(len(v) < want for v in got.values()):
            assert time.time() < end, {t: len(v) for t, v in got.items()}
            frame = await asyncio.wait_for(ws.recv(), timeout=end - time.time())
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg["op"] == "advertise":
                    new = [c for c in msg["channels"] if c["topic"] in topics]
                    for c in new:
                        channels[c["id"]] = c
                    if new:
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                            {"id": c["id"], "channelId": c["id"]} for c in new]}))
                continue
            opcode, sub, log_time = struct.unpack_from("<BIQ", frame)
            assert opcode == 1  # message data
            c = channels[sub]
            payload = frame[13:]
            if c["encoding"] == "json":
                assert c["schemaEncoding"] == "jsonschema"
                decoded = json.loads(payload)
            else:
                assert c["encoding"] == "protobuf"
                decoded = message_class(c).FromString(payload)
            if len(got[c["topic"]]) < want:
                got[c["topic"]].append((log_time, decoded))
        return got
    finally:
        await ws.close()


async def stall(url: str, seconds: float) -> None:
    """A viewer that subscribes to the points and then reads nothing."""
    ws = await connect(url)
    frame = await ws.recv()
    while not (isinstance(frame, str) and json.loads(frame)["op"] == "advertise"
               and any(c["topic"] == TOPICS[0] for c in json.loads(frame)["channels"])):
        frame = await ws.recv()
    points = next(c for c in json.loads(frame)["channels"] if c["topic"] == TOPICS[0])
    await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": points["id"]}]}))
    # Not reading: websockets stops taking frames off the socket once its queue is full.
    await asyncio.sleep(seconds)
    ws.transport.abort()


def test_foxglove_viewers_see_the_pipeline_live_without_slowing_it(cli: Path) -> None:
    port = free_port()
    url = f"ws://127.0.0.1:{port}"
    count, rate = 120, 10
    start = time.time()
    pipeline = subprocess.Popen(
        [str(cli), "pipeline", "--prefix", f"gw-py-view-{port}", "--count", str(count),
         "--rate", str(rate), "--view", f"127.0.0.1:{port}"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        async def viewers() -> tuple:
            slow = asyncio.create_task(stall(url, 6))
            first = await take(url, TOPICS, want=2)
            # It goes, and another comes.
            again = await take(url, (TOPICS[0], TOPICS[3]), want=3)
            await slow
            return first, again

        first, again = asyncio.run(viewers())
        out, err = pipeline.communicate(timeout=60)
    finally:
        if pipeline.poll() is None:
            pipeline.kill()
            pipeline.communicate()
    elapsed = time.time() - start
    assert pipeline.returncode == 0, err[-3000:]

    # The pipeline did all it was asked at its pace, viewers or not.
    assert f"consumer: {count} masks ({count} segmented, 0 rejected)" in out, out
    assert re.search(rf"scan fate: {count} masked \+ 0 rejected \+ 0 unanswered \+ 0 dropped", out), out
    assert elapsed < count / rate + 25, elapsed
    stopped = re.search(r"view stopped masks=(\d+) shown=(\d+) missed=(\d+) unmatched=(\d+)", err)
    assert stopped, err[-3000:]
    masks, shown, missed, _ = map(int, stopped.groups())
    assert masks + missed == count and missed == 0, stopped.group(0)
    assert shown >= 5, stopped.group(0)
    # The viewer that never read was really behind: the server dropped its oldest messages.
    assert "outbox for client" in err, err[-3000:]

    for got in (first, again):
        stats = {m["stamp_ns"]: m for _, m in got["/groundwork/stats"]}
        for log_time, s in got["/groundwork/stats"]:
            assert log_time == s["stamp_ns"]
            assert s["status"] == "ok" and s["masks"] >= 1 and s["clients"] >= 1
            assert 0 < s["ground_points"] < s["points"]
        for log_time, cloud in got["/groundwork/points"]:
            # The scan's stamp on the message and in it.
            assert log_time == cloud.timestamp.seconds * 10**9 + cloud.timestamp.nanos
            names = [f.name for f in cloud.fields]
            assert names[:5] == ["x", "y", "z", "intensity", "ground_probability"]
            assert {"red", "green", "blue", "alpha"} <= set(names)
            rows = np.frombuffer(cloud.data, np.uint8).reshape(-1, cloud.point_stride)
            floats = rows[:, :20].copy().view("<f4")
            prob = floats[:, 4]
            assert np.all((prob >= 0) & (prob <= 1))
            # Its points are the bundled scan's, bit for bit, when its figures came too.
            if log_time in stats:
                s = stats[log_time]
                scan = np.fromfile(SCANS[s["source_index"]], np.float32).reshape(-1, 4)
                assert len(rows) == s["points"] == len(scan)
                assert np.array_equal(floats[:, :4], scan)
                assert int(np.sum(prob >= s["ground_threshold"])) == s["ground_points"]
                assert cloud.frame_id == s["frame_id"]

    boxes = [m for _, m in first["/groundwork/proposals"]]
    for scene in boxes:
        assert [d.type for d in scene.deletions] == [1]  # ALL: the last scan's boxes go
        assert len(scene.entities) > 10
        for e in scene.entities:
            assert e.frame_id == "base_footprint" and len(e.cubes) == 1
            size = e.cubes[0].size
            assert size.x > 0 and size.y > 0 and size.z > 0
            assert {kv.key for kv in e.metadata} == {"class", "points"}
        assert any(kv.value == "object" for e in scene.entities for kv in e.metadata)

    frame = first["/groundwork/points"][0][1].frame_id
    for _, tf in first["/tf"]:
        (t,) = tf.transforms
        assert (t.parent_frame_id, t.child_frame_id) == ("base_footprint", frame)
        assert abs(t.translation.z - MOUNT_HEIGHT) < 1e-9
        q = t.rotation
        assert abs(q.x**2 + q.y**2 + q.z**2 + q.w**2 - 1) < 1e-9


def test_a_view_that_cannot_listen_says_where(cli: Path) -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        r = subprocess.run([str(cli), "view", "--prefix", f"gw-py-view-busy-{port}",
                            "--addr", f"127.0.0.1:{port}"], capture_output=True, text=True, timeout=30)
    assert r.returncode == 2
    assert f"cannot serve the view on 127.0.0.1:{port}" in r.stderr


def test_the_ros2_bridge_serves_a_view_beside_it(cli: Path) -> None:
    """`groundwork ros2 --view`: the view is a thread of the bridge, up with it, stopped with it."""
    port = free_port()
    bridge = subprocess.Popen(
        [str(cli), "ros2", "--prefix", f"gw-py-view-ros2-{port}", "--domain-id", str(100 + port % 100),
         "--view", f"127.0.0.1:{port}"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        async def advertised() -> set:
            ws = await connect(f"ws://127.0.0.1:{port}")
            topics: set = set()
            while not set(TOPICS) <= topics:
                msg = json.loads(await asyncio.wait_for(ws.recv(), timeout=10))
                if msg["op"] == "advertise":
                    topics |= {c["topic"] for c in msg["channels"]}
            await ws.close()
            return topics

        assert set(TOPICS) <= asyncio.run(advertised())
        bridge.send_signal(signal.SIGINT)
        _, err = bridge.communicate(timeout=30)
    finally:
        if bridge.poll() is None:
            bridge.kill()
            bridge.communicate()
    assert bridge.returncode == 0, err[-3000:]
    assert "view stopped" in err and "ROS 2 bridge stopped" in err


def test_recordings_hold_the_proposals_as_boxes_at_their_scans_stamps(cli: Path, tmp_path: Path) -> None:
    """A pipeline recording opens in Foxglove with boxes on the cloud: foxglove.SceneUpdate
    (protobuf, the schema in the file) at each scan's stamp, the boxes `detect` finds."""
    from mcap.reader import make_reader

    # Written by mcap-ros2-support: three clouds at 10 Hz from 1700000000 s.
    fixture = ROOT / "crates/groundwork-io/tests/fixtures/kitti_pointcloud2.mcap"
    recorded = tmp_path / "pipeline.mcap"
    subprocess.run([str(cli), "pipeline", "--count", "3", "--prefix", f"gw-py-boxes-{free_port()}",
                    "--data", str(fixture), "--out", str(recorded)], check=True, capture_output=True)
    subprocess.run([str(cli), "detect", "--out", str(tmp_path / "det"), str(fixture)], check=True,
                   capture_output=True)
    detected = [json.loads(p.read_text())["proposals"]
                for p in sorted((tmp_path / "det").glob("*.proposals.json"))]

    points, scenes = [], []
    with open(recorded, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            if channel.topic == "/points":
                points.append(message.log_time)
            elif channel.topic == "/proposals":
                assert (channel.message_encoding, schema.encoding) == ("protobuf", "protobuf")
                c = {"schema": base64.b64encode(schema.data), "schemaName": schema.name}
                assert schema.name == "foxglove.SceneUpdate"
                scenes.append((message.log_time, message_class(c).FromString(message.data)))
    assert points == [1_700_000_000_000_000_000 + k * 10**8 for k in range(3)]
    # Each scan's boxes at its stamp (the last scan's may miss the consumer's stop).
    assert len(scenes) >= 2 and [t for t, _ in scenes] == points[:len(scenes)]
    for (stamp, scene), want in zip(scenes, detected):
        assert [d.type for d in scene.deletions] == [1]
        assert len(scene.entities) == len(want) > 0
        for e, p in zip(scene.entities, want):
            assert e.id == str(p["id"]) and e.frame_id == "base_footprint"
            assert e.timestamp.seconds * 10**9 + e.timestamp.nanos == stamp
            (cube,) = e.cubes
            centre = (p["center"][0], p["center"][1], p["ground_z"] + 0.5 * (p["bottom"] + p["height"]))
            assert (cube.pose.position.x, cube.pose.position.y, cube.pose.position.z) == \
                pytest.approx(centre, abs=1e-5)
            assert (cube.size.x, cube.size.y, cube.size.z) == \
                pytest.approx((p["length"], p["width"], p["height"] - p["bottom"]), abs=1e-5)
            cls = {kv.key: kv.value for kv in e.metadata}["class"]
            assert cls == ("+".join(p["flags"]) if p["flags"] else "object")
