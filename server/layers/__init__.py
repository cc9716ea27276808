"""Face layers: several inputs mixed into one ``FaceState`` per frame (issue 18).

``model``: the types (``Role``, ``Contribution``, ``Envelope``, ``GazeTarget``, ``Geometry``, the
``Layer`` protocol, ``REGIONS``); ``mix``: the rules (``combine``, ``mix``) and a session's
``Mixer``; the layers: ``overlay`` (``ExpressionLayer``, ``TrackLayer``), ``idle``
(``IdleLayer``), ``gaze`` (``GazeLayer``), ``head`` (``HeadGesture``, ``HeadPose``).
"""

from __future__ import annotations

from .gaze import GazeLayer, parse_gaze
from .head import HeadGesture, HeadPose
from .idle import IdleLayer
from .mix import Mixer, combine, mix, mix_states
from .model import (
    EMPTY,
    REGIONS,
    Contribution,
    Envelope,
    GazeTarget,
    Geometry,
    Layer,
    Role,
    region_mask,
)
from .overlay import ExpressionLayer, TrackLayer

__all__ = [
    "EMPTY",
    "REGIONS",
    "Contribution",
    "Envelope",
    "ExpressionLayer",
    "GazeLayer",
    "GazeTarget",
    "Geometry",
    "HeadGesture",
    "HeadPose",
    "IdleLayer",
    "Layer",
    "Mixer",
    "Role",
    "TrackLayer",
    "combine",
    "mix",
    "mix_states",
    "parse_gaze",
    "region_mask",
]
