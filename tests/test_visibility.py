import numpy as np
import pytest

import sdp
from sdp.change._range_image import HIDDEN, SAME_SURFACE, SEEN_FREE, UNOBSERVED, RangeImage
from sdp.change._visibility import visibility_states
from sdp.data._scene import FURNITURE, INSERTED, office_scene, scan

CAMERA = (0.3, 0.2, 2.2)  # sdp.data._scene's default camera
BOX = INSERTED[0]  # a 30 cm box on the table


def test_range_image_classes_along_rays():
    # a wall 2 m in front of the sensor, sampled on a 1 mm-per-metre angular grid
    u, v = np.meshgrid(np.linspace(-0.3, 0.3, 301), np.linspace(-0.2, 0.2, 201))
    rays = np.c_[u.ravel(), v.ravel(), np.ones(u.size)]
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    image = RangeImage.from_points(2.0 * rays, (0, 0, 0))
    assert image.spacing == pytest.approx(0.002, rel=0.1)  # the grid's angular step
    probe = rays[[100 * 301 + 150, 50 * 301 + 40, 150 * 301 + 250]]
    cls = image.classify(np.r_[1.0 * probe, 2.0 * probe, 3.0 * probe, [[0.0, 0.0, -1.0], [1.0, 0.0, 0.05]]],
                         range_noise=0.0, floor=0.01)
    np.testing.assert_array_equal(cls, [SEEN_FREE] * 3 + [SAME_SURFACE] * 3 + [HIDDEN] * 3 + [UNOBSERVED] * 2)
    # the band grows as r²: 2.03 m is the same surface at range_noise 0.015 (6 cm at 2 m), not at 0.005
    assert (image.classify(2.03 * probe, range_noise=0.015) == SAME_SURFACE).all()
    assert (image.classify(2.03 * probe, range_noise=0.005) == HIDDEN).all()


def test_a_depth_cameras_image_is_its_own_pixels_whatever_its_pose():
    # a 64 × 48 pinhole camera (f = 60 px) turned 30° about two axes and moved, 2 m from a wall
    from scipy.spatial.transform import Rotation

    from sdp._core._pinhole import fit_camera

    c, r = np.meshgrid(np.arange(64.0), np.arange(48.0))
    rays = np.c_[(c.ravel() - 31.5) / 60, (r.ravel() - 23.5) / 60, np.ones(c.size)]
    turn, origin = Rotation.from_euler("xy", [30, -30], degrees=True).as_matrix(), np.array([5.0, -2.0, 1.0])
    frame = origin + (2.0 * rays) @ turn.T
    keep = np.flatnonzero((c.ravel() > 2) | (r.ravel() < 40))  # a dark corner returned nothing
    camera = fit_camera(frame[keep], keep, (48, 64), origin)
    image = RangeImage.from_points(frame[keep], origin, camera=camera)
    assert image.camera is not None and image.shape == (43, 32)  # cells of 1.5 pixels
    assert (image.classify(frame[keep], range_noise=0.0, floor=0.01) == SAME_SURFACE).all()
    probe = origin + np.r_[1.0, 3.0][:, None] * rays[[10 * 64 + 30]] @ turn.T
    np.testing.assert_array_equal(image.classify(probe, range_noise=0.0, floor=0.01), [SEEN_FREE, HIDDEN])
    # the dark corner's rays went out: seen free; behind the camera and beside its image: not in view
    corner = origin + 1.5 * rays[[45 * 64 + 1]] @ turn.T
    behind, beside = origin - 1.0 * rays[[10 * 64 + 30]] @ turn.T, origin + np.array([[2.0, -0.4, 1.2]]) @ turn.T
    assert image.in_view(np.r_[corner, behind, beside]).tolist() == [True, False, False]
    # a frame no pinhole fits (its pixels shuffled) has no camera
    assert fit_camera(frame, np.random.default_rng(0).permutation(len(frame)), (48, 64), origin) is None


def test_a_frame_whose_returns_lie_in_one_row_or_column_fits_no_camera():
    # their rays lie in one plane, which many cameras fit: the DLT's null space is not one vector
    # (a column's raised a singular matrix, a row's gave a camera 0.02° tall)
    from sdp._core._pinhole import fit_camera

    c, r = np.meshgrid(np.arange(64.0), np.arange(48.0))
    frame = 2.0 * np.c_[(c.ravel() - 31.5) / 60, (r.ravel() - 23.5) / 60, np.ones(c.size)]
    row, column = np.flatnonzero(r.ravel() == 20), np.flatnonzero(c.ravel() == 30)
    assert fit_camera(frame[row], row, (48, 64), np.zeros(3)) is None
    assert fit_camera(frame[column], column, (48, 64), np.zeros(3)) is None
    both = np.union1d(row, column)
    assert fit_camera(frame[both], both, (48, 64), np.zeros(3)) is not None

