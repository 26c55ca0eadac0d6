from ._archive import SeriesArchiveError, is_series, open_series
from ._compute import SERIES_FIELDS, parse_times, series
from ._kalman import process_noise, smooth
from ._objects import find_objects, onsets
