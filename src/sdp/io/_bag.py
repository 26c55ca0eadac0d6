"""ROS bags: the ``sensor_msgs/PointCloud2`` messages of a topic, frame by frame, as clouds.

Robots record their point clouds in bags, not folders of files: ROS 1 ``.bag`` files and
ROS 2 bags (a folder with ``metadata.yaml`` and its ``.db3`` or ``.mcap`` files).
:func:`bag_frames` reads them with rosbags (pure Python, no ROS installation; the ``scans``
extra) and yields one :class:`~sdp.io.Cloud` per message of the topic, in the order recorded:
x, y, z as float64, the other fields kept (``rgb``, ``intensity``, …), missing returns (NaN, and
(0, 0, 0) in an organized cloud, as :func:`sdp.read_points` drops them in PCD files) dropped and
counted; a field of several values per point (``count`` > 1) is split as PCD files' are
(``normal__0000``, …). An organized cloud (``height`` > 1: one point per pixel) stays organized,
and the sensor stands at the origin of the message's frame (``header.frame_id``: a camera's or a
lidar's optical frame), so the visibility test of :func:`sdp.detect_changes` follows its rays
unless the caller says otherwise (``--sensor-origin``). A cloud published in a world frame
(REP 105's ``map``, ``odom``, ``earth``, or ``world``: a registered or accumulated cloud), or in a
robot's body frame (``base_link``, ``base_footprint``, ``base_stabilized``: moved off its sensor),
says nothing of where its sensor stood: it is read without one. A bag holding ``/tf`` or
``/tf_static`` moves each message into its root frame (``map``, else ``odom``) at its
``header.stamp`` (:mod:`sdp.io._tf`), its sensor at the frame's origin moved there; a message
without a chain of transforms there is left in its frame (:attr:`~sdp.io.Cloud.tf` says which).
:func:`bag_epoch` reads every message of a topic as one cloud, each message a scan position, as a
multi-scan E57 file is read: a robot's patrol as one epoch of :func:`sdp.series`.

References
----------
.. [1] ROS ``sensor_msgs/PointCloud2`` and ``sensor_msgs/PointField`` message definitions
   (https://docs.ros.org/en/rolling/p/sensor_msgs/).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from contextlib import closing
from pathlib import Path

import numpy as np

from .._core._memory import check_memory
from ..errors import SDPError, require
from ._cloud import Cloud, CloudFileError, EmptyCloudError, is_bag, library_error, unpacked_colour
from ._tf import TransformTree

__all__ = ["bag_epoch", "bag_frames", "bag_message", "bag_path", "bag_start", "bag_topics", "frame_kind", "is_bag",
           "pointcloud2_arrays", "split_topic", "topic_needed"]

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
#: Frames whose origin is no sensor (REP 105's world frames, and the usual name of the fixed one).
WORLD_FRAMES = frozenset({"map", "odom", "earth", "world"})
#: A robot's body frames (REP 105's base_link; base_footprint, its shadow on the floor, and
#: base_stabilized, REP 120's): a cloud moved there from its sensor says nothing of where that stood.
BODY_FRAMES = frozenset({"base_link", "base_footprint", "base_stabilized"})
#: Largest |coordinate| read from a message: a float32 field of noise reaches 3.4e38, and no scene
#: (nor the lattice, 2**40 voxels from the origin) reaches 1e12 units.
MAX_COORDINATE = 1e12
# sensor_msgs/PointField datatypes: INT8 … FLOAT64
_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
#: Bytes per point of a bag read as one epoch: what measuring it takes
#: (:meth:`sdp.distance.PreparedReference.memory_per_epoch`), more than its reading.
EPOCH_POINT_BYTES = 200.0


def bag_path(path) -> Path:
    """The bag ``path`` names, resolved: a ROS 2 bag's storage file (``.db3``, ``.mcap`` beside its
    ``metadata.yaml``) is its folder, so both name one bag."""
    p = Path(path).resolve()
    if p.is_file() and p.suffix.lower() in (".db3", ".mcap") and (p.parent / "metadata.yaml").is_file():
        return p.parent
    return p


def _reader(path):
    if not Path(path).exists():
        raise CloudFileError(f"{path}: no such file or folder")
    highlevel = require("rosbags.highlevel", "scans", "reading ROS bags", package="rosbags")
    p = bag_path(path)
    try:
        reader = highlevel.AnyReader([p])
        reader.open()
    except BaseException as exc:
        if not library_error(exc):
            raise
        raise _error(path, exc) from None
    return reader


def _error(path, exc) -> CloudFileError:
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    text = lines[0][:200] if lines else type(exc).__name__
    return CloudFileError(f"{path}: can't read as a ROS bag ({type(exc).__name__}: {text})")


def bag_topics(path) -> dict[str, int]:
    """The ``sensor_msgs/PointCloud2`` topics of a bag and their message counts."""
    reader = _reader(path)
    try:
        out: dict[str, int] = {}
        for c in reader.connections:
            if c.msgtype == POINTCLOUD2:
                out[c.topic] = out.get(c.topic, 0) + int(c.msgcount)
        return out
    finally:
        reader.close()


def bag_frames(path, topic: str) -> Iterator[tuple[str, Cloud]]:
    """``(name, Cloud)`` of each ``PointCloud2`` message on ``topic``, in the order recorded; the
    name is the message's index on the topic and the time the bag recorded it, in nanoseconds since
    the epoch (``000003@1355495015814212000``): the bag's own time of the message (ROS 2's receive
    time, ROS 1's record time), not its ``header.stamp`` (when the sensor took it, which ``/tf`` is
    looked up at), later by the transport's delay and apart from it entirely in a bag rewritten
    or played back with other times.

    The bag and the topic are checked when this is called (a bag without the topic raises
    :class:`~sdp.io.CloudFileError` listing its point-cloud topics); the messages are read as
    the iterator advances.
    """
    reader = _reader(path)
    try:
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns or any(c.msgtype != POINTCLOUD2 for c in conns):
            clouds = sorted({c.topic for c in reader.connections if c.msgtype == POINTCLOUD2})
            what = "not a PointCloud2 topic" if conns else "no topic"
            raise CloudFileError(f"{path}: {what} {topic!r}; its PointCloud2 topics: {', '.join(clouds) or 'none'}")
        if sum(c.msgcount for c in conns) == 0:  # a stream of no frame: an error, as an empty folder is
            raise CloudFileError(f"{path}: {topic!r} holds 0 messages")
        try:
            tree = TransformTree.read(reader)
        except Exception as exc:
            raise _error(f"{path} /tf", exc) from None
    except BaseException:
        reader.close()
        raise
    return _frames(reader, conns, path, tree)


def topic_needed(path) -> SDPError:
    """The error for a ROS bag given without ``--topic``, listing its point-cloud topics."""
    topics = bag_topics(path)  # a missing or corrupt bag says so instead
    return SDPError(f"{path}: a ROS bag: give --topic, one of its PointCloud2 topics "
                    f"({', '.join(f'{t} ({n} messages)' for t, n in sorted(topics.items())) or 'none'})")


def _headers(path, topic: str) -> Iterator[tuple[int, int]]:
    """(points, ``header.stamp`` in ns) of each message on ``topic``, in the order recorded, one
    message at a time, their points not decoded: the first pass of :func:`bag_epoch`, and
    :func:`bag_start`."""
    reader = _reader(path)
    try:
        conns = [c for c in reader.connections if c.topic == topic and c.msgtype == POINTCLOUD2]
        if not conns:  # bag_frames' one-line refusal, listing the topics
            bag_frames(path, topic)
        for index, (conn, _, raw) in enumerate(reader.messages(connections=conns)):
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception as exc:
                raise _error(f"{path} {topic} message {index}", exc) from None
            yield int(msg.height) * int(msg.width), int(msg.header.stamp.sec) * 10**9 + int(msg.header.stamp.nanosec)
    finally:
        reader.close()


def bag_start(path, topic: str) -> int | None:
    """The ``header.stamp`` (ns since the epoch) of the first message on ``topic``: when the sensor
    took it; None when unstamped (0) or the topic holds no message."""
    with closing(_headers(path, topic)) as headers:  # the reader closed now, not when collected
        first = next(headers, None)
    return first[1] if first is not None and first[1] > 0 else None


def bag_epoch(path, topic: str, *, memory_limit=None) -> Cloud:
    """Every ``PointCloud2`` message on ``topic`` as one cloud: a robot's patrol as one epoch.

    Each message is moved into the bag's root frame (``map``, else ``odom``) with its ``/tf`` at
    its ``header.stamp`` (:func:`bag_frames`) and is one scan position, as a multi-scan E57 file's
    scans are: :attr:`~sdp.io.Cloud.sensors` holds each message's sensor (its frame's origin, moved)
    and the ``scan`` field which message saw each point, so that visibility and normals follow
    each position (:func:`sdp.change._visibility.scanner_of_points`). Messages in a world frame
    (``map``, ``odom``: already registered) need no ``/tf``; they, and messages in a body frame,
    record no sensor, and then the cloud records none (as an E57 file of scans some without a
    pose). Only the coordinates and ``scan`` are kept; a message of no point is no position.

    Raises
    ------
    CloudFileError
        A message left in a sensor's or body frame (no ``/tf`` chain into ``map`` or ``odom`` at
        its stamp: merging a moving sensor's messages without its poses means nothing), messages
        in different world frames, or no point.
    GridTooLargeError
        The messages' points, counted first (:func:`_headers`), beyond ``memory_limit``.
    """
    counts = [n for n, _ in _headers(path, topic)]
    total = sum(counts)
    check_memory(EPOCH_POINT_BYTES * total, f"{path}: {total:,} points in {len(counts)} messages of {topic}",
                 memory_limit, advice="read fewer messages (a shorter bag)")
    parts, sensors, frames, moved, dropped = [], [], set(), set(), 0
    for index, (_, cloud) in enumerate(bag_frames(path, topic)):
        if frame_kind(cloud.frame) != "world":
            why = cloud.tf or (f"left in {cloud.frame!r}: the bag has no /tf" if cloud.frame else "it names no frame")
            raise CloudFileError(f"{path} {topic} message {index}: {why}; an epoch merges its messages in map or odom, "
                                 "which a moving sensor's need /tf to reach")
        frames.add(cloud.frame)
        moved.add(cloud.tf)
        dropped += cloud.n_dropped
        if len(cloud.xyz):  # a message that saw nothing says nothing, as an E57 file's empty scan
            parts.append(cloud.xyz)
            sensors.append(cloud.sensor_origin)
    if len(frames) > 1:
        raise CloudFileError(f"{path} {topic}: messages in frames {', '.join(map(repr, sorted(frames)))}: no /tf "
                             "between them to merge them in one")
    if not parts:
        raise EmptyCloudError(f"{path} {topic}: holds no point with finite x, y, z")
    posed = all(s is not None for s in sensors)
    scan = np.repeat(np.arange(len(parts), dtype=np.uint32), [len(p) for p in parts])
    xyz = np.concatenate(parts)
    del parts
    return Cloud(xyz, {"scan": scan} if posed else {}, Path(path), dropped,
                 sensors=np.array(sensors, np.float64).reshape(-1, 3) if posed else None, frame=frames.pop(),
                 tf="; ".join(sorted(t for t in moved if t)) or None)


def _moved(xyz, frame: str, stamp: int, tree) -> tuple[np.ndarray, np.ndarray | None, str, str]:
    """(points, sensor position or None, frame, what /tf did) of a message's points in ``frame`` at
    ``stamp`` (ns): moved into the tree's root where a chain of transforms reaches it then."""
    m, why = tree.lookup(frame, stamp)
    if m is None:
        return xyz, None, frame, f"left in {frame!r}: {why}"
    return xyz @ m[:3, :3].T + m[:3, 3], m[:3, 3].copy(), tree.root, f"moved from {frame!r} into {tree.root!r} with /tf"


