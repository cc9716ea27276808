"""The web viewer in a real headless Chromium against a real server (Playwright, Debian's chromium)."""

from __future__ import annotations

import asyncio
import json
import shutil
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
import websockets

from facecast.server.faces import load_face

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(not Path(CHROMIUM).exists(), reason="Debian chromium not installed"),
]

ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--use-gl=angle",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]

#: Pixel statistics of a canvas rectangle (x0, y0, x1, y1 in CSS pixels): mean RGB and spread.
PIXELS_JS = """([x0, y0, x1, y1]) => {
  const c = document.getElementById('view'), s = c.width / c.clientWidth;
  const g = c.getContext('webgl2');
  facecast.viewer.flush(); facecast.renderer.draw();  // read in the same task as the draw
  const w = Math.max(1, Math.round((x1 - x0) * s)), h = Math.max(1, Math.round((y1 - y0) * s));
  const px = new Uint8Array(4 * w * h);
  g.readPixels(Math.round(x0 * s), c.height - Math.round(y1 * s), w, h, g.RGBA, g.UNSIGNED_BYTE, px);
  return Array.from(px);
}"""


@pytest.fixture(scope="module")
def playwright():
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        yield p


@pytest.fixture(scope="module")
def browser(playwright):
    b = playwright.chromium.launch(executable_path=CHROMIUM, args=ARGS)
    yield b
    b.close()


def open_page(
    browser, url: str, artifacts: Path | None = None, viewport: tuple[int, int] = (1000, 700)
):
    page = browser.new_page(viewport={"width": viewport[0], "height": viewport[1]})
    problems: list[str] = []
    page.on(
        "console", lambda m: problems.append(f"{m.type}: {m.text}") if m.type == "error" else None
    )
    page.on("pageerror", lambda e: problems.append(f"pageerror: {e}"))
    page.goto(url)
    return page, problems


def region(page, box) -> np.ndarray:
    return np.array(page.evaluate(PIXELS_JS, box), dtype=np.float32).reshape(-1, 4)[:, :3]


def create_session(server, **body) -> dict:
    r = httpx.post(server.url + "/v1/sessions", json=body, headers=server.admin_headers, timeout=60)
    r.raise_for_status()
    return r.json()


async def produce_faps(server, session: dict, frames: list[dict]) -> None:
    url = (
        server.url.replace("http", "ws")
        + f"/v1/sessions/{session['id']}/produce?token={session['producer_token']}"
    )
    async with websockets.connect(url, compression=None) as ws:
        await ws.send(
            json.dumps({"type": "hello", "role": "producer", "protocol": 1, "input": "fap"})
        )
        assert json.loads(await ws.recv())["type"] == "ready"
        for i, faps in enumerate(frames):
            await ws.send(
                json.dumps(
                    {"type": "fap", "seq": i, "t": i / 30, "wall": time.time(), "faps": faps}
                )
            )
            await asyncio.sleep(0.4)
        await asyncio.sleep(1.0)


