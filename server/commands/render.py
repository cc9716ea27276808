"""``facecast render INPUT -o OUT``: batch animation of a .fap, audio or mocap file, on this machine.

With ``--server URL`` the ``facecast`` entry point runs ``facecast.client.commands.render`` instead.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", type=Path, help="input: .fap, .wav/.flac/.ogg or .c3d/.trc/.csv")
    p.add_argument("-o", "--output", type=Path, required=True, help="output: .glb, .npz or .fap")
    p.add_argument(
        "--face", default="default", help="built-in face (default, default:2k, ...) or a mesh path"
    )
    p.add_argument(
        "--engine",
        choices=["fp", "rbf", "shell"],
        default="fp",
        help="deformation engine (default fp)",
    )
    p.add_argument(
        "--backend", choices=["auto", "numpy", "opencl"], default="auto", help="compute backend"
    )
    p.add_argument("--device", default=None, help="OpenCL device (index or name substring)")
    p.add_argument(
        "--layout",
        default=None,
        help="mocap marker layout file (for .c3d/.trc/.csv input; default: "
        "<take>.layout.json or layout.json beside the take; with --server its content is uploaded)",
    )
    m = p.add_argument_group("mocap cleaning (.c3d/.trc/.csv)")
    m.add_argument(
        "--filter",
        choices=["rts", "kalman", "none"],
        default=None,
        help="marker filter: rts (zero-lag smoother, default), kalman (causal, as live) or none",
    )
    m.add_argument(
        "--lowrank",
        default=None,
        metavar="auto|off|N",
        help="project the displacements on their N leading motions (default auto: those above the noise)",
    )
    m.add_argument(
        "--stable",
        default=None,
        metavar="A,B,C",
        help="stable (head) markers, overriding the layout's; one that is not rigid is named and left out",
    )
    m.add_argument(
        "--neutral-frame",
        type=_frame,
        default=None,
        metavar="N|auto",
        help="frame of the actor's neutral face and the head's rest (default: the layout's, else auto: "
        "frame 0 unless another fits the face at rest clearly better)",
    )
    m.add_argument(
        "--prior",
        default=None,
        metavar="auto|off|PATH",
        help="face prior: the face's expression shapes fitted to the markers (auto: the expressions/ "
        "folder beside the face mesh, the default; PATH: a folder of .obj/.obj.xz shapes or an "
        ".npz basis)",
    )
    lay = p.add_argument_group("layers (mixed over the input; local renders only)")
    lay.add_argument(
        "--layer",
        action="append",
        default=None,
        metavar="FILE[@AMOUNT]",
        help="a .fap stream added over the input from its start (an expression overlay), scaled "
        "by AMOUNT (default 1); the input keeps its lip closures; repeatable",
    )
    lay.add_argument(
        "--idle",
        action="store_const",
        const=True,
        default=None,
        help="idle motion: blinks, saccades, head sway, breathing",
    )
    lay.add_argument(
        "--seed", type=int, default=None, help="random seed of the idle motion (default 0)"
    )
    lay.add_argument(
        "--gaze",
        default=None,
        metavar="X,Y,Z|camera",
        help="eyes at a point in the face's coordinates (mesh units) or at the camera",
    )
    p.add_argument(
        "--server",
        metavar="URL",
        default=None,
        help="render on a facecast server instead of locally (admin key from $FACECAST_ADMIN_KEY)",
    )


def _frame(text: str) -> int | str:
    """``--neutral-frame``: a frame index or ``auto``."""
    return "auto" if text.strip().lower() == "auto" else int(text)


def _progress_bar(total_hint: str):
    """A ``(callback, close)`` pair drawing a tqdm bar on a terminal, or doing nothing."""
    if not sys.stderr.isatty():
        return None, lambda: None
    from tqdm import tqdm

    bar = tqdm(desc=total_hint, unit="frame", file=sys.stderr, leave=False)

    def update(done: int, total: int) -> None:
        if bar.total != total:
            bar.total = total
        bar.n = done
        bar.refresh()

    return update, bar.close


def _mocap_options(args: argparse.Namespace) -> dict:
    """The mocap flags the user set, as ``mocap.driver.load`` options."""
    opts = {
        "filter": args.filter,
        "lowrank": args.lowrank,
        "neutral_frame": args.neutral_frame,
        "prior": args.prior,
        "stable": [s.strip() for s in args.stable.split(",") if s.strip()] if args.stable else None,
    }
    return {k: v for k, v in opts.items() if v is not None}


def parse_layer(text: str) -> tuple[Path, float]:
    """``FILE[@AMOUNT]`` -> (path, amount); an ``@`` followed by no number belongs to the path."""
    from ..errors import InputError

    path, sep, tail = text.rpartition("@")
    if sep:
        try:
            amount = float(tail)
        except ValueError:
            return Path(text), 1.0
        if not (math.isfinite(amount) and abs(amount) <= 10):
            raise InputError("a layer amount is a number within ±10", where=text)
        return Path(path), amount
    return Path(text), 1.0


def build_layers(args: argparse.Namespace) -> list:
    """The ``server.layers`` layers the flags ask for (empty without any); InputError names the
    flag or file at fault."""
    from ..drivers import load_animation
    from ..errors import InputError
    from ..layers import GazeLayer, IdleLayer, TrackLayer, parse_gaze

    layers: list = []
    for text in args.layer or ():
        path, amount = parse_layer(text)
        if path.suffix.lower() != ".fap":
            raise InputError("a --layer is a .fap file (an expression or FAP stream)", where=text)
        if not path.is_file():
            raise InputError("layer file not found", where=str(path))
        anim = load_animation(path, None)
        if not anim.states:
            raise InputError("the layer holds no frames", where=str(path))
        layers.append(TrackLayer(anim.states, anim.fps, amount=amount))
    if args.seed is not None and not args.idle:
        raise InputError("--seed sets the idle motion's seed; add --idle", where="--seed")
    if args.idle:
        layers.append(IdleLayer(seed=args.seed or 0))
    if args.gaze is not None:
        try:
            layers.append(GazeLayer(parse_gaze(args.gaze)))
        except ValueError as e:
            raise InputError(str(e), where="--gaze") from None
    return layers


def run(args: argparse.Namespace) -> int:
    """Render locally (``--server`` runs ``facecast.client.commands.render`` instead, see ``cli.REMOTE``)."""
    from ..errors import InputError
    from ..render import output_kind, render_file

    output_kind(args.output)
    if not args.input.is_file():
        raise InputError("input file not found", where=str(args.input))
    layers = build_layers(args)
    progress, close = _progress_bar(args.input.name)
    try:
        render_file(
            args.input,
            args.output,
            face=args.face,
            engine=args.engine,
            backend=args.backend,
            device=args.device,
            layout=args.layout,
            progress=progress,
            mocap=_mocap_options(args),
            layers=layers,
        )
    finally:
        close()
    return 0