def test_a_sparse_grid_of_many_pixels_builds_no_image_of_them(monkeypatch):
    # a TLS grid stored as an organized PCD: 1,500 returns in a 3,000 × 4,000 image; an index of its
    # 12 M pixels (48 MB) or 5 M cells of 1.5 pixels would outweigh the returns many times
    import sdp.change._range_image as R
    from sdp._core._pinhole import fit_camera
    from sdp._core._points import as_points
    from sdp.fields._spacing import kth_in_image

    rng = np.random.default_rng(0)
    pixels = np.sort(rng.choice(3000 * 4000, 1500, replace=False))
    c, r = pixels % 4000, pixels // 4000
    xyz = np.c_[(c - 1999.5) / 2000, (r - 1499.5) / 2000, np.ones(len(c))] * 3.0
    camera = fit_camera(xyz, pixels, (3000, 4000), np.zeros(3))
    assert camera is not None
    pts = as_points(xyz)._replace(image=(pixels, (3000, 4000), np.zeros(3)))
    assert kth_in_image(pts, np.arange(10), 4) is None  # the hashed grid answers
    monkeypatch.setattr(R, "_MAX_CELLS", 1_000_000)
    image = RangeImage.from_points(xyz, np.zeros(3), camera=camera)
    assert image.camera is None and image.shape[0] * image.shape[1] <= 1_000_000  # the angular image, coarser


def test_range_image_covers_a_full_turn():
    # a horizontal 360° scan of a cylindrical wall: the azimuth seam must not lose any ray
    az, z = np.meshgrid(np.linspace(-np.pi, np.pi, 720, endpoint=False), np.linspace(-0.5, 0.5, 60))
    wall = np.c_[3 * np.cos(az.ravel()), 3 * np.sin(az.ravel()), z.ravel()]
    image = RangeImage.from_points(wall, (0, 0, 0))
    assert abs(image.frame[2, 2]) > 0.99  # the pole is vertical
    assert (image.classify(wall, range_noise=0.0, floor=0.01) == SAME_SURFACE).all()
    assert (image.classify(0.5 * wall, range_noise=0.0, floor=0.01) == SEEN_FREE).all()


def test_disoccluded_table_is_not_appeared_with_sensor_origin():
    # the box stood on the table in the reference and is gone: the current sees the table it hid
    rng = np.random.default_rng(1)
    reference, hit_ref = scan(FURNITURE + (BOX,), camera=CAMERA, rng=rng)
    current, _ = scan(FURNITURE, camera=CAMERA, rng=rng)
    box = hit_ref == len(FURNITURE)
    plain = sdp.detect_changes(reference, current, min_region_points=20, lattice=sdp.Lattice(voxel_size="auto"))
    seen = sdp.detect_changes(reference, current, min_region_points=20, lattice=sdp.Lattice(voxel_size="auto"),
                              coverage=sdp.Coverage(sensor_origin=CAMERA))
    assert plain.appeared.sum() > 500  # the uncovered table patch looks new to the density test
    assert seen.appeared.sum() == 0 and seen.appeared_regions == []
    # the box itself did disappear: the current's rays pass through its place
    assert seen.disappeared[box].mean() > 0.6 and not seen.disappeared[~box].any()
    assert seen.disappeared[box].sum() >= 0.95 * plain.disappeared[box].sum()
    assert seen.coverage == {"appeared": "sensor rays", "disappeared": "sensor rays"}
    assert plain.coverage == {"appeared": "footprint", "disappeared": "footprint"}


def test_new_objects_are_still_found():
    s = office_scene(seed=0)
    plain = sdp.detect_changes(s.reference, s.current, min_region_points=20, coverage=sdp.Coverage(enabled=False))  # density alone
    seen = sdp.detect_changes(s.reference, s.current, min_region_points=20,
                              coverage=sdp.Coverage(sensor_origin=CAMERA))
    assert sdp.kappa(s.appeared_truth, seen.appeared) > 0.85
    # what the reference's camera could not see (its far corner, beyond range) is not comparable, not new
    assert 0 < seen.current_not_comparable.sum() < 0.01 * len(s.current)
    assert not (seen.current_not_comparable & seen.appeared).any()
    for i in range(len(INSERTED)):  # every object keeps most of what the density test found, or is not comparable
        obj = s.object_of_current == i
        assert (seen.appeared | seen.current_not_comparable)[obj].sum() >= 0.8 * plain.appeared[obj].sum()
    # what the inserted objects hide in the current scan has not disappeared: it is hidden
    assert seen.disappeared.sum() < 0.2 * plain.disappeared.sum()
    # the regions describe exactly the points kept
    assert sum(g.n_points for g in seen.appeared_regions) == seen.appeared.sum()
    assert all(g.n_points >= 20 for g in seen.appeared_regions)


