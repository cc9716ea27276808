"""Face layers: several inputs mixed into one ``FaceState`` per frame (issue 18).

A frame's face is a **primary** ``FaceState`` (speech, a FAP stream, mocap) mixed with **layers**,
each sampled at the frame's media time (``Layer.sample(t) -> Contribution``) and mixed by the
seed's rules (``mix`` module docstring): offsets add, layers of one role competing for a FAP are
averaged by weight (expression overlays also with the primary, outside a speaking mouth), the
speech keeps its lip closures, blinks/gaze/head poses override.

- ``model``: ``Role``, ``Contribution``, ``Envelope`` (BML start / attack_peak / relax / end),
  ``GazeTarget``, ``Geometry`` (``Geometry.of_rig(animator.rig)``), the ``Layer`` protocol,
  ``REGIONS`` / ``region_mask``.
- ``mix``: ``mix(primary, layers, t, geometry=, closures=)`` (pure), ``combine`` (the same over
  ready contributions), ``mix_states`` (a whole stream), and ``Mixer`` (a session's named layers:
  ``set`` / ``add`` / ``remove`` / ``change(name, **fields)`` / ``layers()``, thread-safe;
  ``Mixer.mix(primary, t)`` drops layers whose ``end`` has passed).
- layers (frozen dataclasses, values checked on construction): ``ExpressionLayer`` (an MPEG-4
  expression or a FAP shape, amount, envelope, regions), ``TrackLayer`` (a FAP stream as an
  overlay), ``IdleLayer`` (blinks, saccades, sway, breathing; seeded), ``GazeLayer`` (a point or
  the camera, compensating the head), ``HeadGesture`` (nod, shake, tilt), ``HeadPose``.
- ``spec.from_spec(data, t0)``: a layer from plain data (a REST body), ``InputError`` otherwise.
- ``batch.mix_batch``: the live path's mix of a deform batch (one frame per session) together;
  ``kernel``: the same rules in one numba-compiled call a batch.
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
from .spec import from_spec

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
    "from_spec",
    "mix",
    "mix_states",
    "parse_gaze",
    "region_mask",
]
