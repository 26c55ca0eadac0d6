from ._store import FieldStore
from ._tiles import build_field_tiled, detect_changes_tiled, distances_tiled
