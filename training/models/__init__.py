"""The networks of the torch reference, one module per pipeline stage."""
from .denoise import SkeletonDenoiser
from .refine import JointRefiner
from .skin import SkinningField
from .skr import SkeletonRegressor
from .smrm import MotionDiscriminator, MotionRetargeter, MotionState

__all__ = ["SkeletonRegressor", "MotionRetargeter", "MotionDiscriminator", "MotionState",
           "SkinningField", "JointRefiner", "SkeletonDenoiser"]
