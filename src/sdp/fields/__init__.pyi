from ._boolean import difference, intersection, union
from ._density import DensityField, threshold
from ._lattice import BLOCK, Grid
from ._spacing import auto_voxel_size
from ._surface import Mesh, extract_surface
