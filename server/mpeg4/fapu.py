"""FAP units measured on a face's neutral feature points (``docs/mpeg4-reference.md`` §1.3)."""

from __future__ import annotations

from ..errors import InputError

#: FAPU -> (fp_a, fp_b, axis): the neutral distance is ``fp_a[axis] - fp_b[axis]``.
FAPU_DEFINITIONS: dict[str, tuple[str, str, int]] = {
    "IRISD": ("3.1", "3.3", 1),
    "ES": ("3.5", "3.6", 0),
    "ENS": ("3.5", "9.15", 1),
    "MNS": ("9.15", "2.2", 1),
    "MW": ("8.3", "8.4", 0),
}
#: The angle unit, radians.
AU = 1e-5


def measure_fapu(face) -> dict[str, float]:
    """FAPU of ``face`` in mesh units per FAP unit (``AU`` in radians).

    ``{"IRISD", "ES", "ENS", "MNS", "MW"}`` = neutral distance / 1024, ``"AU"`` = 1e-5. Raises
    ``InputError`` naming the feature points when one is missing or a distance is not positive
    (a mirrored mesh, wrong axes, or misplaced points).
    """
    out: dict[str, float] = {}
    for unit, (a, b, axis) in FAPU_DEFINITIONS.items():
        missing = [p for p in (a, b) if p not in face.feature_points]
        if missing:
            raise InputError(
                f"face has no feature point {' or '.join(missing)}, needed to measure "
                f"the FAPU {unit}; add it to the face annotation",
                where=str(face.name),
            )
        d = float(face.fp_position(a)[axis] - face.fp_position(b)[axis])
        if not d > 0:
            raise InputError(
                f"FAPU {unit} = {'xyz'[axis]}({a}) - {'xyz'[axis]}({b}) = {d:.6g} is not "
                f"positive; check the feature points {a} and {b} and that the mesh uses "
                "MPEG-4 axes (y up, z out of the face, x to the face's left)",
                where=str(face.name),
            )
        out[unit] = d / 1024.0
    out["AU"] = AU
    return out


def fapu_mm(face) -> dict[str, float]:
    """The neutral distances behind the FAPU in millimetres (IRISD0, ES0, ...): for reports."""
    return {
        f"{k}0": v * 1024.0 * face.mm_per_unit for k, v in measure_fapu(face).items() if k != "AU"
    }
