"""Learning curves of a bench directory: TPR, TNR and trusted share per iteration, one panel per
robot, one line style per preset (mean over seeds), the truly safe share as a dotted line.

    python bench/robots/plot.py DIR      # writes DIR/curves.png
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def main(out: Path) -> None:
    table = json.loads((out / "summary.json").read_text())["robots"]
    robots = list(table)
    fig, axes = plt.subplots(1, len(robots), figsize=(4.2 * len(robots), 3.6), squeeze=False)
    for ax, robot in zip(axes[0], robots, strict=True):
        row = table[robot]
        for preset, style in (("default", "-"), ("paper", "--")):
            if preset not in row:
                continue
            curve = row[preset]["curve"]
            its = [int(i) for i in curve]
            for key, color in (("tpr", "tab:green"), ("tnr", "tab:red"),
                               ("trusted_share", "tab:blue")):
                ys = [curve[str(i)][key]["mean"] for i in its]
                n = row[preset]["posted"]["n"]
                ax.plot(its, ys, style, color=color, marker="o", ms=3,
                        label=f"{key} ({preset}, {n} seeds)")
        safe = row["truly_safe_share"]["mean"]
        if safe is not None:
            ax.axhline(safe, color="gray", ls=":", label="truly safe share")
        ax.set_title(robot)
        ax.set_xlabel("iteration (5 trajectories each)")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
    axes[0][-1].legend(fontsize=7, loc="center left", bbox_to_anchor=(1.02, 0.5))
    fig.tight_layout()
    fig.savefig(out / "curves.png", dpi=110)


if __name__ == "__main__":
    main(Path(sys.argv[1]))
