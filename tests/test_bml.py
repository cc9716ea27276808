"""BML 1.0 scripted performances (issue 18): the parser (happy paths, refusals naming line and
element, hostile XML, fuzzing), the scheduler (sync points within one frame in the rendered
output), the CLI render of a real recording, the REST job and the live play."""

from __future__ import annotations

import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from test_fuzz_parsers import FUZZ, mutated

from facecast.protocol.bml import (
    FACE_LEXEMES,
    MAX_BML_BYTES,
    BmlError,
    Face,
    Gaze,
    Head,
    Speech,
    parse_bml,
)
from facecast.server.bml.perform import render_performance
from facecast.server.bml.schedule import SpeechTiming, schedule
from facecast.server.errors import InputError

NS = 'xmlns="http://www.bml-initiative.org/bml/bml-1.0"'
FPS = 25.0

#: A performance over the real recording "Bobby ripped the ledger" (bobby.wav beside it).
BOBBY = f"""<?xml version="1.0" encoding="UTF-8"?>
<bml {NS} id="bml1" characterId="Bobby">
  <speech id="s1" audio="bobby.wav" start="0.3">
    <text>Bobby ripped <sync id="tm1"/> the ledger</text>
  </speech>
  <faceLexeme id="f1" lexeme="joy" amount="0.8" start="s1:tm1" end="s1:end + 0.6"/>
  <gaze id="g1" target="camera" offsetAngle="15" offsetDirection="LEFT" start="0" end="s1:tm1"/>
  <head id="h1" lexeme="NOD" repetition="2" start="g1:end"/>
</bml>
"""


def _bml(body: str) -> str:
    return f'<bml {NS} id="b">\n{body}\n</bml>'


# ----------------------------------------------------------------------------------------- parser


def test_a_performance_parses_into_typed_behaviours():
    block = parse_bml(BOBBY.encode(), where="p.bml")
    assert block.id == "bml1" and [b.id for b in block.behaviours] == ["s1", "f1", "g1", "h1"]
    s, f, g, h = block.behaviours
    assert isinstance(s, Speech) and s.audio == "bobby.wav"
    assert s.text == "Bobby ripped the ledger" and [(m.id, m.words) for m in s.marks] == [
        ("tm1", 2)
    ]
    assert isinstance(f, Face) and f.lexeme == "JOY" and f.amount == 0.8
    assert str(f.sync["start"]) == "s1:tm1" and str(f.sync["end"]) == "s1:end + 0.6"
    assert isinstance(g, Gaze) and g.target == "camera" and g.offset_direction == "LEFT"
    assert isinstance(h, Head) and h.lexeme == "NOD" and h.repetition == 2
    assert h.sync["start"].ref == "g1" and h.sync["start"].point == "end"


def test_other_forms_parse():
    block = parse_bml(
        _bml(
            '<faceFacs id="a" au="12" side="left" attack="0.4" start="0.1"/>\n'
            '<face id="b" type="facs" au="1"/>\n'
            '<face id="c" lexeme="raise_brows" stroke-start="1"/>\n'
            '<gaze id="d" target="0, 12.5, 300" influence="neck"/>\n'
            '<head id="e" lexeme="tilt" amount="0.3" stroke-start="b:end" stroke-end="b:end+1"/>'
        ).replace('stroke-start="1"', 'attack-peak="1"')
    )
    a, b, c, d, e = block.behaviours
    assert (a.au, a.side, a.sync["attackPeak"].offset) == (12, "LEFT", 0.4)
    assert b.au == 1 and c.lexeme == "RAISE_BROWS" and c.sync["attackPeak"].offset == 1.0
    assert d.point == (0.0, 12.5, 300.0) and d.influence == "NECK"
    assert e.sync["strokeStart"].ref == "b" and e.sync["strokeEnd"].offset == 1.0