def run_async(coro) -> None:
    """Run ``coro`` to completion in its own thread (Playwright's sync API owns this thread's loop)."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(1) as pool:
        pool.submit(asyncio.run, coro).result()


def wait_for(page, js: str, timeout: float = 60.0):
    page.wait_for_function(js, timeout=timeout * 1000)


def test_page_loads_without_errors_and_draws_the_face(server, browser, artifacts):
    page, problems = open_page(browser, server.url + "/")
    wait_for(page, "document.getElementById('status').textContent.includes('loaded')")
    page.wait_for_timeout(500)
    page.screenshot(path=str(artifacts / "web_loaded.png"))
    whole = region(page, [0, 0, 690, 700])
    assert whole.std(axis=0).max() > 20, "the canvas is blank"
    # The face's skin colour dominates the middle of the view.
    middle = region(page, [295, 300, 395, 400]).mean(axis=0)
    assert middle[0] > middle[2] + 30, f"no skin in the middle of the canvas: {middle}"
    assert not problems, problems
    page.close()


def test_a_fap_frame_that_opens_the_jaw_changes_the_mouth(server, browser, artifacts):
    session = create_session(server, input="fap", fps=30)
    face = load_face("default")
    fp = face.feature_points
    page, problems = open_page(
        browser, f"{server.url}/#session={session['id']}&token={session['viewer_token']}"
    )
    wait_for(page, "document.getElementById('status').textContent.includes('watching')")
    run_async(produce_faps(server, session, [{"3": 0.0}]))
    wait_for(page, "window.facecast.viewer.stats.frames >= 1")
    page.wait_for_timeout(300)
    upper, lower = page.evaluate(
        f"[facecast.renderer.project({fp['2.2']}), facecast.renderer.project({fp['2.1']})]"
    )
    box = [upper[0] - 40, upper[1] - 5, upper[0] + 40, lower[1]]
    brow = page.evaluate(f"facecast.renderer.project({fp['4.3']})")
    brow_box = [brow[0] - 20, brow[1] - 20, brow[0] + 20, brow[1] + 20]
    mouth_before, brow_before = region(page, box), region(page, brow_box)
    page.screenshot(path=str(artifacts / "web_jaw_closed.png"))
    seen = page.evaluate("facecast.viewer.stats.frames")
    run_async(produce_faps(server, session, [{"3": 900.0, "5": -500.0}]))
    wait_for(page, f"window.facecast.viewer.stats.frames > {seen}")
    page.wait_for_timeout(300)
    page.screenshot(path=str(artifacts / "web_jaw_open.png"))
    wait_for(
        page, "document.getElementById('st-bytes').textContent.includes('KiB')"
    )  # the stats overlay
    mouth_after, brow_after = region(page, box), region(page, brow_box)
    mouth_change = np.abs(mouth_after - mouth_before).mean()
    brow_change = np.abs(brow_after - brow_before).mean()
    assert mouth_change > 8, f"the mouth region barely changed ({mouth_change:.1f})"
    assert mouth_change > 4 * brow_change, (mouth_change, brow_change)
    assert not problems, problems
    page.close()


def test_microphone_lip_sync_moves_the_mouth(server, playwright, data_dir, artifacts):
    speech = data_dir / "speech" / "bobby_16bit_16khz.wav"
    face = load_face("default")
    fp = face.feature_points
    b = playwright.chromium.launch(
        executable_path=CHROMIUM,
        args=ARGS
        + [
            "--use-fake-ui-for-media-stream",
            "--use-fake-device-for-media-stream",
            f"--use-file-for-fake-audio-capture={speech}",
            "--autoplay-policy=no-user-gesture-required",
        ],
    )
    try:
        page, problems = open_page(b, f"{server.url}/#key={server.admin_key}")
        wait_for(page, "document.getElementById('status').textContent.includes('loaded')")
        page.click("#mic")
        wait_for(page, "window.facecast.viewer.stats.frames >= 10", timeout=90)
        gaps = []
        for _ in range(40):
            page.wait_for_timeout(100)
            gaps.append(
                page.evaluate(
                    f"facecast.renderer.vertex({fp['2.2']})[1] - facecast.renderer.vertex({fp['2.3']})[1]"
                )
            )
        page.screenshot(path=str(artifacts / "web_microphone.png"))
        info = page.inner_text("#mic-info")
        assert "streaming" in info or "microphone on" in info, info
        gaps = np.array(gaps)
        assert np.ptp(gaps) > 0.5, (
            f"the lips did not move with the voice: gap range {np.ptp(gaps):.2f} mm"
        )
        assert not problems, problems
    finally:
        b.close()


def test_page_reconnects_after_a_server_restart_and_says_so(browser, tmp_path, artifacts):
    from conftest import RunningServer

    first = RunningServer(tmp_path / "data").start()
    port = first.port
    try:
        session = create_session(first, input="fap", fps=30)
        httpx.post(
            f"{first.url}/v1/sessions/{session['id']}/demo", headers=first.admin_headers
        ).raise_for_status()
        page, problems = open_page(
            browser, f"{first.url}/#session={session['id']}&token={session['viewer_token']}"
        )
        wait_for(page, "window.facecast.viewer.stats.frames >= 5")
    finally:
        first.stop()
    wait_for(page, "document.getElementById('status').textContent.includes('reconnecting')")
    second = RunningServer(tmp_path / "data")
    second.port, second.url = port, f"http://127.0.0.1:{port}"
    second.start()
    try:
        # Live sessions do not outlive the server: the page reconnects and says the session is gone.
        wait_for(page, "document.getElementById('status').textContent.includes('is gone')")
        page.screenshot(path=str(artifacts / "web_after_restart.png"))
        assert not [p for p in problems if "WebSocket" not in p], problems
    finally:
        page.close()
        second.stop()


#: Record the lip gap (mm, feature points 2.2 minus 2.3) of every frame the page draws, in window.gaps.
RECORD_GAPS_JS = """([upper, lower]) => {
  const v = facecast.viewer, r = facecast.renderer, flush = v.flush.bind(v);
  window.gaps = [];
  v.flush = () => {
    const fresh = flush();
    if (fresh) window.gaps.push(r.vertex(upper)[1] - r.vertex(lower)[1]);
    return fresh;
  };
}"""


def test_playing_an_uploaded_speech_file_moves_the_lips_with_sound(
    server, browser, data_dir, tmp_path, artifacts
):
    """The lips move with the file over its whole playback (every frame the page draws is looked at,
    not samples at moments a loaded machine may reach only after the speech is over)."""
    import soundfile as sf

    fp = load_face("default").feature_points
    samples, rate = sf.read(data_dir / "speech" / "bobby_16bit_16khz.wav", dtype="int16")
    speech = tmp_path / "bobby_three_times.wav"  # 3.6 s: time for the page to see it under load
    sf.write(speech, np.concatenate([samples] * 3), rate, subtype="PCM_16")
    page, problems = open_page(browser, f"{server.url}/#key={server.admin_key}")
    wait_for(page, "document.getElementById('status').textContent.includes('loaded')")
    page.evaluate(RECORD_GAPS_JS, [fp["2.2"], fp["2.3"]])
    page.set_input_files("#file", str(speech))
    page.click("#play")
    wait_for(
        page, "document.getElementById('play-info').textContent.includes('playing')", timeout=120
    )
    # The server tells viewers the producer left once the file's last frame is out.
    wait_for(
        page,
        "document.getElementById('status').textContent.includes('producer not connected')",
        timeout=120,
    )
    gaps = np.array(page.evaluate("window.gaps"))
    assert page.evaluate("document.getElementById('audio').src.startsWith('blob:')")
    assert len(gaps) >= 2, f"the page drew {len(gaps)} frames of the file"
    assert np.ptp(gaps) > 0.5, (
        f"the lips did not move with the file: gap range {np.ptp(gaps):.2f} mm over {len(gaps)} frames"
    )
    page.screenshot(path=str(artifacts / "web_play_speech.png"))
    assert not problems, problems
    page.close()


def jaw_fap(path: Path, frames: int = 100) -> Path:
    """A .fap clip that opens the jaw and closes it again (25 fps)."""
    from facecast.protocol.fap_file import FapFile, FapFrame, write_fap

    values = 900 * np.sin(np.linspace(0, np.pi, frames))
    path.write_text(
        write_fap(
            FapFile(frames=tuple(FapFrame.build(i, {3: int(v)}) for i, v in enumerate(values)))
        )
    )
    return path


def test_play_after_driving_the_face_with_a_button_takes_over_the_producer(
    server, browser, tmp_path, artifacts
):
    page, problems = open_page(browser, f"{server.url}/#key={server.admin_key}")
    wait_for(page, "document.getElementById('status').textContent.includes('loaded')")
    page.click("#expressions button >> text=joy")
    wait_for(page, "window.facecast.viewer.stats.frames >= 1")
    wait_for(page, "window.facecast.state.producer && window.facecast.state.producer.open")
    page.set_input_files("#file", str(jaw_fap(tmp_path / "jaw.fap")))
    seen = page.evaluate(
        "facecast.viewer.stats.frames"
    )  # the button's frame; nothing more comes until Play
    page.click("#play")
    wait_for(
        page,
        "document.getElementById('play-info').textContent.includes('playing') || "
        "document.getElementById('status').className.includes('error')",
        timeout=120,
    )
    info, status = page.inner_text("#play-info"), page.inner_text("#status")
    assert "playing jaw.fap: 100 frames" in info, (info, status)
    assert "409" not in status and "already" not in status, status
    wait_for(page, f"window.facecast.viewer.stats.frames >= {seen + 5}")  # the file's frames arrive
    # and the buttons take the session back from the playing file
    page.click("#visemes button >> text=aa")
    wait_for(page, "window.facecast.state.producer && window.facecast.state.producer.open")
    page.screenshot(path=str(artifacts / "web_button_then_play.png"))
    assert "error" not in page.evaluate("document.getElementById('status').className"), (
        page.inner_text("#status")
    )
    assert not problems, problems
    page.close()


def test_a_dragged_slider_opens_one_producer_connection(server, browser):
    page, problems = open_page(browser, f"{server.url}/#key={server.admin_key}")
    sockets = []
    page.on("websocket", lambda ws: sockets.append(ws.url) if "/produce" in ws.url else None)
    wait_for(page, "document.getElementById('status').textContent.includes('loaded')")
    page.evaluate("""() => {
      const jaw = document.querySelector('#sliders input[data-fap="3"]');
      for (let v = 100; v <= 900; v += 100) { jaw.value = v; jaw.dispatchEvent(new Event('input')); }
    }""")
    wait_for(page, "window.facecast.state.producer && window.facecast.state.producer.open")
    wait_for(page, "window.facecast.viewer.stats.frames >= 1")
    assert len(sockets) == 1, sockets
    assert not problems, problems
    page.close()


def test_a_marker_take_plays_with_the_layout_file_the_page_attaches(
    server, browser, tmp_path, artifacts
):
    from facecast.protocol.markers_file import write_trc
    from facecast.server.mocap.synthetic import synthetic_take

    syn = synthetic_take(load_face("default"), n_markers=16, seconds=1.0, fps=60.0, seed=3)
    (tmp_path / "take.trc").write_text(write_trc(syn.take))
    (tmp_path / "layout.json").write_text(json.dumps(syn.layout))
    page, problems = open_page(browser, f"{server.url}/#key={server.admin_key}")
    wait_for(page, "document.getElementById('status').textContent.includes('loaded')")
    assert not page.is_visible("#layout")  # asked for only with a marker take
    page.set_input_files("#file", str(tmp_path / "take.trc"))
    assert page.is_visible("#layout")
    page.click("#play")  # no layout yet: the page says what is missing, nothing is sent
    assert "layout" in page.inner_text("#status")
    page.set_input_files("#layout", str(tmp_path / "layout.json"))
    page.click("#play")
    wait_for(
        page,
        "document.getElementById('play-info').textContent.includes('playing') || "
        "document.getElementById('status').className.includes('error')",
        timeout=120,
    )
    assert "playing take.trc: 60 frames" in page.inner_text("#play-info"), page.inner_text(
        "#status"
    )
    wait_for(page, "window.facecast.viewer.stats.frames >= 5")
    page.screenshot(path=str(artifacts / "web_marker_take.png"))
    assert not problems, problems
    page.close()


def page_text_everywhere(page) -> str:
    """Everything the page shows or holds in its markup: the address, the title, the rendered text,
    the HTML (attributes included) and the value of every field but the admin key's password box."""
    return "\n".join(
        [
            page.url,
            page.title(),
            page.inner_text("body"),
            page.content(),
            page.evaluate(
                "[...document.querySelectorAll('input, select, textarea, output')]"
                ".filter((e) => e.id !== 'admin-key').map((e) => e.value).join('\\n')"
            ),
        ]
    )


