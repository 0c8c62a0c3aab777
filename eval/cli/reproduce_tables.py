"""`conav reproduce`'s results and tables: every evaluation's metrics.json -> results.json ->
tables.md.

`collect_results` reads the evaluations under OUT/eval into results.json's content (per agent, per
seed; the command line adds the commit, the command and the stage timings) -> `render_tables`
writes tables.md: Table 2 (every agent beside the paper's figures, its privileged inputs named)
and Table 3 (the five intention ablations, and the ground-truth rows where trained), each learned
cell the mean ± sd over training seeds with the 95% t-interval of the mean over seeds
(eval.stats), and a seed-by-seed section of paired contrasts (each row minus its reference, seed
by seed, with the t-interval of the mean difference), and the commits the rows were evaluated at.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

from conav_jax.envs.metrics import METRIC_NAMES
from conav_jax.provenance import UNKNOWN
from conav_jax.eval.stats import paired_difference, resolved, seed_summary
from conav_jax.eval.cli.reproduce_plan import (ABLATIONS, BC_EVAL, BC_ROW_EVAL, CONAV_EVAL, GROUND_TRUTH_ROWS,
                                               LEARNED_BASELINES, baseline_name, dagger_variant, live_dagger_variant)

# The paper's Table 2 and Table 3 (FASR, RASR, FASPL, RASPL, CR, AS), for side-by-side tables.
PAPER_TABLE2 = {
    "random": ("Random Agent", (4.5, 4.6, 3.7, 3.7, 32.7, 442.6)),
    "pioneer": ("Pioneer Agent (Oracle Pathfinder)", (61.6, 61.8, 46.6, 46.7, 30.4, 308.1)),
    "follower": ("Human-following Agent", (3.5, 3.7, 1.6, 1.7, 49.0, 350.8)),
    "objectgoal-oracle": ("Object-goal Agent (Oracle Goal Object)", (15.6, 16.4, 10.7, 10.9, 46.1, 295.5)),
    "objectgoal-predicted": ("Object-goal Agent (Predicted Goal Object)", (8.6, 9.3, 7.2, 7.5, 38.7, 377.4)),
    "imagegoal": ("Image-goal Agent", (7.6, 8.1, 6.0, 6.2, 41.4, 372.5)),
    "conav": ("CoNav Agent (Ours)", (19.8, 23.2, 13.5, 14.9, 20.1, 354.5)),
}
PAPER_TABLE3 = {
    "none": (14.5, 17.0, 10.6, 11.8, 14.7, 402.9),
    "activity": (14.4, 17.4, 10.2, 11.9, 27.7, 330.1),
    "object": (15.7, 18.6, 10.6, 11.7, 16.0, 391.9),
    "activity_object": (17.5, 20.4, 11.4, 12.8, 22.2, 352.5),
    "all": (19.8, 23.2, 13.5, 14.9, 20.1, 354.5),
}

_SEEDED_EVAL = re.compile(r"conav_(.+)_s[0-9]+")




def dagger_rows(evals: Path, planned: str = "dagger") -> list[str]:
    """The DAgger rows to tabulate: the run's own (`planned`, a `dagger_row` or `live_dagger_row`
    name) and every other one evaluated under `evals`: the offline trainer's by the expert's
    share, then round count, then episodes a round (the defaults first), then the live
    trainer's by their final beta."""
    found = {m.group(1) for m in map(_SEEDED_EVAL.fullmatch, (d.name for d in Path(evals).glob("conav_dagger*"))) if m}
    variants = {v: row for row in found | {planned} if (v := dagger_variant(row)) is not None}
    live = {v: row for row in found | {planned} if (v := live_dagger_variant(row)) is not None}
    return ([variants[v] for v in sorted(variants, key=lambda v: (v[0], v[1] or 0, v[2] or 0))]
            + [live[v] for v in sorted(live)])