@pytest.mark.parametrize(
    ("body", "line", "element", "says"),
    [
        (
            '<gesture id="g1" lexeme="BEAT"/>',
            2,
            "gesture",
            "unsupported behaviour; supported: speech",
        ),
        ('<head id="h" lexeme="WAVE"/>', 2, "head", "lexeme='WAVE' is not supported"),
        ('<head id="h" lexeme="NOD" strat="1"/>', 2, "head", "unknown attribute 'strat'"),
        ('<head lexeme="NOD"/>', 2, "head", "id='' must be a name"),
        ('<faceLexeme id="f" lexeme="GRIN"/>', 2, "faceLexeme", "lexeme='GRIN' is not supported"),
        ('<faceLexeme id="f" lexeme="JOY" amount="2"/>', 2, "faceLexeme", "amount='2' must be"),
        ('<faceLexeme id="f" lexeme="JOY" amount="nan"/>', 2, "faceLexeme", "amount='nan'"),
        ('<faceFacs id="f" au="99"/>', 2, "faceFacs", "au='99' is not supported"),
        ('<gaze id="g" target="moon"/>', 2, "gaze", "target='moon' is not supported"),
        ('<gaze id="g" target="camera" influence="WAIST"/>', 2, "gaze", "influence='WAIST'"),
        ('<head id="h" lexeme="NOD" start="h2 end"/>', 2, "head", "is neither seconds"),
        ('<head id="h" lexeme="NOD" start="other:g:end"/>', 2, "head", "refers to BML block"),
        ('<head id="h" lexeme="NOD" start="-1"/>', 2, "head", "must be from 0 to 3600"),
        ('<head id="h" lexeme="NOD" repetition="1.5"/>', 2, "head", "whole number"),
        ('<speech id="s"><text>hi</text></speech>', 2, "speech", "needs its recording"),
        ('<speech id="s" audio="/etc/passwd.wav"/>', 2, "speech", "relative file name"),
        ('<speech id="s" audio="../x/a.wav"/>', 2, "speech", "'..'"),
        ('<speech id="s" audio="a.txt"/>', 2, "speech", "must end with .wav"),
        ('<speech id="s" audio="a.wav">hi</speech>', 2, "speech", "inside its <text>"),
        (
            '<speech id="s" audio="a.wav">\n<text>a <sync id="x"/> b <sync id="x"/></text></speech>',
            3,
            "sync",
            "used twice",
        ),
        ('<speech id="s" audio="a.wav">\n<description/></speech>', 3, "description", "one <text>"),
        ('<head id="h" lexeme="NOD"/>\n<head id="h" lexeme="SHAKE"/>', 3, "head", "already used"),
        ('<head id="h" lexeme="NOD">x</head>', 2, "head", "takes no content"),
        ('<head id="h" lexeme="NOD"\n', 4, "bml", "not well-formed XML"),
    ],
)
def test_each_refusal_names_line_and_element(body, line, element, says):
    with pytest.raises(BmlError) as e:
        parse_bml(_bml(body), where="p.bml")
    assert e.value.line == line and e.value.element == element, str(e.value)
    assert says in str(e.value) and str(e.value).startswith(f"p.bml: line {line}: <{element}>: ")
    assert isinstance(e.value, InputError) and e.value.status == 400


def test_the_message_of_an_unsupported_behaviour_lists_the_supported_ones():
    with pytest.raises(BmlError) as e:
        parse_bml(_bml('<speech id="s" audio="a.wav"/>\n\n\n\n<gesture id="g"/>'))
    assert str(e.value) == (
        "line 6: <gesture>: unsupported behaviour; supported: speech, face, faceLexeme, "
        "faceFacs, gaze, head"
    )


def test_every_face_lexeme_has_a_shape():
    from facecast.server.bml.lexemes import face_shape

    for name in FACE_LEXEMES:
        expression, faps = face_shape(name, None)
        assert expression > 0 or (faps is not None and np.abs(faps).max() > 0), name


