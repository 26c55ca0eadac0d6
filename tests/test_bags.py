"""ROS bags (issue 35): ``sensor_msgs/PointCloud2`` frames of a topic, ROS 1 and ROS 2, written
by the tests, read without a ROS installation."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import sdp
from sdp.io import CloudFileError

pytest.importorskip("rosbags")
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from sdp.cli import watch_folder  # noqa: E402
from sdp.io._bag import bag_frames, bag_topics  # noqa: E402

TS = get_typestore(Stores.ROS2_HUMBLE)
TS1 = get_typestore(Stores.ROS1_NOETIC)
MSGTYPE = "sensor_msgs/msg/PointCloud2"
DATATYPE = {"i1": 1, "u1": 2, "i2": 3, "u2": 4, "i4": 5, "u4": 6, "f4": 7, "f8": 8}
GRABBER = "pcl_kinect/grabber_sequence"


def message(records: np.ndarray, height: int, width: int, *, pad: int = 0, stamp: int = 0, ts=TS):
    """A PointCloud2 (of ``ts``'s ROS version) of a structured array (its fields at their
    offsets), each row padded by ``pad`` bytes."""
    PC2, PF = ts.types[MSGTYPE], ts.types["sensor_msgs/msg/PointField"]
    HEADER, TIME = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    header = dict(seq=0) if ts is TS1 else {}
    step = records.dtype.itemsize
    fields = [PF(name=n, offset=records.dtype.fields[n][1], datatype=DATATYPE[records.dtype[n].str[1:]], count=1)
              for n in records.dtype.names]
    rows = records.reshape(height, width)
    data = b"".join(r.tobytes() + bytes(pad) for r in rows)
    return PC2(header=HEADER(**header, stamp=TIME(sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id="sensor"),
               height=height, width=width, fields=fields, is_bigendian=records.dtype.str[0] == ">",
               point_step=step, row_step=step * width + pad, data=np.frombuffer(data, np.uint8), is_dense=False)


def write_ros2(path: Path, messages, topic="/points", mcap=False):
    """A ROS 2 bag in SQLite (the default before ROS 2 Iron) or MCAP (since)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP if mcap else StoragePlugin.SQLITE3) as w:
        conn = w.add_connection(topic, MSGTYPE, typestore=TS)
        for stamp, msg in messages:
            w.write(conn, stamp, TS.serialize_cdr(msg, MSGTYPE))
    return path


def write_ros1(path: Path, messages, topic="/points"):
    from rosbags.rosbag1 import Writer

    with Writer(path) as w:
        conn = w.add_connection(topic, MSGTYPE, typestore=TS1)
        for stamp, msg in messages:
            w.write(conn, stamp, TS1.serialize_ros1(msg, MSGTYPE))
    return path


def pcd_message(path, stamp):
    from pypcd4 import PointCloud

    pc = PointCloud.from_path(path)
    return stamp, message(pc.pc_data, pc.metadata.height, pc.metadata.width, stamp=stamp)


def small_frames():
    """Two 4×5 organized frames: a missing return as NaN, one as (0, 0, 0), an intensity (f8), a pad byte per row."""
    dtype = np.dtype({"names": ["x", "y", "z", "intensity"], "formats": ["<f4", "<f4", "<f4", "<f8"],
                      "offsets": [0, 4, 8, 16], "itemsize": 32})
    out = []
    for k in range(2):
        rec = np.zeros(20, dtype)
        g = np.arange(20)
        rec["x"], rec["y"], rec["z"], rec["intensity"] = g % 5 + k, g // 5, 1.0 + k, g * 0.5
        rec["x"][3] = np.nan
        rec[["x", "y", "z"]][7] = (0, 0, 0)
        out.append(rec)
    return out


@pytest.mark.parametrize("version", [1, 2, "2 mcap"])
def test_bag_frames_read_pointcloud2_as_pcd_files_are_read(tmp_path, version):
    frames = small_frames()
    ts = TS1 if version == 1 else TS
    msgs = [(10**9 * (k + 1), message(r, 4, 5, pad=3, stamp=10**9 * (k + 1), ts=ts)) for k, r in enumerate(frames)]
    path = (write_ros1(tmp_path / "b.bag", msgs) if version == 1
            else write_ros2(tmp_path / "b2", msgs, mcap=version == "2 mcap"))
    assert bag_topics(path) == {"/points": 2}
    got = list(bag_frames(path, "/points"))
    assert [name for name, _ in got] == ["000000@1000000000", "000001@2000000000"]
    for rec, (_, cloud) in zip(frames, got):
        keep = np.ones(20, bool)
        keep[[3, 7]] = False
        assert cloud.n_dropped == 2 and cloud.organized
        assert np.array_equal(cloud.xyz, np.c_[rec["x"], rec["y"], rec["z"]][keep].astype(np.float64))
        assert np.array_equal(cloud.fields["intensity"], rec["intensity"][keep])
        assert np.array_equal(cloud.sensor_origin, [0, 0, 0])  # the message frame's origin


