from ._store import FieldStore
from ._tiles import TiledChanges, build_field_tiled, detect_changes_tiled, distances_tiled
