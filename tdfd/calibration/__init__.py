"""Camera calibration from a capture folder: sweeps, pairs, breathing; ``tdfd calibrate``."""

from .fit import CalibrationError, CalibrationResult, calibrate_known_distance, calibrate_self
from .measure import in_focus_power_from_pair, measure_pair

__all__ = ["CalibrationError", "CalibrationResult", "calibrate_known_distance", "calibrate_self",
           "in_focus_power_from_pair", "measure_pair"]