def test_the_page_never_shows_a_token_or_the_admin_key(server, browser, tmp_path):
    session = create_session(server, input="fap", fps=30)
    secrets = {
        "admin key": server.admin_key,
        "producer token": session["producer_token"],
        "viewer token": session["viewer_token"],
    }
    bad = tmp_path / "bad.fap"
    bad.write_text("2.1 broken 25 1\nnot a mask\n")
    # A link with the session's tokens and no admin key: producer routes take the token in the query,
    # and the server's refusal of a bad file must not bring it into the status bar.
    page, problems = open_page(
        browser,
        f"{server.url}/#session={session['id']}&token={session['viewer_token']}"
        f"&producer={session['producer_token']}",
    )
    wait_for(page, "document.getElementById('status').textContent.includes('watching')")
    assert page.evaluate("document.getElementById('admin-key').value") == ""
    page.click("#expressions button >> text=joy")
    wait_for(page, "window.facecast.state.producer && window.facecast.state.producer.open")
    page.set_input_files("#file", str(bad))
    page.click("#play")
    wait_for(page, "document.getElementById('status').className.includes('error')", timeout=120)
    assert "400" in page.inner_text("#status")
    shown = page_text_everywhere(page)
    assert f"session={session['id']}" in page.url  # the link still names the session, for a reload
    assert not [name for name, s in secrets.items() if s in shown], page.inner_text("#status")
    page.close()
    # With the admin key in the link: every button, the demo and a file, then look again.
    page, problems = open_page(browser, f"{server.url}/#key={server.admin_key}")
    wait_for(page, "document.getElementById('status').textContent.includes('loaded')")
    assert page.evaluate("document.getElementById('admin-key').type") == "password"
    page.click("#demo")
    wait_for(page, "window.facecast.viewer.stats.frames >= 3")
    page.click("#expressions button >> text=joy")
    wait_for(page, "window.facecast.state.producer && window.facecast.state.producer.open")
    page.set_input_files("#file", str(bad))
    page.click("#play")
    wait_for(page, "document.getElementById('status').className.includes('error')", timeout=120)
    page_secrets = [
        v for t in page.evaluate("Object.values(facecast.state.tokens)") for v in t.values() if v
    ]
    assert page_secrets, "the page holds the tokens of the sessions it made"
    shown = page_text_everywhere(page)
    assert server.admin_key not in shown and not [s for s in page_secrets if s in shown], (
        page.inner_text("#status")
    )
    assert not [p for p in problems if "status of 400" not in p], problems  # the bad file's refusal
    page.close()