def test_a_second_message_given_as_the_current_says_one_topic_serves_both(tmp_path):
    """`sdp change BAG --topic /points:0 /points:1` took the second message for a file: "unknown point-cloud format
    '(no extension)'"."""
    from sdp.cli import compare_files

    bag = write_ros2(tmp_path / "b", [(k + 1, message(f, 4, 5, stamp=k + 1)) for k, f in enumerate(small_frames())])
    with pytest.raises(sdp.SDPError, match=r"^/points:1: no such file; --topic names one message for both inputs: "
                                           r"compare the messages of .*b with sdp watch BAG BAG --topic /points:0"):
        compare_files(bag, "/points:1", output=tmp_path / "o.npz", topic="/points:0")
    r = subprocess.run([sys.executable, "-m", "sdp.cli", "change", "b", "--topic", "/points:0", "/points:1", "-o",
                        "o.npz"], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "--topic names one message for both inputs" in r.stderr
    assert sorted(f.name for f in tmp_path.iterdir()) == ["b"]
    with pytest.raises(sdp.SDPError, match="--topic names one message for both inputs"):  # the first, without :0
        compare_files(bag, "/points:1", output=tmp_path / "o.npz", topic="/points")


def test_a_bag_without_the_topic_lists_its_topics(tmp_path):
    path = write_ros2(tmp_path / "b2", [(1, message(small_frames()[0], 4, 5))], topic="/lidar")
    with pytest.raises(CloudFileError, match=r"no topic '/points'; its PointCloud2 topics: /lidar"):
        bag_frames(path, "/points")
    with pytest.raises(sdp.SDPError, match=r"give --topic, one of its PointCloud2 topics \(/lidar \(1 messages\)\)"):
        watch_folder(np.zeros((10, 3)), path)
    with pytest.raises(sdp.SDPError, match=r"sdp watch reads every message of the bag; give TOPIC"):
        watch_folder(np.zeros((10, 3)), path, topic="/lidar:5")  # once every frame, N ignored
    with pytest.raises(sdp.SDPError, match=r"--format reads point-cloud files, not a ROS bag's messages"):
        watch_folder(path, path, topic="/lidar:0", format="las")  # once read the bags and ignored it
    with pytest.raises(sdp.SDPError, match=r"--format reads point-cloud files, not a ROS bag's messages"):
        sdp.compare_files(path, write_ros1(tmp_path / "b1.bag", [(1, message(small_frames()[0], 4, 5, ts=TS1))],
                                           "/lidar"),
                          output=tmp_path / "never.ply", topic="/lidar:0", format="las")


def test_a_topic_without_messages_is_refused_as_an_empty_folder_is(tmp_path):
    path = write_ros2(tmp_path / "b2", [], topic="/points")  # declared, never written to
    with pytest.raises(CloudFileError, match=r"'/points' holds 0 messages"):
        bag_frames(path, "/points")
    with pytest.raises(CloudFileError, match=r"holds 0 messages"):  # sdp watch once printed nothing, exit 0
        np.save(tmp_path / "r.npy", np.random.default_rng(0).random((100, 3)))
        next(iter(watch_folder(tmp_path / "r.npy", path, topic="/points")))


def test_sdp_info_lists_a_bags_pointcloud2_topics(tmp_path):
    path = write_ros2(tmp_path / "b2", [(1, message(small_frames()[0], 4, 5))] * 2, topic="/lidar")
    from sdp.cli._files import describe_file

    assert describe_file(path) == {"kind": "ROS bag", "pointcloud2_topics": {"/lidar": 2}}


def test_corrupt_bag_is_one_line(tmp_path):
    good = write_ros1(tmp_path / "good.bag", [(1, message(small_frames()[0], 4, 5, ts=TS1))])
    (tmp_path / "cut.bag").write_bytes(good.read_bytes()[:300])
    ref = tmp_path / "ref.npy"
    np.save(ref, np.random.default_rng(0).random((500, 3)))
    p = subprocess.run([sys.executable, "-m", "sdp.cli", "watch", ref, tmp_path / "cut.bag", "--topic", "/points"],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 2 and p.stderr.startswith("sdp: error: ") and len(p.stderr.strip().splitlines()) == 1
    assert "cut.bag: can't read as a ROS bag" in p.stderr


def test_without_the_extra_says_how_to_install(monkeypatch, tmp_path):
    path = write_ros1(tmp_path / "b.bag", [(1, message(small_frames()[0], 4, 5, ts=TS1))])
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)
    with pytest.raises(sdp.MissingDependencyError, match=r"pip install 'sdp\[scans\]'"):
        bag_frames(path, "/points")


@pytest.mark.slow
@pytest.mark.shared_data
def test_grabber_sequence_as_a_ros2_bag_gives_the_states_of_its_pcd_folder(shared_data, tmp_path):
    folder = shared_data / GRABBER
    pcds = sorted(folder.glob("*.pcd"))
    bag = write_ros2(tmp_path / "grabber", [pcd_message(p, 10**9 + 250_000_000 * i) for i, p in enumerate(pcds)],
                     topic="/camera/depth/points")
    from_files = list(watch_folder(pcds[0], folder))
    from_bag = list(watch_folder(pcds[0], bag, topic="/camera/depth/points"))
    assert len(from_files) == len(from_bag) == 3
    assert sum(int(f.appeared.sum()) for f in from_files) > 1000  # the sequence has changes to find
    for a, b in zip(from_files, from_bag):
        assert np.array_equal(a.appeared, b.appeared) and np.array_equal(a.not_comparable, b.not_comparable)
        assert np.array_equal(a.appeared_labels, b.appeared_labels)
    p = subprocess.run([sys.executable, "-m", "sdp.cli", "watch", pcds[0], bag, "--topic", "/camera/depth/points",
                        "--json"], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    frames = [json.loads(line) for line in p.stdout.splitlines()]
    assert [f["appeared"] for f in frames] == [int(f.appeared.sum()) for f in from_files]
    assert [f["not_comparable"] for f in frames] == [int(f.not_comparable.sum()) for f in from_files]


@pytest.mark.slow
@pytest.mark.shared_data
def test_sdp_change_reads_a_message_of_a_bag_as_its_pcd_file(shared_data, tmp_path):
    from sdp.cli import compare_files

    pcds = sorted((shared_data / GRABBER).glob("*.pcd"))
    bag = write_ros2(tmp_path / "grabber", [pcd_message(p, 10**9 * (i + 1)) for i, p in enumerate(pcds)])
    files = compare_files(pcds[0], pcds[2], output=tmp_path / "files.npz", outputs=sdp.Outputs(both=True))
    last = compare_files(pcds[0], bag, output=tmp_path / "bag.npz", topic="/points:-1", outputs=sdp.Outputs(both=True))
    assert last.summary["current"].pop("frame") == "sensor"  # the message's header.frame_id; a file names none
    for cloud in ("current", "reference"):
        assert files.summary[cloud] == last.summary[cloud]
    a, b = np.load(tmp_path / "files.npz"), np.load(tmp_path / "bag.npz")
    assert np.array_equal(a["change"], b["change"]) and a["change"].any()
    with pytest.raises(sdp.SDPError, match="give --topic"):
        compare_files(pcds[0], bag, output=tmp_path / "no.npz")


def test_fields_of_several_values_split_and_world_frames_have_no_sensor(tmp_path):
    """A PointField of count 3 becomes three fields, as a PCD file's; a cloud in a world frame
    (REP 105: map, odom) says nothing of its sensor, one in a sensor's frame puts it at the origin."""
    import dataclasses

    dtype = np.dtype({"names": ["x", "y", "z", "n0", "n1", "n2"], "formats": ["<f4"] * 6,
                      "offsets": [0, 4, 8, 12, 16, 20], "itemsize": 24})
    rec = np.zeros(6, dtype)
    rec["x"], rec["n1"] = np.arange(6), 1.0
    msg = message(rec, 1, 6)
    PF = TS.types["sensor_msgs/msg/PointField"]
    msg = dataclasses.replace(msg, fields=[*msg.fields[:3], PF(name="normal", offset=12, datatype=7, count=3)])
    world = dataclasses.replace(msg, header=dataclasses.replace(msg.header, frame_id="/map"))
    bag = write_ros2(tmp_path / "b", [(1, msg), (2, world)])
    (_, sensor), (_, mapped) = bag_frames(bag, "/points")
    assert sorted(sensor.fields) == ["normal__0000", "normal__0001", "normal__0002"]
    np.testing.assert_array_equal(sensor.fields["normal__0001"], 1.0)
    assert np.array_equal(sensor.sensor_origin, [0, 0, 0]) and mapped.sensor_origin is None


def test_sdp_change_names_the_bag_message_and_refuses_one_message_against_itself(shared_data, tmp_path):
    from sdp.cli import compare_files

    pcds = sorted((shared_data / GRABBER).glob("*.pcd"))
    bag = write_ros2(tmp_path / "grabber", [pcd_message(p, 10**9 * (i + 1)) for i, p in enumerate(pcds)])
    r = compare_files(pcds[0], bag, output=tmp_path / "bag.npz", topic="/points:1")
    assert r.current == f"{bag} (/points:1)" and r.summary["inputs"] == [str(pcds[0]), r.current]
    assert "(/points:1)" in r.summary_text()
    with pytest.raises(sdp.SDPError, match="would be the same message") as refused:
        compare_files(bag, bag, output=tmp_path / "same.npz", topic="/points:1")
    # what the refusal advises works: a bag's message as the reference of its own stream
    assert "sdp watch BAG_OR_REFERENCE BAG" in str(refused.value)
    from_bag = list(watch_folder(bag, bag, topic="/points:0"))
    from_files = list(watch_folder(pcds[0], bag, topic="/points"))
    assert len(from_bag) == 3 and not from_bag[0].appeared.any()  # the reference against itself
    for a, b in zip(from_bag, from_files):
        assert np.array_equal(a.appeared, b.appeared) and np.array_equal(a.not_comparable, b.not_comparable)
    with pytest.raises(sdp.SDPError, match="missing.bag: no such file"):
        compare_files(pcds[0], tmp_path / "missing.bag", output=tmp_path / "m.npz", topic="/points")
    assert sorted(f.name for f in tmp_path.iterdir()) == ["bag.npz", "grabber"]


def room(n=3000, seed=0):
    """An unorganized PointCloud2's records: the floor and two walls of a 4 m room."""
    rng = np.random.default_rng(seed)
    u, v = rng.random((2, n)) * 4
    side = rng.integers(0, 3, n)
    xyz = np.where(side[:, None] == 0, np.c_[u, v, 0 * u], np.where(side[:, None] == 1, np.c_[u, 0 * u, v / 2],
                                                                     np.c_[0 * u, u, v / 2]))
    rec = np.zeros(n, np.dtype({"names": ["x", "y", "z"], "formats": ["<f4"] * 3, "offsets": [0, 4, 8],
                                "itemsize": 12}))
    rec["x"], rec["y"], rec["z"] = xyz.T
    return rec


def in_frame(msg, frame):
    import dataclasses

    return dataclasses.replace(msg, header=dataclasses.replace(msg.header, frame_id=frame))


def test_clouds_in_different_frames_are_refused_unless_aligned(tmp_path):
    """A cloud in map against one in a camera's frame was compared as if both were in one frame."""
    mapped = write_ros2(tmp_path / "map", [(1, in_frame(message(room(), 1, 3000), "map"))])
    camera = write_ros2(tmp_path / "cam", [(1, in_frame(message(room(), 1, 3000), "camera_link")),
                                           (2, in_frame(message(room(), 1, 3000), "/camera_link"))])
    with pytest.raises(sdp.InvalidPointsError, match=r"in frame 'map', .*cam \(/points\) in frame 'camera_link'"):
        sdp.compare_files(mapped, camera, output=tmp_path / "no.npz", topic="/points")
    np.save(tmp_path / "ref.npy", np.c_[room()["x"], room()["y"], room()["z"]].astype(float))
    sdp.compare_files(tmp_path / "ref.npy", camera, output=tmp_path / "file.npz", topic="/points")  # a file: no frame
    r = sdp.compare_files(mapped, camera, output=tmp_path / "aligned.npz", topic="/points", align="gicp")
    assert r.alignment is not None
    # sdp watch: a bag's message against its frames, one of them in another frame
    stream = write_ros2(tmp_path / "stream", [(1, in_frame(message(room(), 1, 3000), "camera_link")),
                                              (2, in_frame(message(room(), 1, 3000), "/camera_link")),
                                              (3, in_frame(message(room(), 1, 3000), "odom"))])
    frames = watch_folder(stream, stream, topic="/points:0")
    assert len([next(frames), next(frames)]) == 2  # a leading / is the same frame
    with pytest.raises(sdp.InvalidPointsError, match=r"frame 000002@3 in frame 'odom'"):
        next(frames)
    frames.close()
    p = subprocess.run([sys.executable, "-m", "sdp.cli", "change", mapped, camera, "--topic", "/points", "-o",
                        tmp_path / "cli.ply"], capture_output=True, text=True, timeout=300)
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1 and "'camera_link'" in p.stderr


@pytest.mark.parametrize("frame", ["base_link", "/base_footprint", "map"])
def test_a_cloud_in_a_body_or_world_frame_has_no_sensor_and_the_summary_says_why(tmp_path, frame):
    """A cloud in base_link once put its sensor at the body's origin (a chair: 0.6 % found instead of 44.9 %)."""
    bag = write_ros2(tmp_path / "b", [(1, in_frame(message(room(), 1, 3000), frame)),
                                      (2, in_frame(message(room(seed=1), 1, 3000), frame))])
    assert all(c.sensor_origin is None and c.frame == frame.lstrip("/") for _, c in bag_frames(bag, "/points"))
    np.save(tmp_path / "ref.npy", np.c_[room()["x"], room()["y"], room()["z"]].astype(float))
    r = sdp.compare_files(tmp_path / "ref.npy", bag, output=tmp_path / "o.npz", topic="/points:1")
    assert r.summary["coverage"]["disappeared"] == "footprint" and r.summary["current"]["frame"] == frame.lstrip("/")
    kind = "a world frame" if frame == "map" else "a robot's body frame"
    assert f"current's footprint (no sensor position known: '{frame.lstrip('/')}' is {kind})" in r.summary_text()


@pytest.mark.parametrize("fault, said", [
    ("huge", r"b /points message 1: coordinates up to 3.4e\+38, beyond ±1e\+12, which no scene reaches"),
    ("overlap", r"b /points message 1: PointCloud2 fields 'x' \(bytes 0–3\) and 'y' \(bytes 2–5\) overlap"),
    ("signalling NaN", None)], ids=["huge", "overlap", "signalling NaN"])
def test_a_corrupt_message_is_one_line_naming_bag_topic_and_message(tmp_path, fault, said):
    """Corrupt messages leaked numpy's RuntimeWarnings and ended in a voxel or offset error naming nothing."""
    import dataclasses
    import warnings

    rec = room()
    msg = message(rec, 1, 3000)
    if fault == "huge":
        rec["x"][5] = 3.4e38
        msg = message(rec, 1, 3000)
    elif fault == "overlap":
        PF = TS.types["sensor_msgs/msg/PointField"]
        msg = dataclasses.replace(msg, fields=[PF(name="x", offset=0, datatype=7, count=1),
                                               PF(name="y", offset=2, datatype=7, count=1),
                                               PF(name="z", offset=8, datatype=7, count=1)])
    else:
        rec["y"].view(np.uint32)[10] = 0x7FA00000  # a float32 signalling NaN: a missing return as any NaN
        msg = message(rec, 1, 3000)
    bag = write_ros2(tmp_path / "b", [(1, message(room(), 1, 3000)), (2, msg)])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        frames = bag_frames(bag, "/points")
        next(frames)
        if said is None:
            assert next(frames)[1].n_dropped == 1
        else:
            with pytest.raises(CloudFileError, match=said):
                next(frames)


def test_a_corrupt_pcd_frame_is_named_by_sdp_watch(tmp_path):
    """A PCD frame of sdp watch FOLDER: a signalling NaN is a missing return, coordinates the lattice can't place
    are refused naming the file."""
    import warnings

    def pcd(path, xyz):
        head = (f"VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {len(xyz)}\nHEIGHT 1\n"
                f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(xyz)}\nDATA binary\n")
        path.write_bytes(head.encode() + np.asarray(xyz, "<f4").tobytes())

    xyz = np.c_[room()["x"], room()["y"], room()["z"]]
    np.save(tmp_path / "ref.npy", xyz.astype(float))
    (tmp_path / "frames").mkdir()
    snan, huge = xyz.copy(), xyz.copy()
    snan.view(np.uint32)[10, 1] = 0x7FA00000
    huge[5, 0] = 3.4e38
    pcd(tmp_path / "frames" / "0001.pcd", snan)
    pcd(tmp_path / "frames" / "0002.pcd", huge)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        frames = watch_folder(tmp_path / "ref.npy", tmp_path / "frames")
        assert next(frames).name == "0001.pcd"
        with pytest.raises(sdp.InvalidPointsError, match=r"^frame 0002.pcd: coordinates up to 3.4e\+38 are"):
            next(frames)


def test_one_bag_as_its_folder_and_its_storage_file_is_refused_as_one_message_against_itself(tmp_path):
    bag = write_ros2(tmp_path / "b", [(1, message(room(), 1, 3000)), (2, message(room(seed=1), 1, 3000))])
    (db3,) = bag.glob("*.db3")
    for ref, cur in ((bag, db3), (db3, bag), (db3, tmp_path / "." / "b" / db3.name)):
        with pytest.raises(sdp.SDPError, match="would be the same message"):
            sdp.compare_files(ref, cur, output=tmp_path / "same.npz", topic="/points:1")
    assert sorted(f.name for f in tmp_path.iterdir()) == ["b"]


def tf_message(stamp: int, *links):
    """A tf2_msgs/TFMessage of (parent, child, translation, rotation as a scipy Rotation) links."""
    T = TS.types
    HEADER, TIME = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
    out = []
    for parent, child, xyz, rot in links:
        x, y, z, w = rot.as_quat()
        out.append(T["geometry_msgs/msg/TransformStamped"](
            header=HEADER(stamp=TIME(sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id=parent),
            child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](translation=T["geometry_msgs/msg/Vector3"](x=xyz[0], y=xyz[1],
                                                                                                  z=xyz[2]),
                                                      rotation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w))))
    return T["tf2_msgs/msg/TFMessage"](transforms=out)


def moving_robot_bag(path, *, tf=True):
    """A robot driving through a static room (map → base_link: x 0 → 2 m, yaw 0 → 90° between 1 s and 3 s; its
    camera 1 m above the body on /tf_static), its camera's clouds at 2 s and 2.5 s in the camera's frame; then one
    at 9 s (after the last /tf) and one in a frame /tf does not know (9.5 s). The room's points in map are returned
    too."""
    from rosbags.rosbag2 import Writer
    from scipy.spatial.transform import Rotation

    camera = (np.array([0.0, 0, 1]), Rotation.from_euler("xyz", [-90, 0, -90], degrees=True))  # optical frame

    def pose(s):  # map → base_link at s seconds (1 ≤ s ≤ 3)
        f = (s - 1) / 2
        return np.array([2 * f, 0, 0]), Rotation.from_euler("z", 90 * f, degrees=True)

    def seen(xyz, s):  # room points (map) in the camera's frame at s
        (t, r), (tc, rc) = pose(s), camera
        return rc.inv().apply(r.inv().apply(xyz - t) - tc)

    clouds, truth = [], []
    for k, (s, frame) in enumerate([(2.0, "camera"), (2.5, "camera"), (9.0, "camera"), (9.5, "lidar")]):
        rec = room(seed=k)
        xyz = np.c_[rec["x"], rec["y"], rec["z"]].astype(float)
        truth.append(xyz)
        rec["x"], rec["y"], rec["z"] = seen(xyz, min(s, 3.0)).T
        stamp = int(s * 10**9)
        clouds.append((stamp, in_frame(message(rec, 1, 3000, stamp=stamp), frame)))
    with Writer(path, version=9) as w:
        conn = w.add_connection("/points", MSGTYPE, typestore=TS)
        if tf:
            dyn = w.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=TS)
            fixed = w.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=TS)
            w.write(fixed, 0, TS.serialize_cdr(tf_message(0, ("base_link", "camera", *camera)),
                                              "tf2_msgs/msg/TFMessage"))
            for s in (1.0, 3.0):
                t = int(s * 10**9)
                w.write(dyn, t, TS.serialize_cdr(tf_message(t, ("map", "base_link", *pose(s))), "tf2_msgs/msg/TFMessage"))
        for stamp, msg in clouds:
            w.write(conn, stamp, TS.serialize_cdr(msg, MSGTYPE))
    return path, truth


