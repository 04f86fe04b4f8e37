"""What the one training loop needs from an algorithm.

An algorithm owns its networks, losses and optimizers and contributes three things to
:func:`torchrl_bail.training.trainer.train`: a :meth:`~Algorithm.prepare` stage that turns the batch (with its returns)
into the data the loop samples from (BAIL fits its envelope and keeps the best actions there), an
:meth:`~Algorithm.update` step on one mini-batch, and a deterministic :attr:`~Algorithm.policy` to evaluate.
Every algorithm is built from its config group, ``Algorithm(obs_dim, action_spec, config, device)``: ``config``
is the ``algo`` node of the command line, :func:`torchrl_bail.configuration.config_builders.algo_config` (the defaults
of
``conf/algo/<name>.yaml`` with overrides) or a plain nested mapping (the keys it leaves out take the yaml's
values). The yaml files are the one place an algorithm's default values live; the constructors hold none. The
schedule (mini-batch size and length in epochs of 10^6 samples) comes from the config too.
"""

from __future__ import annotations

import copy
from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.data import TensorSpec

from torchrl_bail.configuration.config import COMPILE_MODES, is_compile_setting
from torchrl_bail.configuration.config_builders import checked_algo_config

__all__ = ["REGISTRY", "Algorithm", "PrepareContext"]

#: every algorithm class by its ``name`` (``algo.name``), filled as each class that sets ``name`` is defined
#: (:meth:`Algorithm.__init_subclass__`); :data:`torchrl_bail.algorithms.ALGORITHMS` is this, in the schemas' order
REGISTRY: dict[str, type[Algorithm]] = {}


class PrepareContext:
    """Where :meth:`Algorithm.prepare` may write artifacts (plots) and log scalars.

    Attributes:
        run_dir: the run directory (``None`` when nothing should be written).
        logger: a TorchRL logger or ``None``.
        generator: a seeded :class:`torch.Generator` for data splits.
        progress: whether to show progress bars.
    """

    def __init__(self, run_dir: Path | None = None, logger=None, generator: torch.Generator | None = None,
                 progress: bool = False) -> None:
        self.run_dir = None if run_dir is None else Path(run_dir)
        self.logger = logger
        self.generator = generator if generator is not None else torch.Generator().manual_seed(0)
        self.progress = progress

    def log(self, name: str, value: float, step: int = 0) -> None:
        if self.logger is not None:
            self.logger.log_scalar(name, float(value), step=step)