LAUGHS = (
    '<?xml version="1.0"?>\n<!DOCTYPE bml [\n <!ENTITY a "lol">\n'
    + "".join(f' <!ENTITY {c} "{("&" + p + ";") * 10}">\n' for p, c in zip("abcdefgh", "bcdefghi"))
    + "]>\n<bml><speech id='s' audio='a.wav'><text>&i;</text></speech></bml>"
)


@pytest.mark.parametrize(
    ("doc", "says"),
    [
        (LAUGHS, "DOCTYPE"),
        (
            '<!DOCTYPE bml [<!ENTITY x SYSTEM "file:///etc/passwd">]><bml>&x;</bml>',
            "DOCTYPE",
        ),
        ('<!DOCTYPE bml SYSTEM "http://example.com/bml.dtd"><bml/>', "DOCTYPE"),
        ("<bml><head id='h' lexeme='NOD'>&x;</head></bml>", "undefined entity"),
        ("<bml>" + "<a>" * 10000 + "</a>" * 10000 + "</bml>", "nested deeper than 8"),
        (
            "<bml>" + "<head id='h%d' lexeme='NOD'/>" * 1 + "<x/>" * 5000 + "</bml>",
            "more than 4096 elements",
        ),
        ("<bml><head id='h' lexeme='NOD' amount='" + "1" * 5000 + "'/></bml>", "longer than 1000"),
        ("<bml>" + " " * (MAX_BML_BYTES + 1) + "</bml>", "more than 1048576"),
        (b"\xff\xfe<\x00b\x00", "XML"),
        ("", "XML"),
        ("<bml/>", "no behaviours"),
        ("<speech id='s' audio='a.wav'/>", "root must be <bml>"),
    ],
)
def test_hostile_xml_is_refused_quickly(doc, says):
    t0 = time.process_time()
    with pytest.raises(BmlError, match=says):
        parse_bml(doc if isinstance(doc, bytes) else doc.encode())
    assert time.process_time() - t0 < 5.0  # CPU time: a bomb expanded would take far longer


SEEDS = [
    BOBBY.encode(),
    _bml(
        '<speech id="s1" audio="a.wav"><text>Hello <sync id="tm1"/> there</text></speech>\n'
        '<faceFacs id="a" au="12" side="LEFT" attack="s1:tm1" start="0.1" relax="s1:end-0.2"/>\n'
        '<face id="b" type="facs" au="1" start="a:relax" end="a:end + 1e-1"/>\n'
        '<gaze id="d" target="0 12.5 300" influence="HEAD" ready="s1:tm1"/>\n'
        '<head id="e" lexeme="SHAKE" amount=".3" repetition="3" stroke="d:ready"/>'
    ).encode(),
]


def test_bml_fuzz():
    """Mutated real documents: a block or the project's own error (never another exception or a
    hang), and what parses schedules or is refused as BML too."""
    timing = SpeechTiming(1.0, {"tm1": 0.4})

    @FUZZ
    @given(mutated(SEEDS, text=True))
    def check(data):
        try:
            block = parse_bml(data, where="f.bml")
        except BmlError as e:
            assert len(str(e)) < 2000
            return
        speeches = {
            b.id: SpeechTiming(1.0, {m.id: 0.5 for m in b.marks})
            for b in block.behaviours
            if isinstance(b, Speech)
        }
        try:
            perf = schedule(block, speeches or {"s1": timing})
        except BmlError:
            return
        assert all(math.isfinite(v) and v >= 0 for t in perf.timed for v in t.times.values())

    check()


# -------------------------------------------------------------------------------------- scheduler


def _perf(body: str, speech: dict | None = None):
    return schedule(parse_bml(_bml(body)), speech or {}, where="p.bml")


