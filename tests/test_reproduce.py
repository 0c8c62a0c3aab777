"""`conav reproduce` (eval/cli/reproduce*.py): the stages and their steps' calls,
the runner skipping what is done and resuming after a failure, tables rendered from results."""

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conav_jax.eval import cli
from conav_jax.eval.cli import reproduce_plan as rp
from conav_jax.eval.cli import reproduce_progress as rpp
from conav_jax.eval.cli import reproduce_run as rr
from conav_jax.eval.cli import reproduce_steps as rs
from conav_jax.eval.cli import reproduce_tables as rt
from conav_jax.models.policy import PolicyConfig
from conav_jax.train.policy import POLICY_TRAIN

METRICS = ("FASR", "RASR", "FASPL", "RASPL", "CR", "AS")


def _metrics(values, lo=None, hi=None):
    return {m: {"value": v, "lo": v - 1 if lo is None else lo, "hi": v + 1 if hi is None else hi}
            for m, v in zip(METRICS, values)}


def _eval_doc(agents: dict, ablations: dict | None = None, episodes: int = 100) -> dict:
    def entry(key, values):
        return {"agent": key, "title": f"T {key}", "intention_source": "none", "privileged": ["oracle map"],
                "metrics": _metrics(values)}

    return {"episodes": episodes, "agents": {k: entry(k, v) for k, v in agents.items()},
            "ablations": {f"ablation_{k}": entry("conav", v) for k, v in (ablations or {}).items()}}


def _kw(step) -> dict:
    return step.call.kwargs


def _trained(stage) -> list:
    return [s for s in stage.steps if s.call.kind.startswith("train")]


def _model(step):
    """The PolicyConfig a step trains (None for other steps)."""
    model = _kw(step).get("model", _kw(step).get("policy_config"))
    return model if isinstance(model, PolicyConfig) else None


def test_plan_lists_every_stage_and_the_paper_preset_records_a_subset_of_episodes(tmp_path):
    stages = rp.plan_stages(rp.ReproduceConfig(out=tmp_path, preset="paper", seeds=2))
    assert [s.name for s in stages] == list(rp.STAGES)
    bc_stage = {s.name: s for s in stages}["bc"].steps
    bc = bc_stage[::2]
    assert len(bc) == 2 * len(rp.ABLATIONS) and all(s.call.kind == "train policy" for s in bc)
    assert all(_kw(s)["imitation"].episodes and _kw(s)["imitation"].train_intentions == "predicted" for s in bc)
    # Each run is evaluated on val right after it trains (its checkpoint need not travel on).
    for train, evaluate in zip(bc, bc_stage[1::2]):
        out = _kw(train)["run_dir"]
        assert evaluate.call.kind == "eval" and _kw(evaluate)["checkpoint"] == out
        assert _kw(evaluate)["out"].endswith("eval/conav_" + out.rsplit("/", 1)[1])
    dagger = {s.name: s for s in stages}["dagger"].steps
    assert dagger[0].call == rs.Call("copy", {"source": str(tmp_path / "runs" / "bc_all_s0"),
                                              "target": str(tmp_path / "runs" / "dagger_s0")})
    # The paper preset trains the policy with its CNN in bfloat16; the small preset's configs
    # stay as its runs were made, so they resume.
    for step in (*bc, *dagger[1::2]):
        assert _model(step).conv_dtype == "bfloat16"
    small = rp.plan_stages(rp.ReproduceConfig(out=tmp_path, preset="small", seeds=1))
    assert not any(_model(s) and _model(s).conv_dtype != "float32" for st in small for s in st.steps)
    # At 112x448 every policy run rematerialises its CNN (the faster update there); at 32x128
    # the configs stay as the published runs were made.
    assert all(_kw(s)["remat"] for s in (*bc, *dagger[1::2]))
    low = rp.plan_stages(rp.ReproduceConfig(out=tmp_path, preset="paper", resolution=(32, 128)))
    assert not any(_kw(s).get("remat") for st in low for s in st.steps)
    # There DAgger rounds record a subset of the train episodes each (their windows stay on the GPU).
    for step in dagger[1::2]:
        assert _kw(step)["imitation"].dagger_episodes == rp.LARGE_PANORAMA_DAGGER_EPISODES
    assert not any(_kw(s)["imitation"].dagger_episodes for st in low for s in st.steps if "imitation" in _kw(s))
    # The paper preset's baselines record a subset of its 20,293 train episodes (at 112x448 as
    # many as the policy, with its CNN and DAgger subsets), and its imitation runs validate on the
    # 1,000 minival episodes less often; the small preset's configs as run.
    policy_cnn = {k: getattr(_model(bc[0]), k) for k in ("conv_dtype", "conv_channels", "conv_kernels", "conv_strides")}
    for step in {s.name: s for s in stages}["baselines"].steps:
        assert _kw(step)["imitation"].episodes == _kw(bc[0])["imitation"].episodes == 400
        assert _kw(step)["imitation"].dagger_episodes == rp.LARGE_PANORAMA_DAGGER_EPISODES
        assert {k: getattr(_model(step), k) for k in policy_cnn} == policy_cnn and _kw(step)["remat"]
    for step in {s.name: s for s in low}["baselines"].steps:
        assert _kw(step)["imitation"].episodes == 1000
        assert _model(step).conv_dtype == "float32" and not _kw(step)["remat"]
        assert _kw(step)["imitation"].dagger_episodes is None
    for step in (*{s.name: s for s in stages}["baselines"].steps, *bc, *dagger[1::2]):
        assert _kw(step)["cfg"].val_every == 1000
    small_as_run = rp.plan_stages(rp.ReproduceConfig(out=tmp_path, preset="small", seeds=1, resolution=(32, 128)))
    assert not any(_kw(s)["cfg"].val_every != POLICY_TRAIN.val_every or s.call.kind != "train policy"
                   and _kw(s)["imitation"].episodes for st in small_as_run for s in st.steps if "imitation" in _kw(s))
    # The intention predictor crops from the panorama the agents render.
    for res in ((112, 448), (32, 128)):
        (intention,) = [s for s in rp.plan_stages(rp.ReproduceConfig(out=tmp_path, resolution=res))[1].steps
                        if s.call.kind == "train intention"]
        assert _kw(intention)["data"].resolution == res
    with pytest.raises(ValueError, match="ReproduceConfig.seeds must be at least 1"):
        rp.ReproduceConfig(out=tmp_path, seeds=0)


def test_the_predictors_options_reach_its_training_call_alone(tmp_path, capsys):
    plain = rp.plan_stages(rp.ReproduceConfig(out=tmp_path, preset="small"))
    both = rp.plan_stages(rp.ReproduceConfig(out=tmp_path, preset="small", mirror=True, recolour=True,
                                             seen_objects=True))
    (intention,) = [s for s in both[1].steps if s.call.kind == "train intention"]
    assert _kw(intention)["data"].mirror and _kw(intention)["data"].recolour and _kw(intention)["model"].seen_objects
    changed = [a for s0, s1 in zip(plain, both) for a, b in zip(s0.steps, s1.steps) if a != b]
    assert changed == [dataclasses.replace(intention, call=rs.Call(intention.call.kind, {
        **_kw(intention), "data": dataclasses.replace(_kw(intention)["data"], mirror=False, recolour=False),
        "model": dataclasses.replace(_kw(intention)["model"], seen_objects=False)}))]
    assert cli.main(["--compile-cache", "off", "reproduce", "--preset", "tiny", "--seeds", "1", "--out",
                     str(tmp_path / "out"), "--mirror", "--recolour", "--seen-objects", "--dry-run"]) == 0
    printed = capsys.readouterr().out
    assert printed.count("mirror=True") == printed.count("recolour=True") == printed.count("seen_objects=True") == 1


def test_the_patch_encoder_reaches_every_policy_run_and_the_tables_name_it(tmp_path, capsys):
    from conav_jax.models.policy import encoder_config

    plain = {s.name: s for s in rp.plan_stages(rp.ReproduceConfig(out=tmp_path, preset="small", seeds=1))}
    patch = {s.name: s for s in rp.plan_stages(rp.ReproduceConfig(out=tmp_path, preset="small", seeds=1,
                                                                  encoder="patch"))}
    policy_runs = [s for name in ("baselines", "bc", "dagger") for s in _trained(patch[name])]
    # the learned baselines (each of its three seeds) share the policy's CNN
    assert len(policy_runs) == 2 * 3 + len(rp.ABLATIONS) + 1
    for step in policy_runs:
        assert _model(step).conv_strides == (4, 2, 2)
    # Nothing else changes: the default's configs are those of the published runs.
    assert not any(_model(s) and _model(s).conv_strides for st in plain.values() for s in st.steps)
    as_conv = lambda s: dataclasses.replace(s, call=rs.Call(s.call.kind, {  # noqa: E731
        **_kw(s), "model": encoder_config(_model(s), "conv")})) if _model(s) else s
    for name in plain:
        assert [as_conv(s) for s in patch[name].steps] == list(plain[name].steps)
    with pytest.raises(ValueError, match="unknown ReproduceConfig.encoder 'resnet'"):
        rp.ReproduceConfig(out=tmp_path, encoder="resnet")
    # The command line passes it on.
    assert cli.main(["--compile-cache", "off", "reproduce", "--preset", "tiny", "--seeds", "1", "--out",
                     str(tmp_path / "out"), "--encoder", "patch", "--dry-run"]) == 0
    assert capsys.readouterr().out.count("conv_strides=(4, 2, 2)") == len(policy_runs)
    results = {"preset": "small", "seeds": 1, "resolution": "112x448", "agents": {}, "conav": {}}
    assert "encoder" not in rt.render_tables(results)  # results.json files written before the key
    assert "panorama 112x448 (the CoNav policy's panorama encoder: `patch`);" in rt.render_tables({**results, "encoder": "patch"})


def test_learned_cells_are_the_mean_and_sd_with_the_t_interval_over_seeds():
    row = {"title": "CoNav", "privileged": [], "seeds": {
        "0": {"metrics": _metrics((10, 20, 5, 6, 30, 100)), "episodes": 100},
        "1": {"metrics": _metrics((20, 30, 7, 8, 10, 200)), "episodes": 100}}}
    # FASR: mean 15, sd sqrt(50) = 7.07; t(0.975, 1 df) = 12.706: 15 ± 12.706 * 7.07 / sqrt(2).
    assert rt._learned_cell(row, "FASR") == "15.0 ± 7.1 [-48.5, 78.5] (n=2)"
    assert rt._learned_cell(row, "AS") == "150.0 ± 70.7 [-485.3, 785.3] (n=2)"
    one = {**row, "seeds": {"0": row["seeds"]["0"]}}
    assert rt._learned_cell(one, "FASR") == "10.0 (1 seed)"


def test_tables_compare_rows_seed_by_seed_with_their_reference():
    def row(*fasr_rasr):
        return {"title": "CoNav", "privileged": [], "seeds": {
            str(s): {"metrics": _metrics((f, r, 0, 0, 0, 0)), "episodes": 100} for s, (f, r) in enumerate(fasr_rasr)}}

    results = {"seeds": 3, "agents": {}, "conav": {
        "none": row((10, 20), (14, 22), (12, 30)), "object": row((13, 20), (15, 25), (18, 30)),
        "all": row((20, 30), (10, 20)), "dagger": row((26, 31), (13, 20), (30, 30))}}
    lines = rt.render_tables(results).splitlines()
    # object - none: +3, +1, +6 (mean 3.33, sd 2.52, t(0.975, 2 df) = 4.303); RASR 0, +3, 0.
    assert ("| object | none | s0 13.0 / s1 15.0 / s2 18.0 | +3.0 / +1.0 / +6.0 | +3.3 ± 2.5 [-2.9, +9.6] (n=3) | "
            "s0 20.0 / s1 25.0 / s2 30.0 | +0.0 / +3.0 / +0.0 | +1.0 ± 1.7 [-3.3, +5.3] (n=3) |") in lines
    # all holds two seeds: compared on those only.
    assert any(line.startswith("| all | none | s0 20.0 / s1 10.0 | +10.0 / -4.0 | +3.0 ± 9.9 [-85.9, +91.9] (n=2) |")
               for line in lines)
    # DAgger rows against BC with all inputs, on the seeds both hold.
    assert any(line.startswith("| dagger | all | s0 26.0 / s1 13.0 / s2 30.0 | +6.0 / +3.0 | +4.5 ± 2.1 [-14.6, +23.6]"
                               " (n=2) |") for line in lines)
    assert not any(line.startswith("| activity |") for line in lines)  # not run: no row
    assert "Seed by seed" not in rt.render_tables({**results, "conav": {"none": results["conav"]["none"]}})


def test_a_contrast_whose_interval_excludes_zero_is_marked_resolved():
    fasr = {"none": (10, 12, 9, 11, 10, 13, 8, 12), "all": (15, 18, 13, 16, 17, 18, 14, 16)}  # +5 +6 +4 +5 +7 +5 +6 +4
    results = {"seeds": 8, "agents": {}, "conav": {name: {"title": "CoNav", "privileged": [], "seeds": {
        str(s): {"metrics": _metrics((f, f, 0, 0, 0, 0)), "episodes": 100} for s, f in enumerate(v)}}
        for name, v in fasr.items()}}
    line = next(line for line in rt.render_tables(results).splitlines() if line.startswith("| all | none |"))
    assert "| +5.2 ± 1.0 [+4.4, +6.1] (n=8) resolved |" in line