def test_a_depth_camera_in_millimetres_finds_what_it_finds_in_metres():
    # a depth image's points kept in its own unit: the band (per metre) is taken per millimetre,
    # said in the summary; before, its 0.015·r² reached tens of metres and every change was "the
    # same surface"
    s = office_scene(seed=0)
    metres = sdp.detect_changes(s.reference, s.current, coverage=sdp.Coverage(sensor_origin=CAMERA))
    mm = sdp.detect_changes(1000 * s.reference, 1000 * s.current,
                            coverage=sdp.Coverage(sensor_origin=1000 * np.asarray(CAMERA)))
    assert metres.appeared.sum() > 1000 and "range_units" not in metres.summary()
    assert abs(int(mm.appeared.sum()) - int(metres.appeared.sum())) <= 0.02 * metres.appeared.sum()
    assert mm.summary()["range_units"] == {"reference": 1e-3, "current": 1e-3}
    assert mm.range_noise["reference"] == pytest.approx(1e-3 * metres.range_noise["reference"])
    given = sdp.detect_changes(1000 * s.reference, 1000 * s.current,
                               coverage=sdp.Coverage(sensor_origin=1000 * np.asarray(CAMERA), range_noise=0.02))
    assert given.range_noise == {"reference": 0.02, "current": 0.02} and not given.range_units


def test_two_sensor_origins_swap_with_the_clouds():
    a, b = np.array(CAMERA), np.array([0.6, 0.5, 2.0])
    rng = np.random.default_rng(2)
    reference, _ = scan(FURNITURE + INSERTED[:3], camera=a, rng=rng)
    current, hit = scan(FURNITURE + INSERTED[:3] + INSERTED[4:5], camera=b, rng=rng)
    new = hit == len(FURNITURE) + 3
    kw = dict(lattice=sdp.Lattice(voxel_size=sdp.auto_voxel_size(reference, current)), min_region_points=20)  # one voxel both ways
    plain = sdp.detect_changes(reference, current, **kw)
    seen = sdp.detect_changes(reference, current, **kw, coverage=sdp.Coverage(sensor_origin=[a, b]))
    # surfaces only the moved camera sees are mostly explained; the new crate stays
    assert (seen.appeared & ~new).sum() < 0.5 * (plain.appeared & ~new).sum()
    assert seen.appeared[new].mean() > 0.6
    # appeared is judged from the reference's view, disappeared from the current's
    swapped = sdp.detect_changes(current, reference, **kw, coverage=sdp.Coverage(sensor_origin=[b, a]))
    np.testing.assert_array_equal(swapped.appeared, seen.disappeared)
    np.testing.assert_array_equal(swapped.disappeared, seen.appeared)
    alone = sdp.detect_changes(reference, current, **kw, coverage=sdp.Coverage(sensor_origin=a))
    np.testing.assert_array_equal(alone.appeared,
                                  seen.appeared)


def test_without_sensor_origin_nothing_changes(rng):
    s = office_scene(seed=3, width=160, height=120)
    r = sdp.detect_changes(s.reference, s.current, lattice=sdp.Lattice(voxel_size=0.02))
    explicit = sdp.detect_changes(s.reference, s.current, lattice=sdp.Lattice(voxel_size=0.02),
                                  coverage=sdp.Coverage(sensor_origin=None))
    np.testing.assert_array_equal(r.appeared, explicit.appeared)
    np.testing.assert_array_equal(r.disappeared, explicit.disappeared)
    with pytest.raises(sdp.SDPError, match="range_noise .* would be ignored"):  # no rays to widen
        sdp.Coverage(sensor_origin=None, range_noise=0.5)


def test_nan_rows_keep_their_place(rng):
    s = office_scene(seed=4, width=160, height=120)
    cur = s.current.copy()
    cur[::50] = np.nan
    r = sdp.detect_changes(s.reference, cur, lattice=sdp.Lattice(voxel_size=0.02),
                           coverage=sdp.Coverage(sensor_origin=CAMERA))
    assert r.appeared.shape == (len(cur),) and not r.appeared[::50].any()