def collect_results(out: Path, seeds: int, extra: dict, dagger: str = "dagger", rows: tuple[str, ...] = ABLATIONS,
                    eval_dir: str = "eval", baseline_seeds: int = 1) -> dict:
    """results.json's content from the evaluations under `out/eval_dir` ("eval": val's;
    "eval_minival": minival's): per agent its title,
    intention source, privileged inputs and metrics (per seed for the learned CoNav rows and,
    over `baseline_seeds` seeds, the learned baselines: `eval/{agent}`, `eval/{agent}_s{s}`).

    A seed's BC rows come from `eval/conav_bc_{row}_s{s}` (else, as made before, from
    `eval/conav_bc_s{s}`, its five BC runs as one evaluation's ablations), a DAgger
    row (a `dagger_row` name: "dagger", "dagger_beta{share}" with the expert mixed in, either with
    "_rounds{n}" for a round count other than the preset's) from `eval/conav_{row}_s{s}`; each row
    lists the seeds it was measured on. An evaluation of the BC rows or of the run's own DAgger
    row (`dagger`) not made yet is listed under "missing" and the tables say so; other DAgger rows
    appear where evaluated.
    FileNotFoundError without any evaluation (nothing to tabulate)."""
    evals = Path(out) / eval_dir
    made = sorted(evals.glob("*/metrics.json"))
    if not made:
        raise FileNotFoundError(f"no evaluation under {evals}: nothing to tabulate")
    agents: dict[str, dict] = {}
    missing: list[str] = []
    path = evals / "scripted" / "metrics.json"
    if path.is_file():
        for key, entry in json.loads(path.read_text())["agents"].items():
            agents[key] = {k: entry[k] for k in ("title", "intention_source", "privileged", "metrics")}
    else:
        missing.append(f"{eval_dir}/scripted")
    conav: dict[str, dict] = {}

    def add(table: dict, row: str, s: int, entry: dict, episodes: int, doc: dict | None = None) -> None:
        slot = table.setdefault(row, {k: entry[k] for k in ("title", "intention_source", "privileged")} | {"seeds": {}})
        slot["seeds"][str(s)] = {"metrics": entry["metrics"], "episodes": episodes}
        commit = _commit_label((doc or {}).get("provenance"))
        if commit is not None:
            slot.setdefault("commits", [])
            slot["commits"] = sorted({*slot["commits"], commit})
        trained = _commit_label((entry.get("trained") or {}).get("provenance"))
        if trained is not None:  # evaluations made before they recorded it name none
            slot["trained_commits"] = sorted({*slot.get("trained_commits", []), trained})

    for agent in LEARNED_BASELINES:
        for s in range(baseline_seeds):
            path = evals / baseline_name(agent, s) / "metrics.json"
            if not path.is_file():
                missing.append(f"{eval_dir}/{path.parent.name}")
                continue
            doc = json.loads(path.read_text())
            for key, entry in doc["agents"].items():
                add(agents, key, s, entry, doc["episodes"], doc)
    for s in range(seeds):
        for row in ABLATIONS + tuple(GROUND_TRUTH_ROWS):
            path, combined = evals / BC_ROW_EVAL.format(row=row, seed=s) / "metrics.json", evals / BC_EVAL.format(s) / "metrics.json"
            if path.is_file():
                doc = json.loads(path.read_text())
                add(conav, row, s, doc["agents"]["conav"], doc["episodes"], doc)
            elif combined.is_file() and row in ABLATIONS:
                doc = json.loads(combined.read_text())
                add(conav, row, s, doc["ablations"][f"ablation_{row}"], doc["episodes"], doc)
            elif row in rows:
                missing.append(f"{eval_dir}/{path.parent.name}")
    for row in dagger_rows(evals, dagger):
        for s in range(seeds):
            path = evals / CONAV_EVAL.format(row=row, seed=s) / "metrics.json"
            if not path.is_file():
                if row == dagger:
                    missing.append(f"{eval_dir}/{path.parent.name}")
                continue
            doc = json.loads(path.read_text())
            add(conav, row, s, doc["agents"]["conav"], doc["episodes"], doc)
    # The split's size, from any evaluation (each runs the whole split).
    episodes = json.loads(made[0].read_text()).get("episodes")
    return {**extra, "episodes": episodes, "agents": agents, "conav": conav, "missing": missing}


