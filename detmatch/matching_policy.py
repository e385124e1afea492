"""Which teacher detections become DetMatch labels: the matching policy (docs/design.md
section 3, steps 4-5), named once.

Training builds it from the config (`MatchingPolicy.from_config`), export writes it into the
manifest (`serving.manifest.MatchingSpec`), the service reads it back and applies a request's
overrides (`MatchingPolicy.with_overrides`), and `detmatch.pseudo_labels.match_detections`
applies it. No torch, no numpy: the service uses it.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass
from typing import TYPE_CHECKING

from detmatch.constants import TAU_3D, TAU_HUNG

if TYPE_CHECKING:
    from detmatch.config import SemiSupervisedConfig


def finite_number(name: str, value: float) -> float:
    """value as a float; ValueError naming `name` unless it is a finite real number."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise ValueError(f"{name}: expected a finite number, got {value!r}")
    return float(value)


def probability_threshold(name: str, value: float) -> float:
    """value as a float; ValueError naming `name` unless it is a score threshold in [0, 1)."""
    value = finite_number(name, value)
    if not 0.0 <= value < 1.0:
        raise ValueError(f"{name}: expected a probability threshold in [0, 1), got {value}")
    return value


def _on_below_one(value: float) -> float | None:
    """A config threshold on a probability: 1.0 (nothing exceeds it) means the rule is off."""
    return value if value < 1.0 else None


@dataclass(frozen=True)
class MatchingPolicy:
    """tau_hung: assigned 2D-3D pairs whose matching cost is <= tau_hung become labels (good
    pairs cost below zero). tau_3d_outside_view: 3D boxes outside the camera's view whose max
    class probability exceeds it become LiDAR-only labels (the field-of-view fallback to
    confidence thresholding at tau_3D; None: off). tau_3d_unmatched: in-view 3D boxes the
    matching leaves unmatched whose score exceeds it become LiDAR-only labels too (None: off,
    the paper's rule). The defaults are the paper's. Values are checked (ValueError naming the
    field) and stored as floats."""

    tau_hung: float = TAU_HUNG
    tau_3d_outside_view: float | None = TAU_3D
    tau_3d_unmatched: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "tau_hung", finite_number("tau_hung", self.tau_hung))
        for name in ("tau_3d_outside_view", "tau_3d_unmatched"):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, probability_threshold(name, value))

    @classmethod
    def from_config(cls, ssl: SemiSupervisedConfig) -> MatchingPolicy:
        """The policy of a training config: [ssl] tau_hung; the outside-view fallback at
        [ssl] tau_3d; [ssl] tau_3d_unmatched. A probability threshold of 1.0 is off (None)."""
        return cls(
            tau_hung=ssl.tau_hung,
            tau_3d_outside_view=_on_below_one(ssl.tau_3d),
            tau_3d_unmatched=_on_below_one(ssl.tau_3d_unmatched),
        )

    def with_overrides(
        self,
        *,
        tau_hung: float | None = None,
        tau_3d_outside_view: float | None = None,
        tau_3d_unmatched: float | None = None,
        outside_view_fallback: bool = True,
    ) -> MatchingPolicy:
        """This policy with one request's thresholds: None keeps this policy's value (a given
        threshold also turns on a rule this policy has off); outside_view_fallback False turns
        the outside-view fallback off whatever tau_3d_outside_view says. ValueError names a bad
        value."""
        given = {
            "tau_hung": tau_hung,
            "tau_3d_outside_view": tau_3d_outside_view,
            "tau_3d_unmatched": tau_3d_unmatched,
        }
        changes = {name: value for name, value in given.items() if value is not None}
        if not outside_view_fallback:
            changes["tau_3d_outside_view"] = None
        return dataclasses.replace(self, **changes)