def test_tables_put_ours_beside_the_papers_and_name_privileged_inputs():
    results = {
        "preset": "small", "seeds": 1, "resolution": "32x128", "episodes": 100, "commit": "abc1234",
        "agents": {"random": {"title": "Random Agent", "intention_source": "none", "privileged": [],
                              "metrics": _metrics((1, 2, 3, 4, 5, 6))},
                   "expert": {"title": "Imitation expert", "intention_source": "none", "privileged": ["oracle map"],
                              "metrics": {**_metrics((90, 95, 80, 85, 2, 70)),
                                          "CR_full": {"value": 37.0, "lo": 33.0, "hi": 41.0}}}},
        "conav": {"all": {"title": "CoNav Agent", "intention_source": "predicted", "privileged": ["oracle segmentation"],
                          "seeds": {"0": {"metrics": _metrics((12, 13, 14, 15, 16, 17)), "episodes": 100}}}},
    }
    md = rt.render_tables(results)
    lines = md.splitlines()
    assert "| agent | given (privileged inputs) | source | FASR | RASR | FASPL | RASPL | CR | CR_full | AS |" in lines
    # CR_full beside CR: "-" where a row (or the paper) has none.
    assert "| Random Agent | none | ours | 1.0 | 2.0 | 3.0 | 4.0 | 5.0 | - | 6.0 |" in lines
    assert "| Random Agent | | paper | 4.5 | 4.6 | 3.7 | 3.7 | 32.7 | - | 442.6 |" in lines
    assert "| Imitation expert | oracle map | ours | 90.0 | 95.0 | 80.0 | 85.0 | 2.0 | 37.0 | 70.0 |" in lines
    assert any(line.startswith("| CoNav Agent (BC) | oracle segmentation | ours | 12.0 (1 seed) |") for line in lines)
    assert "| 5 | ✓ | ✓ | ✓ | paper | 19.8 | 23.2 | 13.5 | 14.9 | 20.1 | - | 354.5 |" in lines
    assert "commit abc1234" in md


def _write_eval(path: Path, doc: dict) -> None:
    path.mkdir(parents=True, exist_ok=True)
    (path / "metrics.json").write_text(json.dumps(doc))


def test_a_seed_without_its_dagger_run_adds_to_the_bc_rows_only_and_the_tables_say_so(tmp_path):
    evals = tmp_path / "eval"
    for name, agent in (("scripted", "random"), ("objectgoal-oracle", "objectgoal-oracle"),
                        ("objectgoal-predicted", "objectgoal-predicted"), ("imagegoal", "imagegoal")):
        _write_eval(evals / name, _eval_doc({agent: (1, 2, 3, 4, 5, 6)}))
    _write_eval(evals / rp.BC_EVAL.format(0), _eval_doc({"conav": (10, 20, 5, 6, 30, 100)},
                                                         {a: (10, 20, 5, 6, 30, 100) for a in rp.ABLATIONS}))
    _write_eval(evals / rp.DAGGER_EVAL.format(0), _eval_doc({"conav": (40, 50, 5, 6, 30, 100)}))
    # Seed 1 has BC runs only, each evaluated on its own (seed 0's five in one evaluation, as
    # runs made before that did): its all-inputs run is no DAgger row.
    for a in rp.ABLATIONS:
        _write_eval(evals / rp.BC_ROW_EVAL.format(row=a, seed=1), _eval_doc({"conav": (20, 30, 7, 8, 10, 200)}))
    results = rt.collect_results(tmp_path, 2, {"seeds": 2})
    assert set(results["conav"]["dagger"]["seeds"]) == {"0"}
    assert all(set(results["conav"][a]["seeds"]) == {"0", "1"} for a in rp.ABLATIONS)
    lines = rt.render_tables(results).splitlines()
    # One seed: its value, no spread and no interval; the source names the seed.
    assert any(line.startswith("| T conav (BC + DAgger) | oracle map | ours (seed 0 of 2) | 40.0 (1 seed) |")
               for line in lines)
    assert any(line.startswith("| T conav (BC) | oracle map | ours | 15.0 ± 7.1 [") for line in lines)
    assert any(line.startswith("| 1 | ✗ | ✗ | ✗ | ours | 15.0 ± 7.1 [") for line in lines)
    assert results["missing"] == ["eval/conav_dagger_s1"] and "## Not run yet" in rt.render_tables(results)
    # Evaluations not made yet are listed, their rows marked; the learned rows name their seeds.
    (evals / rp.BC_ROW_EVAL.format(row="none", seed=1) / "metrics.json").unlink()
    (evals / "imagegoal" / "metrics.json").unlink()
    results = rt.collect_results(tmp_path, 2, {"seeds": 2})
    assert results["missing"] == ["eval/imagegoal", "eval/conav_bc_none_s1", "eval/conav_dagger_s1"]
    assert set(results["conav"]["activity"]["seeds"]) == {"0", "1"}
    lines = rt.render_tables(results).splitlines()
    assert "| imagegoal | | not run yet | - | - | - | - | - | - | - |" in lines and "- `eval/imagegoal`" in lines
    assert any(line.startswith("| 1 | ✗ | ✗ | ✗ | ours (seed 0 of 2) | 10.0 (1 seed) |") for line in lines)
    (evals / rp.DAGGER_EVAL.format(0) / "metrics.json").unlink()
    (evals / rp.BC_EVAL.format(0) / "metrics.json").unlink()
    for a in rp.ABLATIONS[1:]:
        (evals / rp.BC_ROW_EVAL.format(row=a, seed=1) / "metrics.json").unlink()
    lines = rt.render_tables(rt.collect_results(tmp_path, 2, {"seeds": 2})).splitlines()
    assert "| CoNav Agent (BC + DAgger) | | not run yet | - | - | - | - | - | - | - |" in lines
    assert "| 5 | ✓ | ✓ | ✓ | not run yet | - | - | - | - | - | - | - |" in lines
    (evals / "scripted" / "metrics.json").unlink()
    assert "eval/scripted" in rt.collect_results(tmp_path, 2, {"seeds": 2})["missing"]
    for made in evals.glob("*/metrics.json"):
        made.unlink()
    with pytest.raises(FileNotFoundError, match="no evaluation under"):
        rt.collect_results(tmp_path, 2, {"seeds": 2})


def test_each_learned_baseline_trains_and_is_tabulated_over_its_own_seeds(tmp_path):
    runs, evals = tmp_path / "runs", tmp_path / "eval"
    plan = {s.name: s for s in rp.plan_stages(rp.ReproduceConfig(out=tmp_path, preset="tiny", seeds=1,
                                                                 baseline_seeds=3))}
    trained = [(s.call.kind, _kw(s)["run_dir"], _kw(s)["cfg"].seed, s.seed) for s in plan["baselines"].steps]
    # Seed 0 keeps the names OUT directories made with one seed have, so they continue as they are.
    assert trained == [(f"train {k}", str(runs / (k if s == 0 else f"{k}_s{s}")), s, s)
                       for s in range(3) for k in ("objectnav", "imagenav")]
    baseline_evals = {_kw(s)["out"]: (_kw(s)["checkpoint"], s.seed) for s in plan["eval"].steps
                      if _kw(s)["agents"][0] in rp.LEARNED_BASELINES}
    assert baseline_evals[str(evals / "imagegoal_s2")] == (str(runs / "imagenav_s2"), 2)
    assert baseline_evals[str(evals / "objectgoal-predicted")] == (str(runs / "objectnav"), 0)
    assert len(baseline_evals) == 9 and str(evals / "objectgoal-oracle_s1") in baseline_evals
    with pytest.raises(ValueError, match="ReproduceConfig.baseline_seeds must be at least 1"):
        rp.ReproduceConfig(out=tmp_path, baseline_seeds=0)

    _write_eval(evals / "scripted", _eval_doc({"random": (1, 2, 3, 4, 5, 6)}))
    _write_eval(evals / rp.BC_ROW_EVAL.format(row="all", seed=0), _eval_doc({"conav": (10, 20, 5, 6, 30, 100)}))
    for s, fasr in ((0, 10), (1, 20), (2, 30)):
        _write_eval(evals / rp.baseline_name("objectgoal-oracle", s),
                    _eval_doc({"objectgoal-oracle": (fasr, 40, 5, 6, 30, 100)}))
    _write_eval(evals / "imagegoal_s1", _eval_doc({"imagegoal": (7, 8, 5, 6, 30, 100)}))
    results = rt.collect_results(tmp_path, 1, {"seeds": 1, "baseline_seeds": 3}, baseline_seeds=3)
    assert set(results["agents"]["objectgoal-oracle"]["seeds"]) == {"0", "1", "2"}
    assert {"eval/imagegoal", "eval/imagegoal_s2", "eval/objectgoal-predicted_s1"} <= set(results["missing"])
    lines = rt.render_tables(results).splitlines()
    # mean 20, sd 10, t(0.975, 2 df) = 4.303: 20 ± 4.303 * 10 / sqrt(3) = 20 ± 24.8
    assert any(line.startswith("| T objectgoal-oracle | oracle map | ours | 20.0 ± 10.0 [-4.8, 44.8] (n=3) |")
               for line in lines)
    assert any(line.startswith("| T imagegoal | oracle map | ours (seed 1 of 3) | 7.0 (1 seed) |") for line in lines)
    assert "| objectgoal-predicted | | not run yet | - | - | - | - | - | - | - |" in lines
    # Results made with one baseline seed read as before.
    one = rt.collect_results(tmp_path, 1, {"seeds": 1})
    assert set(one["agents"]["objectgoal-oracle"]["seeds"]) == {"0"} and "eval/imagegoal_s1" not in one["missing"]


def test_dagger_with_the_expert_mixed_in_runs_under_its_own_name_and_the_tables_show_every_variant(tmp_path):
    runs, evals = tmp_path / "runs", tmp_path / "eval"
    plan = {s.name: s for s in rp.plan_stages(rp.ReproduceConfig(out=tmp_path, preset="tiny", seeds=2, dagger_beta=0.5))}
    copy, train = plan["dagger"].steps[:2]
    assert _kw(copy) == {"source": str(runs / "bc_all_s0"), "target": str(runs / "dagger_beta0.5_s0")}
    assert _kw(train)["imitation"].dagger_beta == 0.5 and _kw(train)["run_dir"] == str(runs / "dagger_beta0.5_s0")
    last = _kw(plan["eval"].steps[-1])
    assert (last["checkpoint"], last["out"]) == (str(runs / "dagger_beta0.5_s1"), str(evals / "conav_dagger_beta0.5_s1"))
    # The policy-alone runs keep their configs (and so their progress.json records).
    plain = {s.name: s for s in rp.plan_stages(rp.ReproduceConfig(out=tmp_path, preset="tiny", seeds=2))}
    plain_train = _kw(plain["dagger"].steps[1])
    assert plain_train["imitation"].dagger_beta == 0.0 and plain_train["run_dir"] == str(runs / "dagger_s0")
    with pytest.raises(ValueError, match="ReproduceConfig.dagger_beta is a probability"):
        rp.ReproduceConfig(out=tmp_path, dagger_beta=1.5)

    _write_eval(evals / "scripted", _eval_doc({"random": (1, 2, 3, 4, 5, 6)}))
    for s in (0, 1):
        _write_eval(evals / rp.BC_EVAL.format(s), _eval_doc({"conav": (10, 20, 5, 6, 30, 100)},
                                                             {a: (10, 20, 5, 6, 30, 100) for a in rp.ABLATIONS}))
        _write_eval(evals / f"conav_dagger_beta0.5_s{s}", _eval_doc({"conav": (30 + s, 40, 5, 6, 20, 100)}))
    _write_eval(evals / rp.DAGGER_EVAL.format(0), _eval_doc({"conav": (5, 50, 5, 6, 30, 100)}))
    (evals / "conav_daggerish_s0").mkdir()  # not a DAgger row's evaluation
    mixed = rt.collect_results(tmp_path, 2, {"seeds": 2}, dagger="dagger_beta0.5")
    assert [k for k in mixed["conav"] if k.startswith("dagger")] == ["dagger", "dagger_beta0.5"]
    assert set(mixed["conav"]["dagger_beta0.5"]["seeds"]) == {"0", "1"}
    # Only the run's own variant can be missing; the other is shown with the seeds it has.
    assert mixed["missing"] == ["eval/objectgoal-oracle", "eval/objectgoal-predicted", "eval/imagegoal"]
    lines = rt.render_tables(mixed).splitlines()
    assert any(line.startswith("| T conav (BC + DAgger) | oracle map | ours (seed 0 of 2) | 5.0 (1 seed) |") for line in lines)
    assert any(line.startswith("| T conav (BC + DAgger, the expert acting at 0.5^r of round r's steps) | oracle map | "
                               "ours | 30.5 ± 0.7 [") for line in lines)
    assert "eval/conav_dagger_s1" in rt.collect_results(tmp_path, 2, {"seeds": 2})["missing"]


def test_another_dagger_round_count_runs_under_its_own_name_and_its_row_says_so(tmp_path):
    runs, evals = tmp_path / "runs", tmp_path / "eval"
    cfg = rp.ReproduceConfig(out=tmp_path, preset="paper", seeds=1, dagger_beta=0.5, dagger_rounds=1)
    assert (cfg.rounds, cfg.dagger) == (1, "dagger_beta0.5_rounds1")
    train = _kw({s.name: s for s in rp.plan_stages(cfg)}["dagger"].steps[1])
    assert train["imitation"].dagger_rounds == 1 and train["run_dir"] == str(runs / "dagger_beta0.5_rounds1_s0")
    # The preset's own count names no rounds: the runs made before the option keep their names.
    same = rp.ReproduceConfig(out=tmp_path, preset="paper", dagger_rounds=rp.BUDGETS["paper"].dagger_rounds)
    assert same.dagger == "dagger" and rp.dagger_row(0.0, 3) == "dagger_rounds3"
    assert rp.dagger_variant("dagger_beta0.5_rounds1") == (0.5, 1, None) and rp.dagger_variant("daggerish") is None
    # Every share a row can be named by reads back, however `:g` writes it.
    assert all(rp.dagger_variant(rp.dagger_row(b, 2)) == (b, 2, None) for b in (1.0, 0.25, 1e-05))
    assert rp.dagger_variant("dagger_beta1e-05.") is None
    with pytest.raises(ValueError, match="ReproduceConfig.dagger_rounds must be at least 1"):
        rp.ReproduceConfig(out=tmp_path, dagger_rounds=0)

    _write_eval(evals / "scripted", _eval_doc({"random": (1, 2, 3, 4, 5, 6)}))
    for row, fasr in (("dagger", 5), ("dagger_beta0.5_rounds1", 25), ("dagger_beta0.5", 20), ("dagger_rounds1", 8)):
        _write_eval(evals / f"conav_{row}_s0", _eval_doc({"conav": (fasr, 40, 5, 6, 20, 100)}))
    results = rt.collect_results(tmp_path, 1, {"seeds": 1}, dagger=cfg.dagger)
    # By share, then round count, the preset's first.
    assert [k for k in results["conav"] if k.startswith("dagger")] == [
        "dagger", "dagger_rounds1", "dagger_beta0.5", "dagger_beta0.5_rounds1"]
    lines = rt.render_tables(results).splitlines()
    assert any(line.startswith("| T conav (BC + DAgger, 1 round) | oracle map | ours | 8.0 (1 seed) |") for line in lines)
    assert any(line.startswith("| T conav (BC + DAgger, the expert acting at 0.5^r of round r's steps, 1 round) | "
                               "oracle map | ours | 25.0 (1 seed) |") for line in lines)
    (evals / "conav_dagger_beta0.5_rounds1_s0" / "metrics.json").unlink()
    assert rt.collect_results(tmp_path, 1, {"seeds": 1}, dagger=cfg.dagger)["missing"][-1] == \
        "eval/conav_dagger_beta0.5_rounds1_s0"