def test_at_phone_width_the_face_is_not_covered(server, browser, artifacts):
    page, problems = open_page(
        browser, f"{server.url}/#key={server.admin_key}", viewport=(390, 844)
    )
    wait_for(page, "document.getElementById('status').textContent.includes('loaded')")
    page.click("#demo")
    wait_for(page, "window.facecast.viewer.stats.frames >= 3")
    page.evaluate("window.scrollTo(0, 0)")
    page.screenshot(path=str(artifacts / "web_phone.png"))
    canvas = page.locator("#view").bounding_box()
    assert canvas["width"] >= 0.9 * 390 and canvas["height"] >= 240, canvas
    # The middle half of the canvas (where the camera frames the face) is free of every overlay
    # and of the controls.
    x0, x1 = canvas["x"] + canvas["width"] / 4, canvas["x"] + 3 * canvas["width"] / 4
    y0, y1 = canvas["y"] + canvas["height"] / 4, canvas["y"] + 3 * canvas["height"] / 4
    for sel in ("#stats", "#status", "aside"):
        b = page.locator(sel).bounding_box()
        apart = (
            b["x"] >= x1 or b["x"] + b["width"] <= x0 or b["y"] >= y1 or b["y"] + b["height"] <= y0
        )
        assert apart, f"{sel} {b} covers the middle of the face {(x0, y0, x1, y1)}"
    # and what is drawn there is the face
    w, h = canvas["width"], canvas["height"]
    middle = region(page, [w / 2 - 30, h / 2 - 30, w / 2 + 30, h / 2 + 30]).mean(axis=0)
    assert middle[0] > middle[2] + 30, f"no skin in the middle of the canvas: {middle}"
    assert not problems, problems
    page.close()


