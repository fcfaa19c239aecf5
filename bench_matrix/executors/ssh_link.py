"""A device reached through the system `ssh` client, which needs no extra dependency and honours what the
user's ssh already knows: ~/.ssh/config (aliases, ProxyJump, ports, users), keys and agents. `BatchMode`
means no password prompt ever appears mid-run; one shared connection per device (ControlMaster) makes each
command after the first cheap."""

from __future__ import annotations

import json
import shlex
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from bench_matrix import __version__
from bench_matrix.errors import UserError

REMOTE = "bench_matrix.executors.ssh_device"  # the module a device runs (python -m)
DEFAULT_PYTHON = "python3"
DEFAULT_WORKSPACE = "~/.cache/bench-matrix-device"
CONNECT_TIMEOUT_S = 10
LOST = 255  # ssh's own exit status: it could not connect, or the connection dropped
PHASE = "bench-matrix phase: "  # a line on the remote command's stderr that names the job's phase
NO_LOGIN = ("Permission denied", "Host key verification failed", "REMOTE HOST IDENTIFICATION HAS CHANGED")


class DeviceUnusable(UserError):
    """The device answers but cannot serve: its Python or bench-matrix is missing, or another version."""

    exit_code = 1


class Unreachable(Exception):
    """ssh could not reach the device, or the connection dropped; the message is ssh's."""


@dataclass(frozen=True)
class Device:
    """A device as `--device` names it: `[user@]host[:port][=python]` (host may be an ssh config alias)."""

    target: str
    port: int | None = None
    python: str = DEFAULT_PYTHON

    @classmethod
    def parse(cls, text: str, python: str = DEFAULT_PYTHON) -> Device:
        address, _, own_python = text.partition("=")
        host, _, port = address.rpartition(":")
        if not host or not port.isdigit():
            host, port = address, ""
        if not host or any(c.isspace() for c in host):
            raise UserError(f"--device {text}: expected [user@]host[:port][=python]")
        return cls(host, int(port) if port else None, own_python or python)

    @property
    def name(self) -> str:
        """How messages and records name the device: as the user typed it, without its Python."""
        return f"{self.target}:{self.port}" if self.port else self.target

    @property
    def argument(self) -> str:
        """The device as `--device` takes it again: with its Python unless that is the default."""
        return self.name if self.python == DEFAULT_PYTHON else f"{self.name}={self.python}"

    @property
    def install(self) -> str:
        """The line that installs this bench-matrix on the device, with its port and its Python."""
        port = f"-p {self.port} " if self.port else ""
        return (f"ssh {port}{shlex.quote(self.target)} {shlex.quote(self.python)} -m pip install "
                f"'bench-matrix=={__version__}'")


@dataclass(frozen=True)
class Link:
    """Commands of `python -m bench_matrix.executors.ssh_device WORKSPACE ...` on one device."""

    device: Device
    workspace: str  # on the device; a leading ~ is its user's home
    config: Path | None  # an ssh config file instead of ~/.ssh/config
    control: Path  # the folder of the shared connection's socket

    def argv(self, *command: str) -> list[str]:
        """The ssh command line running `command` of the device's module."""
        remote = shlex.join([self.device.python, "-m", REMOTE, self.workspace, *command])
        return ["ssh", *self.options(), self.device.target, remote]

    def options(self) -> list[str]:
        """ssh's options: never a prompt, a bounded wait to connect, a dropped connection noticed, one
        connection shared."""
        options = ["-o", "BatchMode=yes", "-o", f"ConnectTimeout={CONNECT_TIMEOUT_S}",
                   "-o", "ServerAliveInterval=5", "-o", "ServerAliveCountMax=3",
                   "-o", "ControlMaster=auto", "-o", f"ControlPath={self.control}/%C",
                   "-o", "ControlPersist=60"]
        options += ["-F", str(self.config)] if self.config else []
        return options + (["-p", str(self.device.port)] if self.device.port else [])

    def call(self, *command: str, timeout_s: float = 300) -> Any:
        """Run a command on the device and return what it printed (JSON); Unreachable or UserError when
        it could not run."""
        try:
            done = subprocess.run(self.argv(*command), stdin=subprocess.DEVNULL, capture_output=True,
                                  timeout=timeout_s)
        except subprocess.TimeoutExpired:
            raise Unreachable(f"no answer within {timeout_s:g} s") from None
        stderr = done.stderr.decode(errors="replace")
        if done.returncode != 0:
            raise self.failure(done.returncode, stderr)
        return json.loads(done.stdout)

    def hello(self) -> dict[str, Any]:
        """The device's Python, bench-matrix, host and environment; DeviceUnusable when it cannot serve,
        Unreachable or a UserError when ssh cannot log in."""
        try:
            answer = self.call("hello", timeout_s=60)
        except RuntimeError as exc:
            raise DeviceUnusable(str(exc)) from None
        if answer["bench_matrix"] != __version__:
            raise DeviceUnusable(f"device {self.device.name} has bench-matrix {answer['bench_matrix']}, this "
                                 f"machine {__version__}: install the same there: {self.device.install}")
        return answer

    def start(self, out: IO[bytes]) -> subprocess.Popen:
        """`run` on the device, reading its request from the returned process's stdin (kept open: closing it
        stops the remote job), its answer into `out`, its stderr a pipe (phases as they come)."""
        return subprocess.Popen(self.argv("run"), stdin=subprocess.PIPE, stdout=out, stderr=subprocess.PIPE)

    def failure(self, code: int, stderr: str) -> Exception:
        """Why a command failed: Unreachable (no connection), a UserError (no login), DeviceUnusable (no
        Python or bench-matrix there), or a RuntimeError naming the device's last words."""
        last = last_words(stderr)
        name, python = self.device.name, self.device.python
        if code == LOST and any(text in stderr for text in NO_LOGIN):
            return UserError(f"device {name}: ssh cannot log in ({last}); set up key login so that "
                             f"`ssh -o BatchMode=yes {self.device.target} true` works (docs/devices.md)")
        if code == LOST:
            return Unreachable(last)
        if code == 127:
            return DeviceUnusable(f"device {name}: its Python {python!r} was not found ({last}); name "
                                  "another with --device-python or --device HOST=PYTHON")
        if "No module named 'bench_matrix'" in stderr:
            return DeviceUnusable(f"device {name}: bench-matrix is not installed for {python}; install "
                                  f"it: {self.device.install}")
        if "No module named 'bench_matrix." in stderr:
            return DeviceUnusable(f"device {name}: its bench-matrix is older than {__version__} (it has no "
                                  f"SSH executor); install this one: {self.device.install}")
        return RuntimeError(f"device {name}: exit code {code}: {last}")

    def close(self) -> None:
        """End the shared connection."""
        subprocess.run(["ssh", *self.options(), "-O", "exit", self.device.target], stdin=subprocess.DEVNULL,
                       capture_output=True, timeout=30)


def last_words(stderr: str) -> str:
    """The last line of what ssh or the device's command wrote to stderr."""
    lines = [line.strip() for line in stderr.splitlines() if line.strip() and not line.startswith(PHASE)]
    return lines[-1] if lines else "(nothing on stderr)"
