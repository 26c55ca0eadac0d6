from ._distances import DISTANCE_FIELDS, Distances, distances
