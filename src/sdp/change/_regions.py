"""Connected regions of a volume (F < 0) on a sparse grid, and the points they hold.

A region is a 6-connected component of the grid nodes where a field is negative; a point
belongs to the region of the lowest-valued negative corner of its cell. For change
detection the volume is the difference max(F_cur, −F_ref) < 0, so every changed point (whose
interpolated value is negative) has at least one negative corner and gets a region.

Labelling is union-find over runs of negative nodes along z, not over nodes
(:mod:`sdp.fields._volume_kernels`): a run joins the runs it overlaps in the lines before it along x
and y, and the run that ends its line in the block below (6-connectivity). Per region:
points, centroid, bounding box and volume (negative nodes × l³), largest region first;
``min_region_points`` drops strays.

In tiles (:mod:`sdp.scale._tiles`) each tile labels its own part (:func:`label_part`): the components
of D < 0 over the tile's own nodes and the node planes just beyond its +x and +y faces (its
points' cells reach them; the tile's halo makes their values exact). It returns each label's
node count and first node and the labels of its shared face nodes (its −x/−y faces, the planes
beyond its +x/+y faces), not the blocks. :func:`join_parts` then joins them: every edge of the
whole graph lies in some tile's part and parts overlap only in face nodes, so (tile, label)
pairs holding the same node are joined (the connected components of that small graph, as
distributed connected-component labelling does), and the components are numbered by their
first node, as the untiled labelling numbers them: labels, volumes and point labels equal the
untiled run's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..fields._boolean import check_compatible
from ..fields._density import DensityField
from ..fields._lattice import BLOCK
from ..fields._volume_kernels import (
    corner_labels,
    group_stats,
    label_nodes,
    part_summary,
    volume_at,
    volume_masks,
)

__all__ = ["Region", "label_points", "describe_regions", "PartLabels", "label_part", "join_parts"]


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
        Volume of the region's grid cells: its negative nodes × l³ (world units cubed); with
        ``decision="combined"``, its cells of 1.5σ, which the distance's points fill too.
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
    it holds none); with no ``B`` (``hb`` = inf), v = h_a − A. The kernels of ``sdp.fields._volume_kernels``
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
        return self._at(field, points, signs=False)

    def negative_at(self, field: DensityField, points: np.ndarray) -> np.ndarray:
        """``self.at(field, points) < 0``, without interpolating v where B exceeds h_b at every
        corner of a point's cell (v > 0 there)."""
        return self._at(field, points, signs=True) < 0

    def _at(self, field: DensityField, points: np.ndarray, *, signs: bool) -> np.ndarray:
        out = np.empty(len(points))
        volume_at(points, field.grid.origin, field.voxel_size, field.blocks.directory, *self.kernel_args(field), out,
                  signs)
        return out

    def kernel_args(self, field: DensityField) -> tuple:
        """The arguments of the volume kernels of ``sdp.fields._volume_kernels``, on ``field``'s blocks."""
        return field.blocks.keys, self.a_blocks, self.ha, self.b_blocks, self.b_directory, self.shift, self.hb


_NO_BLOCKS = np.zeros((0, BLOCK**3), np.float32)
_NO_DIRECTORY = np.full((1, 1, 1), -1, np.int32)


