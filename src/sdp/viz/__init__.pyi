from ._render import render_changes, render_changes_html, render_distances, render_field
from ._report import change_report, distance_report
from ._report import series_report