#: Render the current frame twice in one task: as drawn (back faces culled on closed surfaces) and
#: with every triangle drawn unculled, or with per-pixel and per-vertex lighting, or at full and
#: coarse level of detail, or in mesh and vertex-cache triangle order, or with the mouth's interior
#: drawn whole and only inside the mouth window. Returns pixel
#: statistics: `face` the fraction of pixels unlike the background, `differ` the fraction that differ
#: between the two pictures by more than 24 levels, `mad` the mean absolute difference over the face,
#: `mid` the second picture's mean RGB in the middle, `spread` its largest per-channel deviation,
#: `changed` the number of colour bytes that differ at all, `window` the last mouth window.
TWO_RENDERS_JS = """([what, yaw, pitch]) => {
  const r = facecast.renderer, gl = r.gl, m = r.mesh, groups = m.groups, shading = r.shading;
  r.camera.yaw = yaw; r.camera.pitch = pitch;
  const grab = (variant) => {
    if (what === 'cull') m.groups = variant ? groups : [{ first: 0, count: m.count, cull: false }];
    else if (what === 'lod') r.lod = variant ? 1 : 0;
    else if (what === 'order') r.setVertexCacheOrder(variant);
    else if (what === 'scissor') r.mouthScissor = variant;
    else r.shading = variant ? 'vertex' : 'pixel';
    r.draw();
    const px = new Uint8Array(4 * r.canvas.width * r.canvas.height);
    gl.readPixels(0, 0, r.canvas.width, r.canvas.height, gl.RGBA, gl.UNSIGNED_BYTE, px);
    if (what !== 'order') m.groups = groups;
    r.shading = shading; r.lod = 0; r.mouthScissor = true;
    return px;
  };
  const a = grab(false), b = grab(true), W = r.canvas.width, H = r.canvas.height, n = W * H;
  let face = 0, differ = 0, sad = 0;
  const mid = [0, 0, 0], sum = [0, 0, 0], sq = [0, 0, 0]; let k = 0;
  for (let i = 0; i < 4 * n; i += 4) {
    let d = 0, bg = 0;
    for (let c = 0; c < 3; c++) {
      d = Math.max(d, Math.abs(a[i + c] - b[i + c]));
      bg = Math.max(bg, Math.abs(a[i + c] - a[c]));
    }
    if (d > 24) differ++;
    if (bg > 8) {
      face++;
      for (let c = 0; c < 3; c++) {
        sad += Math.abs(a[i + c] - b[i + c]) / 3; sum[c] += b[i + c]; sq[c] += b[i + c] ** 2;
      }
    }
    const x = (i / 4) % W, y = Math.floor(i / 4 / W);
    if (Math.abs(x - W / 2) < 10 && Math.abs(y - H / 2) < 10) { for (let c = 0; c < 3; c++) mid[c] += b[i + c]; k++; }
  }
  const spread = Math.max(...sum.map((s, c) => Math.sqrt(sq[c] / face - (s / face) ** 2)));
  let changed = 0;
  for (let i = 0; i < 4 * n; i++) if (a[i] !== b[i]) changed++;
  return { face: face / n, differ: differ / n, mad: sad / face, mid: mid.map((x) => x / k), spread, changed,
           window: r.lastMouthWindow, size: [W, H] };
}"""


