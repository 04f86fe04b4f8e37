"""Runs that survive a kill: re-running the same command continues from the run directory's checkpoint.

A training run's directory is derived from its config (``outputs/<env>_<kind>_b<index>/<algo>/seed<seed>``, plus
the remaining command-line overrides; see ``conf/config.yaml``), so the same command finds the same directory.
:class:`Resumption` decides, before any work starts, what a run does with that directory, following ``resume``:

* ``auto`` (default): continue from ``checkpoint.pt`` when there is one; report a finished run as complete
  (summary path and ``final_return``) instead of training again; otherwise start fresh.
* ``false``: start over (the directory's checkpoint, summary and scalar logs are removed first).
* ``true``: like ``auto`` but a missing checkpoint is an error.
* ``<run_dir>``: continue another directory's checkpoint (its scalar logs come along) into this run directory.

A checkpoint whose config differs from the command's in anything but the run-only keys (:data:`RUN_ONLY_KEYS`)
is refused with one line naming the differing keys (exit status 2), never silently mixed. Resuming truncates the
CSV scalar logs to their sizes when the checkpoint was written, so rows are neither lost nor repeated. The run
directory is locked while a run uses it: a second process on the same directory stops with a clear error.
What a checkpoint holds, when it is written and how Slurm requeues resume: the docs' "Interrupted runs and
preemption" page (``docs/guides/interrupted-runs.md``).

Examples:
    >>> run_dir_suffix("")
    ''
    >>> run_dir_suffix("algo.epochs=3,preset=quick")
    ',algo.epochs=3,preset=quick'
    >>> run_dir_suffix("dataset=/data/hopper.hdf5")
    ',dataset=%data%hopper.hdf5'
    >>> diff_configs({"a": 1, "b": {"c": 2}}, {"a": 1, "b": {"c": 3}})
    ['b.c: 2 -> 3']
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

__all__ = ["ADDED_KEYS", "RUN_ONLY_KEYS", "ResumeError", "Resumption", "diff_configs", "register_resolvers",
           "run_dir_suffix"]

log = logging.getLogger("torchrl_bail")

#: top-level config keys that may differ between a checkpoint and the command resuming it: they change how a
#: run reports or where it finds its files, never its numbers (``device`` changes numbers only across devices)
RUN_ONLY_KEYS = ("progress", "logger", "resume", "device", "data_dir", "checkpoint", "threads")
#: top-level keys added after checkpoints and runs were made, with the value those older runs behaved as: at that
#: value a key is left out of the comparison, so an older run still resumes and still groups with newer ones
ADDED_KEYS = {"compile": False, "seeds": None}
CHECKPOINT = "checkpoint.pt"
SUMMARY = "summary.json"
LOGS = "logs"
#: longest override suffix kept verbatim in a directory name (file systems allow 255 bytes per component)
_MAX_SUFFIX = 120


class ResumeError(ValueError):
    """The run directory cannot be continued by this command (other config, in use, no checkpoint)."""


def run_dir_suffix(override_dirname: str) -> str:
    """``",<overrides>"`` for a non-empty Hydra ``override_dirname`` (``/`` -> ``%``; long ones shortened with a
    hash), else ``""``: registered as the ``run_dir_suffix`` resolver of ``conf/config.yaml``'s run dirs."""
    text = str(override_dirname or "").replace(os.sep, "%")
    if not text:
        return ""
    if len(text) > _MAX_SUFFIX:
        digest = hashlib.sha1(text.encode()).hexdigest()[:10]
        text = f"{text[:_MAX_SUFFIX - 11]}~{digest}"
    return "," + text


def register_resolvers() -> None:
    """Registers :func:`run_dir_suffix` as the OmegaConf resolver the run directories of ``conf/config.yaml`` use
    (called by :func:`torchrl_bail.config.config_dir`; idempotent)."""
    if not OmegaConf.has_resolver("run_dir_suffix"):
        OmegaConf.register_new_resolver("run_dir_suffix", run_dir_suffix)


def comparable_config(cfg: DictConfig) -> dict[str, Any]:
    """The resolved config without :data:`RUN_ONLY_KEYS`: what a checkpoint's numbers depend on (an
    :data:`ADDED_KEYS` key at its old behaviour is left out too, so checkpoints written before it existed resume)."""
    return _comparable(OmegaConf.to_container(cfg, resolve=True))


def _comparable(container: dict[str, Any]) -> dict[str, Any]:
    """A config's top level without what a checkpoint's numbers do not depend on: :data:`RUN_ONLY_KEYS`, Hydra's
    node and :data:`ADDED_KEYS` at their old behaviour."""
    return {k: v for k, v in container.items() if k not in RUN_ONLY_KEYS and k != "hydra"
            and not (k in ADDED_KEYS and v == ADDED_KEYS[k])}


