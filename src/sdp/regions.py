"""Connected regions of a volume (F < 0) on a sparse grid, and the points they hold.

A region is a 6-connected component of the grid nodes where a field is negative; a point
belongs to the region of the lowest-valued negative corner of its cell. For change
detection the volume is the difference max(F_cur, −F_ref) < 0, so every changed point (whose
interpolated value is negative) has at least one negative corner and gets a region.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ._region_kernels import corner_labels, group_stats, label_nodes, volume_at, volume_masks
from .boolean import check_compatible
from .field import DensityField
from .grid import BLOCK

__all__ = ["Region", "label_points", "describe_regions"]


@dataclass(frozen=True)
class Region:
    """One connected region of changed points.

    Attributes
    ----------
    label : int
        Region number, 0 … n−1, largest region first.
    n_points : int
        Points of the cloud in the region.
    centroid : ndarray (3,)
        Mean position of those points (world units).
    bbox_min, bbox_max : ndarray (3,)
        Axis-aligned bounds of those points (world units).
    volume : float
        Volume of the region's grid cells: its negative nodes × l³ (world units cubed).
    """

    label: int
    n_points: int
    centroid: np.ndarray
    bbox_min: np.ndarray
    bbox_max: np.ndarray
    volume: float

    @property
    def size(self) -> np.ndarray:
        """Extent of the bounding box along x, y, z (world units)."""
        return self.bbox_max - self.bbox_min

    def to_dict(self) -> dict:
        """JSON-serializable fields (lists for the vectors)."""
        return {"label": self.label, "n_points": self.n_points, "centroid": self.centroid.tolist(),
                "bbox_min": self.bbox_min.tolist(), "bbox_max": self.bbox_max.tolist(), "volume": self.volume}


def label_points(field: DensityField, values: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Label the connected components of ``values < 0`` on ``field``'s blocks, and the points in them.

    Parameters
    ----------
    field : DensityField
        Supplies the grid and block layout of ``values``.
    values : ndarray, float32 (m, 512)
        A field's values at the nodes of ``field``'s blocks (e.g. F, or a Boolean result).
    points : ndarray (n, 3)
        World coordinates to assign.

    Returns
    -------
    point_labels : ndarray of int64 (n,)
        Component of each point (-1: no negative corner).
    node_counts : ndarray of int64 (n_components,)
        Number of negative nodes of each component.
    """
    return label_volume(field, Volume.of_values(values), points)


class Volume(NamedTuple):
    """The nodes of a field's blocks where v = max(h_a − A, B − h_b) < 0, never stored whole.

    ``A`` is float32 per node of the field's blocks; ``B`` the blocks of another field on the
    same lattice (found through ``b_directory`` at the field's block keys + ``shift``; 0 where
    it holds none); with no ``B`` (``hb`` = inf), v = h_a − A. The kernels of ``sdp._region_kernels``
    compute v node by node where they need it: change detection labels and interpolates the
    difference max(F_a, −F_b) without writing it out (a field's worth of fresh memory per
    direction).
    """

    a_blocks: np.ndarray
    ha: float
    b_blocks: np.ndarray
    b_directory: np.ndarray
    shift: np.ndarray
    hb: float

    @classmethod
    def difference(cls, a: DensityField, b: DensityField) -> "Volume":
        """max(F_a, −F_b) on a's blocks: a's points there are inside a and outside b."""
        check_compatible(a, b)
        return cls(a.blocks.values, a.h, b.blocks.values, b.blocks.directory,
                   a.grid.block_origin - b.grid.block_origin, b.h)

    @classmethod
    def inside(cls, a: DensityField) -> "Volume":
        """F_a = h − G_a on a's blocks: the cluster volume."""
        return cls(a.blocks.values, a.h, _NO_BLOCKS, _NO_DIRECTORY, np.zeros(3, np.int64), np.inf)

    @classmethod
    def of_values(cls, values: np.ndarray) -> "Volume":
        """Given node values (v = 0 − (−values), exactly)."""
        return cls(np.negative(values, dtype=np.float32), 0.0, _NO_BLOCKS, _NO_DIRECTORY, np.zeros(3, np.int64),
                   np.inf)

    def at(self, field: DensityField, points: np.ndarray) -> np.ndarray:
        """v interpolated at finite world ``points``, as :meth:`DensityField.interpolate` would
        interpolate v stored on ``field``'s blocks."""
        out = np.empty(len(points))
        volume_at(points, field.grid.origin, field.voxel_size, field.blocks.directory, *self.kernel_args(field), out)
        return out

    def kernel_args(self, field: DensityField) -> tuple:
        """The arguments of the volume kernels of ``sdp._region_kernels``, on ``field``'s blocks."""
        return field.blocks.keys, self.a_blocks, self.ha, self.b_blocks, self.b_directory, self.shift, self.hb


_NO_BLOCKS = np.zeros((0, BLOCK**3), np.float32)
_NO_DIRECTORY = np.full((1, 1, 1), -1, np.int32)


def label_volume(field: DensityField, volume: Volume, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`label_points` of a :class:`Volume` on ``field``'s blocks."""
    args = volume.kernel_args(field)
    slot, labels, node_counts = label_nodes(volume_masks(*args), field.blocks.directory, field.blocks.keys)
    point_labels = corner_labels(field.grid.to_grid_units(points), field.blocks.directory, slot, labels, *args)
    return point_labels, node_counts


def describe_regions(points: np.ndarray, point_labels: np.ndarray, node_counts: np.ndarray,
                     voxel_size: float) -> tuple[list[Region], np.ndarray]:
    """Summaries of the components holding labelled points, largest first.

    Returns the regions and each point's region label (-1 for unlabelled points); regions
    are renumbered 0 … n−1 by decreasing point count.
    """
    counts, sums, mins, maxs = group_stats(points, point_labels, len(node_counts))
    used = np.flatnonzero(counts)
    order = used[np.argsort(-counts[used], kind="stable")]
    rank = np.full(len(node_counts) + 1, -1, np.int64)  # the last slot maps label -1 to -1
    rank[order] = np.arange(len(order))
    regions = [Region(label=i, n_points=int(counts[j]), centroid=sums[j] / counts[j], bbox_min=mins[j],
                      bbox_max=maxs[j], volume=float(node_counts[j]) * voxel_size**3)
               for i, j in enumerate(order)]
    return regions, rank[point_labels]
