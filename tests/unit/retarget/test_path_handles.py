"""The handles of a path (``retarget.path_handles``): about one per step on the real CMU walk, turn, run and jump,
at the lowest root key of each contact period, the endpoints always, one lift-only handle at each flight's apex;
and on a seeded sweep of random contact structures the same rules hold (endpoints, time order, one handle per
period unless merged into a neighbour within the merge window, apexes inside their flights)."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from retarget.bvh import CMU_SCALE, read_bvh
from retarget.path_contacts import Contacts, Flight, detect_contacts, locally_maximal_periods
from retarget.path_handles import select_handles

CMU = Path(__file__).resolve().parents[3].parent / "shared" / "traces" / "d_mocap_cyclic" / "cmu_016"


@pytest.mark.parametrize(("name", "paths", "apexes"), [("16_21_walk.bvh", 7, 0), ("16_18_walk_left_turn.bvh", 9, 0),
                                                       ("16_35_run.bvh", 5, 3), ("16_06_forward_jump.bvh", 4, 1)])
def test_about_one_handle_per_step_on_the_cmu_takes(name: str, paths: int, apexes: int) -> None:
    path = CMU / name
    if not path.exists():
        pytest.skip(f"{path} not found (../shared/traces must sit beside the project)")
    clip = read_bvh(path, scale=CMU_SCALE, end_sites=True)[1]
    c = detect_contacts(clip)
    hs = select_handles(clip.root_pos, clip.fps, c)
    assert [h.kind for h in hs].count("path") == paths and [h.kind for h in hs].count("apex") == apexes
    assert hs[0].key == 0 and hs[-1].key == clip.n_frames - 1
    assert [h.index for h in hs] == list(range(len(hs))) and all(a.key < b.key for a, b in itertools.pairwise(hs))
    for h in hs:
        assert h.position == tuple(clip.root_pos[h.key]) and h.time == pytest.approx(h.key / clip.fps)
        if h.kind == "path" and 0 < h.key < clip.n_frames - 1:
            a, b = next((a, b) for a, b in c.periods if a <= h.key < b)
            assert h.key == a + int(np.argmin(clip.root_pos[a:b, 1]))   # the lowest root key of its period


def test_the_rules_hold_on_random_contact_structures() -> None:
    rng = np.random.default_rng(191)
    fps = 120.0
    for case in range(300):
        n = int(rng.integers(2, 400))
        count = np.repeat(rng.integers(0, 3, n // 5 + 1), 5)[:n].astype(np.intp)
        root = np.column_stack([np.cumsum(rng.normal(0, 0.01, n)), 1 + 0.05 * np.sin(np.arange(n) / 7)
                                + rng.normal(0, 0.002, n), np.cumsum(rng.normal(0, 0.01, n))])
        periods = tuple(locally_maximal_periods(count))
        zero = [(a, b) for a, b in zip(*np.flatnonzero(np.diff(np.r_[0, count == 0, 0])).reshape(-1, 2).T,
                                      strict=True) if a > 0 and b < n]
        flights = tuple(Flight(int(a) - 1, int(b), 9.8) for a, b in zero)
        c = Contacts({"left": count > 0, "right": count > 1}, count, periods, flights, True)
        merge = float(rng.choice([0.0, 0.05, 0.1, 0.3]))
        hs = select_handles(root, fps, c, merge_s=merge)
        keys = [h.key for h in hs]
        assert keys == sorted(set(keys)) and keys[0] == 0 and keys[-1] == n - 1, case
        paths = [h.key for h in hs if h.kind == "path"]
        for a, b in periods:
            k = a + int(np.argmin(root[a:b, 1]))
            assert k in paths or any(abs(k - o) <= merge * fps for o in paths), case
        for f in flights:   # its apex is a lift-only handle, unless a path handle already sits on that key
            y = root[f.takeoff:f.landing + 1, 1]
            apex = f.takeoff + int(np.argmax(y - np.linspace(y[0], y[-1], len(y))))
            assert apex in keys, case
            assert next(h.kind for h in hs if h.key == apex) == ("path" if apex in paths else "apex"), case


def test_bad_arguments() -> None:
    c = Contacts({}, np.zeros(1, np.intp), (), (), True)
    with pytest.raises(ValueError, match="at least two keys"):
        select_handles(np.zeros((1, 3)), 60.0, c)
    with pytest.raises(ValueError, match="merge_s"):
        select_handles(np.zeros((3, 3)), 60.0, Contacts({}, np.zeros(3, np.intp), (), (), True), merge_s=-1)
