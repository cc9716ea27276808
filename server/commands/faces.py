"""``facecast faces [SPEC]``: list the built-in faces, or describe one face.

``facecast faces annotate MESH [-o MESH.face.json] [--landmarks L.json] [--preview PNG]
[--template auto|default|ict]``: annotate a
head mesh automatically (``faces.annotate``) and write its ``.face.json``.
"""

from __future__ import annotations

import argparse
import json


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "spec",
        nargs="?",
        default=None,
        help="face to describe (built-in name or mesh path), or 'annotate'",
    )
    p.add_argument(
        "mesh", nargs="?", default=None, help="with 'annotate': the head mesh (OBJ, PLY, GLB, STL)"
    )
    p.add_argument("--json", action="store_true", help="print JSON")
    a = p.add_argument_group("annotate")
    a.add_argument(
        "-o",
        "--output",
        default=None,
        help="annotation to write (default MESH.face.json beside it)",
    )
    a.add_argument(
        "--landmarks",
        default=None,
        help="JSON {MPEG-4 id: [x, y, z]} in mesh units, e.g. 9.3 nose tip, 3.7/3.12 outer eye "
        "corners, 8.3/8.4 mouth corners, 2.1 chin: guides the fit",
    )
    a.add_argument(
        "--preview", default=None, help="PNG showing the feature points from the front and side"
    )
    a.add_argument("--up", default=None, help="the mesh's up axis (+y, -z, ...) if known")
    a.add_argument("--forward", default=None, help="the mesh's face-forward axis if known")
    a.add_argument("--force", action="store_true", help="overwrite an existing annotation")
    a.add_argument(
        "--template",
        choices=("auto", "default", "ict"),
        default="auto",
        help="head fitted to the mesh: the built-in head, the ICT FaceKit neutral (needs "
        "../shared/data/ict-facekit), or auto: the one the head aligns to better",
    )


def describe(face) -> dict:
    """Vertices, triangles, units, parts, feature points, FAP controls and FAPU (mm) of ``face``."""
    from ..errors import FacecastError
    from ..mpeg4 import FEATURE_POINTS, fap_controls, fapu_mm

    try:
        fapu = {k: round(v, 3) for k, v in fapu_mm(face).items()}
    except FacecastError as e:
        fapu = {"error": str(e)}
    return {
        "name": str(face.name),
        "vertices": face.n_vertices,
        "triangles": int(len(face.triangles)),
        "units": face.units,
        "parts": {k: int(len(v)) for k, v in face.parts.items()},
        "feature_points": len(face.feature_points),
        "missing_feature_points": [p for p in FEATURE_POINTS if p not in face.feature_points],
        "fap_controls": int(len(fap_controls(face)[1])),
        "fapu_mm": fapu,
        "mesh_hash": face.mesh_hash,
    }


def annotate(args: argparse.Namespace) -> int:
    """``facecast faces annotate MESH``: write the automatic annotation (and a preview)."""
    from pathlib import Path

    from ..errors import InputError
    from ..faces.annotate import annotate_mesh
    from ..faces.annotate.landmarks import read_landmarks
    from ..faces.loaders import declared_units, face_from_annotation, read_mesh
    from ..output.atomic import write_bytes_atomic

    if args.mesh is None:
        raise InputError("give the mesh to annotate: facecast faces annotate MESH")
    mesh = Path(args.mesh)
    if not mesh.is_file():
        raise InputError("no such mesh file", where=str(mesh))
    out = (
        Path(args.output) if args.output else mesh.with_name(mesh.name.split(".")[0] + ".face.json")
    )
    if out.exists() and not args.force:
        raise InputError(
            "an annotation already exists (a user's annotation wins); use --force to replace it "
            "or -o to write elsewhere",
            where=str(out),
        )
    axes = None
    if args.up or args.forward:
        if not (args.up and args.forward):
            raise InputError("give both --up and --forward, or neither")
        axes = (args.up, args.forward)
    vertices, triangles = read_mesh(mesh)
    landmarks = read_landmarks(Path(args.landmarks), len(vertices)) if args.landmarks else None
    annotation = annotate_mesh(
        vertices,
        triangles,
        landmarks=landmarks,
        axes=axes,
        units=declared_units(mesh),
        template=args.template,
    )
    face = face_from_annotation(
        str(mesh), vertices, triangles, annotation, where="automatic annotation"
    )
    info = describe(face)
    if "error" in info["fapu_mm"]:
        raise InputError(
            f"the automatic annotation cannot drive FAPs: {info['fapu_mm']['error']}",
            where=str(mesh),
        )
    write_bytes_atomic(out, (json.dumps(annotation, indent=1) + "\n").encode())
    if args.preview:
        from ..faces.annotate.preview import annotation_preview

        annotation_preview(face, args.preview)
    report = annotation["automatic"]
    if args.json:
        print(json.dumps({"annotation": str(out), **info, "automatic": report}, indent=2))
        return 0
    print(
        f"{out}: {len(face.feature_points)} of 84 feature points, units {face.units} "
        f"({report['mm_per_unit_measured']:.3g} mm per unit measured), up {annotation['axes']['up']}, "
        f"forward {annotation['axes']['forward']}, parts {', '.join(face.parts)}; template "
        f"{report['template']}; {report['seconds']} s"
    )
    for fp, why in report["left_out"].items():
        print(f"  left out {fp}: {why}")
    for w in report["warnings"]:
        print(f"  warning: {w}")
    print(
        "FAPU (neutral distances, mm): " + ", ".join(f"{k} {v}" for k, v in info["fapu_mm"].items())
    )
    if args.preview:
        print(f"preview: {args.preview}")
    return 0


def run(args: argparse.Namespace) -> int:
    from ..faces import builtin_faces, load_face

    if args.spec == "annotate":
        return annotate(args)

    if args.spec is None:
        faces = builtin_faces()
        if args.json:
            print(json.dumps(faces))
        else:
            for name, n in faces.items():
                print(
                    f"{name}\t~{n} vertices (use {name}:<count>, e.g. {name}:2k, for another resolution)"
                )
        return 0
    info = describe(load_face(args.spec))
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    print(
        f"{info['name']}: {info['vertices']} vertices, {info['triangles']} triangles, units {info['units']}"
    )
    print("parts: " + ", ".join(f"{k} {v}" for k, v in info["parts"].items()))
    missing = info["missing_feature_points"]
    print(
        f"feature points: {info['feature_points']} of 84"
        + (f" (missing {', '.join(missing)})" if missing else "")
    )
    print(f"FAP controls: {info['fap_controls']}")
    print(
        "FAPU (neutral distances, mm): " + ", ".join(f"{k} {v}" for k, v in info["fapu_mm"].items())
    )
    return 0
