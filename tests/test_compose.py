"""The container files: no container engine runs here, so check their structure and what they run."""

from __future__ import annotations

import re
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]


def compose() -> dict:
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())


def dockerfile_instructions() -> list[tuple[str, str]]:
    """``(INSTRUCTION, arguments)`` with line continuations joined and comments dropped."""
    text = re.sub(r"\\\n", " ", (ROOT / "Dockerfile").read_text())
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            word, _, rest = line.partition(" ")
            out.append((word.upper(), rest.strip()))
    return out


def test_compose_defines_the_facecast_service_with_a_data_volume_and_healthcheck():
    doc = compose()
    svc = doc["services"]["facecast"]
    assert svc["build"]["context"] == "."
    assert (ROOT / svc["build"].get("dockerfile", "Dockerfile")).is_file()
    mounts = [v.split(":") for v in svc["volumes"]]
    data = [m for m in mounts if m[1] == "/data"]
    assert data and data[0][0] in doc["volumes"], "the data directory must be a named volume"
    test = " ".join(svc["healthcheck"]["test"])
    assert "/healthz" in test and ":8000" in test
    for port in svc["ports"]:
        assert str(port).split(":")[-1] == "8000"


def test_compose_command_binds_all_interfaces_only_with_allow_remote():
    cmd = compose()["services"]["facecast"]["command"]
    assert cmd[:2] == ["facecast", "serve"]
    assert cmd[cmd.index("--host") + 1] == "0.0.0.0" and "--allow-remote" in cmd
    assert cmd[cmd.index("--data-dir") + 1] == "/data"
    assert cmd[cmd.index("--port") + 1] == "8000"


def test_compose_command_is_accepted_by_facecast_serve():
    from facecast.server.cli import build_parser

    cmd = compose()["services"]["facecast"]["command"]
    args = build_parser(cmd[1:]).parse_args(cmd[1:])
    from facecast.server.commands.serve import make_config

    cfg = make_config(args)
    assert (cfg.host, cfg.port, str(cfg.data_dir), cfg.allow_remote) == (
        "0.0.0.0",
        8000,
        "/data",
        True,
    )


def test_dockerfile_installs_debian_pocl_and_runs_facecast_serve():
    ins = dockerfile_instructions()
    base = [a for i, a in ins if i == "FROM"]
    assert base and re.search(r"(bookworm|trixie|debian)", base[0]), base
    runs = " ".join(a for i, a in ins if i == "RUN")
    assert re.search(r"apt-get install[^&;]*\bpocl-opencl-icd\b", runs)
    assert re.search(r"pip install[^&;]* \.", runs)
    cmd = [a for i, a in ins if i == "CMD"][-1]
    words = yaml.safe_load(cmd)  # JSON exec form
    assert words[:2] == ["facecast", "serve"] and "--allow-remote" in words
    health = [a for i, a in ins if i == "HEALTHCHECK"]
    assert health and "/healthz" in health[0]
    assert any(i == "VOLUME" and "/data" in a for i, a in ins)
    assert any(i == "USER" and a != "root" for i, a in ins)


def test_dockerignore_keeps_the_build_context_small():
    ignored = (ROOT / ".dockerignore").read_text().split()
    assert ".git" in ignored and "tests/artifacts" in ignored


def test_dockerfile_copies_what_pip_install_needs():
    import tomllib

    copied = set()
    for ins, args in dockerfile_instructions():
        if ins == "COPY":
            copied.update(p.rstrip("/").removeprefix("./") for p in args.split()[:-1])
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    needed = {"pyproject.toml", "setup.py", project["readme"], "protocol", "server", "client"}
    assert needed <= copied, needed - copied
    ignored = {line.strip() for line in (ROOT / ".dockerignore").read_text().splitlines()}
    assert not needed & ignored