def test_another_dagger_episode_count_runs_under_its_own_name_and_the_baselines_keep_the_default(tmp_path):
    runs, evals = tmp_path / "runs", tmp_path / "eval"
    cfg = rp.ReproduceConfig(out=tmp_path, preset="paper", seeds=1, dagger_beta=0.5, dagger_rounds=1, dagger_episodes=200)
    assert cfg.dagger == "dagger_beta0.5_rounds1_episodes200"
    plan = {s.name: s for s in rp.plan_stages(cfg)}
    train = _kw(plan["dagger"].steps[1])
    assert train["imitation"].dagger_episodes == 200 and train["run_dir"] == str(runs / f"{cfg.dagger}_s0")
    for step in plan["baselines"].steps:  # the CoNav DAgger rows' option alone
        assert _kw(step)["imitation"].dagger_episodes == rp.LARGE_PANORAMA_DAGGER_EPISODES
    # The resolution's own count names none: the runs made before the option keep their names.
    assert rp.ReproduceConfig(out=tmp_path, dagger_episodes=rp.LARGE_PANORAMA_DAGGER_EPISODES).dagger == "dagger"
    small = rp.ReproduceConfig(out=tmp_path, preset="paper", resolution=(32, 128), dagger_episodes=100)
    assert small.dagger == "dagger_episodes100"
    assert _kw({s.name: s for s in rp.plan_stages(
        dataclasses.replace(small, dagger_episodes=None))}["dagger"].steps[1])["imitation"].dagger_episodes is None
    assert rp.dagger_variant(cfg.dagger) == (0.5, 1, 200) and rp.dagger_variant("dagger_episodes") is None
    with pytest.raises(ValueError, match="ReproduceConfig.dagger_episodes must be at least 1"):
        rp.ReproduceConfig(out=tmp_path, dagger_episodes=0)

    _write_eval(evals / "scripted", _eval_doc({"random": (1, 2, 3, 4, 5, 6)}))
    for row, fasr in (("dagger_beta0.5_rounds1_episodes200", 25), ("dagger_beta0.5_rounds1", 20)):
        _write_eval(evals / f"conav_{row}_s0", _eval_doc({"conav": (fasr, 40, 5, 6, 20, 100)}))
    results = rt.collect_results(tmp_path, 1, {"seeds": 1}, dagger=cfg.dagger)
    assert [k for k in results["conav"] if k.startswith("dagger")] == [
        "dagger_beta0.5_rounds1", "dagger_beta0.5_rounds1_episodes200"]
    assert any(line.startswith("| T conav (BC + DAgger, the expert acting at 0.5^r of round r's steps, 1 round, 200 "
                               "train episodes a round) | oracle map | ours | 25.0 (1 seed) |")
               for line in rt.render_tables(results).splitlines())


@dataclasses.dataclass(frozen=True)
class Made:
    """A step's call as the fake library functions saw it: its kind, the directory it wrote and
    its keywords but the mesh (not compared)."""

    kind: str
    out: str
    kwargs: dict = dataclasses.field(compare=False, hash=False)


@pytest.fixture
def fake_conav(monkeypatch):
    """The library functions of the steps (but copies) replaced by a recorder that writes what the
    real ones would: a run's log, an evaluation's metrics.json. `fail_on` makes one step fail (a
    cut-off run), `term_on` stops the process as `timeout` does."""
    calls, state = [], {"fail_on": None, "term_on": None}

    def fake(kind, mesh=None, **kwargs):
        out = Path(kwargs.get("run_dir") or kwargs.get("out_dir") or kwargs["out"])
        calls.append(Made(kind, str(out), kwargs))
        if state["fail_on"] is not None and any(state["fail_on"] in str(v) for v in kwargs.values()):
            state["fail_on"] = None
            raise RuntimeError("the step failed")
        if state["term_on"] is not None and any(state["term_on"] in str(v) for v in kwargs.values()):
            state["term_on"] = None
            os.kill(os.getpid(), signal.SIGTERM)  # as `timeout` stops a run
            time.sleep(5)
        out.mkdir(parents=True, exist_ok=True)
        if kind == "eval":
            (out / "metrics.json").write_text(json.dumps(_eval_doc({a: (1, 2, 3, 4, 5, 6) for a in kwargs["agents"]})))
        else:
            (out / ("manifest.json" if kind == "generate" else "log.jsonl")).write_text("{}\n")

    real = rs.step_function
    monkeypatch.setattr(rs, "step_function", lambda kind: real(kind) if kind == "copy" else
                        (lambda **kwargs: fake(kind, **kwargs)))
    return calls, state


def _reproduce(out, *extra):
    args = cli.build_parser().parse_args(["reproduce", "--preset", "tiny", "--seeds", "2", "--out", str(out), *extra])
    return args.func(args)


def test_a_step_calls_its_library_function_not_a_command_line(tmp_path, monkeypatch):
    """Each step calls its kind's library function itself with its declared keywords (and the mesh
    of every visible device where the function takes one): no `conav` command runs."""
    import conav_jax.data.episodes as episodes
    import conav_jax.train.intention as intention
    import conav_jax.train.trajectory as trajectory

    def no_command(*args, **kwargs):
        raise AssertionError("a step went through the command line")

    got = []

    def library(name, made):
        def function(*args, **kwargs):
            got.append((name, args, kwargs))
            out = Path(kwargs.get("run_dir") or kwargs["out_dir"])
            out.mkdir(parents=True, exist_ok=True)
            (out / made).write_text("{}\n")
        return function

    monkeypatch.setattr(cli, "main", no_command)
    monkeypatch.setattr(episodes, "generate_dataset", library("generate_dataset", "manifest.json"))
    monkeypatch.setattr(intention, "train_intention_from_data", library("train_intention_from_data", "log.jsonl"))
    monkeypatch.setattr(trajectory, "train_trajectory_from_data", library("train_trajectory_from_data", "log.jsonl"))
    out = tmp_path / "r"
    assert _reproduce(out, "--stage", "predictors") == 0  # the data first, then the predictors
    plan = rp.plan_stages(rp.ReproduceConfig(out=out, preset="tiny", seeds=2, workers=min(2, os.cpu_count() or 1)))
    assert [name for name, _, _ in got] == ["generate_dataset", "train_intention_from_data", "train_trajectory_from_data"]
    for step, (_, args, kwargs) in zip((*plan[0].steps, *plan[1].steps), got):
        mesh = kwargs.pop("mesh", None)
        assert args == () and kwargs == _kw(step)
        assert (mesh is not None) == rs.STEP_KINDS[step.call.kind].mesh


def test_a_run_cut_short_resumes_where_it_stopped_and_gives_the_same_results(fake_conav, tmp_path):
    calls, state = fake_conav
    assert _reproduce(tmp_path / "a") == 0
    straight = list(calls)
    results = json.loads((tmp_path / "a" / "results.json").read_text())
    assert set(results["conav"]) == set(rp.ABLATIONS) | {"dagger"} and set(results["conav"]["all"]["seeds"]) == {"0", "1"}

    calls.clear()
    state["fail_on"] = "bc_object_s1"  # the run is cut during the bc stage
    assert _reproduce(tmp_path / "b") == 1
    first = list(calls)
    calls.clear()
    assert _reproduce(tmp_path / "b") == 0
    # Nothing done before the cut runs again; the cut command and everything after it does.
    done_before = first[:-1]
    assert not set(done_before) & set(calls)
    assert calls[0] == first[-1]
    assert len(done_before) + len(calls) == len(straight)
    resumed = json.loads((tmp_path / "b" / "results.json").read_text())
    for doc in (results, resumed):
        for key in ("command", "stage_seconds", "command_seconds", "cut_seconds"):
            doc.pop(key)
    assert json.dumps(resumed, sort_keys=True).replace("/b/", "/a/") == json.dumps(results, sort_keys=True)
    # Everything done: a third call runs nothing.
    calls.clear()
    assert _reproduce(tmp_path / "b") == 0 and calls == []


def test_a_command_cut_short_counts_its_time_in_its_stage(fake_conav, tmp_path, monkeypatch):
    calls, state = fake_conav
    out = tmp_path / "r"
    state["term_on"] = "bc_none_s0"
    handler = signal.getsignal(signal.SIGTERM)
    with pytest.raises(KeyboardInterrupt):
        _reproduce(out)
    assert signal.getsignal(signal.SIGTERM) == handler  # the command's own handler is gone
    plan = rp.plan_stages(rp.ReproduceConfig(out=out, preset="tiny", seeds=2))
    cut_key = {s.name: s for s in plan}["bc"].steps[0].name
    assert "bc_none_s0" in cut_key
    progress = rpp.read_progress(out)
    assert progress["cut"][cut_key] >= 0.0 and cut_key not in progress["commands"]
    progress["cut"][cut_key] = 300.0  # what the cut attempt took
    rpp.write_progress(out, progress)
    state["fail_on"] = "bc_none_s0"  # a second attempt fails: its time adds up
    assert _reproduce(out) == 1
    assert 300.0 <= rpp.read_progress(out)["cut"][cut_key] < 310.0
    assert _reproduce(out) == 0
    results = json.loads((out / "results.json").read_text())
    bc = [step.name for step in {s.name: s for s in plan}["bc"].steps]
    assert results["cut_seconds"] == rpp.read_progress(out)["cut"]
    assert results["stage_seconds"]["bc"] == pytest.approx(
        sum(results["command_seconds"][k] for k in bc) + results["cut_seconds"][cut_key], abs=0.2)


def test_the_pack_holds_progress_results_and_the_runs_still_needed(fake_conav, tmp_path):
    from conav_jax.checkpoints import checkpoint_path, save_checkpoint

    calls, state = fake_conav
    state["fail_on"] = "dagger_s0"
    out = tmp_path / "r"
    assert _reproduce(out) == 1  # cut in the dagger stage: the runs it continues and the predictors are still needed
    for run in ("intention", "trajectory", "bc_all_s1", "bc_none_s0"):
        save_checkpoint(checkpoint_path(out / "runs" / run, 5), params={"w": [1.0]}, opt_state=None,
                        config={"kind": "policy"}, step=5)
    assert _reproduce(out, "--stage", "pack") == 0
    import tarfile

    names = set(tarfile.open(out / "pack.tar").getnames())
    assert "progress.json" in names and "runs/bc_all_s1/ckpt_00000005.npz" in names
    assert "runs/intention/ckpt_00000005.npz" in names
    assert "runs/bc_none_s0/ckpt_00000005.npz" not in names  # evaluated: no stage reads it again
    assert "eval/conav_bc_none_s0/metrics.json" in names
    fresh = tmp_path / "fresh"
    assert _reproduce(fresh, "--unpack", str(out / "pack.tar"), "--dry-run") == 0
    assert (fresh / "runs" / "bc_all_s1" / "ckpt_00000005.npz").is_file()
    (tmp_path / "junk.tar").write_text("not a tar")
    with pytest.raises(ValueError, match="not a pack"):
        rr.unpack(tmp_path / "junk.tar", tmp_path / "junk")
    with pytest.raises(FileNotFoundError, match="no pack"):
        rr.unpack(tmp_path / "missing.tar", tmp_path / "junk")
    # Packing there reads no data: the record of their making stays.
    gen_key = rp.plan_stages(rp.ReproduceConfig(out=fresh, preset="tiny", seeds=2))[0].steps[0].name
    assert _reproduce(fresh, "--stage", "pack") == 0 and gen_key in rpp.read_progress(fresh)["commands"]
    # On the fresh machine the data are made again, then the run goes on where it was cut, also
    # when one stage is asked for alone.
    calls.clear()
    assert _reproduce(fresh, "--stage", "dagger") == 0
    assert calls[0].kind == "generate" and "dagger_s0" in calls[1].out and calls[-1].kind == "train policy"
    calls.clear()
    assert _reproduce(fresh) == 0
    assert calls and calls[0].kind == "eval"  # the data are there now: not made again
    assert not any(c.kind.startswith("train") and "bc_" in c.out for c in calls)


