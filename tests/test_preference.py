"""Preference losses against hand computation."""

from __future__ import annotations

import math

import pytest
import torch

from aynamics.preference import pro_ranking_loss, sft_on_best, soft_preference_loss, soft_targets

LN = math.log
# model: q = softmax(ℓ) = [1/4, 2/4, 1/4]
LOGPS = torch.tensor([[LN(1.0), LN(2.0), LN(1.0)]], dtype=torch.float64)


def test_soft_preference_hand_worked():
    """s = [1, 0, 0], τ = 1/ln 3: w ∝ 3^s = [3, 1, 1] / 5 = [0.6, 0.2, 0.2].
    L = -(0.6 ln 1/4 + 0.2 ln 1/2 + 0.2 ln 1/4) = 0.8 ln 4 + 0.2 ln 2 = 1.2476649...
    dL/dℓ = q - w = [0.25 - 0.6, 0.5 - 0.2, 0.25 - 0.2] = [-0.35, 0.3, 0.05]."""
    logps = LOGPS.clone().requires_grad_()
    rewards = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
    loss = soft_preference_loss(logps, rewards, temperature=1 / LN(3))
    assert loss.item() == pytest.approx(0.8 * LN(4) + 0.2 * LN(2), abs=1e-12)
    loss.backward()
    torch.testing.assert_close(logps.grad, torch.tensor([[-0.35, 0.3, 0.05]], dtype=torch.float64))


def test_temperature_limits_and_ties():
    """τ → 0: the best candidate only, L = -ln q_best = ln 4; a tie at the top shares: -(ln 1/4 + ln 1/2)/2;
    τ → ∞: uniform targets, L = (2 ln 4 + ln 2) / 3."""
    best = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
    assert soft_preference_loss(LOGPS, best, 0.0).item() == pytest.approx(LN(4))
    assert soft_preference_loss(LOGPS, best, 1e-4).item() == pytest.approx(LN(4))
    tie = torch.tensor([[1.0, 1.0, 0.0]], dtype=torch.float64)
    assert soft_preference_loss(LOGPS, tie, 0.0).item() == pytest.approx((LN(4) + LN(2)) / 2)
    torch.testing.assert_close(soft_targets(tie, 0.0), torch.tensor([[0.5, 0.5, 0.0]], dtype=torch.float64))
    assert soft_preference_loss(LOGPS, best, 1e6).item() == pytest.approx((2 * LN(4) + LN(2)) / 3, abs=1e-6)


def test_loss_is_minimal_when_the_model_matches_the_targets():
    rewards = torch.tensor([[0.9, 0.3, 0.1, 0.0]])
    w = soft_targets(rewards, 0.2)
    at_target = soft_preference_loss(torch.log(w), rewards, 0.2)
    entropy = -(w * torch.log(w)).sum()
    assert at_target.item() == pytest.approx(entropy.item(), abs=1e-6)
    assert soft_preference_loss(torch.zeros(1, 4), rewards, 0.2) > at_target


def test_batch_mean_and_mask():
    """Two rows average; a masked candidate neither receives target mass nor model mass."""
    logps = torch.cat([LOGPS, LOGPS])
    rewards = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 5.0]], dtype=torch.float64)
    mask = torch.tensor([[True, True, True], [True, True, False]])
    # row 2 without its third candidate: q = [1/3, 2/3], best = candidate 1 at τ = 0 -> -ln 2/3
    got = soft_preference_loss(logps, rewards, 0.0, mask)
    assert got.item() == pytest.approx((LN(4) + LN(3 / 2)) / 2)


def test_pro_ranking_hand_worked():
    """ℓ = [0, ln 2, 0], rewards [1, 0.5, 0] (already best first):
    L = -[(0 - ln 4) + (ln 2 - ln 3)] = ln 6."""
    rewards = torch.tensor([[1.0, 0.5, 0.0]], dtype=torch.float64)
    assert pro_ranking_loss(LOGPS, rewards).item() == pytest.approx(LN(6))
    # order comes from the rewards, not the positions: reversing both gives the same loss
    assert pro_ranking_loss(LOGPS.flip(1), rewards.flip(1)).item() == pytest.approx(LN(6))


