"""A synthetic city block in two epochs, written as LAZ lot by lot (never in memory at once).

Lots of 40 m × 40 m separated by 12 m streets, each with a building (walls and a flat roof,
10–30 m high) and parked objects on its street (cars 4.5 × 1.8 × 1.5 m, containers
6 × 2.4 × 2.6 m, bins 1 × 1 × 1.2 m). Every surface is sampled uniformly at ``density`` points
per m² with 1 cm Gaussian noise, independently in each epoch (a rescan, not a copy). Per lot,
some objects exist in epoch 1 only (disappeared) and some in epoch 2 only (appeared); the
others exist in both. Each point carries the extra dimension ``truth`` (1: it belongs to an
object of its epoch only — a change). Coordinates are UTM-like (630 km E, 4 830 km N, 1 mm
scale).

    python benchmarks/city.py 10e6 /tmp/city10M      # writes ref.laz and cur.laz there
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import laspy
import numpy as np

LOT, STREET = 40.0, 12.0
PITCH = LOT + STREET
OFFSET = np.array([630_000.0, 4_830_000.0, 50.0])
OBJECTS = {"car": (4.5, 1.8, 1.5), "container": (6.0, 2.4, 2.6), "bin": (1.0, 1.0, 1.2)}
STATIC, CHANGED = 6, 2  # objects per lot in both epochs / in one epoch only (each way)


def _rect(rng, origin, u, v, n):
    """n points uniform on the parallelogram origin + s·u + t·v."""
    s, t = rng.random((2, n, 1))
    return origin + s * u + t * v


def _box(rng, lo, size, density):
    """The five visible faces of a box (no bottom)."""
    x, y, z = np.eye(3) * np.asarray(size)
    lo = np.asarray(lo, float)
    faces = [(lo, x, y, lo + z), (lo, x, z, lo + y), (lo, y, z, lo + x)]
    parts = [_rect(rng, lo + z, x, y, rng.poisson(density * size[0] * size[1]))]
    for a, u, v, b in faces[1:]:
        n = rng.poisson(density * np.linalg.norm(u) * np.linalg.norm(v))
        parts += [_rect(rng, a, u, v, n), _rect(rng, b, u, v, n)]
    return np.concatenate(parts)


def _lot_layout(seed: int, i: int, j: int):
    """Geometry of lot (i, j), the same in both epochs: building box and the street objects."""
    g = np.random.default_rng([seed, i, j])
    w, d = g.uniform(20, 34, 2)
    x0, y0 = g.uniform(2, LOT - 2 - w), g.uniform(2, LOT - 2 - d)
    building = (np.array([i * PITCH + x0, j * PITCH + y0, 0.0]), np.array([w, d, g.uniform(10, 30)]))
    objects = []  # (lo, size, epochs: 0 both, 1 only epoch 1, 2 only epoch 2)
    slots = g.permutation(24)[:STATIC + 2 * CHANGED]  # 24 non-overlapping slots along the lot's street
    for k, slot in enumerate(slots):
        kind = ("car", "container", "bin")[int(g.integers(0, 3))]
        size = np.array(OBJECTS[kind])
        x = i * PITCH + (slot % 6) * (PITCH / 6) + 0.5
        y = j * PITCH + LOT + 1.0 + (slot // 6) * 2.7
        epochs = 0 if k < STATIC else 1 + (k - STATIC) % 2
        objects.append((np.array([x, y, 0.0]), size, epochs))
    return building, objects


def _lot_points(seed: int, i: int, j: int, epoch: int, density: float):
    """(xyz, truth) of lot (i, j) with its street, as scanned in ``epoch`` (1 or 2)."""
    (blo, bsize), objects = _lot_layout(seed, i, j)
    g = np.random.default_rng([seed, i, j, epoch])
    ground = _rect(g, np.array([i * PITCH, j * PITCH, 0.0]), np.array([PITCH, 0, 0]), np.array([0, PITCH, 0]),
                   g.poisson(density * PITCH**2))
    inside = np.all((ground[:, :2] > blo[:2]) & (ground[:, :2] < blo[:2] + bsize[:2]), axis=1)
    parts, truth = [ground[~inside], _box(g, blo, bsize, density)], []
    truth = [np.zeros(len(p), np.uint8) for p in parts]
    for lo, size, epochs in objects:
        if epochs in (0, epoch):
            pts = _box(g, lo, size, density)
            parts.append(pts)
            truth.append(np.full(len(pts), epochs != 0, np.uint8))
    xyz = np.concatenate(parts)
    return xyz + 0.01 * g.standard_normal(xyz.shape), np.concatenate(truth)


def points_per_lot(density: float) -> float:
    """Expected points of one lot (ground, building of mean size, its street objects)."""
    building = 4 * 27 * 20  # walls of mean footprint 27 m, mean height 20 m (the roof replaces ground)
    objects = STATIC + CHANGED
    mean_object = np.mean([w * d + 2 * (w + d) * h for w, d, h in OBJECTS.values()])
    return density * (PITCH**2 + building + objects * mean_object)


def write_city(folder, n_points: float, *, max_density: float = 300.0, seed: int = 0) -> dict:
    """Write ``folder``/ref.laz and cur.laz of about ``n_points`` points each; returns the layout.

    The city has the fewest square lots that hold ``n_points`` at ``max_density`` points per
    m²; the density is then lowered to give ``n_points``.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    side = max(1, math.ceil(math.sqrt(n_points / points_per_lot(max_density))))
    density = n_points / (side * side * points_per_lot(1.0))
    for epoch, name in ((1, "ref.laz"), (2, "cur.laz")):
        header = laspy.LasHeader(point_format=1, version="1.4")
        header.scales, header.offsets = np.array([0.001] * 3), OFFSET
        header.add_extra_dim(laspy.ExtraBytesParams(name="truth", type=np.uint8))
        tmp = folder / f".{name}"
        with laspy.open(str(tmp), mode="w", header=header, laz_backend=laspy.LazBackend.LazrsParallel) as w:
            for i in range(side):
                for j in range(side):
                    xyz, truth = _lot_points(seed, i, j, epoch, density)
                    rec = laspy.ScaleAwarePointRecord.zeros(len(xyz), header=header)
                    rec.x, rec.y, rec.z = (xyz + OFFSET).T
                    rec.truth = truth
                    rec.intensity = (100 + 50 * truth).astype(np.uint16)
                    w.write_points(rec)
        tmp.replace(folder / name)
    return {"lots": side * side, "side_m": side * PITCH, "density": density,
            "changed_objects": 2 * CHANGED * side * side}


if __name__ == "__main__":
    n, out = float(sys.argv[1]), sys.argv[2]
    print(write_city(out, n))
