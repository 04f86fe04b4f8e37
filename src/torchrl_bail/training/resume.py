"""Runs that survive a kill: re-running the same command continues from the run directory's checkpoint.

A training run's directory is derived from its config (``outputs/<env>_<kind>_b<index>/<algo>/seed<seed>``, plus
the remaining command-line overrides; see ``conf/config.yaml``), so the same command finds the same directory.
:class:`Resumption` decides, before any work starts, what a run does with that directory, following ``resume``:

* ``auto`` (default): continue from ``checkpoint.pt`` when there is one; report a finished run as complete
  (summary path and ``final_return``) instead of training again; otherwise start fresh.
* ``false``: start over (the directory's checkpoint, summary and scalar logs are removed first).
* ``true``: like ``auto`` but a missing checkpoint is an error.
* ``<run_dir>``: continue another directory's checkpoint (its scalar logs come along) into this run directory.

A checkpoint whose config differs from the command's in anything but the run-only keys
(:data:`~torchrl_bail.configuration.run_dirs.RUN_ONLY_KEYS`, marked in the schema)
is refused with one line naming the differing keys (exit status 2), never silently mixed. Resuming truncates the
CSV scalar logs to their sizes when the checkpoint was written, so rows are neither lost nor repeated. The run
directory is locked while a run uses it, with the batches' owner-file lock (:data:`RUN_LOCK`): a second process on
the same directory stops with a clear error, a killed run's lock is taken over (at once on one host, after
:data:`RUN_LOCK_STALE_AFTER_S` without a heartbeat from another host's job).
What a checkpoint holds, when it is written and how Slurm requeues resume: the docs' "Interrupted runs and
preemption" page (``docs/guides/interrupted-runs.md``).

Damaged files: a ``checkpoint.pt`` that does not load (a truncated copy, a disk that failed) is set aside as
``checkpoint.pt.corrupt`` and the run starts over, said in one warning line (``resume=true`` or
``resume=<run_dir>`` stop with one line instead). A ``summary.json`` that does not parse is set aside as
``summary.json.corrupt`` when a whole finished checkpoint can write it again; without one, one line says to train
the run again (``resume=false``). A file-system fault while the run writes (full disk, permissions, read-only) ends
in one :class:`~torchrl_bail.core.io.FileSystemError` line naming the file, or the run directory.

Examples:
    >>> diff_configs({"a": 1, "b": {"c": 2}}, {"a": 1, "b": {"c": 3}})
    ['b.c: 2 -> 3']
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import shutil
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from torchrl_bail.configuration.run_dirs import RUN_ONLY_KEYS
from torchrl_bail.core.errors import ResumeError
from torchrl_bail.core.io import FileSystemError, describe_file_error, file_fault, write_text_atomic
from torchrl_bail.data.locks import HEARTBEAT, LockHeld, LockLost, file_lock

__all__ = ["ADDED_KEYS", "RENAMED_KEYS", "RUN_ONLY_KEYS", "ResumeError", "Resumption", "diff_configs",
           "record_config"]

log = logging.getLogger("torchrl_bail")

#: keys added after checkpoints and runs were made (top-level, or ``group.key``), with the value those older runs
#: behaved as: at that value a key is left out of the comparison, so an older run still resumes and still groups
#: with newer ones
ADDED_KEYS = {"compile": False, "seeds": None, "eval.snapshots": 0}
#: config keys renamed after runs were made (old dotted key -> new): an older run's config is read under the new
#: names, so it still resumes and still groups with newer runs (one spelling: "-ize", as TorchRL's names)
RENAMED_KEYS = {"algo.mmd_stabiliser": "algo.mmd_stabilizer"}
CHECKPOINT = "checkpoint.pt"
SUMMARY = "summary.json"
#: the folder of a run's policy snapshots (``eval.snapshots``)
SNAPSHOTS = "snapshots"
#: the suffix a damaged checkpoint or summary is set aside with
CORRUPT = ".corrupt"
LOGS = "logs"


def comparable_config(cfg: DictConfig) -> dict[str, Any]:
    """The resolved config without :data:`RUN_ONLY_KEYS`: what a checkpoint's numbers depend on (an
    :data:`ADDED_KEYS` key at its old behaviour is left out too, so checkpoints written before it existed resume)."""
    return _comparable(OmegaConf.to_container(cfg, resolve=True))


def _comparable(container: dict[str, Any]) -> dict[str, Any]:
    """A config's top level without what a checkpoint's numbers do not depend on: :data:`RUN_ONLY_KEYS`, Hydra's
    node, :data:`ADDED_KEYS` at their old behaviour, in a ``dataset=`` run the unread ``batch`` group;
    :data:`RENAMED_KEYS` under their new names."""
    container = _recorded(container)
    for old, new in RENAMED_KEYS.items():
        (group, leaf), new_leaf = old.split("."), new.split(".")[1]
        node = container.get(group)
        if isinstance(node, dict) and leaf in node:
            container[group] = {new_leaf if k == leaf else k: v for k, v in node.items()}
    for key, default in ADDED_KEYS.items():
        group, _, leaf = key.rpartition(".")
        node = container.get(group) if group else None
        if isinstance(node, dict) and leaf in node and node[leaf] == default:
            container[group] = {k: v for k, v in node.items() if k != leaf}
    return {k: v for k, v in container.items() if k not in RUN_ONLY_KEYS and k != "hydra"
            and not (k in ADDED_KEYS and v == ADDED_KEYS[k])}


def _recorded(container: dict[str, Any]) -> dict[str, Any]:
    """The config a run records: without the ``batch`` group when ``dataset=`` replaced it."""
    return {k: v for k, v in container.items() if not (k == "batch" and container.get("dataset"))}


def record_config(cfg: DictConfig, path: Path) -> Path:
    """Writes the run's resolved config (``config.yaml``, the record of what ran; no ``batch`` group in a
    ``dataset=`` run, which never reads it) atomically."""
    return write_text_atomic(path, OmegaConf.to_yaml(_recorded(OmegaConf.to_container(cfg, resolve=True))))


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


def _one_line(text: str) -> str:
    return " ".join(line.strip() for line in str(text).splitlines() if line.strip())


def data_fingerprint(data) -> str:
    """A short hash of the training batch's size and returns: a regenerated or replaced batch is noticed."""
    h = hashlib.sha1(str(len(data)).encode())
    h.update(data["return"].detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


# -- the run directory ------------------------------------------------------------------------------------------
#: the run directory's lock: an owner file (:func:`~torchrl_bail.data.locks.file_lock`, the batches' mechanism)
RUN_LOCK = ".lock"
#: how often a run touches its directory's lock, and how old that heartbeat must be before another host's job may
#: take the directory over (seconds): short, so that a job requeued on another node after its predecessor was
#: killed waits at most a minute; on one host a killed run's lock is taken over at once (its pid is gone)
RUN_LOCK_HEARTBEAT_S = 10.0
RUN_LOCK_STALE_AFTER_S = 60.0


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
        try:
            self.run_dir.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            self._raise_file_system_error(err)
            raise
        try:
            self._acquire_lock()
            self._decide()
        except BaseException as err:
            self._release_lock()
            self._raise_file_system_error(err)
            raise
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self._release_lock()
        self._raise_file_system_error(exc)

    def _raise_file_system_error(self, err: BaseException | None) -> None:
        """A file-system fault without a file of its own (e.g. a full disk under a logger's write) is raised as one
        :class:`~torchrl_bail.core.io.FileSystemError` line naming the run directory."""
        fault = None if isinstance(err, FileSystemError) else file_fault(err)
        if fault is not None:
            raise FileSystemError(describe_file_error(fault, fault.filename or self.run_dir)) from err

    def _acquire_lock(self) -> None:
        path = self.run_dir / RUN_LOCK
        with contextlib.suppress(OSError):
            if path.read_text().strip().isdigit():  # a bare pid: the lock file of an flock-era version, never held
                path.unlink()
        lock = contextlib.ExitStack()
        try:
            lock.enter_context(file_lock(path, stale_after_s=RUN_LOCK_STALE_AFTER_S, wait=False,
                                         heartbeat_every_s=RUN_LOCK_HEARTBEAT_S,
                                         what=f"the run directory {self.run_dir}"))
        except LockHeld as held:
            raise ResumeError(f"run directory {self.run_dir} is in use by another process ({held.holder}); wait for "
                              "it to finish or choose another hydra.run.dir") from None
        self._lock = lock

    def _release_lock(self) -> None:
        if self._lock is not None:
            lock, self._lock = self._lock, None
            lock.close()

    def _check_lock(self) -> None:
        """Refuses to write on once another job took the run directory over (this one was suspended, its
        heartbeat stopped for longer than :data:`RUN_LOCK_STALE_AFTER_S`)."""
        try:
            HEARTBEAT.check(self.run_dir / RUN_LOCK)
        except LockLost:
            raise ResumeError(f"run directory {self.run_dir} was taken over by another job while this one was "
                              f"stopped for over {RUN_LOCK_STALE_AFTER_S:.0f} s; stopping without writing to it"
                              ) from None

    # -- the decision ------------------------------------------------------------------------------------------
    def _decide(self) -> None:
        mode = self._mode
        if mode is False or str(mode).lower() == "false":
            self._start_over("resume=false")
            return
        source = self._source(mode)
        ckpt_path = source / CHECKPOINT
        if not ckpt_path.is_file():
            if mode is True or str(mode).lower() == "true":
                raise ResumeError(f"resume=true: no {CHECKPOINT} in {self.run_dir} to continue from")
            self._complete_or_start_over()
            return
        checkpoint = self._load_checkpoint(ckpt_path, source, mode)
        if checkpoint is None:  # damaged, and set aside: as if there were none
            self._complete_or_start_over()
            return
        self._check_config(checkpoint, ckpt_path)
        finished = checkpoint["iteration"] >= checkpoint["iterations"]
        if source == self.run_dir and finished and self._report_if_complete(checkpoint):
            return
        self._resume(checkpoint, source)

    def _source(self, mode) -> Path:
        """The directory whose checkpoint the run continues: this run directory, or ``resume=<dir>``'s (which
        must hold a checkpoint, while this run directory holds none of its own)."""
        if mode in (None, True, "auto") or str(mode).lower() in ("auto", "true"):
            return self.run_dir
        source = Path(str(mode)).expanduser()
        if not source.is_absolute():
            from hydra.utils import to_absolute_path

            source = Path(to_absolute_path(str(source)))
        if source.resolve() == self.run_dir.resolve():
            return self.run_dir
        if not (source / CHECKPOINT).is_file():
            raise ResumeError(f"resume={mode}: no {CHECKPOINT} in {source} to continue from")
        if (self.run_dir / CHECKPOINT).exists():
            raise ResumeError(f"resume={mode}: {self.run_dir} already holds a checkpoint of its own; continue it "
                              "with resume=auto or pick another hydra.run.dir")
        return source

    def _complete_or_start_over(self) -> None:
        """No checkpoint to continue: the run is complete when its summary is there, else it starts over."""
        if not self._report_if_complete(None):
            self._start_over(None)

    def _check_config(self, checkpoint: dict, ckpt_path: Path) -> None:
        """Refuses a checkpoint without a config or written by another config than this run's."""
        if checkpoint.get("config") is None:
            raise ResumeError(f"{ckpt_path} carries no config (written by an older torchrl_bail): it cannot be "
                              "resumed safely; start over with resume=false or choose another hydra.run.dir")
        diffs = diff_configs(_comparable(checkpoint["config"]), self.config)
        if diffs:
            shown = "; ".join(diffs[:4]) + (f"; ... ({len(diffs)} keys in all)" if len(diffs) > 4 else "")
            raise ResumeError(f"{ckpt_path} was written by another config ({shown}); rerun with the checkpoint's "
                              "config, start over with resume=false, or choose another hydra.run.dir")

    def _resume(self, checkpoint: dict, source: Path) -> None:
        """Takes the checkpoint on: adopts ``source``'s files, cuts the logs back to it, records where it stopped."""
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

    def _load_checkpoint(self, path: Path, source: Path, mode) -> dict | None:
        """The checkpoint at ``path``; ``None`` when it is damaged and was set aside (only this run directory's own
        checkpoint under ``resume=auto``: another directory's, or ``resume=true``, stop with one line)."""
        import torch

        try:
            checkpoint = torch.load(path, map_location="cpu", weights_only=False)
            if not isinstance(checkpoint, dict) or not {"iteration", "iterations"} <= checkpoint.keys():
                raise ValueError("not a training checkpoint of torchrl_bail")
        except Exception as err:  # noqa: BLE001 - whatever a damaged file raises, it is reported by name
            if describe_file_error(err) is not None:  # unreadable (permissions...), not damaged
                raise
            reason = _one_line(f"{type(err).__name__}: {err}")
            if source != self.run_dir or mode is True or str(mode).lower() == "true":
                raise ResumeError(f"{path} is damaged and cannot be continued ({reason}); start over with "
                                  "resume=false or choose another hydra.run.dir") from None
            self._set_aside(path, f"{path} is damaged ({reason})", "the run starts over")
            return None
        return checkpoint

    def _set_aside(self, path: Path, what: str, then: str) -> None:
        aside = path.with_name(path.name + CORRUPT)
        os.replace(path, aside)
        log.warning("%s: set aside as %s; %s", what, aside.name, then)

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
        try:
            summary = json.loads(summary_path.read_text())
            float(summary["final_return"])
        except (ValueError, TypeError, KeyError, UnicodeDecodeError) as err:
            reason = _one_line(f"{type(err).__name__}: {err}")
            if checkpoint is None:
                raise ResumeError(f"{summary_path} is damaged ({reason}) and no finished checkpoint can write it "
                                  "again; train the run again with resume=false") from None
            self._set_aside(summary_path, f"{summary_path} is damaged ({reason})",
                            "the finished checkpoint writes it again")
            return False
        self.complete = summary
        log.info("run %s is already complete: final_return %.1f -> %s (resume=false trains it again)",
                 self.run_dir, self.complete["final_return"], summary_path)
        return True

    def _start_over(self, reason: str | None) -> None:
        leftovers = [p for p in (self.run_dir / CHECKPOINT, self.run_dir / SUMMARY, self.run_dir / LOGS,
                                 self.run_dir / SNAPSHOTS) if p.exists()]
        for path in leftovers:
            shutil.rmtree(path) if path.is_dir() else path.unlink()
        if leftovers and reason:
            log.info("%s: starting %s over (removed %s)", reason, self.run_dir, ", ".join(p.name for p in leftovers))
        elif leftovers:
            log.info("no checkpoint in %s: starting fresh (removed the partial %s)", self.run_dir,
                     ", ".join(p.name for p in leftovers))

    def _adopt(self, source: Path) -> None:
        """``resume=<run_dir>``: this directory takes over the other run's scalar logs, plots and policy snapshots."""
        self._start_over(None)
        for folder in (LOGS, SNAPSHOTS):
            if (source / folder).is_dir():
                shutil.copytree(source / folder, self.run_dir / folder)
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
        """Run-level entries of every checkpoint: config, CSV log sizes, resume history, batch fingerprint.

        Raises :class:`~torchrl_bail.core.errors.ResumeError` instead when another job took the run directory over."""
        if self._lock is not None:
            self._check_lock()
        extra = {"config": self.config, "resumed_from": self.resumed_from, "data_fingerprint": self._fingerprint}
        if self.csv_logs:
            extra["log_sizes"] = {p.relative_to(self.run_dir).as_posix(): p.stat().st_size
                                  for p in _scalar_files(self.run_dir)}
        return extra

    def summary_fields(self) -> dict[str, Any]:
        """``resumed_from_iteration``: the iterations this run was continued from (empty when never killed)."""
        return {"resumed_from_iteration": list(self.resumed_from)}
