"""What a reader of the paper sees in the studies' figures and summaries.

Every text of a figure (titles, axis labels, tick labels, legends, annotations, colourbar labels)
is collected just before :func:`magctl.studies.figures.save_figure` writes it, and must write the
micrometre as µm, never as "um". The Fig 14 figure carries the paper's claim (all trials within
ε_p by attempt 4 front, 10 side) with our share of trials there; the stability-region figure a
colourbar labelled K_s; the push figures draw every controller in its own style, so curves that
coincide stay visible. The stability study runs at few trials; the push and Fig 14 figures are
drawn from small synthetic results (their trials take minutes), shaped as ``compute`` returns them.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from magctl.studies import figures
from magctl.studies import runner as studies
from magctl.studies.push import carried_errors, controller_summary

UM_WORD = re.compile(r"\bum\b")


def figure_record(fig) -> dict:
    """Every text of ``fig`` (after a draw, so tick labels exist), its colourbar labels and its labelled lines."""
    from matplotlib.text import Text

    fig.canvas.draw()
    texts = [t.get_text() for t in fig.findobj(Text) if t.get_text()]
    colourbars = [ax.get_ylabel() or ax.get_xlabel() for ax in fig.axes if hasattr(ax, "_colorbar")]
    lines = {line.get_label(): line for ax in fig.axes for line in ax.get_lines()
             if not line.get_label().startswith("_")}
    return {"texts": texts, "colourbars": colourbars,
            "lines": {k: {"ls": v.get_linestyle(), "marker": v.get_marker(), "color": v.get_color(),
                          "y": np.asarray(v.get_ydata(), dtype=float)} for k, v in lines.items()}}


@pytest.fixture
def saved(monkeypatch) -> dict:
    """Stem of each figure file → :func:`figure_record` of the figure, taken as it is saved."""
    records = {}
    real = figures.save_figure

    def spy(fig, path, dpi=120):
        records[Path(path).stem] = figure_record(fig)
        return real(fig, path, dpi)

    monkeypatch.setattr(figures, "save_figure", spy)
    return records


def um_words(lines) -> list[str]:
    return [t for t in lines if UM_WORD.search(t)]


def test_the_check_sees_um_anywhere_in_a_figure(saved, tmp_path):
    """The collector reaches axis labels, legends, annotations and colourbars (so the tests below can fail)."""
    plt = figures.pyplot()
    for where in ("xlabel", "legend", "annotation", "colourbar", "tick"):
        fig, ax = plt.subplots()
        sc = ax.scatter([1, 2], [1, 2], c=[0, 1], label="points (µm)")
        cb = fig.colorbar(sc, ax=ax, label="K_s")
        if where == "xlabel":
            ax.set_xlabel("gap (um)")
        elif where == "legend":
            ax.plot([1, 2], [2, 1], label="ε_p = 7.5 um")
        elif where == "annotation":
            ax.annotate("300 um", (1, 1))
        elif where == "colourbar":
            cb.set_label("gap (um)")
        else:
            ax.set_xticks([1, 2], ["1 um", "2 um"])
        ax.legend()
        figures.save_figure(fig, tmp_path / f"{where}.png")
        assert um_words(saved[where]["texts"]), where
    assert not UM_WORD.search("300 µm, ε_p = 7.5 µm, radius_um, drum")


@pytest.fixture(scope="module")
def stability(tmp_path_factory):
    ctx = studies.StudyContext(out=tmp_path_factory.mktemp("stability"), trials=200, quiet=True, scheduler="serial")
    return studies.compute("stability", ctx), ctx


def test_stability_figures_and_summary(stability, saved):
    computed, ctx = stability
    module = studies.get("stability")
    paths = module.draw(computed, ctx)
    assert {p.stem for p in paths} <= set(saved) and len(saved) == 4
    for stem, rec in saved.items():
        assert not um_words(rec["texts"]), stem
    for stem in ("stability_front_convergence", "stability_side_maps"):
        assert any("µm" in t for t in saved[stem]["texts"]), stem
    assert any("K_s" in label for label in saved["stability_regions"]["colourbars"])
    assert any("K_s" in label for label in saved["stability_pole_paths"]["colourbars"])
    summary, paper = module.summarise(computed)
    report = summary + [f"{r.quantity} | {r.paper} | {r.magctl} | {r.note}" for r in paper]
    assert not um_words(report)


def test_every_stability_axis_is_labelled(stability, monkeypatch, tmp_path):
    computed, _ = stability
    unlabelled = []

    def spy(fig, path, dpi=120):
        for ax in fig.axes:
            if not ax.axison:
                continue
            if hasattr(ax, "_colorbar"):
                if not (ax.get_ylabel() or ax.get_xlabel()):
                    unlabelled.append((Path(path).stem, "colourbar"))
            elif not (ax.get_xlabel() and ax.get_ylabel()):
                unlabelled.append((Path(path).stem, ax.get_title()))
        figures.pyplot().close(fig)
        return path

    monkeypatch.setattr(figures, "save_figure", spy)
    studies.get("stability").draw(computed, studies.StudyContext(out=tmp_path, quiet=True))
    assert not unlabelled


def synthetic_run(rng, n_trials: int, max_attempts: int, start_um: float, eps_um: float, rate: float,
                  stuck: int = 0) -> dict:
    """Push trials shaped as :func:`magctl.studies.trials.run_push_trials` returns them: the error shrinks by
    ``rate`` per attempt until within ``eps_um`` (then the trial stops: NaN after); ``stuck`` trials never get there."""
    from magctl.control.status import Status

    err = np.full((n_trials, max_attempts + 1), np.nan)
    status = np.full(n_trials, int(Status.CONVERGED))
    attempts = np.zeros(n_trials, dtype=int)
    for k in range(n_trials):
        e = start_um * rng.uniform(0.9, 1.1)
        err[k, 0] = e
        for a in range(1, max_attempts + 1):
            e = 1.5 * eps_um if k < stuck else e * rate * rng.uniform(0.8, 1.2)
            err[k, a] = e
            if e <= eps_um:
                break
        attempts[k] = a
        if err[k, a] > eps_um:
            status[k] = int(Status.ATTEMPT_LIMIT)
    return {"error_um": err, "status": status, "attempts": attempts, "signed_error_um": err,
            "final_error_um": np.array([row[np.isfinite(row)][-1] for row in err])}


def convergence_computed() -> studies.Computed:
    """A Computed shaped as the convergence study's, 20 trials: every front trial within ε_p by attempt 4,
    side: 2 of 20 stuck outside (90 % by attempt 10)."""
    rng = np.random.default_rng(0)
    front = synthetic_run(rng, 20, 10, 700.0, 75.0, 0.35)
    side = synthetic_run(rng, 20, 30, 300.0, 7.5, 0.6, stuck=2)
    module = studies.get("convergence")
    f_sum, s_sum = controller_summary(front), controller_summary(side)
    f_err, s_err = carried_errors(front), carried_errors(side)
    results = {
        "front_controller": "K_c=1, δ(0)=98 µm", "side_controller": "lin, K_s=0.9", "trials": 20,
        "front_mean_error_um": np.nanmean(f_err, axis=0).tolist(),
        "side_mean_error_um": np.nanmean(s_err, axis=0).tolist(),
        "front_all_converged_after_attempts": module.attempts_until(f_sum, 1.0),
        "side_all_converged_after_attempts": module.attempts_until(s_sum, 1.0),
        "front_95pct_converged_after_attempts": module.attempts_until(f_sum, 0.95),
        "side_95pct_converged_after_attempts": module.attempts_until(s_sum, 0.95),
        "side_late_overshot_fraction": module.late_overshot(side, 10, 7.5),
        "trials_from_study": {"K_c=1, δ(0)=98 µm": "convergence", "lin, K_s=0.9": "convergence"},
    }
    data = {"front_error_um": f_err, "side_error_um": s_err,
            "front_converged_by_attempt": f_sum["converged_by_attempt"],
            "side_converged_by_attempt": s_sum["converged_by_attempt"],
            "front_eps_um": 75.0, "side_eps_um": 7.5, "front_max_attempts": 10, "side_max_attempts": 30}
    return studies.Computed(results, data)


def test_fig14_carries_the_paper_claim_and_our_share(saved, tmp_path):
    computed = convergence_computed()
    module = studies.get("convergence")
    d = computed.data
    assert d["front_converged_by_attempt"][3] == 1.0 and d["side_converged_by_attempt"][9] == pytest.approx(0.9)
    module.draw(computed, studies.StudyContext(out=tmp_path, quiet=True))
    texts = saved["convergence"]["texts"]
    assert not um_words(texts)
    joined = "\n".join(texts)
    assert "paper: all within ε_p by attempt 4" in joined
    assert "paper: all within ε_p by attempt 10" in joined
    assert "ours: 100% of 20 trials" in joined and "ours: 90% of 20 trials" in joined
    assert "after 4 attempts for front pushing, and 10 for side pushing" in joined
    summary, paper = module.summarise(computed)
    assert not um_words(summary + [f"{r.quantity} {r.paper} {r.magctl} {r.note}" for r in paper])
    # the two stuck side trials never stepped past the goal: the overshoot cause does not hold for them
    side_row = next(r for r in paper if r.section == "§VI-B")
    assert computed.results["side_late_overshot_fraction"] == 0.0 and side_row.cause.startswith("unexplained:")


def test_push_figures_keep_coinciding_curves_visible(saved, tmp_path):
    """Two controllers with identical results stay two visible curves: own style, offset convergence curve."""
    rng = np.random.default_rng(1)
    labels = ["D_g=370 µm fixed", "D_g=500 µm fixed", "lin, K_s=0", "lin, K_s=0.9"]
    same = synthetic_run(rng, 8, 30, 300.0, 7.5, 0.5)
    runs = {labels[0]: same, labels[1]: same, labels[2]: synthetic_run(rng, 8, 30, 300.0, 7.5, 0.7, stuck=3),
            labels[3]: synthetic_run(rng, 8, 30, 300.0, 7.5, 0.4)}
    summaries = {k: controller_summary(r) for k, r in runs.items()}
    figures.plot_convergence(summaries, tmp_path / "conv.png", "Side pushing, 8 trials per controller", 30)
    figures.plot_errors(runs, tmp_path / "err.png", "Side pushing error", 7.5, log=True)
    for stem, suffix in (("conv", " (N_p = "), ("err", ": median")):
        rec = saved[stem]
        assert not um_words(rec["texts"]), stem
        assert any("µm" in t for t in rec["texts"]), stem
        lines = [next(ln for name, ln in rec["lines"].items() if name.startswith(k + suffix)) for k in labels]
        assert len({(ln["ls"], ln["marker"]) for ln in lines}) == len(labels), stem
        assert len({ln["color"] for ln in lines}) == len(labels), stem
    conv = {k: next(ln for name, ln in saved["conv"]["lines"].items() if name.startswith(k + " (")) for k in labels}
    assert not np.allclose(conv[labels[0]]["y"], conv[labels[1]]["y"])      # offset, not drawn over each other
    assert np.allclose(conv[labels[0]]["y"] - conv[labels[1]]["y"], conv[labels[0]]["y"][0] - conv[labels[1]]["y"][0])
    assert any("offset" in t for t in saved["conv"]["texts"])               # and the axis says so