def test_pro_ranking_ties_get_no_order():
    """Rewards [1, 0, 0, 0] at equal likelihoods: one term, -log(1 / 4) (was log 4 + log 3 + log 2 with the tied
    candidates ranked by sampling order); the gradient -3/4 on the best and 1/4 on each tied one alike (was
    [-0.75, -0.42, 0.08, 1.08]: helper-37), and the loss does not change when the tied candidates are reordered."""
    logps = torch.zeros(1, 4, requires_grad=True)
    rewards = torch.tensor([[1.0, 0.0, 0.0, 0.0]])
    loss = pro_ranking_loss(logps, rewards)
    loss.backward()
    assert loss.item() == pytest.approx(LN(4))
    torch.testing.assert_close(logps.grad, torch.tensor([[-0.75, 0.25, 0.25, 0.25]]))
    other = torch.tensor([[0.3, -1.0, 0.5, 2.0]])
    swapped = other[:, [0, 3, 1, 2]]
    assert pro_ranking_loss(other, rewards).item() == pytest.approx(pro_ranking_loss(swapped, rewards).item())
    two_levels = torch.tensor([[0.5, 0.5, 0.0]])  # two best tied above one: log 2 each (each over the worst alone)
    assert pro_ranking_loss(torch.zeros(1, 3), two_levels).item() == pytest.approx(2 * LN(2))


def test_pro_ranking_masked_candidate_has_no_gradient_even_if_not_finite():
    """A masked (padding) candidate whose score is -inf or NaN: the loss and every gradient stay finite, its own 0
    (the tie-aware loss gave NaN there: helper-40)."""
    for bad in (float("-inf"), float("nan")):
        logps = torch.tensor([[0.0, 0.0, 0.0, bad]], requires_grad=True)
        mask = torch.tensor([[True, True, True, False]])
        loss = pro_ranking_loss(logps, torch.tensor([[1.0, 0.0, 0.0, 0.0]]), mask)
        loss.backward()
        assert loss.item() == pytest.approx(LN(3))
        torch.testing.assert_close(logps.grad, torch.tensor([[-2 / 3, 1 / 3, 1 / 3, 0.0]]))


def test_gradient_descent_moves_probability_to_the_best_candidate():
    logps = torch.zeros(1, 4, requires_grad=True)
    rewards = torch.tensor([[0.1, 0.8, 0.4, 0.0]])
    opt = torch.optim.SGD([logps], lr=1.0)
    for loss_fn in (lambda: soft_preference_loss(logps, rewards, 0.1), lambda: pro_ranking_loss(logps, rewards)):
        logps.data.zero_()
        for _ in range(20):
            opt.zero_grad()
            loss_fn().backward()
            opt.step()
        assert logps.argmax().item() == 1 and logps[0, 1] > logps[0, 3]


def test_sft_on_best_picks_the_top_candidate():
    """Best candidate (index 1) has token log-probs [-1, -3] on 2 response tokens: NLL = 2."""
    token_logps = torch.tensor([[[-5.0, -5.0, -5.0], [-1.0, -3.0, -9.0]]])
    token_mask = torch.tensor([[[True, True, True], [True, True, False]]])
    assert sft_on_best(token_logps, token_mask, torch.tensor([[0.2, 0.7]])).item() == pytest.approx(2.0)


def test_bad_shapes_and_temperature_are_refused():
    with pytest.raises(ValueError, match=r"must be \(B, N\)"):
        soft_preference_loss(torch.zeros(3), torch.zeros(3), 1.0)
    with pytest.raises(ValueError, match="temperature = -1"):
        soft_preference_loss(torch.zeros(1, 2), torch.zeros(1, 2), -1.0)