class Algorithm(ABC):
    """Base class: networks in :attr:`modules`, optimizers in :attr:`optimizers`, a schedule, a policy.

    Subclasses set ``name`` (their ``conf/algo/<name>.yaml``; setting it registers the class in :data:`REGISTRY`),
    build their networks/losses/optimizers in ``__init__`` from :attr:`config` and implement :meth:`update`. The
    defaults of :meth:`prepare` (train on the whole batch), :meth:`summary` (nothing to add),
    :meth:`rebuild_policy` (the policy of a ``policy.pt`` file) and :attr:`seed_stack_refusal` (``seeds=`` stacks
    it) suit most baselines. What other modules look up by an algorithm's name lives here, on its class.

    Args:
        obs_dim (int): observation size.
        action_spec (TensorSpec): the bounded action spec.
        config (DictConfig | Mapping): the algorithm's config group (see the module docstring); checked against its
            schema (:data:`torchrl_bail.configuration.algo_schemas.ALGO_SCHEMAS`) and kept, typed, as :attr:`config`.
        device: training device. Defaults to ``"cpu"``.
    """

    name: str = "algorithm"
    #: why ``seeds=`` cannot train this algorithm's seeds stacked (:mod:`torchrl_bail.core.stacking`), in a few words;
    #: ``None`` when it can
    seed_stack_refusal: str | None = None
    #: whether the evaluation policy draws random numbers (BCQ's and BEAR's best-of-N candidates): TorchScript
    #: tracing cannot carry them (:func:`torchrl_bail.evaluation.policy.export_policy`)
    policy_samples: bool = False

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "name" in vars(cls):
            REGISTRY[cls.name] = cls

    @classmethod
    def rebuild_policy(cls, record: dict[str, Any], action_spec: TensorSpec, device) -> nn.Module:
        """The evaluation policy of a ``policy.pt`` record (:func:`torchrl_bail.evaluation.policy.read_policy_file`),
        with
        fresh weights (:func:`~torchrl_bail.evaluation.policy.load_policy` loads the file's): the algorithm built from
        the
        record's config, its :attr:`policy` (a subclass whose policy needs less overrides this)."""
        return cls(record["obs_dim"], action_spec, record["config"]["algo"], device).policy

    def __init__(self, obs_dim: int, action_spec: TensorSpec, config, device: torch.device | str = "cpu") -> None:
        self.config = checked_algo_config(self.name, config)
        self.obs_dim = int(obs_dim)
        self.action_spec = action_spec
        self.batch_size = int(self.config.batch_size)
        self.epochs = float(self.config.epochs)
        #: samples one update counts towards an epoch (Progressive BAIL counts only its envelope's share)
        self.samples_per_update = float(self.batch_size)
        self.device = torch.device(device)
        self.modules: dict[str, nn.Module] = {}
        self.optimizers: dict[str, torch.optim.Optimizer] = {}

    # -- the three contributions to the training loop -------------------------------------------------
    def prepare(self, data: TensorDictBase, ctx: PrepareContext) -> TensorDictBase:
        """Returns the data the loop samples mini-batches from (default: the whole batch)."""
        return data

    def restore_prepared(self, data: TensorDictBase, ctx: PrepareContext) -> TensorDictBase:
        """On resume, after :meth:`load_state_dict`: the data :meth:`prepare` returned, without refitting.

        ``ctx`` carries the same generator state :meth:`prepare` saw and no logger or run directory (what prepare
        logged and plotted is already there). The default runs :meth:`prepare` again, which is exact and cheap
        when prepare fits nothing; an algorithm whose prepare fits a model (BAIL's envelope) overrides this to
        rebuild its output from the fitted state the checkpoint restored.
        """
        return self.prepare(data, ctx)

    def plan_updates(self, updates: int) -> None:
        """Told by the training loop, before its first update (and again when it resumes), how many updates the
        whole run makes: for a schedule over the run (IQL's cosine learning rate). The default ignores it."""
        return None

    @abstractmethod
    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        """One update on a mini-batch; returns detached scalars to log.

        It reads nothing back to the host (no ``.item()``, ``float(tensor)``, ``.cpu()``) and creates every tensor on
        :attr:`device`, so a GPU update never waits for the host (``tests/test_compile.py``).
        """

    # -- compiled updates ------------------------------------------------------------------------------
    #: the method :meth:`compile` compiles: the tensor work of one update, with no Python state that changes from
    #: one update to the next (an algorithm with such state keeps it in :meth:`update` around this method)
    compiled_method: str = "update"

    def compile(self, mode: bool | str = True, *, backend: str = "inductor", cudagraphs: bool | None = None) -> None:
        """Runs every later update through :func:`torch.compile` (the ``compile`` config key).

        Only the update is compiled; the modules and optimizers stay what they were, so :meth:`state_dict` keeps its
        keys and a compiled run checkpoints and resumes like an eager one (call this after
        :meth:`load_state_dict`). Random draws stay torch's own (inductor's ``fallback_random``): a compiled update
        consumes the same random streams as an eager one and agrees with it to float rounding
        (``tests/test_compile.py``). Compiled kernels round differently, so ``compile`` is part of a run's identity
        (its run directory and the config a checkpoint must match), not a run-only key.

        Args:
            mode: ``False`` (nothing to do), ``True`` (inductor's default mode) or a :func:`torch.compile` mode
                (:data:`torchrl_bail.configuration.config.COMPILE_MODES`); ``"reduce-overhead"`` replays CUDA graphs of
                the
                compiled pieces on a GPU.
            backend (str): the :func:`torch.compile` backend (``mode`` is inductor's only). Defaults to
                ``"inductor"``.
            cudagraphs (bool, optional): capture the whole compiled update, optimizer steps included, in one CUDA
                graph (:class:`tensordict.nn.CudaGraphModule`; CUDA only). Defaults to ``mode is True`` on a CUDA
                device.

        Examples:
            >>> from torchrl_bail.algorithms.bc import BehaviourCloning
            >>> from torchrl_bail.configuration.config_builders import algo_config
            >>> from torchrl_bail.modules import action_spec_from_bounds
            >>> config = algo_config("bc", policy={"hidden": [8]})
            >>> algo = BehaviourCloning(3, action_spec_from_bounds([-1.0], [1.0]), config)
            >>> algo.compile(backend="eager")
            >>> sorted(algo.state_dict()["modules"]["actor"])[:1]  # the modules themselves are untouched
            ['module.0.module.0.bias']
        """
        if mode is False:
            return
        if not is_compile_setting(mode):
            raise ValueError(f"compile must be false, true or one of {list(COMPILE_MODES[1:])}, got {mode!r}")
        if cudagraphs is None:
            cudagraphs = mode is True and self.device.type == "cuda"
        if cudagraphs and self.device.type != "cuda":
            raise ValueError(f"CUDA graphs need a CUDA device; this algorithm runs on {self.device}")
        import torch._dynamo.config
        import torch._inductor.config

        torch._inductor.config.fallback_random = True  # the eager random streams: same draws compiled or not
        # each optimizer's step() is one more compiled version of Optimizer.step's code (BEAR alone has four)
        torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, 64)
        torch._dynamo.config.accumulated_recompile_limit = max(torch._dynamo.config.accumulated_recompile_limit, 1024)
        options = {"mode": None if mode is True else mode} if backend == "inductor" else {}
        step = torch.compile(getattr(self, self.compiled_method), backend=backend, dynamic=False, **options)
        if cudagraphs:
            self._make_optimizers_capturable()
            step = _whole_update_graph(step, self.device)
        setattr(self, self.compiled_method, step)

    @property
    @abstractmethod
    def policy(self) -> TensorDictModuleBase:
        """The deterministic evaluation policy (reads ``"observation"``, writes ``"action"``)."""

    def summary(self) -> dict[str, Any]:
        """Extra fields for ``summary.json`` (e.g. BAIL's selected fraction)."""
        return {}

    # -- checkpoints -----------------------------------------------------------------------------------
    #: names of plain attributes (numbers, tensors, dicts of them) that change during training and belong in
    #: the checkpoint next to the modules and optimizers (early-stopping counters, prepare's summary, ...)
    state_attributes: tuple[str, ...] = ()

    def state_dict(self) -> dict[str, Any]:
        """Everything the rest of a run depends on: every module, every optimizer, the :attr:`state_attributes`.

        Loading it into a freshly built algorithm of the same config makes every later :meth:`update` produce
        the same numbers as the original object (given the same random streams).
        """
        return {
            "modules": {k: m.state_dict() for k, m in self.modules.items()},
            "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
            "attributes": {k: copy.deepcopy(getattr(self, k)) for k in self.state_attributes},  # all must exist
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Loads :meth:`state_dict` into this algorithm's modules and optimizers, in place; it shares no tensor
        with ``state`` (torch's ``Optimizer.load_state_dict`` keeps the moment tensors it is given, so loading from a
        live algorithm would tie the two algorithms' Adam moments together: they are copied here)."""
        for k, m in self.modules.items():
            m.load_state_dict(state["modules"][k])
        for k, o in self.optimizers.items():
            o.load_state_dict(copy.deepcopy(state["optimizers"][k]))
        for k, v in state.get("attributes", {}).items():
            setattr(self, k, copy.deepcopy(v))

    def __deepcopy__(self, memo: dict) -> Algorithm:
        """``copy.deepcopy(algorithm)``: an algorithm that trains on its own from this one's state.

        It is built afresh from the same config (the random draws of its initialisation do not touch the caller's
        streams), then loaded with a copy of :meth:`state_dict`; what :meth:`prepare` left behind is deep-copied
        over: attributes the constructor does not set, and those holding plain data (tensors that are no
        module's parameters or buffers, TensorDicts, numbers, strings and containers of them). Python's
        attribute-by-attribute copy would not do: a TorchRL loss holds its networks' parameters in a
        :class:`~tensordict.nn.TensorDictParams`, whose ``__deepcopy__`` clones them apart from the copied networks,
        so the copy's updates would move the loss's clones and never the networks its optimizers and policy use.
        The copy is eager (call :meth:`compile` on it again).

        Examples:
            >>> import copy
            >>> from tensordict import TensorDict
            >>> from torchrl_bail.algorithms.bc import BehaviourCloning
            >>> from torchrl_bail.configuration.config_builders import algo_config
            >>> from torchrl_bail.modules import action_spec_from_bounds
            >>> algo = BehaviourCloning(3, action_spec_from_bounds([-1.0], [1.0]),
            ...                         algo_config("bc", batch_size=8, policy={"hidden": [8]}))
            >>> twin = copy.deepcopy(algo)
            >>> before = [p.clone() for p in twin.actor.parameters()]
            >>> _ = twin.update(TensorDict({"observation": torch.randn(8, 3), "action": torch.zeros(8, 1)}, [8]))
            >>> all(not torch.equal(a, b) for a, b in zip(before, twin.actor.parameters()))  # the copy learns
            True
            >>> all(torch.equal(a, b) for a, b in zip(before, algo.actor.parameters()))  # the original does not
            True
        """
        with torch.random.fork_rng(devices=[self.device] if self.device.type == "cuda" else []):
            twin = type(self)(self.obs_dim, copy.deepcopy(self.action_spec, memo), copy.deepcopy(self.config, memo),
                              self.device)
        memo[id(self)] = twin
        twin.load_state_dict(copy.deepcopy(self.state_dict(), memo))
        module_state = {t.data_ptr() for m in self.modules.values() for t in [*m.parameters(), *m.buffers()]}
        for key, value in vars(self).items():  # what prepare left (validation sets, selections, counters)
            if key not in vars(twin) or _is_plain_data(value, module_state):
                setattr(twin, key, copy.deepcopy(value, memo))
        return twin

    def _make_optimizers_capturable(self) -> None:
        """Step counters on the device (``capturable``): a CUDA graph replays device kernels only, so an optimizer
        that kept its step count on the host would never count a replayed update."""
        for optimizer in self.optimizers.values():
            for group in optimizer.param_groups:
                group["capturable"] = True
            for state in optimizer.state.values():
                if torch.is_tensor(state.get("step")):
                    state["step"] = state["step"].to(self.device, torch.float32)


def _is_plain_data(value, module_state: set[int]) -> bool:
    """Data a deep copy may duplicate: no module, optimizer or object wired to them, no tensor that is a
    module's parameter or buffer (``module_state``: the ``data_ptr`` of each)."""
    if isinstance(value, nn.Module):
        return False
    if value is None or isinstance(value, (bool, int, float, str, torch.Size, torch.device, TensorDictBase)):
        return True
    if isinstance(value, torch.Tensor):
        return not isinstance(value, nn.Parameter) and value.data_ptr() not in module_state
    if isinstance(value, (list, tuple)):
        return all(_is_plain_data(v, module_state) for v in value)
    if isinstance(value, dict):
        return all(_is_plain_data(v, module_state) for v in value.values())
    return False


def _whole_update_graph(step, device: torch.device):
    """``step`` (``batch -> {name: scalar}``) captured in one CUDA graph by :class:`~tensordict.nn.CudaGraphModule`
    (after a few warm-up calls that compile it); each call copies the batch into the graph's input buffers and
    replays every kernel of the update, optimizer steps included, with no Python in between."""
    from tensordict import TensorDict
    from tensordict.nn import CudaGraphModule

    graph = CudaGraphModule(lambda batch: TensorDict(step(batch), batch_size=[]), in_keys=[], out_keys=[],
                            warmup=5, device=device)
    return lambda batch: dict(graph(batch).items())
