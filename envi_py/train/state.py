"""Periodic training state, so a killed training resumes to the same result.

What decides the rest of a training run is written after every validation: the model and optimiser
state, the data-order generator's state, the selector's best weights and curve, and the epoch, plus
whatever else the algorithm keeps (``extra``: GAIL's discriminator, critic, their optimisers, the
torch generators and its learning curve). It is written to a temporary file and renamed, so a
``kill -9`` at any moment leaves either the old state or the new one, never half a file. A
fingerprint of the training (algorithm, hyper-parameters, seed, data hashes) is stored with it:
resuming a different training from it is an error, not a silent mix.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..atomic import atomic_write
from ..model import Checkpoint, load_torch_file
from .common import Selector

STATE_FORMAT = "envi-training-state"


def identity(ckpt: Checkpoint) -> dict[str, Any]:
    """What must match for a state to continue this training (as JSON-able values)."""
    rec = ckpt.record
    blob = {
        "algorithm": rec.algorithm,
        "seed": rec.seed,
        "hyper": rec.hyper,
        "config": asdict(ckpt.config),
        "data": [d["sha256"] for d in rec.data],
        "validation": [d["sha256"] for d in rec.validation],
    }
    return json.loads(json.dumps(blob, sort_keys=True, default=str))


def fingerprint(ckpt: Checkpoint) -> str:
    return hashlib.sha256(json.dumps(identity(ckpt), sort_keys=True).encode()).hexdigest()


def differences(old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    """What differs between two trainings' identities, by name: a hyper-parameter or model setting
    (``epochs``, ``hidden``), ``seed``, ``training data`` or ``validation data``."""
    names = {"data": "training data", "validation": "validation data"}
    out: list[str] = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key), new.get(key)
        if a == b:
            continue
        if isinstance(a, dict) and isinstance(b, dict):
            out += [k for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]
        else:
            out.append(names.get(key, key))
    # a setting recorded both as a hyper-parameter and in the model's config (``hidden``) is one difference
    return list(dict.fromkeys(out))


class TrainingState:
    """The state file of one training run (``<output>.state`` by the command line)."""

    def __init__(self, path: Path, ckpt: Checkpoint) -> None:
        self.path, self.fingerprint, self.algorithm = path, fingerprint(ckpt), ckpt.record.algorithm
        self.identity = json.dumps(identity(ckpt), sort_keys=True)
        #: the algorithm's own state as saved (tensors, numbers, lists, dicts), set by :meth:`restore`
        self.extra: dict[str, Any] = {}

    def save(
        self,
        epoch: int,
        ckpt: Checkpoint,
        opt: torch.optim.Optimizer,
        rng: np.random.Generator,
        selector: Selector,
        extra: dict[str, Any] | None = None,
    ) -> None:
        """Write the state atomically; ``extra`` must hold only what ``torch.load(weights_only=True)``
        reads back (tensors, numbers, strings, lists, dicts)."""
        blob = {
            "format": STATE_FORMAT,
            "fingerprint": self.fingerprint,
            "identity": self.identity,  # to say what differs when another training tries to resume it
            "algorithm": self.algorithm,
            "epoch": epoch,
            "model": ckpt.model.state_dict(),
            "optimizer": opt.state_dict(),
            "rng": json.dumps(rng.bit_generator.state),
            "selector": selector.to_state(),
            "extra": extra or {},
        }
        atomic_write(self.path, lambda fh: torch.save(blob, fh))

    def restore(
        self, ckpt: Checkpoint, opt: torch.optim.Optimizer, rng: np.random.Generator, selector: Selector
    ) -> int:
        """Load the state into the training's objects; returns the last finished epoch. The
        algorithm's own state is left in :attr:`extra` for it to load."""
        blob = load_torch_file(self.path, "no training state to resume from", "not a training state", reason=False)
        if not isinstance(blob, dict) or blob.get("format") != STATE_FORMAT:
            raise ValueError(f"{self.path}: not an envi training state")
        if blob.get("algorithm", "bc") != self.algorithm:
            raise ValueError(
                f"{self.path}: the state is from a {blob.get('algorithm', 'bc')} training, not {self.algorithm}; "
                "remove it or train without --resume"
            )
        if blob.get("fingerprint") != self.fingerprint:
            try:
                which = differences(json.loads(blob["identity"]), json.loads(self.identity))
            except (KeyError, TypeError, ValueError):  # a state of an earlier envi records no identity
                which = []
            raise ValueError(
                f"{self.path}: the state belongs to another training (it differs in "
                f"{', '.join(which) if which else 'data, seed or settings'}); remove it or train without --resume"
            )
        ckpt.model.load_state_dict(blob["model"])
        opt.load_state_dict(blob["optimizer"])
        rng.bit_generator.state = json.loads(blob["rng"])
        selector.load_state(blob["selector"])
        self.extra = blob.get("extra", {})
        return int(blob["epoch"])