def _commit_label(provenance: dict | None) -> str | None:
    """A record's commit as the tables name it: the commit, or where the process could not read
    one (conav_jax.provenance.UNKNOWN) `unknown (code HASH)` when it recorded its source's hash;
    None for a record without provenance."""
    commit = (provenance or {}).get("commit")
    if commit == UNKNOWN and provenance.get("code"):
        return f"{UNKNOWN} (code {provenance['code']})"
    return commit


def _short(commit: str) -> str:
    """A commit shortened to 10 digits; a label that is not a commit (`_commit_label`) whole."""
    return commit if commit.startswith(UNKNOWN) else commit[:10]


def _cell(value: float) -> str:
    return f"{value:.1f}"


def _learned_cell(row: dict, metric: str) -> str:
    """'mean ± sd [lo, hi] (n=k)' over training seeds, the 95% t-interval of the mean over seeds
    (eval.stats.seed_summary; one seed: its value alone). Seeds, not episodes, are the unit: two
    seeds of one row differ by more than their episodes' binomial noise."""
    return seed_summary([s["metrics"][metric]["value"] for s in row["seeds"].values()]).text()


# The tables' columns: the paper's, with CR_full (contacts up to the end of activity B) beside CR.
TABLE_COLUMNS = tuple(c for m in METRIC_NAMES for c in ((m, "CR_full") if m == "CR" else (m,)))


def _paper_cells(paper: tuple[float, ...]) -> str:
    """The paper's figures in TABLE_COLUMNS order; "-" where the paper reports none (CR_full)."""
    values = dict(zip(METRIC_NAMES, paper))
    return " | ".join(_cell(values[c]) if c in values else "-" for c in TABLE_COLUMNS)


def _our_cells(metrics: dict) -> str:
    return " | ".join(_cell(metrics[c]["value"]) if c in metrics else "-" for c in TABLE_COLUMNS)


def _learned_cells(row: dict) -> str:
    have = set.intersection(*(set(s["metrics"]) for s in row["seeds"].values()))
    return " | ".join(_learned_cell(row, c) if c in have else "-" for c in TABLE_COLUMNS)


def _learned_source(row: dict, seeds: int | None) -> str:
    """The source column of a learned row: "ours", and which seeds when not all of the run's."""
    have = sorted(row["seeds"], key=int)
    if seeds is None or len(have) == seeds:
        return "ours"
    return f"ours (seed{'s' if len(have) > 1 else ''} {', '.join(have)} of {seeds})"