def _frames(reader, conns, path, tree=None) -> Iterator[tuple[str, Cloud]]:
    messages = reader.messages(connections=conns)
    index = 0
    try:
        while True:
            where = f"{path} {conns[0].topic} message {index}"
            try:  # a corrupt bag fails in the reader's iteration or in the message's decoding
                item = next(messages, None)
                if item is None:
                    return
                conn, stamp, raw = item
                msg = reader.deserialize(raw, conn.msgtype)
                xyz, fields, organized = pointcloud2_arrays(msg)
            except CloudFileError as exc:
                raise CloudFileError(f"{where}: {exc}") from None
            except MemoryError:
                raise CloudFileError(f"{where}: too large to read into memory") from None
            except BaseException as exc:
                if not library_error(exc):
                    raise
                raise _error(where, exc) from None
            finite = np.isfinite(xyz).all(axis=1)
            dropped = int((~finite).sum())
            if dropped:
                xyz = xyz[finite]
                fields = {k: v[finite] for k, v in fields.items()}
            reach = float(np.abs(xyz).max()) if len(xyz) else 0.0
            if reach > MAX_COORDINATE:
                raise CloudFileError(f"{where}: coordinates up to {reach:.3g}, beyond ±{MAX_COORDINATE:.0e}, which no "
                                     "scene reaches: a corrupt message")
            frame = str(msg.header.frame_id).strip().lstrip("/")
            # a world or body frame's origin is no sensor: the summaries' coverage line says "no sensor position known"
            sensor = None if frame_kind(frame) else np.zeros(3)
            moved = None
            if tree is not None and frame and frame != tree.root:
                header = msg.header.stamp
                xyz, at, frame, moved = _moved(xyz, frame, int(header.sec) * 10**9 + int(header.nanosec), tree)
                if sensor is not None and at is not None:  # a sensor's frame: its origin moved with it
                    sensor = at
            image = (int(msg.height), int(msg.width)) if organized else None  # which pixels returned
            yield f"{index:06d}@{stamp}", Cloud(np.ascontiguousarray(xyz), fields, Path(path), dropped, None, None,
                                                 organized, None if sensor is None else sensor[None, :], None, image,
                                                 np.flatnonzero(finite) if organized else None, frame or None, moved)
            index += 1
    finally:
        reader.close()


