"""Motion cycles: one clean closed loop from several imprecise performed loops (``extract``), a
streaming extractor fed sample by sample (``CycleExtractor``), layering onto a playing master loop
(``layer_onto``) and cycle editing (``cycles.edit``)."""

from cycles.base import CycleExtractor
from cycles.cycle import Cycle, layer_onto
from cycles.extraction import ExtractOptions, extract

__all__ = ["Cycle", "CycleExtractor", "ExtractOptions", "extract", "layer_onto"]
