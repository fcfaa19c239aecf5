"""The local executor: each job runs at once on this machine, in its own process (executors/process.py); a
Ray node runs its tasks' jobs with it too."""

from __future__ import annotations

from collections.abc import Iterator

from bench_matrix.errors import UserError
from bench_matrix.executors.base import Ended, Executor, Limits, Phase, Tick, Work
from bench_matrix.executors.process import run_in_process
from bench_matrix.jobs import ProbeJob
from bench_matrix.jobs.results import Probe
from bench_matrix.measure import env as environment
from bench_matrix.named import resolve
from bench_matrix.workspace import Workspace

PROBE_TIMEOUT_S = 300.0


def probe_here(job: ProbeJob) -> Ended:
    """Run a probe job on this machine (log: the workspace's probe log)."""
    limits = Limits(job.workspace.log("probe"), PROBE_TIMEOUT_S)
    return LocalExecutor(job.workspace).run(Work(job, limits))


def probe(job: ProbeJob) -> Probe:
    """The probe job's result, run on this machine; a UserError when it fails."""
    ended = probe_here(job)
    if not ended.ok:
        raise UserError(f"probing the installed backends failed: {ended.error}")
    return ended.result


class LocalExecutor(Executor):
    """One piece of work at a time on this machine."""

    def __init__(self, workspace: Workspace):
        self.workspace = workspace
        self._ended: list[Ended] = []

    def hosts(self) -> set[str]:
        return {environment.host_name()}

    def submit(self, work: Work, on_phase: Phase, tick: Tick) -> None:
        self._ended.append(self.run(work, on_phase, tick))

    def ended(self, wait: bool) -> Iterator[Ended]:
        while self._ended:
            yield self._ended.pop(0)

    def run(self, work: Work, on_phase: Phase = lambda _: None, tick: Tick = lambda: None) -> Ended:
        """Run the work's job in its own process (a timed one here, each session it times in its own)."""
        job, limits = work.job, work.limits
        if job.timed:
            measured = resolve(job.function)(job, self.workspace.jobs, limits.log.parent, on_phase)
            return Ended(work, (job,), (measured,))
        ended = run_in_process(job, self.workspace.jobs, limits.log, limits.timeout_s, limits.threads,
                               on_phase, tick)
        if not ended.ok:
            return Ended(work, (job,), (), ended.error, ended.user_error, environment.capture())
        return Ended(work, (job,), (ended.result,))