def test_tf_moves_each_message_into_map_at_its_stamp(tmp_path):
    """/tf and /tf_static were ignored: a cloud in a moving camera's frame stayed there."""
    bag, truth = moving_robot_bag(tmp_path / "robot")
    (_, a), (_, b), (_, late), (_, lidar) = bag_frames(bag, "/points")
    for cloud, xyz in ((a, truth[0]), (b, truth[1])):
        assert cloud.frame == "map" and cloud.tf == "moved from 'camera' into 'map' with /tf"
        np.testing.assert_allclose(cloud.xyz, xyz, atol=1e-5)  # interpolated, translation and rotation
    np.testing.assert_allclose(a.sensor_origin, [1, 0, 1], atol=1e-9)  # the camera's origin in map at 2 s
    np.testing.assert_allclose(b.sensor_origin, [1.5, 0, 1], atol=1e-9)
    assert late.frame == "camera" and late.tf == ("left in 'camera': /tf holds 'map' → 'base_link' from 1.000 s to "
                                                  "3.000 s, not at its stamp (no extrapolation, as tf2)")
    assert lidar.frame == "lidar" and lidar.tf == "left in 'lidar': no /tf chain into 'map' ('lidar' has no parent in /tf)"
    assert np.array_equal(lidar.sensor_origin, [0, 0, 0])  # left as it is: the sensor at its frame's origin
    np.save(tmp_path / "map.npy", truth[0])
    r = sdp.compare_files(tmp_path / "map.npy", bag, output=tmp_path / "o.npz", topic="/points:1")
    assert r.summary["current"]["tf"] == b.tf and r.summary["current"]["frame"] == "map"
    assert "the current's message: moved from 'camera' into 'map' with /tf" in r.summary_text()


