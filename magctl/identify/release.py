"""The front push's release D_p,r (§IV-D) from a rig's front-push runs.

Each logged attempt is read exactly as the studies read their simulated ones
(:func:`magctl.studies.front_release.attempt_rows`), so that the rig's numbers and the model's are the same
quantities: push length ``L = e_before + δ(i)``, the attempt map's release ``R = e_after + δ(i)`` (how far short of
``P_o`` the sphere ends: the sphere's follow plus where eq 11 stopped the push inside its ε_p band), and the
follow ``D_p,r`` itself, how far the sphere moved back with the retreating robot after the push (§IV-D). The
follow's mean and scatter go to ``models/push.toml [release]`` (the release the stand-in plant draws); a
least-squares line of the follow on the push length and on the previous attempt's follow says whether the
constant release of eq 14 describes the rig (:meth:`ReleaseFit.dependence`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magctl.config import load_model
from magctl.identify.estimate import Estimate, NotIdentified
from magctl.identify.phases import Run
from magctl.studies.front_release import attempt_rows


@dataclass
class ReleaseFit:
    """Logged front-push attempts and the release statistics fitted to them (metres)."""

    push_length: np.ndarray
    release: np.ndarray
    """D_p,r per attempt: the sphere's follow after the push (§IV-D)."""
    attempt_release: np.ndarray
    """R per attempt, the attempt map's release (``magctl.studies.front_release``)."""
    previous: np.ndarray
    first: np.ndarray
    runs: list[str]

    @property
    def n(self) -> int:
        return self.release.size

    @property
    def mean(self) -> float:
        return float(self.release.mean())

    @property
    def std(self) -> float:
        return float(self.release.std(ddof=1))

    def dependence(self) -> dict[str, float]:
        """OLS ``D_p,r = c0 + c1·(L − L̄) + c2·D_p,r(prev)`` over the later attempts (a previous one exists): the
        slopes with their standard errors; slopes within 2 SE of zero mean the constant release of eq 14 fits
        the rig."""
        later = ~self.first
        if later.sum() < 5:
            return {}
        L = self.push_length[later]
        X = np.column_stack([np.ones(later.sum()), L - L.mean(), self.previous[later]])
        y = self.release[later]
        coef, *_ = np.linalg.lstsq(X, y, rcond=None)
        resid = y - X @ coef
        dof = max(len(y) - 3, 1)
        cov = np.linalg.pinv(X.T @ X) * float(resid @ resid) / dof
        se = np.sqrt(np.diag(cov))
        return {"length_slope": float(coef[1]), "length_slope_se": float(se[1]),
                "previous_slope": float(coef[2]), "previous_slope_se": float(se[2]), "attempts": int(len(y))}

    def estimates(self) -> list[Estimate]:
        where = f"from {self.n} front-push attempts of {len(self.runs)} run(s) ({', '.join(self.runs)})"
        se_mean = self.std / np.sqrt(self.n)
        se_std = self.std / np.sqrt(2.0 * (self.n - 1))
        return [Estimate("push.toml", "release", "mean_um", self.mean * 1e6, se_mean * 1e6,
                         f"{where}: mean of D_p,r, the sphere's follow back along the push line from the end of the "
                         "push to the measurement (magctl.studies.front_release.attempt_rows)"),
                Estimate("push.toml", "release", "std_um", self.std * 1e6, se_std * 1e6,
                         f"{where}: sample standard deviation of D_p,r")]


def fit_release(runs: list[Run]) -> ReleaseFit:
    """Every measured attempt of every front-push run of ``runs``; :class:`NotIdentified` below
    ``models/identify.toml [release] min_attempts_count``."""
    L, R, A, prev, first, names = [], [], [], [], [], []
    for run in runs:
        if run.task != "front-push" or "goal_m" not in run.options:
            continue
        out = run.outputs
        if not {"attempt", "phase", "correction"} <= out.keys():
            continue
        rows = attempt_rows(run.spheres[:, 0], run.robot, out["attempt"], out["phase"], out["correction"],
                            run.options["goal_m"], run.spheres[0, 0])
        last = 0.0
        for row in rows:
            if not np.isfinite(row["follow"]):
                continue                    # an attempt without a push (the flow alone moved the sphere)
            L.append(row["push_length"])
            R.append(row["follow"])
            A.append(row["release"])
            prev.append(last)
            first.append(row["attempt"] == 1)
            last = row["follow"]
        if rows:
            names.append(run.name)
    least = int(load_model("identify").release.min_attempts)
    if len(R) < least:
        raise NotIdentified(f"the front push's release needs at least {least} measured front-push attempts; "
                            f"the logs hold {len(R)}")
    return ReleaseFit(np.array(L), np.array(R), np.array(A), np.array(prev), np.array(first, bool), names)