def test_the_pack_carries_a_run_cut_in_its_first_round_while_it_fits(fake_conav, tmp_path, monkeypatch, capsys):
    import tarfile

    from conav_jax.checkpoints import checkpoint_path, save_checkpoint

    calls, state = fake_conav
    state["fail_on"] = "bc_none_s0"
    out = tmp_path / "r"
    assert _reproduce(out) == 1  # the first BC run cut in its only round
    runs = out / "runs"
    save_checkpoint(checkpoint_path(runs / "bc_none_s0" / "round_0", 3), params={"w": [1.0] * 1000}, opt_state=None,
                    config={"kind": "policy"}, step=3)
    for log in (runs / "bc_none_s0" / "log.jsonl", runs / "bc_none_s0" / "round_0" / "log.jsonl"):
        log.write_text('{"step": 3}\n')
    # A run with a finished round cut in a later one: that round's data came from its policy, so
    # its checkpoint stays behind (the run resumes after its last finished round).
    for path in (checkpoint_path(runs / "bc_object_s0", 5), checkpoint_path(runs / "bc_object_s0" / "round_0", 5),
                 checkpoint_path(runs / "bc_object_s0" / "round_1", 7)):
        save_checkpoint(path, params={"w": [1.0]}, opt_state=None, config={"kind": "policy"}, step=5)
    save_checkpoint(checkpoint_path(runs / "bc_all_s0" / "round_1", 7), params={"w": [1.0]}, opt_state=None,
                    config={"kind": "policy"}, step=7)
    assert _reproduce(out, "--stage", "pack") == 0
    names = set(tarfile.open(out / "pack.tar").getnames())
    assert {"runs/bc_none_s0/round_0/ckpt_00000003.npz", "runs/bc_none_s0/log.jsonl", "runs/bc_none_s0/round_0/log.jsonl",
            "runs/bc_object_s0/ckpt_00000005.npz"} <= names
    assert not any(n.endswith(".npz") and ("round_1" in n or "bc_object_s0/round_0" in n) for n in names)
    # Every run's training log and every step's log travel, as records of how the runs went.
    assert {str(p.relative_to(out)) for p in (*runs.rglob("log.jsonl"), *(out / "logs").glob("*.log"))} <= names
    # Without room for it the pack is still written, without it, and the command says so.
    required = sum(p.stat().st_size for p in rr.pack_members(rp.ReproduceConfig(out=out, preset="tiny", seeds=2),
                                                             rpp.read_progress(out)))
    monkeypatch.setattr(rr, "PACK_LIMIT_BYTES", required + 10)
    capsys.readouterr()
    assert _reproduce(out, "--stage", "pack") == 0
    assert not any("bc_none_s0" in n and n.endswith(".npz") for n in tarfile.open(out / "pack.tar").getnames())
    assert "left out of the pack for want of room: runs/bc_none_s0/round_0/ckpt_00000003.npz" in capsys.readouterr().out


@pytest.mark.parametrize("preset", sorted(rp.BUDGETS))
def test_every_planned_call_binds_to_its_library_function(preset, tmp_path):
    """Each step's keywords are arguments of its kind's library function (with the mesh, where
    it takes one), and its configs are valid: built at planning, each checks itself (e.g. at
    least the learning-rate warm-up's updates)."""
    import inspect

    mixed = {s.name: s for s in rp.plan_stages(rp.ReproduceConfig(out=tmp_path, preset=preset, seeds=1, dagger_beta=0.5,
                                                                   dagger_rounds=1))}
    for stage in [*rp.plan_stages(rp.ReproduceConfig(out=tmp_path, preset=preset, seeds=1)), mixed["dagger"]]:
        for step in stage.steps:
            function = rs.step_function(step.call.kind)
            mesh = {"mesh": None} if rs.STEP_KINDS[step.call.kind].mesh else {}
            inspect.signature(function).bind(**_kw(step), **mesh)
            assert "kwargs" not in inspect.signature(function).parameters or step.call.kind.startswith("train ")


def test_more_seeds_later_rerender_the_tables_and_stage_times_sum_every_call(fake_conav, tmp_path):
    calls, _ = fake_conav
    out = tmp_path / "r"
    args = cli.build_parser().parse_args(["reproduce", "--preset", "tiny", "--seeds", "1", "--out", str(out)])
    assert args.func(args) == 0  # seed 0 first, to the tables
    assert set(json.loads((out / "results.json").read_text())["conav"]["all"]["seeds"]) == {"0"}
    progress = rpp.read_progress(out)  # seed 0's BC runs took 100 s each
    progress["commands"].update({k: 100.0 for k in progress["commands"] if " policy " in k and "bc_" in k})
    rpp.write_progress(out, progress)
    calls.clear()
    assert _reproduce(out) == 0  # the same run with two seeds: only seed 1's commands run
    assert calls and all("_s0" not in str(v) for c in calls for v in c.kwargs.values())
    results = json.loads((out / "results.json").read_text())
    assert results["seeds"] == 2 and set(results["conav"]["all"]["seeds"]) == {"0", "1"}
    assert "ours (seed" not in (out / "tables.md").read_text()
    # The bc stage ran in two calls: its time is every bc command's, not the last call's.
    plan = rp.plan_stages(rp.ReproduceConfig(out=out, preset="tiny", seeds=2))
    bc_keys = [step.name for step in {s.name: s for s in plan}["bc"].steps]
    assert results["stage_seconds"]["bc"] == pytest.approx(sum(results["command_seconds"][k] for k in bc_keys), abs=0.2)
    assert results["stage_seconds"]["bc"] >= 100.0 * len(rp.ABLATIONS)


def test_a_finished_run_continued_with_the_expert_mixed_in_runs_only_its_dagger_runs(fake_conav, tmp_path):
    calls, _ = fake_conav
    out = tmp_path / "r"
    assert _reproduce(out) == 0
    calls.clear()
    assert _reproduce(out, "--dagger-beta", "0.5") == 0
    assert {c.kind for c in calls} == {"train policy", "eval"} and all("dagger_beta0.5_s" in c.out for c in calls)
    assert all(c.kwargs["imitation"].dagger_beta == 0.5 for c in calls if c.kind == "train policy")
    assert len(calls) == 4  # two seeds: a DAgger run and its evaluation each
    results = json.loads((out / "results.json").read_text())
    assert {"dagger", "dagger_beta0.5"} <= set(results["conav"]) and results["missing"] == []
    assert "the expert acting at 0.5^r of round r's steps" in (out / "tables.md").read_text()
    # Its own evaluations are the ones the tables call missing; the plain run's are not needed.
    (out / "eval" / "conav_dagger_beta0.5_s1" / "metrics.json").unlink()
    (out / "eval" / rp.DAGGER_EVAL.format(1) / "metrics.json").unlink()
    assert _reproduce(out, "--dagger-beta", "0.5", "--stage", "tables") == 0
    assert json.loads((out / "results.json").read_text())["missing"] == ["eval/conav_dagger_beta0.5_s1"]


def test_a_relative_out_directory_names_steps_relative_to_out(fake_conav, tmp_path, monkeypatch):
    calls, _ = fake_conav
    monkeypatch.chdir(tmp_path)
    assert _reproduce(".") == 0
    progress = rpp.read_progress(tmp_path)
    keys = progress["commands"]
    assert progress["run_format"] == rpp.RUN_FORMAT and "generate data" in keys and "train policy runs/bc_all_s1" in keys
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["stage_seconds"]["generate"] == keys["generate data"]
    calls.clear()
    assert _reproduce(".") == 0 and calls == []  # done: nothing runs again


def test_an_out_directory_keyed_by_command_lines_resumes_under_step_names(fake_conav, tmp_path, capsys):
    calls, _ = fake_conav
    out = tmp_path / "r"
    assert _reproduce(out, "--stage", "predictors") == 0
    progress = rpp.read_progress(out)
    # As the previous format wrote it: each command line, OUT written as "OUT", and no run_format.
    old = {"generate --preset tiny --out OUT/data --seed 0 --workers 2": 1.0,
           "train intention --data OUT/data --out OUT/runs/intention --steps 100 --resolution 112x448 --no-progress": 2.0,
           "train trajectory --data OUT/data --out OUT/runs/trajectory --steps 100 --no-progress": 3.0,
           "train policy --out OUT/runs/a_variant_not_planned_s0": 5.0}
    (out / rpp.PROGRESS_FILE).write_text(json.dumps({"commands": old, "stages": progress["stages"],
                                                    "config": progress["config"]}))
    calls.clear()
    assert _reproduce(out, "--stage", "predictors") == 0
    assert calls == []  # the predictors are done: their records moved to their step names
    assert "1 record(s) of commands this plan does not hold were dropped" in capsys.readouterr().out
    again = rpp.read_progress(out)
    assert again["run_format"] == rpp.RUN_FORMAT and set(again["commands"]) == set(progress["commands"])
    (out / rpp.PROGRESS_FILE).write_text(json.dumps({**again, "run_format": rpp.RUN_FORMAT + 1}))
    assert _reproduce(out) == 2 and calls == []
    assert "newer than this version's" in capsys.readouterr().err


def test_a_command_line_record_names_the_step_of_its_words_and_out_directory():
    name = rpp.command_step_name
    assert name("eval --data OUT/data --agent conav --checkpoint OUT/runs/bc_all_s0 --out OUT/eval/conav_bc_all_s0 "
                "--batch 64") == "eval eval/conav_bc_all_s0"
    assert name("train live --data OUT/data --out OUT/runs/bc_gt_all_s1 --seed 1") == "train live runs/bc_gt_all_s1"
    assert name("@copy OUT/runs/bc_all_s0 OUT/runs/dagger_s0") == "copy runs/dagger_s0"
    assert name("generate --preset tiny --out /elsewhere/data") is None  # not under OUT
    assert name("train policy --data OUT/data --out") is None  # no directory written


def test_an_out_directory_holds_one_configuration(tmp_path, capsys):
    cfg = rp.ReproduceConfig(out=tmp_path, preset="tiny")
    progress = rpp.read_progress(tmp_path)  # a new directory (or one made before it kept them)
    rpp.check_out(progress, cfg)
    assert progress["config"] == {"preset": "tiny", "resolution": "112x448", "encoder": "conv", "mirror": False,
                                  "seen_objects": False, "trainer": "offline", **{k: None for k in rp.BUDGET_OVERRIDES}}
    rpp.check_out(progress, dataclasses.replace(cfg, seeds=5, dagger_beta=0.5))  # more seeds, other rows: the same OUT
    rpp.write_progress(tmp_path, progress)
    with pytest.raises(ValueError, match=r"made with ReproduceConfig.resolution 112x448 \(given 32x128\), ReproduceConfig.encoder conv \(given patch\)"):
        rpp.check_out(progress, dataclasses.replace(cfg, resolution=(32, 128), encoder="patch"))
    # The command line refuses before it plans or runs anything.
    args = cli.build_parser().parse_args(["reproduce", "--preset", "tiny", "--out", str(tmp_path), "--encoder", "patch",
                                          "--dry-run"])
    assert args.func(args) == 2
    assert "was made with --encoder conv (given patch): give those, or another --out" in capsys.readouterr().err
    # The predictor's options too; a directory recorded before they existed was made without them.
    older = {"config": {"preset": "tiny", "resolution": "112x448", "encoder": "conv"}}
    with pytest.raises(ValueError, match=r"made with ReproduceConfig.seen_objects off \(given on\)"):
        rpp.check_out(older, dataclasses.replace(cfg, seen_objects=True))
    rpp.check_out(older, cfg)
    assert older["config"]["mirror"] is False


def test_one_seed_at_a_time_trains_and_evaluates_it_and_packs_only_what_others_need(fake_conav, tmp_path, capsys):
    from conav_jax.checkpoints import checkpoint_path, save_checkpoint

    calls, state = fake_conav
    out = tmp_path / "r"
    assert _reproduce(out, "--seed", "2") == 2 and "not one of the run's seeds 0..1" in capsys.readouterr().err
    assert not out.exists()  # refused before anything is written
    assert _reproduce(out, "--stage", "predictors") == 0  # the data first, then the predictors
    calls.clear()
    state["fail_on"] = "bc_object_s0"  # the machine is lost after seed 0's first two runs and their evaluations
    assert _reproduce(out, "--stage", "bc", "--seed", "0") == 1
    names = [Path(c.out).name for c in calls]
    assert names == ["bc_none_s0", "conav_bc_none_s0", "bc_activity_s0", "conav_bc_activity_s0", "bc_object_s0"]
    for run in ("intention", "trajectory", "bc_none_s0", "bc_activity_s0"):
        save_checkpoint(checkpoint_path(out / "runs" / run, 5), params={"w": [1.0]}, opt_state=None,
                        config={"kind": "policy"}, step=5)
    assert _reproduce(out, "--stage", "pack") == 0
    import tarfile

    packed = {n for n in tarfile.open(out / "pack.tar").getnames() if n.endswith(".npz")}
    # Evaluated runs do not travel on: the next machine needs the predictors alone.
    assert packed == {"runs/intention/ckpt_00000005.npz", "runs/trajectory/ckpt_00000005.npz"}
    calls.clear()
    assert _reproduce(out, "--stage", "bc", "--seed", "0") == 0
    names = [Path(c.out).name for c in calls]
    assert names == [n for a in rp.ABLATIONS[2:] for n in (f"bc_{a}_s0", f"conav_bc_{a}_s0")]
    assert "bc" not in rpp.read_progress(out)["stages"]  # seed 1's runs are still to come
    calls.clear()
    assert _reproduce(out, "--stage", "eval", "--seed", "0") == 0 and calls == []
    assert "waits for the runs it reads: eval eval/" in capsys.readouterr().out  # its DAgger run's evaluation
    calls.clear()
    assert _reproduce(out) == 0  # the rest: seed 1, the baselines, DAgger, every other evaluation
    assert not any("bc_" in c.out and "_s0" in c.out for c in calls)
    results = json.loads((out / "results.json").read_text())
    assert results["missing"] == [] and set(results["conav"]["all"]["seeds"]) == {"0", "1"}


def test_a_stage_asked_for_alone_runs_what_it_can_and_waits_for_runs_not_trained(fake_conav, tmp_path, capsys):
    calls, _ = fake_conav
    out = tmp_path / "r"
    assert _reproduce(out, "--stage", "predictors") == 0
    calls.clear()
    # The evaluations before any agent is trained: the scripted agents' runs, the learned ones wait.
    assert _reproduce(out, "--stage", "eval") == 0
    assert [Path(c.out).name for c in calls] == ["scripted"]
    printed = capsys.readouterr().out
    assert "waits for the runs it reads: eval eval/" in printed and "objectgoal-oracle" in printed
    assert "eval" not in rpp.read_progress(out)["stages"]
    calls.clear()
    assert _reproduce(out) == 0  # the rest; the scripted agents are not evaluated again
    assert sum(c.out.endswith("/scripted") for c in calls) == 0
    assert json.loads((out / "results.json").read_text())["missing"] == []