@pytest.fixture(scope="module")
def face_page(server, browser):
    page, problems = open_page(browser, server.url + "/")
    wait_for(page, "document.getElementById('status').textContent.includes('loaded')")
    page.evaluate("facecast.setQuality({ scale: 0.5 })")  # small readbacks; fixed, no adaptation
    yield page, problems
    page.close()


def test_back_face_culling_leaves_the_picture_unchanged(face_page):
    page, problems = face_page
    for yaw, pitch in [(0.35, 0.08), (-1.2, -0.3), (2.8, 0.2)]:
        r = page.evaluate(TWO_RENDERS_JS, ["cull", yaw, pitch])
        assert r["face"] > 0.05, f"nothing drawn at yaw {yaw}"
        assert r["differ"] < 0.002, (
            f"culling changed {100 * r['differ']:.2f} % of the pixels at yaw {yaw}"
        )
    assert not problems, problems


def test_per_vertex_lighting_draws_the_same_lit_face(face_page, artifacts):
    page, problems = face_page
    r = page.evaluate(TWO_RENDERS_JS, ["shading", 0.35, 0.08])
    assert r["face"] > 0.05, "nothing drawn"
    mid = r["mid"]
    assert mid[0] > mid[2] + 30, f"no lit skin in the middle with per-vertex lighting: {mid}"
    # Same lights and colours, only interpolated differently: close on average, shaded (not flat).
    assert r["mad"] < 12, r
    assert r["spread"] > 10, r
    page.evaluate("facecast.setQuality({ shading: 'vertex' }); facecast.renderer.draw()")
    page.screenshot(path=str(artifacts / "web_vertex_lighting.png"))
    page.evaluate("facecast.setQuality({ shading: 'pixel' })")
    assert not problems, problems