def test_references_resolve_in_dependency_order():
    p = _perf(
        '<head id="h" lexeme="NOD" start="g:end + 0.5"/>\n'
        '<gaze id="g" target="camera" start="f:attackPeak" end="2"/>\n'
        '<faceLexeme id="f" lexeme="SMILE" start="0.5" attackPeak="1" end="s:end"/>\n'
        '<speech id="s" audio="a.wav" start="0.2"><text>a <sync id="m"/> b</text></speech>',
        {"s": SpeechTiming(3.0, {"m": 1.25})},
    )
    assert p["s"].times == {"start": 0.2, "m": 1.45, "end": 3.2}
    assert p["f"].times["end"] == pytest.approx(3.2) and p["g"].start == 1.0
    assert p["h"].start == pytest.approx(2.5)
    assert p["h"].end == pytest.approx(2.5 + 0.6)  # one nod: its default 0.6 s
    assert p.duration == pytest.approx(3.2)
    f = p["f"].times
    assert f["relax"] == pytest.approx(3.2 - 0.3)  # the default release kept on a long face


def test_defaults_and_two_constraints_on_a_nod():
    p = _perf('<head id="h" lexeme="NOD" repetition="2" stroke="1" end="3"/>')
    t = p["h"].times  # stroke = start + d/4, end = start + d: start 1/3, d 8/3
    assert t["start"] == pytest.approx(1 / 3) and t["stroke"] == pytest.approx(1.0)
    p = _perf('<faceLexeme id="f" lexeme="JOY"/>')
    assert dict(p["f"].times) == {"start": 0.0, "attackPeak": 0.3, "relax": 1.7, "end": 2.0}
    p = _perf('<faceLexeme id="f" lexeme="JOY" end="0.5"/>')  # before 0: moved to 0
    assert p["f"].start == 0.0 and p["f"].end == 0.5


@pytest.mark.parametrize(
    ("body", "line", "says"),
    [
        ('<head id="h" lexeme="NOD" start="g:end"/>', 2, "refers to 'g', which no behaviour has"),
        ('<head id="h" lexeme="NOD" end="h:start+1"/>', 2, "refers to the behaviour itself"),
        (
            '<head id="h" lexeme="NOD" start="g:end"/>\n<gaze id="g" target="user" start="h:end"/>',
            2,
            "cycle: h -> g -> h",
        ),
        (
            '<gaze id="g" target="user"/>\n<head id="h" lexeme="NOD" start="g:stroke"/>',
            3,
            "g (gaze) has no sync point 'stroke'; it has start, ready, relax, end",
        ),
        (
            '<faceLexeme id="f" lexeme="JOY" start="2" end="1"/>',
            2,
            "end (1.000 s) comes before start",
        ),
        (
            '<head id="h" lexeme="NOD" start="0" stroke="0.5" end="3"/>',
            2,
            "evenly spaced; constrain at most two",
        ),
        (
            '<speech id="s" audio="a.wav" start="0" end="5"/>',
            2,
            "comes from its recording (2.00 s); constrain one of them",
        ),
        ('<speech id="s" audio="a.wav" end="1"/>', 2, "would start at -1.000 s"),
        (
            '<speech id="s" audio="a.wav"/>\n<speech id="t" audio="b.wav" start="s:end - 0.5"/>',
            3,
            "while s speaks (0.000-2.000 s); one voice speaks at a time",
        ),
        (
            '<head id="h" lexeme="NOD"/>\n<gaze id="g" target="user" start="h:start-1"/>',
            3,
            "before the block's start",
        ),
    ],
)
def test_bad_references_are_refused_with_line_and_element(body, line, says):
    with pytest.raises(BmlError) as e:
        _perf(body, {"s": SpeechTiming(2.0, {}), "t": SpeechTiming(1.0, {})})
    assert e.value.line == line and says in str(e.value), str(e.value)
    assert f"p.bml: line {line}: <" in str(e.value)


def _silent(seconds: float) -> list:
    from facecast.server.state import FaceState

    return [FaceState(t=i / FPS) for i in range(int(seconds * FPS) + 1)]


def _first_frame(values: np.ndarray) -> int:
    return int(np.flatnonzero(np.abs(values) > 1e-9)[0])


