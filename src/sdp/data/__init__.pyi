from ._demo import run_demo
from ._scene import office_scene, scan
from ._slope import SlopeSeries, slope_series
