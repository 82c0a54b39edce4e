"""Trained models as Hugging Face hub models: ``save_pretrained`` / ``from_pretrained`` / ``push_to_hub``.

Every registered model mixes in :class:`PretrainedModel` (``huggingface_hub``'s
``PyTorchModelHubMixin``). A saved model is a directory (or a hub repository) of::

    config.json                 the model's registry name and full config (what ``saved_config`` gives)
    model.safetensors           the weights
    normalization.safetensors   the training split's normalisation statistics (``Normalizer.stats``)
    data_config.json            the data config it was trained with (features, window, stride)
    calibration.json            how its per-presence-pattern scale factors were fitted, if they were
    README.md                   the hub's model card

so a model loaded anywhere forecasts in the units it was trained in (``ForecastTransform`` and
``load_trained_model`` read these). The statistics and data config travel as the attributes
``normalization_stats`` and ``data_config`` of the model (``None`` until a run or a load sets them);
the fit of the scale factors (``mmf-rl calibrate``; the factors themselves are weights) as
``calibration``.

    model, stats, data = load_trained_model("runs/g1")      # a run, its checkpoints/ or one checkpoint
    model.save_pretrained("exports/g1")                      # stats and data config included
    model.push_to_hub("me/g1-forecaster")                    # online users
    model = from_pretrained("exports/g1")                    # loading's: "me/g1-forecaster" too; any model
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

from huggingface_hub import PyTorchModelHubMixin, hf_hub_download
from huggingface_hub.constants import CONFIG_NAME, SAFETENSORS_SINGLE_FILE

from mmf_rl.checkpoint import CheckpointError, known_mismatch, state_mismatch, state_with_defaults
from mmf_rl.models.registry import config_from_saved

NORMALIZATION_FILE = "normalization.safetensors"
DATA_CONFIG_FILE = "data_config.json"
CALIBRATION_FILE = "calibration.json"


def pretrained_file(model_id: str, filename: str, required: bool = True, **hub_kwargs) -> Path | None:
    """``filename`` of a saved model: from the local directory ``model_id``, else from the hub."""
    from huggingface_hub.errors import EntryNotFoundError

    if os.path.isdir(model_id):
        path = Path(model_id) / filename
        if path.is_file():
            return path
        if required:
            raise FileNotFoundError(
                f"{model_id} is not a saved mmf-rl model: {path} does not exist (a saved model "
                f"holds {CONFIG_NAME} and {SAFETENSORS_SINGLE_FILE}, written by save_pretrained)"
            )
        return None
    try:
        return Path(hf_hub_download(repo_id=model_id, filename=filename, **hub_kwargs))
    except EntryNotFoundError:
        if required:
            raise
        return None


class PretrainedModel(PyTorchModelHubMixin, library_name="mmf-rl", tags=["mmf-rl", "forecasting", "lerobot"]):
    """``save_pretrained`` / ``from_pretrained`` / ``push_to_hub`` for a registered model.

    The mixin's own loading is not strict (a missing weight would stay random): here every
    weight must match, and a mismatch names the parameter with both shapes. Mixed into every
    registered model; not built on its own. :func:`mmf_rl.models.from_pretrained` loads any registered
    model without knowing its class.
    """

    normalization_stats: dict | None = None
    data_config: dict | None = None
    calibration: dict | None = None  # how the scale factors were fitted (mmf_rl.eval.scale_fit)

    def _save_pretrained(self, save_directory: Path) -> None:
        from safetensors.torch import save_file

        super()._save_pretrained(save_directory)
        saved = {"name": self.model_name, **self.config.to_dict()}  # what registry.saved_config gives
        (save_directory / CONFIG_NAME).write_text(json.dumps(saved, indent=2))
        if self.normalization_stats is not None:
            save_file(
                {k: v.detach().contiguous().cpu() for k, v in self.normalization_stats.items()},
                save_directory / NORMALIZATION_FILE,
            )
        if self.data_config is not None:
            (save_directory / DATA_CONFIG_FILE).write_text(json.dumps(self.data_config, indent=2))
        if self.calibration is not None:
            (save_directory / CALIBRATION_FILE).write_text(json.dumps(self.calibration, indent=2))

    def save_pretrained(
        self,
        save_directory,
        *,
        config=None,
        repo_id=None,
        push_to_hub: bool = False,
        model_card_kwargs=None,
        **push_to_hub_kwargs,
    ):
        """The mixin's ``save_pretrained``, written atomically: every file goes to a temporary
        sibling directory first and is renamed into ``save_directory`` (``config.json`` last).

        Args:
            save_directory (str | Path): the directory (created if needed).

        Keyword Args:
            config (dict, optional): the mixin's; unused here: ``config.json`` always holds the model's
                own config.
            repo_id (str, optional): the hub repository when pushing; ``None``: the directory's name.
            push_to_hub (bool, optional): also push the files to the hub. Defaults to ``False``.
            model_card_kwargs (dict, optional): passed to the model card.
            **push_to_hub_kwargs: passed to ``push_to_hub``.

        Returns:
            The hub commit's URL when pushing, else ``None``.
        """
        final = Path(save_directory)
        final.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".tmp", dir=final.parent))
        try:
            super().save_pretrained(staging, config=config, model_card_kwargs=model_card_kwargs)
            files = sorted(staging.iterdir(), key=lambda p: p.name == CONFIG_NAME)
            for path in files:
                os.replace(path, final / path.name)
            if self.calibration is None:  # a fit described there is not the one of these weights
                (final / CALIBRATION_FILE).unlink(missing_ok=True)
        finally:
            shutil.rmtree(staging, ignore_errors=True)
        if push_to_hub:
            return self.push_to_hub(
                repo_id=repo_id or final.name, model_card_kwargs=model_card_kwargs, **push_to_hub_kwargs
            )
        return None

    @classmethod
    def _from_pretrained(
        cls,
        *,
        model_id: str,
        revision,
        cache_dir,
        force_download: bool,
        proxies,
        resume_download,
        local_files_only: bool,
        token,
        config: dict | None = None,
        map_location: str = "cpu",
        strict: bool = True,
        **model_kwargs,
    ):
        from safetensors.torch import load_file

        hub = dict(
            revision=revision,
            cache_dir=cache_dir,
            force_download=force_download,
            proxies=proxies,
            local_files_only=local_files_only,
            token=token,
        )
        if not config:
            raise FileNotFoundError(
                f"{model_id} has no readable {CONFIG_NAME}; it was not written by save_pretrained"
            )
        fields = dict(config)
        name = fields.pop("name", "forecaster")
        if name != cls.model_name:
            raise TypeError(
                f"{model_id} holds a {name!r} model (its config.json), not a {cls.__name__} "
                f"({cls.model_name!r}); "
                "load it with mmf_rl.models.from_pretrained"
            )
        model = cls(config_from_saved(cls.config_class, fields))
        # A model saved before some state existed (e.g. the scale factors) loads with the value that
        # reproduces its behaviour then.
        weights = state_with_defaults(
            model, load_file(pretrained_file(model_id, SAFETENSORS_SINGLE_FILE, **hub))
        )
        if strict:
            check_state_dict(model, weights, f"{model_id}/{SAFETENSORS_SINGLE_FILE}")
        model.load_state_dict(weights, strict=strict)
        stats = pretrained_file(model_id, NORMALIZATION_FILE, required=False, **hub)
        model.normalization_stats = load_file(stats) if stats is not None else None
        data = pretrained_file(model_id, DATA_CONFIG_FILE, required=False, **hub)
        model.data_config = json.loads(data.read_text()) if data is not None else None
        fit = pretrained_file(model_id, CALIBRATION_FILE, required=False, **hub)
        model.calibration = json.loads(fit.read_text()) if fit is not None else None
        return model.to(map_location).eval()


def read_pretrained_config(model_id: str, **kwargs) -> dict:
    """The ``config.json`` of a saved model (a local directory or a hub repository id)."""
    hub = {
        k: kwargs[k]
        for k in ("revision", "cache_dir", "force_download", "token", "local_files_only")
        if k in kwargs
    }
    return json.loads(pretrained_file(model_id, CONFIG_NAME, **hub).read_text())


def check_state_dict(model, state: dict, where: str, skip: str | None = None) -> None:
    """Raise unless ``state`` (completed by :func:`~mmf_rl.checkpoint.state_with_defaults`) fits
    ``model`` exactly, entries whose names start with ``skip`` left out on both sides; the error names
    each parameter with both shapes."""

    def kept(entries: dict) -> dict:
        return {k: v for k, v in entries.items() if skip is None or not k.startswith(skip)}

    mismatch = state_mismatch(kept(model.state_dict()), kept(state_with_defaults(model, state)))
    if mismatch:
        known = known_mismatch(model, state)
        raise CheckpointError(
            f"{where} does not fit this model ({mismatch})" + (f": {known}" if known else "")
        )
