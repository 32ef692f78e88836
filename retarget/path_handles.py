"""The handles of a locomotion clip's path (``docs/design/path-editing.md`` section 1.2): about one per step,
at the key where the root is lowest in each locally maximal contact period (a walk's double stances, a
run's single stances), plus the first and last keys; one vertical-only handle at the apex of each flight,
for the jump's height. The set is chosen once per clip and never changes while editing.

A period handle within ``merge_s`` of an endpoint or of an earlier handle is merged into it (the endpoint
wins), so a clip that starts or ends in a stance has no two handles on one step.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

if TYPE_CHECKING:
    from retarget._types import FloatArray
    from retarget.path_contacts import Contacts

HandleKind = Literal["path", "apex"]


@dataclass(frozen=True)
class Handle:
    """One handle: its number (time order), the key it sits on, its time (s), its kind (``path``: moves
    along the floor and up; ``apex``: only lifts, a flight's height) and the root's original position."""

    index: int
    key: int
    time: float
    kind: HandleKind
    position: tuple[float, float, float]


def select_handles(root_pos: FloatArray, fps: float, contacts: Contacts, *, merge_s: float = 0.1
                   ) -> tuple[Handle, ...]:
    """The handles of a clip with root positions ``(F, 3)`` (Y up) at ``fps`` and its ``contacts``.

    Raises:
        ValueError: fewer than two keys, or ``merge_s`` negative.
    """
    n = len(root_pos)
    if n < 2:
        raise ValueError(f"a path needs at least two keys, not {n}")
    if not merge_s >= 0:
        raise ValueError(f"merge_s must be >= 0, not {merge_s}")
    gap = merge_s * fps
    keys = [0, n - 1]
    for a, b in contacts.periods:
        k = a + int(np.argmin(root_pos[a:b, 1]))
        if all(abs(k - other) > gap for other in keys):
            keys.append(k)
    keys.sort()
    kinds: dict[int, HandleKind] = dict.fromkeys(keys, "path")
    for f in contacts.flights:
        j, k = f.takeoff, f.landing
        y = root_pos[j:k + 1, 1]
        chord = np.linspace(y[0], y[-1], len(y))
        apex = j + int(np.argmax(y - chord))
        if apex not in kinds:
            kinds[apex] = "apex"
    out = []
    for i, key in enumerate(sorted(kinds)):
        p = root_pos[key]
        out.append(Handle(i, key, key / fps, kinds[key], (float(p[0]), float(p[1]), float(p[2]))))
    return tuple(out)


__all__ = ["Handle", "HandleKind", "select_handles"]
