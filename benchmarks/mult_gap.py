"""Where MulT's all-sensor advantage on push comes from: hybrids of MulT and the paper model.

    .venv/bin/python benchmarks/mult_gap.py --jobs 2   # every row, 3 seeds, two runs at once
    .venv/bin/python benchmarks/mult_gap.py --entries paper MulT --seeds 0
    .venv/bin/python benchmarks/mult_gap.py --tiny     # smoke run of the code paths (numbers mean nothing)

With every sensor, MulT forecasts push better than the paper model. The two differ in their tokens
(MulT: one per step; the paper: one per modality's window), in how modalities meet (MulT: one
cross-modal Transformer per ordered pair; the paper: self-attention over all tokens) and in the
readout (MulT: the pairs' last-step readouts concatenated into the head; the paper: a joint MLP with
the latent, then two fixed-query attentions). Each hybrid below swaps one of these, so the table
attributes the gap. Every row is trained and scored by ``mmf_rl.compare`` (as ``benchmarks/
accuracy.py``) with one budget: 1000 steps of batch 32 at 32x32 on the push recording, seeds 0 1 2,
every presence subset of the same test episodes.

The hybrids are models registered under ``gap_*`` names when this script is imported (so the worker
processes of ``--jobs``, which import it again, build them too). Their checkpoints load only where
this script has registered them: in ``mmf-rl eval`` or ``load_trained_model`` they are unknown models.

The recording is made if ``--data`` does not exist, by ``mmf_rl.compare.script`` as for
``benchmarks/accuracy.py`` (same default path, episodes and seed, so the two share it). Completed runs
in ``--out`` are reused: an interrupted run resumes. Writes ``<out>/results.md`` (MSE per row and
presence subset, mean over seeds; all-sensor 95% paired bootstrap intervals against MulT; each row's
all-sensor MSE on training windows beside test, which tells a row that fits worse from one that
generalises worse) and
``<out>/results.json``, and ends with one line: ``summary: MulT all A; MulT on the paper's tokens B
(fixed-query readout C); paper D``
(all-sensor MSE means; ``-`` for a row not run).
"""

from __future__ import annotations

import argparse
import os
import statistics
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from mmf_rl.compare import entries as catalogue
from mmf_rl.compare import report, script
from mmf_rl.compare.bootstrap import Table, build_table, difference_interval
from mmf_rl.compare.entries import Entry, Study, subsets
from mmf_rl.models.attention import FixedQueryAttention
from mmf_rl.models.baselines.common import gaussian_head_output, zero_filled
from mmf_rl.models.baselines.mult import CrossModalLayer, CrossModalTransformer, MulT, MulTConfig
from mmf_rl.models.encoders import StepTokens, build_encoder, mlp
from mmf_rl.models.forecaster.configuration_forecaster import ForecasterConfig
from mmf_rl.models.forecaster.modeling_forecaster import ModalitySpecificDecoder, MultimodalForecaster
from mmf_rl.models.fusion import FusionShape
from mmf_rl.models.registry import register_model

# --- hybrids of MulT ---------------------------------------------------------------------------------


class StagedMulT(MulT):
    """MulT with its forecast in three stages a hybrid can replace one at a time: the modalities'
    token sequences, the pairs' last-step readouts, and the head's input made of them."""

    def modality_tokens(self, td) -> dict[str, torch.Tensor]:
        """``{m: [N, L_m, d]}``: each tokenizer's tokens (a window encoder's one token is the last step)
        plus MulT's step embedding, unless the tokenizer adds its own (the paper's ``StepTokens``)."""
        tokens = {}
        for spec in self.modalities:
            tokenizer = self.tokenizers[spec.name]
            seq = tokenizer(zero_filled(td, spec))
            seq = seq.unsqueeze(1) if seq.dim() == 2 else seq
            own_embedding = isinstance(tokenizer, StepTokens)
            tokens[spec.name] = seq if own_embedding else seq + self.step_embedding[-seq.shape[1] :]
        return tokens

    def pair_readouts(self, tokens: dict[str, torch.Tensor]) -> list[torch.Tensor]:
        """The last token ``[N, d]`` of each ordered pair's cross-modal stream ``i <- j``."""
        return [self.streams[f"{i}<-{j}"](tokens[i], tokens[j])[:, -1] for i, j in self.pairs]

    def head_input(self, readouts: list[torch.Tensor]) -> torch.Tensor:
        return torch.cat(readouts, dim=-1)

    def forecast(self, td):
        cfg = self.config
        raw = self.head(self.head_input(self.pair_readouts(self.modality_tokens(td))))
        return gaussian_head_output(raw, cfg.horizon, cfg.target_dim, cfg.min_scale)


