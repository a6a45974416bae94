"""docker-compose.yml and the Dockerfile, checked by parsing (no docker daemon or compose plugin here).

Compose: PostgreSQL, the migration, the API, the daemon and the job workers; every long-running
service has a healthcheck, and every dependency waits on a condition (healthy, or the migration
completed); the workers scale (no fixed name, no published port).
Dockerfile: a non-root user, the API port exposed, ``driftlab`` as the entrypoint, a wheel install.
The image's commands are driftlab subcommands, so each compose command must parse as one.
"""

from __future__ import annotations

import json
import shlex
from pathlib import Path

import pytest
import yaml

from driftlab.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())


def _dockerfile() -> list[tuple[str, str]]:
    """Return (INSTRUCTION, arguments) of the Dockerfile, continuation lines joined."""
    text = (ROOT / "Dockerfile").read_text().replace("\\\n", " ")
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            word, _, rest = line.partition(" ")
            out.append((word.upper(), rest.strip()))
    return out


def test_compose_services_healthchecks_and_conditions(compose: dict) -> None:
    services = compose["services"]
    assert {"postgres", "migrate", "api", "daemon", "worker"} <= set(services)
    for name in ("postgres", "api", "daemon", "worker"):
        check = services[name].get("healthcheck")
        assert check and check.get("test"), f"{name} has no healthcheck"
    for name in ("migrate", "api", "daemon", "worker"):
        deps = services[name]["depends_on"]
        assert isinstance(deps, dict), f"{name}: depends_on must name conditions"
        for dep, spec in deps.items():
            assert dep in services
            assert spec["condition"] in ("service_healthy", "service_completed_successfully"), (name, dep)
        assert deps["postgres"]["condition"] == "service_healthy"
    for name in ("api", "daemon", "worker"):
        assert services[name]["depends_on"]["migrate"]["condition"] == "service_completed_successfully"
        assert services[name]["environment"]["DRIFTLAB_DB_URL"].startswith("postgresql+psycopg://")
    health = services["api"]["healthcheck"]["test"][-1]
    assert "8765" in health and "/health" in health
    assert all(p.startswith("127.0.0.1:") for s in services.values() for p in s.get("ports", []))


def test_compose_workers_scale(compose: dict) -> None:
    """`docker compose up --scale worker=4`: replicas need no fixed name and publish no port."""
    worker = compose["services"]["worker"]
    assert "container_name" not in worker and "ports" not in worker
    args = build_parser().parse_args(worker["command"])
    assert args.func.__module__ == "driftlab.commands.worker" and args.concurrency >= 1
    assert "--no-jobs" in compose["services"]["api"]["command"]  # the API queues, the workers run


def test_compose_commands_are_driftlab_subcommands(compose: dict) -> None:
    parser = build_parser()
    for name in ("migrate", "api", "daemon", "worker"):
        args = parser.parse_args(compose["services"][name]["command"])
        assert getattr(args, "func", None) is not None, name
    check = compose["services"]["daemon"]["healthcheck"]["test"]
    assert check[:2] == ["CMD", "driftlab"] and build_parser().parse_args(check[2:]).func


def test_dockerfile_runs_as_a_user_with_a_port_and_an_entrypoint() -> None:
    steps = _dockerfile()
    kinds = [k for k, _ in steps]
    users = [v for k, v in steps if k == "USER"]
    assert users and users[-1] not in ("root", "0"), "the image must not run as root"
    assert kinds.index("USER") > max(i for i, k in enumerate(kinds) if k == "RUN"), "USER after the last RUN"
    assert any(k == "EXPOSE" and "8765" in v.split() for k, v in steps)
    [entry] = [v for k, v in steps if k == "ENTRYPOINT"]
    assert json.loads(entry) == ["driftlab"]
    [cmd] = [v for k, v in steps if k == "CMD"]
    assert build_parser().parse_args(json.loads(cmd)).func
    run = " ".join(v for k, v in steps if k == "RUN")
    assert "pip install" in run and " -e " not in f" {run} ", "install the wheel, not an editable checkout"
    assert any(k == "HEALTHCHECK" for k in kinds)
    for _, value in steps:
        assert "ENTRYPOINT []" not in value
    assert shlex.split(dict(steps)["FROM"])[0].startswith("python:")


def test_compose_holds_no_password(compose: dict) -> None:
    """Passwords come from the environment (or an .env file), never from this file (issue 24)."""
    text = (ROOT / "docker-compose.yml").read_text()
    for service in compose["services"].values():
        env = service.get("environment") or {}
        for key, value in env.items():
            if "PASSWORD" in key:
                assert str(value).startswith("${"), (key, value)
            if key == "DRIFTLAB_DB_URL":
                userinfo = str(value).split("://", 1)[1].split("@", 1)[0]
                assert userinfo.split(":", 1)[1].startswith("${"), value
    assert "driftlab:driftlab@" not in text


def test_compose_healthchecks_of_portless_services_are_driftlab_health(compose: dict) -> None:
    parser = build_parser()
    for name, flag in (("daemon", "daemon"), ("worker", "worker")):
        check = compose["services"][name]["healthcheck"]["test"]
        assert check[:3] == ["CMD", "driftlab", "health"], name
        args = parser.parse_args(check[2:])
        assert args.func.__module__ == "driftlab.commands.health" and getattr(args, flag)
    assert compose["services"]["migrate"]["healthcheck"] == {"disable": True}  # one-shot: checked by completion


def test_compose_passes_the_daemons_instruments_through(compose: dict) -> None:
    devices = compose["services"]["daemon"]["devices"]
    inside = {d.rsplit(":", 1)[1] for d in devices}
    assert {"/dev/driftlab-machine", "/dev/driftlab-probe", "/dev/gpib0", "/dev/driftlab-daq"} <= inside
    assert all(d.startswith("${DRIFTLAB_") and ":-/dev/null}" in d for d in devices)  # unset: the demo's /dev/null
    assert "dialout" in compose["services"]["daemon"]["group_add"]
