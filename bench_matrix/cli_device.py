"""SSH devices on the command line: `run --executor ssh --device ...` and its options, and `device check`
(docs/devices.md)."""

from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path
from typing import Any

from bench_matrix import __version__
from bench_matrix.executors.ssh_link import DEFAULT_PYTHON, DEFAULT_WORKSPACE


def add_device_options(parser: argparse.ArgumentParser, many: bool = True) -> None:
    """How devices are reached: --device (repeatable on `run`), their Python, workspace and ssh config."""
    group = parser.add_argument_group("SSH devices (--executor ssh; docs/devices.md)")
    if many:
        group.add_argument("--device", action="append", default=[], metavar="[USER@]HOST[:PORT][=PYTHON]",
                           help="measure on this device over ssh (repeatable; HOST may be an ssh config "
                                "alias)")
    group.add_argument("--device-python", default=DEFAULT_PYTHON, metavar="PYTHON",
                       help="the devices' Python, with bench-matrix installed (default: %(default)s)")
    group.add_argument("--device-workspace", default=DEFAULT_WORKSPACE, metavar="DIR",
                       help="the devices' own workspace: shipped files, logs (default: %(default)s)")
    group.add_argument("--ssh-config", type=Path, metavar="FILE",
                       help="an ssh config file to use instead of ~/.ssh/config")


def ssh_options(args: argparse.Namespace, devices: list[str]) -> Any:
    """The SshOptions the arguments give."""
    from bench_matrix.executors.ssh_executor import SshOptions
    from bench_matrix.executors.ssh_link import Device

    ssh_config = args.ssh_config.resolve() if args.ssh_config else None
    return SshOptions(tuple(Device.parse(d, args.device_python) for d in devices), args.device_workspace,
                      ssh_config)


def add_device_command(sub: Any) -> None:
    device = sub.add_parser("device", help="SSH devices: `device check HOST` says what a device can run")
    commands = device.add_subparsers(dest="device_command", required=True, metavar="COMMAND")
    check = commands.add_parser("check", help="log in, compare versions, probe backends and targets; exit 0 "
                                              "when the device is usable, 1 when not, 2 when unreachable")
    check.add_argument("target", metavar="[USER@]HOST[:PORT][=PYTHON]", nargs="?",
                       help="the device; without one, how noisy this machine is for timing")
    check.add_argument("--seconds", type=float, default=10.0,
                       help="without a device: seconds of timed windows (default: %(default)s)")
    check.add_argument("--json", action="store_true", help="without a device: the check as JSON")
    add_device_options(check, many=False)
    check.set_defaults(handler=_check)


def _here(args: argparse.Namespace, console) -> int:
    """This machine's noise for timing (docs/devices.md §8)."""
    from bench_matrix.errors import UserError
    from bench_matrix.machine_check import check_here, show

    if not 0 < args.seconds <= 600:
        raise UserError(f"--seconds must be more than 0 and at most 600, got {args.seconds:g}")
    show(check_here(args.seconds), console, args.json)
    return 0


def _check(args: argparse.Namespace, console) -> int:
    if args.target is None:
        return _here(args, console)
    from bench_matrix.errors import UserError
    from bench_matrix.executors.ssh_link import Link, Unreachable

    options = ssh_options(args, [args.target])
    control = Path(tempfile.mkdtemp(prefix="bm-ssh-"))
    link = Link(options.devices[0], options.workspace, options.config, control)
    try:
        hello = link.hello()
        console.print(f"[bold]device {link.device.name}[/]: logged in; host {hello['host']}", highlight=False)
        _show_environment(console, hello, link.device.python)
        usable = _show_backends(console, link, args.workspace)
        if emulated := hello["env"].get("emulated"):
            console.print(f"[yellow]{emulated}[/]: records and reports mark every timing measured there",
                          highlight=False)
        return usable
    except Unreachable as exc:
        raise UserError(f"device {link.device.name} is unreachable: {exc}") from None
    finally:
        link.close()
        shutil.rmtree(control, ignore_errors=True)


def _show_environment(console, hello: dict[str, Any], python: str) -> None:
    env = hello["env"]
    gpus = ", ".join(str(g.get("name", g)) if isinstance(g, dict) else str(g) for g in env["gpus"]) or "none"
    rows = [("python", f"{hello['python']} ({python})"),
            ("bench-matrix", f"{hello['bench_matrix']} (the same as here: {__version__})"),
            ("os", env["os"]), ("cpu", f"{env['cpu']}, {env['cores']} cores, {env['memory_gb']} GB memory"),
            *_cpu_rows(env), ("gpus", gpus)]
    if jetson := env.get("jetson"):
        rows += [("power mode", jetson["nvpmodel"]),
                 ("clocks", ", ".join(f"{k} {v}" for k, v in jetson["clocks"].items()))]
    for label, value in rows:
        console.print(f"  {label:<13}{value}", highlight=False, markup=False, soft_wrap=True)


def _cpu_rows(env: dict[str, Any]) -> list[tuple[str, str]]:
    """The CPU's architecture, the features that matter (those it lacks too) and whether it is emulated."""
    from bench_matrix.measure.cpu import ARM, ARM_FEATURES, X86_FEATURES

    arch, has = env.get("arch", "unknown"), env.get("cpu_features", [])
    known = (ARM_FEATURES if arch in ARM else X86_FEATURES).values()
    lacks = [name for name in known if name not in has]
    features = (", ".join(has) or "none of note") + (f" (not: {', '.join(lacks)})" if lacks else "")
    rows = [("arch", arch), ("cpu features", features)]
    return rows + [("emulated", env["emulated"])] if env.get("emulated") else rows


def _show_backends(console, link: Any, workspace: Path) -> int:
    """Each backend's targets as the device's probe rules on them; 1 when probing failed."""
    from bench_matrix.executors.base import Limits, Work
    from bench_matrix.executors.local import PROBE_TIMEOUT_S
    from bench_matrix.executors.ssh_flight import Flight
    from bench_matrix.jobs import ProbeJob
    from bench_matrix.plan_view import target_status
    from bench_matrix.registry import available, vocabulary
    from bench_matrix.workspace import Workspace

    ws = Workspace(workspace)
    names = tuple(available())
    job = ProbeJob(ws, names, measure_only=True)
    ended = Flight(Work(job, Limits(ws.log("probe"), PROBE_TIMEOUT_S)), link, link.device.name,
                   lambda _: None).wait()
    if not ended.ok:
        console.print(f"  [red]probing the backends there failed:[/] {ended.error}", highlight=False)
        return 1
    described, rulings = ended.result.backends, ended.result.rulings
    for name in names:
        if error := described.get(name, {}).get("error"):
            console.print(f"  [bold]{name}[/]: [red]cannot be loaded there:[/] {error}", highlight=False)
            continue
        statuses = [f"{target}: {target_status(name, target, rulings)}" for target in vocabulary().targets
                    if "not supported" not in target_status(name, target, rulings)]
        console.print(f"  [bold]{name}[/]: " + "; ".join(statuses), highlight=False, soft_wrap=True)
    console.print("[green]usable[/]: `bench-matrix run MATRIX --executor ssh --device "
                  f"{link.device.argument}` measures there", highlight=False)
    return 0