def _paired_lines(results: dict, metrics: tuple[str, ...] = ("FASR", "RASR")) -> list[str]:
    """Seed by seed: each learned row's values per seed and its paired difference from its
    reference on the seeds both hold (Table 3's rows against no inputs, DAgger rows against BC
    with all inputs), with the mean difference and its 95% t-interval over those seeds
    (eval.stats.paired_difference); "resolved" where the interval excludes zero."""
    conav = results["conav"]
    pairs = ([(name, "none") for name in ABLATIONS[1:]] + [(gt, GROUND_TRUTH_ROWS[gt]) for gt in GROUND_TRUTH_ROWS]
             + [(gt, "none") for gt in GROUND_TRUTH_ROWS] + [(name, "all") for name in conav if name.startswith("dagger")])
    pairs = [(a, b) for a, b in pairs if a in conav and b in conav]
    if not pairs:
        return []
    lines = ["", "## Seed by seed", "",
             "Each row's value per training seed and its difference from the reference row on the seeds both hold "
             "(seed s of every row shares its initial weights and, with the live trainer, its episode order); "
             "the mean difference ± sd [95% t-interval over those seeds] (n seeds). A contrast whose interval holds "
             "zero is not resolved.", "",
             "| row | reference | " + " | ".join(f"{m} by seed | {m} − reference by seed | paired difference"
                                                 for m in metrics) + " |",
             "|---|---" + "|---|---|---:" * len(metrics) + "|"]
    for name, ref in pairs:
        row, base = conav[name]["seeds"], conav[ref]["seeds"]
        shared = sorted(set(row) & set(base), key=int)
        cells = []
        for m in metrics:
            values = " / ".join(f"s{s} {row[s]['metrics'][m]['value']:.1f}" for s in sorted(row, key=int))
            mine = {int(s): row[s]["metrics"][m]["value"] for s in shared}
            theirs = {int(s): base[s]["metrics"][m]["value"] for s in shared}
            summary = "-"
            if shared:
                contrast = paired_difference(mine, theirs)
                summary = contrast.text(signed=True) + (" resolved" if resolved(contrast) else "")
            cells += [values, " / ".join(f"{mine[int(s)] - theirs[int(s)]:+.1f}" for s in shared) or "-", summary]
        lines.append(f"| {name} | {ref} | " + " | ".join(cells) + " |")
    return lines