def frame_kind(frame: str | None) -> str | None:
    """"world" (:data:`WORLD_FRAMES`) or "body" (:data:`BODY_FRAMES`) for a frame whose origin is no
    sensor, else None (a sensor's frame, or none named)."""
    name = (frame or "").lower()
    return "world" if name in WORLD_FRAMES else "body" if name in BODY_FRAMES else None


def pointcloud2_arrays(msg) -> tuple[np.ndarray, dict[str, np.ndarray], bool]:
    """(xyz float64 (n, 3) with NaN rows for missing returns, other fields, organized) of a
    deserialized ``sensor_msgs/PointCloud2`` (fields read at their offsets, any point step and
    row padding, either byte order)."""
    h, w, step, row_step = int(msg.height), int(msg.width), int(msg.point_step), int(msg.row_step)
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for f in msg.fields:
        if int(f.datatype) not in _TYPES:
            raise CloudFileError(f"field {f.name!r} has an unknown PointField datatype {f.datatype}")
        count = max(int(f.count), 1)
        names.append(f.name)
        formats.append((order + _TYPES[int(f.datatype)], (count,)) if count > 1 else order + _TYPES[int(f.datatype)])
        offsets.append(int(f.offset))
    if not {"x", "y", "z"} <= set(names):
        raise CloudFileError(f"PointCloud2 fields {names} have no x, y, z")
    spans = {n: (o, o + np.dtype(f).itemsize) for n, f, o in zip(names, formats, offsets)}
    for a in ("x", "y", "z"):  # a coordinate shares no byte with another field (numpy would read them anyway)
        for b, (lo, hi) in spans.items():
            if b != a and lo < spans[a][1] and spans[a][0] < hi:
                raise CloudFileError(f"PointCloud2 fields {a!r} (bytes {spans[a][0]}–{spans[a][1] - 1}) and {b!r} "
                                     f"(bytes {lo}–{hi - 1}) overlap")
    try:
        dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    except (TypeError, ValueError) as exc:
        raise CloudFileError(f"PointCloud2 fields don't fit a point of {step} bytes ({exc})") from None
    data = np.asarray(msg.data, np.uint8)
    if h * w and (step <= 0 or row_step < w * step or len(data) < (h - 1) * row_step + w * step):
        raise CloudFileError(f"PointCloud2 of {h}×{w} points of {step} bytes (rows of {row_step}) needs more than its "
                             f"{len(data):,} bytes")
    if row_step != w * step:  # rows padded: drop each row's padding
        rows = [data[r * row_step:r * row_step + w * step] for r in range(h)]
    else:
        rows = [data[:h * w * step]]
    points = np.concatenate(rows).view(dtype) if h * w else np.zeros(0, dtype)
    with np.errstate(invalid="ignore"):  # a signalling NaN is a missing return as any NaN
        xyz = np.c_[points["x"], points["y"], points["z"]].astype(np.float64)
    organized = h > 1
    if organized:  # as PCD files: an organized cloud marks a missing return by NaN or by (0, 0, 0)
        xyz[~xyz.any(axis=1)] = np.nan
    fields = {}
    for n in names:
        if n in ("x", "y", "z") or not n:
            continue
        v = np.ascontiguousarray(points[n]).astype(points[n].dtype.newbyteorder("="))
        fields.update({f"{n}__{i:04d}": np.ascontiguousarray(v[:, i]) for i in range(v.shape[1])} if v.ndim == 2
                      else {n: v})
    return xyz, unpacked_colour(fields), organized


def split_topic(topic: str) -> tuple[str, str]:
    """(topic name, message number as given) of ``--topic``: ``/points`` (its first message, "0")
    or ``/points:N``. ROS names hold no colon."""
    return tuple(topic.rsplit(":", 1)) if ":" in topic else (topic, "0")


def bag_message(path, topic: str) -> Cloud:
    """One message of a bag as a cloud: ``topic`` is ``/points`` (its first message) or
    ``/points:N`` (its N-th, from 0; negative from the end: :func:`split_topic`)."""
    name, number = split_topic(topic)
    try:
        index = int(number)
    except ValueError:
        raise CloudFileError(f"--topic {topic!r}: give TOPIC or TOPIC:N (the N-th message, from 0)") from None
    count = 0
    kept = deque(maxlen=-index if index < 0 else 1)  # the last -N messages, or the one asked for
    for count, (_, cloud) in enumerate(bag_frames(path, name), start=1):
        if index < 0 or count - 1 == index:
            kept.append(cloud)
        if index >= 0 and kept:
            return cloud
    if index < 0 and len(kept) == -index:
        return kept[0]
    raise CloudFileError(f"{path}: {name!r} holds {count} messages, no message {index}")
