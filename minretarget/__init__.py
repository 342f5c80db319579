"""minretarget: correspondence-free online dense human motion retargeting on the CPU.

    from minretarget import Retargeter
    retargeter = Retargeter.from_weights()        # shipped default weights
    retargeter.set_target(target_points)          # (V, 3) T-pose body, metres, +Y up
    for frame in retargeter.run(source_frames):   # each (P, 3), any P >= 64, any order
        frame.vertices                            # (V, 3) the target, posed, in its own order

See minretarget.conventions for units, axes, joint order and quaternion order.
"""
from .contacts import FootLock
from .fit import FitSettings
from .pipeline import PRESETS, PipelineConfig
from .retargeter import RetargetedFrame, Retargeter, Target
from .smoothing import Smoothing
from .stages import StreamState
from .validation import InputWarning, TPoseWarning, UnitsWarning, UpAxisWarning
from .weights import load_weights, save_weights

__all__ = ["Retargeter", "RetargetedFrame", "Target", "StreamState", "PipelineConfig", "PRESETS",
           "Smoothing",
           "FootLock", "FitSettings", "load_weights",
           "save_weights", "InputWarning", "UnitsWarning", "UpAxisWarning", "TPoseWarning"]
__version__ = "0.1.0"
