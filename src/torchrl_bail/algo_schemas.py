"""The algorithms' schemas (``conf/algo``): one per algorithm, registered in :data:`ALGO_SCHEMAS` and named
``algo/base_<name>_schema`` in Hydra (:func:`torchrl_bail.hydra_setup.register_schemas`); the rules come from
:mod:`torchrl_bail.config`. Each schema is also its algorithm's registry entry (:class:`AlgoConfig`'s class
variables): what the study, the drills, the contract suite and the docs know of an algorithm besides its keys.

Why the schemas live here and not in ``algorithms/<name>.py`` beside the update step: an algorithm's module imports
torch, tensordict and torchrl, a command line is checked against its schema before any of them loads, and a bad one
must fail in about a second (:func:`torchrl_bail.cli.run_cli`). Measured on the project's 2-core CPU (one core, the
other busy, load ~4; best and median of five ``python -c "import ..."`` in a fresh process): this module
0.14 s / 0.18 s (omegaconf and the rules only), ``torchrl_bail.algorithms.iql`` 6.0 s / 6.7 s (torch alone
2.8 s / 3.3 s, torchrl 5.1 s / 6.8 s); ``python -m torchrl_bail.train +exp=hopper_ddpg05 algo=iql
algo.batch_size=0`` prints its one line and exits 2 after 2.0-2.3 s, Hydra's composition included. A schema in the
algorithm's module would put those 6 s in front of every such error, so this one torch-free file holds every
schema, and the class beside its update step is found through :data:`ALGO_SCHEMAS` by name (a test keeps the two
registries equal).
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass
from typing import Any, ClassVar, List, Optional  # noqa: UP035 -- OmegaConf reads these annotations at runtime

from omegaconf import MISSING

from torchrl_bail.config import (
    Checked,
    at_least,
    discount,
    fraction,
    layers,
    learning_rate,
    non_negative,
    one_of,
    positive,
    registry_name,
    rule,
)

__all__ = ["ALGO_SCHEMAS", "AlgoConfig", "NetConfig", "blocks_with", "entry_gaps", "study_algorithms"]


# ---------------------------------------------------------------------------------------------------------------
# algorithms (conf/algo)
# ---------------------------------------------------------------------------------------------------------------


@dataclass
class NetConfig(Checked):
    hidden: List[int] = layers()
    lr: float = learning_rate()


@dataclass
class AlgoConfig(Checked):
    """The keys every algorithm has, and its registry entry: class variables (not config keys, torch-free) that the
    study (``results/run_study.py``), the drills (``benchmarks/kill_drill.py``), the contract suite
    (``tests/_contract.py``) and the docs (``docs/gen_algorithm_table.py``) read, so that no list of algorithm names
    is kept anywhere else. A schema sets the ones that differ from these defaults; ``tiny``, ``description`` and
    ``losses`` have none, every schema states them (:func:`entry_gaps`; ``tests/test_contract.py`` fails without)."""

    #: which paper-scale schedule it takes (``results/run_study.PAPER_SCHEDULE``): ``"imitation"`` (the paper's own
    #: epochs) or ``"offline_rl"`` (an actor-critic at 10 % of its paper's 10^6 updates: ~10x an imitation run)
    cost: ClassVar[str] = "imitation"
    #: the batch kinds the study runs it on: ``"all"``, ``"ddpg"`` (the two DDPG batches of each env only, for
    #: cost) or ``"none"`` (not in the study); whether an algorithm joins the study is this one line
    study: ClassVar[str] = "none"
    #: whether the paper-scale Hopper study (``--study paper_hopper``) runs it: the paper's six algorithms
    paper_study: ClassVar[bool] = False
    #: what a run of a few updates needs besides small networks and its length (both set by
    #: :func:`tiny_run_overrides`): overrides of ``algo`` keys (``"warm_start_updates=2"``) that make a handful of
    #: updates cross each switch of the update (BEAR's warm start, Progressive BAIL's validations) and keep
    #: ``prepare`` as short (BAIL's envelope fit); ``()`` when nothing else is needed. The contract suite's tiny
    #: runs and the kill drill read it
    tiny: ClassVar[Optional[tuple[str, ...]]] = None
    #: one line for the docs' table (``docs/guides/algorithms.md``): what the algorithm does, its paper by arXiv id
    #: or section; ``{key}`` fields are filled with the paper preset's values (``{selection.percentile:.0%}``)
    description: ClassVar[Optional[str]] = None
    #: the loss modules (and selection transforms) it trains with, by import path (``torchrl.objectives.BCLoss``);
    #: the docs' table lists them, ``tests/test_contract.py`` checks that each imports and that the built algorithm
    #: holds no loss module missing here
    losses: ClassVar[tuple[str, ...]] = ()

    name: str = registry_name("ALGO_SCHEMAS")
    batch_size: int = at_least(1, "a positive mini-batch size")
    epochs: float = positive("a positive number of epochs (10^6 samples each)")

    def check(self) -> None:
        self._registered_as("name", ALGO_SCHEMAS, "choose the algorithm with algo=<name>")


@dataclass
class EnvelopeConfig(Checked):
    hidden: List[int] = layers()
    head_scale: float = positive()
    penalty: float = rule(lambda v: v >= 1, "a penalty K >= 1 (1: ordinary regression)")
    lr: float = learning_rate()
    weight_decay: float = non_negative("a non-negative L2 coefficient")
    val_fraction: float = rule(lambda v: 0 <= v < 1, "a fraction in [0, 1) (0: no validation, no early stopping)")
    patience: int = at_least(1)


@dataclass
class BAILEnvelopeConfig(EnvelopeConfig):
    batch_size: int = at_least(1)
    epochs: int = at_least(1)
    early_stopping: str = one_of("paper", "as_coded")


@dataclass
class SelectionConfig(Checked):
    percentile: float = fraction()


@dataclass
class BAILSelectionConfig(SelectionConfig):
    by: str = one_of("envelope", "return")
    nonpositive_value: str = one_of("raw", "project", "error")


@dataclass
class BAILConfig(AlgoConfig):
    study = "all"
    paper_study = True
    tiny = ("envelope.epochs=3", "envelope.batch_size=200")
    description = "BAIL (supp. Alg. 1): upper envelope → best {selection.percentile:.0%} by G/V → BC on them"
    losses = ("torchrl_bail.objectives.UpperEnvelopeLoss", "torchrl_bail.transforms.BestActionFilter",
              "torchrl.objectives.BCLoss")

    envelope: BAILEnvelopeConfig = MISSING
    selection: BAILSelectionConfig = MISSING
    policy: NetConfig = MISSING


@dataclass
class PBAILEnvelopeConfig(EnvelopeConfig):
    validate_every: int = at_least(1)


@dataclass
class PBAILConfig(AlgoConfig):
    study = "all"
    paper_study = True
    tiny = ("envelope.validate_every=2",)
    description = ("Progressive BAIL (supp. Alg. 2): envelope step + in-batch top {selection.percentile:.0%} + policy "
                   "step each iteration")
    losses = ("torchrl_bail.objectives.UpperEnvelopeLoss", "torchrl_bail.transforms.best_action_mask",
              "torchrl.objectives.BCLoss")

    envelope: PBAILEnvelopeConfig = MISSING
    selection: SelectionConfig = MISSING
    best_envelope: str = one_of("paper", "as_coded")
    selection_envelope: str = one_of("best", "training")
    v_projection: bool = MISSING
    validation: str = one_of("split", "with_replacement")
    policy: NetConfig = MISSING


@dataclass
class BCConfig(AlgoConfig):
    study = "all"
    paper_study = True
    tiny = ()
    description = "behaviour cloning on the whole batch"
    losses = ("torchrl.objectives.BCLoss",)

    policy: NetConfig = MISSING


@dataclass
class MARWILConfig(AlgoConfig):
    study = "all"
    paper_study = True
    tiny = ()
    description = "MARWIL (Wang et al., NeurIPS 2018): advantage-weighted imitation, β = {beta:g}, running c²"
    losses = ("torchrl_bail.objectives.MARWILLoss",)

    beta: float = non_negative()
    c2_init: float = positive()
    c2_rate: float = fraction()
    vf_coeff: float = non_negative()
    max_exponent: float = positive()
    eps: float = non_negative()
    value_warmup_updates: int = at_least(0)
    value: NetConfig = MISSING
    policy: NetConfig = MISSING


@dataclass
class VAEConfig(NetConfig):
    latent_per_action: int = at_least(1)
    log_std_min: float = MISSING
    log_std_max: float = MISSING

    def check(self) -> None:
        self._ordered("log_std_min", "log_std_max")


@dataclass
class CriticConfig(NetConfig):
    vmap: Any = rule(lambda v: v in ("auto", True, False), "auto | true | false")


@dataclass
class TwinCriticVAEConfig(AlgoConfig):
    """BCQ's and BEAR's shared keys; both are actor-critics the study runs on DDPG batches only (for cost), and
    both are in the paper-scale study."""

    cost = "offline_rl"
    study = "ddpg"
    paper_study = True

    lmbda: float = rule(lambda v: 0 <= v <= 1, "a weight in [0, 1]")
    num_samples: int = at_least(1)
    kl_weight: float = non_negative()
    latent_clip: float = positive()
    gamma: float = discount()
    tau: float = rule(lambda v: 0 < v <= 1, "a soft-update rate in (0, 1]")
    vae: VAEConfig = MISSING
    critic: CriticConfig = MISSING


@dataclass
class BCQConfig(TwinCriticVAEConfig):
    tiny = ()
    description = ("BCQ 2019 (arXiv:1812.02900): VAE + perturbation (Φ = {phi:g}) + soft clipped double Q, best of "
                   "{num_samples}")
    losses = ("torchrl_bail.objectives.BCQLoss", "torchrl_bail.objectives.VAELoss")

    phi: float = non_negative()
    actor: NetConfig = MISSING


@dataclass
class BEARActorConfig(NetConfig):
    noise_clip: float = positive()
    log_std_min: float = MISSING
    log_std_max: float = MISSING


@dataclass
class BEARConfig(TwinCriticVAEConfig):
    tiny = ("warm_start_updates=2",)
    description = ("BEAR v0 (arXiv:1906.00949): Laplacian MMD (σ = {kernel_sigma:g}, {num_samples_match} samples, "
                   "ε = {epsilon:g}), Lagrange α, warm start")
    losses = ("torchrl_bail.objectives.BEARLoss", "torchrl_bail.objectives.VAELoss")

    kernel_sigma: float = positive()
    num_samples_match: int = at_least(1)
    mmd_stabilizer: float = non_negative()
    epsilon: float = non_negative()
    log_alpha_init: Optional[float] = None
    log_alpha_min: float = MISSING
    log_alpha_max: float = MISSING
    lagrange_lr: float = learning_rate()
    warm_start_updates: int = at_least(0)
    actor: BEARActorConfig = MISSING

    def check(self) -> None:
        super().check()
        self._ordered("log_alpha_min", "log_alpha_max")


@dataclass
class TD3BCConfig(AlgoConfig):
    cost = "offline_rl"
    study = "all"  # in the study since it landed (30 jobs): kept, now stated
    tiny = ()
    description = ("TD3+BC (arXiv:2106.06860): TD3 with a behaviour-cloning term in the actor loss (α = {alpha:g}), "
                   "standardised observations; not in the BAIL paper")
    losses = ("torchrl.objectives.TD3BCLoss",)

    alpha: float = non_negative("a non-negative weight alpha of the Q term (0: behaviour cloning)")
    policy_noise: float = non_negative("a non-negative std of the target policy's noise, times max_action")
    noise_clip: float = non_negative("a non-negative clip of the target policy's noise, times max_action")
    policy_delay: int = at_least(1, "a positive number of critic updates per actor update")
    gamma: float = discount()
    tau: float = rule(lambda v: 0 < v <= 1, "a soft-update rate in (0, 1]")
    normalize_observations: bool = MISSING
    normalize_eps: float = positive("a positive number added to the observations' standard deviation")
    actor: NetConfig = MISSING
    critic: CriticConfig = MISSING


@dataclass
class IQLActorConfig(NetConfig):
    log_std_min: float = MISSING
    log_std_max: float = MISSING
    lr_schedule: str = one_of("cosine", "constant")

    def check(self) -> None:
        self._ordered("log_std_min", "log_std_max")


@dataclass
class IQLConfig(AlgoConfig):
    cost = "offline_rl"
    study = "none"
    tiny = ()
    description = ("IQL (arXiv:2110.06169): expectile value (τ = {expectile:g}), critics to r + γV(s'), "
                   "advantage-weighted Gaussian actor (β = {beta:g}, weights clipped at {max_weight:g}) with a cosine "
                   "learning rate; locomotion reward scaling; not in the BAIL paper")
    losses = ("torchrl.objectives.IQLLoss",)

    expectile: float = rule(lambda v: 0 < v < 1, "an expectile in (0, 1) (0.5: mean regression)")
    beta: float = non_negative("a non-negative inverse temperature of the advantage weights")
    # TorchRL's IQLLoss clips the advantage weights at 100 (a constant of its code): the one value it can train
    max_weight: float = rule(lambda v: v == 100, "100, the clip of exp(beta A) that TorchRL's IQLLoss hard-codes")
    gamma: float = discount()
    tau: float = rule(lambda v: 0 < v <= 1, "a soft-update rate in (0, 1]")
    reward_scale: str = one_of("locomotion", "none")
    actor: IQLActorConfig = MISSING
    critic: CriticConfig = MISSING
    value: NetConfig = MISSING


#: algorithm name -> its schema, in the report's column order (kept equal to the algorithm classes' registry,
#: :data:`torchrl_bail.algorithms.ALGORITHMS`, by a test); each schema's class variables are its registry entry
ALGO_SCHEMAS = {"bail": BAILConfig, "pbail": PBAILConfig, "bc": BCConfig, "marwil": MARWILConfig,
                "bcq": BCQConfig, "bear": BEARConfig, "td3bc": TD3BCConfig, "iql": IQLConfig}


def study_algorithms(batches: str) -> list[str]:
    """The registered algorithms the study runs on ``batches`` (``"all"`` or ``"ddpg"``: :attr:`AlgoConfig.study`),
    in registry order.

    Examples:
        >>> study_algorithms("ddpg")
        ['bcq', 'bear']
    """
    return [name for name, schema in ALGO_SCHEMAS.items() if schema.study == batches]


def entry_gaps(name: str) -> list[str]:
    """What algorithm ``name``'s registry entry leaves unstated of what has no default, as ``<Schema>.<variable>``:
    :attr:`AlgoConfig.tiny` (``()`` states that nothing is needed), :attr:`AlgoConfig.description` and
    :attr:`AlgoConfig.losses`. The docs build and ``tests/test_contract.py`` fail on any.

    Examples:
        >>> entry_gaps("bear")
        []
    """
    schema = ALGO_SCHEMAS[name]
    gaps = {"tiny": schema.tiny is None, "description": not schema.description, "losses": not schema.losses}
    return [f"{schema.__name__}.{variable}" for variable, missing in gaps.items() if missing]


def blocks_with(name: str, key: str) -> list[str]:
    """The dotted names of the blocks (nested nodes) of algorithm ``name``'s schema that have the field ``key``, in
    schema order: ``blocks_with(name, "hidden")`` are its networks.

    Examples:
        >>> blocks_with("bail", "hidden"), blocks_with("bail", "batch_size"), blocks_with("bcq", "hidden")
        (['envelope', 'policy'], ['envelope'], ['vae', 'critic', 'actor'])
    """
    return _blocks_with(ALGO_SCHEMAS[name], key)


def _blocks_with(schema: type, key: str, prefix: str = "") -> list[str]:
    types = typing.get_type_hints(schema)
    found = []
    for f in dataclasses.fields(schema):
        block = types[f.name]
        if dataclasses.is_dataclass(block):
            found += [prefix + f.name] if key in {g.name for g in dataclasses.fields(block)} else []
            found += _blocks_with(block, key, f"{prefix}{f.name}.")
    return found