def test_pro_ranking_with_a_masked_candidate():
    """ℓ = [0, ln 2, 0], rewards [1, 0.5, 0], the third candidate masked: the ranking is over the first two only,
    L = -[(0 - ln(1 + 2)) + (ln 2 - ln 2)] = ln 3 (with the masked one in the sums it would be ln 6), finite, with
    finite gradients and none on the masked candidate."""
    logps = LOGPS.clone().requires_grad_()
    rewards = torch.tensor([[1.0, 0.5, 0.0]], dtype=torch.float64)
    mask = torch.tensor([[True, True, False]])
    loss = pro_ranking_loss(logps, rewards, mask)
    assert loss.item() == pytest.approx(LN(3))
    loss.backward()
    assert torch.isfinite(logps.grad).all() and logps.grad[0, 2].item() == 0.0


def test_hard_targets_leave_a_masked_tie_out():
    """τ = 0, rewards [1, 0, 1] with the third candidate masked: the masked 1 does not share the top: [1, 0, 0]."""
    rewards = torch.tensor([[1.0, 0.0, 1.0]], dtype=torch.float64)
    got = soft_targets(rewards, 0.0, torch.tensor([[True, True, False]]))
    torch.testing.assert_close(got, torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64))


def test_bad_masks_are_refused():
    """A mask of another shape, or a row with every candidate masked, is a ValueError naming the problem."""
    rewards = torch.zeros(2, 3)
    with pytest.raises(ValueError, match=r"mask \(2, 2\): must match rewards \(2, 3\)"):
        soft_targets(rewards, 1.0, torch.ones(2, 2, dtype=torch.bool))
    with pytest.raises(ValueError, match="every row needs at least one candidate"):
        pro_ranking_loss(rewards, rewards, torch.tensor([[True, False, False], [False, False, False]]))


def test_sft_on_best_is_a_mean_over_rows():
    """Two rows; the best candidates' token NLLs: row 0 [-1] -> 1, row 1 [-3, -5] -> 4: mean (1 + 4) / 2 = 2.5."""
    token_logps = torch.tensor([[[-1.0, -7.0], [-9.0, -9.0]], [[-9.0, -9.0], [-3.0, -5.0]]])
    token_mask = torch.tensor([[[True, False], [True, True]], [[True, True], [True, True]]])
    rewards = torch.tensor([[0.9, 0.1], [0.2, 0.8]])
    assert sft_on_best(token_logps, token_mask, rewards).item() == pytest.approx(2.5)


def test_soft_targets_leave_a_masked_candidate_out_at_a_positive_temperature():
    """τ = 1/ln 3, rewards [1, 0, 5] with the third masked: w ∝ [3, 1, 0] = [0.75, 0.25, 0] (the masked 5 would
    otherwise take most of the mass). q over the first two = [1/3, 2/3]: L = 0.75 ln 3 + 0.25 ln 3/2. The rewards
    are constants: no gradient reaches them."""
    rewards = torch.tensor([[1.0, 0.0, 5.0]], dtype=torch.float64, requires_grad=True)
    mask = torch.tensor([[True, True, False]])
    torch.testing.assert_close(
        soft_targets(rewards, 1 / LN(3), mask), torch.tensor([[0.75, 0.25, 0.0]], dtype=torch.float64)
    )
    logps = LOGPS.clone().requires_grad_()
    loss = soft_preference_loss(logps, rewards, 1 / LN(3), mask)
    assert loss.item() == pytest.approx(0.75 * LN(3) + 0.25 * LN(1.5))
    loss.backward()
    assert rewards.grad is None


