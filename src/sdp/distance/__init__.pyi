from ._distances import DISTANCE_FIELDS, Distances, distances
from ._reference import PreparedReference
