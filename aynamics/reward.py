"""The simulator as judge: sample N responses per video, parse, simulate and score them against the observed video.

No scene label is needed: a response is scored against the observed segmentation (and flow) by the fast scorer
(`aynamics.scorer`, ray casting on MuJoCo's threaded Batch). The reward of a response is

    iou   (default)  IoU of the candidate's segmentation with the observed one              in [0, 1]
    epe              1 / (1 + EPE / epe_scale): flow end-point error turned into a reward   in (0, 1]
    mix              mix_weight * iou + (1 - mix_weight) * epe-reward

over the full sequence (default) or the first frame. A response that cannot be parsed, validated or simulated
scores 0 and its reason is counted (`RewardStats.reasons`); nothing here raises for a bad response.

    texts = sample_completions(model, processor, prompts, num_samples=32, temperature=0.1, top_p=1.0)  # B x N
    scores = score_completions(texts, [v.observation for v in videos])                                  # B x N
    rewards = rewards_of(scores, RewardConfig(metric="iou"))                                            # (B, N)

In a multi-GPU run every rank calls these on its own batch, so each rank samples and scores its own candidates.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from aynamics.batching import collate, model_inputs, trim_completion
from aynamics.observation import Observation
from aynamics.processor import append_response
from aynamics.scene import SceneError, is_number, parse
from aynamics.scorer import EPE_INVALID, Score, score
from aynamics.simulate import usable_cores

METRICS = ("iou", "epe", "mix")
SPANS = ("full", "first")
MODES = ("greedy", "best1", "bestN")  # the paper's Table 10 evaluation modes
SCORE_FIELDS = ("iou_first", "iou_full", "epe_first", "epe_full")


@dataclass(frozen=True)
class RewardConfig:
    """How a `Score` becomes a scalar reward.

    Attributes:
        metric: "iou" (segmentation IoU, default), "epe" (flow end-point error as a reward) or "mix".
        span: "full" (mean over the sampled frames, default) or "first" (the first frame only).
        mix_weight: Weight of IoU in "mix", in [0, 1]; the EPE reward gets the rest.
        epe_scale: EPE in pixels (of a 480-wide image) at which the EPE reward is 0.5; > 0.
    """

    metric: str = "iou"
    span: str = "full"
    mix_weight: float = 0.5
    epe_scale: float = 5.0

    def __post_init__(self) -> None:
        if self.metric not in METRICS:
            raise ValueError(f"reward metric = {self.metric!r}: must be one of {METRICS}")
        if self.span not in SPANS:
            raise ValueError(f"reward span = {self.span!r}: must be one of {SPANS}")
        for name in ("mix_weight", "epe_scale"):  # "0.5" from a config failed on "'<=' not supported"
            value = getattr(self, name)
            if not is_number(value):
                raise TypeError(f"reward {name} = {value!r}: must be a number, not a {type(value).__name__}")
        if not 0.0 <= self.mix_weight <= 1.0:
            raise ValueError(f"reward mix_weight = {self.mix_weight}: must be in [0, 1]")
        if not (self.epe_scale > 0 and math.isfinite(self.epe_scale)):
            raise ValueError(f"reward epe_scale = {self.epe_scale}: must be a finite number > 0 (pixels)")

    @property
    def needs_flow(self) -> bool:
        return self.metric != "iou"


def reward_of(s: Score, config: RewardConfig = RewardConfig()) -> float:
    """The scalar reward of one score (0 for an invalid response).

    Raises:
        ValueError: an EPE reward asked of a score without flow (the observation has none).
    """
    if not isinstance(s, Score):  # a str failed on "'str' object has no attribute 'valid'"
        raise TypeError(f"reward_of: s is a {type(s).__name__}, not a Score")
    if not isinstance(config, RewardConfig):
        raise TypeError(f"reward_of: config is a {type(config).__name__}, not a RewardConfig")
    if not s.valid:
        return 0.0
    iou = s.iou_full if config.span == "full" else s.iou_first
    if not 0.0 <= iou <= 1.0:  # NaN was returned as the reward
        raise ValueError(f"reward_of: {'iou_' + config.span} = {iou!r}: an IoU must be in [0, 1]")
    if config.metric == "iou":
        return float(iou)
    epe = s.epe_full if config.span == "full" else s.epe_first
    if epe is None:
        raise ValueError(f"reward metric = {config.metric!r} needs flow, but the observed video has none")
    if not epe >= 0:  # NaN was returned as the reward, -epe_scale divided by zero, below it a negative reward
        raise ValueError(f"reward_of: {'epe_' + config.span} = {epe!r}: an end-point error must be >= 0 pixels")
    r_epe = 1.0 / (1.0 + float(epe) / config.epe_scale)
    return r_epe if config.metric == "epe" else config.mix_weight * float(iou) + (1 - config.mix_weight) * r_epe


def rewards_of(scores: Sequence[Sequence[Score]], config: RewardConfig = RewardConfig()) -> torch.Tensor:
    """(B, N) float32 rewards of B videos x N candidates' scores."""
    if isinstance(scores, (str, bytes, Score)) or not hasattr(scores, "__iter__"):
        raise TypeError(f"rewards_of: scores is a {type(scores).__name__}: must be B lists of N Scores")
    scores = list(scores)  # a generator of rows is read once
    for b, row in enumerate(scores):  # a flat list failed on "'Score' object is not iterable"
        if isinstance(row, (str, bytes, Score)) or not hasattr(row, "__len__"):
            hint = " (one video's scores: rewards_of([scores]))" if isinstance(row, Score) else ""
            raise TypeError(f"rewards_of: scores[{b}] is a {type(row).__name__}: must be a list of Scores{hint}")
        if len(row) != len(scores[0]):  # torch's "expected sequence of length 1 at dim 1 (got 0)"
            raise ValueError(f"rewards_of: scores[{b}] has {len(row)} scores, scores[0] {len(scores[0])}: need N each")
    return torch.tensor([[reward_of(s, config) for s in row] for row in scores], dtype=torch.float32)


