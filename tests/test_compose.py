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


def interpolate(text: str, env: dict[str, str]) -> str:
    """Compose's variable substitution: ``${X}``, ``${X:-default}``, ``${X:?error}``, ``$$`` -> ``$``."""

    def one(m: re.Match) -> str:
        name, op, arg = m.group(1), m.group(2) or "", m.group(3) or ""
        if env.get(name):
            return env[name]
        if op == ":?":
            raise KeyError(f"{name}: {arg}")
        return arg

    text = re.sub(r"(?<!\$)\$\{(\w+)(?:(:-|:\?)([^}]*))?\}", one, text)
    return text.replace("$$", "$")


def node() -> dict:
    return compose()["services"]["facecast"]


def test_compose_runs_redis_nodes_and_a_balancer_with_shared_volumes():
    doc = compose()
    assert {"redis", "facecast", "lb"} <= set(doc["services"])
    svc = node()
    assert svc["build"]["context"] == "."
    assert (ROOT / svc["build"].get("dockerfile", "Dockerfile")).is_file()
    mounts = dict(reversed(v.split(":")[:2]) for v in svc["volumes"])
    assert mounts["/data"] in doc["volumes"], "the data directory must be a named volume"
    assert mounts["/results"] in doc["volumes"], "job results go to a volume all nodes share"
    assert svc["environment"]["FACECAST_RESULTS_DIR"] == "/results"
    test = " ".join(svc["healthcheck"]["test"])
    assert "/healthz" in test and ":8000" in test
    assert svc["depends_on"]["redis"]["condition"] == "service_healthy"
    redis = doc["services"]["redis"]
    assert redis["image"].startswith("redis:") and "ping" in redis["healthcheck"]["test"]


def test_the_node_service_scales():
    """``docker compose up --scale facecast=3`` needs a node with no fixed name and no host port."""
    svc = node()
    assert "container_name" not in svc and "ports" not in svc
    assert [str(p) for p in svc["expose"]] == ["8000"]
    assert "deploy" not in svc or "replicas" not in svc["deploy"]


def test_nodes_share_redis_and_the_admin_key_from_the_environment():
    env = node()["environment"]
    assert env["FACECAST_REDIS_URL"].startswith("redis://redis:6379")
    assert env["FACECAST_ALLOW_REMOTE"] == "true" and env["FACECAST_HOST"] == "0.0.0.0"
    key = env["FACECAST_ADMIN_KEY"]
    assert interpolate(key, {"FACECAST_ADMIN_KEY": "k" * 32}) == "k" * 32
    try:  # no key: Compose refuses to start rather than let each node make its own
        interpolate(key, {})
        raise AssertionError("an unset FACECAST_ADMIN_KEY must stop docker compose")
    except KeyError as e:
        assert "FACECAST_ADMIN_KEY" in str(e)


def test_the_node_command_and_environment_are_accepted_by_facecast_serve(monkeypatch):
    from facecast.server.cli import build_parser
    from facecast.server.commands.serve import make_config

    svc = node()
    for k, v in svc["environment"].items():
        monkeypatch.setenv(k, interpolate(str(v), {"FACECAST_ADMIN_KEY": "k" * 32}))
    cmd = svc["command"]
    assert cmd[:2] == ["facecast", "serve"]
    cfg = make_config(build_parser(cmd[1:]).parse_args(cmd[1:]))
    assert (cfg.host, cfg.port, str(cfg.data_dir), cfg.allow_remote) == (
        "0.0.0.0",
        8000,
        "/data",
        True,
    )
    assert cfg.redis_url == "redis://redis:6379/0" and str(cfg.results_dir) == "/results"
    assert cfg.admin_key == "k" * 32


def lb_config() -> str:
    doc = compose()
    lb = doc["services"]["lb"]
    (cfg,) = lb["configs"]
    assert cfg["target"] == "/etc/nginx/conf.d/default.conf" and lb["image"].startswith("nginx:")
    return interpolate(doc["configs"][cfg["source"]]["content"], {})


def test_the_balancer_publishes_8000_on_loopback_and_round_robins_over_the_nodes():
    lb = compose()["services"]["lb"]
    assert [str(p) for p in lb["ports"]] == ["127.0.0.1:8000:8000"]
    text = lb_config()
    # Docker's DNS, re-resolved: scaled nodes join without a restart of the balancer
    assert re.search(r"^resolver 127\.0\.0\.11 valid=\d+s", text, re.MULTILINE)
    up = re.search(r"upstream (\w+) \{(.*?)\}", text, re.DOTALL)
    assert up, text
    assert re.search(r"server facecast:8000 resolve\b", up.group(2)) and "zone" in up.group(2)
    assert "hash" not in up.group(2) and "ip_hash" not in up.group(2)  # plain round robin
    assert f"proxy_pass http://{up.group(1)};" in text
    assert "listen 8000;" in text
    assert re.search(r"client_max_body_size 67108864;", text)


def test_the_balancer_passes_websocket_upgrades_and_keeps_them_open():
    text = lb_config()
    assert "proxy_http_version 1.1;" in text
    assert "proxy_set_header Upgrade $http_upgrade;" in text
    assert "proxy_set_header Connection $connection_upgrade;" in text
    assert re.search(r"map \$http_upgrade \$connection_upgrade \{[^}]*default upgrade;", text)
    assert re.search(r"proxy_read_timeout (\d+)(h|m);", text)
    assert "proxy_buffering off;" in text


def test_docker_compose_config_accepts_the_file():
    """``docker compose config`` where the Compose plugin is installed (it is not everywhere)."""
    import os
    import shutil
    import subprocess

    import pytest

    if shutil.which("docker") is None:
        pytest.skip("no docker CLI")
    version = subprocess.run(["docker", "compose", "version"], capture_output=True, text=True)
    if "Compose" not in version.stdout:
        pytest.skip("the docker CLI has no compose plugin")
    env = {**os.environ, "FACECAST_ADMIN_KEY": "k" * 32}
    r = subprocess.run(
        ["docker", "compose", "config", "--quiet"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr


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