# Steps run as a process of their own (`--gpus`; arguments: their kind, how many they are, the
# directory each writes and an evaluation's agents): writes what fake_conav's steps write, and a
# line for each of when it ran, on which GPU and with how many others; FAKE_FAIL_ON names a step
# that fails.
FAKE_CHILD = r'''
import json, os, sys, time
from pathlib import Path
argv = sys.argv[1:]
t0 = time.time()
kind, count = argv[0], int(argv[1])
outs, agents = [Path(a) for a in argv[2:2 + count]], argv[2 + count:]
def note(**extra):
    with open(os.environ["FAKE_RECORD"], "a") as f:
        for out in outs:
            f.write(json.dumps({"out": str(out), "gpu": os.environ["CUDA_VISIBLE_DEVICES"], "start": t0,
                                "end": time.time(), "preallocate": os.environ.get("XLA_PYTHON_CLIENT_PREALLOCATE"),
                                "with": len(outs) - 1, **extra}) + "\n")
# Each command marks itself running (FAKE_RECORD's folder) while it sleeps FAKE_SECONDS; the
# failing one fails only once another command is running, so that one is still running when the
# failure is seen, whatever the machine's load.
running = Path(os.environ["FAKE_RECORD"]).parent / f"running_{os.getpid()}"
if os.environ.get("FAKE_FAIL_ON") and any(os.environ["FAKE_FAIL_ON"] in a for a in argv):
    deadline = time.time() + 60
    while not list(running.parent.glob("running_*")) and time.time() < deadline:
        time.sleep(0.01)
    print("a failure the log shows")
    note(failed=True)
    sys.exit(3)
running.touch()
time.sleep(float(os.environ.get("FAKE_SECONDS", "0.05")))
running.unlink()
out = outs[0]
for o in outs:
    o.mkdir(parents=True, exist_ok=True)
if kind == "eval":
    entry = lambda a: {"agent": a, "title": f"T {a}", "intention_source": "none", "privileged": ["oracle map"],
                       "metrics": {m: {"value": v, "lo": v - 1, "hi": v + 1}
                                   for m, v in zip(("FASR", "RASR", "FASPL", "RASPL", "CR", "AS"), (1, 2, 3, 4, 5, 6))}}
    for o in outs:
        (o / "metrics.json").write_text(json.dumps({"episodes": 100, "agents": {a: entry(a) for a in agents},
                                                    "ablations": {}}))
else:
    for o in outs:
        (o / ("manifest.json" if kind == "generate" else "log.jsonl")).write_text("{}\n")
note()
'''


@pytest.fixture
def fake_children(monkeypatch, tmp_path):
    """Steps run by `--gpus` as processes of FAKE_CHILD, on the GPUs CUDA_VISIBLE_DEVICES lists;
    returns the file of their records. Each process is asked for by `rr.child_command` (its
    arguments kept in `child_calls`)."""
    script, record = tmp_path / "fake_child.py", tmp_path / "record.jsonl"
    script.write_text(FAKE_CHILD)

    def command(out, digest, steps, compile_cache=None):
        CHILD_CALLS.extend((out, digest, step.name) for step in steps)
        return [sys.executable, str(script), steps[0].call.kind, str(len(steps)),
                *(str(out / step.writes) for step in steps), *_kw(steps[0]).get("agents", ())]

    CHILD_CALLS.clear()
    monkeypatch.setattr(rr, "child_command", command)
    monkeypatch.setenv("FAKE_RECORD", str(record))
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "5,7")
    return record


CHILD_CALLS = []  # (OUT, the stored configuration's digest, the step's name) of each process asked for


def _runs(record: Path) -> list[dict]:
    return [json.loads(line) for line in record.read_text().splitlines()] if record.exists() else []


def test_several_gpus_run_commands_at_once_once_their_runs_are_made_with_the_same_results(
        fake_conav, fake_children, tmp_path, capsys):
    calls, _ = fake_conav
    assert _reproduce(tmp_path / "one") == 0
    assert _reproduce(tmp_path / "two", "--gpus", "2") == 0
    assert not [c for c in calls if str(tmp_path / "two") in c.out]  # none ran in this process
    runs = _runs(fake_children)
    out = tmp_path / "two"
    cfg = rp.ReproduceConfig(out=out, preset="tiny", seeds=2, workers=min(2, os.cpu_count() or 1))
    plan = rp.plan_stages(cfg)
    made = [s for st in plan for s in st.steps if not s.is_copy]
    assert sorted(r["out"] for r in runs) == sorted(str(out / s.writes) for s in made)  # each once, in a process
    # Each process runs its step by name, in the plan of the run's configuration stored in OUT.
    assert sorted(name for _, _, name in CHILD_CALLS) == sorted(s.name for s in made)
    ((where, digest),) = {(o, d) for o, d, _ in CHILD_CALLS}
    assert where == out and rr.load_config(out, digest) == cfg
    # Each started after every step it waits for had ended: the data, the runs it reads.
    needs = rpp.prerequisites(plan)
    ended = {r["out"]: r["end"] for r in runs}
    by_name = {s.name: s for st in plan for s in st.steps}
    for step in made:
        mine = next(r for r in runs if r["out"] == str(out / step.writes))
        for name in needs[step.name]:
            if not by_name[name].is_copy:
                assert ended[str(out / by_name[name].writes)] <= mine["start"]
    # Seed by seed, and within a seed what most commands wait on first: the BC run that DAgger
    # continues before the other BC runs, which only their evaluations wait for.
    started = [line.split(" started (log ")[0].split()[-1] for line in capsys.readouterr().out.splitlines()
               if line.startswith("[gpu ") and line.endswith(".log)")]
    assert started[0] == "data" and set(started[1:3]) == {"runs/intention", "runs/trajectory"}
    bc_runs = [name for name in started if name.startswith("runs/bc_")]
    assert bc_runs[0] == "runs/bc_all_s0" and len(bc_runs) == 10
    assert all(name.endswith("_s0") for name in bc_runs[:5]) and all(name.endswith("_s1") for name in bc_runs[5:])
    # Two at a time, never two on one GPU at once, on the GPUs CUDA_VISIBLE_DEVICES names.
    assert {r["gpu"] for r in runs} == {"5", "7"}
    overlaps = [(a, b) for i, a in enumerate(runs) for b in runs[i + 1:] if a["start"] < b["end"] and b["start"] < a["end"]]
    assert overlaps and all(a["gpu"] != b["gpu"] for a, b in overlaps)
    assert {r["preallocate"] for r in runs} == {None}  # a GPU of its own: JAX's default memory
    assert (out / "logs" / "train_policy_runs_bc_all_s1.log").read_text().startswith("# train policy runs/bc_all_s1\n$ ")
    one, two = (json.loads((tmp_path / d / "results.json").read_text()) for d in ("one", "two"))
    for doc in (one, two):
        for key in ("command", "stage_seconds", "command_seconds", "cut_seconds"):
            doc.pop(key)
    assert json.dumps(two, sort_keys=True).replace("/two/", "/one/") == json.dumps(one, sort_keys=True)
    progress = rpp.read_progress(out)
    assert set(progress["stages"]) >= {"generate", "predictors", "baselines", "bc", "dagger", "eval"}
    assert progress["stages"]["bc"] == round(sum(v for k, v in progress["commands"].items() if "bc_" in k
                                                 and "dagger" not in k), 1)


def _most_at_once(runs: list[dict]) -> tuple[int, int]:
    """(the most processes running at once, the most of them on one GPU), over the records."""
    most = most_on_one = 0
    for r in runs:
        now = [o for o in runs if o["start"] <= r["start"] < o["end"]]
        most = max(most, len(now))
        most_on_one = max(most_on_one, max(sum(o["gpu"] == g for o in now) for g in {o["gpu"] for o in now}))
    return most, most_on_one


def test_steps_per_gpu_share_each_gpu_the_least_busy_first_taking_memory_as_needed(
        fake_conav, fake_children, tmp_path, monkeypatch, capsys):
    monkeypatch.delenv("XLA_PYTHON_CLIENT_PREALLOCATE", raising=False)
    monkeypatch.delenv("XLA_PYTHON_CLIENT_MEM_FRACTION", raising=False)
    monkeypatch.setenv("FAKE_SECONDS", "0.4")
    out = tmp_path / "r"
    assert _reproduce(out, "--gpus", "2", "--steps-per-gpu", "2", "--stage", "generate", "--stage", "predictors",
                      "--stage", "bc") == 0
    assert "up to 4 at once on GPU(s) 5, 7 (2 each)" in capsys.readouterr().out
    runs = _runs(fake_children)
    assert {r["gpu"] for r in runs} == {"5", "7"} and {r["preallocate"] for r in runs} == {"false"}
    # Ten BC runs, all ready once the predictors are: four at once, two on each GPU, never three.
    assert _most_at_once(runs) == (4, 2)
    # The predictors (two at once) went to different GPUs, not both to the first.
    (intention,) = [r for r in runs if r["out"].endswith("runs/intention")]
    (trajectory,) = [r for r in runs if r["out"].endswith("runs/trajectory")]
    assert intention["gpu"] != trajectory["gpu"]
    # A step whose process ran beside another on its GPU is recorded as shared (plans go by lone times).
    progress = rpp.read_progress(out)
    shared = progress["shared"]
    for r in runs:
        beside = any(o is not r and o["gpu"] == r["gpu"] and o["start"] < r["end"] and r["start"] < o["end"] for o in runs)
        (name,) = [k for k in progress["commands"] if str(out / k.split(" ")[-1]) == r["out"]]
        if beside:  # the parent sees at least the overlaps its children record
            assert shared.get(name) == 2, name
    assert sum(n == 2 for n in shared.values()) >= 8 and set(shared.values()) == {2}
    assert (rr.gpu_slots(2, 2), rr.gpu_slots(1, 3)) == (["5", "7", "5", "7"], ["5", "5", "5"])
    with pytest.raises(ValueError, match="steps_per_gpu must be at least 1"):
        rr.gpu_slots(2, 0)
    assert _reproduce(tmp_path / "bad", "--gpus", "2", "--steps-per-gpu", "0") == 2
    assert "--steps-per-gpu must be at least 1, got 0" in capsys.readouterr().err
    # Memory variables the environment sets are the user's: left as they are.
    monkeypatch.setenv("XLA_PYTHON_CLIENT_MEM_FRACTION", "0.3")
    assert _reproduce(tmp_path / "mine", "--gpus", "2", "--steps-per-gpu", "2", "--stage", "generate") == 0
    assert _runs(fake_children)[-1]["preallocate"] is None


def test_several_gpus_stop_starting_commands_after_a_failure_and_resume(fake_conav, fake_children, tmp_path,
                                                                       monkeypatch, capsys):
    out = tmp_path / "r"
    monkeypatch.setenv("FAKE_FAIL_ON", "bc_none_s0")
    # It fails while the other GPU's command runs (FAKE_CHILD), which then runs on for 2 s: the
    # runner sees the failure (it polls every 0.1 s) before that command ends.
    monkeypatch.setenv("FAKE_SECONDS", "2")
    assert _reproduce(out, "--gpus", "2") == 3
    printed = capsys.readouterr()
    assert "bc_none_s0 failed (exit 3)" in printed.out and "a failure the log shows" in printed.out
    after = printed.out.split("bc_none_s0 failed (exit 3)")[1]
    assert " started (log " not in after and " done in " in after  # none starts after it; those running end
    assert "not started after the failure: eval eval/" in after and "waits for the runs it reads" not in after
    first = _runs(fake_children)
    (failure,) = [r for r in first if r.get("failed")]
    failed_at = max(r["end"] for r in first)
    progress = rpp.read_progress(out)
    assert any("bc_none_s0" in k for k in progress["cut"]) and not any("bc_none_s0" in k for k in progress["commands"])
    assert "bc" not in progress["stages"] and "predictors" in progress["stages"]
    monkeypatch.delenv("FAKE_FAIL_ON")
    monkeypatch.delenv("FAKE_SECONDS")
    assert _reproduce(out, "--gpus", "2") == 0
    again = _runs(fake_children)[len(first):]
    assert not {r["out"] for r in first if not r.get("failed")} & {r["out"] for r in again}  # nothing done runs again
    assert failure["out"] in {r["out"] for r in again}
    assert all(r["start"] >= failed_at for r in again)
    assert json.loads((out / "results.json").read_text())["missing"] == []


def test_several_gpus_stopped_stop_every_command_and_count_their_time_as_cut(fake_conav, fake_children, tmp_path,
                                                                             monkeypatch):
    import threading

    out = tmp_path / "r"
    monkeypatch.setenv("FAKE_SECONDS", "30")  # commands that would outlast the stop
    timer = threading.Timer(1.5, os.kill, (os.getpid(), signal.SIGTERM))  # as `timeout` stops a run
    timer.start()
    t0 = time.perf_counter()
    with pytest.raises(KeyboardInterrupt):
        _reproduce(out, "--gpus", "2", "--stage", "generate")
    timer.join()
    assert time.perf_counter() - t0 < 20  # the command was stopped, not waited for
    assert _runs(fake_children) == []
    progress = rpp.read_progress(out)
    assert progress["commands"] == {} and [k.split()[0] for k in progress["cut"]] == ["generate"]
    assert progress["cut"][next(iter(progress["cut"]))] >= 1.0


