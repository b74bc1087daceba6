"""One PRO step split into sampling, scoring and forward/backward, with the tiny model; candidates scored per second.

    .venv/bin/python benchmarks/bench_pro.py [--videos 2] [--samples 8] [--repeats 2]

Each video of a small generated data set (real generator, 240x160) gets N candidates. The tiny model's own samples
are almost all invalid YAML (and an invalid candidate costs the scorer nothing), so the scorer is timed on N valid
candidates per video: the true scene plus N - 1 perturbed copies (positions +-0.3 m, velocities +-1 m/s), as a
trained model's samples would be. Sampling is timed on the same number of candidates with the tiny model forced
to write as many tokens as those scenes have (`min_new_tokens`), and forward/backward on those candidate texts.
Target: scoring costs less than sampling the same candidates.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from timing import timed  # noqa: E402

from aynamics import lm  # noqa: E402
from aynamics import reward as rw  # noqa: E402
from aynamics.generate import GenerateConfig, generate_dataset  # noqa: E402
from aynamics.pro import ProModule  # noqa: E402
from aynamics.processor import response_ids  # noqa: E402
from aynamics.scene import dump, parse  # noqa: E402
from aynamics.unlabeled import GeneratedVideos  # noqa: E402


def perturbed(scene, rng: np.random.Generator):
    objs = []
    for o in scene.objects:
        st = o.state
        pos = tuple(np.add(st.position, [*rng.uniform(-0.3, 0.3, 2), 0.0]).round(3))
        vel = tuple(np.add(st.linear_velocity, [*rng.uniform(-1, 1, 2), 0.0]).round(3))
        objs.append(o.model_copy(update={"state": st.model_copy(update={"position": pos, "linear_velocity": vel})}))
    return scene.model_copy(update={"objects": tuple(objs)})


def best_and_result(fn, repeats: int):
    t = timed(fn, repeats)
    return t.best, t.result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--videos", type=int, default=2)
    ap.add_argument("--samples", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(os.cpu_count() or 1)
    rng = np.random.default_rng(0)

    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        cfg = GenerateConfig(width=240, height=160, workers=0, splits=(1.0, 0.0, 0.0))
        path = generate_dataset(f"{tmp}/synth", num=args.videos, seed=0, config=cfg)
        print(f"generated {args.videos} videos in {time.perf_counter() - t:.1f} s")
        videos = [v for v in GeneratedVideos(path, "train", use_flow=True)]
        import datasets

        truth = datasets.load_from_disk(str(path))["train"]["scene_yaml"]

    prompt = lm.PromptSpec(num_frames=4, min_pixels=3136, max_pixels=12544)
    module = ProModule(lm.ModelSpec(kind="tiny"), prompt=prompt, num_samples=args.samples, max_new_tokens=2048)
    module.ensure_processor()
    proc = module.processor
    texts = []
    for y in truth:
        scene = parse(y)
        texts.append(
            [f"<answer>\n{y}</answer>"]
            + [f"<answer>\n{dump(perturbed(scene, rng))}</answer>" for _ in range(args.samples - 1)]
        )
    ids = [[response_ids(proc, t) for t in row] for row in texts]
    n_tokens = int(np.mean([len(i) for row in ids for i in row]))
    n_cands = args.videos * args.samples
    prompts = module.prompts([v.frames for v in videos])
    print(
        f"{args.videos} videos x N = {args.samples} candidates = {n_cands}; a scene is ~{n_tokens} tokens; "
        f"{len(prompts[0]['input_ids'])} prompt tokens; {torch.get_num_threads()} torch threads, "
        f"{os.cpu_count()} cores"
    )

    def sample():
        torch.manual_seed(0)
        return rw.sample_completions(
            module.model,
            proc,
            prompts,
            num_samples=args.samples,
            temperature=1.0,
            max_new_tokens=n_tokens,
            min_new_tokens=n_tokens,
        )

    sample()  # warm-up (first-call allocations), untimed, as scoring and the forward pass are
    t_sample, (s_ids, _) = best_and_result(sample, args.repeats)
    got = int(np.mean([len(i) for row in s_ids for i in row]))

    observations = [v.observation for v in videos]
    t_score, scores = best_and_result(lambda: rw.score_completions(texts, observations), args.repeats)
    t_score2, _ = best_and_result(lambda: rw.score_completions(texts, observations, workers=2), args.repeats)
    valid = sum(s.valid for row in scores for s in row)
    rewards = rw.rewards_of(scores)

    def fwd_bwd():
        module.model.zero_grad()
        loss, _ = module.preference_loss(prompts, ids, rewards)
        loss.backward()
        return loss

    fwd_bwd()  # warm-up
    t_fb, _ = best_and_result(fwd_bwd, args.repeats)
    total = t_sample + t_score + t_fb
    print(f"\nOne PRO step ({n_cands} candidates), tiny model, CPU:")
    print(f"  sampling          {t_sample:8.2f} s   ({n_cands * got / t_sample:7.0f} tokens/s, {got} tokens each)")
    print(f"  scoring           {t_score:8.2f} s   ({n_cands / t_score:7.1f} candidates/s, {valid}/{n_cands} valid)")
    print(f"  scoring, 2 videos at once {t_score2:.2f} s ({n_cands / t_score2:.1f} candidates/s)")
    print(f"  forward+backward  {t_fb:8.2f} s")
    print(f"  total             {total:8.2f} s   scoring share {t_score / total:.1%}")
    print(
        f"  scoring / sampling = {t_score / t_sample:.3f}  (target < 1: {'met' if t_score < t_sample else 'NOT met'})"
    )
    print(
        f"  best reward per video: {[round(float(r), 3) for r in rewards.max(1).values]}, "
        f"true scene ranked first in {sum(int(r.argmax()) == 0 for r in rewards)}/{args.videos}"
    )


if __name__ == "__main__":
    main()