#: One triangle in the plane z = 0 seen from +z, of part `part`, wound to face the eye (or away, `back`),
#: drawn with every vertex normal set to `n` (no session: the page's mesh is replaced). Returns the RGB
#: in the middle of the canvas for each shading mode.
ONE_TRIANGLE_JS = """([n, part, back]) => {
  const r = facecast.renderer, gl = r.gl;
  const tri = back ? [0, 2, 1] : [0, 1, 2];
  const corners = Float32Array.from([-1, -1, 0, 1, -1, 0, 0, 1, 0]);
  r.setMesh(corners, Uint32Array.from(tri), Uint8Array.from([0, 0, 0]), [part]);
  r.camera.yaw = 0; r.camera.pitch = 0;
  const out = {};
  for (const shading of ['pixel', 'vertex']) {
    r.shading = shading;
    gl.bindBuffer(gl.ARRAY_BUFFER, r.mesh.nrm);
    gl.bufferSubData(gl.ARRAY_BUFFER, 0, Float32Array.from([...n, ...n, ...n]));
    r.draw();
    const px = new Uint8Array(4);
    gl.readPixels(r.canvas.width >> 1, r.canvas.height >> 1, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
    out[shading] = Array.from(px.slice(0, 3));
  }
  r.shading = 'pixel';
  return out;
}"""


def test_a_front_face_is_lit_with_its_own_normal_even_where_it_points_away(server, browser):
    """Interpolated normals of a closed surface point away from the eye along silhouettes and in
    creases (the crown seen from the front, the eyelids): lighting them from the other side drew a
    dark rim on the crown and dark patches around the eyes. Only the back of a two-sided sheet is lit
    with its normal reversed."""
    page, problems = open_page(browser, server.url + "/")
    wait_for(page, "document.getElementById('status').textContent.includes('loaded')")
    away = np.array([0.3, 0.95, -0.1]) / np.linalg.norm([0.3, 0.95, -0.1])  # towards the key light
    lit = page.evaluate(ONE_TRIANGLE_JS, [away.tolist(), "skin", False])
    reversed_ = page.evaluate(ONE_TRIANGLE_JS, [(-away).tolist(), "skin", False])
    for shading in ("pixel", "vertex"):
        assert sum(lit[shading]) > sum(reversed_[shading]) + 60, (shading, lit, reversed_)
    # the back of a two-sided sheet is lit as the front with the normal reversed
    sheet_back = page.evaluate(ONE_TRIANGLE_JS, [(-away).tolist(), "eyelashes", True])
    sheet_front = page.evaluate(ONE_TRIANGLE_JS, [away.tolist(), "eyelashes", False])
    for shading in ("pixel", "vertex"):
        diff = np.abs(np.subtract(sheet_back[shading], sheet_front[shading])).max()
        assert diff <= 2, (shading, sheet_back, sheet_front)
    assert not problems, problems
    page.close()


def test_the_coarse_level_draws_the_same_lit_face(face_page, artifacts):
    page, problems = face_page
    r = page.evaluate(TWO_RENDERS_JS, ["lod", 0.35, 0.08])
    assert r["face"] > 0.05, "nothing drawn"
    assert r["mid"][0] > r["mid"][2] + 30, (
        f"no lit skin in the middle at the coarse level: {r['mid']}"
    )
    assert r["differ"] < 0.05, f"the coarse level changed {100 * r['differ']:.1f} % of the pixels"
    page.evaluate("facecast.setQuality({ lod: 1 }); facecast.renderer.draw()")
    page.screenshot(path=str(artifacts / "web_coarse_level.png"))
    page.evaluate("facecast.setQuality({ lod: 0 })")
    assert not problems, problems


def test_vertex_cache_order_draws_the_same_picture(face_page):
    page, problems = face_page
    for yaw, pitch in [(0.35, 0.08), (-1.2, -0.3)]:
        r = page.evaluate(TWO_RENDERS_JS, ["order", yaw, pitch])
        assert r["face"] > 0.05, f"nothing drawn at yaw {yaw}"
        # the same triangles; only where two surfaces meet at equal depth may the other one win
        assert r["differ"] < 0.002, (
            f"the triangle order changed {100 * r['differ']:.2f} % of the pixels"
        )
    assert not problems, problems