@register_model("gap_mult_fq", MulTConfig, loss=("nll",))
class MulTFixedQueryReadout(StagedMulT):
    """Swaps MulT's readout: the pairs' last-step readouts are aggregated by the paper decoder's two
    fixed-query attentions (``M`` learned queries; the second refines the first) and the ``M`` rows
    flattened into the head, instead of concatenated. Tokens and pair streams stay MulT's."""

    def __init__(self, config: MulTConfig):
        super().__init__(config)
        d, m = config.d_model, len(self.modalities)
        self.queries = nn.Parameter(torch.randn(m, d) * 0.02)
        self.aggregate = FixedQueryAttention(d, config.num_heads)
        self.refine = FixedQueryAttention(d, config.num_heads)
        self.head = mlp(m * d, config.head_hidden, 2 * config.horizon * config.target_dim)

    def head_input(self, readouts: list[torch.Tensor]) -> torch.Tensor:
        h0 = torch.stack(readouts, dim=1)
        # Zero-fill: an absent modality is a zero signal, so no readout is masked out.
        none_absent = torch.zeros(h0.shape[:2], dtype=torch.bool, device=h0.device)
        queries = self.queries.expand(h0.shape[0], -1, -1)
        h1 = self.aggregate(queries, h0, none_absent, residual=queries)
        return self.refine(h1, h0, none_absent, residual=h1).flatten(1)


@register_model("gap_mult_tok1", MulTConfig, loss=("nll",))
class MulTOnPaperTokens(StagedMulT):
    """Swaps MulT's tokens: the paper's unimodal encoders (``build_encoder``, one token per modality's
    window) feed MulT's pair streams, whose readouts are concatenated into MulT's head."""

    def __init__(self, config: MulTConfig):
        super().__init__(config)
        d = config.d_model
        self.tokenizers = nn.ModuleDict(
            {s.name: build_encoder(s, config.history, d) for s in self.modalities}
        )
        del self.step_embedding  # one token per modality: no steps to tell apart

    def modality_tokens(self, td) -> dict[str, torch.Tensor]:
        return {s.name: self.tokenizers[s.name](zero_filled(td, s)).unsqueeze(1) for s in self.modalities}


@register_model("gap_mult_tok1_fq", MulTConfig, loss=("nll",))
class MulTOnPaperTokensFixedQueryReadout(MulTOnPaperTokens, MulTFixedQueryReadout):
    """Both swaps: the paper's one-token encoders feed MulT's pair streams, whose readouts the
    paper decoder's two fixed-query attentions aggregate."""


@register_model("gap_mult_shared", MulTConfig, loss=("nll",))
class MulTSharedPairLayer(MulTOnPaperTokens):
    """:class:`MulTOnPaperTokens` with one cross-modal layer shared by every pair (a learned pair
    embedding added to its query says which pair it serves) instead of one Transformer per pair."""

    def __init__(self, config: MulTConfig):
        super().__init__(config)
        d = config.d_model
        self.shared = CrossModalLayer(d, config.num_heads, config.mlp_hidden)
        self.pair_embedding = nn.Parameter(torch.randn(len(self.pairs), d) * 0.02)
        del self.streams

    def pair_readouts(self, tokens: dict[str, torch.Tensor]) -> list[torch.Tensor]:
        return [
            self.shared(tokens[i] + self.pair_embedding[k], tokens[j])[:, -1]
            for k, (i, j) in enumerate(self.pairs)
        ]


@register_model("gap_mult_stackimg", MulTConfig, loss=("nll",))
class MulTStackedImageToken(StagedMulT):
    """Swaps MulT's image tokens only: the camera window becomes one token of the paper's
    frame-stacked ConvNet (with the last step's embedding); the vectors keep MulT's per-step tokens,
    pair streams and concatenated head."""

    def __init__(self, config: MulTConfig):
        super().__init__(config)
        for spec in self.modalities:
            if spec.kind == "image":
                self.tokenizers[spec.name] = build_encoder(spec, config.history, config.d_model)


