from ._coverage import CHANGED, NOT_COMPARABLE, UNCHANGED, footprint_covered
from ._detect import ChangeResult, detect_changes
from ._metrics import confusion_matrix, kappa, scores
from ._regions import Region
