"""MPEG-4 face animation tables: the 68 FAPs, the 84 feature points, the 10 FAP groups.

Facts from ``docs/mpeg4-reference.md`` §2–3 restated as data. Axes are MPEG-4's: +x = the face's
own left, +y up, +z out of the face. Positive rotations (eyeball/head yaw, pitch, roll) are
right-hand rotations about +y, +x and +z: yaw "left" turns the gaze (+z) toward +x, pitch "down"
turns it toward -y, roll "right" tips the top of the head toward -x.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..faces.face import FEATURE_POINT_IDS

#: FAP units. Distances are a neutral-face distance / 1024; AU is 1e-5 rad.
UNITS: tuple[str, ...] = ("MNS", "MW", "ES", "ENS", "IRISD", "AU")

#: Direction words -> unit vector (MPEG-4 axes) for translations, rotation axis for rotations.
DIRECTIONS: dict[str, tuple[float, float, float]] = {
    "up": (0.0, 1.0, 0.0),
    "down": (0.0, -1.0, 0.0),
    "left": (1.0, 0.0, 0.0),
    "right": (-1.0, 0.0, 0.0),
    "forward": (0.0, 0.0, 1.0),
    "yaw": (0.0, 1.0, 0.0),
    "pitch": (1.0, 0.0, 0.0),
    "roll": (0.0, 0.0, 1.0),
    "growing": (0.0, 0.0, 0.0),
    "concave_up": (0.0, 1.0, 0.0),
}


@dataclass(frozen=True)
class Fap:
    """One row of the FAP table.

    Attributes:
        number: 1..68.
        name: standard name (``open_jaw``).
        unit: one of ``UNITS`` (``""`` for the high-level FAPs 1, 2).
        bidirectional: False for the unidirectional FAPs (3, 14, 41, 42, 47); real files still
            carry negative values for them, which are applied as they are.
        direction: word of the + direction (``down``, ``left``, ``yaw``, ...).
        group: FAP group 1..10.
        fps: feature points moved (empty for eyeball and head rotations and FAPs 1/2).
        kind: ``high`` (1, 2), ``move`` (FP translation), ``jaw`` (3, 14, 15: rigid jaw),
            ``eye_rot`` / ``eye_move`` (23-28), ``pupil`` (29, 30), ``tongue_roll`` (47),
            ``head`` (48-50).
    """

    number: int
    name: str
    unit: str
    bidirectional: bool
    direction: str
    group: int
    fps: tuple[str, ...]
    kind: str

    @property
    def vector(self) -> np.ndarray:
        """``(3,) float64`` unit vector of the + direction (rotation axis for rotations)."""
        return np.array(DIRECTIONS[self.direction])


# number, name, unit, U/B, + direction, group, FPs, kind
_ROWS = """
1 viseme - - - 1 - high
2 expression - - - 1 - high
3 open_jaw MNS U down 2 2.1 jaw
4 lower_t_midlip MNS B down 2 2.2 move
5 raise_b_midlip MNS B up 2 2.3 move
6 stretch_l_cornerlip MW B left 2 2.4 move
7 stretch_r_cornerlip MW B right 2 2.5 move
8 lower_t_lip_lm MNS B down 2 2.6 move
9 lower_t_lip_rm MNS B down 2 2.7 move
10 raise_b_lip_lm MNS B up 2 2.8 move
11 raise_b_lip_rm MNS B up 2 2.9 move
12 raise_l_cornerlip MNS B up 2 2.4 move
13 raise_r_cornerlip MNS B up 2 2.5 move
14 thrust_jaw MNS U forward 2 2.1 jaw
15 shift_jaw MW B right 2 2.1 jaw
16 push_b_lip MNS B forward 2 2.3 move
17 push_t_lip MNS B forward 2 2.2 move
18 depress_chin MNS B up 2 2.10 move
19 close_t_l_eyelid IRISD B down 3 3.1 move
20 close_t_r_eyelid IRISD B down 3 3.2 move
21 close_b_l_eyelid IRISD B up 3 3.3 move
22 close_b_r_eyelid IRISD B up 3 3.4 move
23 yaw_l_eyeball AU B yaw 3 - eye_rot
24 yaw_r_eyeball AU B yaw 3 - eye_rot
25 pitch_l_eyeball AU B pitch 3 - eye_rot
26 pitch_r_eyeball AU B pitch 3 - eye_rot
27 thrust_l_eyeball ES B forward 3 - eye_move
28 thrust_r_eyeball ES B forward 3 - eye_move
29 dilate_l_pupil IRISD B growing 3 3.5 pupil
30 dilate_r_pupil IRISD B growing 3 3.6 pupil
31 raise_l_i_eyebrow ENS B up 4 4.1 move
32 raise_r_i_eyebrow ENS B up 4 4.2 move
33 raise_l_m_eyebrow ENS B up 4 4.3 move
34 raise_r_m_eyebrow ENS B up 4 4.4 move
35 raise_l_o_eyebrow ENS B up 4 4.5 move
36 raise_r_o_eyebrow ENS B up 4 4.6 move
37 squeeze_l_eyebrow ES B right 4 4.1 move
38 squeeze_r_eyebrow ES B left 4 4.2 move
39 puff_l_cheek ES B left 5 5.1 move
40 puff_r_cheek ES B right 5 5.2 move
41 lift_l_cheek ENS U up 5 5.3 move
42 lift_r_cheek ENS U up 5 5.4 move
43 shift_tongue_tip MW B right 6 6.1 move
44 raise_tongue_tip MNS B up 6 6.1 move
45 thrust_tongue_tip MW B forward 6 6.1 move
46 raise_tongue MNS B up 6 6.2 move
47 tongue_roll AU U concave_up 6 6.3,6.4 tongue_roll
48 head_pitch AU B pitch 7 - head
49 head_yaw AU B yaw 7 - head
50 head_roll AU B roll 7 - head
51 lower_t_midlip_o MNS B down 8 8.1 move
52 raise_b_midlip_o MNS B up 8 8.2 move
53 stretch_l_cornerlip_o MW B left 8 8.3 move
54 stretch_r_cornerlip_o MW B right 8 8.4 move
55 lower_t_lip_lm_o MNS B down 8 8.5 move
56 lower_t_lip_rm_o MNS B down 8 8.6 move
57 raise_b_lip_lm_o MNS B up 8 8.7 move
58 raise_b_lip_rm_o MNS B up 8 8.8 move
59 raise_l_cornerlip_o MNS B up 8 8.3 move
60 raise_r_cornerlip_o MNS B up 8 8.4 move
61 stretch_l_nose ENS B left 9 9.1 move
62 stretch_r_nose ENS B right 9 9.2 move
63 raise_nose ENS B up 9 9.3 move
64 bend_nose ENS B right 9 9.3 move
65 raise_l_ear ENS B up 10 10.1 move
66 raise_r_ear ENS B up 10 10.2 move
67 pull_l_ear ENS B left 10 10.3 move
68 pull_r_ear ENS B right 10 10.4 move
"""


def _parse_rows() -> tuple[Fap, ...]:
    rows = []
    for line in _ROWS.strip().splitlines():
        num, name, unit, ub, direction, group, fps, kind = line.split()
        rows.append(
            Fap(
                int(num),
                name,
                "" if unit == "-" else unit,
                ub == "B",
                "" if direction == "-" else direction,
                int(group),
                () if fps == "-" else tuple(fps.split(",")),
                kind,
            )
        )
    return tuple(rows)


#: The 68 FAPs in order: ``FAPS[k - 1].number == k``.
FAPS: tuple[Fap, ...] = _parse_rows()
#: FAP name -> number.
FAP_NUMBER: dict[str, int] = {f.name: f.number for f in FAPS}
#: FAP group -> its FAP numbers (10 groups).
FAP_GROUPS: dict[int, tuple[int, ...]] = {
    g: tuple(f.number for f in FAPS if f.group == g) for g in range(1, 11)
}

#: The 84 feature points (groups 2..11), defined with the face model.
FEATURE_POINTS: tuple[str, ...] = FEATURE_POINT_IDS

#: Feature point -> FAPs that name it (45 points; 3.5/3.6 are also moved by the eyeball FAPs).
FP_FAPS: dict[str, tuple[int, ...]] = {}
for _f in FAPS:
    for _p in _f.fps:
        FP_FAPS[_p] = FP_FAPS.get(_p, ()) + (_f.number,)
del _f, _p

#: Skin feature points that ride the jaw (their displacement includes the rigid jaw motion).
JAW_SKIN_FPS: tuple[str, ...] = ("2.1", "2.10", "2.11", "2.12")
#: Tongue feature points (displacements are in jaw-local space).
TONGUE_FPS: tuple[str, ...] = ("6.1", "6.2", "6.3", "6.4")


def fap(key: int | str) -> Fap:
    """The table row of FAP ``key`` (number 1..68 or name)."""
    n = FAP_NUMBER[key] if isinstance(key, str) else int(key)
    if not 1 <= n <= 68:
        raise KeyError(key)
    return FAPS[n - 1]
