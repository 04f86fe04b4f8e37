"""TorchRL loss modules, one per file: BAIL's upper envelope, the baselines MARWIL, BCQ and BEAR, and Fitted Q
Evaluation (FQE), which scores a trained policy on the batch.

BC (and BAIL's imitation step) is TorchRL's own :class:`~torchrl.objectives.BCLoss`.
"""

from torchrl_bail.objectives.bcq import BCQLoss
from torchrl_bail.objectives.bear import BEARLoss, laplacian_mmd
from torchrl_bail.objectives.common import BestOfNPolicy, soft_clipped_double_q_target
from torchrl_bail.objectives.fqe import FQELoss, episode_starts
from torchrl_bail.objectives.marwil import MARWILLoss
from torchrl_bail.objectives.upper_envelope import UpperEnvelopeLoss, envelope_penalty
from torchrl_bail.objectives.vae import VAELoss

__all__ = [
    "BCQLoss",
    "BEARLoss",
    "BestOfNPolicy",
    "FQELoss",
    "MARWILLoss",
    "UpperEnvelopeLoss",
    "VAELoss",
    "envelope_penalty",
    "episode_starts",
    "laplacian_mmd",
    "soft_clipped_double_q_target",
]
