"""The reports ``magctl stability front`` and ``magctl stability side`` print: the analyses of
:mod:`magctl.stability.iteration` and :mod:`magctl.stability.switched` gathered into one JSON-able document each
(µm in unit-suffixed keys), which :mod:`magctl.cli.stability` writes as JSON or as a text summary.

The command line builds its parser from every module of :mod:`magctl.cli`, so this one imports its computing code
inside the functions (``magctl --help`` loads neither numpy nor python-control).
"""

from __future__ import annotations


def _tf_doc(tf) -> dict:
    """A python-control transfer function's numerator, denominator and period."""
    import numpy as np

    return {"num": np.asarray(tf.num[0][0], float), "den": np.asarray(tf.den[0][0], float), "dt": tf.dt}


def _poles_doc(poles) -> list:
    """Poles as real part, imaginary part and modulus."""
    import numpy as np

    return [{"re": float(p.real), "im": float(p.imag), "abs": float(abs(p))} for p in np.asarray(poles)]


def front_report(kc: float, delta0_um: float = 0.0, trials: int = 20000, seed: int = 0,
                 model: str = "paper") -> dict:
    """Everything ``magctl stability front`` prints (µm in keys).

    ``model="paper"``: the eq 14 0th-order plant, ``D_p,r ~ N(300, 75²) µm`` i.i.d. (Markov chain and
    Monte Carlo); ``model="identified"``: the release map identified from the closed loop
    (``models/front_release.toml``, :func:`~magctl.stability.iteration.front_identified_map`, Monte Carlo).
    """
    import numpy as np

    from magctl.core.checks import check_finite
    from magctl.core.errors import MagctlError
    from magctl.core.units import UM
    from magctl.stability.iteration import (
        FRONT_EPS,
        FRONT_MAX_ATTEMPTS,
        RELEASE_MEAN,
        RELEASE_STD,
        ReleaseMap,
        front_attempts_identified,
        front_attempts_markov,
        front_attempts_monte_carlo,
        front_loop,
    )

    if model not in ("paper", "identified"):
        raise MagctlError(f"--model {model!r} is not known; use 'paper' (eq 14, D_p,r i.i.d.) or 'identified' "
                          "(the release map identified from the closed loop)")
    kc = check_finite("--kc", kc)
    delta0 = check_finite("--delta0-um", delta0_um) * UM
    loop = front_loop(kc)
    doc = {
        "loop": "front", "equations": "eq 13-15", "kc": kc, "delta0_um": delta0 / UM,
        "G_ol": _tf_doc(loop.open_loop), "G_cl": _tf_doc(loop.closed_loop), "poles": _poles_doc(loop.poles),
        "verdict": loop.verdict, "damping": loop.damping,
        "stable_gain_range": list(loop.stable_gain_range), "critically_damped_gain": 1.0,
    }
    n = np.arange(1, FRONT_MAX_ATTEMPTS + 1)
    if model == "identified" and (loop.verdict == "stable" or kc == 0):
        rmap = ReleaseMap.load()
        p = front_attempts_identified(kc, delta0, trials, release_map=rmap, seed=seed)
        doc["convergence"] = {
            "model": "identified", "source": rmap.source, "eps_p_um": FRONT_EPS / UM,
            "max_attempts": FRONT_MAX_ATTEMPTS,
            "p_attempt_monte_carlo": p[:-1], "p_not_converged_monte_carlo": p[-1],
            "p_converged_by_attempt": np.cumsum(p[:-1]),
            "mean_attempts": float((n * p[:-1]).sum() + FRONT_MAX_ATTEMPTS * p[-1]),
            "mean_attempts_if_converged": float((n * p[:-1]).sum() / max(p[:-1].sum(), 1e-300)),
        }
    elif loop.verdict == "stable" or kc == 0:
        markov = front_attempts_markov(kc, delta0)
        mc = front_attempts_monte_carlo(kc, delta0, trials=trials, seed=seed)
        doc["convergence"] = {
            "model": "paper", "release_mean_um": RELEASE_MEAN / UM, "release_std_um": RELEASE_STD / UM,
            "eps_p_um": FRONT_EPS / UM, "max_attempts": FRONT_MAX_ATTEMPTS,
            "p_attempt_markov": markov[:-1], "p_not_converged_markov": markov[-1],
            "p_attempt_monte_carlo": mc[:-1], "p_not_converged_monte_carlo": mc[-1],
            "mean_attempts_if_converged": float((n * markov[:-1]).sum() / max(markov[:-1].sum(), 1e-300)),
        }
    return doc