def test_tf_makes_a_static_room_seen_by_a_moving_robot_unchanged(tmp_path):
    """A moving robot's frames of a static room, compared in the camera's frame, flag much of the room."""
    import warnings

    from sdp.io import ReadNotice

    share = {}
    for tf in (False, True):
        bag, _ = moving_robot_bag(tmp_path / f"robot{tf}", tf=tf)
        frames = watch_folder(bag, bag, topic="/points:0")
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            next(frames)
            moved = next(frames)  # the camera 0.5 m and 22.5° on
        assert [str(w.message).split(": ", 1)[1] for w in said if w.category is ReadNotice] == \
            ["frames moved from 'camera' into 'map' with /tf (from frame 000000@2000000000)"] * tf
        frames.close()
        share[tf] = (moved.n_appeared + moved.not_comparable.sum()) / len(moved.appeared)
    assert share[False] > 0.1 and share[True] < 0.005  # 18.3 % appeared or not comparable → 0


def test_a_frames_name_is_its_index_and_the_time_the_bag_recorded_it_not_its_header_stamp(tmp_path):
    bag = write_ros2(tmp_path / "b", [(5 * 10**9 + 7, message(room(), 1, 3000, stamp=10**9))])
    assert [name for name, _ in bag_frames(bag, "/points")] == ["000000@5000000007"]


