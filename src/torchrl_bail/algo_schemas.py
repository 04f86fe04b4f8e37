"""The algorithms' schemas (``conf/algo``): one per algorithm, registered in :data:`ALGO_SCHEMAS` and named
``algo/base_<name>_schema`` in Hydra (:func:`torchrl_bail.hydra_setup.register_schemas`). Torch-free, like every
schema, so a bad command line fails before torch loads; the rules come from :mod:`torchrl_bail.config`.
"""

from __future__ import annotations

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

__all__ = ["ALGO_SCHEMAS", "AlgoConfig", "NetConfig", "study_algorithms"]


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
    study (``results/run_study.py``), the drills (``benchmarks/kill_drill.py``) and the docs read, so that no list of
    algorithm names is kept anywhere else. A schema sets the ones that differ from these defaults."""

    #: which paper-scale schedule it takes (``results/run_study.PAPER_SCHEDULE``): ``"imitation"`` (the paper's own
    #: epochs) or ``"offline_rl"`` (an actor-critic at 10 % of its paper's 10^6 updates: ~10x an imitation run)
    cost: ClassVar[str] = "imitation"
    #: the batch kinds the study runs it on: ``"all"``, ``"ddpg"`` (the two DDPG batches of each env only, for
    #: cost) or ``"none"`` (not in the study); whether an algorithm joins the study is this one line
    study: ClassVar[str] = "none"
    #: whether the paper-scale Hopper study (``--study paper_hopper``) runs it: the paper's six algorithms
    paper_study: ClassVar[bool] = False
    #: command-line overrides for a run of a few hundred updates (the kill drills)
    drill: ClassVar[tuple[str, ...]] = ()

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
    drill = ("algo.epochs=0.2", "eval.every_epochs=0.02", "algo.envelope.epochs=10", "algo.envelope.batch_size=100")

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
    drill = ("algo.epochs=0.3", "eval.every_epochs=0.02", "algo.envelope.validate_every=20")

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
    drill = ("algo.epochs=0.4", "eval.every_epochs=0.02")

    policy: NetConfig = MISSING


@dataclass
class MARWILConfig(AlgoConfig):
    study = "all"
    paper_study = True
    drill = ("algo.epochs=0.4", "eval.every_epochs=0.02")

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
    drill = ("algo.epochs=0.02", "eval.every_epochs=0.002", "algo.vae.hidden=[32,32]", "algo.actor.hidden=[32,32]",
             "algo.critic.hidden=[32,32]")

    phi: float = non_negative()
    actor: NetConfig = MISSING


@dataclass
class BEARActorConfig(NetConfig):
    noise_clip: float = positive()
    log_std_min: float = MISSING
    log_std_max: float = MISSING


@dataclass
class BEARConfig(TwinCriticVAEConfig):
    drill = ("algo.epochs=0.03", "eval.every_epochs=0.002", "algo.vae.hidden=[32,32]", "algo.actor.hidden=[32,32]",
             "algo.critic.hidden=[32,32]", "algo.warm_start_updates=100")

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
