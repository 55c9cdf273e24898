"""Analytic depth from defocus: tile spectra, the Fourier-ratio estimator, calibration."""

from .fourier_ratio import DFDResult, FourierRatioDFD, fourier_ratio_dfd, validate_pair, whole_image_dfd
from .register import register_sensor_pair
from .spectra import TileSpectra, fft_tile_power, periodic_hann

__all__ = ["DFDResult", "FourierRatioDFD", "fourier_ratio_dfd", "validate_pair", "whole_image_dfd",
           "TileSpectra", "fft_tile_power", "periodic_hann", "register_sensor_pair"]
