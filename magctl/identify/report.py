"""The identification's one-page report: the fits, what the identified plant means for the controllers, and,
given held-out logs, the identified plant's predictions against what those runs did.

Recommendations come from ``magctl --models DIR stability front|side|servo --json`` run as separate processes on
the written folder — the commands a user runs, on the parameters they will use — so the report cannot disagree
with them.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from magctl.config import load_file
from magctl.core.errors import MagctlError
from magctl.identify.phases import attempts_to_converge, side_passes
from magctl.identify.run import Identification
from magctl.identify.side import measured, pass_noise


def _magctl_json(folder: Path, *args: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "MAGCTL_MODELS"}
    cmd = [sys.executable, "-m", "magctl", "--models", str(folder), *args, "--json"]
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    if done.returncode != 0:
        raise MagctlError(f"magctl {' '.join(args)} on {folder} failed: {done.stderr.strip()[-300:]}")
    return json.loads(done.stdout)


def recommend(folder: Path, kc: float | None = None, ks: float | None = None) -> dict:
    """The paper's controllers on the identified plant: the front push's stable K_c range and predicted attempts
    (δ(0) = 0 and δ(0) = the identified mean release), the side push's stable K_s ranges and verdict at ``ks``,
    the servo's margins at the identified camera lag; and the gains to run. ``kc``, ``ks`` default to the
    folder's ``push.toml`` (the paper's K_c = 1, K_s = 0.9 unless changed)."""
    push = load_file(Path(folder) / "push.toml")
    kc = float(push.front.kc) if kc is None else kc
    ks = float(push.side.ks) if ks is None else ks
    front0 = _magctl_json(folder, "stability", "front", "--kc", repr(kc))
    release = front0["convergence"]["release_mean_um"] if front0.get("convergence") else 0.0
    front_model = _magctl_json(folder, "stability", "front", "--kc", repr(kc), "--delta0-um", repr(release))
    side = _magctl_json(folder, "stability", "side", "--ks", repr(ks))
    servo = _magctl_json(folder, "stability", "servo")

    def mean_attempts(doc):
        c = doc.get("convergence") or {}
        p = np.asarray(c.get("p_attempt_markov", []), float)
        if p.size == 0:
            return None
        miss = float(c["p_not_converged_markov"])
        return float((np.arange(1, p.size + 1) * p).sum() + p.size * miss)

    a0, am = mean_attempts(front0), mean_attempts(front_model)
    best_delta0 = release if (am is not None and a0 is not None and am < a0) else 0.0
    ranges = side["switched"]["stable_gain_ranges"]
    ks_ok = any(lo <= ks <= hi for lo, hi in ranges)
    wide = max(ranges, key=lambda r: r[1] - r[0]) if ranges else None
    ks_run = ks if ks_ok or wide is None else round(0.5 * (wide[0] + wide[1]), 2)
    return {
        "front": {"kc": kc, "stable_gain_range": front0["stable_gain_range"], "release_mean_um": release,
                  "mean_attempts_delta0_0": a0, "mean_attempts_delta0_release": am, "delta0_um": best_delta0},
        "side": {"ks": ks, "verdict": side["verdict"], "stable_gain_ranges": ranges, "ks_to_run": ks_run},
        "servo": {k: servo[k] for k in ("delay_frames", "stable", "gain_margin", "phase_margin_deg",
                                        "sim_overshoot_um", "settling_time_s")},
        "run": (f"magctl --models {folder} rig run --task front-push --kc {kc:g} --option delta0_um={best_delta0:.4g}; "
                f"magctl --models {folder} rig run --task side-push --option ks={ks_run:g}"),
    }


def validate(result: Identification, holdout, recommendations: dict | None) -> dict:
    """The identified plant against held-out runs: per-pass displacement predicted at each logged pass's gap,
    and front-push attempts-to-converge predicted (the iteration-domain analysis at the logged K_c) against
    logged."""
    out: dict = {}
    passes = side_passes(holdout)
    if passes and result.side is not None:
        gaps = np.array([p.gap for p in passes])
        logged = np.array([p.displacement for p in passes])
        predicted = np.exp(measured(np.log(result.side.plant.predict(gaps)), result.fix_noise))
        ok = (logged > 0) & np.isfinite(predicted)
        err = np.log(predicted[ok] / logged[ok])
        # against the passes' own scatter (the plant fit's noise model): |z| ≲ 2 is a prediction within it
        s_abs, s_rel = pass_noise()
        z = (logged[ok] - predicted[ok]) / np.hypot(s_rel * predicted[ok], s_abs)
        out["side_passes"] = {"n": int(len(passes)), "gap_um": (gaps * 1e6).tolist(),
                              "logged_um": (logged * 1e6).tolist(), "predicted_um": (predicted * 1e6).tolist(),
                              "compared": int(ok.sum()), "log_error_mean": float(err.mean()) if ok.any() else None,
                              "log_error_rms": float(np.sqrt((err**2).mean())) if ok.any() else None,
                              "z_rms": float(np.sqrt((z**2).mean())) if ok.any() else None}
    fronts = attempts_to_converge(holdout, "front-push")
    if fronts and recommendations:
        n = np.array([a for _, a, _ in fronts])
        out["front_attempts"] = {"runs": len(fronts), "logged": n.tolist(), "logged_mean": float(n.mean()),
                                 "predicted_mean": recommendations["front"]["mean_attempts_delta0_0"]}
    return out


def _figures(result: Identification, folder: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    made = []

    def figure(name: str, draw, xlabel: str, ylabel: str, legend: dict | None = None) -> None:
        fig, ax = plt.subplots(figsize=(5, 3.2))
        draw(ax)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        if legend is not None:
            ax.legend(fontsize=7, **legend)
        fig.tight_layout()
        fig.savefig(folder / name, dpi=110)
        plt.close(fig)
        made.append(name)

    if result.speed is not None:
        s = result.speed

        def speed(ax):
            for amp in np.unique(s["b_osc"]):
                m = s["b_osc"] == amp
                ax.plot(s["freq"][m], s["speed"][m] * 1e3, "o", label=f"{amp * 1e3:.3g} mT")

        figure("identify-speed.png", speed, "field frequency [Hz]", "robot speed [mm/s]",
               {"title": "oscillating field"})
    if result.side is not None:
        c = result.side.curves()
        gaps, disp = result.side_data

        def side(ax):
            ax.semilogy(gaps * 1e6, disp * 1e6, "o", label="logged passes")
            ax.semilogy(c["gap"] * 1e6, c["eq22"] * 1e6, "-", label="eq 22 fit")
            ax.semilogy(c["gap"] * 1e6, c["plant"] * 1e6, "--", label="flow model fit (depth, mobility)")

        figure("identify-side.png", side, "side gap D_g [µm]", "sphere displacement D_s [µm]", {})
    if result.release is not None:
        r = result.release
        figure("identify-release.png", lambda ax: ax.hist(r.release * 1e6, bins=max(5, r.n // 3)),
               "release D_p,r [µm]", "attempts")
    return made


def write_report(folder: Path, result: Identification, recommendations: dict | None, validation: dict | None,
                 figures: bool = True) -> Path:
    """``folder/report.md``: one page of fits, recommendations and validation."""
    lines = [f"# Identification of {len(result.runs)} run log(s)", "",
             "Parameter folder: this folder (`magctl --models " + str(folder) + " …`).", "",
             "## Identified", "", "| parameter | value | ± 1σ | from |", "|---|---|---|---|"]
    for e in result.estimates:
        lines.append(f"| `{e.name}` | {e.value:.4g} | {e.uncertainty:.2g} | {e.evidence} |")
    lines += ["", "## Not identified (defaults kept)", ""]
    lines += [f"- **{k}**: {v}" for k, v in result.not_identified.items()] or ["- nothing: every fit ran"]
    if result.side is not None:
        lines += ["", "## Side-push curve", "", f"- eq 22: {result.side.eq22.describe()}",
                  f"- flow model: {result.side.plant.describe()}; {result.side.plant.mobility_note()}"]
    if result.release is not None:
        dep = result.release.dependence()
        lines += ["", "## Front-push release", "",
                  f"{result.release.n} attempts: D_p,r = {result.release.mean * 1e6:.1f} ± "
                  f"{result.release.std * 1e6:.1f} µm (mean ± sd)."]
        if dep:
            lines.append(f"Later attempts: slope on push length {dep['length_slope']:.3g} ± "
                         f"{dep['length_slope_se']:.2g}, on the previous release {dep['previous_slope']:.3g} ± "
                         f"{dep['previous_slope_se']:.2g} ({dep['attempts']} attempts; slopes within 2σ of 0 mean "
                         "eq 14's constant release fits).")
    if recommendations:
        f, s, v = recommendations["front"], recommendations["side"], recommendations["servo"]
        lines += ["", "## On this rig", "",
                  f"- Front push (eq 13-15): stable for {f['stable_gain_range'][0]:g} < K_c < "
                  f"{f['stable_gain_range'][1]:g}; at K_c = {f['kc']:g} predicted mean attempts "
                  f"{f['mean_attempts_delta0_0']:.2f} with δ(0) = 0, {f['mean_attempts_delta0_release']:.2f} with "
                  f"δ(0) = the identified release {f['release_mean_um']:.0f} µm.",
                  f"- Side push (eq 18-20, switched analysis): K_s = {s['ks']:g} is {s['verdict']}; stable K_s "
                  f"ranges {s['stable_gain_ranges']}.",
                  f"- Servo at the identified lag ({v['delay_frames']} frames): stable {v['stable']}, gain margin "
                  f"{v['gain_margin']:.3g}, phase margin {v['phase_margin_deg']:.3g}°.",
                  "", f"Run: `{recommendations['run']}`"]
    if validation:
        lines += ["", "## Held-out runs: predicted against logged", ""]
        sp = validation.get("side_passes")
        if sp and sp["compared"]:
            lines.append(f"- {sp['compared']} of {sp['n']} side passes (the rest outside the model's gaps): "
                         f"ln(predicted/logged) mean {sp['log_error_mean']:+.3f}, RMS {sp['log_error_rms']:.3f}; "
                         f"RMS of (logged − predicted) in units of a pass's scatter {sp['z_rms']:.2f} (≲ 2: "
                         "within it).")
        fa = validation.get("front_attempts")
        if fa:
            lines.append(f"- {fa['runs']} front-push runs: logged mean attempts {fa['logged_mean']:.2f}, predicted "
                         f"{fa['predicted_mean']:.2f}.")
    if figures:
        lines += ["", *[f"![{name}]({name})" for name in _figures(result, folder)]]
    path = folder / "report.md"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path
