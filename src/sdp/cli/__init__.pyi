from ._actions import evaluate_actions, predict_actions, stream_actions, train_actions
from ._change import ChangePlan, FileComparison, compare_files, plan_change
from ._distance import FileDistances, distance_files
from ._files import (
    Evaluation,
    align_files,
    build_field_file,
    combine_files,
    describe_file,
    evaluate_files,
    mesh_file,
    render_file,
    watch_folder,
)
from ._main import build_parser, main, run
from ._series import SeriesRun, describe_series, series_files
