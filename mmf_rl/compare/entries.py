"""What a comparison trains: entries (a name and its config overrides), the budget, presence subsets,
and the runs behind each entry's cells.

An entry's ``kind`` says how its cells are read: ``paper`` (the model every row is compared with),
``variant`` (an option of the paper model), ``zero-fill`` (a baseline trained once on every modality,
seeing an absent one through its own absence handling), ``retrained`` (a baseline trained anew for
each presence subset with only that subset present: the paper's protocol), ``fusion`` /
``learned fusion`` (the paper model with another fusion, under the standard / learned prior) and
``ablation``; ``trained for missing`` (a baseline trained with sensors removed: modality dropout,
``L_mis``, or both, and scored like a zero-fill one).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

TRAINED_FOR_MISSING_KIND = "trained for missing"
KINDS = (
    "paper",
    "variant",
    "zero-fill",
    "retrained",
    TRAINED_FOR_MISSING_KIND,
    "fusion",
    "learned fusion",
    "ablation",
)
BASELINE_KINDS = ("zero-fill", "retrained", TRAINED_FOR_MISSING_KIND)


@dataclass(frozen=True)
class Entry:
    """One row of a comparison: a label and the training overrides that make it.

    Args:
        label (str): the row's name.
        kind (str): one of ``KINDS`` (see the module docstring).
        overrides (tuple[str, ...]): ``mmf-rl train`` overrides (e.g. ``("model=mult",)``).
        base (Entry, optional): for ``retrained``, the zero-fill entry whose all-modality run gives its
            ``"all"`` cell; for ``learned fusion``, the entry it is compared with (the same prior with
            the paper's fusion); ``None`` for every other kind.

    Raises:
        ValueError: an unknown kind, or a base given to the wrong kind (or missing).
    """

    label: str
    kind: str
    overrides: tuple[str, ...]
    base: Entry | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"entry {self.label!r}: kind {self.kind!r} is not one of {KINDS}")
        if (self.base is not None) != (self.kind in ("retrained", "learned fusion")):
            raise ValueError(
                f"entry {self.label!r}: a base is given exactly for retrained and learned fusion"
            )


@dataclass(frozen=True)
class Budget:
    """What every run of a comparison trains with.

    Args:
        steps (int): training steps of each run.
        batch_size (int): its batch size.
        seeds (tuple[int, ...]): the training seeds, one run each.
        image_size (int, optional): square images of this size; ``None``: the data config's.
    """

    steps: int
    batch_size: int
    seeds: tuple[int, ...]
    image_size: int | None = None


@dataclass(frozen=True)
class Study:
    """One comparison: its entries on one data config, its budget, where its runs go. Picklable, so
    that worker processes (``jobs`` > 1) receive it whole.

    Args:
        out (Path): where its runs (and the window cache) go.
        budget (Budget): what every run trains with.
        entries (tuple[Entry, ...]): the rows.
        modalities (tuple[str, ...]): the data config's modalities, in the order the subsets are named.
        data_overrides (tuple[str, ...], optional): Hydra overrides choosing the data, after each
            entry's own.
        config_dirs (tuple[Path, ...], optional): the user's config directories (``--config-dir``).
        device (str, optional): where runs train. Defaults to ``"cpu"``.
        jobs (int, optional): runs trained at once, one process each. Defaults to ``1``.
        retrained_for (tuple[str, ...], optional): the subsets a retrained baseline is trained for;
            ``None``: every subset but ``"all"``.
    """

    out: Path
    budget: Budget
    entries: tuple[Entry, ...]
    modalities: tuple[str, ...]
    data_overrides: tuple[str, ...] = ()
    config_dirs: tuple[Path, ...] = ()
    device: str = "cpu"
    jobs: int = 1
    retrained_for: tuple[str, ...] | None = None


LEARNED = ("model.prior=learned",)
PAPER = Entry("paper", "paper", ("model=forecaster",))
PAPER_LEARNED = Entry("paper prior=learned", "variant", ("model=forecaster", *LEARNED))
LF_LSTM = Entry("LF-LSTM", "zero-fill", ("model=lf_lstm",))
MVAE = Entry("MVAE", "zero-fill", ("model=mvae",))
MULT = Entry("MulT", "zero-fill", ("model=mult",))
ZERO_FILL = (LF_LSTM, MVAE, MULT)
RETRAINED = tuple(Entry(f"{e.label} (retrained)", "retrained", e.overrides, base=e) for e in ZERO_FILL)
# Missing-sensor training, for any model: modality dropout drawn every batch, L_mis beside the model's
# own term (its supervised term first), or both.
DROPOUT = ("loss.modality_dropout=subsets",)
OWN_TERM = {"LF-LSTM": "nll", "MVAE": "elbo", "MulT": "nll"}


def missing_sensor_trainings(own_term: str) -> dict[str, tuple[str, ...]]:
    """The trainings for missing sensors of a model whose supervised term is ``own_term``, by the suffix
    of their entries' labels."""
    l_mis = (f"loss.terms=[{own_term},mis]",)
    return {"modality dropout": DROPOUT, "L_mis": l_mis, "modality dropout + L_mis": (*DROPOUT, *l_mis)}


TRAINED_FOR_MISSING = tuple(
    Entry(f"{e.label}, {training}", TRAINED_FOR_MISSING_KIND, (*e.overrides, *overrides))
    for e in ZERO_FILL
    for training, overrides in missing_sensor_trainings(OWN_TERM[e.label]).items()
)
FUSIONS = ("linear", "average", "sum", "cross_attention")
FUSION_ABLATIONS = tuple(
    Entry(f"paper fusion={fusion}", "fusion", ("model=forecaster", f"model.fusion={fusion}"))
    for fusion in FUSIONS
)
# Under the learned prior the fusion also gives p(z|X), the latent a test forecast decodes: these rows
# compare the fusions there too.
LEARNED_FUSION_ABLATIONS = tuple(
    Entry(
        f"paper prior=learned, fusion={fusion}",
        "learned fusion",
        ("model=forecaster", *LEARNED, f"model.fusion={fusion}"),
        base=PAPER_LEARNED,
    )
    for fusion in FUSIONS
)
# The forecaster the README recommends for accuracy with every sensor and robustness to a missing one
# (configs/experiment/robust_mult.yaml: chosen on the push benchmark's val split).
RECOMMENDED = Entry("recommended", TRAINED_FOR_MISSING_KIND, ("experiment=robust_mult",))
NO_MIS = Entry("paper w/o L_mis", "ablation", ("model=forecaster", "loss=no_mis"))
PAPER_DROPOUT = Entry("paper, modality dropout + L_mis", "variant", ("model=forecaster", *DROPOUT))
NO_MIS_DROPOUT = Entry("paper, modality dropout", "variant", ("model=forecaster", "loss=no_mis", *DROPOUT))
# The entries `mmf-rl compare` offers on any data: none names a modality.
CATALOGUE = (
    PAPER,
    PAPER_LEARNED,
    *ZERO_FILL,
    *RETRAINED,
    *TRAINED_FOR_MISSING,
    RECOMMENDED,
    *FUSION_ABLATIONS,
    *LEARNED_FUSION_ABLATIONS,
    NO_MIS,
    PAPER_DROPOUT,
    NO_MIS_DROPOUT,
)
DEFAULT_ENTRIES = ("paper", *(e.label for e in ZERO_FILL), RECOMMENDED.label)


def select_entries(
    catalogue: Sequence[Entry], labels: Sequence[str] | None, paper_required: bool = True
) -> list[Entry]:
    """The ``catalogue``'s entries named by ``labels`` (all for None), in catalogue order. The paper
    model must be among them when ``paper_required``: the summaries compare every entry with it."""
    known = [e.label for e in catalogue]
    if labels is not None:
        problems = [f"unknown {unknown}"] if (unknown := sorted(set(labels) - set(known))) else []
        if paper_required and "paper" not in labels:
            problems.append("'paper' missing (every comparison is against it)")
        if problems:
            raise ValueError(f"entries: {' and '.join(problems)}; the entries are {known}")
    return [e for e in catalogue if labels is None or e.label in labels]


def subsets(modalities: Sequence[str]) -> list[tuple[str, dict[str, bool]]]:
    """The named presence subsets of ``modalities`` (:func:`mmf_rl.datasets.presence_subsets`), as a list.

    Args:
        modalities (Sequence[str]): the data's modalities.

    Returns:
        ``[(label, {modality: kept}), ...]``, ``"all"`` first.
    """
    from mmf_rl.datasets import presence_subsets

    return list(presence_subsets(list(modalities)))


def slug(text: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in text).strip("_").lower()


def retrained_subsets(study: Study) -> list[tuple[str, dict[str, bool]]]:
    return [
        (name, subset)
        for name, subset in subsets(study.modalities)[1:]
        if study.retrained_for is None or name in study.retrained_for
    ]


Run = tuple[Entry, int, Path, tuple[str, ...], str]


def run_plan(entry: Entry, study: Study) -> list[Run]:
    """The runs behind one entry's cells.

    Args:
        entry (Entry): the entry.
        study (Study): its comparison.

    Returns:
        ``(entry trained, seed, run_dir, extra overrides, subset)`` per run; ``subset`` is the one a
        retrained run's cell comes from, ``""`` when every subset counts.

    Examples:
        >>> from pathlib import Path
        >>> from mmf_rl.compare import Budget, Entry, Study, run_plan
        >>> baseline = Entry("MulT", "zero-fill", ("model=mult",))
        >>> retrained = Entry("MulT (retrained)", "retrained", ("model=mult",), base=baseline)
        >>> study = Study(Path("runs/compare"), Budget(steps=500, batch_size=64, seeds=(0,)),
        ...               (baseline, retrained), modalities=("image", "force"))
        >>> [(trained.label, str(run_dir), extra, subset) for trained, _, run_dir, extra, subset
        ...  in run_plan(retrained, study)]  # doctest: +NORMALIZE_WHITESPACE
        [('MulT', 'runs/compare/mult/seed0', (), 'all'),
         ('MulT (retrained)', 'runs/compare/mult__retrained/without_image/seed0',
          ('+data.missing.image=1.0',), 'without_image'),
         ('MulT (retrained)', 'runs/compare/mult__retrained/without_force/seed0',
          ('+data.missing.force=1.0',), 'without_force')]
    """
    plan = []
    for seed in study.budget.seeds:
        if entry.kind != "retrained":
            plan.append((entry, seed, study.out / slug(entry.label) / f"seed{seed}", (), ""))
            continue
        base = entry.base
        plan.append((base, seed, study.out / slug(base.label) / f"seed{seed}", (), "all"))
        for name, subset in retrained_subsets(study):
            dropped = tuple(f"+data.missing.{m}=1.0" for m, kept in subset.items() if not kept)
            plan.append((entry, seed, study.out / slug(entry.label) / name / f"seed{seed}", dropped, name))
    return plan
