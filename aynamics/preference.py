"""Preference objectives for the PRO stage: pure functions of sequence log-likelihoods and simulator rewards.

Shapes: `seq_logps` and `rewards` are (B, N): B input videos, N sampled candidates each. `seq_logps[b, n]` is the
length-normalised log-likelihood of candidate n, i.e. the mean per-token log-probability of its response tokens
given the input (`aynamics.logprobs.mean_token_logprob`). `rewards[b, n]` is the simulator's score (IoU in
[0, 1]; 0 for an invalid response).
"""

from __future__ import annotations

import torch


def _check(seq_logps: torch.Tensor, rewards: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """The candidate mask (B, N) bool, once the shapes, the batch and the kept candidates' rewards are sound.

    Raises:
        ValueError: shapes that are not one (B, N), an empty batch (B = 0: its mean is NaN), a row without a
            candidate, or a NaN / infinite reward on a kept candidate (softmax(s / τ) of one is NaN for every
            candidate of its row; the ranking compared it with none), naming where.
    """
    if seq_logps.ndim != 2 or seq_logps.shape != rewards.shape:
        raise ValueError(f"seq_logps {tuple(seq_logps.shape)} and rewards {tuple(rewards.shape)}: both must be (B, N)")
    if rewards.shape[0] == 0:
        raise ValueError(f"rewards {tuple(rewards.shape)}: an empty batch has no loss (B = 0)")
    if mask is None:
        keep = torch.ones_like(rewards, dtype=torch.bool)
    elif mask.shape != rewards.shape:
        raise ValueError(f"mask {tuple(mask.shape)}: must match rewards {tuple(rewards.shape)}")
    else:
        keep = mask.bool()
    if not keep.any(dim=1).all():
        raise ValueError("mask: every row needs at least one candidate")
    check_finite_rewards(rewards, keep)
    return keep


def check_finite_rewards(rewards: torch.Tensor, keep: torch.Tensor | None = None) -> None:
    """Refuse a NaN or infinite reward (on a `keep` candidate, default all), naming the first and the count."""
    bad = ~torch.isfinite(rewards.detach())
    bad = bad & keep if keep is not None else bad
    if bad.any():
        b, n = (int(i) for i in bad.nonzero()[0])
        raise ValueError(
            f"rewards[{b}, {n}] = {rewards[b, n].item()}: simulator scores must be finite numbers "
            f"({int(bad.sum())} are not)"
        )


def soft_targets(rewards: torch.Tensor, temperature: float, mask: torch.Tensor | None = None) -> torch.Tensor:
    """w = softmax(s / τ) over the N candidates of each row (masked candidates get 0).

    τ → 0 gives the one-hot of the best candidate (ties share equally: τ = 0 is that limit exactly);
    τ → ∞ gives the uniform distribution over the candidates.
    """
    if not temperature >= 0:  # NaN too
        raise ValueError(f"temperature = {temperature}: must be >= 0")
    keep = _check(rewards, rewards, mask)
    s = rewards.detach().to(torch.float64)
    # weights of integer (or bool) scores are fractions: cast back to those, they truncated to 0
    dtype = rewards.dtype if rewards.is_floating_point() else torch.get_default_dtype()
    if temperature == 0:
        best = s.masked_fill(~keep, float("-inf")).amax(dim=1, keepdim=True)
        w = ((s == best) & keep).to(torch.float64)
        return (w / w.sum(dim=1, keepdim=True)).to(dtype)
    logits = (s / temperature).masked_fill(~keep, float("-inf"))
    return torch.softmax(logits, dim=1).to(dtype)


def soft_preference_loss(
    seq_logps: torch.Tensor, rewards: torch.Tensor, temperature: float, mask: torch.Tensor | None = None
) -> torch.Tensor:
    """Reward-weighted soft-label cross-entropy between the simulator's preference and the model's.

    With ℓ_bn the length-normalised log-likelihood of candidate n for input b and s_bn its simulator score:

        w_bn = exp(s_bn / τ) / Σ_m exp(s_bm / τ)          (targets; no gradient)
        q_bn = exp(ℓ_bn) / Σ_m exp(ℓ_bm)                  (the model's distribution over its own candidates)
        L    = -(1/B) Σ_b Σ_n w_bn log q_bn

    dL/dℓ_bn = (q_bn - w_bn) / B: probability moves toward candidates the simulator scores above the model's
    current preference. L is minimal (= the entropy of w) when q = w.

    Args:
        seq_logps: (B, N) length-normalised sequence log-likelihoods (with gradient).
        rewards: (B, N) simulator scores (treated as constants).
        temperature: τ > 0 (τ = 0: hard best-candidate targets, ties shared).
        mask: optional (B, N) bool, False for padding candidates.

    Returns:
        Scalar loss.
    """
    keep = _check(seq_logps, rewards, mask)
    w = soft_targets(rewards, temperature, keep).to(seq_logps.dtype)
    log_q = torch.log_softmax(seq_logps.masked_fill(~keep, float("-inf")), dim=1)
    return -(w * log_q.masked_fill(~keep, 0.0)).sum(dim=1).mean()


def pro_ranking_loss(seq_logps: torch.Tensor, rewards: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """The original hard-ranking PRO loss (Song et al., 2024): a Plackett-Luce likelihood of the reward ranking.

    Each candidate k is pushed above every candidate scored strictly below it:

        L = -(1/B) Σ_b Σ_k log( exp(ℓ_bk) / (exp(ℓ_bk) + Σ_{i: s_bi < s_bk} exp(ℓ_bi)) )

    Without ties this is the Plackett-Luce likelihood of the ranking π(1), ..., π(N), best first:
    Σ_k log( exp(ℓ_bπ(k)) / Σ_{i≥k} exp(ℓ_bπ(i)) ). Candidates that score the same get no term against each other
    (a ranking would invent an order among them: the many invalid responses at 0 pushed apart by sampling order),
    and a candidate with none below it (the worst, or all tied) adds log 1 = 0.
    """
    keep = _check(seq_logps, rewards, mask)
    seq_logps = seq_logps.masked_fill(~keep, 0.0)  # a masked candidate's value (-inf, NaN) never reaches a gradient
    s = rewards.detach()
    below = (s[:, None, :] < s[:, :, None]) & keep[:, None, :] & keep[:, :, None]  # [b, k, i]: s_i < s_k
    rivals = below | torch.eye(s.shape[1], dtype=torch.bool, device=s.device)  # with k itself
    lp = seq_logps[:, None, :].expand(-1, s.shape[1], -1).masked_fill(~rivals, float("-inf"))
    terms = (seq_logps - torch.logsumexp(lp, dim=2)).masked_fill(~keep, 0.0)  # (B, N)
    return -terms.sum(dim=1).mean()


def sft_on_best(token_logps: torch.Tensor, token_mask: torch.Tensor, rewards: torch.Tensor) -> torch.Tensor:
    """Optional SFT term: the mean negative log-likelihood per token of each row's best-scored candidate.

    Args:
        token_logps: (B, N, L) per-token log-probabilities of the responses.
        token_mask: (B, N, L) bool, True on response tokens.
        rewards: (B, N) simulator scores (finite).

    A best candidate without response tokens adds 0 (as `logprobs.mean_token_logprob`).

    Raises:
        ValueError: shapes that do not match (B, N, L) and (B, N), an empty batch, or a NaN / infinite reward (its
            `argmax` is the NaN candidate).
    """
    if token_logps.ndim != 3 or token_mask.shape != token_logps.shape or rewards.shape != token_logps.shape[:2]:
        raise ValueError(
            f"token_logps {tuple(token_logps.shape)}, token_mask {tuple(token_mask.shape)}, rewards "
            f"{tuple(rewards.shape)}: must be (B, N, L), (B, N, L) and (B, N)"
        )
    if rewards.shape[0] == 0 or rewards.shape[1] == 0:
        raise ValueError(f"rewards {tuple(rewards.shape)}: no candidate to imitate (B = 0 or N = 0)")
    check_finite_rewards(rewards)
    best = rewards.argmax(dim=1)  # (B,)
    idx = torch.arange(len(best))
    lp, m = token_logps[idx, best], token_mask[idx, best].to(token_logps.dtype)
    return -((lp * m).sum(dim=1) / m.sum(dim=1).clamp(min=1)).mean()
