"""MPEG-4 face animation: FAP/FP tables, FAPU, high-level FAPs and the FAP rig of a face."""

from .fapu import AU, FAPU_DEFINITIONS, fapu_mm, measure_fapu
from .highlevel import (
    EXPRESSION_NAMES,
    EXPRESSIONS,
    VISEME_NAMES,
    VISEMES,
    expand,
    expression_faps,
    viseme_faps,
)
from .rig import FapRig, fap_controls
from .tables import FAP_GROUPS, FAP_NUMBER, FAPS, FEATURE_POINTS, FP_FAPS, Fap, fap

__all__ = [
    "AU",
    "EXPRESSIONS",
    "EXPRESSION_NAMES",
    "FAPS",
    "FAPU_DEFINITIONS",
    "FAP_GROUPS",
    "FAP_NUMBER",
    "FEATURE_POINTS",
    "FP_FAPS",
    "VISEMES",
    "VISEME_NAMES",
    "Fap",
    "FapRig",
    "expand",
    "expression_faps",
    "fap",
    "fap_controls",
    "fapu_mm",
    "measure_fapu",
    "viseme_faps",
]