def test_tf_says_why_a_message_is_left_in_its_frame_and_refuses_a_child_of_two_parents(tmp_path):
    """A base_link given by odom and by map (5 m apart) once moved a cloud by 5 m between two stamps 1 ns apart, both
    said 'moved into odom'; an unstamped message and one after the last /tf were both 'no /tf chain at its stamp'."""
    from rosbags.rosbag2 import Writer
    from scipy.spatial.transform import Rotation

    still = Rotation.identity()
    rec = room()
    clouds = [(stamp, in_frame(message(rec, 1, 3000, stamp=stamp), "/camera")) for stamp in (0, 2 * 10**9, 4 * 10**9)]
    for two in (False, True):
        with Writer(tmp_path / f"b{two}", version=9) as w:
            conn = w.add_connection("/points", MSGTYPE, typestore=TS)
            dyn = w.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=TS)
            fixed = w.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=TS)
            w.write(fixed, 1, TS.serialize_cdr(tf_message(1, ("base_link", "camera", (0, 0, 1), still)),
                                               "tf2_msgs/msg/TFMessage"))
            for s in (1, 3):
                links = [("odom", "base_link", (s, 0, 0), still)] + [("map", "base_link", (s + 5, 0, 0), still)] * two
                w.write(dyn, s * 10**9, TS.serialize_cdr(tf_message(s * 10**9, *links), "tf2_msgs/msg/TFMessage"))
            for stamp, msg in clouds:
                w.write(conn, stamp + 1, TS.serialize_cdr(msg, MSGTYPE))
        said = [(c.frame, c.tf) for _, c in bag_frames(tmp_path / f"b{two}", "/points")]
        if two:
            assert said == [("camera", "left in 'camera': /tf gives 'base_link' several parents ('map', 'odom'): a "
                                       "broken tree")] * 3
        else:
            unstamped = "left in 'camera': its header.stamp is 0 (unstamped): no time to look /tf up at"
            assert said == [("camera", unstamped),
                            ("odom", "moved from 'camera' into 'odom' with /tf"),
                            ("camera", "left in 'camera': /tf holds 'odom' → 'base_link' from 1.000 s to 3.000 s, not "
                                       "at its stamp (no extrapolation, as tf2)")]


