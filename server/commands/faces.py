"""``facecast faces [SPEC]``: list the built-in faces, or describe one face."""
from __future__ import annotations

import argparse
import json


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("spec", nargs="?", default=None, help="face to describe (built-in name or mesh path)")
    p.add_argument("--json", action="store_true", help="print JSON")


def describe(face) -> dict:
    """Vertices, triangles, units, parts, feature points, FAP controls and FAPU (mm) of ``face``."""
    from ..errors import FacecastError
    from ..mpeg4 import FEATURE_POINTS, fap_controls, fapu_mm

    try:
        fapu = {k: round(v, 3) for k, v in fapu_mm(face).items()}
    except FacecastError as e:
        fapu = {"error": str(e)}
    return {
        "name": str(face.name), "vertices": face.n_vertices, "triangles": int(len(face.triangles)),
        "units": face.units, "parts": {k: int(len(v)) for k, v in face.parts.items()},
        "feature_points": len(face.feature_points),
        "missing_feature_points": [p for p in FEATURE_POINTS if p not in face.feature_points],
        "fap_controls": int(len(fap_controls(face)[1])), "fapu_mm": fapu, "mesh_hash": face.mesh_hash,
    }


def run(args: argparse.Namespace) -> int:
    from ..faces import builtin_faces, load_face

    if args.spec is None:
        faces = builtin_faces()
        if args.json:
            print(json.dumps(faces))
        else:
            for name, n in faces.items():
                print(f"{name}\t~{n} vertices (use {name}:<count>, e.g. {name}:2k, for another resolution)")
        return 0
    info = describe(load_face(args.spec))
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    print(f"{info['name']}: {info['vertices']} vertices, {info['triangles']} triangles, units {info['units']}")
    print("parts: " + ", ".join(f"{k} {v}" for k, v in info["parts"].items()))
    missing = info["missing_feature_points"]
    print(f"feature points: {info['feature_points']} of 84" + (f" (missing {', '.join(missing)})" if missing else ""))
    print(f"FAP controls: {info['fap_controls']}")
    print("FAPU (neutral distances, mm): " + ", ".join(f"{k} {v}" for k, v in info["fapu_mm"].items()))
    return 0