def side_report(ks: float, model: str = "lin", min_gap_um: float | None = None, goal_um: float | None = None,
                ratio: float | None = None, plant: str = "exp", plant_scale: float = 1.0,
                plant_gap_scale: float = 1.0) -> dict:
    """Everything ``magctl stability side`` prints (µm in keys).

    ``min_gap_um`` and ``goal_um`` default to the side push's (``models/push.toml`` ``[side]``).

    ``plant`` is ``exp`` (eq 22) or ``fluid``; ``plant_scale`` multiplies its displacements and
    ``plant_gap_scale`` stretches its gap axis (:class:`~magctl.stability.switched.ScaledSideModel`: a
    mismatched plant). Three analyses of the loop at the model ratio ``ρ`` (``ratio``; by default the
    exact one when the pairing is linear — eq 22 model against eq 22 scaled by ``s`` gives ``ρ = s`` —
    else 1): eq 19–20 as printed, the signed 1-D model, and the switched map the algorithm runs
    (:mod:`magctl.stability.switched`), whose verdict is the report's ``verdict``.
    """
    import numpy as np

    from magctl.control.side_models import ExpSideModel, side_model
    from magctl.core.checks import check_finite, check_positive
    from magctl.core.errors import MagctlError
    from magctl.core.units import UM
    from magctl.stability import switched as W
    from magctl.stability.iteration import (
        MIN_GAP,
        SIDE_EPS,
        SIDE_GOAL,
        SIDE_MAX_ATTEMPTS,
        classify,
        fluid_side_plant,
        local_ratio,
        side_attempt_map,
        side_full_poles,
        side_full_stable_range,
        side_loop,
        side_nonlinear_gain_range,
    )

    ks = check_finite("--ks", ks)
    mdl = side_model(model)
    min_gap = check_positive("--min-gap-um", MIN_GAP / UM if min_gap_um is None else min_gap_um) * UM
    goal = check_positive("--goal-um", SIDE_GOAL / UM if goal_um is None else goal_um) * UM
    plant_scale = check_positive("--plant-scale", plant_scale)
    plant_gap_scale = check_positive("--plant-gap-scale", plant_gap_scale)
    if plant not in ("exp", "fluid"):
        raise MagctlError(f"--plant {plant!r} is not known; use 'exp' (eq 22) or 'fluid' (the fluid model's curve)")
    plant_name = "exp (eq 22)" if plant == "exp" else "fluid model (Fig 6 simulation)"
    base = ExpSideModel() if plant == "exp" else fluid_side_plant()
    scaled = plant_scale != 1.0 or plant_gap_scale != 1.0
    if scaled:
        plant_name += f", displacements x{plant_scale:g}, gaps x{plant_gap_scale:g}"
    plant_obj = W.ScaledSideModel(base, plant_scale, plant_gap_scale) if scaled else base
    linear_pair = mdl.name == "exp" and plant == "exp" and plant_gap_scale == 1.0
    if ratio is None:
        rho = plant_scale if linear_pair else 1.0
        rho_source = ("exact: eq 22 model against eq 22 scaled, D_s,act = ratio (D_s,des + Delta)" if linear_pair
                      else "assumed 1 (the pairing is nonlinear: see operating_range for the local ratio)")
    else:
        rho = check_positive("--ratio", ratio)
        rho_source = "given (--ratio)"
    d_max_model = float(mdl.displacement(min_gap))
    d_act_max = float(plant_obj.displacement(max(float(mdl.gap(d_max_model)), min_gap)))
    d_range = np.linspace(SIDE_EPS, d_act_max, 200)
    r_local = local_ratio(d_range, mdl, plant_obj)
    paper = side_loop(ks, rho)
    full_p = side_full_poles(ks, rho)
    full_verdict, full_damping = classify(full_p)
    sw = W.switched_verdict(ks, rho)
    map_rate = float(W.map_growth_rate(ks, rho))
    run = side_attempt_map(ks, goal, model=mdl, plant=plant_obj, min_gap=min_gap)
    errs = run["error"][0]
    nl = side_nonlinear_gain_range(mdl, plant=plant_obj, min_gap=min_gap)
    r_lo, r_hi = float(r_local.min()), float(r_local.max())
    poles = {name: _poles_doc(p) for name, p in sw.branch_poles.items()}
    return {
        "loop": "side", "equations": "eq 16-20, 22-23", "ks": ks, "model": mdl.name, "plant": plant_name,
        "plant_scale": plant_scale, "plant_gap_scale": plant_gap_scale,
        "min_gap_um": min_gap / UM, "goal_um": goal / UM, "eps_p_um": SIDE_EPS / UM,
        "ratio": rho, "ratio_source": rho_source,
        "verdict": sw.verdict, "verdict_source": "switched (the algorithm as run)",
        "paper_analysis": {
            "label": "eq 19-20 as printed: one state, ratio constant",
            "ratio": rho, "H_ol": _tf_doc(paper.open_loop), "H_cl": _tf_doc(paper.closed_loop),
            "poles": _poles_doc(paper.poles), "verdict": paper.verdict, "damping": paper.damping,
            "stable_gain_range": list(paper.stable_gain_range),
        },
        "with_feedforward": {
            "label": "signed 1-D model: eq 16-18 with e keeping its sign (no branch switch on over-push)",
            "ratio": rho, "poles": _poles_doc(full_p), "verdict": full_verdict, "damping": full_damping,
            "stable_gain_range": side_full_stable_range(rho),
        },
        "switched": {
            "label": "switched map as the task runs it: |e| (eq 16), over-push reverses the next pass, "
                     "no pass when D_s,des + Delta <= 0",
            "ratio": rho, "verdict": sw.verdict, "growth_rate": sw.growth_rate,
            "growth_rate_attempt_map": map_rate,
            "growth_rate_attempt_map_note": "side_attempt_map, eq 22 model against eq 22 scaled by the ratio, "
                                            "33 starts, bounds off",
            "branch_poles": poles, "jsr_bounds_any_switching": list(sw.jsr),
            "growing_ray": sw.growing_ray,
            "stable_gain_ranges": [list(r) for r in W.switched_gain_ranges(rho)],
        },
        "operating_range": {
            "max_desired_displacement_um": d_max_model / UM, "max_actual_displacement_um": d_act_max / UM,
            "local_ratio_min": r_lo, "local_ratio_max": r_hi,
            "paper_test_gain_range_over_range": [0.0, 2.0 / r_hi] if r_hi > 0 else None,
        },
        "nonlinear_map": {
            "label": "side_attempt_map with the bounds of §V-B and the plant above",
            "converged": bool(run["attempts"][0] >= 0), "attempts": int(run["attempts"][0]),
            "max_attempts": SIDE_MAX_ATTEMPTS,
            "error_um": [float(x) / UM for x in errs[np.isfinite(errs)]],
            "stable_gain_range": None if nl["range"] is None else list(nl["range"]),
            "stable_gain_range_note": "K_s converging from every start 10-300 µm within 30 attempts",
        },
    }