def test_sync_points_land_within_one_frame_in_the_rendered_output():
    """A smile whose start is a speech's mark, a nod at the gaze's end, a tilt's stroke: the first
    frame each moves and a nod's deepest frame are within one frame of their references."""
    p = _perf(
        '<speech id="s" audio="a.wav" start="0.37"><text>one <sync id="m"/> two</text></speech>\n'
        '<faceLexeme id="f" lexeme="JOY" start="s:m" end="s:end"/>\n'
        '<gaze id="g" target="camera" start="0" end="s:m + 0.61"/>\n'
        '<head id="h" lexeme="NOD" start="g:end"/>',
        {"s": SpeechTiming(2.0, {"m": 0.83})},
    )
    anim = render_performance(p, {"s": _silent(2.0)}, FPS)
    faps = np.array([s.faps for s in anim.states])
    mark = 0.37 + 0.83
    assert abs(_first_frame(faps[:, 41]) / FPS - mark) <= 1 / FPS + 1e-9  # joy raises the cheeks
    nod = 0.37 + 0.83 + 0.61
    assert abs(_first_frame(faps[:, 48]) / FPS - nod) <= 1 / FPS + 1e-9
    assert abs(np.argmax(faps[:, 48]) / FPS - p["h"].times["stroke"]) <= 1 / FPS + 1e-9
    assert faps[:, 48].max() > 0 and len(anim.states) == int(p.duration * FPS) + 1


# ------------------------------------------------------------------------- with a real recording


@pytest.fixture
def bobby(data_dir, tmp_path) -> Path:
    """``perf.bml`` (``BOBBY``) beside a link to the real recording ``bobby.wav``."""
    (tmp_path / "bobby.wav").symlink_to(data_dir / "speech" / "bobby_16bit_16khz.wav")
    (tmp_path / "perf.bml").write_text(BOBBY)
    return tmp_path / "perf.bml"


def _word_onset(data_dir: Path, word: str) -> float:
    text = (data_dir / "speech" / "bobby_words.TextGrid").read_text()
    i = text.index(f'text = "{word}"')
    return float(text[:i].rsplit("xmin =", 1)[1].split()[0])


def test_a_mark_in_the_text_lands_on_its_word_and_the_smile_on_the_mark(bobby, data_dir):
    import shutil

    if shutil.which("espeak-ng") is None:
        pytest.skip("the transcript alignment needs espeak-ng")
    from facecast.server.drivers import load_animation

    anim = load_animation(bobby, None, fps=FPS)
    from facecast.server.bml.driver import perform, read_block

    perf, spoken = perform(read_block(bobby), bobby.parent, FPS)
    assert spoken["s1"].marks_from == "aligned"
    mark = perf["s1"].times["tm1"]
    assert abs(mark - 0.3 - _word_onset(data_dir, "THE")) <= 1 / FPS + 1e-9  # the forced alignment
    faps = np.array([s.faps for s in anim.states])
    assert abs(_first_frame(faps[:, 41]) / FPS - mark) <= 1 / FPS + 1e-9
    assert (
        abs(_first_frame(faps[:, 48]) / FPS - perf["g1"].end) <= 1 / FPS + 1e-9
    )  # nod at gaze end
    speech = faps[int(0.3 * FPS) : int((0.3 + 1.19) * FPS), 3]
    assert speech.max() > 50  # the jaw moves with the words


def test_without_espeak_ng_the_marks_are_spread_by_characters(bobby, monkeypatch):
    import shutil

    from facecast.server.bml import speech as bml_speech

    which = shutil.which
    monkeypatch.setattr(  # the system edge: the phone finder is not installed
        bml_speech.shutil, "which", lambda name: None if name == "espeak-ng" else which(name)
    )
    s1 = parse_bml(BOBBY).behaviours[0]
    spoken = bml_speech.lipsync_speech(s1, bobby.parent / "bobby.wav", FPS)
    assert spoken.marks_from == "characters"
    mark = spoken.timing.marks["tm1"]  # 12 of 23 characters ("Bobby ripped") into the sound
    loud = spoken.lipsync.features.energy_db >= spoken.lipsync.calibration.silence_db
    times = spoken.lipsync.features.times[loud]
    assert times[0] < mark < times[-1]
    assert mark == pytest.approx(times[0] + (times[-1] + 0.01 - times[0]) * 12 / 23, abs=0.011)