@register_model("gap_mult_self", MulTConfig, loss=("nll",))
class MulTWithSelfPairs(StagedMulT):
    """Swaps MulT's pair set for the paper pair-stream decoder's: all ``M × M`` ordered pairs, the
    self pairs ``i <- i`` included, each with its own cross-modal Transformer; the ``M²`` readouts
    are concatenated into a head as much wider. Tokens and readout stay MulT's."""

    def __init__(self, config: MulTConfig):
        super().__init__(config)
        names = [s.name for s in self.modalities]
        d = config.d_model
        self.pairs = [(i, j) for i in names for j in names]
        self.streams = nn.ModuleDict(
            {
                f"{i}<-{j}": CrossModalTransformer(d, config.num_heads, config.mlp_hidden, config.num_layers)
                for i, j in self.pairs
            }
        )
        self.head = mlp(len(self.pairs) * d, config.head_hidden, 2 * config.horizon * config.target_dim)


@register_model("gap_mult_steptok", MulTConfig, loss=("nll",))
class MulTOnPaperStepTokens(StagedMulT):
    """Swaps MulT's vector tokenizer (a linear layer + ReLU per step, one step embedding shared by the
    modalities) for the paper's ``steps`` encoder (a two-layer MLP per step, a step embedding per
    modality). The image keeps MulT's per-frame tokens; pair streams and head stay MulT's."""

    def __init__(self, config: MulTConfig):
        super().__init__(config)
        for spec in self.modalities:
            if spec.kind == "sequence":
                self.tokenizers[spec.name] = StepTokens(spec, config.history, config.d_model)


# --- hybrids of the paper model ----------------------------------------------------------------------


class TokenFeatures(nn.Module):
    """In place of the decoder's joint MLP: a token's own ``d`` features (with ``P^D``), ``z`` dropped."""

    def __init__(self, d_model: int):
        super().__init__()
        self.d_model = d_model

    def forward(self, joint: torch.Tensor) -> torch.Tensor:
        return joint[..., : self.d_model]


class PerModalityJoint(nn.Module):
    """The decoder's joint MLP with one set of weights per modality, applied to its tokens."""

    def __init__(self, token_counts: list[int], in_dim: int, hidden: int, out_dim: int):
        super().__init__()
        self.token_counts = token_counts
        self.mlps = nn.ModuleList(mlp(in_dim, hidden, out_dim) for _ in token_counts)

    def forward(self, joint: torch.Tensor) -> torch.Tensor:
        # Tokens come in modality order (MultimodalForecaster.encode).
        columns = joint.split(self.token_counts, dim=1)
        return torch.cat([f(x) for f, x in zip(self.mlps, columns, strict=True)], dim=1)


class ResidualJoint(nn.Module):
    """The decoder's joint MLP as a residual branch: a token's ``d`` features plus the MLP's output."""

    def __init__(self, joint: nn.Module, d_model: int):
        super().__init__()
        self.joint, self.d_model = joint, d_model

    def forward(self, joint: torch.Tensor) -> torch.Tensor:
        return joint[..., : self.d_model] + self.joint(joint)


@register_model("gap_fc_nojoint", ForecasterConfig, loss=("elbo", "mis"))
class ForecasterWithoutJoint(MultimodalForecaster):
    """The paper model whose decoder has no joint MLP: the tokens plus ``P^D`` go straight into its
    fixed-query attentions and ``z`` is unused. Everything else stays."""

    def __init__(self, config: ForecasterConfig):
        super().__init__(config)
        self.decoder.joint = TokenFeatures(config.d_model)


@register_model("gap_fc_pm", ForecasterConfig, loss=("elbo", "mis"))
class ForecasterPerModalityJoint(MultimodalForecaster):
    """The paper model with one decoder joint MLP per modality instead of one shared by all; its
    tokens, attentions and head stay."""

    def __init__(self, config: ForecasterConfig):
        super().__init__(config)
        d = config.d_model
        self.decoder.joint = PerModalityJoint(self.token_counts, d + config.d_latent, config.mlp_hidden, d)


@register_model("gap_fc_res", ForecasterConfig, loss=("elbo", "mis"))
class ForecasterResidualJoint(MultimodalForecaster):
    """The paper model whose decoder joint MLP is a residual branch (a token keeps its own features);
    everything else stays."""

    def __init__(self, config: ForecasterConfig):
        super().__init__(config)
        self.decoder.joint = ResidualJoint(self.decoder.joint, config.d_model)