def test_pro_ranking_is_a_mean_over_rows():
    """Row 0: the hand-worked ln 6 (`test_pro_ranking_hand_worked`); row 1: equal likelihoods, rewards [1, 0, 0]:
    one term -ln(1/3) = ln 3. Loss (ln 6 + ln 3) / 2."""
    logps = torch.cat([LOGPS, torch.zeros(1, 3, dtype=torch.float64)])
    rewards = torch.tensor([[1.0, 0.5, 0.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    assert pro_ranking_loss(logps, rewards).item() == pytest.approx((LN(6) + LN(3)) / 2)


def test_bad_rewards_batches_and_temperatures_are_refused_not_nan():
    """A NaN or infinite reward on a kept candidate made the soft loss NaN (softmax of the row) and left the ranking
    loss silently finite (NaN compares with nothing); an empty batch gave NaN (a mean of nothing); a NaN temperature
    gave NaN; the SFT term took the NaN candidate as the best, read a (B', N) reward of another batch or a mask that
    broadcast. Each is now a ValueError naming it; a masked candidate's score may still be anything."""
    logps = torch.zeros(1, 3, requires_grad=True)
    for bad in (float("nan"), float("inf"), float("-inf")):
        rewards = torch.tensor([[bad, 0.5, 0.2]])
        for loss in (lambda: soft_preference_loss(logps, rewards, 0.1), lambda: pro_ranking_loss(logps, rewards)):
            with pytest.raises(ValueError, match=rf"rewards\[0, 0\] = {bad}: simulator scores must be finite"):
                loss()
        with pytest.raises(ValueError, match="must be finite"):
            sft_on_best(torch.zeros(1, 3, 2), torch.ones(1, 3, 2, dtype=torch.bool), rewards)
        masked = torch.tensor([[False, True, True]])
        assert torch.isfinite(soft_preference_loss(logps, rewards, 0.1, masked))
    empty = torch.zeros(0, 3)
    for loss in (lambda: soft_preference_loss(empty, empty, 0.1), lambda: pro_ranking_loss(empty, empty)):
        with pytest.raises(ValueError, match="empty batch"):
            loss()
    with pytest.raises(ValueError, match="every row needs at least one candidate"):  # N = 0: ranking gave 0
        pro_ranking_loss(torch.zeros(2, 0), torch.zeros(2, 0))
    with pytest.raises(ValueError, match="temperature = nan"):
        soft_preference_loss(logps, torch.tensor([[1.0, 0.0, 0.0]]), float("nan"))
    lp, m = torch.zeros(2, 3, 4), torch.ones(2, 3, 4, dtype=torch.bool)
    for bad_lp, bad_m, bad_r in (
        (lp, m, torch.rand(1, 3)),
        (lp, m[..., :1], torch.rand(2, 3)),
        (lp, m, torch.rand(2, 2)),
    ):
        with pytest.raises(ValueError, match=r"must be \(B, N, L\), \(B, N, L\) and \(B, N\)"):
            sft_on_best(bad_lp, bad_m, bad_r)
    with pytest.raises(ValueError, match="no candidate to imitate"):
        sft_on_best(torch.zeros(0, 3, 4), torch.zeros(0, 3, 4, dtype=torch.bool), torch.zeros(0, 3))


def test_integer_rewards_give_fractional_targets():
    """Integer scores (e.g. 1 valid / 0 invalid): the weights were cast back to the rewards' integer dtype, every
    fraction truncated to 0 and the loss 0 with no gradient."""
    rewards = torch.tensor([[1, 0, 0]])
    torch.testing.assert_close(soft_targets(rewards, 0.0), torch.tensor([[1.0, 0.0, 0.0]]))
    torch.testing.assert_close(soft_targets(torch.tensor([[1, 1, 0]]), 0.0), torch.tensor([[0.5, 0.5, 0.0]]))
    logps = LOGPS.clone().requires_grad_()
    assert soft_preference_loss(logps, rewards, 1 / LN(3)).item() == pytest.approx(
        soft_preference_loss(LOGPS, rewards.double(), 1 / LN(3)).item()
    )
