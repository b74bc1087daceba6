"""Log-probabilities of a batch's labelled tokens under the model: pure functions shared by the SFT and PRO stages.

`token_logprobs` gives each labelled token's log p (in chunks recomputed in backward above `CHUNK_ENTRIES` logit
entries), `mean_token_logprob` each row's mean.

    out = model(**model_inputs(batch)); lp = mean_token_logprob(out.logits, batch["labels"])
"""

from __future__ import annotations

import torch

from aynamics.processor import IGNORE_INDEX

# Above this many logit entries of labelled positions (256 MB in float32), log-probabilities are computed in
# chunks recomputed in backward: a 7B vocabulary (152k) reaches it at ~440 tokens, and the full float32 copy plus the
# log-softmax kept for backward would take ~8 bytes per entry (PRO's 32 candidates of ~800 tokens: ~30 GB).
CHUNK_ENTRIES = 1 << 26


def token_logprobs(
    logits: torch.Tensor, labels: torch.Tensor, chunk_entries: int = CHUNK_ENTRIES
) -> tuple[torch.Tensor, torch.Tensor]:
    """Log-probability of every labelled token under the model, with the usual one-step shift.

    Args:
        logits: (B, K, V) model outputs for the last K positions of input_ids of length L (K = L: all of them;
            fewer with the model's `logits_to_keep=K`, when every labelled token lies in the last K - 1).
        labels: (B, L), -100 where no loss; labels[:, t] is predicted by the logits of position t - 1.
        chunk_entries: Above this many logit entries at labelled positions, log-probabilities are computed per
            chunk of positions (log p = x[label] - logsumexp(x) in float32), and the backward recomputes each
            chunk's softmax: memory of one chunk instead of two float32 copies of them all.

    Returns:
        logp (B, L-1) float32, 0 where masked, and mask (B, L-1) bool. The one-pass path normalises only the
        labelled positions; the chunked one every kept position (the padding of shorter candidates too).

    Raises:
        ValueError: shapes that disagree, or a labelled token outside the kept logits.
    """
    b, length = labels.shape
    kept = logits.shape[1]
    if logits.shape[0] != b or not 1 <= kept <= length:
        raise ValueError(f"logits {tuple(logits.shape)} and labels {tuple(labels.shape)} disagree on (B, L)")
    target = labels[:, 1:]
    mask = target != IGNORE_INDEX
    start = length - kept  # logits[:, j] is position start + j, predicting labels[:, start + j + 1]
    if start and mask[:, :start].any():
        raise ValueError(f"labelled tokens before the last {kept} positions, whose logits were not kept")
    window, tail = target[:, start:], mask[:, start:]
    out = torch.zeros(target.shape, dtype=torch.float32, device=logits.device)
    n = int(tail.sum())
    if n * logits.shape[-1] <= chunk_entries:
        picked = logits[:, :-1][tail].float()  # (n, V)
        lp = picked.log_softmax(-1).gather(-1, window[tail].unsqueeze(-1)).squeeze(-1)
        return out.masked_scatter(mask, lp), mask
    lp = _ChunkedLabelLogprob.apply(logits, window.clamp(min=0), max(1, chunk_entries // logits.shape[-1]))
    out[:, start:] = torch.where(tail, lp, torch.zeros_like(lp))
    return out, mask


class _ChunkedLabelLogprob(torch.autograd.Function):
    """log softmax(logits[:, t])[label[:, t]] for t < K - 1, (B, K - 1) float32, a few positions at a time.

    Nothing of size V is kept between forward and backward: the backward recomputes each chunk's softmax and
    writes d logp / d x = onehot(label) - softmax(x) into one gradient of the logits' shape and dtype (slicing
    under autograd instead allocated a zero tensor of the logits' full size for every chunk in backward)."""

    @staticmethod
    def _chunks(logits: torch.Tensor, rows: int):
        for i in range(logits.shape[0]):
            for t in range(0, logits.shape[1] - 1, rows):
                yield i, t, min(t + rows, logits.shape[1] - 1)  # the last position predicts nothing

    @staticmethod
    def forward(ctx, logits: torch.Tensor, labels: torch.Tensor, rows: int) -> torch.Tensor:
        out = torch.empty(labels.shape, dtype=torch.float32, device=logits.device)
        for i, t, end in _ChunkedLabelLogprob._chunks(logits, rows):
            x = logits[i, t:end].float()
            out[i, t:end] = x.gather(-1, labels[i, t:end, None])[:, 0] - torch.logsumexp(x, -1)
        ctx.save_for_backward(logits, labels)
        ctx.rows = rows
        return out

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        logits, labels = ctx.saved_tensors
        grad = torch.zeros_like(logits)
        for i, t, end in _ChunkedLabelLogprob._chunks(logits, ctx.rows):
            g = -torch.softmax(logits[i, t:end].float(), -1)
            g.scatter_add_(-1, labels[i, t:end, None], torch.ones_like(g[:, :1]))
            grad[i, t:end] = g * grad_out[i, t:end, None]
        return grad, None, None


def mean_token_logprob(logits: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Length-normalised sequence log-likelihood: mean log p over each row's labelled tokens, (B,); 0 if none."""
    lp, mask = token_logprobs(logits, labels)
    return lp.sum(-1) / mask.sum(-1).clamp(min=1)
