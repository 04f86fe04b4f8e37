"""Make (or find) a behaviour batch: ``python -m torchrl_bail.collect +exp=hopper_ddpg05 [preset=quick]``.

The batch for ``env`` x ``batch`` is collected once and cached under ``data_dir`` (see
:mod:`torchrl_bail.data.cache`, made by :mod:`torchrl_bail.behaviour`); a second call only reports it. Multirun works
as for training::

    python -m torchrl_bail.collect -m +exp=hopper_ddpg05 batch.index=1,2

List what is cached (name, size on disk, transitions, episodes, mean/max episode return, recipe)::

    python -m torchrl_bail.collect --list [--data-dir DIR]

Convert and cache a dataset you already have (D4RL-layout ``.hdf5``, local Minari dataset folder; see
:mod:`torchrl_bail.data.importers`), checking its sizes against an env (a ``conf/env`` name or a gymnasium id)::

    python -m torchrl_bail.collect --import PATH [--env hopper] [--data-dir DIR]

Install a batch someone else made (a hosted copy of a cache entry with its ``SHA256SUMS``), refused with one clear
error unless its checksums, recipe hash, episode count and mean return all match (see
:mod:`torchrl_bail.data.install`)::

    python -m torchrl_bail.collect --install PATH [--data-dir DIR]

Write a batch as a Minari dataset (made or found as by the plain command; ``dataset=PATH`` exports an imported or
native batch; see :mod:`torchrl_bail.data.minari_export`) into Minari's data path (``$MINARI_DATASETS_PATH``)::

    python -m torchrl_bail.collect --export-minari bail/hopper-ddpg05-b1-v0 +exp=hopper_ddpg05 [--force]
        [--ref-max-score R]
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

from torchrl_bail import config_dir
from torchrl_bail.cli import checkpoint_before_requeue, exit_on_config_error, run_cli, use_job_threads
from torchrl_bail.configuration.config import validate_config
from torchrl_bail.configuration.config_builders import collection_config
from torchrl_bail.core.errors import CommandLineError

__all__ = ["collect", "export_main", "format_listing", "import_main", "install_main", "main"]

log = logging.getLogger("torchrl_bail")


def collect(cfg: DictConfig) -> dict:
    """Ensures the batch of ``cfg`` exists; returns a summary (path, cached, statistics)."""
    from torchrl_bail.behaviour import ensure_batch
    from torchrl_bail.data.cache import batch_path, load_cached_batch

    path = batch_path(collection_config(cfg))
    cached = load_cached_batch(path) is not None
    batch = ensure_batch(cfg, progress=bool(cfg.get("progress", True)))
    returns = batch.episode_returns()
    data = batch.data
    meta = batch.metadata
    summary = {
        "path": str(batch.path),
        "cached": cached,
        "name": meta.get("name", Path(str(batch.path)).name),
        "env_id": batch.env_id,
        "transitions": int(batch.num_transitions),
        "episodes": int(batch.num_episodes),
        "terminated": int(data["next", "terminated"].sum()),
        "truncated": int(data["next", "truncated"].sum()),
        "episode_return_mean": float(returns.mean()),
        "episode_return_max": float(returns.max()),
        "episode_return_min": float(returns.min()),
        "collection_wall_time_s": meta.get("collection_wall_time_s"),
        "collection_timed_from_step": meta.get("collection_timed_from_step"),
        "resumed_from_step": meta.get("resumed_from_step"),
        "simulator_unstable_episodes": meta.get("simulator_unstable_episodes"),
    }
    if meta.get("behaviour_return") is not None:
        summary["behaviour_return"] = meta["behaviour_return"]
    return summary


def _print_summary(s: dict) -> None:
    state = "already cached" if s["cached"] else "collected"
    print(f"{s['name']}: {state} at {s['path']}")
    print(f"  env {s['env_id']}: {s['transitions']} transitions, {s['episodes']} episodes "
          f"({s['terminated']} terminated, {s['truncated']} truncated)")
    print(f"  episode return mean {s['episode_return_mean']:.1f}, min {s['episode_return_min']:.1f}, "
          f"max {s['episode_return_max']:.1f}")
    if s.get("behaviour_return") is not None:
        print(f"  behaviour policy return {s['behaviour_return']:.1f}")
    if s.get("collection_wall_time_s") is not None:
        resumed, timed_from = s.get("resumed_from_step"), s.get("collection_timed_from_step")
        print(f"  collection time {s['collection_wall_time_s']:.0f} s"
              + (f" (all its parts; the last resumed from its checkpoint at env step {resumed})"
                 if resumed is not None else "")
              + (f" (from env step {timed_from} on: an older version's checkpoint kept no time)"
                 if timed_from else ""))
    if s.get("simulator_unstable_episodes"):
        print(f"  {s['simulator_unstable_episodes']} episodes ended on a simulator instability (SimulatorGuard)")
    sys.stdout.flush()


@hydra.main(config_path=str(config_dir()), config_name="config", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> None:
    use_job_threads(cfg)
    with checkpoint_before_requeue(), exit_on_config_error():  # Slurm: checkpoint, then submitit requeues
        validate_config(cfg)
        summary = collect(cfg)
    _print_summary(summary)


def format_listing(rows: list[dict]) -> str:
    """The ``--list`` table."""
    from torchrl_bail.data.listing import format_bytes

    if not rows:
        return "no cached batches"

    def num(v, fmt):
        return "-" if v is None else format(v, fmt)

    table = [("name", "size", "transitions", "episodes", "mean ret", "max ret", "recipe")]
    for r in rows:
        table.append((r["name"], format_bytes(r["bytes"]), num(r.get("transitions"), "d"),
                      num(r.get("episodes"), "d"), num(r.get("mean_return"), ".1f"), num(r.get("max_return"), ".1f"),
                      r.get("recipe", "")))
    widths = [max(len(str(row[i])) for row in table) for i in range(len(table[0]))]
    right = {1, 2, 3, 4, 5}
    lines = []
    for j, row in enumerate(table):
        cells = [str(c).rjust(w) if i in right else str(c).ljust(w)
                 for i, (c, w) in enumerate(zip(row, widths, strict=True))]
        lines.append("  ".join(cells).rstrip())
        if j == 0:
            lines.append("  ".join("-" * w for w in widths))
    return "\n".join(lines)


def _list_main(argv: list[str]) -> int:
    from torchrl_bail.data.cache import data_dir_of
    from torchrl_bail.data.listing import list_batches

    data_dir = None
    it = iter(argv)
    for arg in it:
        if arg == "--data-dir":
            data_dir = next(it, None)
        elif arg.startswith(("--data-dir=", "data_dir=")):
            data_dir = arg.split("=", 1)[1]
        elif arg != "--list":
            print(f"--list accepts only --data-dir DIR (or data_dir=DIR), got {arg!r}", file=sys.stderr)
            return 2
    root = data_dir_of(None, data_dir)
    rows = list_batches(root)
    from torchrl_bail.data.importers import iter_imported

    for row, description in iter_imported(rows):  # imported datasets: say where they came from
        row["recipe"] = description
    print(f"cached batches in {root}:")
    print(format_listing(rows))
    return 0


def _flag_values(argv: list[str], flags: tuple[str, ...], accepts: str) -> dict[str, str | None] | None:
    """The values of ``flags`` in ``argv`` (``--flag VALUE``, ``--flag=VALUE``, or ``env=`` / ``data_dir=`` for
    ``--env`` / ``--data-dir``); ``None``, with one line on stderr (``accepts``, then the offending argument), for
    any other argument or a flag without a value."""
    opts: dict[str, str | None] = dict.fromkeys(flags)
    it = iter(argv)
    for arg in it:
        key, eq, value = arg.partition("=")
        key = {"env": "--env", "data_dir": "--data-dir"}.get(key, key) if eq else key
        if key not in opts:
            print(f"{accepts}, got {arg!r}", file=sys.stderr)
            return None
        opts[key] = value if eq else next(it, None)
        if opts[key] is None:
            print(f"{key} needs a value", file=sys.stderr)
            return None
    return opts


def install_main(argv: list[str]) -> int:
    """``--install PATH [--data-dir DIR]``: check a hosted batch and copy it into the cache, print where."""
    from torchrl_bail.data import BatchValidationError
    from torchrl_bail.data.install import install_batch

    opts = _flag_values(argv, ("--install", "--data-dir"), "--install accepts only PATH and --data-dir DIR")
    if opts is None:
        return 2
    source, data_dir = opts["--install"], opts["--data-dir"]
    print(f"checking {source} (checksums, recipe hash, episodes, mean return) ...", flush=True)
    try:
        path, copied = install_batch(source, data_dir)
    except (BatchValidationError, OSError) as err:
        print(f"error: {err}; nothing was installed", file=sys.stderr)
        return 2
    print(f"{'installed' if copied else 'already installed and intact'}: {path}")
    return 0


def _env_id_of(name: str) -> str:
    """``hopper`` (a ``conf/env`` name) -> ``Hopper-v5``; anything else is taken as a gymnasium id."""
    from omegaconf import OmegaConf

    conf = config_dir() / "env" / f"{name}.yaml"
    return str(OmegaConf.load(conf).id) if conf.is_file() else name


def import_main(argv: list[str]) -> int:
    """``--import PATH [--env NAME|ID] [--data-dir DIR]``: convert and cache an external dataset, print where."""
    from torchrl_bail.data import BatchValidationError
    from torchrl_bail.data.importers import import_cache_path, import_dataset

    opts = _flag_values(argv, ("--import", "--env", "--data-dir"), "--import accepts only PATH, --env NAME and "
                        "--data-dir DIR")
    if opts is None:
        return 2
    path, env, data_dir = opts["--import"], opts["--env"], opts["--data-dir"]
    env_id = _env_id_of(env) if env else None
    try:
        cache = import_cache_path(path, data_dir)
        cached = cache is not None and (cache / "metadata.json").is_file()
        batch = import_dataset(path, env_id=env_id, data_dir=data_dir)
    except (BatchValidationError, FileNotFoundError) as err:
        print(f"torchrl_bail: {type(err).__name__}: {err}", file=sys.stderr)
        return 2
    meta, data, returns = batch.metadata, batch.data, batch.episode_returns()
    state = "native batch (used in place)" if cache is None else ("already cached" if cached else "converted")
    print(f"{meta.get('name', Path(str(batch.path)).name)}: {state} at {batch.path}")
    print(f"  env {meta.get('env_id') or 'unknown (pass --env to check sizes)'}: {batch.num_transitions} transitions, "
          f"{batch.num_episodes} episodes ({int(data['next', 'terminated'].sum())} terminated, "
          f"{int(data['next', 'truncated'].sum())} truncated), obs {batch.obs_dim}, act {batch.act_dim}")
    if meta.get("dropped_rows"):
        print(f"  dropped {meta['dropped_rows']} rows whose next observation is unknown (no next_observations)")
    print(f"  episode return mean {float(returns.mean()):.1f}, min {float(returns.min()):.1f}, "
          f"max {float(returns.max()):.1f}")
    print(f"  train on it: python -m torchrl_bail.train dataset={path}{f' env={env}' if env else ''}")
    sys.stdout.flush()
    return 0


def _export_options(argv: list[str]) -> tuple[dict, list[str]]:
    """``(options, Hydra overrides)`` of an ``--export-minari`` command line; :class:`CommandLineError` for a bad
    one."""
    opts: dict = {"dataset_id": None, "force": False, "ref_max_score": None}
    overrides = []
    it = iter(argv)
    for arg in it:
        key, eq, value = arg.partition("=")
        if key in ("--export-minari", "--ref-max-score"):
            value = value if eq else next(it, None)
            if value is None:
                raise CommandLineError(f"{key} needs a value")
            if key == "--ref-max-score":
                try:
                    opts["ref_max_score"] = float(value)
                except ValueError:
                    raise CommandLineError(f"--ref-max-score {value!r}: expected a number (a return)") from None
            else:
                opts["dataset_id"] = value
        elif arg == "--force":
            opts["force"] = True
        elif arg.startswith("-"):
            raise CommandLineError(f"--export-minari accepts only --force, --ref-max-score R and key=value "
                                   f"overrides (one batch, no -m), got {arg!r}")
        else:
            overrides.append(arg)
    return opts, overrides


def export_main(argv: list[str]) -> int:
    """``--export-minari DATASET_ID [--force] [--ref-max-score R] <overrides>``: make or find the batch of the
    overrides (or import ``dataset=PATH``) and write it as a Minari dataset; prints where."""
    from hydra import compose, initialize_config_dir

    with exit_on_config_error():  # a bad command line, config or batch: one line, exit code 2
        opts, overrides = _export_options(argv)
        if opts["dataset_id"] is None:
            raise CommandLineError("--export-minari needs a dataset id, e.g. bail/hopper-ddpg05-b1-v0")
        with initialize_config_dir(str(config_dir()), version_base="1.3"):
            cfg = compose("config", overrides=overrides)
        validate_config(cfg)
        from torchrl_bail.data.minari_export import MinariExportError, check_dataset_id, export_minari
        from torchrl_bail.train import load_training_batch

        logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s][%(levelname)s] - %(message)s")
        try:
            check_dataset_id(opts["dataset_id"], force=opts["force"])  # before a collection that may take hours
            batch = load_training_batch(cfg)
            path = export_minari(batch, opts["dataset_id"], force=opts["force"],
                                 ref_max_score=opts["ref_max_score"])
        except MinariExportError as err:
            print(f"torchrl_bail: {err}", file=sys.stderr)
            return 2
    import minari

    dataset = minari.MinariDataset(path / "data")
    meta = dataset.storage.metadata
    print(f"{opts['dataset_id']}: {dataset.total_episodes} episodes, {dataset.total_steps} steps of "
          f"{batch.metadata.get('name', Path(str(batch.path)).name)} at {path}")
    print(f"  env {batch.env_id}; ref_min_score {meta.get('ref_min_score')}, ref_max_score "
          f"{meta.get('ref_max_score')}")
    print(f"  load it: minari.load_dataset({opts['dataset_id']!r}) | python -m torchrl_bail.train dataset={path}")
    sys.stdout.flush()
    return 0


def main() -> None:
    argv = sys.argv[1:]
    if "--list" in argv:
        raise SystemExit(_list_main(argv))
    if any(a == "--install" or a.startswith("--install=") for a in argv):
        raise SystemExit(install_main(argv))
    if any(a == "--import" or a.startswith("--import=") for a in argv):
        raise SystemExit(import_main(argv))
    if any(a == "--export-minari" or a.startswith("--export-minari=") for a in argv):
        os.environ.setdefault("RL_WARNINGS", "0")
        raise SystemExit(export_main(argv))
    # keep collection runs' Hydra files apart from training runs, unless the user chose a directory
    extra = []
    if not any(a.startswith(("hydra.run.dir", "hydra.sweep.dir")) for a in argv):
        extra = [
            "hydra.run.dir=outputs/collect/${env.name}_${batch.kind}_b${batch.index}/${now:%Y%m%d-%H%M%S}",
            "hydra.sweep.dir=multirun/collect/${now:%Y-%m-%d_%H-%M-%S}",
        ]
    os.environ.setdefault("RL_WARNINGS", "0")
    # a bad command line: one line on stderr, exit code 2; Ctrl-C/SIGTERM: checkpoint, one line, exit code 130/143
    run_cli(_hydra_main, extra, command="python -m torchrl_bail.collect")


if __name__ == "__main__":
    main()
