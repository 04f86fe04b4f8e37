"""Many seeds in one process: ``S`` copies of one algorithm trained as one, their networks stacked.

Each seed's algorithm is built on its own, under its own seed, exactly as a single-seed run builds it; a
:class:`SeedStack` then stacks the ``S`` algorithms' parameters (and their target networks' copies) along a new
*seed dimension* of one host algorithm (one more of the same class and config), so that one update step of the host
serves every seed:

* every ``nn.Linear`` of the host becomes a :class:`SeedStackedLinear`: a weight ``[S, out, in]`` applied to inputs
  ``[S, *B, in]`` by one batched matrix product (:func:`linear`), row ``s`` with seed ``s``'s weights;
* the host sees mini-batches ``[S, B]`` (row ``s`` sampled from seed ``s``'s data by seed ``s``'s own random stream,
  :class:`SeedBatchSampler`, with the ``torch.randint`` call of a single-seed run's sampler; the stream is a copy of
  the global one right after seed ``s``'s algorithm was built, on CUDA a CUDA generator seeded with ``s``, so row
  ``s`` is the mini-batch the single-seed run draws); its losses reduce ``[S, B]`` batches per seed (the mean over
  ``B``) and then average over the seeds, so a gradient hook multiplies every stacked parameter's gradient by
  ``S``: each seed's slice receives exactly its own loss' gradient, and Adam (elementwise) over the stacked tensors
  is per-seed Adam; BEAR's Lagrange multiplier and MARWIL's ``c2`` are one per seed;
* BAIL fits the ``S`` upper envelopes as one stacked network (:func:`~torchrl_bail.training.envelope.fit_upper_envelope`
  of ``S`` networks, :class:`SeedModules`): each seed has its own split, epoch shuffles, validation loss, patience
  counter, reverts and best weights, and selects its best actions under its own envelope; Progressive BAIL keeps
  per-seed validation sets and early-stopping trackers on slices of the stacked envelopes and selects inside each
  seed's row of the mini-batch;
* the evaluation policy sees observations ``[S, N, obs_dim]`` (:class:`~torchrl_bail.evaluation.Evaluator` of ``S``
  seeds, the ``S x episodes`` test episodes in one step loop) and plays each seed's policy on its own row;
  each seed gets the reset seeds its single-seed run uses.

One seed is not a stack of one. A seed dimension of size 1 would send every layer through a batched matrix product,
which rounds differently from the plain one, so the functions that take a list of seeds keep a list of one
unstacked: :func:`torchrl_bail.training.trainer.make_trainee` trains one algorithm itself, :class:`SeedModules` of one
module
is that module, and an :class:`~torchrl_bail.evaluation.Evaluator` of one seed plays a ``[N, obs_dim]`` policy. A
single-seed run is thereby the run it was before seeds could be stacked, to every digit.

:meth:`SeedStack.unstack` writes the trained slices (parameters, target networks, per-seed buffers, optimizer
states) back into the ``S`` original algorithms, which then save their policies, checkpoints and summaries exactly
as a single-seed run does. Using ``seeds=`` from the command line, its outputs, resuming and what matches a
single-seed run: the docs' "Many seeds in one process" page (``docs/guides/many-seeds.md``).

Examples:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_bail.algorithms.bc import BehaviourCloning
    >>> from torchrl_bail.configuration.config_builders import algo_config
    >>> from torchrl_bail.modules import action_spec_from_bounds
    >>> config = algo_config("bc", batch_size=8, policy={"hidden": [16]})
    >>> def build(seed):
    ...     _ = torch.manual_seed(seed)
    ...     return BehaviourCloning(4, action_spec_from_bounds([-1.0] * 2, [1.0] * 2), config)
    >>> stack = SeedStack([build(1), build(2), build(3)])
    >>> batch = TensorDict({"observation": torch.randn(3, 8, 4), "action": torch.rand(3, 8, 2) * 2 - 1}, [3, 8])
    >>> stack.update(batch)["loss_bc"].shape  # the loss' mean over the seeds
    torch.Size([])
    >>> stack.policy(TensorDict({"observation": torch.randn(3, 5, 4)}, [3, 5]))["action"].shape
    torch.Size([3, 5, 2])
    >>> stack.unstack()  # the three BehaviourCloning objects now hold their trained weights
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from typing import Any

import torch
from tensordict import TensorDictBase, TensorDictParams
from torch import nn

__all__ = ["SeedBatchSampler", "SeedModules", "SeedSlice", "SeedStack", "SeedStackedLinear", "StackedTrainee",
           "linear", "prepare_seeds", "stack_modules", "unstack_modules"]

_TARGET = "target_"


def linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None = None) -> torch.Tensor:
    """``F.linear`` for one network (``weight [out, in]``) or for ``S`` seed-stacked ones (``weight [S, out, in]``,
    ``bias [S, out]``, input ``[S, *B, in]``: one batched matrix product, row ``s`` through seed ``s``'s layer).

    Examples:
        >>> w, b, x = torch.randn(3, 5, 4), torch.randn(3, 5), torch.randn(3, 7, 4)
        >>> torch.allclose(linear(x, w, b)[1], nn.functional.linear(x[1], w[1], b[1]), atol=1e-6)
        True
    """
    if weight.ndim == 2:
        return nn.functional.linear(x, weight, bias)
    seeds = weight.shape[0]
    if x.ndim < 2 or x.shape[0] != seeds:
        raise ValueError(f"a layer stacked over {seeds} seeds needs inputs [S={seeds}, ..., in], got {tuple(x.shape)}")
    flat = x.reshape(seeds, -1, x.shape[-1])
    out = (torch.bmm(flat, weight.transpose(-1, -2)) if bias is None
           else torch.baddbmm(bias.unsqueeze(-2), flat, weight.transpose(-1, -2)))
    return out.reshape(*x.shape[:-1], weight.shape[-2])


class SeedStackedLinear(nn.Linear):
    """An ``nn.Linear`` whose weights may carry a leading seed dimension (see :func:`linear`)."""

    def forward(self, input: torch.Tensor) -> torch.Tensor:  # noqa: A002 - nn.Linear's signature
        return linear(input, self.weight, self.bias)


def stack_modules(modules: Sequence[nn.Module]) -> nn.Module:
    """One module of ``modules[0]``'s architecture holding the ``S`` modules' parameters stacked along a leading seed
    dimension (its ``nn.Linear`` layers become :class:`SeedStackedLinear`): inputs ``[S, *B, in]``, row ``s``
    through ``modules[s]``. Buffers are taken from ``modules[0]`` (constants). :func:`unstack_modules` writes the
    slices back.

    Examples:
        >>> nets = [nn.Sequential(nn.Linear(3, 4), nn.ReLU(), nn.Linear(4, 1)) for _ in range(2)]
        >>> x = torch.randn(2, 5, 3)
        >>> torch.allclose(stack_modules(nets)(x)[1], nets[1](x[1]), atol=1e-6)
        True
    """
    stacked = copy.deepcopy(modules[0])
    for layer in stacked.modules():
        if type(layer) is nn.Linear:
            layer.__class__ = SeedStackedLinear
    with torch.no_grad():
        for name, param in stacked.named_parameters():
            param.data = torch.stack([m.get_parameter(name).detach() for m in modules]).clone()
    return stacked


def unstack_modules(stacked: nn.Module, modules: Sequence[nn.Module]) -> None:
    """Copies seed ``s``'s slice of ``stacked`` (see :func:`stack_modules`) into ``modules[s]``'s parameters."""
    with torch.no_grad():
        for name, param in stacked.named_parameters():
            for s, module in enumerate(modules):
                module.get_parameter(name).copy_(param[s])


class SeedSlice:
    """Seed ``s``'s view of a seed-stacked module, as far as saving and loading weights goes: ``state_dict()`` holds
    views of its slices of the parameters (the buffers as they are) under the single module's keys, and
    ``load_state_dict`` writes into those slices. What per-seed early stopping
    (:class:`~torchrl_bail.training.envelope.EarlyStoppingTracker`,
    :class:`~torchrl_bail.training.envelope.BestWeights`) records and
    restores.

    Examples:
        >>> net = stack_modules([nn.Linear(2, 1), nn.Linear(2, 1)])
        >>> one = SeedSlice(net, 1)
        >>> one.state_dict()["weight"].shape
        torch.Size([1, 2])
        >>> one.load_state_dict({"weight": torch.zeros(1, 2), "bias": torch.zeros(1)})
        >>> float(net.weight[1].abs().sum()), bool(net.weight[0].abs().sum() > 0)
        (0.0, True)
    """

    def __init__(self, module: nn.Module, seed_index: int) -> None:
        self.module = module
        self.seed_index = int(seed_index)

    def state_dict(self) -> dict[str, torch.Tensor]:
        params = dict(self.module.named_parameters())
        return {name: (params[name].detach()[self.seed_index] if name in params else value)
                for name, value in self.module.state_dict().items()}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        with torch.no_grad():
            for name, target in self.state_dict().items():
                target.copy_(state[name])



class SeedModules:
    """``S`` modules of one architecture, one per seed, as one module to train (BAIL's envelopes in
    :func:`~torchrl_bail.training.envelope.fit_upper_envelope`).

    For ``S > 1``, :attr:`module` holds the modules' parameters stacked along a leading seed dimension
    (:func:`stack_modules`: inputs ``[S, *B, in]``, row ``s`` through ``modules[s]``), :attr:`seeds` is each seed's
    view of it (:class:`SeedSlice`), :meth:`batch` stacks per-seed tensors into that layout and :meth:`unstack` writes
    the trained slices back into the modules. One module is its own stack: :attr:`module` and ``seeds[0]`` are the
    module itself, :meth:`batch` returns the one seed's tensor unchanged and :meth:`unstack` has nothing to write. The
    module then sees the very inputs, shapes and matrix products of a fit that never heard of seeds, so a single-seed
    fit is that fit to every digit (a seed dimension of size 1 would round differently: see the module docstring).

    Args:
        modules: the ``S >= 1`` modules, trained in place (for ``S > 1`` from :meth:`unstack` on).

    Examples:
        >>> nets = [nn.Linear(2, 1), nn.Linear(2, 1)]
        >>> both, one = SeedModules(nets), SeedModules(nets[:1])
        >>> both.module.weight.shape, one.module is nets[0], one.seeds == [nets[0]]
        (torch.Size([2, 1, 2]), True, True)
        >>> both.batch([torch.zeros(5), torch.ones(5)]).shape, one.batch([torch.zeros(5)]).shape
        (torch.Size([2, 5]), torch.Size([5]))
    """

    def __init__(self, modules: Sequence[nn.Module]) -> None:
        self.modules = list(modules)
        if not self.modules:
            raise ValueError("SeedModules needs at least one module")
        self.stacked = len(self.modules) > 1
        #: the module to train: the stack, or the one module itself
        self.module = stack_modules(self.modules) if self.stacked else self.modules[0]
        #: per seed, what its weights are saved from and loaded into (early stopping's best-weights record)
        self.seeds: list = ([SeedSlice(self.module, s) for s in range(len(self.modules))] if self.stacked
                            else [self.module])

    def batch(self, tensors: Sequence[torch.Tensor]) -> torch.Tensor:
        """One tensor per seed in :attr:`module`'s batch layout: stacked along a new leading seed dimension, or the
        one seed's tensor itself."""
        return torch.stack(list(tensors)) if self.stacked else tensors[0]

    def unstack(self) -> None:
        """Writes each seed's trained slice of :attr:`module` back into its module (nothing to write for one)."""
        if self.stacked:
            unstack_modules(self.module, self.modules)


def _entries(algorithm) -> list[tuple[str, torch.Tensor, int]]:
    """``(name, tensor, seed dim)`` of everything a seed owns: every parameter of the algorithm's modules and every
    target-network copy of one (``target_<name>`` buffers of TorchRL losses), in a fixed order. The seed dimension
    follows the batch dimensions of the :class:`~tensordict.TensorDictParams` holding the tensor (the twin critics'
    ``[2, ...]`` stack: ``[2, S, ...]``)."""
    out, seen = [], set()
    for key, module in algorithm.modules.items():
        batch_dims = {prefix: m.batch_dims for prefix, m in module.named_modules()
                      if isinstance(m, TensorDictParams) and prefix}
        params = dict(module.named_parameters())
        buffers = {name: b for name, b in module.named_buffers()
                   if name.startswith(_TARGET) and name[len(_TARGET):] in params}
        for name, tensor in [*params.items(), *buffers.items()]:
            if id(tensor) in seen:
                continue
            seen.add(id(tensor))
            prefix = name.rsplit(".", 1)[0]
            while prefix and prefix not in batch_dims:
                prefix = prefix.rsplit(".", 1)[0] if "." in prefix else ""
            out.append((f"{key}.{name}", tensor, batch_dims.get(prefix, 0)))
    return out


def _reachable_modules(algorithm) -> dict[str, nn.Module]:
    """Every ``nn.Module`` the algorithm reaches through attributes (its registered modules and the networks TorchRL
    losses keep outside their module tree), under the first attribute path that reaches it, the attributes
    visited in name order (so that two algorithms built alike give the same paths, whatever ran since)."""
    found: dict[int, tuple[str, nn.Module]] = {}

    def visit(obj: Any, path: str) -> None:
        if isinstance(obj, nn.Module):
            if id(obj) in found:
                return
            found[id(obj)] = (path, obj)
            items = {**vars(obj), **obj._modules}.items()
        elif isinstance(obj, (list, tuple)):
            items = [(str(i), v) for i, v in enumerate(obj)]
        elif isinstance(obj, dict):
            items = [(str(k), v) for k, v in obj.items()]
        else:
            return
        for name, child in sorted(items, key=lambda kv: kv[0]):
            if isinstance(child, (nn.Module, list, tuple, dict)):
                visit(child, f"{path}.{name}" if path else name)

    visit(vars(algorithm), "")
    return {path: module for path, module in found.values()}


def _other_buffers(algorithm, stacked_ids: set[int]) -> dict[str, torch.Tensor]:
    """The buffers :func:`_entries` leaves unstacked, of every reachable module, by path (constants, counters such
    as BEAR's warm-start clock, and state a loss keeps per seed itself such as MARWIL's ``c^2``)."""
    found: dict[str, torch.Tensor] = {}
    seen: set[int] = set(stacked_ids)
    for path, module in _reachable_modules(algorithm).items():
        for name, b in module.named_buffers(recurse=False):
            if id(b) not in seen:
                seen.add(id(b))
                found[f"{path}.{name}"] = b
    return found


class SeedStack:
    """``S`` independently initialised copies of one algorithm, trained by one update step (see the module
    docstring); :class:`StackedTrainee` trains it (:func:`torchrl_bail.training.trainer.train`).

    Args:
        algorithms: ``S`` algorithms of one class and config, each built (and prepared) as its single-seed run
            builds it. They are left untouched until :meth:`unstack` writes the trained state back into them.
    """

    def __init__(self, algorithms: Sequence[Any]) -> None:
        self.algorithms = list(algorithms)
        if not self.algorithms:
            raise ValueError("SeedStack needs at least one algorithm")
        first = self.algorithms[0]
        if any(type(a) is not type(first) for a in self.algorithms):
            raise ValueError("SeedStack needs algorithms of one class")
        self.seeds_count = len(self.algorithms)
        with torch.random.fork_rng(devices=[]):  # a fresh build, whose random initialisation leaves the global
            # stream alone and is overwritten next (a deep copy would copy the first seed's state for nothing)
            self.host = host = type(first)(first.obs_dim, first.action_spec, first.config, first.device)
        for attr in ("name", "batch_size", "epochs", "samples_per_update", "device"):
            setattr(self, attr, getattr(host, attr))
        self._entries = _entries(host)
        per_seed = [_entries(a) for a in self.algorithms]
        for s, entries in enumerate(per_seed):
            if [n for n, _, _ in entries] != [n for n, _, _ in self._entries]:
                raise ValueError(f"algorithm {s} is not built like algorithm 0: SeedStack needs one config")
        self._seed_tensors = [[t for _, t, _ in entries] for entries in per_seed]
        self._stacked_ids = {id(t) for _, t, _ in self._entries}
        for layer in _reachable_modules(host).values():
            if type(layer) is nn.Linear:
                layer.__class__ = SeedStackedLinear
        self.restack()
        scale = float(self.seeds_count)
        for _, tensor, _ in self._entries:
            if isinstance(tensor, nn.Parameter) and tensor.requires_grad:
                tensor.register_hook(lambda grad: grad * scale)

    # -- what the training loop calls -------------------------------------------------------------------------------
    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        """One update of every seed on a ``[S, B]`` mini-batch (row ``s`` for seed ``s``)."""
        return self.host.update(batch)

    @property
    def policy(self):
        """The host's policy: observations ``[S, N, obs_dim]`` in, each row acted on by its seed's policy."""
        return self.host.policy

    # -- moving state between the stack and the seeds' own algorithms ---------------------------------------------
    def restack(self) -> None:
        """Copies the seeds' current state (weights, target networks, optimizer moments, the algorithm's own
        per-seed attributes through its ``stack_attributes`` hook) into the stack."""
        with torch.no_grad():
            for i, (_, tensor, dim) in enumerate(self._entries):
                stacked = torch.stack([seed[i].detach() for seed in self._seed_tensors], dim=dim)
                if tensor.shape == stacked.shape:  # stacked already: in place, so cached views stay valid
                    tensor.data.copy_(stacked)
                else:
                    tensor.data = stacked
        for key, optimizer in self.host.optimizers.items():
            self._stack_optimizer_state(key, optimizer)
        if hasattr(self.host, "stack_attributes"):
            self.host.stack_attributes(self.algorithms)

    def unstack(self) -> None:
        """Writes each seed's slice of the stack (weights, target networks, per-seed buffers such as MARWIL's
        ``c^2``, optimizer states, the algorithm's own per-seed attributes) back into its own algorithm."""
        count = self.seeds_count
        with torch.no_grad():
            for s, seed_tensors in enumerate(self._seed_tensors):
                for (_, tensor, dim), own in zip(self._entries, seed_tensors, strict=True):
                    own.data.copy_(tensor.detach().select(dim, s))  # in place: cached views stay valid
            host_buffers = _other_buffers(self.host, self._stacked_ids)
            for s, algorithm in enumerate(self.algorithms):
                own_buffers = _other_buffers(algorithm, {id(t) for t in self._seed_tensors[s]})
                for name, own in own_buffers.items():
                    tensor = host_buffers.get(name)
                    if tensor is None:
                        continue
                    if tensor.shape == own.shape:
                        own.copy_(tensor)
                    elif tensor.shape == (count, *own.shape):  # a loss keeps it per seed (MARWIL's c^2)
                        own.copy_(tensor[s])
                    else:
                        raise RuntimeError(f"buffer {name}: stacked shape {tuple(tensor.shape)} does not match "
                                           f"the seed's {tuple(own.shape)}")
        for key, optimizer in self.host.optimizers.items():
            self._unstack_optimizer_state(key, optimizer)
        if hasattr(self.host, "unstack_attributes"):
            self.host.unstack_attributes(self.algorithms)

    # -- checkpoints: one single-seed checkpoint per seed ---------------------------------------------------------
    def seed_checkpoints(self, state: dict[str, Any]) -> list[dict[str, Any]]:
        """The training loop's checkpoint ``state`` of the stack (per-seed ``evaluations``, ``[S]`` metric sums, the
        :class:`SeedBatchSampler`'s generators) split into one checkpoint per seed in the single-seed format of
        :func:`torchrl_bail.training.trainer.train`: the seed's own ``algorithm`` state (after :meth:`unstack`), and as
        ``rng["torch"]`` (or ``"torch_cuda"``) its mini-batch stream, where a single-seed run keeps it. Each can
        be resumed by the single-seed run of that seed, or all of them by the stacked run (:meth:`merge_checkpoints`;
        the stack's own global streams ride along under ``"stack_rng"``)."""
        self.unstack()
        count = self.seeds_count
        sampler = state["sampler"]
        out = []
        for j, algorithm in enumerate(self.algorithms):
            rng = dict(state["rng"])
            if sampler.get("device", "cpu") == "cpu":
                rng["torch"] = sampler["generators"][j]
            else:
                cuda = list(rng.get("torch_cuda", []))
                index = sampler.get("device_index", 0)
                cuda[index:index + 1] = [sampler["generators"][j]]
                rng["torch_cuda"] = cuda
            out.append({
                **state, "algorithm": algorithm.state_dict(), "evaluations": state["evaluations"][j],
                "metric_sums": {k: (v[j] if torch.is_tensor(v) and v.ndim and v.shape[0] == count else v)
                                for k, v in state["metric_sums"].items()},
                "rng": rng, "sampler": {}, "stack_rng": state["rng"],
                "stack_mean_metrics": [k for k, v in state["metric_sums"].items()
                                       if not (torch.is_tensor(v) and v.ndim and v.shape[0] == count)],
            })
        return out

    @staticmethod
    def merge_checkpoints(states: Sequence[dict[str, Any]], sampler: SeedBatchSampler) -> dict[str, Any]:
        """The stack's loop state from ``S`` seeds' checkpoints (:meth:`seed_checkpoints`, or single-seed runs' own,
        when all stopped at the same iteration); the seeds' algorithms must already hold their ``algorithm`` state.
        """
        iterations = sorted({int(st["iteration"]) for st in states})
        if len(iterations) > 1:
            raise ValueError(f"the seeds' checkpoints stopped at different iterations {iterations}: a stacked run "
                             "continues seeds that stopped together; continue them one by one (seed=<s>) instead")
        keys = {k for st in states for k in st["metric_sums"]}
        means = set(states[0].get("stack_mean_metrics", ()))  # the losses' means over the seeds stay scalars

        def stacked_sum(k):
            if k in means:
                return states[0]["metric_sums"][k]
            values = [torch.as_tensor(st["metric_sums"].get(k, 0.0)) for st in states]
            return torch.stack([v.reshape(()) for v in values])

        if sampler.device.type == "cpu":
            generators = [st["rng"]["torch"] for st in states]
        else:
            generators = [st["rng"]["torch_cuda"][sampler.device.index or 0] for st in states]
        return {
            **states[0], "evaluations": [st["evaluations"] for st in states],
            "metric_sums": {k: stacked_sum(k) for k in keys},
            "rng": states[0].get("stack_rng", states[0]["rng"]), "sampler": {"generators": generators},
        }

    def _optimizer_pairs(self, key: str, optimizer: torch.optim.Optimizer, s: int):
        """``(host parameter, seed s's parameter, seed dim)`` for the optimizer ``key``, in parameter order."""
        dims = {id(t): d for _, t, d in self._entries}
        own = [p for g in self.algorithms[s].optimizers[key].param_groups for p in g["params"]]
        host = [p for g in optimizer.param_groups for p in g["params"]]
        return [(h, o, dims.get(id(h), 0)) for h, o in zip(host, own, strict=True)]

    def _stack_optimizer_state(self, key: str, optimizer: torch.optim.Optimizer) -> None:
        pairs = [self._optimizer_pairs(key, optimizer, s) for s in range(self.seeds_count)]
        for i, (host_param, own_param, dim) in enumerate(pairs[0]):
            states = [self.algorithms[s].optimizers[key].state.get(pairs[s][i][1]) for s in range(self.seeds_count)]
            if not states[0]:
                optimizer.state.pop(host_param, None)
                continue
            optimizer.state[host_param] = {
                name: (torch.stack([st[name] for st in states], dim=dim).clone()
                       if torch.is_tensor(value) and value.shape == own_param.shape and value.ndim else
                       (value.clone() if torch.is_tensor(value) else value))
                for name, value in states[0].items()
            }

    def _unstack_optimizer_state(self, key: str, optimizer: torch.optim.Optimizer) -> None:
        for s, algorithm in enumerate(self.algorithms):
            own_optimizer = algorithm.optimizers[key]
            for host_param, own_param, dim in self._optimizer_pairs(key, optimizer, s):
                state = optimizer.state.get(host_param)
                if not state:
                    continue
                own_optimizer.state[own_param] = {
                    name: (value.select(dim, s).clone() if torch.is_tensor(value) and value.shape == host_param.shape
                           and value.ndim else (value.clone() if torch.is_tensor(value) else value))
                    for name, value in state.items()
                }


class SeedBatchSampler:
    """Mini-batches ``[S, B]`` for a :class:`SeedStack`: row ``s`` is drawn with replacement from seed ``s``'s data by
    seed ``s``'s own generator, with the very call a single-seed run's :class:`~torchrl.data.RandomSampler` makes
    (``torch.randint(0, len(data), (B,))``), so each row equals the mini-batch the single-seed run draws.

    Args:
        datas: per seed, the TensorDict ``[N_s]`` its algorithm prepared (the same object may serve every seed).
        batch_size (int): ``B``.
        generators: per seed, the :class:`torch.Generator` (on the data's device) its indices are drawn from.
    """

    def __init__(self, datas: Sequence[TensorDictBase], batch_size: int, generators: Sequence[torch.Generator],
                 device=None) -> None:
        if len(datas) != len(generators):
            raise ValueError(f"{len(datas)} data sets but {len(generators)} generators: one of each per seed")
        if any(len(d) == 0 for d in datas):
            raise ValueError("the training data of a seed is empty: nothing to sample mini-batches from")
        shared = all(_same_tensors(d, datas[0]) for d in datas)
        self.storage = (datas[0] if shared else torch.cat(list(datas))).to(device)
        sizes = [len(d) for d in datas]
        self.sizes = sizes
        offsets = [0] * len(sizes) if shared else [sum(sizes[:i]) for i in range(len(sizes))]
        self.offsets = torch.tensor(offsets, device=self.device).unsqueeze(-1)
        self.batch_size = int(batch_size)
        self.generators = list(generators)

    def __len__(self) -> int:
        return len(self.storage)

    def sample(self) -> TensorDictBase:
        index = torch.stack([torch.randint(0, n, (self.batch_size,), generator=g, device=self.device)
                             for n, g in zip(self.sizes, self.generators, strict=True)])
        return self.storage[index + self.offsets]

    @property
    def device(self) -> torch.device:
        """Where the data lie and the indices are drawn."""
        if self.storage.device is not None:
            return self.storage.device
        return next(iter(self.storage.values(True, True))).device

    def state_dict(self) -> dict[str, Any]:
        return {"generators": [g.get_state() for g in self.generators], "device": self.device.type,
                "device_index": self.device.index or 0}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        for g, s in zip(self.generators, state["generators"], strict=True):
            g.set_state(s)


class StackedTrainee:
    """``S`` seeds trained as one (:func:`torchrl_bail.training.trainer.train`' trainee): ``stack``'s update on the
    ``[S, B]`` mini-batches of ``sampler``, each seed's checkpoint a single-seed one
    (:meth:`SeedStack.seed_checkpoints`).

    Training scalars: a ``[S]`` value (a per-seed diagnostic) is logged per seed under its name, a plain one (a
    loss, averaged over the seeds by the host's update) by every seed as ``<name>_mean_over_seeds``.
    """

    layout = "networks stacked"

    def __init__(self, stack: SeedStack, sampler: SeedBatchSampler) -> None:
        self.stack, self.sampler = stack, sampler
        self.seeds = stack.seeds_count
        self.name, self.epochs, self.samples_per_update = stack.name, stack.epochs, stack.samples_per_update

    @property
    def policy(self):
        return self.stack.policy

    def sample(self) -> TensorDictBase:
        return self.sampler.sample()

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        return self.stack.update(batch)

    def plan_updates(self, updates: int) -> None:
        for algorithm in (self.stack.host, *self.stack.algorithms):
            algorithm.plan_updates(updates)

    def compile(self, mode: bool | str) -> None:
        """Compiles the host's update, the one all seeds share."""
        self.stack.host.compile(mode)

    def seed_metrics(self, sums: dict[str, Any]) -> list[dict[str, Any]]:
        def per_seed(value) -> bool:
            return torch.is_tensor(value) and bool(value.ndim)

        return [{(k if per_seed(v) else f"{k}_mean_over_seeds"): (v[j] if per_seed(v) else v) for k, v in sums.items()}
                for j in range(self.seeds)]

    def checkpoints(self, state: dict[str, Any]) -> list[dict[str, Any]]:
        return self.stack.seed_checkpoints({**state, "sampler": self.sampler.state_dict()})

    def restore(self, checkpoints: list[dict[str, Any]]) -> dict[str, Any]:
        state = self.stack.merge_checkpoints(checkpoints, self.sampler)
        self.sampler.load_state_dict(state["sampler"])
        return state

    def algorithms(self) -> list[Any]:
        self.stack.unstack()
        return self.stack.algorithms


def prepare_seeds(algorithms: Sequence[Any], data: TensorDictBase, contexts: Sequence[Any]) -> list[TensorDictBase]:
    """Each seed's training data (``S >= 1`` seeds): the algorithm class' ``prepare_seeds(algorithms, data, contexts)``
    when it has one (BAIL fits its ``S`` envelopes in one fit, and its ``prepare`` is that of a list of one), else
    each algorithm's own ``prepare`` with its seed's context, as its single-seed run calls it. A subclass that
    overrides ``prepare`` below the class defining ``prepare_seeds`` (a BAIL of your own with another selection) has
    its ``prepare`` called, seed by seed: the override is never bypassed."""
    cls = type(algorithms[0])
    own = getattr(cls, "prepare_seeds", None)
    if own is not None and issubclass(_definer(cls, "prepare_seeds"), _definer(cls, "prepare")):
        return own(algorithms, data, contexts)
    return [algorithm.prepare(data, ctx) for algorithm, ctx in zip(algorithms, contexts, strict=True)]


def _definer(cls: type, attribute: str) -> type:
    """The class of ``cls``' MRO that defines ``attribute`` (``object`` when none does)."""
    return next((c for c in cls.__mro__ if attribute in vars(c)), object)


def _same_tensors(a: TensorDictBase, b: TensorDictBase) -> bool:
    """Whether two TensorDicts view the same tensors (two seeds that kept the whole batch share one storage)."""
    if a is b:
        return True
    keys = sorted(a.keys(True, True), key=str)
    return (a.batch_size == b.batch_size and keys == sorted(b.keys(True, True), key=str)
            and all(a.get(k).data_ptr() == b.get(k).data_ptr() and a.get(k).shape == b.get(k).shape for k in keys))