@pytest.mark.parametrize("origin, error, match", [
    ((0.0, 1.0), sdp.InvalidPointsError, r"or one row per scan .* got shape \(2,\)"),
    (np.zeros((3, 3)), sdp.InvalidPointsError, r"got shape \(3, 3\)"),
    ((0.0, np.nan, 1.0), sdp.InvalidPointsError, "must be finite"),
    ("camera", sdp.InvalidOptionError, "sensor_origin"),
])
def test_bad_sensor_origin_is_a_clear_error(origin, error, match):
    pts = np.random.default_rng(0).random((500, 3))
    with pytest.raises(error, match=match):
        sdp.detect_changes(pts, pts + 0.001, lattice=sdp.Lattice(voxel_size=0.05),
                           coverage=sdp.Coverage(sensor_origin=origin))
    with pytest.raises(ValueError, match="range_noise"):
        sdp.detect_changes(pts, pts, lattice=sdp.Lattice(voxel_size=0.05),
                           coverage=sdp.Coverage(sensor_origin=(0, 0, -1), range_noise=-1))


def test_sensor_origin_on_every_point_is_a_clear_error():
    pts = np.zeros((10, 3))
    with pytest.raises(sdp.SDPError, match="no ray"):
        RangeImage.from_points(pts, (0, 0, 0))


def test_visibility_states_leave_unchanged_points_alone(rng):
    pts = rng.random((1000, 3)) + [0, 0, 2]
    changed = np.zeros(1000, bool)
    assert not visibility_states(pts, changed, pts, (0, 0, 0), sigma=0.01).any()


def test_pcd_viewpoint_is_the_sensor_origin(tmp_path):
    header = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 3\nHEIGHT 1\n"
              "VIEWPOINT 0.5 -1 2 0.7071068 0 0.7071068 0\nPOINTS 3\nDATA ascii\n")
    (tmp_path / "a.pcd").write_text(header + "1 2 3\n4 5 6\n7 8 9\n")
    cloud = sdp.read_points(tmp_path / "a.pcd")
    np.testing.assert_allclose(cloud.viewpoint, [0.5, -1, 2, 0.7071068, 0, 0.7071068, 0], rtol=1e-6)
    np.testing.assert_allclose(cloud.sensor_origin, [0.5, -1, 2])
    sdp.write_points(tmp_path / "a.ply", cloud.xyz)
    assert sdp.read_points(tmp_path / "a.ply").sensor_origin is None


@pytest.mark.shared_data
def test_real_kinect_pair_with_sensor_origin(shared_data):
    # mOSD learn0 -> learn1 (fixed camera): objects were moved, uncovering table the reference never saw
    ref = sdp.read_points(shared_data / "mosd/learn/learn0.pcd")
    cur = sdp.read_points(shared_data / "mosd/learn/learn1.pcd")
    np.testing.assert_array_equal(ref.sensor_origin, [0, 0, 0])
    table = (cur.fields["label"] >= 1) & (cur.fields["label"] < 10)
    objects = cur.fields["label"] // 10 >= 2
    plain = sdp.detect_changes(ref.xyz, cur.xyz, min_region_points=50, lattice=sdp.Lattice(voxel_size="auto"))
    seen = sdp.detect_changes(ref.xyz, cur.xyz, min_region_points=50, lattice=sdp.Lattice(voxel_size="auto"),
                              coverage=sdp.Coverage(sensor_origin=[ref.sensor_origin, cur.sensor_origin]))
    assert plain.appeared[table].sum() > 2000  # uncovered table, flagged by the density test alone
    assert seen.appeared[table].sum() < 0.05 * plain.appeared[table].sum()
    assert seen.appeared[objects].sum() > 0.9 * plain.appeared[objects].sum()


@pytest.mark.slow
def test_field_of_view_is_the_convex_hull_of_the_returned_cells():
    from scipy.spatial import Delaunay

    from sdp.change._range_image import _convex_hull

    rng = np.random.default_rng(7)
    squares = np.array([[-0.5, -0.5], [-0.5, 0.5], [0.5, -0.5], [0.5, 0.5]])
    for _ in range(100):
        seen = np.zeros((rng.integers(3, 30), rng.integers(3, 30)), bool)
        seen.flat[rng.integers(0, seen.size, rng.integers(3, 9))] = True
        corners = (np.argwhere(seen)[:, None, :] + squares).reshape(-1, 2)
        if np.linalg.matrix_rank(corners - corners[0]) < 2:
            continue
        centres = np.argwhere(np.ones_like(seen)).astype(float)
        brute = (Delaunay(corners).find_simplex(centres, tol=1e-9) >= 0).reshape(seen.shape)
        np.testing.assert_array_equal(_convex_hull(seen), brute)


