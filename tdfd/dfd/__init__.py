"""Analytic depth from defocus: tile spectra, the Fourier-ratio estimator, calibration, and the
likelihood stage that refines a model's map by each tile's cross-residual fit."""

from .fourier_ratio import DFDResult, FourierRatioDFD, fourier_ratio_dfd, validate_pair, whole_image_dfd
from .inverse_variance import LikelihoodScales
from .likelihood_stage import LikelihoodStage, LikelihoodStageResult, likelihood_stage
from .psf_hypotheses import PsfHypothesis, psf_hypotheses
from .register import register_sensor_pair
from .spectra import TileSpectra, fft_tile_power, periodic_hann

__all__ = ["DFDResult", "FourierRatioDFD", "fourier_ratio_dfd", "validate_pair", "whole_image_dfd",
           "TileSpectra", "fft_tile_power", "periodic_hann", "register_sensor_pair", "LikelihoodStage",
           "LikelihoodStageResult", "likelihood_stage", "LikelihoodScales", "PsfHypothesis", "psf_hypotheses"]
