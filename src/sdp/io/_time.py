"""When a scan was made, as its file records it: what a series uses when no times are given.

- **LAS/LAZ**: the points' GPS time when the header says it is *adjusted standard* GPS time
  (global encoding bit 0: seconds since the GPS epoch minus 10⁹), the median over the first
  chunk of points (a scan takes minutes; the median is not moved by a few bad stamps); GPS
  *week* time (bit 0 clear) restarts every week and dates nothing, so then the header's creation
  date (a day) is used, if it has one.
- **E57**: the earliest ``acquisitionStart`` of the file's scans (GPS seconds; 0 or absent: none).
- **ROS bags** (read as one epoch with a topic, :func:`sdp.io._bag.bag_epoch`): the first message's
  ``header.stamp`` on that topic (UTC, as ROS time is; 0, unstamped: none).

GPS time runs ahead of UTC by the leap seconds inserted since 1980 (:data:`_LEAP`, IERS Bulletin
C); times are returned as UTC days since 1970-01-01, the unit of a series' dated epochs.

References
----------
.. [1] ASPRS, "LAS Specification 1.4 – R15" (2019): global encoding, GPS time.
.. [2] ASTM E2807-11, "Standard Specification for 3D Imaging Data Exchange, Version 1.0" (E57):
   ``acquisitionStart``, a GPS date-time.
.. [3] IERS Bulletin C: the leap seconds (UTC − TAI), https://hpiers.obspm.fr/eop-pc/.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ._las import las_point_count

__all__ = ["file_time", "gps_to_days"]

_GPS_EPOCH_DAYS = 3657.0  # 1980-01-06 in days since 1970-01-01
#: (GPS seconds at the UTC midnight it took effect, GPS − UTC in seconds from then on)
_LEAP = np.array([(46828801, 1), (78364802, 2), (109900803, 3), (173059204, 4), (252028805, 5), (315187206, 6),
                  (346723207, 7), (393984008, 8), (425520009, 9), (457056010, 10), (504489611, 11),
                  (551750412, 12), (599184013, 13), (820108814, 14), (914803215, 15), (1025136016, 16),
                  (1119744017, 17), (1167264018, 18)], np.float64)


def gps_to_days(seconds):
    """UTC days since 1970-01-01 of GPS seconds since the GPS epoch (1980-01-06)."""
    seconds = np.asarray(seconds, np.float64)
    leap = np.concatenate([[0.0], _LEAP[:, 1]])[np.searchsorted(_LEAP[:, 0], seconds, side="right")]
    return _GPS_EPOCH_DAYS + (seconds - leap) / 86400.0


_GPS_FORMATS = frozenset({1, 3, 4, 5, 6, 7, 8, 9, 10})  # LAS point formats with a GPS time


def _las_time(path) -> tuple[float, str] | None:
    import datetime
    import struct

    with open(path, "rb") as f:  # the header's fixed fields: laspy only when the points are needed
        head = f.read(111)
    if head[:4] != b"LASF" or len(head) < 111:
        return None
    (encoding,) = struct.unpack_from("<H", head, 6)
    day, year = struct.unpack_from("<HH", head, 90)
    if encoding & 1 and head[104] & 0x3F in _GPS_FORMATS and las_point_count(path):
        import laspy

        with laspy.open(str(path)) as f:
            gps = np.asarray(next(iter(f.chunk_iterator(100_000))).gps_time, np.float64)
        gps = gps[np.isfinite(gps)]
        if gps.size:
            return float(gps_to_days(np.median(gps) + 1e9)), "LAS GPS time"
    try:  # as laspy reads it: day 0 is the last of the year before, year 0 no date
        date = datetime.date(year, 1, 1) + datetime.timedelta(day - 1)
    except (ValueError, OverflowError):
        return None
    return float((np.datetime64(date, "D") - np.datetime64("1970-01-01", "D")).astype(np.int64)), "LAS creation date"


def _e57_time(path) -> tuple[float, str] | None:
    from ._e57 import e57_start

    start = e57_start(path)
    return None if start is None else (float(gps_to_days(start)), "E57 acquisition start")


def file_time(path, *, topic: str | None = None) -> tuple[float, str] | None:
    """(UTC days since 1970-01-01, what it was read from) of the scan in ``path``, or None
    when its format records no time (see the module docstring). A file whose header can't be
    read gives None: its reader says why when the points are read. A ROS bag with ``topic``: its
    first message's stamp, a bag that can't be read or lacks the topic raising its one-line error."""
    if not isinstance(path, (str, os.PathLike)):
        return None
    from ._cloud import is_bag

    if topic is not None and is_bag(path):
        from ._bag import bag_start

        stamp = bag_start(path, topic)
        return None if stamp is None else (stamp / 86_400e9, "ROS header.stamp")
    suffix = Path(path).suffix.lower()
    try:
        if suffix in (".las", ".laz"):
            return _las_time(path)
        if suffix == ".e57":
            return _e57_time(path)
    except Exception:  # noqa: BLE001 - any failure to read a header: no time from the file
        return None
    return None
