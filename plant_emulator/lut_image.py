"""Former home of the LUT image codec, now drivers/lut_image.py (one definition both sides import).

Only the old names stay here, for callers outside plant_emulator that still import them
(tests/test_storage_export.py); the emulator itself imports drivers.lut_image.
"""
from drivers.lut_image import Lut, LutImageError
from drivers.lut_image import decode as parse

__all__ = ["Lut", "LutImageError", "parse"]
