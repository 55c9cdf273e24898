"""The combined model: analytic Fourier-ratio DFD plus a learned refinement CNN.

:class:`DFDModel` is what training fits, what ``models/reference.*`` holds and what the
export turns into ONNX.
"""

from .combined import MODEL_FORMAT, DFDModel, RefinedResult, context_sizes, num_features, pool_measurements, tile_features
from .family_inference import FAMILY_CLASSES, FamilyInference, family_classes
from .psf_family_code import FAMILY_CODES, append_family_maps, family_code, training_codes
from .refine import RefineNet, ResidualBlock

__all__ = ["DFDModel", "RefinedResult", "RefineNet", "ResidualBlock", "tile_features", "num_features", "context_sizes",
           "pool_measurements", "MODEL_FORMAT", "FAMILY_CODES", "family_code", "append_family_maps", "training_codes",
           "FAMILY_CLASSES", "FamilyInference", "family_classes"]