def _score_one(texts: Sequence[str], observation: Observation, nthread: int | None) -> list[Score]:
    """Parse here (so the reason names the YAML problem), then let the scorer batch the valid scenes."""
    out: list[Score | None] = [None] * len(texts)
    scenes, where = [], []
    for k, t in enumerate(texts):
        try:
            scenes.append(parse(t))
            where.append(k)
        except (SceneError, ValueError, TypeError, RecursionError) as e:  # a model's text must never crash a step
            epe = EPE_INVALID if observation.flow is not None else None
            out[k] = Score(0.0, 0.0, epe, epe, False, f"parse: {' '.join(str(e).split())}")
    for k, s in zip(where, score(scenes, observation, nthread=nthread) if scenes else [], strict=True):
        out[k] = s if s.valid else Score(s.iou_first, s.iou_full, s.epe_first, s.epe_full, False, f"sim: {s.reason}")
    return out  # type: ignore[return-value]


def _check_observations(observations: Sequence[Observation]) -> None:
    if isinstance(observations, Observation) or not hasattr(observations, "__len__"):
        raise TypeError(f"observations is a {type(observations).__name__}: must be a list of Observations")
    for b, o in enumerate(observations):
        if not isinstance(o, Observation):
            raise TypeError(f"observations[{b}] is a {type(o).__name__}, not an Observation")