def test_a_bag_given_where_files_are_read_says_where_its_messages_go(tmp_path):
    """sdp series BAG said "is a folder, not a point-cloud file" (a ROS 2 bag), "unknown point-cloud format '.db3'"
    (its storage file) or "'.bag'" (a ROS 1 bag, even a missing one)."""
    bag = write_ros2(tmp_path / "b", [(1, message(room(), 1, 3000))])
    (db3,) = bag.glob("*.db3")
    ros1 = write_ros1(tmp_path / "b1.bag", [(1, message(room(), 1, 3000, ts=TS1))])
    for path in (bag, db3, ros1):
        with pytest.raises(CloudFileError, match=r"a ROS bag, not a point-cloud file: sdp change and sdp watch read its "
                                                 r"PointCloud2 messages \(--topic TOPIC:N\), sdp series all of them "
                                                 r"as one epoch \(--topic TOPIC\)$"):
            sdp.read_points(path)
    with pytest.raises(CloudFileError, match=r"missing.bag: no such file or folder$"):
        sdp.read_points(tmp_path / "missing.bag")
    p = subprocess.run([sys.executable, "-m", "sdp.cli", "series", bag, bag, "-o", tmp_path / "s.zarr"],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 2 and p.stderr.strip().splitlines() == [f"sdp: error: {bag}: a ROS bag: give --topic, one "
                                                                   "of its PointCloud2 topics (/points (1 messages))"]


def test_sdp_change_without_topic_lists_the_bags_topics_before_calling_it_one_message(tmp_path):
    """One bag of two PointCloud2 topics given twice without --topic said "would be the same message (None)"; a bag
    beside a file said "give --topic TOPIC" without naming any."""
    from rosbags.rosbag2 import Writer

    with Writer(tmp_path / "two", version=9) as w:
        for topic in ("/front/points", "/rear/points"):
            conn = w.add_connection(topic, MSGTYPE, typestore=TS)
            w.write(conn, 1, TS.serialize_cdr(message(room(), 1, 3000), MSGTYPE))
    np.save(tmp_path / "ref.npy", np.c_[room()["x"], room()["y"], room()["z"]].astype(float))
    listed = r"two: a ROS bag: give --topic, one of its PointCloud2 topics \(/front/points \(1 messages\), /rear/points"
    for ref in (tmp_path / "two", tmp_path / "ref.npy"):
        with pytest.raises(sdp.SDPError, match=listed):
            sdp.compare_files(ref, tmp_path / "two", output=tmp_path / "o.npz")


NIGHT = 1_700_000_000 * 10**9  # the first night's first stamp (2023-11-14); a night a day later than the one before


def patrol_scene(night: int, seed: int, n: int = 6000):
    """Points (map) of a 4 m room's floor and two walls, and a 0.6 m box on the floor at (1, 1), moved to (2.6, 2.6)
    from night 1 on; a depth camera's noise of 3 mm."""
    rng = np.random.default_rng(seed)
    u, v = rng.random((2, n)) * 4
    side = rng.integers(0, 3, n)
    xyz = np.where(side[:, None] == 0, np.c_[u, v, 0 * u], np.where(side[:, None] == 1, np.c_[u, 0 * u, v / 2],
                                                                     np.c_[0 * u, u, v / 2]))
    corner = np.array([1.0, 1.0, 0.0]) if night == 0 else np.array([2.6, 2.6, 0.0])
    under = ((xyz[:, 0] > corner[0]) & (xyz[:, 0] < corner[0] + 0.6) & (xyz[:, 1] > corner[1])
             & (xyz[:, 1] < corner[1] + 0.6) & (xyz[:, 2] == 0))
    top = corner + np.c_[rng.random((1500, 2)) * 0.6, np.full(1500, 0.6)]
    xyz = np.r_[xyz[~under], top]
    return xyz + rng.normal(0, 0.003, xyz.shape)


def patrol_bag(path, night: int, *, tf=True, keep=None, frame="camera"):
    """One night's bag: the robot (map → base_link on /tf, its camera 1 m above on /tf_static, turned 30°) stops at
    three places and its camera's messages hold the scene (``keep``: the points kept) in the camera's frame."""
    from rosbags.rosbag2 import Writer
    from scipy.spatial.transform import Rotation

    camera = (np.array([0.0, 0, 1]), Rotation.from_euler("z", 30, degrees=True))
    start = NIGHT + night * 86_400 * 10**9
    stops = [(start + k * 10**9, np.array([1.0 + k, 3.0, 0]), Rotation.from_euler("z", 20 * k, degrees=True))
             for k in range(3)]
    with Writer(path, version=9) as w:
        conn = w.add_connection("/camera/points", MSGTYPE, typestore=TS)
        if tf:
            dyn = w.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=TS)
            fixed = w.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=TS)
            w.write(fixed, start, TS.serialize_cdr(tf_message(start, ("base_link", "camera", *camera)),
                                                   "tf2_msgs/msg/TFMessage"))
            for t, where, turn in stops:  # held still at each stop, 0.1 s either side of the message
                for dt in (-10**8, 10**8):
                    w.write(dyn, t + dt, TS.serialize_cdr(tf_message(t + dt, ("map", "base_link", where, turn)),
                                                          "tf2_msgs/msg/TFMessage"))
        for k, (t, where, turn) in enumerate(stops):
            xyz = patrol_scene(night, seed=10 * night + k)
            if keep is not None:
                xyz = xyz[keep(xyz)]
            local = camera[1].inv().apply(turn.inv().apply(xyz - where) - camera[0])
            rec = np.zeros(len(xyz), room(1).dtype)
            rec["x"], rec["y"], rec["z"] = local.T
            w.write(conn, t, TS.serialize_cdr(in_frame(message(rec, 1, len(rec), stamp=t), frame), MSGTYPE))
    return path


