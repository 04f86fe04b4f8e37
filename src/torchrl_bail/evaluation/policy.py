"""Trained policies a user can run: ``policy.pt`` files, :func:`load_policy` and standalone exports.

A run writes ``policy.pt`` (the final policy) and ``policy_best.pt`` (the best-evaluated one) with
:func:`save_policy`. Each is a plain ``torch.save`` dict holding everything needed to rebuild the actor without the
run's data: the algorithm, observation size, action size and bounds, the hidden sizes of its networks, the env id,
the run's resolved config, where in training it was taken (iteration, epoch, evaluation return) and the policy's
state dict. :func:`load_policy` returns a ready TensorDict policy (reads ``"observation"``, writes ``"action"``),
rebuilt as the algorithm's class says (:meth:`~torchrl_bail.algorithms.base.Algorithm.rebuild_policy`): the
deterministic tanh actor of BAIL, Progressive BAIL, BC and MARWIL, or the best-of-N policy of BCQ and BEAR
(``num_samples`` candidates, the best by ``Q_1``; it draws its candidates from torch's random stream).

:func:`export_policy` writes a file that runs with plain torch (or onnxruntime), without this package, as a
function ``observation [B, obs_dim] -> action [B, act_dim]``:

=============  ===============================  ===========================================================
format         BAIL, Progressive BAIL, BC,      BCQ, BEAR (samples candidates)
               MARWIL (deterministic)
=============  ===============================  ===========================================================
``pt2``        yes (``torch.export.load``)      yes; draws from torch's stream: same seed, same actions
``onnx``       yes (onnxruntime)                yes; onnxruntime's own random stream, so other samples
``torchscript``  yes (``torch.jit.load``)       no: tracing cannot carry the sampling (a clear error)
=============  ===============================  ===========================================================

``onnx`` needs the ``export`` extra (``pip install "torchrl_bail[export]"``: onnx, onnxscript, onnxruntime).
An ONNX file holds its weights (one file to copy); only a model with more than :data:`ONNX_EMBED_LIMIT` bytes of
weights has them beside it in ``<file>.data`` (:func:`onnx_external_data`). A re-export leaves nothing else.

Examples:
    >>> import torch, tempfile
    >>> from pathlib import Path
    >>> from tensordict import TensorDict
    >>> from torchrl_bail.algorithms.bc import BehaviourCloning
    >>> from torchrl_bail.modules import action_spec_from_bounds
    >>> spec = action_spec_from_bounds([-1.0, -1.0], [1.0, 1.0])
    >>> cfg = {"algo": {"name": "bc", "policy": {"hidden": [8]}}, "env": {"id": "Hopper-v5"}}
    >>> algo = BehaviourCloning(3, spec, cfg["algo"])  # the keys left out: conf/algo/bc.yaml's values
    >>> path = save_policy(Path(tempfile.mkdtemp()) / "policy.pt", algo, cfg, obs_dim=3, action_spec=spec)
    >>> policy = load_policy(path)
    >>> obs = TensorDict({"observation": torch.randn(4, 3)}, [4])
    >>> torch.equal(policy(obs.clone())["action"], algo.policy(obs.clone())["action"])
    True
"""

from __future__ import annotations

import copy
import os
import tempfile
from pathlib import Path
from typing import Any

import torch
from torch import nn

from torchrl_bail.algorithms import ALGORITHMS
from torchrl_bail.core.io import atomic_path, write_atomic
from torchrl_bail.modules import action_spec_from_bounds

__all__ = ["POLICY_FORMAT", "EXPORT_FORMATS", "PolicyFileError", "save_policy", "read_policy_file", "load_policy",
           "policy_actions", "export_policy", "onnx_external_data"]

POLICY_FORMAT = 1
EXPORT_FORMATS = {"pt2": ".pt2", "onnx": ".onnx", "torchscript": ".ts"}
#: weight bytes up to which an ONNX export embeds its weights (torch's own switch to external data, 1.5 GiB:
#: protobuf files cannot exceed 2 GiB)
ONNX_EMBED_LIMIT = 3 * 2**29


class PolicyFileError(ValueError):
    """A policy file is missing, unreadable or lacks a field; the message names the file."""


def _container(cfg: Any) -> dict:
    from omegaconf import DictConfig, OmegaConf

    if isinstance(cfg, DictConfig):
        return OmegaConf.to_container(cfg, resolve=True)
    return copy.deepcopy(dict(cfg))


def _network_sizes(algo_cfg: dict) -> dict[str, list[int]]:
    """``{"policy": [400, 300]}`` (or ``actor``/``vae``/``critic``...): every block of the algo config with
    ``hidden``."""
    return {k: [int(h) for h in v["hidden"]] for k, v in algo_cfg.items() if isinstance(v, dict) and "hidden" in v}