def test_plane_test_helpers_match_numpy(rng):
    """The sensor test's kernels give what the NumPy expressions they replace gave."""
    from sdp.change._planes import _cube_means, _every_nth_unchanged

    query = rng.normal(size=(5_000, 3)) * [1.0, 2.0, 0.5] + 1e3  # far from the origin, as world coordinates
    inverse, centres = _cube_means(query, 0.4)
    cells = np.floor(query / 0.4).astype(np.int64)
    keys, ref_inverse = np.unique(cells, axis=0, return_inverse=True)
    ref_inverse = ref_inverse.ravel()
    ref = np.stack([np.bincount(ref_inverse, weights=query[:, d]) for d in range(3)], axis=1)
    ref /= np.bincount(ref_inverse)[:, None]
    assert len(centres) == len(keys) and inverse.max() == len(centres) - 1
    # the same grouping (numbered otherwise) and the same means, bit for bit
    order = np.empty(len(keys), np.int64)
    order[inverse] = ref_inverse
    np.testing.assert_array_equal(order[inverse], ref_inverse)
    np.testing.assert_array_equal(centres, ref[order])
    changed = rng.random(len(query)) < 0.3
    for stride in (1, 3, 8):
        np.testing.assert_array_equal(_every_nth_unchanged(query, changed, stride),
                                      query[np.flatnonzero(~changed)[::stride]])
    # which points lie within a reach of another set: as a brute force, at any reach (none, some, all)
    from scipy.spatial.distance import cdist

    from sdp.change._planes import near_any

    others = query[::50] + 0.3
    nearest = cdist(query, others).min(axis=1)
    for reach in (1e-9, 1e-3, 0.2, 0.5, 50.0):  # 1e-9: too many cells to key, the k-d tree answers
        np.testing.assert_array_equal(near_any(query, others, reach), nearest <= reach)


@pytest.mark.parametrize("far", [0.0, -3e5, 1e6])
def test_cube_means_number_cubes_by_first_point_in_any_box(rng, far):
    """Cubes are numbered in the order their first point comes and their means summed in row order,
    around the origin and in a box wider than a cell key packs (2**21 cubes per axis: 1e6 / 0.4)."""
    from sdp.change._planes import _cube_means

    query = rng.normal(size=(3_000, 3)) * [1.0, 2.0, 0.5]
    query[::500] += far  # a few points far away (none when far is 0)
    inverse, centres = _cube_means(query, 0.4)
    cells = np.floor(query / 0.4).astype(np.int64)
    _, first, ref_inverse = np.unique(cells, axis=0, return_index=True, return_inverse=True)
    ref_inverse = ref_inverse.ravel()
    number = np.empty(len(first), np.int64)
    number[np.argsort(first)] = np.arange(len(first))
    np.testing.assert_array_equal(inverse, number[ref_inverse])
    ref = np.stack([np.bincount(inverse, weights=query[:, d]) for d in range(3)], axis=1)
    np.testing.assert_array_equal(centres, ref / np.bincount(inverse)[:, None])
    inverse, centres = _cube_means(query[:0], 0.4)
    assert inverse.shape == (0,) and centres.shape == (0, 3)


def test_ground_the_other_scan_never_saw_is_not_comparable_far_from_what_it_saw():
    """The current scan reaches 2.5 m beyond the reference's floor, with a box there: the plane of
    the floor the reference saw is not extrapolated over ground it never saw (that was called
    unchanged, the box's foot too); what lies within the seen patch's reach is explained."""
    rng = np.random.default_rng(0)

    def floor(n, x1):
        p = rng.uniform(0, 1, (n, 3))
        p[:, 0] *= x1
        p[:, 2] = rng.normal(0, 0.002, n)
        return p

    box = rng.uniform(0, 1, (800, 3)) * [0.1, 0.1, 0.1] + [2.0, 0.4, 0.0]
    ref, cur = floor(3000, 0.5), np.vstack([floor(18000, 3.0), box])
    r = sdp.detect_changes(ref, cur, coverage=sdp.Coverage(sensor_origin=(0.25, 0.5, 1.0)))
    far = cur[:, 0] > 1.0  # more than a patch's reach beyond what the reference saw
    assert (r.current_state[far] == sdp.NOT_COMPARABLE).all()
    near = (cur[:, 0] > 0.5) & (cur[:, 0] < 0.55)
    assert (r.current_state[near] == sdp.UNCHANGED).mean() > 0.9  # the seen floor continued: explained


