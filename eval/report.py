"""Confidence intervals, the Markdown tables and report.md of an evaluation (pure functions, no JAX).

Per-episode results (the env's final metrics, envs.metrics) -> per-episode outcomes ->
each metric's value with a 95% interval (Wilson for the rates FASR, RASR, CR; a seeded
percentile bootstrap for the SPLs and AS) -> rows laid out like the paper's Tables 2 and 3.
"""

from __future__ import annotations

import math
from typing import Mapping, Sequence

import numpy as np

from conav_jax.envs.metrics import episode_outcomes, reported_metrics

Z_95 = 1.959963984540054  # standard normal quantile of 0.975
RATES = ("FASR", "RASR", "CR", "CR_full")  # 0/1 per episode: Wilson intervals
HIGHER_IS_BETTER = {"FASR": True, "RASR": True, "FASPL": True, "RASPL": True, "CR": False, "AS": False,
                    "CR_full": False, "FASPL_m": True, "RASPL_m": True}
# Table columns: the paper's, with CR_full beside CR and the metre SPLs last.
TABLE_ORDER = ("FASR", "RASR", "FASPL", "RASPL", "CR", "CR_full", "AS", "FASPL_m", "RASPL_m")


def wilson_interval(successes: int, n: int, z: float = Z_95) -> tuple[float, float]:
    """Wilson score interval (lo, hi) in [0, 1] for `successes` out of `n` trials."""
    if n <= 0:
        raise ValueError(f"a rate needs at least one trial, got n={n}")
    if not 0 <= successes <= n:
        raise ValueError(f"successes must be in [0, n={n}], got {successes}")
    p = successes / n
    z2 = z * z
    denom = 1.0 + z2 / n
    centre = (p + z2 / (2 * n)) / denom
    half = z / denom * math.sqrt(p * (1.0 - p) / n + z2 / (4 * n * n))
    return max(0.0, centre - half), min(1.0, centre + half)


def bootstrap_interval(values: np.ndarray, seed: int = 0, resamples: int = 2000, level: float = 0.95) -> tuple[float, float]:
    """Percentile bootstrap interval (lo, hi) of the mean of `values` (1-D, >= 1 value).
    Seeded: the same values and seed give the same interval."""
    v = np.asarray(values, np.float64)
    if v.ndim != 1 or v.size == 0:
        raise ValueError("bootstrap needs a non-empty 1-D array of values")
    rng = np.random.default_rng(seed)
    means = v[rng.integers(0, v.size, size=(resamples, v.size))].mean(axis=1)
    tail = (1.0 - level) / 2.0 * 100.0
    return float(np.percentile(means, tail)), float(np.percentile(means, 100.0 - tail))


def summarize_with_ci(metrics: Mapping[str, np.ndarray], seed: int = 0) -> dict[str, dict[str, float]]:
    """{metric: {"value", "lo", "hi"}} over the episodes of `metrics` (the env's final metrics,
    arrays over episodes). Rates and SPLs in percent, AS in steps, as in the paper's tables."""
    out = episode_outcomes(metrics)
    summary = {}
    for name in reported_metrics(out):
        v = out[name]
        scale = 1.0 if name == "AS" else 100.0
        if name in RATES:
            lo, hi = wilson_interval(int(round(v.sum())), v.size)
        else:
            lo, hi = bootstrap_interval(v, seed=seed)
        summary[name] = {"value": float(v.mean()) * scale, "lo": lo * scale, "hi": hi * scale}
    return summary


def format_cell(entry: Mapping[str, float], digits: int = 1) -> str:
    """'value ± h', h half the interval's width (Wilson intervals are not symmetric: the exact
    bounds are in metrics.json)."""
    return f"{entry['value']:.{digits}f} ± {(entry['hi'] - entry['lo']) / 2.0:.{digits}f}"


def table_columns(summaries: Sequence[Mapping[str, object]]) -> tuple[str, ...]:
    """The metrics every summary holds, in TABLE_ORDER (CR_full only where episodes ran to t_end)."""
    return tuple(m for m in TABLE_ORDER if all(m in s for s in summaries))


