"""Capture folders (CONTRACT.md section 4) and the rigs that fill them; ``tdfd capture``."""

from .folder import CaptureFolderError, CaptureFrame, FrameMetadata, read_folder, read_frame, write_frame
from .session import capture_session, parse_pair, parse_sweep

__all__ = ["CaptureFolderError", "CaptureFrame", "FrameMetadata", "read_folder", "read_frame", "write_frame",
           "capture_session", "parse_pair", "parse_sweep"]