def save_policy(path: str | Path, algorithm, cfg, *, obs_dim: int, action_spec, **info: Any) -> Path:
    """Writes ``algorithm.policy`` with what is needed to rebuild it (atomically).

    Args:
        path: the file to write (``<run_dir>/policy.pt``).
        algorithm (Algorithm): the trained :class:`~torchrl_bail.algorithms.base.Algorithm`.
        cfg (DictConfig | dict): the run's config (DictConfig or dict with ``algo`` and ``env``), stored resolved.

    Keyword Args:
        obs_dim (int): observation size.
        action_spec (Bounded): the :class:`~torchrl.data.Bounded` action spec (its bounds are stored).
        **info: where in training the policy was taken (``iteration``, ``epoch``, ``mean_return``...).
    """
    config = _container(cfg)
    algo_cfg = config["algo"]
    record = {
        "format": POLICY_FORMAT,
        "algo": algo_cfg["name"],
        "env_id": config.get("env", {}).get("id"),
        "obs_dim": int(obs_dim),
        "act_dim": int(action_spec.shape[-1]),
        "action_low": [float(x) for x in action_spec.space.low.reshape(-1)],
        "action_high": [float(x) for x in action_spec.space.high.reshape(-1)],
        "hidden": _network_sizes(algo_cfg),
        "num_samples": algo_cfg.get("num_samples"),
        "config": config,
        "info": {k: (float(v) if isinstance(v, float) else v) for k, v in info.items()},
        "state_dict": {k: v.detach().cpu() for k, v in algorithm.policy.state_dict().items()},
    }
    return write_atomic(path, lambda f: torch.save(record, f))


def _policy_path(source: str | Path, best: bool = False) -> Path:
    source = Path(source)
    if source.is_dir():
        source = source / ("policy_best.pt" if best else "policy.pt")
    if not source.is_file():
        raise PolicyFileError(f"{source}: no such policy file (a finished run directory holds policy.pt)")
    return source


def _damage(path: Path) -> str | None:
    """Why the policy file at ``path`` is damaged, or ``None`` when its archive is whole.

    ``torch.save`` writes a zip archive with a CRC-32 checksum per entry: an entry that fails its checksum (bytes
    changed on disk or in a copy) is damage that ``torch.load`` may not notice. A file that is no zip archive at
    all (random bytes, a copy cut short: a zip's directory is at its end) is ``"not a zip archive"``, damage only
    if ``torch.load`` cannot read it either (the caller decides: torch's legacy format is no zip archive).
    """
    import zipfile

    try:
        with zipfile.ZipFile(path) as archive:
            bad = archive.testzip()
    except (zipfile.BadZipFile, EOFError, OSError):
        return "not the zip archive torch.save writes"
    return None if bad is None else f"its entry {bad} fails its checksum"


def _damaged(path: Path, reason: str) -> PolicyFileError:
    return PolicyFileError(f"{path}: not a readable policy file: corrupt or truncated ({reason}); train the run "
                           f"again or restore the file")


def read_policy_file(source: str | Path, *, best: bool = False) -> dict:
    """The record :func:`save_policy` wrote (``source``: a run directory or a policy file).

    A damaged file (random bytes, a copy cut short, an entry of its zip archive failing its checksum) raises
    :class:`PolicyFileError` saying ``not a readable policy file: corrupt or truncated (<why>)`` at its path, rather
    than ``torch.load``'s own message, which advises ``weights_only=False``: no damaged file survives that. Any other
    unreadable file is named with the first line of torch's error.
    """
    path = _policy_path(source, best)
    reason = _damage(path)
    if reason is not None and "checksum" in reason:
        raise _damaged(path, reason)
    try:
        record = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - any unpickling error names the file
        if reason is not None:  # no zip archive, and not a file torch reads either
            raise _damaged(path, reason) from None
        first_line = (str(err).strip().splitlines() or [""])[0]
        raise PolicyFileError(f"{path}: not a readable policy file ({type(err).__name__}: {first_line})") from None
    if not isinstance(record, dict) or record.get("format") != POLICY_FORMAT:
        raise PolicyFileError(f"{path}: not a torchrl_bail policy file of format {POLICY_FORMAT} "
                              f"(files written before policy files carried their config cannot be rebuilt)")
    record["path"] = str(path)
    return record


def _rebuild(record: dict, device) -> nn.Module:
    spec = action_spec_from_bounds(record["action_low"], record["action_high"])
    algo = record["algo"]
    if algo not in ALGORITHMS:
        raise PolicyFileError(f"{record['path']}: unknown algorithm {algo!r} (this version knows "
                              f"{', '.join(ALGORITHMS)})")
    return ALGORITHMS[algo].rebuild_policy(record, spec, device)


def load_policy(source: str | Path, *, device: str | torch.device = "cpu", best: bool = False):
    """The trained policy of a run, ready to act: a TensorDict module ``"observation" -> "action"``.

    Args:
        source: a run directory (its ``policy.pt``, or ``policy_best.pt`` with ``best=True``) or a policy file.

    Keyword Args:
        device: where the policy runs. Defaults to ``"cpu"``.
        best (bool): the best-evaluated policy instead of the final one (run directories only).

    The record (algorithm, env id, config, info) is kept as ``policy.record`` (without the weights). The policy is
    for acting: in eval mode, its parameters without ``requires_grad`` (actions carry no graph); call
    ``policy.requires_grad_(True)`` to fine-tune it.
    """
    record = read_policy_file(source, best=best)
    policy = _rebuild(record, device).to(device)
    try:
        policy.load_state_dict(record.pop("state_dict"))
    except RuntimeError as err:
        raise PolicyFileError(f"{record['path']}: weights do not fit the recorded networks ({err})") from None
    policy.eval().requires_grad_(False)
    policy.record = record
    return policy