def test_the_gpus_are_those_the_driver_lists_and_several_named_without_gpus_get_a_hint(fake_conav, tmp_path,
                                                                                     monkeypatch, capsys):
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    monkeypatch.setattr(rr.shutil, "which", lambda name: None)
    assert rr.visible_gpus() is None and rr.gpu_slots(2) == ["0", "1"]  # a CPU machine
    listed = "GPU 0: NVIDIA H100 80GB HBM3 (UUID: a)\nGPU 1: NVIDIA H100 80GB HBM3 (UUID: b)\n"
    monkeypatch.setattr(rr.shutil, "which", lambda name: "/usr/bin/" + name)
    monkeypatch.setattr(rr.subprocess, "run", lambda *a, **k: subprocess.CompletedProcess(a, 0, listed, ""))
    assert rr.visible_gpus() == ["0", "1"] and rr.gpu_slots(2) == ["0", "1"]
    with pytest.raises(ValueError, match="gpu_slots.gpus 3: 2 GPU"):
        rr.gpu_slots(3)
    assert _reproduce(tmp_path / "r", "--stage", "generate") == 0
    assert "2 GPUs visible: each step runs on all of them as one device mesh; --gpus 2" in capsys.readouterr().out
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "1")
    assert _reproduce(tmp_path / "r", "--stage", "generate") == 0
    assert "GPUs visible" not in capsys.readouterr().out


def test_more_gpus_than_visible_is_an_error(fake_conav, fake_children, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "3")
    assert _reproduce(tmp_path / "r", "--gpus", "2") == 2
    assert "--gpus 2: 1 GPU(s) visible (3)" in capsys.readouterr().err
    assert rr.gpu_slots(1) == ["3"]
    with pytest.raises(ValueError, match="at least 1"):
        rr.gpu_slots(0)
    for bad in ("0", "-2"):  # not a silent run of one command at a time
        assert _reproduce(tmp_path / "r", "--gpus", bad) == 2
        assert f"--gpus must be at least 1, got {bad}" in capsys.readouterr().err
    assert not (tmp_path / "r" / "progress.json").exists()


def test_two_processes_on_one_out_keep_each_others_records(fake_conav, tmp_path):
    out = tmp_path / "r"
    assert _reproduce(out, "--stage", "predictors") == 0
    mine, theirs = rpp.read_progress(out), rpp.read_progress(out)  # two processes read the file
    theirs["commands"]["train policy ... OUT/runs/other_s0"] = 12.0
    theirs["cut"] = {"eval ... OUT/eval/other_s0": 3.0, "eval ... OUT/eval/both_s0": 2.0}
    rpp.write_progress(out, theirs)
    mine["commands"]["train policy ... OUT/runs/mine_s0"] = 7.0
    mine["stages"]["mine"] = 7.0
    mine["cut"] = {"eval ... OUT/eval/both_s0": 5.0}  # a record both hold: the writer's wins
    rpp.write_progress(out, mine)
    on_disk = rpp.read_progress(out)
    assert on_disk["commands"]["train policy ... OUT/runs/other_s0"] == 12.0
    assert on_disk["commands"]["train policy ... OUT/runs/mine_s0"] == 7.0
    assert on_disk["cut"] == {"eval ... OUT/eval/other_s0": 3.0, "eval ... OUT/eval/both_s0": 5.0}
    assert on_disk["stages"]["mine"] == 7.0
    assert mine == on_disk  # the writer sees the others' records too


def test_a_gpu_process_runs_its_step_alone_by_name_with_the_runs_options(fake_conav, tmp_path):
    calls, _ = fake_conav
    out = tmp_path / "r"
    cfg = rp.ReproduceConfig(out=out, preset="tiny", seeds=2, dagger_beta=0.5, dagger_rounds=3, mirror=True)
    (step,) = [s for st in rp.plan_stages(cfg) for s in st.steps if s.name == "train policy runs/dagger_beta0.5_rounds3_s1"]
    digest = rr.save_config(cfg)
    assert rr.save_config(cfg) == digest and len(list((out / rr.CONFIGS_DIR).iterdir())) == 1  # stored once
    argv = rr.child_command(out, digest, [step])
    assert argv[1:4] == ["-P", "-m", "conav_jax.eval.cli.reproduce_run"] and argv[-2:] == ["--step", step.name]
    assert rr.main(argv[4:]) == 0
    assert calls == [Made("train policy", str(out / step.writes), {})] and calls[0].kwargs == _kw(step)  # that call alone
    assert not (out / rpp.PROGRESS_FILE).exists()  # the parent records it
    with pytest.raises(ValueError, match="the plan has no step 'train policy runs/nothing_s0'"):
        rr.main([*argv[4:-1], "train policy runs/nothing_s0"])
    with pytest.raises(FileNotFoundError, match="no run configuration"):
        rr.main([*argv[4:6], "--config", "0" * 16, "--step", step.name])
    # Started where a `conav_jax/` folder lies (a checkout's source tree), it still finds the package.
    checkout = tmp_path / "checkout"
    (checkout / "conav_jax").mkdir(parents=True)
    (checkout / "conav_jax" / "__init__.py").write_text("")
    done = subprocess.run([*argv[:4], "--help"], cwd=checkout, capture_output=True, text=True)
    assert done.returncode == 0 and "--step NAME" in done.stdout, done.stderr


def test_live_runs_of_one_row_join_into_one_process_and_one_call(fake_conav, fake_children, tmp_path, monkeypatch,
                                                                  capsys):
    out = tmp_path / "r"
    assert _reproduce(out, "--trainer", "live", "--gpus", "2", "--runs-per-process", "2") == 0
    runs = _runs(fake_children)
    live = [r for r in runs if "/runs/bc_" in r["out"] or "/runs/dagger" in r["out"]]
    assert live and all(r["with"] == 1 for r in live)  # two seeds a process: the tiny preset has two
    evals = [r for r in runs if "/eval/" in r["out"]]
    assert sum(r["with"] == 1 for r in evals) >= 10  # evaluations of one data, split and agents join
    assert all(r["with"] == 0 for r in runs if r not in live + evals)  # nothing else is joined
    # Joined evaluations evaluate one agent (each its own run); the scripted agents' runs alone.
    (scripted,) = [r for r in evals if r["out"].endswith("/eval/scripted")]
    assert scripted["with"] == 0
    by_start = {}
    for r in live:
        by_start.setdefault((r["start"], r["gpu"]), []).append(Path(r["out"]).name)
    assert sorted(sorted(names) for names in by_start.values()) == sorted(
        [f"{row}_s0", f"{row}_s1"] for row in {name.rsplit("_s", 1)[0] for names in by_start.values() for name in names})
    printed = capsys.readouterr().out
    assert "train live runs/bc_none_s0 + train live runs/bc_none_s1 started" in printed
    assert (out / "logs" / "train_live_runs_bc_none_s1.log").read_text().endswith(
        "its log is train_live_runs_bc_none_s0.log\n")
    progress = rpp.read_progress(out)
    assert progress["commands"]["train live runs/bc_none_s0"] == progress["commands"]["train live runs/bc_none_s1"]
    assert json.loads((out / "results.json").read_text())["missing"] == []
    assert _reproduce(tmp_path / "bad", "--runs-per-process", "0") == 2
    assert "--runs-per-process must be at least 1, got 0" in capsys.readouterr().err


def test_steps_that_differ_only_in_their_seed_run_as_one_call(tmp_path, monkeypatch):
    cfg = rp.ReproduceConfig(out=tmp_path, preset="tiny", seeds=2, trainer="live", dagger_beta=0.5)
    steps = {s.name: s for st in rp.plan_stages(cfg) for s in st.steps}
    none0, none1 = steps["train live runs/bc_none_s0"], steps["train live runs/bc_none_s1"]
    assert rs.joinable(none0, none1) and rs.joinable(none1, none0)
    for other in ("train live runs/bc_all_s1", "train live runs/dagger_live_beta0.5_s1", "train live runs/bc_none_s0",
                  "eval eval/conav_bc_none_s1", "train intention runs/intention"):
        assert not rs.joinable(none0, steps[other]), other
    # Evaluations join when only their runs differ: one agent, data, split, intention inputs.
    eval0, eval1 = steps["eval eval/conav_bc_none_s0"], steps["eval eval/conav_bc_none_s1"]
    assert rs.joinable(eval0, eval1) and rs.joinable(eval0, steps["eval eval/conav_bc_all_s1"])
    for other in ("eval eval/conav_bc_gt_all_s0", "eval eval/scripted", "eval eval/conav_bc_none_s0"):
        assert not rs.joinable(eval0, steps[other]), other  # ground truth asked for; other agents; itself
    called = []
    monkeypatch.setattr(rs, "together_function", lambda kind: lambda **kw: called.append((kind, kw)))
    rs.run_together([none0, none1])
    ((kind, kw),) = called
    assert kind == "train live" and kw["out_dirs"] == [_kw(none0)["out_dir"], _kw(none1)["out_dir"]]
    assert [live.seed for live in kw["lives"]] == [0, 1] and "out_dir" not in kw and "live" not in kw
    assert {k: v for k, v in kw.items() if k not in ("out_dirs", "lives")} == {
        k: v for k, v in _kw(none0).items() if k not in ("out_dir", "live")}
    with pytest.raises(ValueError, match="differ in more than their runs"):
        rs.run_together([none0, steps["train live runs/bc_all_s1"]])
    called.clear()
    rs.run_together([eval0, eval1])
    ((kind, kw),) = called
    assert kind == "eval" and kw["outs"] == [_kw(eval0)["out"], _kw(eval1)["out"]]
    assert kw["checkpoints"] == [_kw(eval0)["checkpoint"], _kw(eval1)["checkpoint"]]
    assert {k: v for k, v in kw.items() if k not in ("outs", "checkpoints")} == {
        k: v for k, v in _kw(eval0).items() if k not in ("out", "checkpoint")}
    import conav_jax.train.live as lv

    import conav_jax.eval.sweep as sweep

    assert rs.STEP_KINDS["train live"].together.endswith(":train_live_seeds_from_data")
    assert callable(lv.train_live_seeds_from_data)
    # run_evals: each evaluation in turn, in this process.
    made = []
    monkeypatch.setattr(sweep, "run_eval", lambda *a, **kw: made.append((a, kw)) or len(made))
    assert sweep.run_evals("d", "val", ("conav",), ["o0", "o1"], ["r0", None], batch=8) == [1, 2]
    assert made == [(("d", "val", ("conav",), "o0"), {"checkpoint": "r0", "batch": 8}),
                    (("d", "val", ("conav",), "o1"), {"checkpoint": None, "batch": 8})]
    with pytest.raises(ValueError, match="a checkpoint .* per out"):
        sweep.run_evals("d", "val", ("conav",), ["o0"], [])


def test_a_gpu_process_is_the_module_run_by_python_and_plans_from_out(tmp_path):
    """The process `--gpus` starts, for real: a DAgger run's copy of its BC run, found by name in
    the plan of the configuration stored in OUT."""
    out = tmp_path / "r"
    cfg = rp.ReproduceConfig(out=out, preset="tiny", seeds=1, dagger_beta=0.5)
    (step,) = [s for st in rp.plan_stages(cfg) for s in st.steps if s.name == "copy runs/dagger_beta0.5_s0"]
    (out / "runs" / "bc_all_s0").mkdir(parents=True)
    (out / "runs" / "bc_all_s0" / "log.jsonl").write_text("{}\n")
    argv = rr.child_command(out, rr.save_config(cfg), [step], compile_cache="off")
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    assert (out / "runs" / "dagger_beta0.5_s0" / "log.jsonl").read_text() == "{}\n"


def test_the_live_trainer_plans_ground_truth_rows_paired_seeds_and_a_dagger_from_scratch(tmp_path):
    cfg = rp.ReproduceConfig(out=tmp_path, preset="paper", seeds=2, trainer="live")
    stages = {st.name: st for st in rp.plan_stages(cfg)}
    train = {s.name: s for s in stages["bc"].steps if s.call.kind == "train live"}
    assert set(train) == {f"train live runs/bc_{row}_s{s}" for row in cfg.all_rows for s in (0, 1)}
    for name, step in train.items():
        assert _kw(step)["live"].seed == step.seed  # seed s of every row: one order, one init
        assert _kw(step)["live"].iterations == cfg.budget.live_iterations
        assert not _kw(step)["live"].remat  # the live window's panoramas are prepared: no recompute
    gt, predicted = train["train live runs/bc_gt_all_s1"], train["train live runs/bc_all_s1"]
    assert "intention_run" not in _kw(gt) and gt.reads == ("data",)  # the env's true intentions
    assert _model(gt) == _model(predicted) and _model(gt).use_trajectory  # the inputs of `all`
    assert _kw(predicted)["intention_run"].endswith("runs/intention") and "runs/intention" in predicted.reads
    none = train["train live runs/bc_none_s1"]  # reads no intention: starts without waiting for the predictors
    assert "intention_run" not in _kw(none) and none.reads == ("data",)
    evals = {s.name: s for s in stages["bc"].steps if s.call.kind == "eval"}
    assert _kw(evals["eval eval/conav_bc_gt_object_s0"])["intention_kwargs"] == {"ground_truth": True}
    assert _kw(evals["eval eval/conav_bc_object_s0"])["intention_kwargs"] == {}
    # DAgger: its own run from scratch (no copy of BC), beta falling from 1 to --dagger-beta.
    (dagger, _) = stages["dagger"].steps
    assert dagger.name == "train live runs/dagger_live_beta0_s0" and not any(s.is_copy for s in stages["dagger"].steps)
    live = _kw(dagger)["live"]
    assert (live.beta_start, live.beta_end) == (1.0, 0.0)
    assert live.beta_decay_iterations == cfg.budget.live_iterations // 2
    assert "eval eval/conav_dagger_live_beta0_s1" in {s.name for s in stages["eval"].steps}
    # The object-goal baseline trains live at the rows' budget and seed; the image-goal one offline.
    baselines = {s.name: s for s in stages["baselines"].steps}
    objectnav = baselines["train objectnav live runs/objectnav_s1"]
    assert _kw(objectnav)["live"] == _kw(train["train live runs/bc_none_s1"])["live"]
    assert _model(objectnav).use_object and not _model(objectnav).use_human_pos and _model(objectnav).visual_norm
    assert "train imagenav runs/imagenav_s1" in baselines
    # --baselines keeps a sitting to some of them, their evaluations with them.
    only = {st.name: st for st in rp.plan_stages(dataclasses.replace(cfg, baselines=("objectnav",)))}
    assert {s.name for s in only["baselines"].steps} == {f"train objectnav live runs/{n}"
                                                         for n in ("objectnav", "objectnav_s1", "objectnav_s2")}
    evaluated = {s.name for s in only["eval"].steps}
    assert "eval eval/objectgoal-predicted_s2" in evaluated and not any("imagegoal" in n for n in evaluated)
    with pytest.raises(ValueError, match="ReproduceConfig.baselines pointnav: each once, from objectnav, imagenav"):
        rp.ReproduceConfig(out=tmp_path, baselines=("pointnav",))
    # A subset of the rows; unknown rows and the offline trainer's lack of ground-truth rows refused.
    some = rp.plan_stages(dataclasses.replace(cfg, rows=("none", "gt_all")))
    assert {s.name for s in _trained(some[3])} == {
        f"train live runs/bc_{r}_s{s}" for r in ("none", "gt_all") for s in (0, 1)}
    with pytest.raises(ValueError, match="ReproduceConfig.rows gt_all"):
        rp.ReproduceConfig(out=tmp_path, rows=("gt_all",))
    # DAgger's runs are the dagger stage's, not a row: a subset of the rows keeps them.
    assert {s.name for s in some[4].steps} == {f"train live runs/{cfg.dagger}_s{s}" for s in (0, 1)}
    with pytest.raises(ValueError, match="DAgger's runs are not a row: the dagger stage trains them"):
        dataclasses.replace(cfg, rows=(cfg.dagger,))
    with pytest.raises(ValueError, match="ReproduceConfig.trainer"):
        rp.ReproduceConfig(out=tmp_path, trainer="online")


