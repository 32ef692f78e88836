"""Runs ``tests/js/read_session.mjs``, which reads an MCAP file with the official TypeScript MCAP reader
(``@mcap/core`` from npm, pinned in ``tests/js/package-lock.json``), and returns the JSON it prints.

The pinned packages are installed with ``npm ci`` into ``tests/js/node_modules`` (not committed) the first
time a test asks for them, and again only when the lock file changes. An exclusive ``flock`` on a lock file
guards the install and a shared one each run of the script, so parallel test runs in one checkout neither
install at once nor see a half-installed tree. Without node and npm, or when the npm registry cannot be
reached, the calling test skips and says what is missing; any other failure fails it.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import re
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:
    from collections.abc import Iterator

JS_DIR = Path(__file__).resolve().parent / "js"
SCRIPT = JS_DIR / "read_session.mjs"
NODE_MODULES = JS_DIR / "node_modules"
#: written into node_modules after a successful install: the hash of the manifests it was installed from
STAMP = NODE_MODULES / ".perfcap-installed"
MISSING = "needs node and npm (apt-get install nodejs npm) and the npm registry"
MIN_NODE_MAJOR = 18
#: far above what either takes on a loaded machine (npm ci: a few seconds; the script: under a second)
INSTALL_TIMEOUT_S = 400.0
RUN_TIMEOUT_S = 180.0

# npm's error codes and messages when the registry cannot be reached (DNS, refused, timeouts, proxies, offline)
_NETWORK_ERROR = re.compile(
    r"ENOTFOUND|EAI_AGAIN|ECONNREFUSED|ECONNRESET|ETIMEDOUT|ESOCKETTIMEDOUT|ENETUNREACH|EHOSTUNREACH|"
    r"ENOTCACHED|ECONNABORTED|EPROTO|ERR_SOCKET|network|proxy|getaddrinfo|socket hang up|"
    r"request to https?://\S+ failed",
    re.IGNORECASE,
)

#: this run's install outcome ("ok", "skip" or "fail", and why): npm ci is tried once per run
_outcome: dict[str, tuple[str, str]] = {}


def _lock_path() -> Path:
    # outside tests/js: npm ci deletes node_modules, and a lock file there would be replaced while held
    key = hashlib.sha256(str(JS_DIR).encode()).hexdigest()[:16]
    return Path(tempfile.gettempdir()) / f"perfcap-js-reader-{key}.lock"


@contextlib.contextmanager
def _locked(exclusive: bool) -> Iterator[None]:
    fd = os.open(_lock_path(), os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH)
        yield
    finally:
        os.close(fd)  # releases the lock


def _manifest_hash() -> str:
    h = hashlib.sha256()
    for name in ("package.json", "package-lock.json"):
        h.update((JS_DIR / name).read_bytes())
    return h.hexdigest()


def _tools() -> tuple[str, str]:
    """The paths of node and npm; skips the test when either is missing or node is too old."""
    node, npm = shutil.which("node"), shutil.which("npm")
    missing = [name for name, path in (("node", node), ("npm", npm)) if path is None]
    if node is None or npm is None:
        pytest.skip(f"{MISSING}: {' and '.join(missing)} not found on PATH")
    out = subprocess.run([node, "--version"], capture_output=True, text=True, timeout=60, check=False)
    m = re.match(r"v(\d+)\.", out.stdout.strip())
    if out.returncode != 0 or m is None:
        pytest.fail(f"`{node} --version` failed (exit {out.returncode}): {out.stdout}{out.stderr}")
    if int(m.group(1)) < MIN_NODE_MAJOR:
        pytest.skip(f"{MISSING}: node {out.stdout.strip()} is older than {MIN_NODE_MAJOR}")
    return node, npm


def _npm_env() -> dict[str, str]:
    env = dict(os.environ)
    env.update(npm_config_update_notifier="false", npm_config_fund="false", npm_config_audit="false",
               npm_config_progress="false", npm_config_loglevel="warn")
    return env


def _install(npm: str) -> None:
    """``npm ci`` the pinned packages unless node_modules already holds exactly them (caller holds the lock)."""
    want = _manifest_hash()
    if STAMP.is_file() and STAMP.read_text().strip() == want:
        return
    cmd = [npm, "ci", "--no-audit", "--no-fund", "--ignore-scripts", "--fetch-retries=2",
           "--fetch-retry-mintimeout=2000", "--fetch-retry-maxtimeout=10000", "--fetch-timeout=60000"]
    try:
        out = subprocess.run(cmd, cwd=JS_DIR, capture_output=True, text=True, timeout=INSTALL_TIMEOUT_S,
                             env=_npm_env(), check=False)
    except subprocess.TimeoutExpired:
        pytest.skip(f"{MISSING}: `npm ci` in {JS_DIR} did not finish in {INSTALL_TIMEOUT_S:.0f} s "
                    "(is the npm registry reachable?)")
    if out.returncode != 0:
        text = (out.stderr + out.stdout).strip()
        tail = "\n".join(text.splitlines()[-15:])
        network = [line.strip() for line in text.splitlines() if _NETWORK_ERROR.search(line)]
        if network:
            pytest.skip(f"{MISSING}: the npm registry is unreachable (`npm ci` in {JS_DIR}: {network[0]})")
        pytest.fail(f"`{' '.join(cmd)}` in {JS_DIR} failed (exit {out.returncode}):\n{tail}")
    for package in ("@mcap/core", "@mcap/support"):
        if not (NODE_MODULES / package / "package.json").is_file():
            pytest.fail(f"`npm ci` in {JS_DIR} succeeded but left no {package} in {NODE_MODULES}")
    STAMP.write_text(want + "\n")


def ensure_installed() -> str:
    """Installs the pinned packages (once per test run) and returns the path of node; skips the test without
    node, npm or the registry."""
    node, npm = _tools()
    if "install" not in _outcome:
        try:
            with _locked(exclusive=True):
                _install(npm)
        except pytest.skip.Exception as e:
            _outcome["install"] = ("skip", str(e.msg))
        except pytest.fail.Exception as e:
            _outcome["install"] = ("fail", str(e.msg))
        else:
            _outcome["install"] = ("ok", "")
    kind, msg = _outcome["install"]
    if kind == "skip":
        pytest.skip(msg)
    if kind == "fail":
        pytest.fail(msg)
    return node


def read_session(path: str | os.PathLike[str]) -> dict[str, Any]:
    """What the TypeScript reader reads in the MCAP file at ``path``, as ``read_session.mjs`` prints it."""
    node = ensure_installed()
    with _locked(exclusive=False):
        try:
            out = subprocess.run([node, str(SCRIPT), os.fspath(path)], cwd=JS_DIR, capture_output=True,
                                 text=True, timeout=RUN_TIMEOUT_S, check=False)
        except subprocess.TimeoutExpired as e:
            raise AssertionError(f"{SCRIPT.name} did not finish reading {path} in {RUN_TIMEOUT_S:.0f} s") from e
    if out.returncode != 0:
        raise AssertionError(f"{SCRIPT.name} {path} exited {out.returncode}:\n{out.stderr}{out.stdout}")
    try:
        report: dict[str, Any] = json.loads(out.stdout)
    except json.JSONDecodeError as e:
        raise AssertionError(f"{SCRIPT.name} {path} printed no JSON ({e}):\n{out.stdout}\n{out.stderr}") from e
    return report
