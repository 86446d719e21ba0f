"""Pareto fronts and CPU ratios from tidy work-precision rows (no plotting here)."""

from __future__ import annotations

import math

#: Accuracies of the ratio table [rad or m].
TARGET_ERRORS = (1e-3, 1e-6, 1e-9)


def _ok(row: dict) -> bool:
    return row["status"] == "ok" and math.isfinite(row["error"]) and math.isfinite(row["cpu_s"])


def pareto_front(rows: list[dict]) -> list[dict]:
    """Rows not beaten on both CPU and error by another row, sorted by CPU."""
    front, best = [], math.inf
    for row in sorted((r for r in rows if _ok(r)), key=lambda r: (r["cpu_s"], r["error"])):
        if row["error"] < best:
            front.append(row)
            best = row["error"]
    return front


def cheapest_at(rows: list[dict], error: float) -> dict | None:
    """The cheapest row with error <= ``error`` (None when none reaches it)."""
    ok = [r for r in rows if _ok(r) and r["error"] <= error]
    return min(ok, key=lambda r: r["cpu_s"]) if ok else None


def cpu_at(rows: list[dict], error: float) -> float:
    """CPU at exactly ``error`` on the Pareto front of ``rows``: log-log interpolation between
    the two front runs around it (a step or tolerance grid puts its runs at whatever error
    they land on; this removes the grid's luck from a ratio). The cheapest front run when it
    already reaches ``error`` (no extrapolation); nan when no run reaches it."""
    front = pareto_front(rows)
    for i, r in enumerate(front):
        if r["error"] <= error:
            if i == 0 or not r["error"] > 0:
                return r["cpu_s"]
            p = front[i - 1]
            s = math.log(error / p["error"]) / math.log(r["error"] / p["error"])
            return math.exp(math.log(p["cpu_s"]) + s * math.log(r["cpu_s"] / p["cpu_s"]))
    return math.nan


def ratio_table(rows: list[dict], agreements: dict[str, float]) -> list[dict]:
    """CPU of closedchain's cheapest run over each peer's cheapest run at each target error.

    Args:
        rows: tidy work-precision rows.
        agreements: scenario -> agreement of the reference with its confirmation;
            targets below it cannot be ranked.

    Returns:
        Rows (scenario, peer, target, ratio, interpolated, closedchain, peer_run, note):
        ratio < 1 means closedchain needs less CPU; ``interpolated`` is the same ratio
        with each side's CPU at exactly the target (:func:`cpu_at`).
    """
    out = []
    for sc in sorted({r["scenario"] for r in rows}):
        mine = [r for r in rows if r["scenario"] == sc and r["family"] == "closedchain"]
        peers = sorted({r["family"] for r in rows if r["scenario"] == sc} - {"closedchain"})
        for peer in peers:
            theirs = [r for r in rows if r["scenario"] == sc and r["family"] == peer]
            for target in TARGET_ERRORS:
                entry = dict(
                    scenario=sc,
                    peer=peer,
                    target=target,
                    ratio=math.nan,
                    interpolated=math.nan,
                    closedchain="",
                    peer_run="",
                    note="",
                )
                if not math.isfinite(agreements.get(sc, 0.0)):
                    entry["note"] = "no confirmed reference"
                    out.append(entry)
                    continue
                if agreements.get(sc, 0.0) > target:
                    entry["note"] = f"reference confirmed only to {agreements[sc]:.1e}"
                    out.append(entry)
                    continue
                a, b = cheapest_at(mine, target), cheapest_at(theirs, target)
                if a:
                    entry["closedchain"] = f"{a['solver']} {a['settings']}"
                if b:
                    entry["peer_run"] = f"{b['solver']} {b['settings']}"
                if a and b:
                    entry["ratio"] = a["cpu_s"] / b["cpu_s"]
                    entry["interpolated"] = cpu_at(mine, target) / cpu_at(theirs, target)
                elif not b:
                    ok = [r for r in theirs if _ok(r)]
                    if ok:
                        best = min(ok, key=lambda r: r["error"])
                        entry["note"] = (
                            f"{peer} cannot reach it: best error {best['error']:.1e}"
                            f" at {best['cpu_s']:.3g} CPU s/s"
                        )
                    else:
                        entry["note"] = f"{peer}: no successful run"
                    if not a:
                        entry["note"] += "; closedchain cannot reach it either"
                else:
                    entry["note"] = "closedchain cannot reach it"
                out.append(entry)
    return out


def ratio_markdown(table: list[dict]) -> str:
    """The ratio table as Markdown (closedchain CPU / peer CPU at equal error)."""
    lines = [
        "| scenario | peer | error <= | closedchain / peer CPU | interpolated on the fronts "
        "| closedchain run | peer run | note |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for e in table:
        ratio = "" if math.isnan(e["ratio"]) else f"{e['ratio']:.3g}"
        inter = e.get("interpolated", math.nan)
        inter = "" if math.isnan(inter) else f"{inter:.3g}"
        lines.append(
            f"| {e['scenario']} | {e['peer']} | {e['target']:.0e} | {ratio} | {inter} | "
            f"{e['closedchain']} | {e['peer_run']} | {e['note']} |"
        )
    return "\n".join(lines) + "\n"