def test_tables_show_the_ground_truth_bound_and_its_paired_contrasts(tmp_path):
    evals = tmp_path / "eval"
    fasr = {"none": (10, 12, 9), "object": (11, 12, 12), "all": (14, 13, 12), "gt_object": (20, 22, 19),
            "gt_all": (30, 33, 27), "dagger_live_beta0": (16, 13, 12)}
    for row, values in fasr.items():
        for s, f in enumerate(values):
            name = rp.CONAV_EVAL.format(row=row, seed=s) if row.startswith("dagger") else \
                rp.BC_ROW_EVAL.format(row=row, seed=s)
            doc = _eval_doc({"conav": (f, f, 0, 0, 0, 0)})
            doc["provenance"] = {"commit": "abcdef0123456789"}
            if row == "gt_all":
                doc["agents"]["conav"]["trained"] = {"run": "r", "step": 5, "provenance": {"commit": f"5eed{s}00000000"}}
            if row == "gt_object" and s == 2:  # a process that could not read its commit: its code's hash
                doc["provenance"] = {"commit": "unknown", "code": "4dc8b08880fe1d7c"}
                doc["agents"]["conav"]["trained"] = {"run": "r", "step": 5, "provenance": {"commit": "unknown"}}
            _write_eval(evals / name, doc)
    results = rt.collect_results(tmp_path, 3, {"seeds": 3, "trainer": "live"}, "dagger_live_beta0",
                                 ("none", "object", "all", "gt_object", "gt_all"))
    # The baselines not evaluated: listed, the tables made all the same; no planned row missing.
    assert results["missing"] == ["eval/scripted", "eval/objectgoal-oracle", "eval/objectgoal-predicted",
                                  "eval/imagegoal"] and results["episodes"] == 100
    assert results["conav"]["gt_all"]["commits"] == ["abcdef0123456789"]
    lines = rt.render_tables(results).splitlines()
    assert any(line.startswith("| 6 | ✗ | GT | ✗ | ours | 20.3 ± 1.5 [") for line in lines)
    assert any(line.startswith("| 7 | GT | GT | GT | ours | 30.0 ± 3.0 [") for line in lines)
    # gt_all - all: +16 +20 +15 (mean 17, sd 2.65, t(0.975, 2) = 4.303: 17 ± 6.6).
    assert any(line.startswith("| gt_all | all | s0 30.0 / s1 33.0 / s2 27.0 | +16.0 / +20.0 / +15.0 | "
                               "+17.0 ± 2.6 [+10.4, +23.6] (n=3) resolved |") for line in lines)
    assert any(line.startswith("| gt_all | none |") for line in lines)
    assert any(line.startswith("| dagger_live_beta0 | all | ") for line in lines)
    assert any("live DAgger, the expert's share falling from 1 to 0" in line for line in lines)
    assert any(line.startswith("| T conav (live imitation) |") for line in lines)  # Table 2's none row beside all
    assert sum(line.startswith("| T conav (live imitation) |") for line in lines) == 2
    assert "- `gt_all`: abcdef0123 (trained at 5eed000000, 5eed100000, 5eed200000)" in lines
    assert "- `none`: abcdef0123" in lines  # evaluations that name no training commit
    assert "- `gt_object`: abcdef0123, unknown (code 4dc8b08880fe1d7c) (trained at unknown)" in lines
    assert not any(line.startswith("| activity |") for line in lines)  # not planned: no contrast, nothing missing


def test_choices_are_made_on_minival_in_files_of_their_own(tmp_path):
    cfg = rp.ReproduceConfig(out=tmp_path, preset="tiny", seeds=1, trainer="live", rows=("none",), eval_split="minival")
    stages = {st.name: st for st in rp.plan_stages(cfg)}
    (evaluation,) = [s for s in stages["bc"].steps if s.call.kind == "eval"]
    assert evaluation.name == "eval eval_minival/conav_bc_none_s0"
    assert _kw(evaluation)["split"] == "minival"
    assert stages["tables"].outputs == (tmp_path / "results_minival.json", tmp_path / "tables_minival.md")
    # The runs are val's: the same step, the same directory.
    val = rp.plan_stages(dataclasses.replace(cfg, eval_split="val"))
    assert _trained(val[3]) == _trained(stages["bc"])
    _write_eval(tmp_path / "eval_minival" / rp.BC_ROW_EVAL.format(row="none", seed=0), _eval_doc({"conav": (5, 6, 0, 0, 0, 0)}))
    results = rt.collect_results(tmp_path, 1, {"seeds": 1, "split": "minival"}, cfg.dagger, cfg.table3_rows, cfg.eval_dir)
    assert set(results["conav"]["none"]["seeds"]) == {"0"} and "eval_minival/scripted" in results["missing"]
    assert "split minival (100 episodes)" in rt.render_tables(results)
    with pytest.raises(ValueError, match="ReproduceConfig.eval_split"):
        rp.ReproduceConfig(out=tmp_path, eval_split="test")


BUDGET_OVERRIDE_CASES = {
    # the overridden fields, the flags that give them, the step's config that then holds them
    # (its keyword) and its fields, and the field the refused OUT names
    # (the paper preset's 50 warm-up updates: a live run of fewer is refused at planning; the
    # dry run shows the fields that differ from LiveConfig's defaults, lr 3e-4 among them)
    "live": (dict(live_iterations=400, live_lr=5e-4), ["--live-iterations", "400", "--live-lr", "5e-4"],
             ("live", {"iterations": 400, "lr": 5e-4}), "live_iterations 400"),
    "intention": (dict(intention_steps=24000, intention_batch=256, intention_lr=6e-4),
                  ["--intention-steps", "24000", "--intention-batch", "256", "--intention-lr", "6e-4"],
                  ("cfg", {"steps": 24000, "batch": 256, "lr": 6e-4}), "intention_steps 24000"),
}


def test_the_runs_flags_are_the_configs_fields_with_their_comments_as_help():
    from conav_jax.eval.cli.args import config_from_args, field_docs

    parser = cli.build_parser()
    args = parser.parse_args(["reproduce", "--out", "o", "--rows", "none, all", "--resolution", "32x128", "--mirror",
                              "--live-lr", "0.01", "--dagger-rounds", "3"])
    expected = rp.ReproduceConfig(out=Path("o"), rows=("none", "all"), resolution=(32, 128), mirror=True, live_lr=0.01,
                                  dagger_rounds=3, workers=args.workers)
    assert config_from_args(rp.ReproduceConfig, args, out=Path("o")) == expected
    (sub,) = [a for a in parser._actions if a.dest == "command"]
    helps = {a.dest: a.help for a in sub.choices["reproduce"]._actions}
    docs = field_docs(rp.ReproduceConfig)
    assert helps["preset"] == f"{docs['preset']} (default paper)" and helps["rows"] == docs["rows"]
    assert helps["resolution"] == f"{docs['resolution']} (default 112x448)"


def _budget_step(cfg, kind):
    """The step a budget override of `kind` reaches: a live run, or the intention predictor's."""
    if kind == "live":
        (step,) = _trained(rp.plan_stages(cfg)[3])
    else:
        (step,) = [s for s in rp.plan_stages(cfg)[1].steps if s.call.kind == "train intention"]
    return step


@pytest.mark.parametrize("kind", sorted(BUDGET_OVERRIDE_CASES))
def test_a_budget_other_than_the_presets_is_an_out_directory_of_its_own(tmp_path, capsys, kind):
    from conav_jax.train.intention import INTENTION_TRAIN

    fields, flags, (keyword, expected), refused = BUDGET_OVERRIDE_CASES[kind]
    cfg = rp.ReproduceConfig(out=tmp_path, preset="paper", seeds=1, trainer="live", rows=("gt_all",), **fields)
    step = _budget_step(cfg, kind)
    config = _kw(step)[keyword]
    assert {k: getattr(config, k) for k in expected} == expected
    if kind == "live":
        assert config.lanes == rp.BUDGETS["paper"].live_lanes  # not overridden: the preset's
    else:
        assert rp.plan_stages(cfg)[1].outputs[0].name == "ckpt_00024000.npz"
        # The preset's own schedule keeps the published one: `conav train intention`'s batch and lr.
        default = _kw(_budget_step(rp.ReproduceConfig(out=tmp_path), kind))["cfg"]
        assert (default.batch, default.lr) == (INTENTION_TRAIN.batch, INTENTION_TRAIN.lr)
    progress = rpp.read_progress(tmp_path)
    rpp.check_out(progress, cfg)
    name = refused.split()[0]
    with pytest.raises(ValueError, match=rf"ReproduceConfig.{refused} \(given None\)"):
        rpp.check_out(progress, dataclasses.replace(cfg, **{name: None}))
    for field in fields:
        with pytest.raises(ValueError, match=f"ReproduceConfig.{field} must be positive"):
            dataclasses.replace(cfg, **{field: 0})
    # The command line: flags to fields, and into the configuration each --gpus process plans from.
    args = cli.build_parser().parse_args(["reproduce", "--preset", "paper", "--trainer", "live", "--out", str(tmp_path),
                                          *flags, "--dry-run"])
    assert args.func(args) == 0
    assert ", ".join(f"{k}={v!r}" for k, v in expected.items()) in capsys.readouterr().out
    stored = rr.load_config(tmp_path, rr.save_config(cfg))
    assert stored == cfg and [getattr(stored, f) for f in fields] == list(fields.values())
    assert all(getattr(stored, f) is None for f in rp.BUDGET_OVERRIDES if f not in fields)


@pytest.mark.parametrize("gpus", ["1", "2"])
def test_a_time_limit_starts_only_the_steps_that_end_within_it_with_their_evaluations(
        fake_conav, fake_children, tmp_path, gpus, capsys):
    calls, _ = fake_conav
    out = tmp_path / "r"
    assert _reproduce(out, "--seed", "0", "--gpus", gpus) == 0  # seed 0, and what every seed shares
    progress = rpp.read_progress(out)  # as recorded: a training 100 s, an evaluation 30 s
    progress["commands"].update({k: 100.0 if k.startswith("train ") else 30.0 if k.startswith("eval ") else v
                                 for k, v in progress["commands"].items()})
    rpp.write_progress(out, progress)
    ran = lambda: {Path(c.out).name for c in calls} | {Path(r["out"]).name for r in _runs(fake_children)}  # noqa: E731
    before = ran()
    capsys.readouterr()
    # 120 s: a seed-1 training (100 s) fits, but not with its evaluation (30 s): neither starts.
    assert _reproduce(out, "--gpus", gpus, "--time-limit", "120") == 0
    assert not {n for n in ran() - before if n.endswith("_s1")}
    assert "not started, for want of time: train policy runs/bc_none_s1" in capsys.readouterr().out
    assert "train policy runs/bc_none_s1" not in rpp.read_progress(out)["commands"]
    # 135 s: each fits, and the fake steps take no time, so the seed runs to its end.
    assert _reproduce(out, "--gpus", gpus, "--time-limit", "135") == 0
    assert {"bc_none_s1", "conav_bc_none_s1", "dagger_s1", "conav_dagger_s1"} <= ran() - before
    assert _reproduce(out, "--time-limit", "0") == 2


def test_a_time_limit_expects_a_run_to_take_as_long_as_its_configurations_other_seeds(
        fake_conav, fake_children, tmp_path, capsys):
    """A slower configuration's record (a DAgger run, the scripted agents' evaluation) does not
    stop a run whose own configuration's seeds fit: each step is reckoned by the steps alike it."""
    calls, _ = fake_conav
    ran = lambda: {Path(c.out).name for c in calls} | {Path(r["out"]).name for r in _runs(fake_children)}  # noqa: E731
    live = ("--trainer", "live")
    out = tmp_path / "r"
    assert _reproduce(out, *live, "--seed", "0", "--gpus", "1") == 0
    progress = rpp.read_progress(out)
    assert "train live runs/dagger_live_beta0_s0" in progress["commands"]
    progress["commands"] = {k: (400.0 if "dagger" in k else 100.0) if k.startswith("train ") else 30.0
                            for k in progress["commands"]}
    progress["commands"]["eval eval/scripted"] = 300.0  # as though it had run
    rpp.write_progress(out, progress)
    before = ran()
    capsys.readouterr()
    # 200 s: a BC run (100 s) with its evaluation (30 s) fits; a DAgger run (400 s) does not.
    assert _reproduce(out, *live, "--gpus", "1", "--time-limit", "200") == 0
    made = ran() - before
    assert {f"bc_{row}_s1" for row in ("none", "all", "gt_all")} | {"conav_bc_none_s1"} <= made
    assert "dagger_live_beta0_s1" not in made
    assert ("not started, for want of time: train live runs/dagger_live_beta0_s1 (expected 430 s with its run's "
            "evaluations, ") in capsys.readouterr().out