def test_an_unchanged_object_seen_from_either_side_changes_nothing():
    """A static room scanned from either side of a partition (a multi-station survey): what one
    station saw behind it is hidden from the other by the partition's far face, which the first
    never saw. That face missing from the first scan says nothing of whether it is gone: the post
    behind it and the faces themselves are not comparable, not changed."""
    from sdp.data._scene import Box

    rng = np.random.default_rng(3)
    partition, post = Box((2.4, 0.0, 0.0), (2.6, 4.0, 2.0)), Box((1.5, 1.8, 0.0), (1.6, 2.2, 1.2))
    a, b = (0.4, 2.0, 1.5), (4.6, 2.0, 1.5)
    reference, hit = scan((partition, post), camera=a, target=(2.4, 2.0, 0.7), rng=rng)
    current, _ = scan((partition, post), camera=b, target=(2.6, 2.0, 0.7), rng=rng)
    r = sdp.detect_changes(reference, current, coverage=sdp.Coverage(sensor_origin=[a, b]))
    assert (hit == 1).sum() > 300 and r.reference_not_comparable[hit == 1].mean() > 0.9
    assert r.disappeared.sum() < 0.001 * len(reference) and r.appeared.sum() < 0.001 * len(current), \
        (r.disappeared.sum(), r.appeared.sum())


def _spinning_lidar(origin, yaw, boxes, *, beams=16, columns=1800, seed=0, tilt=0.0):
    """A spinning LiDAR's returns (beams rings from -15° to 15°, ``columns`` steps of azimuth, 1 cm
    of range noise; its axis tilted by ``tilt`` degrees) inside a room 10 × 8 × 3 m holding
    axis-aligned ``boxes`` (lo, hi)."""
    from scipy.spatial.transform import Rotation

    rings = np.linspace(-15, 15, beams) if np.isscalar(beams) else np.asarray(beams, float)  # or the rings' angles
    el = np.deg2rad(rings)[:, None]
    az = np.linspace(-np.pi, np.pi, columns, endpoint=False)[None, :]
    d = np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)), -1).reshape(-1, 3)
    d = d @ Rotation.from_euler("yz", [tilt, yaw], degrees=True).as_matrix().T
    o = np.asarray(origin, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        room_lo, room_hi = np.array([-4.0, -4.0, 0.0]), np.array([6.0, 4.0, 3.0])
        t = np.max([(room_lo - o) / d, (room_hi - o) / d], axis=0).min(axis=1)  # leaving the room
        for lo, hi in boxes:  # slabs: entering the box before leaving it
            near, far = np.sort([(np.asarray(lo) - o) / d, (np.asarray(hi) - o) / d], axis=0)
            t_in, t_out = near.max(axis=1), far.min(axis=1)
            t = np.where((t_in <= t_out) & (t_in > 0) & (t_in < t), t_in, t)
    t = t + np.random.default_rng(seed).normal(0, 0.01, len(t))
    return o + d * t[:, None]


# a VLP-32C's rings: 0.33° apart near the horizon, 9.4° at the bottom
UNEVEN = [-25, -15.6, -11.3, -8.8, -7.3, -6.1, -5.3, -4.7, -4, -3.7, -3.3, -3, -2.7, -2.3, -2, -1.7, -1.3, -1, -0.7, -0.3,
          0, 0.3, 0.7, 1, 1.3, 1.7, 2.3, 3.3, 4.7, 7, 10.3, 15]


@pytest.mark.parametrize("beams, height, tilt", [(16, 0.5, 0), (16, 1.0, 0), (32, 1.0, 20), (64, 0.5, 0),
                                                 (UNEVEN, 1.0, 0)])
def test_a_spinning_lidars_rings_leave_no_false_change_between_them(beams, height, tilt):
    # two robot poses 0.58 m and 20° apart in a static room: the floor between one scan's rings,
    # and below its lowest ring, is no change; most of a box brought in is found
    table = ([1.5, 1.0, 0.0], [2.5, 2.0, 0.8])
    a_at, b_at = [1.0, 0.0, height], [1.5, -0.3, height]
    a = _spinning_lidar(a_at, 0, [table], beams=beams, seed=1, tilt=tilt)
    b = _spinning_lidar(b_at, 20, [table], beams=beams, seed=2, tilt=tilt)
    for noise in (0.001, 0.015):  # a laser's range noise, and the default's
        r = sdp.detect_changes(a, b, coverage=sdp.Coverage(sensor_origin=[a_at, b_at], range_noise=noise))
        assert r.appeared.sum() == 0 and r.disappeared.sum() == 0, (noise, r.appeared.sum(), r.disappeared.sum())
    box = ([3.0, -2.0, 0.0], [3.6, -1.4, 0.6])
    b = _spinning_lidar(b_at, 20, [table, box], beams=beams, seed=2, tilt=tilt)
    on_box = np.all((b >= np.array(box[0]) - 0.02) & (b <= np.array(box[1]) + 0.02), axis=1) & (b[:, 2] > 0.05)
    r = sdp.detect_changes(a, b, coverage=sdp.Coverage(sensor_origin=[a_at, b_at], range_noise=0.001))
    assert r.appeared[on_box].mean() > 0.5 and r.appeared[~on_box].sum() < 0.002 * len(b), \
        (r.appeared[on_box].mean(), r.appeared[~on_box].sum())


def test_a_scan_pattern_that_leaves_directions_unsampled_says_nothing_of_them(tmp_path):
    # a rosette-like scanner's unorganized PCD files: each window samples a pattern of directions
    # that leaves half of its view unsampled, the next window another; a static bumpy wall 3 m away
    def window(shift, seed):
        rng = np.random.default_rng(seed)
        u, v = rng.uniform(-0.5, 0.5, (2, 120_000))
        keep = np.sin(9 * u + shift) + np.sin(9 * v + shift) > 0
        u, v = u[keep], v[keep]
        d = np.c_[np.ones(len(u)), u, v]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        xyz = d * (3.0 + 0.25 * np.sin(25 * u) * np.sin(25 * v) + rng.normal(0, 0.002, len(u)))[:, None]
        path = tmp_path / f"w{seed}.pcd"
        path.write_text(f"VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {len(xyz)}\nHEIGHT 1\n"
                        f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(xyz)}\nDATA ascii\n"
                        + "\n".join(f"{x:.5f} {y:.5f} {z:.5f}" for x, y, z in xyz) + "\n")
        return sdp.read_points(path)

    a, b = window(0.0, 1), window(1.5, 2)
    assert not a.organized  # a sensor's own points, not an image
    r = sdp.detect_changes(a, b, coverage=sdp.Coverage(sensor_origin=(0, 0, 0)))  # 16,503 appeared before
    assert r.appeared.sum() == 0 and r.disappeared.sum() == 0, (r.appeared.sum(), r.disappeared.sum())
    # arrays, as a camera's frames are passed: every ray taken as sent, a missing return as seen free
    assert sdp.detect_changes(a.xyz, b.xyz, coverage=sdp.Coverage(sensor_origin=(0, 0, 0))).appeared.sum() > 1000


