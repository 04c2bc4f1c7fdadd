"""The reproducible install (issue "Reliability", item 13): pyproject.toml keeps version ranges for
library users; requirements.lock (what docker/Dockerfile installs) and requirements-test.lock (what
.ci/run installs) pin every package with hashes, and must agree with pyproject.toml and each other."""

from __future__ import annotations

import re
import tomllib
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
# uvicorn[standard]'s extras: the service uses none of them (no websockets, reload, .env or uvloop)
UNUSED_SERVER_EXTRAS = {"uvloop", "httptools", "websockets", "watchfiles"}


def read_lock(name: str) -> dict[str, tuple[str, list[str]]]:
    """package (canonical name) -> (pinned version, hashes)."""
    pins: dict[str, tuple[str, list[str]]] = {}
    current = None
    for line in (ROOT / name).read_text().splitlines():
        if m := re.match(r"^([A-Za-z0-9_.\-]+)==([^\s\\;]+)", line):
            current = canonicalize_name(m.group(1))
            pins[current] = (m.group(2), [])
        elif current and (h := re.search(r"--hash=(sha256:[0-9a-f]{64})", line)):
            pins[current][1].append(h.group(1))
        elif line.strip() and not line.lstrip().startswith("#"):
            assert line.startswith(" "), f"{name}: unexpected line {line!r}"
    return pins


RUNTIME = read_lock("requirements.lock")
TEST = read_lock("requirements-test.lock")


@pytest.mark.parametrize("lock, requirements", [
    (RUNTIME, PYPROJECT["dependencies"]),
    (TEST, PYPROJECT["dependencies"] + PYPROJECT["optional-dependencies"]["test"]),
])
def test_every_declared_dependency_is_pinned_within_its_range(lock, requirements):
    for text in requirements:
        req = Requirement(text)
        name = canonicalize_name(req.name)
        assert name in lock, f"{req.name} is in pyproject.toml but not locked"
        assert req.specifier.contains(lock[name][0], prereleases=True), \
            f"{req.name}=={lock[name][0]} is outside pyproject's {req.specifier}"


def test_every_pin_has_hashes_and_the_test_lock_extends_the_runtime_lock():
    for lock in (RUNTIME, TEST):
        assert all(hashes for _, hashes in lock.values())
    for name, (pinned, _) in RUNTIME.items():
        assert TEST.get(name, (None,))[0] == pinned, f"{name}: the two locks disagree"


def test_the_server_runs_without_uvicorns_standard_extras():
    uvicorn = next(Requirement(r) for r in PYPROJECT["dependencies"] if r.startswith("uvicorn"))
    assert not uvicorn.extras
    assert not UNUSED_SERVER_EXTRAS & set(RUNTIME)


def test_this_environment_runs_the_locked_versions():
    """What the suite passes with is what the lock pins (a drifted environment tests something else)."""
    drifted = {}
    for name, (pinned, _) in TEST.items():
        try:
            installed = version(name)
        except PackageNotFoundError:
            drifted[name] = (pinned, None)
            continue
        if installed != pinned:
            drifted[name] = (pinned, installed)
    assert not drifted, f"(locked, installed): {drifted}; install requirements-test.lock"


def test_the_image_and_ci_install_from_the_locks():
    assert "--require-hashes -r requirements.lock" in (ROOT / "docker" / "Dockerfile").read_text()
    readme = (ROOT / "README.md").read_text().splitlines()
    serve = [line for line in readme if re.fullmatch(r"pip install .*&& python -m service serve", line)]
    test = [line for line in readme if re.fullmatch(r"pip install .*&& python -m pytest -q", line)]
    assert len(serve) == len(test) == 1, "the README's two commands, each on one line"
    assert serve[0].startswith("pip install --require-hashes -r requirements.lock && "
                               "pip install --no-deps -e .")
    assert test[0].startswith("pip install --require-hashes -r requirements-test.lock && "
                              "pip install --no-deps -e .")
    ci = (ROOT / ".ci" / "run").read_text()
    # CI runs those lines as the README writes them (it reads them from README.md)
    assert "grep -m1 -E '^pip install .*&& python -m service serve$' README.md" in ci
    assert "grep -m1 -E '^pip install .*&& python -m pytest -q$' README.md" in ci
