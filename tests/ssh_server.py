"""A real OpenSSH server on 127.0.0.1 for the SSH executor's tests: its own host key, key-only login as the
current user, an ssh config file for the client, and device Pythons (wrapper scripts) standing for a device:
this machine's venv with its own host name, timing lock and environment."""

from __future__ import annotations

import getpass
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

SSHD = shutil.which("sshd") or "/usr/sbin/sshd"
PRIVILEGE_SEPARATION = Path("/run/sshd")  # Debian's sshd refuses to start as root without it


@dataclass
class Server:
    """A running sshd: its port, the client's ssh config file, the process (its own process group)."""

    port: int
    config: Path
    proc: subprocess.Popen

    @property
    def device(self) -> str:
        return device_at(self.port)

    def drop_connections(self) -> None:
        """Kill the processes serving its connections (sshd forks them, each in a session of its own), as a
        cut network would end them; the commands they run are left to notice. The server listens on."""
        _kill(_descendants(self.proc.pid, "sshd"))

    def kill(self) -> None:
        """Kill the server and every connection it serves."""
        self.drop_connections()
        _kill([self.proc.pid])
        self.proc.wait()


def _kill(pids: list[int]) -> None:
    for pid in pids:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def processes() -> dict[int, tuple[int, str, str]]:
    """Every process: its id -> its parent's, its name, its command line."""
    found = {}
    for entry in Path("/proc").glob("[0-9]*"):
        try:
            stat = (entry / "stat").read_text()
            command = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        name, fields = stat[stat.index("(") + 1:stat.rindex(")")], stat[stat.rindex(")") + 2:].split()
        found[int(entry.name)] = (int(fields[1]), name, command)
    return found


def _descendants(root: int, name: str) -> list[int]:
    """The processes called `name` below `root`."""
    table = processes()
    below, found = {root}, True
    while found:
        found = {pid for pid, (parent, _, _) in table.items() if parent in below and pid not in below}
        below |= found
    return [pid for pid in below - {root} if table.get(pid, (0, "", ""))[1] == name]


def device_at(port: int) -> str:
    """The current user at 127.0.0.1:port, as --device names it."""
    return f"{getpass.getuser()}@127.0.0.1:{port}"


def why_no_sshd() -> str | None:
    """Why sshd cannot run here, or None."""
    if not Path(SSHD).is_file() or shutil.which("ssh") is None or shutil.which("ssh-keygen") is None:
        return "OpenSSH server or client not installed (apt-get install openssh-server openssh-client)"
    if os.geteuid() == 0 and not PRIVILEGE_SEPARATION.is_dir():
        try:
            PRIVILEGE_SEPARATION.mkdir(mode=0o755)
        except OSError as exc:
            return f"sshd needs {PRIVILEGE_SEPARATION} as root and it cannot be made: {exc}"
    return None


def start_server(root: Path) -> Server:
    """sshd on a free loopback port with a key pair of its own under `root`; the client's config beside."""
    root.mkdir(parents=True, exist_ok=True)
    for name in ("host_key", "client_key"):
        if not (root / name).exists():
            subprocess.run(["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-f", str(root / name)],
                           check=True)
    (root / "authorized_keys").write_text((root / "client_key.pub").read_text())
    port = free_port()
    (root / "sshd_config").write_text(
        f"Port {port}\nListenAddress 127.0.0.1\nHostKey {root / 'host_key'}\n"
        f"AuthorizedKeysFile {root / 'authorized_keys'}\nPidFile {root / 'sshd.pid'}\n"
        "StrictModes no\nUsePAM no\nPasswordAuthentication no\nKbdInteractiveAuthentication no\n"
        "PubkeyAuthentication yes\nPermitRootLogin prohibit-password\nLogLevel ERROR\n")
    (root / "ssh_config").write_text(
        f"Host *\n  IdentityFile {root / 'client_key'}\n  IdentitiesOnly yes\n  StrictHostKeyChecking no\n"
        "  UserKnownHostsFile /dev/null\n  LogLevel ERROR\n")
    log = open(root / "sshd.log", "ab")
    proc = subprocess.Popen([SSHD, "-D", "-e", "-f", str(root / "sshd_config")], stdout=log,
                            stderr=subprocess.STDOUT)
    server = Server(port, root / "ssh_config", proc)
    _wait_listening(server, root / "sshd.log")
    return server


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_listening(server: Server, log: Path) -> None:
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        if server.proc.poll() is not None:
            raise RuntimeError(f"sshd exited: {log.read_text(errors='replace').strip()}")
        try:
            socket.create_connection(("127.0.0.1", server.port), timeout=1).close()
            return
        except OSError:
            time.sleep(0.05)
    server.kill()
    raise RuntimeError("sshd did not listen within 10 s")


def device_python(path: Path, host: str, lock: Path, variables: dict[str, str] | None = None) -> Path:
    """A script standing for a device's Python: this venv's, with the device's host name, timing lock and
    environment `variables` (sshd gives commands a clean environment)."""
    lines = [f"export BENCH_MATRIX_HOST={host} BENCH_MATRIX_LOCK_DIR={lock}"]
    lines += [f"export {k}='{v}'" for k, v in (variables or {}).items()]
    path.write_text("#!/bin/sh\n" + "\n".join(lines) + f'\nexec {sys.executable} "$@"\n')
    path.chmod(0o755)
    return path


def jetson_path(folder: Path) -> dict[str, str]:
    """A PATH whose `nvpmodel` answers as a Jetson's does: the environment of a device standing for one."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "nvpmodel").write_text("#!/bin/sh\necho 'NV Power Mode: MAXN'\necho 0\n")
    (folder / "nvpmodel").chmod(0o755)
    return {"PATH": f"{folder}:{os.environ['PATH']}"}
