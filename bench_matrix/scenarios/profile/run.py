"""A cell's profile, in its measure job's process after the rounds: one test sample run under the runtime's
own profiler through Session.profile; the record gets the `profile_*` fields (docs/metrics.md, Profiles),
and, for the roofline, the work of an inference and the machine's peak (`work_*`, `machine_*`: §17)."""

from __future__ import annotations

from bench_matrix import data
from bench_matrix.op_profile import Profile
from bench_matrix.phases import phase
from bench_matrix.scenarios.base import Loaded, Outcome
from bench_matrix.scenarios.profile import ProfilePlan
from bench_matrix.scenarios.profile.machine import peak_fields, work_fields
from bench_matrix.tensors import bind, take


def run_profile(loaded: Loaded, plan: ProfilePlan) -> Outcome:
    """The profile of the first test sample (batch 1, as the p50 is timed), or the reason there is none."""
    job, session, calls = loaded.job, loaded.session, plan.spec.calls
    few, _ = data.load_split(job.data.directory, "test", job.data.preprocess, job.layout, 1)
    prepared = session.prepare(take(bind(few, job.source.inputs), slice(0, 1)))
    phase(f"profile · {calls} calls")
    try:
        profile = session.profile(prepared, calls)
    except Exception as exc:  # any: a profiler's failure leaves the timed figures valid
        profile = Profile(reason=f"the profiler failed: {type(exc).__name__}: {exc}")
    fields = profile.fields()
    if "profile_reason" in fields:
        fields["profile_reason"] = f"{loaded.backend.name}: {fields['profile_reason']}"
        return Outcome(fields)
    meta = job.converted.manifest.get("meta") or {}
    peak = peak_fields(job.workspace, job.settings.threads) if job.cell.target == "cpu" else {
        "machine_reason": f"the peak measured is the CPU's; a cell on {job.cell.target} is not held to it"}
    return Outcome({**fields, **work_fields(loaded.backend.name, meta), **peak})
