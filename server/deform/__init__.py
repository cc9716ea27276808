"""Deformation engines. Each compiles, once per face and parameter set, to an ``Operator``: u = B·D."""

from .operator import Operator

__all__ = ["Operator"]