def score_completions(
    completions: Sequence[Sequence[str]],
    observations: Sequence[Observation],
    *,
    nthread: int | None = None,
    workers: int = 1,
) -> list[list[Score]]:
    """Score each video's candidate texts against its observation; never raises for a bad candidate.

    Args:
        completions: B lists of candidate texts (model outputs; the YAML is taken from `<answer>` if present).
        observations: B observed videos.
        nthread: Threads of each MuJoCo Batch (None: all cores).
        workers: Videos scored at once in a thread pool, the cores shared among them (on 2 cores measured no
            faster than 1: `benchmarks/bench_pro.py`).

    Returns:
        B lists of `Score`s in candidate order; invalid ones have `valid=False` and a reason starting with
        "parse:" (no YAML or an invalid scene) or "sim:" (the simulation failed or diverged).
    """
    _check_observations(observations)
    for b, c in enumerate(completions):  # a text here was scored as its characters, each an invalid candidate
        if isinstance(c, (str, bytes)) or not hasattr(c, "__len__"):
            raise TypeError(f"completions[{b}] is a {type(c).__name__}: must be a list of candidate texts")
    if len(completions) != len(observations):
        raise ValueError(f"{len(completions)} candidate lists for {len(observations)} observations: must match")
    if workers < 1:
        raise ValueError(f"workers = {workers}: must be >= 1")
    if workers == 1 or len(observations) == 1:
        return [_score_one(c, o, nthread) for c, o in zip(completions, observations, strict=True)]
    per = max(1, (nthread or usable_cores()) // workers)
    with ThreadPoolExecutor(workers) as pool:
        return list(pool.map(lambda co: _score_one(co[0], co[1], per), zip(completions, observations, strict=True)))


def simulator_rewards(
    predictions: Sequence[str],
    observations: Sequence[Observation],
    *,
    config: RewardConfig = RewardConfig(),
    nthread: int | None = None,
) -> list[float]:
    """Pure, batched reward function: one reward per (prediction, observation) pair, 0.0 for invalid predictions.

    Predictions sharing one `Observation` object are scored in one batch.
    """
    if isinstance(predictions, (str, bytes)) or not hasattr(predictions, "__len__"):
        raise TypeError(f"predictions is a {type(predictions).__name__}: must be a list of texts")
    _check_observations(observations)
    if len(predictions) != len(observations):
        raise ValueError(f"{len(predictions)} predictions for {len(observations)} observations: must match")
    groups: dict[int, list[int]] = {}
    for k, o in enumerate(observations):
        groups.setdefault(id(o), []).append(k)
    out = [0.0] * len(predictions)
    for idx in groups.values():
        for k, s in zip(idx, _score_one([predictions[k] for k in idx], observations[idx[0]], nthread), strict=True):
            out[k] = reward_of(s, config)
    return out


# --------------------------------------------------------------------------------------------
# Statistics
# --------------------------------------------------------------------------------------------
TRUNCATED = "truncated"  # the reason prefix of an invalid response that reached the token limit


def reason_kind(reason: str | None) -> str:
    """A countable kind of an invalid response's reason: "truncated" (cut off at the token limit: `mark_truncated`),
    "no_yaml" (none, a syntax error or not a list of items), "invalid_scene" (fields missing or out of range) or
    "simulation" (failed or diverged)."""
    if reason is None:
        return "valid"
    if reason.startswith(TRUNCATED):
        return TRUNCATED
    if reason.startswith("sim:"):
        return "simulation"
    text = reason.lower()
    not_yaml = ("no yaml found", "yaml:", "must be a yaml list")
    return "no_yaml" if any(m in text for m in not_yaml) else "invalid_scene"


@dataclass(frozen=True)
class RewardStats:
    """Reward statistics of a batch: mean, best (mean over videos of the best candidate), share invalid."""

    mean: float
    best: float
    invalid: float
    count: int
    reasons: dict[str, int] = field(default_factory=dict)

    @classmethod
    def of(cls, rewards: torch.Tensor, scores: Sequence[Sequence[Score]]) -> RewardStats:
        flat = [s for row in scores for s in row]
        kinds = Counter(reason_kind(s.reason) for s in flat if not s.valid)
        bad = sum(kinds.values())
        return cls(
            float(rewards.mean()), float(rewards.max(dim=1).values.mean()), bad / max(len(flat), 1), len(flat), kinds
        )

    def to_metrics(self, prefix: str = "reward/") -> dict[str, float]:
        """{prefix}mean, best, invalid and invalid_<kind> shares, ready for `LightningModule.log_dict`."""
        out = {f"{prefix}mean": self.mean, f"{prefix}best": self.best, f"{prefix}invalid": self.invalid}
        for kind in (TRUNCATED, "no_yaml", "invalid_scene", "simulation"):
            out[f"{prefix}invalid_{kind}"] = self.reasons.get(kind, 0) / max(self.count, 1)
        return out


def evaluation_modes(
    greedy: Sequence[Score], samples: Sequence[Sequence[Score]], rewards: torch.Tensor
) -> dict[str, float]:
    """The paper's Table 10 modes averaged over B videos: greedy, Best@1 (mean over samples), Best@N.

    Best@N takes, per video, the sample with the highest simulator reward (`rewards`, (B, N)) and reports its
    metrics; among samples tied on the reward a valid one is taken (an IoU reward ties a valid scene of IoU 0 with
    an invalid one, whose EPE of 100 px was then reported when it came first). EPE keys are present only when
    every score has flow. Invalid samples count with IoU 0 and EPE `scorer.EPE_INVALID`.

    Returns:
        {"greedy/iou_first": ..., "best1/epe_full": ..., "bestN/iou_full": ...}
    """
    if len(greedy) != len(samples) or rewards.shape[0] != len(samples):
        raise ValueError(f"{len(greedy)} greedy scores, {len(samples)} sample lists, rewards {tuple(rewards.shape)}")
    best = []
    for row, scores in zip(rewards.tolist(), samples, strict=True):
        top = max(row)
        tied = [k for k, r in enumerate(row) if r == top]
        best.append(next((k for k in tied if scores[k].valid), tied[0]))
    out: dict[str, float] = {}
    for name in SCORE_FIELDS:
        g = [getattr(s, name) for s in greedy]
        per = [[getattr(s, name) for s in row] for row in samples]
        if any(v is None for v in g) or any(v is None for row in per for v in row):
            continue
        out[f"greedy/{name}"] = float(np.mean(g))
        out[f"best1/{name}"] = float(np.mean([np.mean(row) for row in per]))
        out[f"bestN/{name}"] = float(np.mean([row[b] for row, b in zip(per, best, strict=True)]))
    return out


# --------------------------------------------------------------------------------------------
# Sampling and the candidates' batch
# --------------------------------------------------------------------------------------------
def vision_token_ids(model: torch.nn.Module) -> list[int]:
    """Ids of the image / video placeholder and vision start / end tokens of a Qwen2.5-VL model's config.

    A response must never contain them: in the log-likelihood pass they would be taken for image slots.
    """
    cfg = model.config
    names = ("image_token_id", "video_token_id", "vision_start_token_id", "vision_end_token_id")
    return [int(getattr(cfg, n)) for n in names if getattr(cfg, n, None) is not None]


def mark_truncated(
    scores: Sequence[Sequence[Score]], ids: Sequence[Sequence[Sequence[int]]], max_new_tokens: int, eos: Sequence[int]
) -> list[list[Score]]:
    """The B x N `scores` of the responses `ids` (as `sample_completions` trims them), each invalid one that reached
    `max_new_tokens` without an end-of-turn id (`eos`) given the reason "truncated ...": it may be a right scene
    cut off, which counts apart from scenes the model got wrong (`reason_kind`)."""
    stop = set(eos)

    def marked(s: Score, c: Sequence[int]) -> Score:
        if s.valid or len(c) < max_new_tokens or (c and c[-1] in stop):
            return s
        return replace(s, reason=f"{TRUNCATED} at max_new_tokens = {max_new_tokens}: {s.reason}")

    return [[marked(s, c) for s, c in zip(srow, crow, strict=True)] for srow, crow in zip(scores, ids, strict=True)]


def eos_ids(model: torch.nn.Module) -> list[int]:
    """The model's end-of-turn token ids (its generation config's)."""
    eos = model.generation_config.eos_token_id
    return [eos] if isinstance(eos, int) else list(eos or [])


def decoding(temperature: float, top_p: float = 1.0) -> dict:
    """`generate` settings for exactly greedy decoding (temperature 0) or exactly temperature + nucleus sampling.

    Everything that shapes the distribution is given: `generate` fills what is not passed from the checkpoint's
    `generation_config.json`, and Qwen2.5-VL Instruct's (top_k 1, repetition_penalty 1.05, do_sample true) would
    make N samples one repeated response (no preference pairs for PRO) and put a repetition penalty into greedy
    evaluation; transformers' own default adds top_k 50.
    """
    neutral = {"repetition_penalty": 1.0, "no_repeat_ngram_size": 0}
    if temperature > 0:
        return neutral | {"do_sample": True, "temperature": temperature, "top_p": top_p, "top_k": 0}
    return neutral | {"do_sample": False}


@torch.no_grad()
def sample_completions(
    model: torch.nn.Module,
    processor,
    prompts: Sequence[dict[str, torch.Tensor]],
    *,
    num_samples: int,
    temperature: float,
    top_p: float = 1.0,
    max_new_tokens: int = 512,
    min_new_tokens: int = 0,
) -> tuple[list[list[list[int]]], list[list[str]]]:
    """Sample `num_samples` responses per prompt (temperature 0: greedy, one response repeated once).

    Args:
        model: The (LoRA-wrapped) Qwen2.5-VL model; put in eval mode for sampling, its mode restored after.
        processor: The model's processor (tokenizer for padding and decoding).
        prompts: B unbatched prompts from `processor.build_prompt`.
        num_samples: N responses per prompt (>= 1).
        temperature: Sampling temperature (> 0), or 0 for greedy decoding (N must then be 1).
        top_p: Nucleus sampling mass in (0, 1].
        max_new_tokens: Response length limit in tokens.
        min_new_tokens: End-of-turn suppressed before this many tokens (benchmarks: a scene's length).

    Returns:
        (ids, texts): B x N trimmed token-id lists (ending in the end-of-turn id when the model stopped) and the
        decoded texts (special tokens dropped).
    """
    if num_samples < 1:
        raise ValueError(f"num_samples = {num_samples}: must be >= 1")
    if not temperature >= 0 or not 0 < top_p <= 1:  # NaN too: it decoded greedily
        raise ValueError(f"temperature = {temperature}, top_p = {top_p}: need temperature >= 0, 0 < top_p <= 1")
    if temperature == 0 and num_samples != 1:
        raise ValueError(f"temperature = 0 (greedy) with num_samples = {num_samples}: greedy gives one response")
    if max_new_tokens < 1:
        raise ValueError(f"max_new_tokens = {max_new_tokens}: must be >= 1")
    from aynamics.sharding import gathered, generation_kwargs

    tok = processor.tokenizer
    batch = collate(list(prompts), tok.pad_token_id)
    device = next(model.parameters()).device
    inputs = {k: v.to(device) for k, v in model_inputs(batch).items()}
    was_training = model.training
    model.eval()
    try:
        with gathered(model):  # sharded weights (trainer=fsdp): gathered once for the whole response, not per token
            out = model.generate(
                **inputs,
                max_new_tokens=max_new_tokens,
                min_new_tokens=min_new_tokens,
                num_return_sequences=num_samples,
                use_cache=True,
                suppress_tokens=vision_token_ids(model),  # never sampled: they would count as image slots
                **decoding(temperature, top_p),
                **generation_kwargs(model),  # sharded weights (trainer=fsdp): every process generates together
            )
    finally:
        model.train(was_training)
    gen = out[:, batch["input_ids"].shape[1] :].cpu()  # (B*N, T): rows of prompt b are b*N .. b*N + N - 1
    eos = eos_ids(model)
    rows = [trim_completion(r, pad_token_id=tok.pad_token_id, eos_token_ids=eos) for r in gen]
    texts = tok.batch_decode(rows, skip_special_tokens=True)
    n = num_samples
    return [rows[b * n : (b + 1) * n] for b in range(len(prompts))], [
        texts[b * n : (b + 1) * n] for b in range(len(prompts))
    ]


def candidate_batch(
    prompts: Sequence[dict[str, torch.Tensor]],
    completions: Sequence[Sequence[Sequence[int]]],
    pad_token_id: int,
    forbidden: Sequence[int] = (),
) -> dict[str, torch.Tensor]:
    """B x N rows (prompt b + its candidate n, row b*N + n) for the log-likelihood forward pass.

    Every row carries its own copy of its prompt's visual tensors, so `pixel_values`, `image_grid_thw` (and the
    video ones) follow the row order, and `mm_token_type_ids` is 0 on the candidate tokens. Labels hold the
    candidate tokens (-100 elsewhere), ready for `mean_token_logprob`. Every candidate must be non-empty and free
    of the `forbidden` ids (`vision_token_ids(model)`: they would be taken for image slots).
    """
    if len(prompts) != len(completions):
        raise ValueError(f"{len(prompts)} prompts for {len(completions)} candidate lists: must match")
    sizes = {len(c) for c in completions}
    if len(sizes) != 1:
        raise ValueError(f"candidate lists of sizes {sorted(sizes)}: every prompt needs the same N")
    rows = []
    for b, (p, cands) in enumerate(zip(prompts, completions, strict=True)):
        for n, c in enumerate(cands):
            if len(c) == 0:
                raise ValueError(f"candidate {n} of prompt {b} is empty: append the end-of-turn id at least")
            bad = set(forbidden).intersection(int(i) for i in c)
            if bad:
                raise ValueError(f"candidate {n} of prompt {b} holds vision token ids {sorted(bad)}: not allowed")
            rows.append(append_response(p, c))
    return collate(rows, pad_token_id)
