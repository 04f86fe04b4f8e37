"""What two runs of one job must agree on: their ``summary.json`` less what differs from one run to the next."""

from __future__ import annotations

#: the summary keys that differ between two runs of one job: the wall time, where the run and its batch lie, and
#: the iterations a resumed run continued from
VOLATILE = ("wall_time_s", "run_dir", "batch_path", "resumed_from_iteration")


def comparable(summary: dict) -> dict:
    """``summary`` less :data:`VOLATILE` and ``platform.source``, the commit of the checkout that ran it: a commit
    landing between two runs (on a developer machine where a campaign commits its results) is not a result."""
    out = {k: v for k, v in summary.items() if k not in VOLATILE}
    if isinstance(out.get("platform"), dict):
        out["platform"] = {k: v for k, v in out["platform"].items() if k != "source"}
    return out
