"""The picture of an extracted cycle: for each channel, the performed loops time-aligned to the cycle
(thin, translucent) under the extracted loop (thick), with the period, loops, confidence and closure
error in the header, so a user sees at a glance whether the extraction worked.

matplotlib is imported when a report is drawn (not with ``cycles``), and drawn on its Agg canvas
through a ``Figure`` object: no display, no pyplot and no global matplotlib state are involved.
"""

from __future__ import annotations

import math
import textwrap
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from cycles.cycle import Cycle

LOOP_COLOR = "#4c72b0"
CYCLE_COLOR = "#dd5a12"


def report_channels(cycle: Cycle, max_channels: int) -> list[int]:
    """The channels a report shows, in input order: all of them, or the ``max_channels`` whose
    extracted loop varies most (variance in the channel's own units).

    Raises:
        ValueError: ``max_channels`` is less than 1.
    """
    if max_channels < 1:
        raise ValueError("max_channels must be at least 1")
    c = cycle.values.shape[1]
    if c <= max_channels:
        return list(range(c))
    var = np.var(cycle.values, axis=0)
    keep = np.argsort(-var, kind="stable")[:max_channels]
    return sorted(int(i) for i in keep)


def _header(cycle: Cycle, width_chars: int) -> str:
    parts = [f"period {cycle.period_s:.4g} s", f"{cycle.loops} loops", f"confidence {cycle.confidence:.2f}",
             f"closure error {cycle.closure_error:.3g} sd"]
    spans = np.asarray(cycle.loop_spans_s, np.float64).reshape(-1, 2)
    if len(spans):
        d = spans[:, 1] - spans[:, 0]
        parts.append(f"loop durations {d.min():.3g}-{d.max():.3g} s")
    if cycle.elapsed_ms:
        parts.append(f"extracted in {cycle.elapsed_ms:.0f} ms")
    lines = [parts[0]]
    for p in parts[1:]:
        if len(lines[-1]) + 3 + len(p) > width_chars:
            lines.append(p)
        else:
            lines[-1] += "   " + p
    return "\n".join(lines)


def write_report(cycle: Cycle, path: str, *, title: str = "", max_channels: int = 12) -> None:
    """Draw ``cycle`` to an image file (PNG unless ``path`` names another format matplotlib writes).

    One subplot per channel (at most ``max_channels``: beyond that, the channels that vary most, and
    the title says so): the input loops time-aligned to the cycle (``cycle.aligned``), the extracted
    cycle over them, time in the cycle (s) on the x axis.

    Args:
        cycle: the extracted cycle.
        path: where to write the image.
        title: first header line (default: "motion cycle").
        max_channels: most channels drawn.

    Raises:
        OSError: the file cannot be written.
        ValueError: ``max_channels`` < 1, or a file name extension matplotlib cannot write.
        ImportError: matplotlib is not installed.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    shown = report_channels(cycle, max_channels)
    n_ch = cycle.values.shape[1]
    ncols = 1 if len(shown) <= 3 else 2 if len(shown) <= 8 else 3
    nrows = math.ceil(len(shown) / ncols)
    width = max(7.5, 4.2 * ncols + 1.0)
    sub = _header(cycle, int(width * 13))
    if cycle.aligned is None:
        sub += "\n(the input loops were not kept: only the extracted cycle is drawn)"
    if cycle.notes:
        sub += "\n" + "\n".join(textwrap.shorten(n, int(width * 13)) for n in cycle.notes[:3])
    fig = Figure(figsize=(width, 1.9 * nrows + 1.35 + 0.16 * sub.count("\n")), dpi=100)
    FigureCanvasAgg(fig)
    head = title or "motion cycle"
    if len(shown) < n_ch:
        head += f" (showing the {len(shown)} of {n_ch} channels that vary most)"
    fig.suptitle(head, fontsize=12, fontweight="bold", y=0.995)
    top_in = 0.9 + 0.16 * sub.count("\n")
    height = fig.get_figheight()
    fig.text(0.5, 1.0 - 0.42 / height, sub, ha="center", va="top", fontsize=9)
    fig.subplots_adjust(left=0.07, right=0.98, bottom=0.35 / height + 0.04, top=1.0 - top_in / height,
                        hspace=0.55, wspace=0.22)

    t = np.asarray(cycle.times_s, np.float64)
    aligned = cycle.aligned
    for k, ch in enumerate(shown):
        ax = fig.add_subplot(nrows, ncols, k + 1)
        if aligned is not None and len(aligned):
            a = np.asarray(aligned[:, :, ch], np.float64)
            ta = np.linspace(0.0, cycle.period_s, a.shape[1])
            for i, row in enumerate(a):
                ax.plot(ta, row, color=LOOP_COLOR, lw=0.9, alpha=0.55,
                        label="input loops, time-aligned" if i == 0 else None)
        ax.plot(t, cycle.values[:, ch], color=CYCLE_COLOR, lw=1.8, label="extracted cycle")
        ax.set_title(cycle.channels[ch], fontsize=9, pad=3)
        ax.set_xlim(0.0, cycle.period_s)
        ax.tick_params(labelsize=7)
        ax.grid(True, lw=0.3, alpha=0.5)
        if k >= len(shown) - ncols:
            ax.set_xlabel("time in the cycle (s)", fontsize=8)
        if k == 0:
            ax.legend(fontsize=7, loc="best", frameon=False)
    fig.savefig(path)
