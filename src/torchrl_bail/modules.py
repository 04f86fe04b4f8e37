"""Network builders shared by every algorithm.

All networks are plain TorchRL modules reading TED keys (``"observation"``, ``"action"``) so that
they plug into TorchRL losses, replay buffers and environments without adapters.

Examples:
    >>> import torch
    >>> from torchrl.data import Bounded
    >>> from tensordict import TensorDict
    >>> spec = Bounded(-0.4, 0.4, shape=(3,))
    >>> actor = make_deterministic_actor(11, spec)
    >>> td = actor(TensorDict({"observation": torch.randn(5, 11)}, [5]))
    >>> td["action"].shape, bool(td["action"].abs().max() <= 0.4)
    (torch.Size([5, 3]), True)
    >>> value = make_value_network(11)
    >>> value(TensorDict({"observation": torch.randn(5, 11)}, [5]))["state_value"].shape
    torch.Size([5, 1])
"""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torch.distributions import ComposeTransform
from torch.distributions.utils import _sum_rightmost
from torchrl.data import Bounded, TensorSpec
from torchrl.envs.utils import ExplorationType
from torchrl.modules import MLP, ProbabilisticActor, TanhModule, TanhNormal, ValueOperator
from torchrl.objectives import LossModule, SoftUpdate

from torchrl_bail.core.stacking import linear

__all__ = [
    "fast_tensordict_outputs",
    "mlp",
    "action_spec_from_bounds",
    "make_deterministic_actor",
    "make_value_network",
    "make_qvalue_network",
    "ConditionalVAE",
    "make_vae",
    "PerturbationActor",
    "make_perturbation_actor",
    "TanhGaussianParams",
    "TanhNormalScoredOnTanh",
    "make_sac_actor",
    "PlainMLP",
    "FusedSoftUpdate",
    "fused_soft_update",
]


def fast_tensordict_outputs() -> None:
    """Works around a per-call cost in tensordict 0.14: every ``TensorDictModule`` output goes through
    ``TensorDict.from_any``, which calls ``importlib.util.find_spec("pandas")`` -- a scan of ``sys.path`` (about
    0.2 ms, several times per update) when pandas is not installed. Registering pandas as absent in ``sys.modules``
    makes that lookup instant; ``import pandas`` fails exactly as before (``ImportError``). No-op when pandas is
    installed, and after the first call (one dictionary lookup).

    Not applied at import: every network builder of this module calls it (through :func:`mlp`), so the package's
    algorithms, behaviour agents and evaluation are fast without anything happening when :mod:`torchrl_bail` is
    merely imported. Call it yourself when you use the loss modules with networks of your own. The one visible
    effect: pandas installed *later in the same process* needs a restart to import.
    """
    if "pandas" not in sys.modules and importlib.util.find_spec("pandas") is None:
        sys.modules["pandas"] = None  # type: ignore[assignment]


def mlp(in_features: int, out_features: int, hidden: Sequence[int]) -> MLP:
    """A ReLU MLP ``in -> hidden... -> out`` with PyTorch's default init (never TorchRL's 1-layer default).

    Every builder below goes through here, which applies :func:`fast_tensordict_outputs` once.
    """
    fast_tensordict_outputs()
    return MLP(
        in_features=in_features,
        out_features=out_features,
        num_cells=list(hidden),
        activation_class=nn.ReLU,
    )


def action_spec_from_bounds(low, high, dtype: torch.dtype = torch.float32) -> Bounded:
    """A :class:`~torchrl.data.Bounded` action spec from per-dimension (or scalar) bounds."""
    low = torch.as_tensor(low, dtype=dtype)
    high = torch.as_tensor(high, dtype=dtype)
    return Bounded(low, high, shape=low.shape, dtype=dtype)


def make_deterministic_actor(
    obs_dim: int,
    action_spec: TensorSpec,
    hidden: Sequence[int] = (400, 300),
    *,
    observation_key="observation",
    action_key="action",
) -> TensorDictSequential:
    """Deterministic policy ``obs -> 400 -> 300 -> |A| -> tanh`` scaled to the action bounds (supp. C.3).

    For Humanoid (bound 0.4) the output is ``0.4 * tanh(.)``.
    """
    act_dim = action_spec.shape[-1]
    body = TensorDictModule(mlp(obs_dim, act_dim, hidden), in_keys=[observation_key], out_keys=["param"])
    head = TanhModule(in_keys=["param"], out_keys=[action_key], spec=action_spec)
    return TensorDictSequential(body, head)


