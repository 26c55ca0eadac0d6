"""4D objects of change, tracked epoch by epoch, and the epoch each change starts.

A core point at an epoch is *changed* when its smoothed change is significant: ``|smoothed| >
1.96·smoothed_sigma`` (the smoother's own 95 % bound), and it was measured at that epoch: where an
epoch has no distance (nothing seen near the core point), the smoother's value is a guess from the
epochs around, and not seen is not changed. Changed core points of the same sign are
joined to their spatial neighbours at the same epoch (core points closer than ``radius``, by
default the 90th percentile of each core point's distance to its 6th nearest) where both changed
in one way: gradually, or by steps at the same epoch (± 1; the steps of :mod:`sdp.timeseries._kalman`),
since a step and a creep beside it, or two steps at different epochs, are different events.
Each epoch's connected sets continue the tracks of the epoch before that share a core point
changed the same way in both, as the objects-by-change of Anders et al. [1]_ grow in space and
time; a set touching no track starts one. Tracks are followed forward only, so an epoch's
objects never change once its smoothed values are final (:mod:`sdp.timeseries._kalman`'s lag):

- a set that touches several tracks continues the oldest object among them (the smallest id),
  or if none is an object yet, the oldest track; an object that loses this way ends the epoch
  before (two changes that meet are two objects, the younger ending where they meet), and a
  track that is not yet an object is taken in whole;
- a set's track splits when it does: the parts keep its id;
- a track none of whose core points was measured at an epoch (a partial scan) waits: its points
  keep their track and sign, and it goes on where they are seen again, under its id (not seen is
  not the end of a change either);
- a track becomes an object at the first epoch at which ``min_points`` of its core points are
  changed together (:func:`min_object_points`: ten, or as many as cover three cylinders'
  footprints where core points are denser than the cylinders, which then share their noise);
  its ids count from 1 in that order, its rows are labelled from that epoch (0 before and for
  tracks that never grow so large: noise);
- the object table: the epochs it starts and ends, its distinct core points and their area,
  its largest smoothed change (signed) and its mean velocity over every (epoch, point) of the
  track, including those before it became an object.

The onset of a core point's change is the first epoch from which its smoothed change stays
significant for two measured epochs running (an epoch without a distance between them neither
breaks nor counts), or the epoch of its first step if that comes first;
``onset_kind`` says which (1: step, 2: gradual). A step with no significant change after it is
no onset.

:class:`Tracker` holds what an epoch needs of the ones before (each point's track and sign at the
last epoch, the live tracks, the objects' table, the onsets), so that a run saves it after the
last final epoch and an append goes on from there.

References
----------
.. [1] K. Anders, L. Winiwarter, H. Mara, R. Lindenbergh, S. E. Vos, B. Höfle, "Fully automatic
   spatiotemporal segmentation of 3D LiDAR time series for the extraction of natural surface
   changes", ISPRS J. Photogramm. 173 (2021) 297–308.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .._core._disjoint import find, union

__all__ = ["neighbour_pairs", "min_object_points", "Tracker", "OBJECT_FIELDS"]

OBJECT_FIELDS = ("object_start", "object_end", "object_start_time", "object_end_time", "object_points",
                 "object_area", "object_peak_change", "object_mean_velocity")
#: Neighbours each core point reaches (at the 90th percentile): a triangulation's mean degree. Core
#: points drawn at random (every n-th point of a scan) joined only to their nearest reach about
#: five on average, at the edge of percolation: one change fell apart into many small pieces.
_RING = 6
#: Neighbours whose disc measures a core point's area: enough that a grid's rings of equal
#: distances and a random draw's clumps average out (16 reads a grid 2 % low, 8 by 21 %).
_AREA_RING = 32
#: The per-track numbers of :class:`Tracker` (live tracks, and the objects' table): one array each.
_TRACK = ("uid", "obj", "first", "end", "peak", "vsum", "vcount")
_OBJECT = ("start", "end", "points", "peak", "vsum", "vcount")


def neighbour_pairs(xyz: np.ndarray, radius: float | None = None) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(i, j, radius, area per core point): the core points' neighbour pairs within ``radius``
    (default the 90th percentile of the distance to the :data:`_RING`-th nearest: core points
    subsampled on a grid reach about seven on average, core points drawn at random about nine,
    well past the edge of percolation); the area is the median over the core points of the disc
    reaching their :data:`_AREA_RING`-th nearest over that many (π r²/k: within 3 % on a grid, on
    points drawn at random and on core points subsampled from a cloud, where the nearest
    neighbour's spacing squared reads 100 %, 22 % and 79 % of it)."""
    from scipy.spatial import cKDTree  # imported here: an append reads the pairs it saved, and skips the import

    tree = cKDTree(xyz)
    if len(xyz) > 1:
        k = min(len(xyz) - 1, _AREA_RING)
        d, _ = tree.query(xyz[:: max(1, len(xyz) // 5000)], k=[_RING + 1, k + 1] if k > _RING else [k + 1, k + 1])
        far, area = float(np.quantile(d[:, 0], 0.9)), float(np.median(np.pi * d[:, 1] ** 2 / k))
    else:
        far, area = 1.0, 1.0
    radius = far if radius is None else float(radius)
    pairs = tree.query_pairs(radius, output_type="ndarray")
    return pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64), radius, area


def min_object_points(xyz: np.ndarray, projection_scale: float, *, footprints: float = 3.0,
                      floor: int = 10) -> int:
    """The fewest core points of an object: ``floor``, or as many as cover ``footprints``
    cylinders (π d²/4 each) at the core points' median spacing, if more. Core points closer than
    the cylinder share their points and their noise: a cluster of them flickers together."""
    _, _, _, area = neighbour_pairs(xyz[:: max(1, len(xyz) // 200_000)], 0.0)
    area /= max(1, len(xyz) // 200_000)  # a sample of every n-th point holds n times the area each
    return int(max(floor, math.ceil(footprints * math.pi * projection_scale**2 / 4.0 / area)))


def _components(sign: np.ndarray, i: np.ndarray, j: np.ndarray, step: np.ndarray, k: int) -> tuple[np.ndarray, int]:
    """Per core point, its component among the changed points of one epoch ``k`` (-1: unchanged),
    numbered in the order of their first point; ``i, j``: the neighbour pairs; ``step``: each
    point's first step epoch (-1: none): a pair joins only changes of one kind (both gradual, or
    both steps by then, at epochs at most one apart)."""
    out = np.full(len(sign), -1, np.int64)
    return out, _epoch_labels(np.ascontiguousarray(sign, np.int8), i, j, step, k, out)


@nb.njit(cache=True)
def _epoch_labels(sign, i, j, step, k, out):
    """:func:`_components`' kernel: ``out`` filled, the number of components returned."""
    m = len(sign)
    parent = np.arange(m)
    for e in range(len(i)):
        a, b = i[e], j[e]
        sa = sign[a]
        if sa != 0 and sa == sign[b]:
            sta, stb = step[a], step[b]
            da, db = 0 <= sta <= k, 0 <= stb <= k
            if da != db or (da and abs(sta - stb) > 1):  # a step beside a creep, or steps apart
                continue
            union(parent, a, b)
    ids = np.full(m, -1, np.int64)  # root → component
    n = 0
    for p in range(m):
        if sign[p] != 0:
            r = find(parent, p)
            if ids[r] < 0:
                ids[r] = n
                n += 1
            out[p] = ids[r]
    return n


def _of_tracks(keys: np.ndarray, m: int, uids: np.ndarray) -> np.ndarray:
    """Which of the sorted ``keys`` (uid·m + point) belong to tracks ``uids``: each track's keys
    are one run, found by bisection."""
    inside = np.zeros(len(keys) + 1, np.int64)
    np.add.at(inside, np.searchsorted(keys, uids * m), 1)
    np.add.at(inside, np.searchsorted(keys, (uids + 1) * m), -1)
    return np.cumsum(inside[:-1]) > 0


def _distinct(a: np.ndarray) -> np.ndarray:
    """The sorted distinct values of ``a``, by sorting (NumPy's hash-based ``unique`` is
    several times slower on these integer keys)."""
    a = np.sort(a)
    return a[np.r_[True, a[1:] != a[:-1]]] if len(a) else a


def _merged(keys: np.ndarray, more: np.ndarray) -> np.ndarray:
    """The sorted distinct ``keys`` with ``more`` added: most of an epoch's keys are there already,
    and a stable sort of the two sorted runs is one merge."""
    more = _distinct(more)
    if not len(keys):
        return more
    at = np.minimum(np.searchsorted(keys, more), len(keys) - 1)
    more = more[keys[at] != more]
    return np.sort(np.concatenate([keys, more]), kind="stable") if len(more) else keys


@nb.njit(cache=True, nogil=True)
def _signs(smoothed, sigma):
    """Per core point, the sign of its smoothed change where significant (|d| > 1.96 σ), else 0."""
    out = np.zeros(len(smoothed), np.int8)
    for p in range(len(smoothed)):
        d, s = smoothed[p], sigma[p]
        if np.isfinite(d) and np.isfinite(s) and abs(d) > 1.96 * s:
            out[p] = 1 if d > 0 else (-1 if d < 0 else 0)
    return out


@nb.njit(cache=True, nogil=True)
def _epoch(k, min_points, n_objects, comp, n, sign, prev_sign, prev_track, smoothed, velocity, step, onset,
           onset_kind, seen_sign, seen_at, uid, obj, first, peak, vsum, vcount):
    """:meth:`Tracker.add`'s kernel: epoch ``k``'s components (``comp``, ``n`` of them) into tracks.

    Returns the next live tracks' arrays (:data:`_TRACK`: the continued ones in the order of their
    priority, then the new ones in the order of their components), each point's track (-1: none),
    its object id (int32, 0: none), and, among the live tracks that end, those that were objects
    (``done``), those taken in whole by a continued track (``taken``, and the track ``into``
    which), and the rest (``gone``). ``onset``, ``onset_kind`` are updated in place."""
    m, n_live = len(comp), len(uid)
    prio = np.empty(n_live, np.int64)  # objects first (by id), then tracks by age (uid)
    for t in range(n_live):
        prio[t] = obj[t] if obj[t] > 0 else 2**61 + uid[t]
    # links: a point changed the same way at this epoch and the last, in a live track
    best = np.full(n, -1, np.int64)  # each component's track of highest priority among its links
    lowest = np.full(n_live, -1, np.int64)  # each live track's first component among its links
    anchor = np.full(n, -1, np.int64)  # each component's first point
    for p in range(m):
        c = comp[p]
        if c < 0:
            continue
        if anchor[c] < 0:
            anchor[c] = p
        t = prev_track[p]
        if t >= 0 and sign[p] == prev_sign[p]:
            if best[c] < 0 or prio[t] < prio[best[c]]:
                best[c] = t
            if lowest[t] < 0 or c < lowest[t]:
                lowest[t] = c
    continued = np.zeros(n_live, np.bool_)
    for c in range(n):
        if best[c] >= 0:
            continued[best[c]] = True
    cont = np.flatnonzero(continued)
    cont = cont[np.argsort(prio[cont], kind="mergesort")]
    n_cont = len(cont)
    slot = np.full(n_live, -1, np.int64)
    for i in range(n_cont):
        slot[cont[i]] = i
    of_comp = np.empty(n, np.int64)
    n_next = n_cont
    for c in range(n):
        if best[c] >= 0:
            of_comp[c] = slot[best[c]]
        else:
            of_comp[c] = n_next
            n_next += 1
    u_, o_, f_ = np.zeros(n_next, np.int64), np.zeros(n_next, np.int64), np.zeros(n_next, np.int64)
    e_ = np.full(n_next, k, np.int64)  # every track of this epoch ends at it so far
    pk, vs, vc = np.zeros(n_next), np.zeros(n_next), np.zeros(n_next)
    for i in range(n_cont):
        t = cont[i]
        u_[i], o_[i], f_[i], pk[i], vs[i], vc[i] = uid[t], obj[t], first[t], peak[t], vsum[t], vcount[t]
    for c in range(n):
        if best[c] < 0:
            u_[of_comp[c]] = k * m + anchor[c]
            f_[of_comp[c]] = k
    # live tracks not continued: objects end; others are taken in whole by the track of the first
    # component they touch, or are noise that ends
    n_done = n_taken = n_gone = 0
    done, taken, into, gone = np.empty(n_live, np.int64), np.empty(n_live, np.int64), np.empty(n_live, np.int64), \
        np.empty(n_live, np.int64)
    for t in range(n_live):
        if continued[t]:
            continue
        if obj[t] > 0:
            done[n_done] = t
            n_done += 1
        if obj[t] == 0 and lowest[t] >= 0:
            i = of_comp[lowest[t]]
            taken[n_taken], into[n_taken] = t, i
            n_taken += 1
            f_[i] = min(f_[i], first[t])
            vs[i] += vsum[t]
            vc[i] += vcount[t]
            if abs(peak[t]) > abs(pk[i]):
                pk[i] = peak[t]
        else:
            gone[n_gone] = t
            n_gone += 1
    # this epoch's points into their tracks
    track = np.full(m, -1, np.int64)
    size = np.zeros(n_next, np.int64)
    vsum_now, vcount_now = np.zeros(n_next), np.zeros(n_next)
    for p in range(m):
        c = comp[p]
        if c < 0:
            continue
        i = of_comp[c]
        track[p] = i
        size[i] += 1
        if abs(smoothed[p]) > abs(pk[i]):
            pk[i] = smoothed[p]
        if np.isfinite(velocity[p]):
            vsum_now[i] += velocity[p]
            vcount_now[i] += 1.0
    for i in range(n_next):
        vs[i] += vsum_now[i]
        vc[i] += vcount_now[i]
    # tracks with min_points changed together become objects, in the order of their priority
    for i in range(n_next):
        if o_[i] == 0 and size[i] >= min_points:
            n_objects += 1
            o_[i] = n_objects
    labels = np.zeros(m, np.int32)
    for p in range(m):
        if track[p] >= 0:
            labels[p] = o_[track[p]]
    # onsets: the first of two measured epochs running with significant change (an epoch without
    # a distance between them neither breaks nor counts), or the step before it
    for p in range(m):
        if onset[p] < 0 and sign[p] != 0 and seen_sign[p] != 0:
            if 0 <= step[p] <= k - 1:
                onset[p], onset_kind[p] = step[p], 1
            else:
                onset[p], onset_kind[p] = seen_at[p], 2
    return (u_, o_, f_, e_, pk, vs, vc, track, labels, done[:n_done], taken[:n_taken], into[:n_taken],
            gone[:n_gone])


class Tracker:
    """The objects and onsets of a series, built one epoch at a time (see the module docstring).

    Parameters
    ----------
    xyz : ndarray (m, 3)
        The core points.
    min_points : int
        The fewest core points changed together that make a track an object.
    radius : float, optional
        Neighbour distance (default from the core points' spacing, :func:`neighbour_pairs`).
    pairs : tuple, optional
        The neighbour pairs, radius and area per point :func:`neighbour_pairs` gave these core
        points before (the state of an earlier run).
    """

    def __init__(self, xyz: np.ndarray, *, min_points: int, radius: float | None = None, pairs=None):
        if pairs is None:
            self.i, self.j, self.radius, self.area = neighbour_pairs(xyz, radius)
        else:  # (i, j, radius, area) of an earlier run on these core points
            self.i, self.j, self.radius, self.area = pairs
        m = len(xyz)
        self.m, self.min_points = m, int(min_points)
        self.epoch = -1
        self.track = np.full(m, -1, np.int64)  # each point's live track (an index) at the last epoch
        self.sign = np.zeros(m, np.int8)
        # each point's sign at the last epoch it was measured at, and that epoch (onsets over gaps)
        self.seen_sign, self.seen_at = np.zeros(m, np.int8), np.full(m, -1, np.int64)
        self.onset = np.full(m, -1, np.int64)
        self.onset_kind = np.zeros(m, np.int64)
        self.live = {k: np.zeros(0, np.float64 if k in ("peak", "vsum", "vcount") else np.int64) for k in _TRACK}
        self.keys = np.zeros(0, np.int64)  # the live tracks' distinct core points: uid·m + point, sorted
        self.objects = {k: np.zeros(0, np.float64 if k in ("peak", "vsum", "vcount") else np.int64)
                        for k in _OBJECT}

    def _count(self, uid: np.ndarray) -> np.ndarray:
        """Distinct core points of the live tracks ``uid``."""
        return np.searchsorted(self.keys, (uid + 1) * self.m) - np.searchsorted(self.keys, uid * self.m)

    # ---------------------------------------------------------------- one epoch
    def add(self, k: int, smoothed: np.ndarray, sigma: np.ndarray, velocity: np.ndarray,
            step: np.ndarray) -> np.ndarray:
        """Epoch ``k`` (the one after the last added): its object ids per core point (int32, 0: none).
        ``step``: each point's first step epoch (-1: none); a step counts from its epoch on."""
        if k != self.epoch + 1:
            raise ValueError(f"epoch {k} after {self.epoch}")
        m = self.m
        sign = _signs(smoothed, sigma)
        comp, n = _components(sign, self.i, self.j, step, k)
        live = self.live
        (uid, obj, first, end, peak, vsum, vcount, track, labels, done, taken, into, gone) = _epoch(
            k, self.min_points, len(self.objects["start"]), comp, n, sign, self.sign, self.track, smoothed, velocity,
            step, self.onset, self.onset_kind, self.seen_sign, self.seen_at,
            *(live[key] for key in _TRACK if key != "end"))
        nxt = dict(zip(_TRACK, (uid, obj, first, end, peak, vsum, vcount)))
        # not seen is not the end of a change either: a track none of whose points was seen at this
        # epoch waits, its points keeping their track and sign, and goes on where they are seen again
        seen = np.isfinite(sigma)  # not seen: a NaN σ (sdp.timeseries._compute)
        before = self.track >= 0
        waits = (np.bincount(self.track[before], minlength=len(live["uid"])) > 0) & (
            np.bincount(self.track[before & seen], minlength=len(live["uid"])) == 0)
        if waits.any():
            done, gone = done[~waits[done]], gone[~waits[gone]]
            for key in _TRACK:
                nxt[key] = np.concatenate([nxt[key], live[key][waits]])
        next_track, next_sign = track.copy(), sign.copy()
        carried = np.flatnonzero(before & ~seen)
        if carried.size and nxt["uid"].size:  # into their track's place among the next live ones, if it lives on
            order = np.argsort(nxt["uid"])
            was = live["uid"][self.track[carried]]
            place = order[np.minimum(np.searchsorted(nxt["uid"], was, sorter=order), len(order) - 1)]
            lives = nxt["uid"][place] == was
            next_track[carried[lives]] = place[lives]
            next_sign[carried[lives]] = self.sign[carried[lives]]
        # live tracks not continued: objects end the epoch before; others are taken in whole by a
        # set they touch (their points then count for it), or are noise that ends
        o = live["obj"][done] - 1
        for key in ("end", "peak", "vsum", "vcount"):
            self.objects[key][o] = live[key][done]
        self.objects["points"][o] = self._count(live["uid"][done])
        if taken.size:
            src = live["uid"][taken]
            moved = _of_tracks(self.keys, m, src)
            by = np.argsort(src)
            again = uid[into][by][np.searchsorted(src[by], self.keys[moved] // m)] * m + self.keys[moved] % m
            self.keys = _distinct(np.concatenate([self.keys[~moved], again]))
        if gone.size:
            self.keys = self.keys[~_of_tracks(self.keys, m, live["uid"][gone])]
        at = np.flatnonzero(track >= 0)
        self.keys = _merged(self.keys, uid[track[at]] * m + at)
        born = int(obj.max(initial=0)) - len(self.objects["start"])  # objects born this epoch: ids go on
        if born > 0:
            for key in _OBJECT:
                self.objects[key] = np.concatenate([self.objects[key], np.zeros(born, self.objects[key].dtype)])
            self.objects["start"][-born:] = k
        self.live, self.track = nxt, next_track
        self.sign, self.epoch = next_sign, k
        self.seen_sign[seen], self.seen_at[seen] = sign[seen], k
        return labels

    # ---------------------------------------------------------------- results and state
    def table(self, times: np.ndarray) -> dict:
        """The object table (:data:`OBJECT_FIELDS`, ids 1… in the order the objects were found)
        with the live objects as they stand."""
        obj = {k: v.copy() for k, v in self.objects.items()}
        live = self.live
        now = np.flatnonzero(live["obj"] > 0)
        o = live["obj"][now] - 1
        for key in ("end", "peak", "vsum", "vcount"):
            obj[key][o] = live[key][now]
        obj["points"][o] = self._count(live["uid"][now])
        start, end = obj["start"].astype(np.int32), obj["end"].astype(np.int32)
        return {"object_start": start, "object_end": end, "object_start_time": times[start],
                "object_end_time": times[end], "object_points": obj["points"].astype(np.int64),
                "object_area": obj["points"] * self.area, "object_peak_change": obj["peak"],
                "object_mean_velocity": obj["vsum"] / np.maximum(obj["vcount"], 1),
                "radius": self.radius, "area_per_point": self.area}

    def state(self) -> dict[str, np.ndarray]:
        """Arrays (copies) from which :meth:`from_state` makes this tracker again: per core point,
        per live track, per object, the live tracks' points, and the epoch."""
        return {"points": np.c_[self.track, self.sign, self.onset, self.onset_kind, self.seen_sign, self.seen_at],
                "live": np.stack([self.live[k].astype(np.float64) for k in _TRACK], axis=1),
                "objects": np.stack([self.objects[k].astype(np.float64) for k in _OBJECT], axis=1),
                "keys": self.keys.copy(), "epoch": np.array([self.epoch]), "pair_i": self.i, "pair_j": self.j,
                "pair_scales": np.array([self.radius, self.area])}

    @classmethod
    def from_state(cls, xyz: np.ndarray, arrays: dict, *, min_points: int) -> "Tracker":
        radius, area = (float(v) for v in arrays["pair_scales"])
        tr = cls(xyz, min_points=min_points, pairs=(arrays["pair_i"], arrays["pair_j"], radius, area))
        tr.epoch = int(arrays["epoch"][0])
        pts = np.asarray(arrays["points"], np.int64)
        # contiguous columns: the kernels are compiled (and warmed up) for contiguous arrays
        if pts.shape[1] == 4:  # saved before the last measured epoch was kept: the last epoch's
            pts = np.c_[pts, pts[:, 1], np.full(len(pts), tr.epoch)]
        tr.track, tr.sign, tr.onset, tr.onset_kind, tr.seen_sign, tr.seen_at = (
            np.ascontiguousarray(pts[:, a], t) for a, t in enumerate((np.int64, np.int8, np.int64, np.int64, np.int8,
                                                                      np.int64)))
        for name, into, keys in (("live", tr.live, _TRACK), ("objects", tr.objects, _OBJECT)):
            a = np.asarray(arrays[name], np.float64).reshape(-1, len(keys))
            for n, key in enumerate(keys):
                into[key] = a[:, n].astype(into[key].dtype)
        tr.keys = np.asarray(arrays["keys"], np.int64)
        return tr