def test_a_time_limit_joins_runs_only_while_they_would_fit_one_after_another(fake_conav, fake_children, tmp_path):
    live = ("--trainer", "live", "--seeds", "3")
    for name, limit, joined in (("short", "200", False), ("long", "1000", True)):
        out = tmp_path / name
        assert _reproduce(out, *live, "--seed", "0", "--gpus", "1") == 0
        progress = rpp.read_progress(out)  # as recorded: a training 100 s, an evaluation 30 s
        progress["commands"].update({k: 100.0 if k.startswith("train ") else 30.0 if k.startswith("eval ") else v
                                     for k, v in progress["commands"].items()})
        rpp.write_progress(out, progress)
        start = len(_runs(fake_children))
        assert _reproduce(out, *live, "--gpus", "1", "--runs-per-process", "2", "--time-limit", limit) == 0
        trained = [r for r in _runs(fake_children)[start:] if "/runs/bc_" in r["out"]]
        # 200 s: a run with its evaluation (130 s) fits, two one after another (260 s) do not.
        assert len(trained) == 14 and {r["with"] for r in trained} == ({1} if joined else {0})  # 7 rows, 2 seeds
        after = rpp.read_progress(out)  # the runs of seeds 1 and 2 (BC and DAgger), recorded as run in pairs
        pairs = {k for k, n in after.get("joined", {}).items() if n == 2 and k.startswith("train ")}
        assert pairs == ({k for k in after["commands"] if k.startswith("train live") and k.endswith(("_s1", "_s2"))}
                         if joined else set()) and len(pairs) == (16 if joined else 0)


def test_expected_seconds_go_by_runs_that_ran_as_many_to_a_process():
    """A lone run goes by its configuration's lone runs, a pair by pairs (the process's time once,
    with both runs' evaluations); a size never run, by its runs' times added up. A stage's time
    counts a pair's process once."""
    plan = rp.plan_stages(rp.ReproduceConfig(out=Path("o"), preset="tiny", trainer="live", seeds=6, rows=("none",)))
    step = {st.name: st for stage in plan for st in stage.steps}
    run = lambda s: step[f"train live runs/bc_none_s{s}"]  # noqa: E731
    progress = {"commands": {"train live runs/bc_none_s0": 100.0, "train live runs/bc_none_s1": 250.0,
                             "train live runs/bc_none_s2": 250.0, "eval eval/conav_bc_none_s0": 30.0},
                "joined": {"train live runs/bc_none_s1": 2, "train live runs/bc_none_s2": 2}, "stages": {}}
    expected = rpp.expected_seconds(plan, progress)
    assert rpp.stage_seconds(plan, progress)["bc"] == 100.0 + 250.0 + 30.0  # the pair's process counted once
    assert expected([run(3)]) == 100.0 + 30.0
    assert expected([run(3), run(4)]) == 250.0 + 2 * 30.0
    assert expected([run(3), run(4), run(5)]) == 3 * (100.0 + 30.0)
    assert rpp.fits_in([run(3), run(4)], expected, 310.0) and not rpp.fits_in([run(3), run(4)], expected, 300.0)
    progress["joined"] = {}  # the pairs forgotten: a lone run goes by the longest of its configuration's
    assert expected([run(3)]) == 250.0 + 30.0
    # Runs that shared their GPU with another process count only where no run had a GPU to itself.
    progress["shared"] = {"train live runs/bc_none_s1": 2, "train live runs/bc_none_s2": 2}
    assert expected([run(3)]) == 100.0 + 30.0
    progress["commands"].pop("train live runs/bc_none_s0")
    assert expected([run(3)]) == 250.0 + 30.0


def test_a_group_size_never_run_in_its_configuration_goes_by_another_configurations_groups():
    """Two seeds of `all` in one process, never run so: `all`'s lone time scaled as a `none` pair
    took against a lone `none` (its evaluations added as lone ones); with no pair anywhere, the
    lone times added up."""
    plan = rp.plan_stages(rp.ReproduceConfig(out=Path("o"), preset="tiny", trainer="live", seeds=6,
                                             rows=("none", "all")))
    step = {st.name: st for stage in plan for st in stage.steps}
    run = lambda row, s: step[f"train live runs/bc_{row}_s{s}"]  # noqa: E731
    progress = {"commands": {"train live runs/bc_none_s0": 100.0, "train live runs/bc_none_s1": 150.0,
                             "train live runs/bc_none_s2": 150.0, "train live runs/bc_all_s0": 120.0,
                             "eval eval/conav_bc_all_s0": 40.0},
                "joined": {"train live runs/bc_none_s1": 2, "train live runs/bc_none_s2": 2}, "stages": {}}
    expected = rpp.expected_seconds(plan, progress)
    assert expected([run("all", 3), run("all", 4)]) == pytest.approx(1.5 * 120.0 + 2 * 40.0)
    assert expected([run("none", 3), run("none", 4)]) == 150.0 + 2 * 40.0  # its own pairs' record
    progress["shared"] = {"train live runs/bc_none_s1": 2, "train live runs/bc_none_s2": 2}  # no lone GPU
    assert expected([run("all", 3), run("all", 4)]) == 2 * (120.0 + 40.0)
    progress["shared"], progress["joined"] = {}, {}
    assert expected([run("all", 3), run("all", 4)]) == 2 * (120.0 + 40.0)


def test_the_dry_run_says_how_much_work_is_left_at_the_times_recorded(tmp_path, capsys):
    """Each stage and the whole plan: the steps done, and the steps left with their own times
    added up (a run's evaluation counted once, as its own step), by their configuration's
    recorded seeds; steps of a kind never finished are counted apart."""
    live = ("--trainer", "live", "--rows", "none", "--seeds", "3")
    out = tmp_path / "r"
    cfg = rp.ReproduceConfig(out=out, preset="tiny", trainer="live", seeds=3, rows=("none",))
    plan = rp.plan_stages(cfg)
    progress = {"commands": {"train live runs/bc_none_s0": 120.0, "eval eval/conav_bc_none_s0": 60.0}, "stages": {}}
    bc = next(stage for stage in plan if stage.name == "bc")
    assert [st.name for st in bc.steps].count("eval eval/conav_bc_none_s2") == 1  # a run's evaluation is bc's step
    assert rpp.time_left_text(plan, progress, bc.steps) == (
        "2 of 6 steps done; the 4 left: about 6 min one after another, at the times recorded")  # 2 x (120 + 60) s
    baselines = next(stage for stage in plan if stage.name == "baselines")
    assert rpp.time_left_text(plan, progress, baselines.steps).endswith(
        f"the {len(baselines.steps)} left have no time to go by")
    assert rpp.time_left_text(plan, {"commands": {st.name: 1.0 for st in bc.steps}, "stages": {}}, bc.steps) == (
        "6 of 6 steps done")
    # The command line says the same of an OUT holding these records.
    out.mkdir()
    rpp.write_progress(out, {**rpp.read_progress(out), **progress})
    assert _reproduce(out, *live, "--dry-run") == 0
    text = capsys.readouterr().out
    assert "[bc] to run (2 of 6 steps done; the 4 left: about 6 min one after another" in text
    assert "\nin all: 2 of " in text and "with no time to go by" in text.splitlines()[-1]


def test_a_time_limit_joins_runs_that_ran_joined_before_by_their_group_time(fake_conav, fake_children, tmp_path):
    """A group of two whose pairs took 120 s a process here (with 30 s evaluations: 180 s) joins
    in 200 s, though its runs one after another (300 s) would not fit."""
    live = ("--trainer", "live", "--seeds", "3")
    out = tmp_path / "r"
    assert _reproduce(out, *live, "--seed", "0", "--gpus", "1") == 0
    progress = rpp.read_progress(out)
    progress["commands"].update({k: 120.0 if k.startswith("train ") else 30.0 if k.startswith("eval ") else v
                                 for k, v in progress["commands"].items()})
    progress["joined"] = {k: 2 for k in progress["commands"] if k.startswith("train live runs/bc_")}
    rpp.write_progress(out, progress)
    start = len(_runs(fake_children))
    assert _reproduce(out, *live, "--gpus", "1", "--runs-per-process", "2", "--time-limit", "200") == 0
    trained = [r for r in _runs(fake_children)[start:] if "/runs/bc_" in r["out"]]
    assert len(trained) == 14 and {r["with"] for r in trained} == {1}


def test_packs_made_on_two_machines_at_once_join_into_one_out(fake_conav, tmp_path, capsys):
    import io
    import tarfile

    made = {seed: tmp_path / f"s{seed}" for seed in (0, 1)}  # each seed on a machine of its own
    for seed, out in made.items():
        assert _reproduce(out, "--seed", str(seed)) == 0
        progress = rpp.read_progress(out)  # the steps both made, timed apart
        progress["commands"].update({k: 1.0 + seed for k in progress["commands"] if not k.endswith(("_s0", "_s1"))})
        rpp.write_progress(out, progress)
        (out / "runs" / "intention" / "log.jsonl").write_text(json.dumps({"machine": seed}) + "\n")  # both made it
        assert _reproduce(out, "--stage", "pack") == 0
    joined = tmp_path / "joined"
    packs = [a for out in made.values() for a in ("--unpack", str(out / "pack.tar"))]
    assert _reproduce(joined, *packs, "--dry-run") == 0  # the first pack's results stay till the tables stage
    assert (joined / "results.json").read_bytes() == (made[0] / "results.json").read_bytes()
    assert _reproduce(joined, "--stage", "tables") == 0
    first, second = (rpp.read_progress(out) for out in made.values())
    progress = rpp.read_progress(joined)
    assert progress["commands"].keys() == first["commands"].keys() | second["commands"].keys()
    assert {k: progress["commands"][k] for k in first["commands"]} == first["commands"]  # the OUT's own win
    assert progress["commands"]["generate data"] == 1.0 and second["commands"]["generate data"] == 2.0
    assert json.loads((joined / "runs" / "intention" / "log.jsonl").read_text())["machine"] == 0
    tables = (joined / "tables.md").read_text()
    assert not [k for k in second["commands"] if k.endswith("_s0")]  # the machines' runs differ
    for seed in made:
        for row in ("none", "all"):
            assert (joined / "eval" / f"conav_bc_{row}_s{seed}" / "metrics.json").is_file()
            assert f"`eval/conav_bc_{row}_s{seed}`" not in tables  # not listed as not run yet
    # A pack of another configuration joins nothing.
    other = {**second, "config": {**second["config"], "preset": "paper"}}
    record = json.dumps(other).encode()
    with tarfile.open(tmp_path / "other.tar", "w") as tar:
        info = tarfile.TarInfo(rpp.PROGRESS_FILE)
        info.size = len(record)
        tar.addfile(info, io.BytesIO(record))
    before = rpp.read_progress(joined)
    capsys.readouterr()
    assert _reproduce(joined, "--unpack", str(tmp_path / "other.tar"), "--dry-run") == 2
    assert "cannot join" in (err := capsys.readouterr().err) and "preset tiny and paper" in err
    assert rpp.read_progress(joined) == before


def test_the_pack_leaves_out_a_trained_run_it_has_no_room_for_and_its_record(fake_conav, tmp_path, monkeypatch,
                                                                            capsys):
    import tarfile

    from conav_jax.checkpoints import checkpoint_path, save_checkpoint

    calls, state = fake_conav
    out = tmp_path / "r"
    state["fail_on"] = "eval/conav_bc_none_s1"
    assert _reproduce(out) == 1  # bc_none_s1 trained, its evaluation cut
    save_checkpoint(checkpoint_path(out / "runs" / "bc_none_s1", 5), params={"w": [1.0] * 4000}, opt_state=None,
                    config={"kind": "policy"}, step=5)
    cfg = rp.ReproduceConfig(out=out, preset="tiny", seeds=2)
    progress = rpp.read_progress(out)
    assert "train policy runs/bc_none_s1" in progress["commands"]
    members = rr.pack_members(cfg, progress)
    run_bytes = sum(p.stat().st_size for p in members if "bc_none_s1" in str(p))
    assert run_bytes > 0
    limit_mib = (sum(p.stat().st_size for p in members) - run_bytes // 2) / 2**20
    assert _reproduce(out, "--stage", "pack", "--pack-limit-mib", "0") == 2
    assert "--pack-limit-mib must be positive, got 0" in capsys.readouterr().err
    for flag in ("--pack-limit-mib", "--time-limit"):  # argparse reads both as floats
        assert _reproduce(out, "--stage", "pack", flag, "inf") == 2 and _reproduce(out, "--stage", "pack", flag, "nan") == 2
        assert capsys.readouterr().err.count(f"{flag} must be finite") == 2
    assert _reproduce(out, "--stage", "pack", "--pack-limit-mib", f"{limit_mib:.6f}") == 0
    assert f"left out of the pack for want of room: runs/bc_none_s1/ckpt_00000005.npz ({rr.TRAINS_AGAIN})" in \
        capsys.readouterr().out
    tar = tarfile.open(out / "pack.tar")
    assert not any("bc_none_s1" in n and n.endswith(".npz") for n in tar.getnames())
    assert "runs/bc_none_s1/log.jsonl" in tar.getnames()  # a record; a run trained again drops it
    packed = json.loads(tar.extractfile(rpp.PROGRESS_FILE).read())
    assert "train policy runs/bc_none_s1" not in packed["commands"] and "bc" not in packed["stages"]
    assert "train policy runs/bc_none_s0" in packed["commands"]
    assert "train policy runs/bc_none_s1" in rpp.read_progress(out)["commands"]  # this machine's record stays
    # A fresh machine continuing from the pack trains the run again, then evaluates it.
    calls.clear()
    assert _reproduce(tmp_path / "fresh", "--unpack", str(out / "pack.tar"), "--stage", "bc") == 0
    made = [Path(c.out).name for c in calls]
    assert made.index("bc_none_s1") < made.index("conav_bc_none_s1")
    assert "bc_none_s0" not in made