def diff_configs(old: Any, new: Any, prefix: str = "") -> list[str]:
    """``"key: old -> new"`` for every leaf that differs between two nested dicts."""
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for key in sorted(set(old) | set(new), key=str):
            name = f"{prefix}.{key}" if prefix else str(key)
            if key not in old:
                out.append(f"{name}: (absent) -> {new[key]!r}")
            elif key not in new:
                out.append(f"{name}: {old[key]!r} -> (absent)")
            else:
                out.extend(diff_configs(old[key], new[key], name))
        return out
    return [] if old == new else [f"{prefix}: {old!r} -> {new!r}"]


def data_fingerprint(data) -> str:
    """A short hash of the training batch's size and returns: a regenerated or replaced batch is noticed."""
    h = hashlib.sha1(str(len(data)).encode())
    h.update(data["return"].detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


# -- the run directory ------------------------------------------------------------------------------------------
try:
    import fcntl
except ImportError:  # pragma: no cover - Windows: no advisory locks, document and go on
    fcntl = None


def _scalar_files(run_dir: Path) -> list[Path]:
    root = run_dir / LOGS / "scalars"
    return sorted(root.rglob("*.csv")) if root.is_dir() else []


class Resumption:
    """What one training command does with its run directory; a context manager holding the directory's lock.

    Attributes:
        complete (dict | None): the summary of a finished run with this config (nothing left to do).
        checkpoint (dict | None): the checkpoint to continue from (``None``: start fresh).
        resumed_from (list[int]): iterations this run was resumed from, oldest first.
    """

    def __init__(self, cfg: DictConfig, run_dir: Path) -> None:
        self.run_dir = Path(run_dir)
        self.config = comparable_config(cfg)
        self.csv_logs = OmegaConf.select(cfg, "logger.backend", default="csv") == "csv"
        self.complete: dict | None = None
        self.checkpoint: dict | None = None
        self.resumed_from: list[int] = []
        self._fingerprint: str | None = None
        self._lock = None
        self._mode = cfg.get("resume", "auto")

    # -- context manager: lock, decide, release --------------------------------------------------------------
    def __enter__(self) -> Resumption:
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self._acquire_lock()
        try:
            self._decide()
        except BaseException:
            self._release_lock()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self._release_lock()

    def _acquire_lock(self) -> None:
        if fcntl is None:
            return
        handle = open(self.run_dir / ".lock", "a+")  # noqa: SIM115 - held until __exit__
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            owner = handle.read().strip() or "?"
            handle.close()
            raise ResumeError(f"run directory {self.run_dir} is in use by another process (pid {owner}); wait for "
                              "it to finish or choose another hydra.run.dir") from None
        handle.seek(0)
        handle.truncate()
        handle.write(str(os.getpid()))
        handle.flush()
        self._lock = handle

    def _release_lock(self) -> None:
        if self._lock is not None:
            self._lock.close()  # closing the descriptor releases the flock
            self._lock = None

    # -- the decision ------------------------------------------------------------------------------------------
    def _decide(self) -> None:
        mode = self._mode
        if mode is False or str(mode).lower() == "false":
            self._start_over("resume=false")
            return
        source = self.run_dir
        if mode not in (None, True, "auto") and str(mode).lower() not in ("auto", "true"):
            source = Path(str(mode)).expanduser()
            if not source.is_absolute():
                from hydra.utils import to_absolute_path

                source = Path(to_absolute_path(str(source)))
            if source.resolve() == self.run_dir.resolve():
                source = self.run_dir
            elif not (source / CHECKPOINT).is_file():
                raise ResumeError(f"resume={mode}: no {CHECKPOINT} in {source} to continue from")
            elif (self.run_dir / CHECKPOINT).exists():
                raise ResumeError(f"resume={mode}: {self.run_dir} already holds a checkpoint of its own; continue it "
                                  "with resume=auto or pick another hydra.run.dir")
        ckpt_path = source / CHECKPOINT
        if not ckpt_path.is_file():
            if mode is True or str(mode).lower() == "true":
                raise ResumeError(f"resume=true: no {CHECKPOINT} in {self.run_dir} to continue from")
            if self._report_if_complete(None):
                return
            self._start_over(None)
            return
        import torch

        checkpoint = torch.load(ckpt_path, map_location="cpu", weights_only=False)
        if checkpoint.get("config") is None:
            raise ResumeError(f"{ckpt_path} carries no config (written by an older torchrl_bail): it cannot be "
                              "resumed safely; start over with resume=false or choose another hydra.run.dir")
        diffs = diff_configs(_comparable(checkpoint["config"]), self.config)
        if diffs:
            shown = "; ".join(diffs[:4]) + (f"; ... ({len(diffs)} keys in all)" if len(diffs) > 4 else "")
            raise ResumeError(f"{ckpt_path} was written by another config ({shown}); rerun with the checkpoint's "
                              "config, start over with resume=false, or choose another hydra.run.dir")
        finished = checkpoint["iteration"] >= checkpoint["iterations"]
        if source == self.run_dir and finished and self._report_if_complete(checkpoint):
            return
        if source != self.run_dir:
            self._adopt(source)
        self._truncate_logs(checkpoint.get("log_sizes"))
        self.checkpoint = checkpoint
        self.resumed_from = [*checkpoint.get("resumed_from", []), int(checkpoint["iteration"])]
        self._fingerprint = checkpoint.get("data_fingerprint")
        evaluations = checkpoint.get("evaluations", [])
        log.info("resuming %s from its checkpoint at iteration %d of %d (%d evaluations so far%s)", source,
                 checkpoint["iteration"], checkpoint["iterations"], len(evaluations),
                 f", last return {evaluations[-1]['mean_return']:.1f}" if evaluations else "")

    def _report_if_complete(self, checkpoint: dict | None) -> bool:
        import json

        summary_path = self.run_dir / SUMMARY
        if not summary_path.is_file():
            return False
        if checkpoint is None:  # checkpoints disabled: the directory's config.yaml tells whose summary it is
            config_path = self.run_dir / "config.yaml"
            if not config_path.is_file():
                return False
            saved = _comparable(OmegaConf.to_container(OmegaConf.load(config_path)))
            diffs = diff_configs(saved, self.config)
            if diffs:
                raise ResumeError(f"{self.run_dir} holds a finished run of another config ({'; '.join(diffs[:4])}); "
                                  "start over with resume=false or choose another hydra.run.dir")
        self.complete = json.loads(summary_path.read_text())
        log.info("run %s is already complete: final_return %.1f -> %s (resume=false trains it again)",
                 self.run_dir, self.complete["final_return"], summary_path)
        return True

    def _start_over(self, reason: str | None) -> None:
        leftovers = [p for p in (self.run_dir / CHECKPOINT, self.run_dir / SUMMARY, self.run_dir / LOGS) if p.exists()]
        for path in leftovers:
            shutil.rmtree(path) if path.is_dir() else path.unlink()
        if leftovers and reason:
            log.info("%s: starting %s over (removed %s)", reason, self.run_dir, ", ".join(p.name for p in leftovers))
        elif leftovers:
            log.info("no checkpoint in %s: starting fresh (removed the partial %s)", self.run_dir,
                     ", ".join(p.name for p in leftovers))

    def _adopt(self, source: Path) -> None:
        """``resume=<run_dir>``: this directory takes over the other run's scalar logs and plots."""
        self._start_over(None)
        if (source / LOGS).is_dir():
            shutil.copytree(source / LOGS, self.run_dir / LOGS)
        for plot in source.glob("*.png"):
            shutil.copy2(plot, self.run_dir / plot.name)

    def _truncate_logs(self, sizes: dict[str, int] | None) -> None:
        """Cuts every CSV scalar file back to its size at the checkpoint; removes files written after it."""
        if sizes is None or not self.csv_logs:
            return
        for path in _scalar_files(self.run_dir):
            rel = path.relative_to(self.run_dir).as_posix()
            if rel not in sizes:
                path.unlink()
                continue
            if path.stat().st_size < sizes[rel]:
                log.warning("%s is shorter than when the checkpoint was written: rows were lost", path)
            with open(path, "rb+") as f:
                f.truncate(sizes[rel])

    # -- what the training run asks ----------------------------------------------------------------------------
    def check_data(self, data) -> None:
        """Refuses to continue on a batch other than the checkpoint's (e.g. regenerated with other code)."""
        fingerprint = data_fingerprint(data)
        if self._fingerprint is not None and fingerprint != self._fingerprint:
            raise ResumeError(f"the training batch differs from the one the checkpoint in {self.run_dir} trained on "
                              "(regenerated or replaced); start over with resume=false")
        self._fingerprint = fingerprint

    def checkpoint_extra(self) -> dict[str, Any]:
        """Run-level entries of every checkpoint: config, CSV log sizes, resume history, batch fingerprint."""
        extra = {"config": self.config, "resumed_from": self.resumed_from, "data_fingerprint": self._fingerprint}
        if self.csv_logs:
            extra["log_sizes"] = {p.relative_to(self.run_dir).as_posix(): p.stat().st_size
                                  for p in _scalar_files(self.run_dir)}
        return extra

    def summary_fields(self) -> dict[str, Any]:
        """``resumed_from_iteration``: the iterations this run was continued from (empty when never killed)."""
        return {"resumed_from_iteration": list(self.resumed_from)}