def _camera_frame(path, boxes, *, reach=4.5, width=96, height=72, f=80.0, seed=0):
    """An organized PCD frame of a pinhole camera at the origin looking along +z (y down): the
    floor 1.2 m below, a wall 3 m away on the left and a hall to the right whose far wall, 6 m
    away, lies beyond ``reach`` (no return), ``boxes`` (lo, hi) in front."""
    rng = np.random.default_rng(seed)
    c, r = np.meshgrid(np.arange(width), np.arange(height))
    d = np.stack([(c - width / 2 + 0.5) / f, (r - height / 2 + 0.5) / f, np.ones_like(c, float)], -1).reshape(-1, 3)
    t = np.full(len(d), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        floor = np.where(d[:, 1] > 0, 1.2 / d[:, 1], np.inf)
        t = np.minimum(t, np.where(floor > 0, floor, np.inf))
        t = np.minimum(t, np.where(d[:, 0] < 0, 3.0, 6.0) / d[:, 2])
        for lo, hi in boxes:
            t1, t2 = np.asarray(lo) / d, np.asarray(hi) / d
            near, far = np.nanmax(np.minimum(t1, t2), axis=1), np.nanmin(np.maximum(t1, t2), axis=1)
            t = np.where((near <= far) & (near > 0), np.minimum(t, near), t)
    xyz = d * (t + rng.normal(0, 0.002, len(t)) * t**2)[:, None]  # depth noise along each pixel's ray
    xyz[np.linalg.norm(xyz, axis=1) > reach] = np.nan  # beyond the camera's range: no return
    path.write_text(f"VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {width}\nHEIGHT {height}\n"
                    f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {width * height}\nDATA ascii\n"
                    + "\n".join(f"{x:.5f} {y:.5f} {z:.5f}" for x, y, z in xyz) + "\n")
    return sdp.read_points(path)


def test_a_camera_ray_that_returned_nothing_looked_through_the_place(tmp_path):
    # a person steps in front of a wall beyond the camera's range: the reference's pixels there
    # returned nothing, yet they are rays the camera sent (an organized frame's every pixel), so
    # the person's place was seen free, not outside the field of view
    person = ([0.3, -1.2, 2.2], [0.9, 0.6, 2.5])
    a, b = _camera_frame(tmp_path / "a.pcd", []), _camera_frame(tmp_path / "b.pcd", [person], seed=1)
    assert a.image == (72, 96) and len(a.pixels) == len(a.xyz) and a.n_dropped > 0.2 * 72 * 96
    r = sdp.detect_changes(a, b)
    on_person = (b.xyz[:, 2] < 2.6) & (b.xyz[:, 0] > 0.25) & (b.xyz[:, 0] < 0.95) & (b.xyz[:, 1] < 0.65)
    assert on_person.sum() > 300
    assert r.appeared[on_person].mean() > 0.9 and r.current_not_comparable[on_person].mean() < 0.05
    assert not r.appeared[~on_person].any()
    # rows or columns without any return at the image's edge are margins the sensor never measured
    # (a depth image registered to a colour camera): not rays that found nothing
    from sdp._core._pinhole import fit_camera

    cut = np.flatnonzero(a.pixels % 96 < 88)  # the last 8 columns empty, as a registration margin leaves them
    camera = fit_camera(a.xyz[cut], a.pixels[cut], a.image, np.zeros(3))
    assert camera is not None and camera.box[3] == 87 and fit_camera(a.xyz, a.pixels, a.image, np.zeros(3)).box[3] == 95
    view = RangeImage.from_points(a.xyz[cut], np.zeros(3), camera=camera).in_view(a.xyz)
    assert view[cut].all() and not view[a.pixels % 96 >= 88].any()  # each pixel projects to its own
    # sdp info names the camera the frame's returns fit (the synthetic one: f = 80 px, centred)
    from sdp.cli._files import describe_file

    camera = describe_file(tmp_path / "a.pcd")["image"]["pinhole"]
    assert camera["focal_px"] == pytest.approx([80, 80], abs=0.5)
    assert camera["principal_point_px"] == pytest.approx([47.5, 35.5], abs=0.5)
    assert camera["field_of_view_deg"][0] == pytest.approx(2 * np.degrees(np.arctan(48 / 80)), abs=0.5)
    # an array gives no image: its view ends at its returns, and the person above them is not comparable
    plain = sdp.detect_changes(a.xyz, b.xyz, coverage=sdp.Coverage(sensor_origin=(0, 0, 0)))
    assert plain.current_not_comparable[on_person].mean() > 0.3


def _plates(plates, *, rng, width=240, height=240, fov=0.6, noise=0.001):
    """A camera at the origin looking along +z, one ray per pixel cast against ``plates`` (centre,
    normal, half-width in x and in y of each rectangle, bounded in the camera's x and y) and a
    wall at z = 2.5 m: (hits (n, 3), index of the plate hit, -1 the wall)."""
    u, v = np.meshgrid(np.linspace(-fov / 2, fov / 2, width), np.linspace(-fov / 2, fov / 2, height))
    rays = np.c_[u.ravel(), v.ravel(), np.ones(u.size)]
    t = np.full(len(rays), 2.5)
    which = np.full(len(rays), -1)
    for i, (centre, normal, hx, hy) in enumerate(plates):
        centre, normal = np.asarray(centre, float), np.asarray(normal, float)
        ti = (centre @ normal) / (rays @ normal)
        p = rays * ti[:, None]
        hit = (ti > 0) & (ti < t) & (np.abs(p[:, 0] - centre[0]) <= hx) & (np.abs(p[:, 1] - centre[1]) <= hy)
        t, which = np.where(hit, ti, t), np.where(hit, i, which)
    r = np.linalg.norm(rays, axis=1) * t
    r = r + noise * rng.standard_normal(len(r))
    return rays / np.linalg.norm(rays, axis=1, keepdims=True) * r[:, None], which


def test_a_new_object_behind_the_front_of_the_one_it_replaced_is_found_and_the_uncovered_wall_is_not():
    # a plate turned 30° stood 1.5 m away; it is taken away and a plate facing the camera is put
    # in its place across half of its silhouette, 5 cm behind its centre: where the old plate's front
    # stood before the new one, the reference could not see; the two surfaces cross along a line,
    # where the new plate's points lie on the old plate's surface (a band the density calls unchanged)
    rng = np.random.default_rng(3)
    old = ((0.0, 0.0, 1.5), (-np.sin(np.radians(30)), 0.0, np.cos(np.radians(30))), 0.2, 0.2)
    new = ((0.0, -0.1, 1.55), (0.0, 0.0, 1.0), 0.2, 0.1)
    reference, hit_ref = _plates([old], rng=rng)
    current, which = _plates([new], rng=rng)
    r = sdp.detect_changes(reference, current, lattice=sdp.Lattice(voxel_size=0.005),
                           coverage=sdp.Coverage(sensor_origin=(0.0, 0.0, 0.0)))
    plate = which == 0
    hidden = plate & (current[:, 0] < 0.0)  # behind the old plate by 5σ and more (the band: x ≈ 0.02–0.14 m)
    assert hidden.sum() > 2500
    assert r.appeared[hidden].mean() > 0.95  # not the new plate's band continued (none of it was found before)
    uncovered = (which == -1) & (hit_ref == 0)  # the same rays: the wall the old plate hid, nothing put there
    assert uncovered.sum() > 2500
    assert not r.appeared[uncovered].any() and r.current_not_comparable[uncovered].mean() < 0.05
