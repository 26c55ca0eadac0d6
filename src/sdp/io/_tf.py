"""A bag's ``/tf`` and ``/tf_static``: where each message's frame stood in the bag's root frame.

A robot's point clouds are published in its sensors' frames (``camera_link``), which move with it;
``tf2_msgs/TFMessage`` on ``/tf`` (dynamic: the robot in ``odom`` or ``map``, as localization
publishes it) and ``/tf_static`` (fixed: the camera on the robot) say where each frame stood in its
parent's at each time [1]_. :class:`TransformTree` holds them all and gives the transform of a
frame into the root (``map``, else ``odom``: REP 105's world frames [2]_) at a message's
``header.stamp``, composing the chain of parents: each dynamic link interpolated between the two
transforms recorded around the stamp, translation linearly and rotation by spherical linear
interpolation (scipy's :class:`~scipy.spatial.transform.Slerp`), as tf2 does. A stamp outside a
link's recorded times has no transform (tf2 refuses to extrapolate), nor has a frame without a
chain of parents to the root, nor one that ``/tf`` gives two parents (``odom`` → ``base_link``
and ``map`` → ``base_link``: a broken tree, whose transforms, read as one link's, would move the
cloud between the two parents' frames from one stamp to the next); :meth:`TransformTree.lookup`
says which.

References
----------
.. [1] T. Foote, "tf: The transform library", IEEE TePRA 2013.
.. [2] W. Meeussen, "REP 105: Coordinate Frames for Mobile Platforms", ros.org.
"""

from __future__ import annotations

import numpy as np

__all__ = ["TF_TOPICS", "TransformTree"]

TF_TOPICS = ("/tf", "/tf_static")
TFMESSAGE = "tf2_msgs/msg/TFMessage"
#: Root frames, the first present taken: the fixed world frame, else the continuous one.
ROOTS = ("map", "odom")


def _frame(name) -> str:
    return str(name).strip().lstrip("/")


class _Link:
    """One parent → child link: its transforms at their stamps (ns), or one fixed transform."""

    def __init__(self, parent: str):
        self.parent = parent
        self.other_parents: set[str] = set()  # parents /tf also gave this child: the tree is broken there
        self.stamps, self.translations, self.rotations = [], [], []
        self.static = False
        self._slerp = None

    def add(self, stamp: int, translation, rotation, static: bool) -> None:
        if static:  # the latest static transform holds at every time
            self.stamps, self.translations, self.rotations = [stamp], [translation], [rotation]
            self.static = True
        elif not self.static:
            self.stamps.append(stamp)
            self.translations.append(translation)
            self.rotations.append(rotation)

    def matrix(self, stamp: int) -> np.ndarray | None:
        """The 4 × 4 transform of child coordinates into the parent's at ``stamp``, or None outside
        the recorded times."""
        from scipy.spatial.transform import Rotation, Slerp

        if self._slerp is None:  # sorted once, on the first lookup
            order = np.argsort(self.stamps, kind="stable")
            t, keep = np.asarray(self.stamps, np.int64)[order], np.ones(len(order), bool)
            keep[1:] = np.diff(t) > 0  # one transform per stamp
            self._t = t[keep]
            self._xyz = np.asarray(self.translations, np.float64)[order][keep]
            rot = Rotation.from_quat(np.asarray(self.rotations, np.float64)[order][keep])  # x, y, z, w
            self._slerp = rot if len(self._t) == 1 else Slerp(self._t.astype(np.float64), rot)
        m = np.eye(4)
        if self.static or len(self._t) == 1:
            if not (self.static or stamp == self._t[0]):
                return None
            m[:3, :3], m[:3, 3] = self._slerp.as_matrix()[0], self._xyz[0]
            return m
        if not self._t[0] <= stamp <= self._t[-1]:
            return None
        m[:3, :3] = self._slerp([float(stamp)]).as_matrix()[0]
        m[:3, 3] = [np.interp(stamp, self._t, self._xyz[:, a]) for a in range(3)]
        return m


class TransformTree:
    """The transforms of a bag's ``/tf`` and ``/tf_static`` (:meth:`read` makes one)."""

    def __init__(self):
        self.links: dict[str, _Link] = {}  # child frame → its link to its parent

    @classmethod
    def read(cls, reader) -> "TransformTree | None":
        """The tree of an open rosbags ``AnyReader``'s ``/tf`` and ``/tf_static`` messages, or None
        when the bag holds none."""
        conns = [c for c in reader.connections if c.topic in TF_TOPICS and c.msgtype == TFMESSAGE]
        if not conns:
            return None
        tree = cls()
        for conn, _, raw in reader.messages(connections=conns):
            for t in reader.deserialize(raw, conn.msgtype).transforms:
                stamp = int(t.header.stamp.sec) * 10**9 + int(t.header.stamp.nanosec)
                q, v = t.transform.rotation, t.transform.translation
                parent = _frame(t.header.frame_id)
                link = tree.links.setdefault(_frame(t.child_frame_id), _Link(parent))
                if parent != link.parent:
                    link.other_parents.add(parent)
                    continue
                link.add(stamp, (v.x, v.y, v.z), (q.x, q.y, q.z, q.w), conn.topic == "/tf_static")
        return tree if tree.links else None

    @property
    def root(self) -> str | None:
        """``map`` if a link reaches it, else ``odom``, else None."""
        frames = set(self.links) | {link.parent for link in self.links.values()}
        return next((r for r in ROOTS if r in frames), None)

    def lookup(self, frame: str, stamp: int) -> tuple[np.ndarray | None, str]:
        """(the 4 × 4 transform of ``frame``'s coordinates into :attr:`root`'s at ``stamp`` (ns), "")
        or (None, why there is none: the link that has no transform then, and why)."""
        root, m, seen = self.root, np.eye(4), set()
        frame = _frame(frame)
        if root is None:
            return None, "/tf reaches neither map nor odom"
        while frame != root:
            link = self.links.get(frame)
            if link is None:
                return None, f"no /tf chain into {root!r} ({frame!r} has no parent in /tf)"
            if frame in seen:
                return None, f"/tf's links loop through {frame!r}"
            if link.other_parents:
                names = ", ".join(repr(p) for p in sorted({link.parent} | link.other_parents))
                return None, f"/tf gives {frame!r} several parents ({names}): a broken tree"
            seen.add(frame)
            step = link.matrix(stamp)
            if step is None:
                if stamp == 0:  # a driver that stamps nothing: no time to look /tf up at
                    return None, "its header.stamp is 0 (unstamped): no time to look /tf up at"
                t = np.asarray(link.stamps, np.int64) / 1e9
                held = f"at {t.min():.3f} s only" if t.min() == t.max() else f"from {t.min():.3f} s to {t.max():.3f} s"
                return None, (f"/tf holds {link.parent!r} → {frame!r} {held}, not at its stamp (no extrapolation, "
                              "as tf2)")
            m, frame = step @ m, link.parent
        return m, ""
