from torchrl_bail.objectives.bcq import BCQLoss  # noqa: F401
from torchrl_bail.objectives.bear import BEARLoss  # noqa: F401
from torchrl_bail.objectives.common import BestOfNPolicy, soft_clipped_double_q_target  # noqa: F401
from torchrl_bail.objectives.marwil import MARWILLoss  # noqa: F401
from torchrl_bail.objectives.vae import VAELoss  # noqa: F401
