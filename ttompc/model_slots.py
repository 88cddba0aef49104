"""The model slots: the two kinds of model a closed-loop method plans with, a pre-trained transformer (``TTO``) and
one DAgger fine-tuned from it (``FT-TTO``), each with the config key that names its model (and its ``--flag``).

The one source of these names: the method registry gives each model method a slot (``ttompc.mpc.methods``), a
model card's ``kind`` is one (``ttompc.zoo.cards``), and a bundle's metadata tells which a model fills
(``slot_of``). Imports nothing of ttompc, so every layer may name a slot.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

PRETRAINED, FINE_TUNED = "TTO", "FT-TTO"
# the model slots, pre-trained first (the order of METHODS and of the reports), each with its config key
MODEL_SLOTS = {PRETRAINED: "model", FINE_TUNED: "ft_model"}


def slot_flag(slot: str) -> str:
    """The command-line flag naming the model of ``slot``: ``--model`` (TTO), ``--ft-model`` (FT-TTO)."""
    return "--" + MODEL_SLOTS[slot].replace("_", "-")


def slot_of(extra: Mapping[str, Any]) -> str:
    """The slot a model with metadata ``extra`` (``Planner.extra``, a bundle's ``extra``) fills: FT-TTO when it
    records what it was fine-tuned from, else TTO."""
    return FINE_TUNED if "finetuned_from" in extra else PRETRAINED