class _ObservationToAction(nn.Module):
    """``observation -> action`` as a plain tensor function (what an exported file computes)."""

    def __init__(self, policy: nn.Module) -> None:
        super().__init__()
        self.policy = policy

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        from tensordict import TensorDict

        td = TensorDict({"observation": observation}, batch_size=observation.shape[:-1])
        return self.policy(td).get("action")


def policy_actions(policy, observation) -> torch.Tensor:
    """Actions of a TensorDict ``policy`` for ``[B, obs_dim]`` observations (no gradient).

    ``observation`` may be a tensor or an array (e.g. gymnasium's float64 NumPy observations): it is cast once,
    here, to the dtype and device of the policy's parameters.
    """
    reference = next(iter(policy.parameters()), None)
    dtype = reference.dtype if reference is not None else torch.get_default_dtype()
    device = reference.device if reference is not None else None
    observation = torch.as_tensor(observation, dtype=dtype, device=device)
    with torch.no_grad():
        return _ObservationToAction(policy)(observation)


def onnx_external_data(path: str | Path) -> Path:
    """Where the weights of an ONNX file too large to hold them go: ``<file>.data`` beside it (the name the file
    itself records, so the pair can be moved together)."""
    path = Path(path)
    return path.with_name(path.name + ".data")


def _onnx_weight_bytes(program) -> int:
    return sum(value.const_value.nbytes for value in program.model.graph.initializers.values()
               if value.const_value is not None)


def _save_onnx(program, path: Path) -> None:
    """Writes ``program`` to ``path`` with its weights inside; above :data:`ONNX_EMBED_LIMIT` bytes of weights
    (protobuf cannot hold 2 GiB) they go to :func:`onnx_external_data` instead. Either way the files are written
    under their final names in a scratch directory beside ``path`` and renamed into place (the weights first),
    and a weights file an earlier export left under that name is removed when this one embeds them."""
    data = onnx_external_data(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=f".{path.name}.", dir=path.parent) as scratch:
        staged = Path(scratch) / path.name
        program.save(staged, external_data=_onnx_weight_bytes(program) > ONNX_EMBED_LIMIT)
        staged_data = onnx_external_data(staged)
        if staged_data.exists():
            os.replace(staged_data, data)
        else:
            data.unlink(missing_ok=True)
        os.replace(staged, path)


def export_policy(source, path: str | Path, fmt: str, *, best: bool = False) -> Path:
    """Writes a standalone ``observation [B, obs_dim] -> action [B, act_dim]`` file (see the module's table).

    Args:
        source (str | Path | nn.Module): a run directory, a policy file or a policy from :func:`load_policy`.
        path: the file to write.
        fmt: ``"pt2"`` (``torch.export``), ``"onnx"`` (``torch.onnx.export``) or ``"torchscript"``.

    Returns:
        ``path``. An ONNX file holds its weights; only above :data:`ONNX_EMBED_LIMIT` bytes of weights are they
        written beside it as :func:`onnx_external_data` (``<path>.data``), which must travel with it.
    """
    if fmt not in EXPORT_FORMATS:
        raise ValueError(f"--export {fmt!r}: expected one of {', '.join(EXPORT_FORMATS)}")
    policy = source if isinstance(source, nn.Module) else load_policy(source, best=best)
    algo = policy.record["algo"]
    if fmt == "torchscript" and ALGORITHMS[algo].policy_samples:
        raise ValueError(f"--export torchscript: {algo}'s policy samples (best-of-N candidates), which TorchScript "
                         f"tracing cannot carry; use --export pt2 (same actions for the same torch seed) or onnx")
    # tracing would leave fake tensors in the loss' cached parameters: export a copy
    module = _ObservationToAction(copy.deepcopy(policy)).eval()
    example = torch.zeros(2, policy.record["obs_dim"])
    path = Path(path)
    with torch.no_grad():
        if fmt == "pt2":
            program = torch.export.export(module, (example,), dynamic_shapes=({0: torch.export.Dim("batch")},))
            with atomic_path(path, suffix=".pt2") as tmp:
                torch.export.save(program, tmp)
        elif fmt == "torchscript":
            traced = torch.jit.trace(module, (example,), check_trace=False)
            with atomic_path(path, suffix=".ts") as tmp:
                traced.save(str(tmp))
        else:
            for package in ("onnx", "onnxscript"):
                try:
                    __import__(package)
                except ImportError:
                    raise ImportError(f"--export onnx needs the {package!r} package: "
                                      f"pip install \"torchrl_bail[export]\"") from None
            program = torch.onnx.export(module, (example,), input_names=["observation"], output_names=["action"],
                                        dynamic_shapes=({0: "batch"},), dynamo=True, verbose=False)
            _save_onnx(program, path)
    return path
