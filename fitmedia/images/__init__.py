"""Image input: reading linear photographs, merging brackets, estimating noise.

Importing this package opens no files and does not import OpenCV, tifffile or
rawpy; the readers import them when called.
"""

from .io import Frame, LoadedImage, load_entry, read_frame, read_image, write_float_tiff
from .noise import estimate_noise

__all__ = ["Frame", "LoadedImage", "estimate_noise", "load_entry", "read_frame", "read_image",
           "write_float_tiff"]
