"""The examples that end each ``sdp`` command's ``--help``, kept as written (the columns align)."""

MEMORY_HELP = ("memory of the whole job, the process and Dask workers included (e.g. 2GB; default $SDP_MEMORY_LIMIT "
               "or 4GiB)")
REPORT_HELP = ("one self-contained HTML page: summary, parameters and why, maps, histogram (changes: regions with "
               "thumbnails and a 3-D view; needs the plots extra; in memory only)")

CHANGE = """  sdp change ref.pcd cur.pcd -o changes.ply                  appeared points of cur.pcd
  sdp change ref.laz cur.laz -o out.laz --report report.html  one page to read or send
  sdp change ref.laz cur.laz -o out.laz --both --voxel-size 0.1
  sdp change ref.ply cur.ply -o out.ply --grid-size 80        the paper's parameters
  sdp change ref.pcd cur.pcd -o out.ply --json                summary as JSON
  sdp change ref.pcd rescan.pcd -o out.ply --align density    register the rescan first
  sdp change ref.ply cur.ply -o out.ply --sensor-origin 0,0,0   the sensor stood there (PCD: read from the file)
  sdp change a.laz b.laz -o out.laz --voxel-size 0.1 --memory-limit 2GB   any size: tiles on Dask
  sdp change a.laz b.laz -o out.laz --voxel-size 0.1 --scheduler tcp://host:8786   on a cluster
"""

DISTANCE = """  sdp distance 2015.laz 2023.laz -o d.laz --png d.png    how much, and is it significant
  sdp distance 2015.laz 2023.laz -o d.laz --report d.html one page: summary, map, histogram, 3-D view
  sdp distance a.laz b.laz -o d.laz --align density --align-class 2 --fix-horizontal
                                                              register on the ground first
  sdp distance a.ply b.ply -o d.npz --core-points grid.ply --registration-error 0.02
  sdp distance a.ply b.ply -o d.ply --projection-scale 0.5 --normal-scale 1   M3C2's d and D, as diameters
"""

SERIES = """  sdp series day*.laz -o slope.zarr --times 2024-05-01,2024-05-02,2024-05-03
  sdp series day4.laz --append -o slope.zarr --times 2024-05-04   only the new epoch is measured
  sdp series e*.laz -o s.zarr --core-points core.laz --registration-error 0.005 --report s.html
  sdp series e*.laz -o s.zarr --epoch-output 3:distances3.laz --points-output p.csv --points 10,20
  sdp series big*.laz -o big.zarr --tiled --max-distance 0.5    epochs beyond memory: tiles on Dask
  sdp info s.zarr                                              epochs, objects, every parameter
"""

BUILD = """  sdp build scan.pcd -o scan.sdpf --voxel-size 0.01
  sdp build city.laz -o city.zarr --voxel-size 0.1        any size: tiles on Dask, on disk
"""
MESH = """  sdp mesh scan.sdpf -o surface.ply
  sdp mesh scan.pcd -o surface.obj --level 0
  sdp mesh city.zarr -o city.ply                             a field store (sdp build -o X.zarr), tile by tile
"""
DEMO = """  sdp demo -o demo-output
"""
BOOL = """  sdp bool difference cur.sdpf ref.sdpf -o new.sdpf          what cur has and ref lacks
  sdp bool union a.pcd b.pcd -o both.ply                      surface of the union (auto voxel from both)
  sdp bool intersection a.sdpf b.ply -o common.stl            b is built on a's lattice
  sdp bool union a.zarr b.zarr -o u.zarr                      two field stores, tile by tile
"""
ALIGN = """  sdp align reference.pcd rescan.pcd -o T.txt               density-based, coarse to fine
  sdp align reference.pcd rescan.pcd -o T.txt --method gicp  small_gicp (extra: align)
  sdp change reference.pcd rescan.pcd -o out.ply --align density   align, then compare
"""
WATCH = """  sdp watch empty_room.pcd frames/                         each frame against a sliding window
  sdp watch first.pcd frames/ --align gicp                  a hand-held camera: register each frame first
  sdp watch first.ply frames/ --sensor-origin 0,0,0         the sensor's rays (a PCD's VIEWPOINT is read by itself)
  sdp watch map.sdpf frames/ --update none --json           against a fixed reference field
"""
ACTION = """  sdp action eval ../shared/data/msr_action3d --json          the cross-subject protocol
  sdp action train ../shared/data/msr_action3d -o model.npz --subjects 1,3,5,7,9
  sdp action predict model.npz a05_s02_e01_sdepth.mat
  sdp action predict model.npz --stream frames/               a folder of .npy depth frames, as they come
"""
EVAL = """  sdp eval changes.ply truth.ply                              field 'change' of both
  sdp eval demo-output/current_labelled.ply demo-output/current_labelled.ply --truth-field truth
  sdp eval changes.las scan_labels.las --truth-field classification --json
"""
RENDER = """  sdp render changes.ply --png changes.png                    'change' field: changed in vermillion
  sdp render changes.laz --html changes.html --field change   interactive, opens in a browser
  sdp render scan.sdpf --png slices.png                       three slices of F = h - G
"""
