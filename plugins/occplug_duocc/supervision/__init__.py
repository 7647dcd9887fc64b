"""DuOcc's supervision sources: :mod:`.auxiliary` (``duocc_occupied``, ``duocc_forecast``, ``duocc_detection``: the
auxiliary losses of suppl. A.4) and :mod:`.mask_decoder` (``duocc_mask``: the auxiliary mask decoder, a source
that owns its decoder)."""

from .auxiliary import DuOccDetection, DuOccForecast, DuOccOccupied
from .mask_decoder import DuOccMask

__all__ = ["DuOccDetection", "DuOccForecast", "DuOccMask", "DuOccOccupied"]
