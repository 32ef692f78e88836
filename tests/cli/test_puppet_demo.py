"""The demo's puppet: the simulated phone performs the puppeteer's choreography (through the real page
codec, clock sync and recorder), and ``perfcap demo``'s puppet step walks, runs and hops the character
from that session, with no fall, and writes a BVH that reads back."""

from __future__ import annotations

import os
import re

import numpy as np

from capture.app.demo import demo_puppet
from capture.session import SessionReader
from retarget.bvh import read_bvh


def test_the_demo_puppet_walks_runs_and_hops_from_the_puppeteer_phone(tmp_path, record_phone_session):
    session = record_phone_session(tmp_path / "demo.mcap", duration_s=5.0, motion="puppeteer")
    out = [ln for ln in demo_puppet(SessionReader(str(session))).splitlines() if ln.strip()]
    assert len(out) == 1, out
    line = out[0]
    m = re.search(r"covered ([0-9.]+) m at up to ([0-9.]+) m/s; states (.*); BVH (.*)$", line)
    assert m, line
    assert m.group(3) == "LOCOMOTION -> JUMP_ANTICIPATION -> AIRBORNE -> LANDING"
    assert float(m.group(2)) > 2.5 and float(m.group(1)) > 4.0       # it ran, and went somewhere
    bvh = m.group(4)
    assert bvh == os.path.join(str(tmp_path), "puppet.bvh")
    _, clip = read_bvh(bvh)
    ground = np.hypot(np.diff(clip.root_pos[:, 0]), np.diff(clip.root_pos[:, 2])) * clip.fps
    assert np.percentile(ground, 95) > 2.5
