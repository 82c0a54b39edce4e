"""How a dataset was made, as `mmf-rl record` writes it into the dataset: ``meta/mmf_rl_recording.json``.

A recording's episodes say nothing of the options that drew them (seed, steady or drawn pusher,
exploration, faults, camera, the policy that acted): without this file a steady recording and a
drawn-style one look alike. It lives with the datasets, below the recorder that writes it
(`mmf_rl.record.recording_provenance`), so that `mmf-rl inspect` and any script can read it back.
A merge writes ``{"merged": [<each source's provenance, or null>, ...]}``, in source order.
"""

from __future__ import annotations

import json
from pathlib import Path

PROVENANCE_FILE = Path("meta") / "mmf_rl_recording.json"


def read_recording_provenance(root: str | Path) -> dict | None:
    """The provenance `mmf-rl record` wrote into the dataset at ``root``; ``None`` when it wrote none
    (a dataset recorded by something else, or by an older mmf-rl)."""
    path = Path(root) / PROVENANCE_FILE
    try:
        text = path.read_text()
    except FileNotFoundError:
        return None
    fix = "restore the file or delete it (the dataset then reads as one of unknown provenance)"
    try:
        provenance = json.loads(text)
    except json.JSONDecodeError as error:
        raise ValueError(f"{path}: not valid JSON ({error}); {fix}") from None
    if not isinstance(provenance, dict):
        found = type(provenance).__name__
        raise ValueError(f"{path}: a JSON {found}, expected the object mmf-rl record writes; {fix}")
    return provenance


def describe_provenance(provenance: dict) -> str:
    """One line on how a dataset was made (`read_recording_provenance`'s dict), for reports."""
    if "merged" in provenance:
        sources = [
            f"({i}) " + (_describe_source(p) if p is not None else "unknown")
            for i, p in enumerate(provenance["merged"], 1)
        ]
        return f"merged by mmf-rl record from {len(sources)} recordings: {'; '.join(sources)}"
    return f"recorded by mmf-rl record: {_describe_source(provenance)}"


def _describe_source(p: dict) -> str:
    """One recording's provenance (a merge among a merge's sources: just how many it joined)."""
    if "merged" in p:
        return f"a merge of {len(p['merged'])} recordings"
    if p.get("policy") is not None:
        actor = f"policy {p['policy']}"
    else:
        actor = "steady scripted pusher" if p.get("steady") else "scripted pusher, a style drawn per episode"
    return (
        f"{p.get('episodes')} episodes of {p.get('steps')} steps, seed {p.get('seed')}, {actor}, "
        f"exploration {p.get('exploration')}, {'faults' if p.get('faults') else 'no faults'}, "
        f"{p.get('camera')} camera {p.get('image_size')} px ({p.get('vcodec')}), "
        f"mmf-rl {p.get('mmf_rl_version')}"
    )
