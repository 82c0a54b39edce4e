"""Fine-tuning: start a run from the weights of a trained model of the same kind (``init_from``)."""

from __future__ import annotations

from pathlib import Path

from torch import nn

from mmf_rl.checkpoint import CheckpointError
from mmf_rl.models.hub import check_state_dict
from mmf_rl.models.loading import load_trained_model, trained_location

# A learned sampler is trained on the forecaster it samples from, after it; fine-tuning changes that
# forecaster, so a source's sampler is never copied, and this run's own (if it has one) trains anew.
SAMPLER_PREFIX = "latent_sampler."


def init_weights_from(model: nn.Module, source_path) -> Path:
    """Fine-tuning: copy the weights of a trained model (``init_from``) into ``model``, built for this run.

    The source may be anything :func:`load_trained_model` reads. A different model type, a
    modality missing on either side or of another kind or shape, or a parameter of another shape
    is an error naming it (this run's value first, then the source's). The source's scale factors
    (``mmf-rl calibrate``) and learned sampler are not copied: a run with ``model.learned_samples=K``
    may start from a source without a sampler, and the reverse.

    Args:
        model (nn.Module): the model of this run, changed in place.
        source_path (str | Path): anything :func:`load_trained_model` reads.

    Returns:
        The source's location (a run's ``checkpoints/``, else the path given).

    Raises:
        CheckpointError: a different model type, differing modalities or a parameter of another shape
            (this run's value first, then the source's).
    """
    location = trained_location(Path(source_path))
    source, _, _ = load_trained_model(location)
    here, there = model.model_name, source.model_name
    if here != there:
        raise CheckpointError(
            f"init_from={source_path} holds a {there!r} model, but this run builds {here!r}; "
            f"train model={there} or start from a {here!r} run"
        )
    mine = {s.name: (s.kind, tuple(s.shape)) for s in model.config.modalities}
    theirs = {s.name: (s.kind, tuple(s.shape)) for s in source.config.modalities}
    problems = [
        f"modality {n!r}: this run has {mine.get(n, 'none')}, {source_path} has {theirs.get(n, 'none')}"
        for n in sorted(set(mine) | set(theirs))
        if mine.get(n) != theirs.get(n)
    ]
    if problems:
        raise CheckpointError(
            "init_from: the modalities differ (" + "; ".join(problems) + "); map the same "
            "modality names to features of the same kind and shape (images: data.image_size)"
        )
    differing = sorted(
        k
        for k, v in model.config.to_dict().items()
        if k != "modalities" and source.config.to_dict().get(k) != v
    )
    forecaster = {k: v for k, v in source.state_dict().items() if not k.startswith(SAMPLER_PREFIX)}
    try:
        check_state_dict(model, forecaster, f"init_from={source_path}", skip=SAMPLER_PREFIX)
    except CheckpointError as error:
        hint = ", ".join(
            f"model.{k}: this run {getattr(model.config, k)!r}, source {getattr(source.config, k)!r}"
            for k in differing
        )
        raise CheckpointError(f"{error}{'; the configs differ in ' + hint if hint else ''}") from None
    model.load_state_dict(forecaster, strict=False)
    # The source's scale factors were fitted for its weights, not for the ones fine-tuning makes.
    model.scale_calibration.reset()
    return location
