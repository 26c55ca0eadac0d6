import numpy as np
import pytest

import sdp
from sdp.io import CloudFileError, read_points, write_mesh, write_points


@pytest.mark.shared_data
def test_reads_real_scans(shared_data):
    mosd = read_points(shared_data / "mosd/learn/learn1.pcd")  # organized, binary_compressed
    assert len(mosd) + mosd.n_dropped == 640 * 480 and mosd.n_dropped > 0
    assert mosd.fields["label"].dtype == np.uint32 and len(mosd.fields["label"]) == len(mosd)
    assert set(np.unique(mosd.fields["label"] // 10)) >= {0, 2}
    assert np.isfinite(mosd.xyz).all() and 0.3 < np.median(mosd.xyz[:, 2]) < 3  # Kinect range, metres
    dlut = read_points(shared_data / "dlut/A603_reference.pcd")  # ascii
    assert len(dlut) == 51_903 and dlut.n_dropped == 1_525  # organized: (0, 0, 0) marks no return
    als = read_points(shared_data / "als_toronto/TTP_2023.laz")
    assert als.xyz[:, 0].min() > 600_000 and "classification" in als.fields  # UTM metres kept exact
    tree = read_points(shared_data / "trees/tree10_2022.xyz")
    assert len(tree) > 10_000
    kinect = read_points(shared_data / "pcl_kinect/office1.pcd")  # binary
    assert len(kinect) > 100_000


@pytest.mark.shared_data
def test_real_kinect_pair_change_detection(shared_data):
    # mOSD learn0 -> learn1: fixed camera; objects (label // 10 >= 2) moved between the scenes
    ref = read_points(shared_data / "mosd/learn/learn0.pcd")
    cur = read_points(shared_data / "mosd/learn/learn1.pcd")
    r = sdp.detect_changes(ref.xyz, cur.xyz, min_region_points=20, lattice=sdp.Lattice(voxel_size="auto"))
    table = (cur.fields["label"] >= 1) & (cur.fields["label"] < 10)
    assert r.appeared[table].mean() < r.appeared[~table].mean()  # changes concentrate off the table
    assert r.appeared_regions and r.timings["detect"] >= 0


def test_round_trips(tmp_path, rng):
    xyz = rng.random((500, 3)) * 100 + [630_000.0, 4_830_000.0, 70.0]
    change = rng.random(500) < 0.3
    for ext in ("ply", "laz", "las", "npz"):
        path = write_points(tmp_path / f"c.{ext}", xyz, {"change": change.astype(np.uint8)})
        back = read_points(path)
        tol = 1e-3 if ext in ("las", "laz") else 0  # LAS stores millimetre integers
        np.testing.assert_allclose(back.xyz, xyz, atol=tol, rtol=0)
        np.testing.assert_array_equal(back.fields["change"].astype(bool), change)
    np.savetxt(tmp_path / "c.xyz", xyz, fmt="%.6f")
    np.testing.assert_allclose(read_points(tmp_path / "c.xyz").xyz, xyz, atol=1e-6)
    with open(tmp_path / "c.csv", "w") as fh:
        fh.write("x,y,z,intensity\n")
        np.savetxt(fh, np.c_[xyz, np.arange(500)], delimiter=",", fmt="%.6f")
    c = read_points(tmp_path / "c.csv")
    np.testing.assert_allclose(c.fields["intensity"], np.arange(500))


def test_las_output_keeps_input_dimensions(tmp_path, rng, monkeypatch):
    import laspy

    header = laspy.LasHeader(point_format=3, version="1.4")
    header.scales, header.offsets = [0.01] * 3, [600_000.0, 4_800_000.0, 0.0]
    las = laspy.LasData(header)
    xyz = rng.random((200, 3)) * 50 + [600_000.0, 4_800_000.0, 10.0]
    las.x, las.y, las.z = xyz.T
    las.classification = rng.integers(1, 7, 200).astype(np.uint8)
    las.write(str(tmp_path / "in.las"))
    cloud = read_points(tmp_path / "in.las")
    write_points(tmp_path / "out.las", cloud.xyz, {"change": np.ones(200, np.uint8)}, like=cloud)
    back = read_points(tmp_path / "out.las")
    np.testing.assert_array_equal(back.fields["classification"], las.classification)
    for other in ("out.ply", "out.npz"):  # and written as another format, as fields
        write_points(tmp_path / other, cloud.xyz, {"change": np.ones(200, np.uint8)}, like=cloud)
        np.testing.assert_array_equal(read_points(tmp_path / other).fields["classification"], las.classification)
    import sdp.io._las

    monkeypatch.setattr(sdp.io._las, "LAS_CHUNK", 64)  # 4 chunks, as a large file is read (with a progress bar)
    chunked = read_points(tmp_path / "out.las")
    np.testing.assert_array_equal(chunked.xyz, back.xyz)
    np.testing.assert_array_equal(chunked.fields["change"], back.fields["change"])
    np.testing.assert_array_equal(back.fields["change"], 1)
    from sdp.io._las import las_point_count

    six = laspy.LasData(laspy.LasHeader(point_format=6, version="1.4"))  # its legacy count is 0: the 64-bit one
    six.x, six.y, six.z = xyz[:150].T
    six.write(str(tmp_path / "six.laz"))
    (tmp_path / "not.las").write_bytes(b"PLY and more")
    assert [las_point_count(tmp_path / f) for f in ("in.las", "six.laz", "not.las")] == [200, 150, None]
    lean = read_points(tmp_path / "out.las", fields=False)  # the coordinates alone, in chunks too
    assert lean.fields == {} and lean.las is None
    np.testing.assert_array_equal(lean.xyz, back.xyz)
    # moved (an aligned output): its records at the new coordinates, the offset moved as far as needed;
    # the cloud read keeps its own records (no output's dimension added to them)
    for shift in ([0.0, 0.0, -0.5], [3e7, 0.0, 0.0]):  # 30,000 km: beyond 2**31 centimetres of the offset
        write_points(tmp_path / "moved.laz", cloud.xyz + shift, {"change": np.ones(200, np.uint8)}, like=cloud)
        moved = read_points(tmp_path / "moved.laz")
        assert np.abs(moved.xyz - (cloud.xyz + shift)).max() <= 0.005 + 1e-6
        np.testing.assert_array_equal(moved.fields["classification"], las.classification)
    assert "change" not in cloud.las.point_format.dimension_names


@pytest.mark.parametrize("packed", ["rgb", "rgba"])
def test_a_pcds_packed_colour_is_written_as_colour(tmp_path, rng, packed):
    """PCL packs colour into one field (``rgb``: a float32's bytes 0x00RRGGBB; ``rgba``: a uint32
    0xAARRGGBB): read as red, green, blue, it is LAS's and PLY's colour."""
    import laspy
    from pypcd4 import Encoding, PointCloud

    xyz = rng.random((300, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, (300, 3)).astype(np.uint32)
    bits = (np.uint32(200) << 24 if packed == "rgba" else 0) | (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]
    kind = np.float32 if packed == "rgb" else np.uint32
    pc = PointCloud.from_points([xyz[:, 0], xyz[:, 1], xyz[:, 2], bits.view(kind)], ("x", "y", "z", packed),
                                (np.float32, np.float32, np.float32, kind))
    pc.save(tmp_path / "c.pcd", encoding=Encoding.BINARY)
    cloud = read_points(tmp_path / "c.pcd")
    assert packed not in cloud.fields
    for c, name in enumerate(("red", "green", "blue")):
        np.testing.assert_array_equal(cloud.fields[name], rgb[:, c])
    write_points(tmp_path / "c.las", cloud)
    las = laspy.read(str(tmp_path / "c.las"))
    np.testing.assert_array_equal(las.blue, rgb[:, 2].astype(np.uint16) * 257)


def test_a_text_files_colour_columns_are_written_as_colour(tmp_path, rng):
    # text columns are read as floats: whole numbers within 8 bits are colour all the same
    import laspy

    rgb = rng.integers(0, 256, (200, 3))
    np.savetxt(tmp_path / "c.txt", np.c_[rng.random((200, 3)), rgb, rgb[:, 0] + 0.5], fmt="%.6f",
               header="x y z red green blue intensity", comments="//")
    write_points(tmp_path / "c.las", read_points(tmp_path / "c.txt"))
    las = laspy.read(str(tmp_path / "c.las"))
    assert las.header.point_format.id == 2
    np.testing.assert_array_equal(las.green, rgb[:, 1].astype(np.uint16) * 257)
    np.testing.assert_array_equal(las.input_intensity, rgb[:, 0] + 0.5)  # not whole: kept as it is


def test_other_inputs_keep_their_fields_and_las_says_only_what_they_hold(tmp_path, rng):
    import laspy

    xyz = rng.random((300, 3))
    colour = {c: rng.integers(0, 256, 300).astype(np.uint8) for c in ("red", "green", "blue")}
    fields = {**colour, "intensity": rng.random(300).astype(np.float32), "label": rng.integers(0, 9, 300)}
    write_points(tmp_path / "in.ply", xyz, fields)
    cloud = read_points(tmp_path / "in.ply")
    write_points(tmp_path / "out.las", cloud.xyz, {"change": np.ones(300, np.uint8)}, like=cloud)
    write_points(tmp_path / "out.ply", cloud.xyz, {"change": np.ones(300, np.uint8)}, like=cloud)
    las = laspy.read(str(tmp_path / "out.las"))
    assert las.header.point_format.id == 2  # LAS's own colour, spread over 16 bits
    np.testing.assert_array_equal(las.red, colour["red"].astype(np.uint16) * 257)
    np.testing.assert_array_equal(las.intensity, np.round(fields["intensity"] * 65535).astype(np.uint16))
    np.testing.assert_array_equal(las.label, fields["label"])
    back = read_points(tmp_path / "out.ply")
    assert sorted(back.fields) == sorted([*fields, "change"])
    np.testing.assert_array_equal(back.fields["green"], colour["green"])
    write_points(tmp_path / "plain.las", xyz, {"change": np.ones(300, np.uint8)})
    plain = laspy.read(str(tmp_path / "plain.las"))  # no colour given: none claimed (zeros read as black)
    assert plain.header.point_format.id == 0 and "red" not in plain.point_format.dimension_names
    write_points(tmp_path / "again.ply", cloud)  # a cloud as read, written again with its fields
    assert sorted(read_points(tmp_path / "again.ply").fields) == sorted(fields)


def test_mesh_writers(tmp_path, rng):
    f = sdp.DensityField.from_points(rng.normal(0, 0.1, (3000, 3)), voxel_size=0.02)
    mesh = f.mesh()
    for ext in ("ply", "obj", "stl"):
        p = write_mesh(tmp_path / f"m.{ext}", mesh)
        assert p.stat().st_size > 1000
    assert (tmp_path / "m.stl").stat().st_size == 84 + 50 * len(mesh.faces)
    # far from the origin (UTM): OBJ keeps every digit; STL's 32-bit floats would move the vertices by more
    # than the mesh's detail, so it is refused and nothing is written
    far = sdp.Mesh(mesh.vertices + [634_000.0, 4_831_000.0, 80.0], mesh.faces)
    write_mesh(tmp_path / "far.obj", far)
    back = np.array([line.split()[1:] for line in open(tmp_path / "far.obj") if line.startswith("v ")], float)
    np.testing.assert_allclose(back, far.vertices, rtol=0, atol=1e-9)
    with pytest.raises(sdp.CloudFileError, match="STL holds 32-bit floats"):
        write_mesh(tmp_path / "far.stl", far)
    assert not (tmp_path / "far.stl").exists()


@pytest.mark.parametrize("name, content, match", [
    ("a.foo", b"1 2 3\n", "unknown point-cloud format"),
    ("a.ply", b"ply\nformat ascii 1.0\nelement vertex 10\n", "can't read"),
    ("a.pcd", b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\n", "can't read"),
    ("a.xyz", b"1 2\n3 4\n", "at least 3 columns"),
    ("a.xyz", b"", "empty"),
    ("a.las", b"LASF" + b"\0" * 50, "can't read"),
    ("a.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n",
     "no x, y, z"),
])
def test_bad_files_raise_one_clear_error(tmp_path, name, content, match):
    p = tmp_path / name
    p.write_bytes(content)
    with pytest.raises(CloudFileError, match=match) as err:
        read_points(p)
    assert name in str(err.value)
    with pytest.raises(CloudFileError, match="no such file"):
        read_points(tmp_path / "missing.ply")


def test_outputs_never_overwrite_inputs(tmp_path, rng):
    p = write_points(tmp_path / "in.ply", rng.random((10, 3)))
    before = p.read_bytes()
    with pytest.raises(sdp.SDPError, match="overwrite an input"):
        write_points(p, rng.random((10, 3)), inputs=(p,))
    assert p.read_bytes() == before
    assert sorted(x.name for x in tmp_path.iterdir()) == ["in.ply"]


def test_missing_xyz_and_truncated_files(tmp_path, rng):
    np.savez(tmp_path / "a.npz", points=rng.random((5, 3)))
    with pytest.raises(CloudFileError, match="a.npz: NPZ needs an array 'xyz'"):
        read_points(tmp_path / "a.npz")
    write_points(tmp_path / "whole.laz", rng.random((5000, 3)) * 100)
    data = (tmp_path / "whole.laz").read_bytes()
    (tmp_path / "cut.laz").write_bytes(data[: len(data) // 2])  # a download that stopped halfway
    with pytest.raises(CloudFileError, match="cut.laz"):
        read_points(tmp_path / "cut.laz")


def test_io_modules_import_one_way():
    """sdp.io's private modules import no sibling's underscore names, and never in a cycle."""
    import ast
    from pathlib import Path

    import sdp.io

    graph = {}
    for path in Path(sdp.io.__file__).parent.glob("*.py"):
        graph[path.stem] = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level == 1:
                assert not [a.name for a in node.names if a.name.startswith("_")], (path.name, node.module)
                graph[path.stem].add(node.module)
    done: set[str] = set()

    def visit(name, stack):
        assert name not in stack, f"import cycle {' -> '.join(stack + [name])}"
        if name not in done:
            for dep in graph.get(name, ()):
                visit(dep, stack + [name])
            done.add(name)

    for name in graph:
        visit(name, [])
    assert {"_cloud", "_read", "_output", "_source", "_las", "_ply"} <= done


@pytest.mark.parametrize("point_format", [3, 7])
def test_xyz_alone_from_a_layered_laz_equal_the_whole_read(tmp_path, rng, point_format, monkeypatch):
    """Read without its other dimensions (a series' epochs), a LAZ of point format 6-10 skips their
    layers: the same coordinates as a whole read, which keeps its colours and intensities."""
    import laspy

    asked = []
    real_open = laspy.open

    def spy(*args, **kwargs):
        asked.append(kwargs.get("decompression_selection"))
        return real_open(*args, **kwargs)

    monkeypatch.setattr(laspy, "open", spy)

    header = laspy.LasHeader(point_format=point_format, version="1.4")
    header.scales, header.offsets = [0.001] * 3, [600_000.0, 4_800_000.0, 0.0]
    las = laspy.LasData(header)
    xyz = rng.random((3000, 3)) * 50 + [600_000.0, 4_800_000.0, 10.0]
    las.x, las.y, las.z = xyz.T
    las.intensity = rng.integers(1, 60_000, 3000).astype(np.uint16)
    las.red = rng.integers(1, 60_000, 3000).astype(np.uint16)
    las.write(str(tmp_path / "in.laz"))
    whole, bare = read_points(tmp_path / "in.laz"), read_points(tmp_path / "in.laz", fields=False)
    np.testing.assert_array_equal(bare.xyz, whole.xyz)
    np.testing.assert_array_equal(whole.fields["intensity"], las.intensity)
    np.testing.assert_array_equal(whole.fields["red"], las.red)
    assert bare.fields == {} and np.abs(whole.xyz - xyz).max() < 1e-3
    # the coordinates' read asked lazrs for their layers alone: in a layered format (6-10) the
    # others are left undecoded (only their first point's value comes back), format 3 decodes whole
    skipped = laspy.read(str(tmp_path / "in.laz"), decompression_selection=asked[-1])
    layered = point_format >= 6
    assert np.array_equal(skipped.intensity, las.intensity) != layered
    assert np.array_equal(skipped.red, las.red) != layered
    np.testing.assert_array_equal(skipped.X, las.X)


def test_a_las_files_time_read_from_its_header_agrees_with_laspy(tmp_path):
    """file_time reads the LAS header's fixed fields itself (laspy only for the points' GPS time):
    the creation date laspy reads (year 0: none), or the GPS time where the encoding says
    standard and the point format has one; formats 0, 3 and 6, both encodings."""
    import datetime as dt

    import laspy

    from sdp.io._time import file_time, gps_to_days

    checked = 0
    for fmt in (0, 3, 6):
        for standard in (False, True):
            for date in (dt.date(2023, 3, 4), dt.date(2020, 12, 31), None):
                header = laspy.LasHeader(point_format=fmt, version="1.4" if fmt >= 6 else "1.2")
                header.global_encoding.value = (1 if standard else 0) | (16 if fmt >= 6 else 0)
                las = laspy.LasData(header)
                las.x = las.y = las.z = np.arange(5.0)
                if "gps_time" in las.point_format.dimension_names:
                    las.gps_time = 3e8 + np.arange(5.0)
                path = tmp_path / f"f{fmt}{int(standard)}{date}.laz"
                las.header.creation_date = date or dt.date(2000, 1, 1)
                las.write(path)
                if date is None:  # year 0: laspy reads no date
                    raw = bytearray(path.read_bytes())
                    raw[90:94] = bytes(4)
                    path.write_bytes(raw)
                with laspy.open(str(path)) as f:
                    read = f.header
                if standard and fmt != 0:
                    want = (float(gps_to_days(3e8 + 2.0 + 1e9)), "LAS GPS time")
                elif read.creation_date is None:
                    want = None
                else:
                    want = ((read.creation_date - dt.date(1970, 1, 1)).days, "LAS creation date")
                assert file_time(path) == want, (fmt, standard, date)
                checked += 1
    assert checked == 18


def test_text_columns_as_their_header_names_them(tmp_path, rng):
    """The header's x, y, z wherever they stand; a PTS file's point count; a comment's comma."""
    xyz = np.round(rng.random((50, 3)) * 10, 4)
    ids = np.arange(50.0)

    def write(name, text):
        (tmp_path / name).write_text(text)
        return read_points(tmp_path / name)

    rows = "\n".join(",".join(f"{v:.4f}" for v in r) for r in np.c_[xyz[:, 1], xyz[:, 0], xyz[:, 2]])
    np.testing.assert_array_equal(write("yxz.csv", "y,x,z\n" + rows + "\n").xyz, xyz)
    rows = "\n".join(",".join(f"{v:.4f}" for v in r) for r in np.c_[ids, xyz])
    c = write("id.csv", "id,x,y,z\n" + rows + "\n")
    np.testing.assert_array_equal(c.xyz, xyz)
    np.testing.assert_array_equal(c.fields["id"], ids)
    rows = "\n".join(";".join(f"{v:.4f}" for v in r) for r in np.c_[xyz, ids])
    c = write("cc.txt", "//X;Y;Z;Intensity\n" + rows + "\n")  # CloudCompare's header, semicolons
    np.testing.assert_array_equal(c.xyz, xyz)
    np.testing.assert_array_equal(c.fields["intensity"], ids)
    rows = "\n".join(" ".join(f"{v:.4f}" for v in r) + " 100 1 2 3" for r in xyz)
    c = write("scan.pts", f"{len(xyz)}\n{rows}\n")
    np.testing.assert_array_equal(c.xyz, xyz)
    assert sorted(c.fields) == ["blue", "green", "intensity", "red"] and c.fields["blue"][0] == 3
    rows = "\n".join(" ".join(f"{v:.4f}" for v in r) for r in xyz)
    np.testing.assert_array_equal(write("c.xyz", "# exported by a scanner, v2\n" + rows + "\n").xyz, xyz)


def test_an_npz_cloud_with_metadata_reads(tmp_path, rng):
    # a 0-d array beside the points (an epoch's year) is metadata, not a per-point field
    np.savez(tmp_path / "c.npz", xyz=rng.random((50, 3)), change=np.zeros(50, np.uint8), epoch=np.array(2023))
    cloud = read_points(tmp_path / "c.npz")
    assert len(cloud.xyz) == 50 and set(cloud.fields) == {"change"}


def _pcl_pcd(path, n, fields, columns, *, height=1, data="binary_compressed"):
    """A PCD file written as PCL writes it: ``fields`` (name, type, size, count); ``columns`` one
    (n, count) array per field; binary_compressed stores each field's column whole, a point's
    values together (``pcl::PCDWriter::writeBinaryCompressed``)."""
    import struct

    import lzf

    head = (f"VERSION 0.7\nFIELDS {' '.join(f[0] for f in fields)}\nSIZE {' '.join(str(f[2]) for f in fields)}\n"
            f"TYPE {' '.join(f[1] for f in fields)}\nCOUNT {' '.join(str(f[3]) for f in fields)}\n"
            f"WIDTH {n // height}\nHEIGHT {height}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n").encode()
    if data == "binary_compressed":
        body = b"".join(np.ascontiguousarray(c).tobytes() for c in columns)
        packed = lzf.compress(body, 2 * len(body) + 64)
        path.write_bytes(head + struct.pack("<II", len(packed), len(body)) + packed)
    else:  # binary: point by point
        path.write_bytes(head + np.hstack([np.ascontiguousarray(c).view(np.uint8).reshape(n, -1)
                                           for c in columns]).tobytes())


def test_a_compressed_pcd_field_of_several_values_reads_as_pcl_wrote_it(tmp_path, rng):
    # PCL stores a field of COUNT c as one column, each point's c values together; pypcd4 reads
    # it as c columns one after the other, which scrambled the values across points
    n = 6
    xyz = rng.random((n, 3)).astype(np.float32)
    xyz[3] = np.nan  # organized: a missing return, dropped; the fields' rows must stay with theirs
    pair = (np.arange(n)[:, None] * 10 + np.arange(2)).astype(np.float32)
    hist = (np.arange(n)[:, None] * 100 + np.arange(33)).astype(np.uint16)  # a 33-bin descriptor
    fields = [("x", "F", 4, 1), ("y", "F", 4, 1), ("z", "F", 4, 1), ("v", "F", 4, 2), ("h", "U", 2, 33)]
    for data in ("binary_compressed", "binary"):
        path = tmp_path / f"{data}.pcd"
        _pcl_pcd(path, n, fields, [xyz[:, :1], xyz[:, 1:2], xyz[:, 2:], pair, hist], height=2, data=data)
        c = read_points(path)
        kept = np.arange(n) != 3
        assert c.n_dropped == 1
        np.testing.assert_array_equal(c.xyz, xyz[kept])
        for k in range(2):
            np.testing.assert_array_equal(c.fields[f"v__{k:04d}"], pair[kept, k], err_msg=data)
        for k in (0, 1, 32):
            np.testing.assert_array_equal(c.fields[f"h__{k:04d}"], hist[kept, k], err_msg=data)


def test_pcl_padding_fields_are_left_out(tmp_path, rng):
    # PCL pads records with fields named "_" (FIELDS x y z _ rgb _); pypcd4 names each after a
    # random string: kept, they were a dozen junk dimensions in every output, named anew each run
    n = 20
    xyz = rng.random((n, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, (n, 3)).astype(np.uint32)
    packed = ((rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]).view(np.float32)[:, None]
    fields = [("x", "F", 4, 1), ("y", "F", 4, 1), ("z", "F", 4, 1), ("_", "U", 1, 4), ("rgb", "F", 4, 1),
              ("_", "U", 1, 12)]
    pad = [np.full((n, 4), 7, np.uint8), np.full((n, 12), 9, np.uint8)]
    for data in ("binary", "binary_compressed"):
        path = tmp_path / f"{data}.pcd"
        _pcl_pcd(path, n, fields, [xyz[:, :1], xyz[:, 1:2], xyz[:, 2:], pad[0], packed, pad[1]], data=data)
        c = read_points(path)
        np.testing.assert_array_equal(c.xyz, xyz)
        assert sorted(c.fields) == ["blue", "green", "red"], data
        for k, name in enumerate(("red", "green", "blue")):
            np.testing.assert_array_equal(c.fields[name], rgb[:, k])


def test_a_text_files_byte_order_mark_is_skipped(tmp_path):
    # Excel's "CSV UTF-8" starts with a byte-order mark: read as text, it made the first point a
    # header (the point lost) or the first column's name "\ufeffid"
    rows = [[1.5, 2.5, 3.5], [4.5, 5.5, 6.5], [7.5, 8.5, 9.5]]
    body = "\n".join(",".join(map(str, r)) for r in rows) + "\n"
    ids = "id,x,y,z\n" + "".join(f"{i}," + ",".join(map(str, r)) + "\n" for i, r in enumerate(rows))
    for name, text in (("plain.csv", body), ("ids.csv", ids), ("c.txt", body.replace(",", " "))):
        (tmp_path / name).write_text(text, encoding="utf-8-sig")
        c = read_points(tmp_path / name)
        assert c.xyz.tolist() == rows, name
        assert sorted(c.fields) == (["id"] if name == "ids.csv" else []), name


def test_a_ply_vertex_list_property_is_left_out_with_a_notice(tmp_path, rng, capfd):
    # a list per vertex (the views a photogrammetry tool saw each point in) is no field: kept, every
    # output failed after the whole computation ("field 'views' must hold one real number per point")
    from plyfile import PlyData, PlyElement

    from sdp.cli._main import main
    from sdp.io._cloud import ReadNotice

    xyz = rng.random((40, 3)).astype(np.float32)
    v = np.empty(40, [("x", "f4"), ("y", "f4"), ("z", "f4"), ("views", "O"), ("label", "u1")])
    v["x"], v["y"], v["z"] = xyz.T
    v["views"] = [np.arange(i % 3, dtype="i4") for i in range(40)]
    v["label"] = np.arange(40) % 5
    for text in (False, True):
        path = tmp_path / f"{'ascii' if text else 'binary'}.ply"
        element = PlyElement.describe(v, "vertex", val_types={"views": "i4"}, len_types={"views": "u1"})
        PlyData([element], text=text).write(str(path))
        with pytest.warns(ReadNotice, match=r"list property 'views' left out"):
            c = read_points(path)
        np.testing.assert_array_equal(c.xyz, xyz)
        assert list(c.fields) == ["label"]
        np.testing.assert_array_equal(c.fields["label"], v["label"])
        write_points(tmp_path / "out.ply", c)  # written as any other cloud
        assert list(read_points(tmp_path / "out.ply").fields) == ["label"]
    assert main(["info", str(path)]) == 0  # the command line says it in one line
    err = capfd.readouterr().err
    assert err == f"sdp: {path}: vertex list property 'views' left out (a list per point, which no field holds; " \
                  "Open3D and CloudCompare leave them out too)\n"
    assert main(["info", str(path), "-q"]) == 0 and capfd.readouterr().err == ""


def test_withheld_and_noise_las_points_are_compared_with_a_notice(tmp_path, rng, capfd):
    # kept as PDAL and CloudCompare keep them (every output keeps its rows), but said: a change
    # found among them may be noise, not the surface
    import warnings

    import laspy

    from sdp.cli._main import main
    from sdp.io._cloud import ReadNotice

    def las(name, point_format, classification, withheld):
        data = laspy.LasData(laspy.LasHeader(point_format=point_format, version="1.4"))
        data.x, data.y, data.z = rng.random((3, 50)) * 10
        data.classification, data.withheld = classification, withheld
        data.write(str(tmp_path / name))
        return tmp_path / name

    classes = np.full(50, 2, np.uint8)
    classes[:3], classes[3:5] = 7, 18
    flags = (np.arange(50) >= 45).astype(np.uint8)
    for point_format, told in ((6, "5 points flagged withheld and 5 classified noise (class 7 or 18)"),
                               (0, "5 points flagged withheld and 3 classified noise (class 7)")):  # 18: 6-10 only
        path = las(f"f{point_format}.las", point_format, classes, flags)
        with pytest.warns(ReadNotice) as seen:
            c = read_points(path)
        assert len(seen) == 1 and str(seen[0].message) == (
            f"{path}: {told}, compared as any other point; to leave them out, filter the file first (e.g. las2las "
            f"-drop_withheld -drop_class {'7 18' if point_format == 6 else '7'})")
        assert len(c) == 50 and np.array_equal(c.fields["classification"], classes)
    path = las("noise.las", 6, np.where(np.arange(50) == 0, 7, 2).astype(np.uint8), np.zeros(50, np.uint8))
    assert main(["info", str(path)]) == 0
    assert capfd.readouterr().err == (f"sdp: {path}: 1 point classified noise (class 7 or 18), compared as any other "
                                      "point; to leave them out, filter the file first (e.g. las2las "
                                      "-drop_class 7 18)\n")
    with warnings.catch_warnings():  # a file without either: no word
        warnings.simplefilter("error")
        read_points(las("clean.las", 6, np.full(50, 2, np.uint8), np.zeros(50, np.uint8)))