@register_model("gap_fc_pair", ForecasterConfig, loss=("elbo", "mis"))
class ForecasterPairTokens(MultimodalForecaster):
    """The paper model whose decoder reads MulT's pair structure: ``M × M`` tokens, token ``i <- j`` a
    cross-modal layer of its own from modality ``i``'s token to ``j``'s (``i <- i``: itself), absent
    when ``i`` or ``j`` is; ``P^D`` of ``i`` is added to it. The decoder's joint MLP, fixed-query
    attentions and head stay. Needs one token per modality and ``decoder_input="tokens"``."""

    def __init__(self, config: ForecasterConfig):
        super().__init__(config)
        if config.decoder_input != "tokens" or set(self.token_counts) != {1}:
            raise ValueError(
                "gap_fc_pair builds pair tokens from one raw token per modality: set "
                "model.decoder_input=tokens and one-token encoders (conv, mlp, gru)"
            )
        m, d = len(self.modalities), config.d_model
        self.pair_index = [(i, j) for i in range(m) for j in range(m)]
        self.pair_layers = nn.ModuleList(
            CrossModalLayer(d, config.num_heads, config.mlp_hidden) for _ in self.pair_index
        )
        self.register_buffer("pair_modality", torch.tensor([i for i, _ in self.pair_index]), persistent=False)

    def decoder_tokens(self, tokens: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        pairs = zip(self.pair_layers, self.pair_index, strict=True)
        return torch.stack(
            [layer(tokens[:, i : i + 1], tokens[:, j : j + 1])[:, 0] for layer, (i, j) in pairs], dim=1
        )

    def _decode_prepared(self, decoder_tokens, present, z, action=None):
        absent = torch.stack([~(present[:, i] & present[:, j]) for i, j in self.pair_index], dim=1)
        return self.decoder(decoder_tokens, absent, self.pair_modality, z, action)


class WideDecoder(ModalitySpecificDecoder):
    """The paper's decoder with ``queries_per_modality × M`` learned queries (the head reads all their
    rows) and, with ``post_mlp``, a residual pre-LN MLP after each of its two attentions."""

    def __init__(self, cfg: ForecasterConfig, shape: FusionShape, queries_per_modality: int, post_mlp: bool):
        super().__init__(cfg, shape)
        if self.fusion is not None:
            raise ValueError(f"a wide decoder widens the paper's attention; model.fusion={cfg.fusion!r}")
        m, d = len(cfg.modalities), cfg.d_model
        self.queries = nn.Parameter(torch.randn(queries_per_modality * m, d) * 0.02)
        self.head = mlp(queries_per_modality * m * d, cfg.head_hidden, 2 * cfg.horizon * cfg.target_dim)
        self.post = (
            nn.ModuleList(nn.Sequential(nn.LayerNorm(d), mlp(d, cfg.mlp_hidden, d)) for _ in range(2))
            if post_mlp
            else None
        )

    def forward(self, tokens, absent, token_modality, z, action=None):
        n = tokens.shape[0]
        h0 = self.joint_tokens(tokens, token_modality, z, action)
        queries = self.queries.expand(n, -1, -1)
        h1 = self.aggregate(queries, h0, absent, residual=queries)
        h1 = h1 if self.post is None else h1 + self.post[0](h1)
        h2 = self.refine(h1, h0, absent, residual=h1)
        h2 = h2 if self.post is None else h2 + self.post[1](h2)
        loc, raw_scale = self.head(h2.flatten(1)).view(n, 2, *self.out_shape).unbind(1)
        return loc, F.softplus(raw_scale) + self.min_scale


class ForecasterWideDecoder(MultimodalForecaster):
    """The paper model with a :class:`WideDecoder` of the class's ``queries_per_modality`` and
    ``post_mlp``; the encoders and the multimodal encoder stay."""

    queries_per_modality = 1
    post_mlp = False

    def __init__(self, config: ForecasterConfig):
        super().__init__(config)
        shape = FusionShape(
            num_modalities=len(self.modalities),
            num_tokens=sum(self.token_counts),
            d_model=config.d_model,
            num_heads=config.num_heads,
            mlp_hidden=config.mlp_hidden,
            num_layers=config.num_encoder_layers,
            role="decoder",
        )
        self.decoder = WideDecoder(config, shape, self.queries_per_modality, self.post_mlp)


@register_model("gap_fc_q4", ForecasterConfig, loss=("elbo", "mis"))
class ForecasterFourQueries(ForecasterWideDecoder):
    """The paper model whose decoder aggregates with 4 learned queries per modality instead of ``P^D``'s
    one (the head reads ``4 M`` rows); everything before the decoder's attentions stays."""

    queries_per_modality = 4


@register_model("gap_fc_post", ForecasterConfig, loss=("elbo", "mis"))
class ForecasterPostAggregationMLP(ForecasterWideDecoder):
    """The paper model whose decoder has a residual MLP after each of its two attentions (its queries
    learned apart from ``P^D``); everything before the decoder's attentions stays."""

    post_mlp = True


# --- the benchmark -----------------------------------------------------------------------------------

REPO = Path(__file__).resolve().parents[1]
MODALITIES = ("force", "image", "proprio")
PAPER = ("model=forecaster",)
MULT = ("model=mult",)
MULT_TOKENS = "MulT on the paper's tokens"
MULT_TOKENS_FQ = "MulT on the paper's tokens, fixed-query readout"
ENTRIES = [
    catalogue.PAPER,
    catalogue.MULT,
    Entry("MulT, fixed-query readout", "zero-fill", (*MULT, "model.name=gap_mult_fq")),
    Entry(MULT_TOKENS, "zero-fill", (*MULT, "model.name=gap_mult_tok1")),
    Entry(MULT_TOKENS_FQ, "zero-fill", (*MULT, "model.name=gap_mult_tok1_fq")),
    Entry(
        "MulT on the paper's tokens, one layer shared by the pairs",
        "zero-fill",
        (*MULT, "model.name=gap_mult_shared"),
    ),
    Entry("MulT, frame-stacked image token", "zero-fill", (*MULT, "model.name=gap_mult_stackimg")),
    Entry("MulT, self pairs too", "zero-fill", (*MULT, "model.name=gap_mult_self")),
    Entry("MulT, the paper's per-step vector tokens", "zero-fill", (*MULT, "model.name=gap_mult_steptok")),
    Entry("paper, no decoder joint MLP", "variant", (*PAPER, "model.name=gap_fc_nojoint")),
    Entry("paper, one joint MLP per modality", "variant", (*PAPER, "model.name=gap_fc_pm")),
    Entry("paper, residual joint MLP", "variant", (*PAPER, "model.name=gap_fc_res")),
    Entry("paper, pair tokens", "variant", (*PAPER, "model.name=gap_fc_pair", "model.decoder_input=tokens")),
    Entry("paper, 4 queries per modality", "variant", (*PAPER, "model.name=gap_fc_q4")),
    Entry("paper, MLP after each aggregation", "variant", (*PAPER, "model.name=gap_fc_post")),
    Entry(
        "paper, deterministic",
        "ablation",
        (*PAPER, "loss=no_mis", "loss.kl_weight=0", "model.eval_latent=posterior"),
    ),
    catalogue.NO_MIS,
]
SUBSET_COLUMNS = {
    "all": "all",
    "without_force": "w/o force",
    "without_image": "w/o image",
    "without_proprio": "w/o proprio",
    "only_force": "force only",
    "only_image": "image only",
    "only_proprio": "proprio only",
}


# Every row, 3 seeds, 1000 steps of batch 32 at 32x32 on accuracy.py's recording of 200 episodes.
STANDARD = script.Mode(image_size=32, batch_size=32, steps=1000, seeds=(0, 1, 2), entries=None, episodes=200)
# Tiny: the code paths (a paper hybrid with pair tokens, a MulT hybrid with both swaps) in seconds;
# the numbers mean nothing.
TINY = script.Mode(
    image_size=32,
    batch_size=8,
    steps=4,
    seeds=(0,),
    entries=("paper", MULT_TOKENS_FQ, "paper, pair tokens"),
    episodes=16,
)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tiny", action="store_true", help="smoke run: 1 seed, 4 steps of batch 8, 3 rows")
    parser.add_argument(
        "--data",
        type=Path,
        default=None,
        help="recorded push dataset (default data/push_bench_<episodes>ep, as benchmarks/accuracy.py; "
        "recorded if absent)",
    )
    parser.add_argument(
        "--out", type=Path, default=None, help="runs and results (default runs/bench_mult_gap_<mode>)"
    )
    script.add_override_flags(parser, "seeds")
    parser.add_argument("--entries", nargs="+", default=None, help="the rows to run (labels; default all)")
    script.add_run_flags(parser)
    args = parser.parse_args(argv)
    script.check_run_flags(parser, args, ENTRIES, paper_required=False)
    args.mode = "tiny" if args.tiny else "standard"
    args.budget = (TINY if args.tiny else STANDARD).overridden(args)
    args.data = (args.data or script.push_recording_path(REPO, args.budget.episodes)).resolve()
    args.out = (args.out or REPO / "runs" / f"bench_mult_gap_{args.mode}").resolve()
    return args


def mse_table(table: Table, labels: list[str], seeds: int) -> str:
    """Rows x the presence subsets and their mean: test MSE, mean over seeds."""
    names = [s for s in SUBSET_COLUMNS if s in table.subsets]
    lines = [
        "| model | seeds | " + " | ".join(SUBSET_COLUMNS[s] for s in names) + " | mean of 7 |",
        "|---" * (len(names) + 3) + "|",
    ]
    for label in labels:
        cells = table.cells[label]
        means = [cells[s].mean for s in names if s in cells]
        mean = f"{statistics.fmean(means):.3f}" if len(means) == len(SUBSET_COLUMNS) else "-"
        row = " | ".join(f"{cells[s].mean:.3f}" if s in cells else "-" for s in names)
        lines.append(f"| {label} | {seeds} | {row} | {mean} |")
    return "\n".join(lines)


def against_mult(table: Table, labels: list[str]) -> str:
    """All-sensor MSE with its 95% interval, and the paired difference to MulT (negative: better)."""
    lines = ["| model | all sensors [95% interval] | minus MulT [95% interval] |", "|---|---|---|"]
    mult = table.cells.get(catalogue.MULT.label, {}).get("all")
    for label in labels:
        cell = table.cells[label].get("all")
        if cell is None:
            continue
        difference = "-"
        if mult is not None and label != catalogue.MULT.label:
            low, high = difference_interval(cell, mult)
            difference = f"{cell.mean - mult.mean:+.3f} [{low:+.3f}, {high:+.3f}]"
        lines.append(f"| {label} | {cell.mean:.3f} [{cell.low:.3f}, {cell.high:.3f}] | {difference} |")
    return "\n".join(lines)


def summary_line(table: Table) -> tuple[str, dict[str, float | None]]:
    """``summary: MulT all A; MulT on the paper's tokens B (fixed-query readout C); paper D``."""
    labels = {"mult": "MulT", "tokens": MULT_TOKENS, "tokens_fq": MULT_TOKENS_FQ, "paper": "paper"}
    means = {
        key: (table.cells[label]["all"].mean if "all" in table.cells.get(label, {}) else None)
        for key, label in labels.items()
    }
    text = {key: "-" if value is None else f"{value:.3f}" for key, value in means.items()}
    line = (
        f"summary: MulT all {text['mult']}; MulT on the paper's tokens {text['tokens']} "
        f"(fixed-query readout {text['tokens_fq']}); paper {text['paper']}"
    )
    return line, means


def markdown(study: Study, table: Table, info: dict, fit: dict) -> str:
    budget, labels = study.budget, [e.label for e in study.entries]
    return (
        "# The gap to MulT with every sensor: hybrids of MulT and the paper model\n\n"
        f"Push dataset {info['data']}, split by episode, test episodes: {info['test_episodes']}; images "
        f"{budget.image_size}x{budget.image_size}. Every model: {budget.steps} steps of batch "
        f"{budget.batch_size}, seeds {', '.join(map(str, budget.seeds))}. Wall time "
        f"{info['seconds'] / 60:.1f} min ({info['reused']} of {info['runs']} runs reused).\n\n"
        "## Test MSE (normalised target), mean over seeds\n\n"
        + mse_table(table, labels, len(budget.seeds))
        + "\n\n## With every sensor, against MulT\n\n"
        "95% percentile bootstrap over the test episodes, paired (the same resamples for every row).\n\n"
        + against_mult(table, labels)
        + "\n\n"
        + report.fit_section(fit)
    )


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    study = script.push_study(args, ENTRIES, MODALITIES, paper_required=False)
    script.check_study(study, "mult_gap benchmark")
    outcome = script.run_study(study, script.PushRecording(args.data, args.budget.episodes))
    collected = outcome.collected
    table, episodes = build_table(collected.errors, collected.kinds, [n for n, _ in subsets(MODALITIES)])
    info = {
        "data": str(args.data),
        "test_episodes": len(episodes),
        "seconds": outcome.seconds,
        "runs": outcome.runs,
        "reused": outcome.reused,
    }
    line, summary = summary_line(table)
    text = markdown(study, table, info, collected.fit) + f"{line}\n"
    results = {
        "mode": args.budget.__dict__,
        "info": info,
        "cells": report.cells_json(table),
        "summary": summary,
        "fit": collected.fit,
    }
    script.report_results(args.out, text, results)
    return 0


if __name__ == "__main__":
    script.run_as_script(main)