def test_cli_renders_a_bml_with_a_real_recording_to_a_valid_glb(bobby, tmp_path):
    from test_render import read_glb

    out = tmp_path / "out.glb"
    r = subprocess.run(
        [sys.executable, "-m", "facecast.server.cli", "render", str(bobby), "-o", str(out)],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    glb = read_glb(out)
    assert glb["gltf"].asset.version == "2.0"
    from facecast.server.bml.driver import perform, read_block

    perf, _ = perform(read_block(bobby), bobby.parent, FPS)  # the nod after the gaze ends last
    assert perf.duration > 0.3 + 1.19 and perf.duration == perf["h1"].end
    assert len(glb["times"]) == glb["extras"]["frames"] == int(perf.duration * FPS + 1e-9) + 1
    assert glb["extras"]["max_error_mm"] <= glb["extras"]["tolerance_mm"] + 1e-6


def test_cli_refuses_a_missing_recording_naming_the_speech(tmp_path):
    (tmp_path / "perf.bml").write_text(BOBBY)
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "facecast.server.cli",
            "render",
            str(tmp_path / "perf.bml"),
            "-o",
            str(tmp_path / "o.glb"),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert r.returncode != 0 and not (tmp_path / "o.glb").exists()
    assert "line 3: <speech>: audio 'bobby.wav' is not a file next to the BML file" in r.stderr


# --------------------------------------------------------------------------- REST job and live play


@pytest.fixture(scope="module")
def job_server(tmp_path_factory):
    from conftest import RunningServer

    s = RunningServer(
        tmp_path_factory.mktemp("bml-jobs"), "--face", "default:2k", "--workers", "1"
    ).start()
    yield s
    s.stop()


def _speech_bytes(data_dir: Path) -> bytes:
    return (data_dir / "speech" / "bobby_16bit_16khz.wav").read_bytes()


def test_a_bml_job_with_its_uploaded_recording_renders_a_glb(job_server, data_dir):
    import httpx
    import pygltflib
    from test_jobs import wait

    srv = job_server
    r = httpx.post(
        srv.url + "/v1/jobs",
        files=[
            ("file", ("perf.bml", BOBBY.encode())),
            ("audio", ("bobby.wav", _speech_bytes(data_dir))),
        ],
        data={"face": "default:2k"},
        headers=srv.admin_headers,
        timeout=60,
    )
    assert r.status_code == 202, r.text
    assert r.json()["input_kind"] == "bml" and r.json()["input_name"] == "perf.bml"
    done = wait(srv, r.json()["id"])
    assert done["status"] == "done", done
    glb = httpx.get(srv.url + done["result_url"], headers=srv.admin_headers, timeout=60)
    assert glb.status_code == 200 and 'filename="perf.glb"' in glb.headers["content-disposition"]
    gltf = pygltflib.GLTF2.load_from_bytes(glb.content)
    assert gltf.asset.version == "2.0" and gltf.animations


@pytest.mark.parametrize(
    ("bml", "audio", "status", "says"),
    [
        (BOBBY, [], 400, "line 3: <speech>: audio 'bobby.wav' was not uploaded"),
        (BOBBY, [("other.wav", b"x")], 400, "was not uploaded"),
        (BOBBY.replace("bobby.wav", "../bobby.wav"), [], 400, "line 3: <speech>: audio="),
        (BOBBY.replace("bobby.wav", "/etc/x.wav"), [], 400, "relative file name"),
        (
            BOBBY.replace("bobby.wav", "input.bml/bobby.wav"),
            [("bobby.wav", b"RIFF")],
            400,
            "cannot be kept under that name",
        ),
        (BOBBY.replace('lexeme="NOD"', 'lexeme="BOW"'), [], 400, "line 8: <head>: lexeme='BOW'"),
        (
            BOBBY.replace(
                '<?xml version="1.0" encoding="UTF-8"?>', '<!DOCTYPE bml [<!ENTITY a "b">]>'
            ),
            [],
            400,
            "DOCTYPE",
        ),
    ],
    ids=["missing", "other-name", "dotdot", "absolute", "clash", "lexeme", "doctype"],
)
def test_a_bad_bml_upload_is_refused_with_line_and_element(job_server, bml, audio, status, says):
    import httpx

    srv = job_server
    files = [("file", ("perf.bml", bml.encode()))] + [("audio", a) for a in audio]
    r = httpx.post(srv.url + "/v1/jobs", files=files, headers=srv.admin_headers, timeout=60)
    assert r.status_code == status and says in r.json()["error"], r.text
    assert "/tmp" not in r.text and "jobs/" not in r.text


def test_unused_or_misplaced_audio_parts_are_refused(job_server, data_dir):
    import httpx

    srv = job_server
    wav = _speech_bytes(data_dir)
    extra = [("audio", ("bobby.wav", wav)), ("audio", ("spare.wav", wav))]
    r = httpx.post(
        srv.url + "/v1/jobs",
        files=[("file", ("perf.bml", BOBBY.encode())), *extra],
        headers=srv.admin_headers,
        timeout=60,
    )
    assert r.status_code == 400 and "'spare.wav' is not named by any speech" in r.text
    r = httpx.post(
        srv.url + "/v1/jobs",
        files=[("file", ("bobby.wav", wav)), ("audio", ("bobby.wav", wav))],
        headers=srv.admin_headers,
        timeout=60,
    )
    assert r.status_code == 400 and "go with a .bml performance only" in r.text


def test_playing_a_bml_into_a_live_session_streams_the_performance(server, data_dir):
    import asyncio

    import httpx
    from test_playback import collect, create

    s = create(server)
    r = httpx.post(
        f"{server.url}/v1/sessions/{s['id']}/play?token={s['producer_token']}",
        files=[
            ("file", ("perf.bml", BOBBY.encode())),
            ("audio", ("bobby.wav", _speech_bytes(data_dir))),
        ],
        timeout=120,
    )
    assert r.status_code == 202, r.text
    info = r.json()
    assert info["kind"] == "bml" and info["fps"] == 30 and info["seconds"] > 1.5
    frames = asyncio.run(collect(server, s, 20))
    pos = np.stack([f.positions() for f in frames])
    assert np.abs(pos - pos[0]).max() > 0.1, "the performance did not move the face"
    r = httpx.post(
        f"{server.url}/v1/sessions/{s['id']}/play?token={s['producer_token']}",
        files=[("file", ("perf.bml", BOBBY.encode()))],
        timeout=60,
    )
    assert r.status_code in (400, 409) and ("not uploaded" in r.text or "already" in r.text)


def test_render_server_uploads_the_recordings_named_by_the_bml(job_server, bobby, tmp_path):
    from test_render import read_glb

    from facecast.client.jobs import RemoteJobError, render_remote

    out = render_remote(
        job_server.url,
        bobby,
        tmp_path / "remote.glb",
        options={"face": "default:2k"},
        admin_key=job_server.admin_key,
    )
    assert read_glb(out)["gltf"].asset.version == "2.0"
    (bobby.parent / "bobby.wav").unlink()
    with pytest.raises(RemoteJobError, match="audio 'bobby.wav' is not a file next to"):
        render_remote(job_server.url, bobby, tmp_path / "x.glb", admin_key=job_server.admin_key)


def test_a_gaze_with_head_influence_turns_the_head_most_of_the_way_and_the_eyes_the_rest():
    from facecast.server.bml.perform import HEAD_SHARE

    p = _perf(
        '<gaze id="g" target="camera" influence="HEAD" offsetAngle="20" offsetDirection="LEFT" '
        'start="0" ready="0.3" relax="1.7" end="2"/>\n'
        '<gaze id="e" target="user" offsetAngle="10" offsetDirection="DOWN" start="3" end="4"/>'
    )
    faps = np.array([s.faps for s in render_performance(p, {}, FPS).states])
    au_per_deg = math.pi / 180 / 1e-5
    hold = faps[int(1.0 * FPS)]
    assert hold[49] == pytest.approx(20 * HEAD_SHARE * au_per_deg, rel=1e-6)  # yaw to the left
    assert hold[23] > 0 and hold[24] > 0  # the eyes turn further the same way
    eyes = faps[int(3.5 * FPS)]
    assert eyes[49] == 0 and eyes[25] != 0 and eyes[23] == pytest.approx(0, abs=1e-6)
    assert np.all(faps[int(2.5 * FPS), 23:27] == 0)  # between the gazes: straight ahead


def test_speeches_share_one_audio_budget_refused_before_decoding(bobby, monkeypatch):
    """Many speeches naming one recording cost no more than the limit: the one past it is refused
    from its header, naming its line."""
    from facecast.server.drivers import load_animation

    monkeypatch.setenv("FACECAST_MAX_AUDIO_SECONDS", "3")
    speeches = "\n".join(
        f'<speech id="s{i}" audio="bobby.wav"' + (f' start="s{i - 1}:end"' if i else "") + "/>"
        for i in range(300)
    )
    bobby.write_text(_bml(speeches))
    with pytest.raises(BmlError) as e:
        load_animation(bobby, None)
    assert e.value.line == 4 and e.value.element == "speech"  # the third: 2 × 1.19 s, 0.6 s left
    assert "over the limit of 1 s" in str(e.value) and "left of 3 s for all the speeches" in str(
        e.value
    )


def test_render_idle_on_a_bml_is_a_layer_of_the_performance_so_its_gaze_looks_past_the_sway(
    tmp_path,
):
    """``render x.bml --idle`` (``render_file`` with the idle layer) mixes idle with the
    performance's own layers in one mix: the gaze at the camera is worked out from the head
    pose the idle sway makes, so the eyes look at the camera within 2° in every frame (mixed
    after the performance, the saccades added to the eyes and the sway turned them away)."""
    from facecast.server.drivers import load_animation
    from facecast.server.faces import load_face
    from facecast.server.layers import GazeTarget, Geometry, IdleLayer
    from facecast.server.layers.mix import _AU, _rot, gaze_faps
    from facecast.server.render import render_file

    face = load_face("default:2k")
    bml = tmp_path / "look.bml"
    bml.write_text(_bml('<gaze id="g" target="camera" start="0" end="4"/>'))
    out = tmp_path / "look.fap"
    render_file(bml, out, face=face, layers=[IdleLayer(seed=5)])
    states = load_animation(out, None).states
    geo = Geometry.of_face(face)
    worst = 0.0
    for s in [s for s in states if 0.3 <= s.t <= 3.7]:  # the gaze at full weight (no ramps)
        pitch, yaw, roll = (float(s.faps[k]) * _AU for k in (48, 49, 50))
        R = _rot(pitch, yaw, roll)
        pv = geo.head_pivot.tolist()
        t = [pv[i] - sum(R[i][j] * pv[j] for j in range(3)) for i in range(3)]
        want = gaze_faps(GazeTarget.camera(), geo, R, t)
        worst = max(worst, max(abs(a - b) for a, b in zip(s.faps[23:27], want)) * _AU)
    assert abs(states[40].faps[49]) > 0  # the idle sway turns the head
    assert math.degrees(worst) < 2.0
