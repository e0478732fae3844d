"""The study protocol: compute without matplotlib, draw into files, explicit reuse of trials."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from magctl.cli.common import to_jsonable
from magctl.control.status import STATUS_NAMES, Status
from magctl.core.errors import MagctlError
from magctl.loops import Experiment
from magctl.studies import push
from magctl.studies import runner as studies

CONVERGED, ATTEMPT_LIMIT = Status.CONVERGED, Status.ATTEMPT_LIMIT

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
GIF_MAGIC = b"GIF8"


def fake_trials(status, attempts, max_attempts: int, start_um: float = 300.0) -> dict:
    """Push-trial results in the shape of ``run_push_trials``: the error halves every attempt until the trial ends."""
    status, attempts = np.asarray(status), np.asarray(attempts)
    b = status.size
    err = np.full((b, max_attempts + 1), np.nan)
    for k in range(b):
        err[k, : attempts[k] + 1] = start_um * 0.5 ** np.arange(attempts[k] + 1) * (1 + 0.1 * k)
    final = err[np.arange(b), attempts]
    return {"status": status, "attempts": attempts, "error_um": err, "signed_error_um": err.copy(),
            "final_error_um": final, "frames": 100 * attempts, "correction_um": np.zeros(b)}


def fake_path(n_spheres: int = 1, frames: int = 6) -> dict:
    """A short straight drive past the spheres, in the shape of ``push.trial_path``."""
    t = np.arange(frames) / 30
    robot = np.c_[1e-3 + 1e-4 * t, np.full(frames, 1.8e-3)]
    spheres = np.tile(np.array([[2.0e-3, 1.8e-3], [2.6e-3, 1.8e-3]])[:n_spheres], (frames, 1, 1))
    return {"t": t, "robot_xy": robot, "robot_heading": np.zeros(frames), "spheres_xy": spheres, "title": "fake"}


def context(tmp_path, study: str, reuses=(), cache=None, trials: int = 4) -> studies.StudyContext:
    return studies.StudyContext(out=tmp_path / study, trials=trials, quiet=True, scheduler="serial",
                                trial_cache=cache if cache is not None else studies.TrialCache(), study=study,
                                reuses=tuple(reuses))


def test_every_study_defines_the_three_steps_and_valid_reuses():
    found = studies.discover()
    assert {"actuator", "stability", "servo", "sidepush-curve", "release", "front-push", "side-push",
            "convergence", "assembly"} <= set(found)
    for module in found.values():
        assert all(callable(getattr(module, step)) for step in studies.STEPS)
    studies.check_reuses(found)
    assert set(found["convergence"].REUSES) == {"front-push", "side-push"}


def ours(importer: str) -> bool:
    """Whether a module name is magctl's or a study's (``analysis/`` files load as ``magctl_study_*``)."""
    return importer.split(".")[0] == "magctl" or importer.startswith("magctl_study_")


def test_compute_needs_no_matplotlib(cheap_studies):
    """Importing every study and computing the cheap ones imports neither matplotlib nor a drawing
    module from magctl or study code (fresh interpreter)."""
    at_import, in_compute = cheap_studies["imports_at_import"], cheap_studies["imports_in_compute"]
    assert [i for i in at_import if ours(i[0])] == []
    assert [i for i in in_compute if ours(i[0])] == []
    assert cheap_studies["drawing_modules_loaded"] == []
    assert not any(ours(i[0]) for i in at_import + in_compute)


def test_the_import_record_sees_drawing(cheap_studies):
    """The same record caught the actuator's ``draw``, run last in the child, importing matplotlib:
    the check above can fail."""
    assert any(ours(importer) and name.split(".")[0] == "matplotlib"
               for importer, name in cheap_studies["imports_in_draw"])
    assert any(ours(importer) and name == "magctl.studies.figures"
               for importer, name in cheap_studies["imports_in_draw"])


def test_computed_results_are_plain_and_summarise(cheap_studies):
    for name, computed in cheap_studies["computed"].items():
        assert isinstance(computed, studies.Computed)
        json.dumps(to_jsonable(computed.results))  # plain numbers
        summary, paper = cheap_studies["summaries"][name]
        assert summary and all(isinstance(line, str) for line in summary)
        assert paper and all(isinstance(row, studies.PaperRow) for row in paper)


def test_a_study_missing_a_step_is_refused(tmp_path, monkeypatch):
    (tmp_path / "half.py").write_text("NAME = 'half'\ndef compute(ctx):\n    return None\n")
    monkeypatch.setenv("MAGCTL_STUDIES", str(tmp_path))
    with pytest.raises(MagctlError, match="draw, summarise"):
        studies.discover()


def test_check_reuses_refuses_unknown_and_later_studies():
    a = SimpleNamespace(ORDER=1)
    b = SimpleNamespace(ORDER=2, REUSES=("a",))
    studies.check_reuses({"a": a, "b": b})
    with pytest.raises(MagctlError, match="not a study"):
        studies.check_reuses({"a": a, "b": SimpleNamespace(ORDER=2, REUSES=("x",))})
    with pytest.raises(MagctlError, match="runs after it"):
        studies.check_reuses({"b": SimpleNamespace(ORDER=0, REUSES=("a",)), "a": a})


def test_trial_cache_gives_entries_only_to_the_studies_allowed():
    cache = studies.TrialCache()
    cache.store("k", "front-push", 42)
    assert "k" in cache and len(cache) == 1
    assert cache.lookup("k", ("front-push",)) == ("front-push", 42)
    assert cache.lookup("k", ("convergence", "front-push")) == ("front-push", 42)
    assert cache.lookup("k", ("convergence",)) is None
    assert cache.lookup("other", ("front-push",)) is None
    cache.store("k", "convergence", 43)  # its own entry; the front-push one stays
    assert len(cache) == 2
    assert cache.lookup("k", ("convergence", "front-push")) == ("convergence", 43)
    assert cache.lookup("k", ("front-push",)) == ("front-push", 42)


@pytest.fixture
def fake_sweeps(monkeypatch):
    """Replace the trial fan-out by a recorder returning fake trials (so no simulation runs)."""
    calls = []

    def run_sweeps(jobs, **kw):
        calls.append(sorted(jobs))
        return {label: fake_trials([CONVERGED] * n, [1] * n, 2) for label, (_, n, _) in jobs.items()}

    import magctl.sweep

    monkeypatch.setattr(magctl.sweep, "run_sweeps", run_sweeps)
    return calls


def test_run_experiments_reuses_only_declared_studies(tmp_path, fake_sweeps):
    exps = {"a": Experiment("front", task=dict(kc=1.0), label="a"), "b": Experiment("side", label="b")}
    cache = studies.TrialCache()
    first, src = push.run_experiments(context(tmp_path, "front-push", cache=cache), exps, 4)
    assert fake_sweeps == [["a", "b"]] and src == {"a": "front-push", "b": "front-push"}

    # a study that declares the reuse gets the same objects, nothing runs
    again, src = push.run_experiments(context(tmp_path, "convergence", ("front-push",), cache), {"x": exps["a"]}, 4)
    assert again["x"] is first["a"] and src == {"x": "front-push"} and len(fake_sweeps) == 1

    # one that does not declare it runs its own trials
    own, src = push.run_experiments(context(tmp_path, "assembly", cache=cache), {"a": exps["a"]}, 4)
    assert own["a"] is not first["a"] and src == {"a": "assembly"} and fake_sweeps[-1] == ["a"]

    # other trial counts or seeds are other trials
    push.run_experiments(context(tmp_path, "front-push", cache=cache), {"a": exps["a"]}, 5)
    assert len(fake_sweeps) == 3


def test_reuse_note_names_the_studies():
    note = push.reuse_note({"ctl-a": "front-push", "ctl-b": "convergence"}, "convergence")
    assert "ctl-a from the front-push study" in note and "ctl-b" not in note
    assert "reused" not in push.reuse_note({"ctl-a": "convergence"}, "convergence")


def test_controller_summary_counts_against_hand_numbers():
    """Four trials: converged at attempts 1, 2, 3 and one stopped at the 5-attempt limit."""
    r = fake_trials([CONVERGED, CONVERGED, CONVERGED, ATTEMPT_LIMIT], [1, 2, 3, 5], 5)
    s = push.controller_summary(r)
    assert s["trials"] == 4 and s["converged_fraction"] == 0.75
    assert s["converged_by_attempt"] == [0.25, 0.5, 0.75, 0.75, 0.75]
    assert s["mean_attempts_converged"] == pytest.approx(2.0)
    assert s["mean_attempts_all"] == pytest.approx((1 + 2 + 3 + 5) / 4)
    assert s["status"][STATUS_NAMES[CONVERGED]] == 3 and s["status"][STATUS_NAMES[ATTEMPT_LIMIT]] == 1
    # a finished trial's last error is carried forward: trial 0 ends at 150 µm after attempt 1
    assert s["mean_error_um_by_attempt"][5] == pytest.approx(np.mean([150, 330 / 4, 360 / 8, 390 / 32]))


def _fake_push_cache(front, side, max_front: int, max_side: int, n: int):
    """A trial cache holding fake trials for every controller of the front- and side-push studies."""
    cache = studies.TrialCache()
    status = [CONVERGED] * (n - 1) + [ATTEMPT_LIMIT]
    for study, module, max_att in (("front-push", front, max_front), ("side-push", side, max_side)):
        exps = module.controllers(module.model_delta0()) if study == "front-push" else module.experiments()
        for i, exp in enumerate(exps.values()):
            attempts = [min(1 + i + k, max_att) for k in range(n - 1)] + [max_att]
            cache.store(push.trials_key(exp, n, 0), study, fake_trials(status, attempts, max_att))
            cache.store(push.path_key(exp, 0), study, fake_path())
    return cache


def test_push_studies_compute_from_cached_trials_and_draw(tmp_path):
    """Front push, side push and convergence from fake cached trials: results, reuse, and every figure drawn."""
    found = studies.discover()
    front, side = found["front-push"], found["side-push"]
    n = 4
    cache = _fake_push_cache(front, side, front.MAX_ATTEMPTS, side.MAX_ATTEMPTS, n)
    paths = []
    for name in ("front-push", "side-push", "convergence"):
        ctx = context(tmp_path, name, cache=cache, trials=n)  # compute() sets the study's own REUSES
        computed = studies.compute(name, ctx)
        json.dumps(to_jsonable(computed.results))
        summary, paper = found[name].summarise(computed)
        assert summary and paper
        paths += found[name].draw(computed, ctx)
        if name == "front-push":
            # controller i converges at attempts 1+i, 2+i, 3+i and fails once: hand numbers
            s = computed.results["controllers"]["K_c=0.5, δ(0)=0"]  # third controller (i = 2)
            assert s["converged_fraction"] == 0.75 and s["mean_attempts_converged"] == pytest.approx(4.0)
            assert computed.results["naive_steady_error_um"] == pytest.approx(300 * 0.5 ** front.MAX_ATTEMPTS * 1.3)
        if name == "convergence":
            r = computed.results
            assert r["trials_from_study"] == {r["front_controller"]: "front-push", r["side_controller"]: "side-push"}
            assert r["front_95pct_converged_after_attempts"] is None  # one trial in four never converges
            assert any("reused" in line and "front-push" in line for line in summary)
    assert len(paths) == 3 + 3 + 1
    for p in paths:
        head = p.read_bytes()[:8]
        assert p.stat().st_size > 1000 and head.startswith(PNG_MAGIC if p.suffix == ".png" else GIF_MAGIC), p


def test_assembly_computes_from_cached_trials_and_draws(tmp_path):
    found = studies.discover()
    asm = found["assembly"]
    cache = studies.TrialCache()
    exps = asm.experiments()
    for exp in exps.values():
        cache.store(push.trials_key(exp, 3, 0), "assembly",
                    fake_trials([CONVERGED, ATTEMPT_LIMIT, CONVERGED], [2, 10, 4], 10))
        cache.store(push.path_key(exp, 0), "assembly", fake_path(n_spheres=2))
    ctx = context(tmp_path, "assembly", cache=cache, trials=3)
    computed = studies.compute("assembly", ctx)
    for s in computed.results["methods"].values():
        assert s["converged_fraction"] == pytest.approx(2 / 3)
        assert s["mean_attempts_all"] == pytest.approx((2 + 10 + 4) / 3)
    paths = asm.draw(computed, ctx)
    assert computed.results["fig15_side_passes_median"] == pytest.approx(np.median([2 - 1, 4 - 1]))
    summary, paper = asm.summarise(computed)
    assert all(row.verdict and row.section == "§VI-C" for row in paper)
    assert [p.suffix for p in paths] == [".png", ".gif", ".gif", ".gif"] and all(p.stat().st_size > 1000 for p in paths)


def test_beyond_computes_from_cached_trials_and_judges_its_targets(tmp_path):
    """The beyond study from fake trials: hand numbers for the summaries and the targets, the figure drawn, and
    the attempt-map grid (curve law within 5 attempts of the floor wherever the floor is within 30)."""
    beyond = studies.discover()["beyond"]
    exps = beyond.experiments() | beyond.front_experiments() | beyond.assembly_experiments()
    n = 4
    attempts = {beyond.CURVE: [4, 5, 6, 11], "lin-fit, K_s=0.9": [5, 6, 6, 7],
                f"{beyond.CURVE}, dirt": [5, 6, 20, 30], "lin-fit, K_s=0.9, dirt": [5, 6, 22, 30],
                f"{beyond.CURVE_FRONT}, dirt": [5, 6, 7, 9], beyond.RELEASE: [2, 3, 4, 10], beyond.KC1: [2, 2, 3, 4],
                beyond.FRONT_SIDE: [1, 2, 2, 2]}
    kc1_model = next(label for label in exps if label.startswith("K_c=1,") and label != beyond.KC1)
    attempts[kc1_model] = [2, 3, 3, 4]          # slower than δ(0) = 0 here: the baseline stays beyond.KC1
    planned, greedy = beyond.PLANNED, beyond.GREEDY
    attempts |= {label: [12, 14, 16, 18] for label in beyond.assembly_experiments()}
    attempts |= {f"3 line, {planned}": [18, 20, 22, 30], f"3 line, {greedy}": [25, 30, 30, 30],
                 f"3 triangle, {planned}": [15, 16, 18, 21], f"3 triangle, {greedy}": [14, 16, 18, 20],
                 f"2 pair, {planned}": [8, 9, 10, 11]}
    cache = studies.TrialCache()
    for label, exp in exps.items():
        limit = 10 if label in (beyond.RELEASE, beyond.KC1, kc1_model, beyond.FRONT_SIDE) else 30
        status = [CONVERGED] * (n - 1) + [ATTEMPT_LIMIT if attempts[label][-1] == limit else CONVERGED]
        cache.store(push.trials_key(exp, n, 0), "beyond", fake_trials(status, attempts[label], limit))
    computed = studies.compute("beyond", context(tmp_path, "beyond", cache=cache, trials=n))
    s = computed.results["controllers"]
    assert s[beyond.CURVE]["mean_attempts_all"] == pytest.approx(6.5)
    assert s[beyond.CURVE]["converged_by"] == {"4": 0.25, "10": 0.75, "30": 1.0}
    assert s[f"{beyond.CURVE}, dirt"]["attempts_p95"] == pytest.approx(np.percentile([5, 6, 20, 30], 95))
    met = [ok for _, _, ok in beyond.targets(computed.results)]
    assert met == [False, False, True]  # mean 6.5 > 5; 75 % by 10; with dirt 95th percentile 8.7 below 28.8
    fc = computed.results["front_controllers"]
    assert fc[beyond.RELEASE]["mean_attempts_all"] == pytest.approx(4.75)
    assert fc[beyond.KC1]["mean_attempts_all"] == pytest.approx(2.75)
    assert beyond.kc1_baseline(fc) == computed.results["kc1_baseline"] == beyond.KC1      # 2.75 against 3.0
    assert computed.results["front_bound"]["kc1_delta0_um"] == 0.0
    assert beyond.front_target(computed.results)[2] is False  # 2 attempts worse, not 0.5 better
    assert fc[beyond.FRONT_SIDE]["mean_attempts_all"] == pytest.approx(1.75)
    assert beyond.front_side_target(computed.results)[2] is True   # 1.75 against 2.75: 1 attempt fewer
    a = computed.results["assembly"]
    assert a[f"3 line, {planned}"]["assembled"] == pytest.approx(0.75)       # the 30-pass trial hit the limit
    assert a[f"3 line, {planned}"]["passes_mean"] == pytest.approx(20.0)
    assert a[f"3 line, {planned}"]["passes_all_mean"] == pytest.approx(22.5)
    assert a[f"3 line, {greedy}"]["passes_all_mean"] == pytest.approx(28.75)
    met = [ok for _, _, ok in beyond.assembly_targets(computed.results)]
    # line: 75 % < 90 %, 22.5 < 28.75 passes; triangle: 100 %, 17.5 > 17 passes; pair: 9.5 < 15 passes
    assert met[:5] == [False, True, True, False, True]
    assert computed.results["pair_question"][1]["planned_passes"] <= computed.results["pair_question"][1][
        "greedy_passes"]
    summary, paper = beyond.summarise(computed)
    assert paper == [] and any("**missed**" in line for line in summary)
    assert any(line.startswith("| 3 triangle, planned") for line in summary)
    for row in computed.results["scale_grid"]:
        if row["fewest"] <= 25:
            assert row["curve"] is not None and row["curve"] <= row["fewest"] + 5, row
    paths = beyond.draw(computed, context(tmp_path, "beyond", cache=cache, trials=n))
    assert len(paths) == 3 and all(p.read_bytes()[:8] == PNG_MAGIC for p in paths)


def test_beyond_states_the_bound_only_where_its_numbers_hold():
    """The release-model bound sentence: "no member gains" only when the gain is short of the target and no fold's
    later-attempt success reaches the need; otherwise it says the bound does not rule the target out."""
    beyond = studies.discover()["beyond"]
    fb = {"gain_attempts": 0.14, "first_success_best": 0.55, "kc1_mean_attempts": 2.26, "later_success_needed": 0.59,
          "conditional_release_std_um": 51.5, "eps_um": 75.0, "normal_cap": 0.855,
          "folds": {"0→1": {"policy_later_success": 0.45}, "1→0": {"policy_later_success": 0.44}}}
    assert "no member of the family gains" in beyond.bound_sentence(fb) and "44%–45%" in beyond.bound_sentence(fb)
    fb |= {"gain_attempts": 0.61, "later_success_needed": 0.36}
    assert "does not rule the target out" in beyond.bound_sentence(fb)
    fb |= {"gain_attempts": 0.3}       # short of the target, but within the later success's reach
    assert "does not rule the target out" in beyond.bound_sentence(fb)


def test_cheap_studies_draw_nonempty_pngs(cheap_studies, tmp_path):
    """Every cheap study draws its figures from the results its compute step returned."""
    found = studies.discover()
    expected = {"actuator": 1, "stability": 4, "servo": 2, "release": 1, "sidepush-curve": 2}
    for name, computed in cheap_studies["computed"].items():
        ctx = studies.StudyContext(out=tmp_path / name, quiet=True)
        paths = found[name].draw(computed, ctx)
        assert len(paths) == expected[name], name
        for p in paths:
            assert p.parent == tmp_path / name and p.suffix == ".png"
            assert p.stat().st_size > 1000 and p.read_bytes()[:8] == PNG_MAGIC, p


def test_run_study_without_figures_writes_nothing(tmp_path):
    res = studies.run_study("actuator", studies.StudyContext(out=tmp_path / "s", quiet=True), figures=False)
    assert res.name == "actuator" and res.figures == [] and not (tmp_path / "s").exists()
    assert res.summary and res.paper and res.results["nominal_speed_um_s"] > 0