def label_volume(field: DensityField, volume: Volume, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`label_points` of a :class:`Volume` on ``field``'s blocks."""
    args = volume.kernel_args(field)
    slot, labels, node_counts = label_nodes(volume_masks(*args), field.blocks.directory, field.blocks.keys)
    point_labels = corner_labels(field.grid.to_grid_units(points), field.blocks.directory, slot, labels, *args)
    return point_labels, node_counts


def describe_regions(points: np.ndarray, point_labels: np.ndarray,
                     volumes: np.ndarray) -> tuple[list[Region], np.ndarray]:
    """Summaries of the components holding labelled points, largest first; ``volumes``: each
    component's (world units cubed: its nodes, or a combined region's cells).

    Returns the regions and each point's region label (-1 for unlabelled points); regions
    are renumbered 0 … n−1 by decreasing point count.
    """
    counts, sums, mins, maxs = group_stats(points, point_labels, len(volumes))
    used = np.flatnonzero(counts)
    order = used[np.argsort(-counts[used], kind="stable")]
    rank = np.full(len(volumes) + 1, -1, np.int64)  # the last slot maps label -1 to -1
    rank[order] = np.arange(len(order))
    regions = [Region(label=i, n_points=int(counts[j]), centroid=sums[j] / counts[j], bbox_min=mins[j],
                      bbox_max=maxs[j], volume=float(volumes[j]))
               for i, j in enumerate(order)]
    return regions, rank[point_labels]


# ---------------------------------------------------------------------------- regions in parts (tiles)
# A tile labels the components of its own nodes plus the node planes just beyond its +x and +y faces
# (its points' cells reach them; their values are exact there, inside the halo). Every edge of the
# whole graph lies in some tile's part and parts overlap only in face nodes, so joining the parts'
# labels wherever two parts hold the same node gives the whole volume's components: only the face
# nodes travel (as in distributed connected-component labelling).
_LINE_X, _LINE_Y = np.divmod(np.arange(BLOCK * BLOCK), BLOCK)


@dataclass
class PartLabels:
    """The components of one part (a tile) of a volume, as :func:`join_parts` needs them.

    Attributes
    ----------
    point_labels : ndarray of int64 (n,)
        The part's component of each point given to :func:`label_part` (-1: none).
    node_counts : ndarray of int64 (n_labels,)
        Negative nodes of each component that are the part's own (not those beyond its faces).
    first_node : ndarray of int64 (n_labels, 4)
        The component's first own node in the order of an untiled field's labels (global block
        key x, y, z, node index in the block); the int64 maximum for a component holding none.
    face_nodes : ndarray of int64 (f, 3)
        Global node coordinates of the negative nodes the part shares with its neighbours (its
        own nodes on its −x and −y faces, its nodes beyond its +x and +y faces).
    face_labels : ndarray of int64 (f,)
        Their components.
    """

    point_labels: np.ndarray
    node_counts: np.ndarray
    first_node: np.ndarray
    face_nodes: np.ndarray
    face_labels: np.ndarray


def label_part(field: DensityField, volume: Volume, points: np.ndarray, blocks_lo, blocks_hi) -> PartLabels:
    """Components of ``volume`` < 0 in one part of ``field``'s blocks: the blocks whose global x, y
    keys lie in [``blocks_lo``, ``blocks_hi``) (a tile's own column), and the first node plane
    beyond its +x and +y faces; and the component of each of ``points`` (cells in the part).

    ``field`` must hold exact values there (a tile's field built with its halo). Labels are the
    part's own; :func:`join_parts` numbers the whole's components as :func:`label_points` does.
    """
    lo, hi = np.asarray(blocks_lo, np.int64), np.asarray(blocks_hi, np.int64)
    keys = field.global_keys
    in_x, in_y = (keys[:, 0] >= lo[0]) & (keys[:, 0] < hi[0]), (keys[:, 1] >= lo[1]) & (keys[:, 1] < hi[1])
    past_x, past_y = keys[:, 0] == hi[0], keys[:, 1] == hi[1]
    own = in_x & in_y
    args = volume.kernel_args(field)
    masks = volume_masks(*args)  # per block, per line of nodes along z (line = x·8 + y)
    masks[~(own | (past_x & (in_y | past_y)) | (in_x & past_y))] = 0
    # beyond the faces, only their first plane: farther, the values are not exact
    masks[np.ix_(past_x, _LINE_X > 0)] = 0
    masks[np.ix_(past_y, _LINE_Y > 0)] = 0
    slot, labels, counts = label_nodes(masks, field.blocks.directory, field.blocks.keys)
    point_labels = corner_labels(field.grid.to_grid_units(points), field.blocks.directory, slot, labels, *args)
    active = np.flatnonzero(slot >= 0)  # the blocks of the rows of ``labels``, in order
    node_counts, first_node, nodes, node_labels = part_summary(labels, own[active], keys[active], lo, len(counts))
    return PartLabels(point_labels, node_counts, first_node, nodes, node_labels)


def _node_key(nodes: np.ndarray) -> np.ndarray:
    """One sortable value per node (k, 3), equal for equal nodes: x, y, z packed into an int64 from
    their minima (one sort instead of a sort on three keys: 13 M face nodes joined in 5.5 s, not 14 s),
    or, for a box too large to pack, each row's bytes (grouped alike, in another order)."""
    if len(nodes) == 0:
        return np.zeros(0, np.int64)
    lo = nodes.min(axis=0)
    bits = [int(v).bit_length() for v in nodes.max(axis=0) - lo]
    if sum(bits) > 62:
        return np.ascontiguousarray(nodes, np.int64).view(np.dtype((np.void, 24))).ravel()
    shifted = nodes - lo
    return (shifted[:, 0] << (bits[1] + bits[2])) | (shifted[:, 1] << bits[2]) | shifted[:, 2]


def join_parts(parts: list[PartLabels]) -> tuple[list[np.ndarray], np.ndarray]:
    """The whole volume's components from its parts' (:func:`label_part`): each part's point
    labels in the whole's numbering (that of :func:`label_points` on the whole volume), and the
    negative nodes of each component."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    sizes = np.array([len(p.node_counts) for p in parts], np.int64)
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    total = int(offsets[-1])
    nodes = np.concatenate([p.face_nodes for p in parts]) if parts else np.zeros((0, 3), np.int64)
    ids = np.concatenate([p.face_labels + o for p, o in zip(parts, offsets, strict=False)]) if parts else nodes[:, 0]
    key = _node_key(nodes)
    order = np.argsort(key)  # equal nodes side by side (their order does not matter)
    key, ids = key[order], ids[order]
    same = np.flatnonzero(key[1:] == key[:-1])
    graph = coo_matrix((np.ones(len(same)), (ids[same], ids[same + 1])), shape=(total, total))
    _, component = connected_components(graph, directed=False)
    first = np.concatenate([p.first_node for p in parts]) if parts else np.zeros((0, 4), np.int64)
    by_first = np.lexsort(first.T[::-1])
    seen, at = np.unique(component[by_first], return_index=True)  # each component's first position
    rank = np.empty(len(seen), np.int64)
    rank[seen[np.argsort(at, kind="stable")]] = np.arange(len(seen))
    label = rank[component] if total else np.zeros(0, np.int64)
    counts = np.bincount(label, weights=np.concatenate([p.node_counts for p in parts]) if parts else None,
                         minlength=len(seen)).astype(np.int64)
    point_labels = [np.where(p.point_labels >= 0, label[np.maximum(p.point_labels, 0) + o], -1)
                    for p, o in zip(parts, offsets, strict=False)]
    return point_labels, counts