def make_value_network(
    obs_dim: int,
    hidden: Sequence[int] = (128, 128),
    *,
    head_scale: float = 0.1,
    observation_key="observation",
    out_key="state_value",
) -> ValueOperator:
    """State-value net ``obs -> 128 -> 128 -> 1`` (supp. B.2, Table 1).

    Hidden layers keep PyTorch's default init; the output layer's weight is the default init times
    ``head_scale`` and its bias is zero, as in the authors' upper envelope. That scaling is made here, once: a
    loss' ``reset_parameters_recursive()`` redraws every layer from PyTorch's default init, as it does for
    TorchRL's own networks (build a new network for the authors' initial head).
    """
    net = mlp(obs_dim, 1, hidden)
    last = net[-1]
    with torch.no_grad():
        last.weight.mul_(head_scale)
        last.bias.zero_()
    return ValueOperator(net, in_keys=[observation_key], out_keys=[out_key])


def make_qvalue_network(
    obs_dim: int,
    act_dim: int,
    hidden: Sequence[int] = (400, 300),
    *,
    observation_key="observation",
    action_key="action",
    out_key="state_action_value",
) -> ValueOperator:
    """Action-value net ``(obs, action) -> 400 -> 300 -> 1`` (critics of BCQ, BEAR and DDPG)."""
    return ValueOperator(mlp(obs_dim + act_dim, 1, hidden), in_keys=[observation_key, action_key], out_keys=[out_key])