def test_a_bag_is_one_epoch_of_a_series_each_message_a_scan_position(tmp_path):
    """sdp series refused a bag: "a ROS bag, not a point-cloud file"."""
    from sdp.io._bag import bag_epoch

    nights = [patrol_bag(tmp_path / "night1", 0), patrol_bag(tmp_path / "night2", 1),
              patrol_bag(tmp_path / "night3", 2, keep=lambda xyz: xyz[:, 0] < 2.0)]  # the robot looked away
    cloud = bag_epoch(nights[0], "/camera/points")
    assert cloud.frame == "map" and cloud.tf == "moved from 'camera' into 'map' with /tf"
    np.testing.assert_allclose(cloud.sensors, [[1, 3, 1], [2, 3, 1], [3, 3, 1]], atol=1e-9)  # each stop's camera
    assert np.array_equal(np.bincount(cloud.scan), [len(patrol_scene(0, k)) for k in range(3)])
    np.testing.assert_allclose(cloud.xyz[:len(patrol_scene(0, 0))], patrol_scene(0, 0), atol=1e-5)
    ds = sdp.series(nights, output=tmp_path / "patrol.zarr", topic="/camera/points",
                    cylinder=sdp.Cylinder(projection_scale=0.2))
    assert ds.attrs["epochs"][0]["time_source"] == "file (ROS header.stamp)"
    assert ds.attrs["parameters"]["used"]["orientation"] == "towards each point's scanner"  # as a multi-scan E57's
    days = (ds.time.values - np.datetime64("1970-01-01")) / np.timedelta64(1, "D")
    np.testing.assert_allclose(days, [NIGHT / 86_400e9 + k for k in range(3)], rtol=0, atol=1e-9)
    x, y, z = (ds[a].values for a in "xyz")
    old_box = (x > 1.05) & (x < 1.55) & (y > 1.05) & (y < 1.55) & (z > 0.55)
    static = (z > 0.3) & ((x < 0.05) | (y < 0.05)) & (x < 1.8)  # the walls, seen every night
    assert old_box.sum() > 5 and static.sum() > 50
    sig = ds.significant.values
    assert sig[1, old_box].mean() > 0.9 and np.all(ds.distance.values[1, old_box] < -0.4)  # the box gone
    assert sig[1, static].mean() < 0.1 and sig[2, static].mean() < 0.1  # a 95 % level's false alarms: about 5 %
    away = x > 2.3  # night 3 did not look there: not measured, not changed
    assert np.isnan(ds.distance.values[2, away]).all() and not sig[2, away].any()
    # --append: a bag epoch added to the archive of the first two measures as the full run did
    sdp.series(nights[:2], output=tmp_path / "two.zarr", topic="/camera/points",
               cylinder=sdp.Cylinder(projection_scale=0.2))
    appended = sdp.series(nights[2:], output=tmp_path / "two.zarr", topic="/camera/points", append=True)
    np.testing.assert_array_equal(appended.distance.values, ds.distance.values)
    assert appended.attrs["epochs"][2]["time_source"] == "file (ROS header.stamp)"


