"""Which forecast locates the pushed object through a camera outage: the latched one or a fresh one?

    .venv/bin/python benchmarks/latched_forecast_outage.py --checkpoint runs/push [--die-at 10 20 30]

Replays the held-out (test) episodes of the checkpoint's own dataset through
`LatchedForecastTransform`, all episodes at once as a batch of envs, fed what the env emits
(camera frames from the window cache, raw force and proprioception). The camera dies at step
``d`` for the rest of the episode (each ``--die-at``); from then on, at every step with a full
future in the episode, the forecast is scored against the truth in the target's own frame (ADE
and FDE in the target's units, metres for the push data; the NLL under the run's output
distribution, ``model.output_distribution``) for each rule
(`RULES`), and for the fresh forecast with per-step presence (the partial window). ``camera on``
scores the same steps with the camera never lost: the ceiling. Errors are also split by the
latch's age.
"""

from __future__ import annotations

import argparse

import torch
from tensordict import TensorDict

from mmf_rl import keys
from mmf_rl.datasets.config import DataConfig
from mmf_rl.datasets.windows import WindowDataset
from mmf_rl.log import configure_logging
from mmf_rl.models.loading import load_trained_model
from mmf_rl.objectives import output_distribution_of
from mmf_rl.rl.latched_forecast import RULES, LatchedForecastTransform

AGE_BUCKETS = ((1, 5), (6, 10), (11, 1000))


def episode_frames(
    dataset: WindowDataset, episodes: list[int]
) -> tuple[TensorDict, torch.Tensor, torch.Tensor | None]:
    """The episodes' frames as env steps ``[L, n]`` (cut to the shortest), the target ``[L, n, D]`` and
    the target's anchor reference ``[L, n, D]`` (None for an absolute or self-relative target)."""
    frames = TensorDict.load_memmap(dataset.cache_path / "frames")
    rows = [(dataset.frame_episode == e).nonzero().flatten() for e in episodes]
    length = min(len(r) for r in rows)
    index = torch.stack([r[:length] for r in rows], 1)  # [L, n]
    steps = TensorDict(batch_size=index.shape)
    for spec in dataset.specs:
        steps.set(spec.obs_key, frames.get(spec.obs_key).as_subclass(torch.Tensor)[index])
        steps.set(spec.present_key, frames.get(spec.present_key).as_subclass(torch.Tensor)[index])
    target = frames.get("target").as_subclass(torch.Tensor)[index]
    reference = None
    if dataset.config.target.relative_to is not None:
        reference = frames.get("target_reference").as_subclass(torch.Tensor)[index]
    return steps, target, reference


def truth(dataset: WindowDataset, target: torch.Tensor, reference, t: int) -> torch.Tensor:
    """The future ``[n, T, D]`` from step ``t`` in the model's target frame (target units)."""
    stride, horizon = dataset.config.stride, dataset.config.horizon
    future = target[t + stride : t + stride * horizon + 1 : stride].transpose(0, 1)
    if reference is not None:
        return future - reference[t][:, None]
    if dataset.config.target.relative:
        return future - target[t][:, None]
    return future


def replay(transform, steps: TensorDict, die_at: int | None) -> list[TensorDict]:
    camera = [s.present_key for s in transform.specs if s.kind == "image"]
    outputs = []
    for t in range(steps.shape[0]):
        step = steps[t].clone()
        if die_at is not None and t >= die_at:
            for key in camera:
                step.set(key, torch.zeros_like(step.get(key)))
        outputs.append(transform.observe_reset(step) if t == 0 else transform.observe_step(step))
    return outputs


def score(dataset, outputs, target, reference, die_at, family) -> dict[str, float]:
    """ADE, FDE and the NLL per step and dim (of the truth under the forecast's ``loc``, ``scale``, read
    by the run's output ``family``) over the outage steps with a full future, and ADE per age bucket (of
    the latch)."""
    span = dataset.config.stride * dataset.config.horizon
    ade, fde, nll, ages = [], [], [], []
    for t in range(die_at, target.shape[0] - span):
        loc, scale = outputs[t].get(keys.FORECAST_LOC), outputs[t].get(keys.FORECAST_SCALE)
        future = truth(dataset, target, reference, t)
        error = (loc - future).norm(dim=-1)
        ade.append(error.mean(1))
        fde.append(error[:, -1])
        nll.append(family.nll(future, loc, scale).mean((1, 2)))
        ages.append(torch.full_like(error[:, 0], t - die_at + 1))
    ade, fde, nll, ages = torch.cat(ade), torch.cat(fde), torch.cat(nll), torch.cat(ages)
    result = {"ade": ade.mean().item(), "fde": fde.mean().item(), "nll": nll.mean().item()}
    for low, high in AGE_BUCKETS:
        chosen = (ages >= low) & (ages <= high)
        if chosen.any():
            result[f"ade age {low}-{min(high, int(ages.max()))}"] = ade[chosen].mean().item()
    return result


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--checkpoint", required=True, help="a run directory or its checkpoints/")
    parser.add_argument(
        "--die-at", type=int, nargs="+", default=[10, 20, 30], help="camera lost from this step"
    )
    parser.add_argument("--split", default="test")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    model, stats, data_config = load_trained_model(args.checkpoint)
    family = output_distribution_of(model)
    dataset = WindowDataset(DataConfig.from_dict(data_config))
    episodes = dataset.split_episodes[args.split]
    steps, target, reference = episode_frames(dataset, episodes)
    variants = {rule: {"rule": rule} for rule in RULES}
    variants["fresh, per-step presence"] = {"rule": "fresh", "per_step_presence": True}
    rows: dict[str, list[dict[str, float]]] = {}
    ceiling = replay(LatchedForecastTransform.from_checkpoint(args.checkpoint), steps, None)
    for die_at in args.die_at:
        rows.setdefault("camera on", []).append(score(dataset, ceiling, target, reference, die_at, family))
        for name, options in variants.items():
            outputs = replay(
                LatchedForecastTransform.from_checkpoint(args.checkpoint, **options), steps, die_at
            )
            rows.setdefault(name, []).append(score(dataset, outputs, target, reference, die_at, family))
    frame = data_config["target"]
    print(
        f"{args.checkpoint}: target {frame['feature']} {frame['dims']} (relative={frame.get('relative')}, "
        f"relative_to={frame.get('relative_to')}); {len(episodes)} {args.split} episodes x {steps.shape[0]} "
        f"steps; camera lost from step {args.die_at}; errors in target units, mean over the outages"
    )
    for name, results in rows.items():
        columns = {k: sum(r[k] for r in results if k in r) / sum(k in r for r in results) for k in results[0]}
        print(f"{name:>26}: " + ", ".join(f"{k} {v:.4f}" for k, v in columns.items()))
    best = min((n for n in rows if n != "camera on"), key=lambda n: sum(r["ade"] for r in rows[n]))
    best_ade = sum(r["ade"] for r in rows[best]) / len(args.die_at)
    print(f"summary: camera outage ADE best {best!r} ({best_ade:.4f})")


if __name__ == "__main__":
    configure_logging()  # the library's progress messages, as `mmf-rl bench` shows them
    main()
