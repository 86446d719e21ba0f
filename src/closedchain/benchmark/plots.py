"""Charts of the benchmark's tidy rows (matplotlib, Agg; reads rows, computes nothing new)."""

from __future__ import annotations

import math
from pathlib import Path

from .._io import save_figure
from .analysis import pareto_front

#: Colours per family (others get matplotlib's cycle).
FAMILY_COLORS = {
    "closedchain": "tab:blue",
    "scipy": "tab:orange",
    "pinocchio-euler": "tab:green",
    "mujoco": "tab:red",
    "lesson": "tab:purple",
}
#: Error floor drawn for runs with zero error (log axes) [rad].
ERROR_FLOOR = 1e-16


def plot_work_precision(
    rows: list[dict],
    scenario: str,
    path: str | Path,
    *,
    agreement: float | None = None,
    title: str = "",
) -> None:
    """Error (log) against CPU seconds per simulated second (log) for one scenario:
    every run as a point, each family's Pareto front as a line, closedchain's bold."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in rows if r["scenario"] == scenario]
    fig, ax = plt.subplots(figsize=(7.5, 5.5))
    families = sorted({r["family"] for r in rows}, key=lambda f: (f != "closedchain", f))
    for fam in families:
        mine = [r for r in rows if r["family"] == fam]
        ok = [r for r in mine if r["status"] == "ok" and math.isfinite(r["error"])]
        color = FAMILY_COLORS.get(fam)
        ax.scatter(
            [r["cpu_s"] for r in ok],
            [max(r["error"], ERROR_FLOOR) for r in ok],
            s=14,
            color=color,
            alpha=0.45,
        )
        front = pareto_front(mine)
        ax.plot(
            [r["cpu_s"] for r in front],
            [max(r["error"], ERROR_FLOOR) for r in front],
            "-o",
            color=color,
            lw=3.0 if fam == "closedchain" else 1.2,
            ms=5 if fam == "closedchain" else 3,
            label=f"{fam} (front)",
        )
    if agreement is not None and math.isfinite(agreement):  # inf: no confirmed reference
        ax.axhline(
            max(agreement, ERROR_FLOOR),
            color="gray",
            ls=":",
            label=f"reference agreement {agreement:.1e}",
        )
    if any(r["status"] == "ok" and math.isfinite(r["error"]) for r in rows):
        ax.set_xscale("log")
        ax.set_yscale("log")
    else:  # log axes need a point: a scenario without a confirmed reference has none
        ax.text(
            0.5,
            0.5,
            "no confirmed reference: errors not measured",
            ha="center",
            va="center",
            transform=ax.transAxes,
        )
    ax.set_xlabel("CPU seconds per simulated second")
    ax.set_ylabel("max coordinate error over the horizon [rad]")
    ax.set_title(title or scenario)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def plot_stability_map(rows: list[dict], path: str | Path) -> None:
    """Grid chart of the stability map: one panel per case, configurations x step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    states = ["ok", "drift", "diverged", "raised"]
    cmap = ListedColormap(["#4caf50", "#ffc107", "#e53935", "#7e57c2"])
    cases = sorted({r["case"] for r in rows})
    fig, axes = plt.subplots(
        len(cases), 1, figsize=(9, 2.2 + 0.28 * len(rows) / max(len(cases), 1)), squeeze=False
    )
    for ax, case in zip(axes[:, 0], cases, strict=True):
        mine = [r for r in rows if r["case"] == case]
        configs = sorted({r["config"] for r in mine})
        steps = sorted({r["step"] for r in mine})
        grid = [[math.nan] * len(steps) for _ in configs]
        for r in mine:
            grid[configs.index(r["config"])][steps.index(r["step"])] = states.index(r["status"])
        ax.imshow(grid, cmap=cmap, vmin=-0.5, vmax=3.5, aspect="auto")
        ax.set_yticks(range(len(configs)), configs, fontsize=7)
        ax.set_xticks(range(len(steps)), [f"{s:.0e}" for s in steps], fontsize=7)
        ax.set_title(case, fontsize=9)
    handles = [plt.Rectangle((0, 0), 1, 1, color=cmap(i)) for i in range(4)]
    fig.legend(handles, states, loc="upper right", ncol=4, fontsize=8)
    axes[-1, 0].set_xlabel("step [s]")
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def plot_scaling(rows: list[dict], path: str | Path) -> None:
    """Cost per evaluation against nv (log-log), one panel per family, one line per
    method and backend, with the fitted exponent in the legend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .scaling import growth_exponents, series_label

    families = list(dict.fromkeys(r.get("family", "") for r in rows))
    fig, axes = plt.subplots(1, len(families), figsize=(6 * len(families), 5), squeeze=False)
    for ax, family in zip(axes[0], families, strict=True):
        mine = [r for r in rows if r.get("family", "") == family]
        exps = growth_exponents(mine, size="nv")
        for label in sorted({series_label(r) for r in mine}):
            line = sorted((r for r in mine if series_label(r) == label), key=lambda r: r["nv"])
            style = "--s" if "compiled" in label else ("-^" if "numpy" not in label else "-o")
            p = exps.get(label)
            ax.plot(
                [r["nv"] for r in line],
                [r["us"] for r in line],
                style,
                label=label + ("" if p is None else f"  p = {p:.2f}"),
            )
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("nv (degrees of freedom of the tree)")
        ax.set_ylabel("CPU microseconds per evaluation")
        ax.set_title(family or "cost per evaluation")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle("cost per forward-dynamics evaluation against nv (fitted cost ~ nv^p)")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)