def test_a_bag_epoch_without_tf_or_topic_is_refused_in_one_line(tmp_path):
    from sdp.io._bag import bag_epoch

    bare = patrol_bag(tmp_path / "bare", 0, tf=False)
    with pytest.raises(CloudFileError, match=r"bare /camera/points message 0: left in 'camera': the bag has no /tf; an "
                                             r"epoch merges its messages in map or odom"):
        bag_epoch(bare, "/camera/points")
    mapped = patrol_bag(tmp_path / "mapped", 0, tf=False, frame="map")  # already in map: no /tf needed
    assert bag_epoch(mapped, "/camera/points").sensors is None and bag_epoch(mapped, "/camera/points").frame == "map"
    with pytest.raises(sdp.SDPError, match=r"would need .* above the memory limit"):  # counted before reading
        bag_epoch(mapped, "/camera/points", memory_limit=10**6)
    with pytest.raises(sdp.SDPError, match=r"give --topic, one of its PointCloud2 topics \(/camera/points \(3 messag"):
        sdp.series([mapped, mapped], output=tmp_path / "s.zarr")
    np.save(tmp_path / "a.npy", patrol_scene(0, 0))
    with pytest.raises(sdp.SDPError, match=r"--topic '/camera/points:1': a bag epoch is every message of the topic"):
        sdp.series([mapped, mapped], output=tmp_path / "s.zarr", topic="/camera/points:1")
    with pytest.raises(sdp.SDPError, match=r"--topic reads a ROS bag epoch"):
        sdp.series([tmp_path / "a.npy"] * 2, output=tmp_path / "s.zarr", topic="/camera/points")
    p = subprocess.run([sys.executable, "-m", "sdp.cli", "series", mapped, bare, "--topic", "/camera/points", "-o",
                        tmp_path / "s.zarr"], capture_output=True, text=True, timeout=300)
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1 and "bare /camera/points message 0" in p.stderr
    assert not (tmp_path / "s.zarr").exists()