#: Views for the mouth window checks: front, side, from below, from behind (yaw, pitch).
MOUTH_VIEWS = [(0.35, 0.08), (-1.0, 0.3), (0.2, -1.3), (3.0, 0.1)]


def check_mouth_window(server, browser, artifacts, face: str, fp: dict) -> list[dict]:
    """Drive a session's mouth closed, then open, then open with the tongue thrust out, and render each
    state from MOUTH_VIEWS with the mouth's interior drawn whole and only inside the mouth window:
    every pixel must be the same."""
    session = create_session(server, input="fap", fps=30, face=face)
    page, problems = open_page(
        browser, f"{server.url}/#session={session['id']}&token={session['viewer_token']}"
    )
    try:
        wait_for(page, "document.getElementById('status').textContent.includes('watching')")
        page.evaluate("facecast.setQuality({ scale: 0.5 })")
        results = []
        # closed; jaw open; jaw open with the tongue thrust out to its limit and raised (the built-in
        # head's tongue then comes out through the lips and the skin of the chin)
        for faps in (
            {"3": 0.0},
            {"3": 900.0, "5": -500.0},
            {"3": 900.0, "45": 1080.0, "44": 400.0},
        ):
            seen = page.evaluate("facecast.viewer.stats.frames")
            run_async(produce_faps(server, session, [faps]))
            wait_for(page, f"window.facecast.viewer.stats.frames > {seen}")
            gap = page.evaluate(
                f"facecast.renderer.vertex({fp['2.2']})[1] - facecast.renderer.vertex({fp['2.3']})[1]"
            )
            for yaw, pitch in MOUTH_VIEWS:
                r = page.evaluate(TWO_RENDERS_JS, ["scissor", yaw, pitch])
                assert r["face"] > 0.02, f"nothing drawn at {yaw, pitch}"
                assert r["changed"] == 0, (
                    f"the mouth window changed {r['changed']} bytes at {(yaw, pitch)}, FAPs {faps}"
                )
                results.append(
                    {
                        "faps": faps,
                        "view": (yaw, pitch),
                        "window": r["window"],
                        "size": r["size"],
                        "gap": gap,
                    }
                )
        page.evaluate(
            "facecast.renderer.camera.yaw = 0.35; facecast.renderer.camera.pitch = 0.08; facecast.renderer.draw()"
        )
        page.screenshot(path=str(artifacts / f"web_mouth_window_{face}.png"))
        assert not problems, problems
        return results
    finally:
        page.close()


def window_area(r: dict) -> float:
    w = r["window"]
    return (
        0.0
        if w is None
        else max(0, w[2] - w[0]) * max(0, w[3] - w[1]) / (r["size"][0] * r["size"][1])
    )


def test_the_mouth_window_leaves_the_picture_unchanged(server, browser, artifacts):
    fp = load_face("default").feature_points
    results = check_mouth_window(server, browser, artifacts, "default", fp)
    front = [r for r in results if r["view"] == MOUTH_VIEWS[0]]
    assert front[1]["gap"] > front[0]["gap"] + 0.5, "the jaw did not open"
    # the window is in use (the built-in head's shell is closed): small, larger with the mouth open
    assert all(r["window"] is not None for r in front)
    assert 0 < window_area(front[0]) < window_area(front[1]) < 0.1, front


@pytest.mark.slow
def test_the_mouth_window_leaves_the_ict_head_unchanged(browser, data_dir, tmp_path, artifacts):
    from conftest import RunningServer

    mesh = data_dir / "ict-facekit" / "generic_neutral_mesh.obj"
    if not mesh.exists():
        pytest.skip("ICT FaceKit head not in the shared data")
    srv = RunningServer(tmp_path / "data", env={"FACECAST_FACES": f"ict={mesh}"}).start()
    try:
        fp = load_face(str(mesh)).feature_points
        results = check_mouth_window(srv, browser, artifacts, "ict", fp)
    finally:
        srv.stop()
    front = [r for r in results if r["view"] == MOUTH_VIEWS[0]]
    assert all(r["window"] is not None and 0 < window_area(r) < 0.1 for r in front), front
    # from below, the eye sees into the neck opening: the interior is drawn whole
    assert all(r["window"] is None for r in results if r["view"] == MOUTH_VIEWS[2]), results
