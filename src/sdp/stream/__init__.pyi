from ._watch import FrameChange, watch
