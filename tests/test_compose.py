"""docker-compose.yml and the Dockerfile describe the app as the README runs it.

`docker-compose config` (Debian's docker-compose v1, installed by scripts/setup.sh) validates
and normalises the compose file without a Docker engine; the checks read its output.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import tomllib
from pathlib import Path
from typing import Any

import pytest
import yaml

ROOT = Path(__file__).resolve().parent.parent
POSTGRES_URL = "postgresql+psycopg://sepoa:sepoa@postgres:5432/sepoa"


def compose_config(tmp_path: Path, *args: str, **env: str) -> dict[str, Any]:
    """The normalised compose file, as `docker-compose [args] config` prints it."""
    binary = shutil.which("docker-compose")
    if binary is None:
        pytest.fail("docker-compose is not installed: scripts/setup.sh --for-tests installs "
                    "it (apt-get install docker-compose)")
    # Only the variables given here: none from the caller's shell or a stray .env file.
    clean = {k: v for k, v in os.environ.items()
             if not k.startswith(("SEPOA_", "POSTGRES_", "COMPOSE_", "DOCKER_"))}
    env_file = tmp_path / "empty.env"
    env_file.write_text("")
    result = subprocess.run(
        [binary, "--env-file", str(env_file), "-f", str(ROOT / "docker-compose.yml"), *args,
         "config"],
        capture_output=True, text=True, env=clean | env, cwd=ROOT, timeout=60,
    )
    assert result.returncode == 0, f"docker-compose config failed:\n{result.stderr}"
    config: dict[str, Any] = yaml.safe_load(result.stdout)
    return config


def mounts(service: dict[str, Any]) -> set[tuple[str, str]]:
    """(source, target) of each volume, from short ("data:/data:rw") or long syntax."""
    found = set()
    for volume in service.get("volumes", []):
        if isinstance(volume, str):
            source, target = volume.split(":")[:2]
        else:
            source, target = volume.get("source"), volume["target"]
        found.add((source, target))
    return found


def test_api_and_worker_share_the_data_volume_and_the_database(tmp_path: Path) -> None:
    config = compose_config(tmp_path)
    services = config["services"]
    assert {"api", "worker"} <= set(services)
    assert "data" in config["volumes"]
    for name in ("api", "worker"):
        service = services[name]
        assert ("data", "/data") in mounts(service), name
        env = service["environment"]
        assert env["SEPOA_DATA_DIR"] == "/data", name
        # The SQLite file in the shared volume unless SEPOA_DATABASE_URL says otherwise.
        assert env["SEPOA_DATABASE_URL"] == "sqlite:////data/queue.db", name
        assert env["MUJOCO_GL"] == "egl", name
        assert "SEPOA_OPERATOR_TOKEN" in env, name
    assert services["api"]["command"] == ["serve", "--host", "0.0.0.0", "--port", "8000"]
    assert services["worker"]["command"] == ["worker"]


def test_api_publishes_port_8000_and_checks_healthz(tmp_path: Path) -> None:
    api = compose_config(tmp_path)["services"]["api"]
    published = set()
    for port in api["ports"]:
        if isinstance(port, dict):
            published.add((int(port["published"]), int(port["target"])))
        else:
            *_, host, container = str(port).split(":")
            published.add((int(host), int(container.split("/")[0])))
    assert (8000, 8000) in published
    assert any("/healthz" in part for part in api["healthcheck"]["test"])


def test_plain_up_starts_api_and_worker_only_and_postgres_is_a_profile(tmp_path: Path) -> None:
    services = compose_config(tmp_path)["services"]
    assert {name for name, s in services.items() if not s.get("profiles")} == {"api", "worker"}
    postgres = services["postgres"]
    assert postgres["profiles"] == ["postgres"]
    assert postgres["image"].startswith("postgres:16")
    assert "healthcheck" in postgres


def test_the_postgres_profile_points_both_at_one_database(tmp_path: Path) -> None:
    services = compose_config(tmp_path, "--profile", "postgres",
                              SEPOA_DATABASE_URL=POSTGRES_URL)["services"]
    assert "postgres" in services
    for name in ("api", "worker"):
        assert services[name]["environment"]["SEPOA_DATABASE_URL"] == POSTGRES_URL, name


def test_dockerfile_copies_every_package_the_install_needs() -> None:
    # An editable install keeps the packages beside migrations/ and web/, which labelqueue and
    # the server find relative to their own files.
    dockerfile = (ROOT / "Dockerfile").read_text()
    # The sources of each COPY (all words but the last, the destination).
    copied = {word for line in re.findall(r"^COPY\s+(.+)$", dockerfile, re.M)
              for word in line.split()[:-1]}
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    packages = {p.rstrip("*") for p in project["tool"]["setuptools"]["packages"]["find"]["include"]}
    missing = (packages | {"migrations", "web", "pyproject.toml", "README.md"}) - copied
    assert not missing, f"the Dockerfile does not copy {sorted(missing)}"
    assert re.search(r"pip install .*-e \"?\.\[postgres\]", dockerfile)
    assert re.search(r"^ENTRYPOINT \[\"sepoa\"\]", dockerfile, re.M)


def test_workers_scale_and_share_one_results_folder(tmp_path: Path) -> None:
    # `docker-compose up --scale worker=N`: no fixed name or published port on the worker, and
    # every replica writes experiments' runs where `sepoa report` reads them.
    worker = compose_config(tmp_path)["services"]["worker"]
    assert "container_name" not in worker and not worker.get("ports")
    assert worker["environment"]["SEPOA_RESULTS_DIR"] == "/data/results"
    assert ("data", "/data") in mounts(worker)
