"""Facial motion capture: marker takes in (C3D, TRC, CSV), cleaned, stabilised and retargeted onto a face.

``driver.load(path, face, layout=...)`` decodes a take into an ``Animation`` whose ``controls`` are
the displacements of the marker vertices on the face; ``live.MarkerLiveDriver`` does the same per
frame, causally, for live producers.
"""
