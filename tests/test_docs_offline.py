"""``/docs`` and ``/redoc`` work offline: their scripts come from the server, not from a CDN."""

from __future__ import annotations

import re
import shutil
from pathlib import Path
from urllib.parse import urlparse

import pytest
from conftest import RunningServer
from fastapi.testclient import TestClient

from facecast.server.api.app import create_app
from facecast.server.api.config import ServerConfig

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    app = create_app(
        ServerConfig(
            data_dir=tmp_path_factory.mktemp("docs"), admin_key="k", job_workers=0, backend="numpy"
        )
    )
    return TestClient(app)


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_docs_pages_reference_no_external_host_and_their_assets_load(client, page):
    resp = client.get(page)
    assert resp.status_code == 200 and resp.headers["content-type"].startswith("text/html")
    refs = re.findall(r"""(?:src|href)\s*=\s*["']([^"']+)["']""", resp.text)
    assert refs, resp.text
    assert not re.search(r"https?://|//[a-z]", resp.text, re.IGNORECASE), (
        "the page names an external host"
    )
    for ref in refs:
        assert not urlparse(ref).netloc, ref
        asset = client.get(ref)
        assert asset.status_code == 200 and len(asset.content) > 1000, ref
    assert "openapi.json" in resp.text


def test_only_the_docs_assets_are_served(client):
    assert client.get("/docs-assets/swagger-ui.css").headers["content-type"].startswith("text/css")
    for name in ("core.py", "..%2Fcore.py", "__init__.py"):
        resp = client.get(f"/docs-assets/{name}")
        assert resp.status_code == 404 and resp.json()["error"]


@pytest.mark.browser
@pytest.mark.skipif(not Path(CHROMIUM).exists(), reason="Debian chromium not installed")
def test_swagger_ui_renders_the_api_with_no_network(tmp_path):
    from playwright.sync_api import sync_playwright

    srv = RunningServer(tmp_path, "--face", "default:2k", "--job-workers", "0").start()
    outside: list[str] = []
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(
                executable_path=CHROMIUM, args=["--no-sandbox", "--disable-gpu"]
            )
            try:
                page = browser.new_page()

                def only_loopback(route):
                    if urlparse(route.request.url).hostname in ("127.0.0.1", "localhost"):
                        return route.continue_()
                    outside.append(route.request.url)
                    return route.abort()

                page.route("**/*", only_loopback)  # as on a machine with no internet access
                page.goto(srv.url + "/docs")
                page.wait_for_selector(".opblock", timeout=60_000)  # the operations are listed
                text = page.inner_text("#swagger-ui")
                assert "/v1/jobs" in text and "/v1/faces" in text
            finally:
                browser.close()
    finally:
        srv.stop()
    assert outside == [], outside
