"""Interference with a timed phase, from what the operating system reports: this process's involuntary context
switches (getrusage), CPU time other processes took (/proc/stat busy time minus our own) and CPU steal."""

from __future__ import annotations

import os
import resource
import time
from dataclasses import dataclass

CLOCK_TICKS = os.sysconf("SC_CLK_TCK")  # /proc/stat counts in these units per second
BUSY_FIELDS = (0, 1, 2, 5, 6)  # user, nice, system, irq, softirq (guest time is already inside user)
STEAL_FIELD = 7
JUDGED_FROM_S = 40 / CLOCK_TICKS  # /proc/stat counts whole ticks: a shorter window's shares are judged with
COUNTING_ERROR_S = 2 / CLOCK_TICKS  # this much (two ticks per CPU) taken off, so that only gross work counts


@dataclass(frozen=True)
class Limits:
    """Above any of these, a timed phase counts as disturbed (chosen from measurements: docs/metrics.md §5).
    Preemptions have none: a runtime's own threads preempt each other hundreds of times a second."""

    other_share: float = 0.05  # other processes' CPU time on the measuring CPUs ÷ those CPUs' capacity
    machine_share: float = 0.25  # other processes' CPU time on every CPU ÷ the machine's capacity
    steal_share: float = 0.03  # time the hypervisor gave others on the measuring CPUs ÷ their capacity


LIMITS = Limits()  # a timed window with interference above these is dropped and taken again in a later round


@dataclass(frozen=True)
class Interference:
    """What other work did during one timed phase, as seconds, counts, rates and shares of wall time."""

    wall_s: float
    cpus: tuple[int, ...]  # the measuring process's CPUs (its affinity)
    own_cpu_s: float  # CPU time of every thread of the measuring process
    other_cpu_s: float  # CPU time others took on the measuring CPUs
    other_share: float  # other_cpu_s ÷ (wall_s × len(cpus))
    machine_share: float  # others' CPU time on every CPU ÷ (wall_s × CPU count)
    steal_share: float  # steal on the measuring CPUs ÷ (wall_s × len(cpus))
    preemptions: int  # involuntary context switches of the measuring process (recorded; no limit: see Limits)
    cpu_busy: dict[int, float]  # every CPU's busy share of the window (ours included)

    @property
    def preemptions_per_s(self) -> float:
        return self.preemptions / self.wall_s if self.wall_s > 0 else 0.0

    def problem(self, limits: Limits) -> str | None:
        """Why this window counts as disturbed under `limits`, or None when it does not (a window shorter than
        JUDGED_FROM_S with the counting error taken off its shares)."""
        slack = COUNTING_ERROR_S / self.wall_s if self.wall_s < JUDGED_FROM_S else 0.0
        checks = ((self.other_share, limits.other_share,
                   "other processes took {:.0%} of the measuring CPU(s) (limit {:.0%})"),
                  (self.machine_share, limits.machine_share,
                   "other processes took {:.0%} of the machine's CPU time (limit {:.0%})"),
                  (self.steal_share, limits.steal_share, "CPU steal {:.0%} (limit {:.0%})"))
        return "; ".join(text.format(value, limit) for value, limit, text in checks
                         if value - slack > limit) or None

    def as_dict(self) -> dict[str, object]:
        """The figures as stored in a record (shares and rates rounded to 4 digits)."""
        return {"wall_s": round(self.wall_s, 4), "cpus": list(self.cpus),
                "own_cpu_s": round(self.own_cpu_s, 4),
                "other_cpu_s": round(self.other_cpu_s, 4), "other_share": round(self.other_share, 4),
                "machine_share": round(self.machine_share, 4), "steal_share": round(self.steal_share, 4),
                "preemptions": self.preemptions, "preemptions_per_s": round(self.preemptions_per_s, 1),
                "cpu_busy": {str(cpu): round(share, 4) for cpu, share in sorted(self.cpu_busy.items())}}


def cpu_jiffies() -> dict[int, tuple[int, int]]:
    """(busy, steal) clock ticks of every CPU since boot, from /proc/stat; empty where it cannot be read."""
    try:
        with open("/proc/stat") as stat:
            lines = [line.split() for line in stat if line.startswith("cpu") and line[3:4].isdigit()]
    except OSError:
        return {}
    counts = {int(parts[0][3:]): [int(v) for v in parts[1:]] for parts in lines}
    return {cpu: (sum(v[i] for i in BUSY_FIELDS if i < len(v)), v[STEAL_FIELD] if len(v) > STEAL_FIELD else 0)
            for cpu, v in counts.items()}


@dataclass(frozen=True)
class Reading:
    """The OS's counts at one moment: wall clock (s), this process's CPU time (s), its involuntary context
    switches and CPUs (its affinity), and every CPU's (busy, steal) ticks since boot."""

    wall_s: float
    own_cpu_s: float
    preemptions: int
    cpus: tuple[int, ...]
    jiffies: dict[int, tuple[int, int]]


def read_counts() -> Reading:
    """This moment's Reading, from perf_counter, getrusage, the affinity and /proc/stat."""
    wall, usage, jiffies = time.perf_counter(), resource.getrusage(resource.RUSAGE_SELF), cpu_jiffies()
    cpus = tuple(sorted(os.sched_getaffinity(0)))
    return Reading(wall, usage.ru_utime + usage.ru_stime, usage.ru_nivcsw, cpus, jiffies)


def between(begin: Reading, end: Reading) -> Interference:
    """The interference from `begin` to `end`, on the CPUs the process had at `end`."""
    wall = max(end.wall_s - begin.wall_s, 1e-9)
    own = end.own_cpu_s - begin.own_cpu_s
    delta = {cpu: (busy - begin.jiffies[cpu][0], steal - begin.jiffies[cpu][1])
             for cpu, (busy, steal) in end.jiffies.items() if cpu in begin.jiffies}
    ours = [delta[cpu] for cpu in end.cpus if cpu in delta]
    other = max(sum(busy for busy, _ in ours) / CLOCK_TICKS - own, 0.0)
    machine = max(sum(busy for busy, _ in delta.values()) / CLOCK_TICKS - own, 0.0)
    return Interference(
        wall_s=wall, cpus=end.cpus, own_cpu_s=own, other_cpu_s=other,
        other_share=other / (wall * len(ours)) if ours else 0.0,
        machine_share=machine / (wall * len(delta)) if delta else 0.0,
        steal_share=sum(steal for _, steal in ours) / CLOCK_TICKS / (wall * len(ours)) if ours else 0.0,
        preemptions=end.preemptions - begin.preemptions,
        cpu_busy={cpu: busy / CLOCK_TICKS / wall for cpu, (busy, _) in delta.items()})


class Sampler:
    """`start()` before a timed phase and `stop()` after it give the interference during it."""

    def __init__(self) -> None:
        self._begin: Reading | None = None

    def start(self) -> None:
        self._begin = read_counts()

    def stop(self) -> Interference:
        end = read_counts()
        if self._begin is None:
            raise RuntimeError("Sampler.stop() without start()")
        return between(self._begin, end)
