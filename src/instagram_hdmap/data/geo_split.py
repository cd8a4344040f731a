"""Geographically disjoint splits (``data.split_scheme: geo``): validation on streets never driven in training.

The official nuScenes and Argoverse 2 splits share locations between training and validation (the same
streets, other drives). StreamMapNet (Yuan et al., WACV 2024) re-split both datasets so that no validation
scene overlaps a training one; later work (MapTracker and papers reporting on the "new split") uses its
lists. They are shipped here exactly as StreamMapNet publishes them, as package data, not re-derived:

    geo_splits/nuscenes_{train,val}.txt   tools/data_converter/nusc_split.py: TRAIN_SCENES (698), VAL_SCENES (148)
    geo_splits/av2_{train,val}.txt        tools/data_converter/av2_{train,val}_split.txt (749 and 149 log ids)
    geo_splits/*_left_out.txt             FAIL_SCENES (nuscenes_converter.py) and FAIL_LOGS
                                          (argoverse_converter.py): dropped by StreamMapNet's converters

from github.com/yuantianyuan01/StreamMapNet at commit b911651186bf05c34fcbcf39e9fea4ff86f19460 (unchanged
through 4c7aaf42116461ad8a8b0f5cdc486903a7f15bb8). A geo AV2 split draws its logs from any of the dataroot's
``train/``, ``val/`` and ``test/`` folders, as StreamMapNet's converter does.

A listed scene or log that the dataset on disk lacks (nuScenes downloaded in parts, an AV2 subset) is
named in the split's line, never dropped silently; a split none of whose scenes is there is refused.

Synthetic worlds (``instagram-hdmap synth``) drive four road networks, one per nuScenes location, and
their own train / val scenes share them. Their geo split holds out one network: every scene on
``SYNTHETIC_HELD_OUT`` is validation, every scene on the other three is training.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

from ..errors import UserError

SOURCE = "StreamMapNet's geo split (github.com/yuantianyuan01/StreamMapNet @ b911651)"
GEO_SPLITS = ("train", "val")
# the fourth of the synthetic worlds' maps (network.LOCATIONS), a network of its own
SYNTHETIC_HELD_OUT = "singapore-queenstown"
SYNTHETIC_FORMAT_PREFIX = "instagram-hdmap synthetic"


class GeoSplitError(UserError, ValueError):
    """A geo split that cannot be drawn from the dataset on disk."""


def check_split(split: str) -> None:
    if split not in GEO_SPLITS:
        raise GeoSplitError(f"data.split_scheme=geo has the splits {' and '.join(map(repr, GEO_SPLITS))}, not "
                            f"{split!r} (set data.train_split / data.val_split to them)")


def listed(dataset: str, split: str) -> list[str]:
    """StreamMapNet's scene names (nuScenes) or log ids (AV2) of ``split``, in its order."""
    check_split(split)
    return _read(f"{dataset}_{split}.txt")


def left_out(dataset: str) -> list[str]:
    """The scenes / logs StreamMapNet's converter drops from every split (its FAIL_SCENES / FAIL_LOGS)."""
    return _read(f"{dataset}_left_out.txt")


def _read(name: str) -> list[str]:
    text = resources.files(__package__).joinpath("geo_splits", name).read_text()
    return [line.strip() for line in text.splitlines() if line.strip()]


@dataclass
class GeoSplit:
    """The scenes (or logs) of one geo split that the dataroot holds, and what the list has that it lacks."""

    split: str
    names: list[str]  # in the dataroot's order
    listed: int  # how many the list names (after StreamMapNet's left-out ones)
    missing: list[str] = field(default_factory=list)  # listed, not in the dataroot
    left_out: list[str] = field(default_factory=list)  # listed, dropped as StreamMapNet's converter does
    source: str = SOURCE
    unit: str = "scene"

    def line(self, where: str, samples: int) -> str:
        """One line for the console: the split's counts, with every missing name."""
        text = (f"geo split '{self.split}' of {where} ({self.source}): {len(self.names)} of its {self.listed} "
                f"{self.unit}s, {samples} samples")
        if self.left_out:
            text += f"; {len(self.left_out)} left out as StreamMapNet's converter does ({', '.join(self.left_out)})"
        if self.missing:
            text += (f"; {len(self.missing)} listed {self.unit}(s) not in the dataroot (a dataset in parts?): "
                     + ", ".join(self.missing))
        return text


def from_list(dataset: str, split: str, present: list[str], where: str) -> GeoSplit:
    """The geo split ``split`` of a real dataset whose scenes (or logs) on disk are ``present``."""
    unit = "log" if dataset == "av2" else "scene"
    dropped = set(left_out(dataset))
    names = listed(dataset, split)
    kept = [n for n in names if n not in dropped]
    on_disk = set(present)
    chosen = set(kept) & on_disk
    if not chosen:
        raise GeoSplitError(f"geo split '{split}' ({SOURCE}, {len(kept)} {unit}s, e.g. {kept[:2]}): none of them is "
                            f"in {where}, which holds {len(present)} {unit}(s) (e.g. {present[:2]}); a geo split "
                            "needs the real dataset's names (set data.split_scheme=official for another dataset)")
    return GeoSplit(split, [n for n in present if n in chosen], len(kept),
                    missing=[n for n in kept if n not in on_disk], left_out=[n for n in names if n in dropped],
                    unit=unit)


def synthetic_manifest(dataroot: str | Path) -> dict | None:
    """The world.json of a synthetic world at ``dataroot``, or None for any other dataset."""
    path = Path(dataroot) / "world.json"
    try:
        manifest = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    ok = isinstance(manifest, dict) and str(manifest.get("format", "")).startswith(SYNTHETIC_FORMAT_PREFIX)
    return manifest if ok else None


def from_networks(split: str, network_of: dict[str, str], where: str) -> GeoSplit:
    """The geo split ``split`` of a synthetic world whose scenes (or logs) drive the networks ``network_of``
    (name -> location, in the dataroot's order): validation is ``SYNTHETIC_HELD_OUT``, training the others."""
    check_split(split)
    held_out = [n for n, loc in network_of.items() if loc == SYNTHETIC_HELD_OUT]
    others = [n for n, loc in network_of.items() if loc != SYNTHETIC_HELD_OUT]
    names = held_out if split == "val" else others
    if not held_out or not others:
        raise GeoSplitError(
            f"geo split of the synthetic world {where}: validation is the road network of {SYNTHETIC_HELD_OUT}, "
            f"training the other networks, but its {len(network_of)} scene(s) drive "
            f"only {', '.join(sorted(set(network_of.values()))) or 'no network'}; "
            "a world of at least 4 scenes drives all four (synth --scenes-train / --scenes-val)")
    return GeoSplit(split, names, len(names), source=f"road network{'' if split == 'val' else 's'} "
                    + (SYNTHETIC_HELD_OUT if split == "val" else
                       ", ".join(sorted({loc for loc in network_of.values() if loc != SYNTHETIC_HELD_OUT}))))
