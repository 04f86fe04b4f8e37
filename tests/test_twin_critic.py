"""What BCQ and BEAR share (objectives/common.py), tested once for both: the critic target's bootstrap flag, the
best-of-N evaluation policy and the two ways of running the twin critics."""

from __future__ import annotations

import pytest
import torch
from _batch_rl_testing import (
    ACT,
    OBS,
    SPEC,
    batch,
    bcq_loss,
    bear_loss,
    linear_critics,
    one_thread,  # noqa: F401 (autouse fixture)
)
from tensordict import TensorDict

twin_critic_losses = pytest.mark.parametrize("make_loss", [bcq_loss, bear_loss], ids=["bcq", "bear"])


@twin_critic_losses
def test_critic_target_reads_terminated_never_done(make_loss):
    torch.manual_seed(0)
    loss = make_loss()
    assert ("next", "terminated") in loss.in_keys and ("next", "done") not in loss.in_keys
    with pytest.raises(KeyError, match="never on 'done'"):
        loss(batch().exclude(("next", "terminated")))


@twin_critic_losses
def test_target_bootstraps_a_truncation_but_not_a_termination(make_loss):
    # constant critics Q1 = 1, Q2 = 3: every sample's soft clipped value is 0.75 * 1 + 0.25 * 3 = 1.5
    loss = make_loss(qvalue=linear_critics(k=(0.0, 0.0), b=(1.0, 3.0)), gamma=0.9, reduction="none")
    td = batch((3,), terminated=torch.tensor([False, False, True]), truncated=torch.tensor([False, True, False]),
               reward=torch.tensor([0.5, 0.5, 0.5]))
    assert td["next", "done"].squeeze(-1).tolist() == [False, True, True]
    y = torch.tensor([0.5 + 0.9 * 1.5, 0.5 + 0.9 * 1.5, 0.5])  # the truncated row bootstraps like a plain one
    loss_qvalue, meta = loss.qvalue_loss(td)
    torch.testing.assert_close(loss_qvalue, (1.0 - y) ** 2 + (3.0 - y) ** 2)
    torch.testing.assert_close(meta["target_value_mean"], y.mean())


@twin_critic_losses
def test_policy_plays_the_argmax_q1_candidate_within_bounds(make_loss):
    # Q1 = -a_0, Q2 = +a_0: the policy must pick the candidate with the *smallest* first coordinate
    loss = make_loss(qvalue=linear_critics(k=(-1.0, 1.0)))
    policy = loss.policy(num_samples=10)
    observation = torch.randn(5, OBS)
    torch.manual_seed(3)
    with torch.no_grad():
        candidates = loss.candidate_actions(observation, 10)
    expected = candidates[torch.arange(5), candidates[..., 0].argmin(-1)]
    torch.manual_seed(3)
    action = policy(TensorDict({"observation": observation}, [5]))["action"]
    torch.testing.assert_close(action, expected)
    assert action.shape == (5, ACT) and not action.requires_grad
    low, high = SPEC.space.low, SPEC.space.high
    assert ((candidates >= low) & (candidates <= high)).all()
    single = policy(TensorDict({"observation": torch.randn(OBS)}, []))["action"]
    assert single.shape == (ACT,) and ((single >= low) & (single <= high)).all()


@twin_critic_losses
def test_vmap_and_loop_critics_agree(make_loss):
    torch.manual_seed(0)
    loss = make_loss()
    td = batch((5,))
    torch.manual_seed(2)
    vmapped = loss.qvalue_loss(td)[0]
    loss.deactivate_vmap = True
    torch.manual_seed(2)
    looped = loss.qvalue_loss(td)[0]
    torch.testing.assert_close(vmapped, looped)
