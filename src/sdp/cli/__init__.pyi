from ._commands import (
    ChangePlan,
    FileComparison,
    FileDistances,
    compare_files,
    distance_files,
    plan_change,
)
from ._main import build_parser, main, run