def _bounds_affine(low: torch.Tensor, high: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(loc, scale)`` with ``loc + scale * tanh(x)`` spanning ``[low, high]`` (``max_action * tanh`` when
    symmetric)."""
    low = torch.as_tensor(low, dtype=torch.float32)
    high = torch.as_tensor(high, dtype=torch.float32)
    return (high + low) / 2, (high - low) / 2


class ConditionalVAE(nn.Module):
    """The conditional VAE of BCQ and BEAR: a generative model of the batch's actions given the state (supp. C.2, BCQ).

    * encoder ``(s, a) -> hidden -> (mu, log sigma)`` with ``log sigma`` clamped to ``[log_std_min, log_std_max]``;
    * decoder ``(s, z) -> hidden -> |A|``, squashed by ``tanh`` and scaled to the action bounds
      (``max_action * tanh`` for symmetric bounds);
    * sampling (:meth:`sample`, :meth:`decode` without a latent) draws ``z ~ N(0, I)`` clipped to
      ``[-latent_clip, latent_clip]`` from torch's global random stream.

    The two encoder heads of the authors' code (``mean`` and ``log_std``, each ``Linear(hidden, latent)``) are one
    ``Linear(hidden, 2 * latent)`` here: the same function class and the same initial distribution. Every method
    takes any leading batch shape.

    Args:
        obs_dim (int): observation size.
        act_dim (int): action size.
        action_low (float or Tensor): the lower action bound (a scalar or ``[act_dim]``).
        action_high (float or Tensor): the upper action bound (a scalar or ``[act_dim]``).
        hidden (sequence of int): hidden sizes of the encoder and of the decoder. Defaults to ``(750, 750)``.

    Keyword Args:
        latent_dim (int): size of ``z`` (the authors use ``2 * act_dim``).
        log_std_min (float): lower clamp of the encoder's ``log sigma``. Defaults to ``-4.0``.
        log_std_max (float): upper clamp of the encoder's ``log sigma``. Defaults to ``15.0``.
        latent_clip (float): sampled latents are clipped to ``[-latent_clip, latent_clip]``. Defaults to ``0.5``.

    Examples:
        >>> import torch
        >>> vae = ConditionalVAE(11, 3, -1.0, 1.0, hidden=(16, 16), latent_dim=6)
        >>> recon, mean, log_std = vae(torch.randn(5, 11), torch.rand(5, 3) * 2 - 1)
        >>> recon.shape, mean.shape, log_std.shape
        (torch.Size([5, 3]), torch.Size([5, 6]), torch.Size([5, 6]))
        >>> actions, pre_tanh = vae.sample(torch.randn(5, 11), 10)
        >>> actions.shape, bool(actions.abs().max() <= 1.0), pre_tanh.shape
        (torch.Size([5, 10, 3]), True, torch.Size([5, 10, 3]))
    """

    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        action_low,
        action_high,
        hidden: Sequence[int] = (750, 750),
        *,
        latent_dim: int,
        log_std_min: float = -4.0,
        log_std_max: float = 15.0,
        latent_clip: float = 0.5,
    ) -> None:
        super().__init__()
        if int(latent_dim) < 1:
            raise ValueError(f"the VAE latent_dim must be >= 1, got {latent_dim}")
        if not float(log_std_min) <= float(log_std_max):
            raise ValueError(f"log_std_min ({log_std_min}) must be <= log_std_max ({log_std_max})")
        if not float(latent_clip) > 0:
            raise ValueError(f"latent_clip must be > 0, got {latent_clip}")
        self.latent_dim = int(latent_dim)
        self.log_std_min = float(log_std_min)
        self.log_std_max = float(log_std_max)
        self.latent_clip = float(latent_clip)
        self.encoder = mlp(obs_dim + act_dim, 2 * self.latent_dim, hidden)
        self.decoder = mlp(obs_dim + self.latent_dim, act_dim, hidden)
        loc, scale = _bounds_affine(action_low, action_high)
        self.register_buffer("action_loc", loc.expand(act_dim).clone())
        self.register_buffer("action_scale", scale.expand(act_dim).clone())

    def reset_parameters_recursive(self) -> None:
        """Draws every layer afresh from its initial distribution (PyTorch's default, the one the VAE is built
        with): what a TorchRL loss' ``reset_parameters_recursive`` calls on each of its networks."""
        for module in self.modules():
            if module is not self and hasattr(module, "reset_parameters"):
                module.reset_parameters()

    def encode(self, observation: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(mu, log sigma)`` of ``q(z | s, a)``, ``log sigma`` clamped."""
        mean, log_std = self.encoder(torch.cat([observation, action], -1)).chunk(2, dim=-1)
        return mean, log_std.clamp(self.log_std_min, self.log_std_max)

    def forward(self, observation: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """``(reconstruction, mu, log sigma)`` with ``z = mu + sigma * eps`` (reparameterised, not clipped)."""
        mean, log_std = self.encode(observation, action)
        latent = mean + log_std.exp() * torch.randn_like(mean)
        return self.decode(observation, latent), mean, log_std

    def sample_latent(self, batch_shape: torch.Size | Sequence[int]) -> torch.Tensor:
        """``z ~ N(0, I)`` of shape ``[*batch_shape, latent_dim]``, clipped to ``+-latent_clip``."""
        z = torch.randn(*batch_shape, self.latent_dim, device=self.action_loc.device, dtype=self.action_loc.dtype)
        return z.clamp(-self.latent_clip, self.latent_clip)

    def decode_raw(
        self, observation: torch.Tensor, latent: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(action, pre-tanh action)``; a clipped prior latent is drawn when ``latent`` is ``None``."""
        if latent is None:
            latent = self.sample_latent(observation.shape[:-1])
        raw = self.decoder(torch.cat([observation, latent], -1))
        return self.action_loc + self.action_scale * torch.tanh(raw), raw

    def decode(self, observation: torch.Tensor, latent: torch.Tensor | None = None) -> torch.Tensor:
        """The decoded action (see :meth:`decode_raw`)."""
        return self.decode_raw(observation, latent)[0]

    def sample(self, observation: torch.Tensor, num_samples: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``num_samples`` decoded actions per state: ``(actions, pre-tanh)``, each ``[*B, num_samples, |A|]``."""
        observation = observation.unsqueeze(-2).expand(*observation.shape[:-1], int(num_samples), observation.shape[-1])
        return self.decode_raw(observation)


def make_vae(
    obs_dim: int,
    action_spec: TensorSpec,
    hidden: Sequence[int] = (750, 750),
    *,
    latent_dim: int,
    log_std_min: float = -4.0,
    log_std_max: float = 15.0,
    latent_clip: float = 0.5,
) -> ConditionalVAE:
    """The BCQ/BEAR :class:`ConditionalVAE` on the bounds of a :class:`~torchrl.data.Bounded` action spec."""
    return ConditionalVAE(
        obs_dim, action_spec.shape[-1], action_spec.space.low, action_spec.space.high, hidden,
        latent_dim=latent_dim, log_std_min=log_std_min, log_std_max=log_std_max, latent_clip=latent_clip,
    )


class PerturbationActor(nn.Module):
    """BCQ's perturbation model: ``a' = clamp(a + phi * max_action * tanh(f(s, a)), low, high)`` (supp. C.2, BCQ).

    ``f`` is ``(s, a) -> hidden -> |A|``; ``max_action`` is the half-width of the bounds (their upper bound when
    they are symmetric, as in every MuJoCo task).

    Examples:
        >>> import torch
        >>> actor = PerturbationActor(11, 3, -1.0, 1.0, hidden=(16, 16), phi=0.05)
        >>> a = torch.rand(4, 3) * 2 - 1
        >>> bool(((actor(torch.randn(4, 11), a) - a).abs() <= 0.05 + 1e-6).all())
        True
    """

    def __init__(self, obs_dim: int, act_dim: int, action_low, action_high, hidden: Sequence[int] = (400, 300), *,
                 phi: float = 0.05) -> None:
        super().__init__()
        if not float(phi) >= 0:
            raise ValueError(f"phi must be >= 0, got {phi}")
        self.net = mlp(obs_dim + act_dim, act_dim, hidden)
        loc, scale = _bounds_affine(action_low, action_high)
        self.register_buffer("max_perturbation", float(phi) * scale.expand(act_dim).clone())
        self.register_buffer("action_low", (loc - scale).expand(act_dim).clone())
        self.register_buffer("action_high", (loc + scale).expand(act_dim).clone())

    def forward(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        perturbation = self.max_perturbation * torch.tanh(self.net(torch.cat([observation, action], -1)))
        return torch.clamp(action + perturbation, self.action_low, self.action_high)


def make_perturbation_actor(
    obs_dim: int,
    action_spec: TensorSpec,
    hidden: Sequence[int] = (400, 300),
    *,
    phi: float = 0.05,
    observation_key="observation",
    action_key="action",
) -> TensorDictModule:
    """BCQ's :class:`PerturbationActor` as a TensorDict module: reads a candidate ``action``, writes it perturbed."""
    net = PerturbationActor(obs_dim, action_spec.shape[-1], action_spec.space.low, action_spec.space.high, hidden,
                            phi=phi)
    return TensorDictModule(net, in_keys=[observation_key, action_key], out_keys=[action_key])


class TanhGaussianParams(nn.Module):
    """``obs -> hidden -> (loc, scale)`` with ``log scale`` clamped to ``[log_std_min, log_std_max]``."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: Sequence[int] = (256, 256), *,
                 log_std_min: float = -20.0, log_std_max: float = 2.0):
        super().__init__()
        self.net = mlp(obs_dim, 2 * act_dim, hidden)
        self.log_std_min = float(log_std_min)
        self.log_std_max = float(log_std_max)

    def forward(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        loc, log_std = self.net(observation).chunk(2, dim=-1)
        return loc, log_std.clamp(self.log_std_min, self.log_std_max).exp()


class TanhNormalScoredOnTanh(TanhNormal):
    """A :class:`~torchrl.modules.TanhNormal` on ``[low, high]`` whose log-probability is that of the *unscaled*
    tanh output ``y = tanh(u)`` in ``[-1, 1]``, as in the authors' SAC (sac_adapt), not that of the action.

    The action is unchanged, ``a = (high + low) / 2 + (high - low) / 2 * tanh(u)``; only its score drops the affine
    Jacobian: ``log pi(y) = log N(u) - sum log(1 - tanh(u)^2)``, i.e. ``log pi(a) + sum log((high - low) / 2)``.
    With the default bounds ``[-1, 1]`` it is exactly :class:`~torchrl.modules.TanhNormal`. TorchRL's
    :class:`~torchrl.objectives.SACLoss` scores its samples through :meth:`rsample_and_log_prob` (actor loss,
    alpha loss and the soft-Q target alike), so all three see the unscaled log-probability.

    Examples:
        >>> import math, torch
        >>> loc, scale = torch.zeros(2, 3), torch.ones(2, 3)
        >>> dist = TanhNormalScoredOnTanh(loc, scale, low=-0.4, high=0.4)
        >>> a, lp = dist.rsample_and_log_prob()
        >>> bool(a.abs().max() <= 0.4)
        True
        >>> unscaled = TanhNormal(loc, scale)
        >>> torch.allclose(lp, unscaled.log_prob(a / 0.4), atol=1e-5)
        True
        >>> torch.allclose(lp, TanhNormal(loc, scale, low=-0.4, high=0.4).log_prob(a) + 3 * math.log(0.4))
        True
    """

    def _tanh_and_affine(self):
        """``(tanh transform, affine transform or None)``: the parts of the action map."""
        transform = self.transforms[0]
        if isinstance(transform, ComposeTransform):
            return transform.parts[0], transform.parts[1]
        return transform, None

    def _score_preimage(self, preimage: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        tanh, affine = self._tanh_and_affine()
        unit = tanh(preimage)
        jacobian = _sum_rightmost(tanh.log_abs_det_jacobian(preimage, unit), len(self.event_shape))
        log_prob = self.base_dist.log_prob(preimage) - jacobian
        return (unit if affine is None else affine(unit)), log_prob

    def rsample_and_log_prob(self, sample_shape=()) -> tuple[torch.Tensor, torch.Tensor]:
        """A reparameterised action and the log-probability of its tanh output (same draw)."""
        if self._tanh_and_affine()[1] is None:  # bounds +-1: TorchRL's own code path, bit for bit
            return super().rsample_and_log_prob(sample_shape)
        return self._score_preimage(self.base_dist.rsample(torch.Size(sample_shape)))

    def sample_and_log_prob(self, sample_shape=()) -> tuple[torch.Tensor, torch.Tensor]:
        """A detached action and the (differentiable) log-probability of its tanh output (same draw)."""
        if self._tanh_and_affine()[1] is None:
            return super().sample_and_log_prob(sample_shape)
        action, log_prob = self._score_preimage(self.base_dist.sample(torch.Size(sample_shape)))
        return action.detach(), log_prob

    def log_prob(self, value: torch.Tensor, **kwargs) -> torch.Tensor:
        """The log-probability of the tanh output ``y`` that gives the action ``value``."""
        log_prob = super().log_prob(value, **kwargs)
        _, affine = self._tanh_and_affine()
        if affine is None:
            return log_prob
        log_half_range = torch.log(torch.as_tensor(affine.scale, dtype=log_prob.dtype)).expand(value.shape)
        return log_prob + _sum_rightmost(log_half_range, len(self.event_shape))


def make_sac_actor(obs_dim: int, action_spec, hidden: Sequence[int] = (256, 256), *, log_std_min: float = -20.0,
                   log_std_max: float = 2.0, log_prob_on: str = "action") -> ProbabilisticActor:
    """The SAC tanh-Gaussian policy as a TorchRL :class:`~torchrl.modules.ProbabilisticActor`.

    Under ``ExplorationType.DETERMINISTIC`` it outputs ``max_action * tanh(mu)``; under ``RANDOM`` a sample.
    ``log_prob_on`` says what its log-probabilities score: ``"action"`` (TorchRL's :class:`TanhNormal`, the density
    of the action on ``[low, high]``) or ``"tanh"`` (:class:`TanhNormalScoredOnTanh`, the density of the unscaled
    tanh output in ``[-1, 1]``, as the authors' SAC). Both sample the same actions, and with bounds ``+-1`` they are
    the same distribution. The SAC behaviour agent uses ``"tanh"``; BEAR's actor only samples (its losses never
    score log pi), so it keeps the default.
    """
    distributions = {"action": TanhNormal, "tanh": TanhNormalScoredOnTanh}
    if log_prob_on not in distributions:
        raise ValueError(f"log_prob_on: expected one of {sorted(distributions)}, got {log_prob_on!r}")
    act_dim = action_spec.shape[-1]
    params = TensorDictModule(
        TanhGaussianParams(obs_dim, act_dim, hidden, log_std_min=log_std_min, log_std_max=log_std_max),
        in_keys=["observation"], out_keys=["loc", "scale"],
    )
    low, high = action_spec.space.low, action_spec.space.high
    return ProbabilisticActor(
        params, in_keys=["loc", "scale"], spec=action_spec, distribution_class=distributions[log_prob_on],
        distribution_kwargs={"low": low, "high": high, "tanh_loc": False}, return_log_prob=False,
        default_interaction_type=ExplorationType.RANDOM,
    )


class PlainMLP:
    """A ``Sequential`` of ``nn.Linear`` and parameter-free layers (a TorchRL ``MLP``) run from plain tensors: the
    one plain-tensor network runner of the package (BCQ's and BEAR's twin critics, the SAC behaviour agent's).

    ``params.to_module`` swaps every tensor into the module on each call; at batch 100 on one CPU thread that
    bookkeeping costs about as much as a 400-300 forward, and twin critics run several times per update. This
    reads the (stacked) weights straight from the parameter TensorDict and calls ``F.linear`` and the layers'
    own activations: the same operations in the same order as ``module(torch.cat(inputs, -1))``, so the numbers
    are identical. :meth:`build` returns ``None`` for any other architecture (the caller then uses ``to_module``).

    Examples:
        >>> from tensordict import TensorDict
        >>> net = mlp(3, 1, (8,))
        >>> plain = PlainMLP.build(net, ())
        >>> params = TensorDict.from_module(net)
        >>> x = torch.randn(4, 3)
        >>> torch.equal(plain({k: params.get(k) for k in plain.keys}, x), net(x))
        True
    """

    def __init__(self, steps: list) -> None:
        self.steps = steps  # (weight key, bias key | None) for a Linear, torch.relu_ or the layer itself otherwise
        self.keys = [key for step in steps if isinstance(step, tuple) for key in step if key is not None]

    @classmethod
    def build(cls, module: nn.Module, prefix: tuple[str, ...]) -> PlainMLP | None:
        if not isinstance(module, nn.Sequential) or getattr(module, "_reshape_out", False):
            return None
        if type(module).forward not in (nn.Sequential.forward, MLP.forward):
            return None
        steps: list = []
        for name, layer in module.named_children():
            if type(layer) is nn.Linear:
                steps.append((prefix + (name, "weight"), prefix + (name, "bias") if layer.bias is not None else None))
            elif type(layer) is nn.ReLU and steps and isinstance(steps[-1], tuple):
                steps.append(torch.relu_)
            elif next(layer.parameters(), None) is None and next(layer.buffers(), None) is None:
                steps.append(layer)
            else:
                return None
        return cls(steps)

    def members(self, params: TensorDictBase | dict, count: int, *, detach: bool = False) -> list[dict]:
        """For stacked parameters ``[count, ...]`` (a parameter TensorDict, or ``{key: tensor}``): one
        ``{key: tensor}`` per member, views of the stack (``detach``: outside the autograd graph)."""
        stacked = {key: params.get(key) for key in self.keys}
        return [{key: value[i].detach() if detach else value[i] for key, value in stacked.items()}
                for i in range(count)]

    def __call__(self, weights: dict, *inputs: torch.Tensor) -> torch.Tensor:
        x = torch.cat(inputs, -1) if len(inputs) > 1 else inputs[0]
        for step in self.steps:
            if isinstance(step, tuple):
                x = linear(x, weights[step[0]], None if step[1] is None else weights[step[1]])
            else:  # torch.relu_ after a Linear (whose backward never reads its output) or a parameter-free layer
                x = step(x)
        return x


class FusedSoftUpdate(SoftUpdate):
    """A :class:`~torchrl.objectives.SoftUpdate` whose ``step`` is one fused kernel (same result).

    TorchRL's ``SoftUpdate.step`` rebuilds ``.data`` views of every parameter TensorDict on each call (1-2 ms per
    step on a 2-core CPU, as much as a small network's whole update). This subclass keeps the updater's
    construction and initialisation (target = source at start, same ``eps``/``tau``) and replaces ``step`` by one
    ``torch._foreach_lerp_`` over the cached leaf tensors: ``target <- target + (1 - eps) * (source - target)``.
    Parameters are updated in place by the optimizers, so the cached views stay valid.
    """

    def _pairs(self) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        pairs = self.__dict__.get("_fused_pairs")
        if pairs is None:
            targets, sources = [], []
            for key, param in self._sources.items(True, True):
                key = key if isinstance(key, tuple) else (key,)
                targets.append(self._targets.get(("target_" + key[0], *key[1:])).data)
                sources.append(param.data)
            pairs = self.__dict__["_fused_pairs"] = (targets, sources)
        return pairs

    def step(self) -> None:
        if not self.initialized:
            raise RuntimeError("the target updater must be initialized before step()")
        targets, sources = self._pairs()
        with torch.no_grad():
            torch._foreach_lerp_(targets, sources, 1.0 - self.eps)


def fused_soft_update(loss_module: LossModule, *, eps: float | None = None,
                      tau: float | None = None) -> FusedSoftUpdate:
    """A :class:`FusedSoftUpdate` of ``loss_module``'s target parameters (``eps = 1 - tau``)."""
    return FusedSoftUpdate(loss_module, eps=eps, tau=tau)