def _header(columns: Sequence[str]) -> str:
    arrows = [f"{m}{'↑' if HIGHER_IS_BETTER[m] else '↓'}" for m in columns]
    return "| " + " | ".join(arrows) + " |"


def table2_markdown(rows: Sequence[tuple[str, Mapping[str, Mapping[str, float]]]]) -> str:
    """The paper's Table 2: one row per agent (title, summary from summarize_with_ci), the
    paper's columns with ours beside them."""
    cols = table_columns([s for _, s in rows])
    lines = ["| Methods " + _header(cols), "|---" + "|---:" * len(cols) + "|"]
    for title, summary in rows:
        lines.append(f"| {title} | " + " | ".join(format_cell(summary[m]) for m in cols) + " |")
    return "\n".join(lines) + "\n"


def _mark(flag: bool | None) -> str:
    return "?" if flag is None else ("✓" if flag else "✗")


def table3_markdown(
    rows: Sequence[tuple[str, tuple[bool | None, bool | None, bool | None], Mapping[str, Mapping[str, float]]]],
) -> str:
    """The paper's Table 3: one row per ablation (name, (intended activity, intended object,
    intended trajectory) inputs used, '?' where unknown, summary)."""
    cols = table_columns([s for _, _, s in rows])
    lines = [
        "| Exp. | Activity | Object | Trajectory " + _header(cols),
        "|---|:---:|:---:|:---:" + "|---:" * len(cols) + "|",
    ]
    for name, flags, summary in rows:
        marks = " | ".join(_mark(f) for f in flags)
        lines.append(f"| {name} | {marks} | " + " | ".join(format_cell(summary[m]) for m in cols) + " |")
    return "\n".join(lines) + "\n"


def report_markdown(doc: dict, agents: Sequence, ablations: Sequence, maps: list[tuple[str, str]]) -> str:
    """report.md of an evaluation: its setting (from `doc`, the metrics.json content), Table 2
    of `agents`, what each row was given, Table 3 of `ablations` (rows as eval.sweep.Row: each
    its `given` description and `summary`) and the figures `maps` ((title, png) each)."""
    if doc["data"] is not None and doc["content_hash"] is not None:
        source = f"Data `{doc['data']}` (content hash {doc['content_hash'][:16]})"
    else:
        source = "Episodes made in memory (no dataset directory or content hash)"
    lines = [
        "# CoNav evaluation",
        "",
        f"{source}, split `{doc['split']}`, {doc['episodes']} episodes (each run to the human's end of activity B); "
        f"seed {doc['seed']}, batch {doc['batch']}, panorama {doc['resolution']}.",
        "",
        "## Agents (paper Table 2)",
        "",
        table2_markdown([(row.given["title"], row.summary) for row in agents]),
        "Rates and SPLs in percent, AS in steps (0.1 s). FASPL/RASPL weigh success by the paper's "
        "l / max(l, p) in control steps; FASPL_m/RASPL_m by metres. CR counts contacts up to the "
        "first reach (the paper's), CR_full up to the human's end of activity B. `±` is half the "
        "width of the 95% interval: Wilson for the rates, a percentile bootstrap (2000 resamples, "
        "the run's seed) for the SPLs and AS; exact bounds in metrics.json.",
        "",
        "What each row was given (privileged inputs are what a robot with the paper's sensors lacks):",
        "",
        "| row | intention inputs | privileged inputs | observation keys read |",
        "|---|---|---|---|",
    ]
    for row in (*agents, *ablations):
        g = row.given
        reads = ", ".join([f"`{k}`" for k in g["reads"]] + (["the simulator's state"] if g.get("reads_state") else [])) or "none"
        lines.append(f"| {g['title']} | {g['intention_source']} | {', '.join(g['privileged']) or 'none'} | {reads} |")
    lines.append("")
    if ablations:
        table3 = table3_markdown([(row.given["title"], tuple(row.given["inputs"].values()), row.summary) for row in ablations])
        lines += ["## Ablations of the intention inputs (paper Table 3)", "", table3, "`?`: the run does not say which inputs it uses.", ""]
    lines += ["## Figures", "", "![success by step](success_over_time.png)", ""]
    lines += [f"![{title}: longest episode]({png})" for title, png in maps]
    return "\n".join(lines) + "\n"