def render_tables(results: dict) -> str:
    """tables.md: Table 2 (ours beside the paper's) and Table 3 from results.json's content."""
    cols = TABLE_COLUMNS
    head = "| " + " | ".join(cols) + " |"
    lines = [
        "# CoNav: the paper's Tables 2 and 3, reproduced",
        "",
        f"Data: preset `{results.get('preset', '?')}`, split {results.get('split', 'val')} ({results.get('episodes', '?')} episodes), panorama "
        f"{results.get('resolution', '?')}"
        + (f" (the CoNav policy's panorama encoder: `{results['encoder']}`)" if "encoder" in results else "")
        + f"; {results.get('seeds', '?')} training seed(s) for every learned CoNav row; "
        f"commit {results.get('commit', '?')}. Rates and SPLs in percent, AS in steps. Learned rows: mean ± sd over "
        "training seeds [95% t-interval of the mean over seeds] (n seeds; a row measured on fewer seeds says which). CR counts contacts up to the "
        "first reach (the paper's), CR_full up to the end of activity B. Paper: the published figures (a different simulator, scenes and agents' "
        "implementations; they are context, not a target).",
        "",
        "## Table 2: agents",
        "",
        "| agent | given (privileged inputs) | source " + head,
        "|---|---|---" + "|---:" * len(cols) + "|",
    ]
    not_run = " | ".join("-" for _ in cols)
    for key, (paper_title, paper) in PAPER_TABLE2.items():
        if key == "conav":
            trained = "live imitation" if results.get("trainer") == "live" else "BC"
            for name in ("all", "none"):
                row = results["conav"].get(name)
                if row is not None:
                    title = row["title"].removeprefix(f"{name}: ")  # the evaluation names its ablation rows "NAME: title"
                    lines.append(f"| {title} ({trained}) | {', '.join(row['privileged']) or 'none'} | "
                                 f"{_learned_source(row, results.get('seeds'))} | " + _learned_cells(row) + " |")
                elif name == "all":
                    lines.append(f"| CoNav Agent (BC) | | not run yet | {not_run} |")
            daggers = [k for k in results["conav"] if k.startswith("dagger")]
            for name in daggers:
                row, live_end = results["conav"][name], live_dagger_variant(name)
                if live_end is not None:
                    how = f"live DAgger, the expert's share falling from 1 to {live_end:g}"
                else:
                    share, rounds, episodes = dagger_variant(name)
                    how = ("BC + DAgger" + ("" if share == 0.0 else f", the expert acting at {share:g}^r of round r's steps")
                           + ("" if rounds is None else f", {rounds} round{'s' * (rounds > 1)}")
                           + ("" if episodes is None else f", {episodes} train episodes a round"))
                lines.append(f"| {row['title']} ({how}) | {', '.join(row['privileged']) or 'none'} | "
                             f"{_learned_source(row, results.get('seeds'))} | " + _learned_cells(row) + " |")
            if not daggers:
                lines.append(f"| CoNav Agent (BC + DAgger) | | not run yet | {not_run} |")
        else:
            entry = results["agents"].get(key)
            if entry is not None and "seeds" in entry:  # a learned baseline, over its training seeds
                lines.append(f"| {entry['title']} | {', '.join(entry['privileged']) or 'none'} | "
                             f"{_learned_source(entry, results.get('baseline_seeds'))} | " + _learned_cells(entry) + " |")
            elif entry is not None:
                lines.append(f"| {entry['title']} | {', '.join(entry['privileged']) or 'none'} | ours | "
                             + _our_cells(entry["metrics"]) + " |")
            else:
                lines.append(f"| {key} | | not run yet | {not_run} |")
        lines.append(f"| {paper_title} | | paper | " + _paper_cells(paper) + " |")
    for key, entry in results["agents"].items():
        if key not in PAPER_TABLE2:  # ours without a paper row (e.g. the planner, the expert)
            lines.append(f"| {entry['title']} | {', '.join(entry['privileged']) or 'none'} | ours | "
                         + _our_cells(entry["metrics"]) + " |")
    live = results.get("trainer") == "live"
    lines += ["", "## Table 3: intention inputs (" + ("live imitation, beta 1" if live else "BC") + ", predicted "
              "intentions; rows GT: ground-truth intentions, privileged)", "",
              "| # | activity | object | trajectory | source " + head, "|---|:---:|:---:|:---:|---" + "|---:" * len(cols) + "|"]
    flags = {"none": (0, 0, 0), "activity": (1, 0, 0), "object": (0, 1, 0), "activity_object": (1, 1, 0), "all": (1, 1, 1)}
    shown = list(ABLATIONS) + [gt for gt in GROUND_TRUTH_ROWS if gt in results["conav"] or live]
    for k, name in enumerate(shown, start=1):
        gt = name in GROUND_TRUTH_ROWS
        marks = " | ".join(("GT" if gt else "✓") if f else "✗" for f in flags[GROUND_TRUTH_ROWS.get(name, name)])
        row = results["conav"].get(name)
        if row is not None:
            lines.append(f"| {k} | {marks} | {_learned_source(row, results.get('seeds'))} | " + _learned_cells(row) + " |")
        else:
            lines.append(f"| {k} | {marks} | not run yet | {not_run} |")
        if not gt:
            lines.append(f"| {k} | {marks} | paper | " + _paper_cells(PAPER_TABLE3[name]) + " |")
    lines += _paired_lines(results)
    learned = {**{k: v for k, v in results["agents"].items() if "seeds" in v}, **results["conav"]}
    commits = [(name, row["commits"], row.get("trained_commits", [])) for name, row in learned.items()
               if row.get("commits")]
    if commits:
        lines += ["", "## Commits", "", "The commits each learned row's evaluations ran at and, where they record "
                  "it, those its runs were trained at (their metrics.json provenance). A process that could not "
                  "read its commit names the hash of its source instead (`unknown (code HASH)`: "
                  "conav_jax.provenance.code_hash at a checkout says whether that commit made it).", ""]
        lines += [f"- `{name}`: {', '.join(_short(c) for c in found)}" +
                  (f" (trained at {', '.join(_short(c) for c in trained)})" if trained else "")
                  for name, found, trained in commits]
    if results.get("missing"):
        lines += ["", "## Not run yet", "",
                  "These evaluations are not made yet; the rows above that need them are marked so, and the learned "
                  "rows name the seeds they hold. Running `conav reproduce` again with the same arguments continues.", ""]
        lines += [f"- `{m}`" for m in results["missing"]]
    return "\n".join(lines) + "\n"
