"""Batch rendering: an input file (.fap, audio, mocap) to an output file (.glb, .npz, .fap)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from pathlib import Path

from .errors import InputError

log = logging.getLogger(__name__)

#: Output suffixes ``render_file`` writes.
OUTPUTS: tuple[str, ...] = (".glb", ".npz", ".fap")

#: A ``.glb`` whose frames would take more bytes than this is encoded from frame chunks rendered
#: again on each of the encoder's passes (usually two) instead of being held in memory.
GLB_STREAM_BYTES = 512 * 2**20
#: Frames rendered at once for such a streamed ``.glb``: at most 64, and at most this many bytes.
GLB_CHUNK_BYTES = 96 * 2**20


def output_kind(path: str | Path) -> str:
    """``glb`` | ``npz`` | ``fap`` from the output suffix; InputError for anything else."""
    suffix = Path(path).suffix.lower()
    if suffix not in OUTPUTS:
        raise InputError(
            f"unsupported output type {suffix or '(none)'!r}; expected one of {', '.join(OUTPUTS)}",
            where=str(path),
        )
    return suffix[1:]


def render_file(
    input: str | Path,
    output: str | Path,
    *,
    face="default",
    engine: str = "fp",
    backend: str = "auto",
    device: str | None = None,
    layout: str | None = None,
    progress: Callable[[int, int], None] | None = None,
    mocap: dict | None = None,
    text: str | None = None,
    layers: Sequence | None = None,
) -> dict:
    """Decode ``input``, animate ``face`` and write ``output`` atomically (nothing is left on failure).

    Args:
        input: ``.fap``, ``.wav/.flac/.ogg`` or ``.c3d/.trc/.csv``.
        output: ``.glb`` (animated mesh), ``.npz`` (``vertices (T, V, 3)``, ``faces``, ``fps``) or
            ``.fap`` (the FAPs, no deformation needed).
        face: a face spec for ``load_face`` (``default``, ``default:2k``, a mesh path) or a ``Face``.
        engine, backend, device: see ``pipeline.Animator``; ``layout``: mocap marker layout.
        progress: ``callable(done, total)`` in frames.
        mocap: mocap cleaning choices for ``mocap.driver.load`` (``filter``, ``lowrank``, ``stable``,
            ``neutral_frame``).
        text: audio input's transcript (``audio.driver.load``); None = none.
        layers: ``server.layers`` layers (expression overlays, idle, gaze, head) mixed over the
            input's states (``layers.mix_states``). A speaking input (audio, mocap, a .fap with
            visemes) keeps its lip closures and adds expressions to its mouth; an expression
            stream (.fap without visemes) competes with them there. None or empty: the input
            as it is.

    Returns:
        a summary: ``frames``, ``fps``, ``output`` and, for glTF, the ``extras.facecast`` record.
    """
    from .drivers import load_animation
    from .faces import load_face

    input, output = Path(input), Path(output)
    kind = output_kind(output)
    if not input.is_file():
        raise InputError("input file not found", where=str(input))
    if not output.parent.is_dir():
        raise InputError("output folder does not exist", where=str(output.parent))
    options = {"layout": layout} if layout is not None else {}
    if text is not None:
        options["text"] = text
    if input.suffix.lower() in (".c3d", ".trc", ".csv"):
        options.update(
            {k: v for k, v in (mocap or {}).items() if v is not None}
        )  # mocap.driver.load's
    if layers and input.suffix.lower() == ".bml":  # a performance mixes them with its own
        options["layers"], layers = list(layers), None  # (its gaze looks past the idle sway)
    if input.suffix.lower() == ".fap":  # FAPs do not depend on the face: check the input first
        animation = load_animation(input, None)
        face_obj = load_face(face) if isinstance(face, (str, Path)) else face
    else:
        face_obj = load_face(face) if isinstance(face, (str, Path)) else face
        animation = load_animation(input, face_obj, **options)
    if not animation.states:
        raise InputError("the input holds no frames", where=str(input))
    if layers:
        from .layers import Geometry, mix_states

        # audio and mocap speak; a .fap stream speaks when it carries visemes (FAP 1)
        speaks = input.suffix.lower() != ".fap" or any(
            s.viseme is not None for s in animation.states
        )
        animation.states = mix_states(
            animation.states, list(layers), geometry=Geometry.of_face(face_obj), closures=speaks
        )
    summary = {"frames": len(animation.states), "fps": float(animation.fps), "output": str(output)}
    if kind == "fap":
        from .output.fap import write_fap_file

        write_fap_file(output, animation)
        if progress:
            progress(len(animation.states), len(animation.states))
        return summary

    from .pipeline import Animator

    animator = Animator(
        face_obj,
        engine=engine,
        backend=backend,
        device=device,
        control_vertices=animation.control_vertices,
    )
    n_frames = len(animation.states)
    if kind == "glb" and n_frames * face_obj.n_vertices * 12 > GLB_STREAM_BYTES:
        frames = _frame_chunks(animator, animation, progress)
    else:
        frames = animator.render(animation, progress=progress)
    if kind == "npz":
        from .output.npz import write_npz

        write_npz(output, frames, face_obj.triangles, animation.fps)
    else:
        from .output.gltf import write_glb

        summary["gltf"] = write_glb(
            output,
            frames,
            face_obj.vertices,
            face_obj.triangles,
            animation.fps,
            mm_per_unit=face_obj.mm_per_unit,
            name=input.stem or "facecast",
            extras={"source": input.name, "face": str(face_obj.name)}
            | ({"layers": [type(x).__name__ for x in layers]} if layers else {}),
        )
    log.info("rendered %s -> %s (%d frames at %g fps)", input, output, n_frames, animation.fps)
    return summary


def _frame_chunks(
    animator, animation, progress: Callable[[int, int], None] | None, size: int | None = None
):
    """A re-iterable source of ``(c, V, 3) float32`` frame chunks of ``size`` frames (default: 64, fewer
    on big faces, see ``GLB_CHUNK_BYTES``), rendered anew on every pass; ``progress`` follows the
    first pass."""
    import numpy as np

    size = size or int(min(64, max(4, GLB_CHUNK_BYTES // (12 * animator.face.n_vertices))))
    passes = []

    def chunks():
        first = not passes
        passes.append(1)
        total = len(animation.states)
        for start in range(0, total, size):
            states = animation.states[start : start + size]
            D, T = animator.solve_batch(states)
            verts = np.asarray(animator.deformer.deform_batch(D, T), dtype=np.float32)
            animator.add_shapes(verts, states, T)
            yield verts
            if progress is not None and first:
                progress(start + len(D), total)

    return chunks
