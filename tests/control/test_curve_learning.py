"""The curve-learning side-push law: its Kalman step against filterpy's EKF, its inversion, its convergence over
plant scales where eq 18 fails, and the attempt map against the 30 Hz task."""

import numpy as np
import pytest
from filterpy.kalman import ExtendedKalmanFilter
from reference.push_blocks import numpy_form
from test_push import ideal_loop

from magctl.control.curve_learning import CurveLearningLaw, curve_learning_law
from magctl.control.learning import side_push_law
from magctl.control.push.side import REPOSITION, SETTLE, SidePushTask
from magctl.control.side_models import ExpSideModel, LinSideModel, side_model
from magctl.control.status import Status
from magctl.core.errors import MagctlError
from magctl.core.simulation import simulate
from magctl.core.units import UM
from magctl.stability import iteration as S
from magctl.stability.switched import ScaledSideModel

MIN_GAP = 370 * UM   # the paper's bound: the law's properties below are stated there (docs/push-control.md §6)


def law(**kw):
    return curve_learning_law(**kw)


def test_kalman_step_matches_filterpy_extended_kalman_filter():
    """Five passes of one trial, one iteration: estimate and covariance equal filterpy's EKF (predict with Q,
    Joseph-form update)."""
    cl = law(iterations=1)
    rng = np.random.default_rng(3)
    gaps = rng.uniform(380, 650, 5) * UM
    # passes scattered ±30 % round the prior's curve (far-off ones would drive the rate to its floor)
    xg0 = (gaps - cl.reference_gap) / cl.reference_gap
    meas = np.exp(cl.prior_mean[0] - cl.prior_mean[1] * xg0) * rng.lognormal(0.0, 0.3, 5)
    ekf = ExtendedKalmanFilter(dim_x=3, dim_z=1)
    ekf.x = cl.prior_mean.copy().reshape(3, 1)
    ekf.P = cl.prior_cov.copy()
    ekf.Q = cl.drift.copy()
    state = cl.initial_state(1)
    for g, z in zip(gaps, meas, strict=True):
        xg = (g - cl.reference_gap) / cl.reference_gap
        ekf.predict()
        e = float(np.exp(ekf.x[0, 0] - ekf.x[1, 0] * xg))  # h evaluated at the predicted estimate

        def jacobian(x, xg=xg):
            ex = np.exp(x[0, 0] - x[1, 0] * xg)
            return np.array([[ex, -xg * ex, -1.0]])

        def h(x, xg=xg):
            return np.array([[np.exp(x[0, 0] - x[1, 0] * xg) - x[2, 0]]])

        ekf.update(np.array([[z]]), jacobian, h, R=np.array([[cl.pass_rel_var * e * e + cl.measure_var]]))
        state = cl.update(state, {"gap": np.array([g]), "displacement": np.array([z])})
        assert state["theta"][0, 1] > cl.b_min  # the rate floor does not act: a plain EKF step
        np.testing.assert_allclose(state["theta"][0], ekf.x[:, 0], rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(state["cov"][0], ekf.P, rtol=1e-10, atol=1e-20)


def test_iterated_update_reaches_the_posterior_mode():
    """Iterated to convergence, one pass's update is the minimiser of the negative log posterior (prior plus the
    pass, its variance at the predicted estimate), found independently by scipy."""
    from scipy.optimize import minimize

    cl = law(iterations=30)
    state = cl.initial_state(1)
    theta0, p = state["theta"][0], state["cov"][0] + cl.drift
    g, z = 370 * UM, 560 * UM  # 9 times the prior's displacement there: far from the linearisation point
    x = (g - cl.reference_gap) / cl.reference_gap
    r = cl.pass_rel_var * np.exp(theta0[0] - theta0[1] * x) ** 2 + cl.measure_var
    scale = np.sqrt(np.diag(p))
    p_inv = np.linalg.inv(p)

    def cost(v):
        t = theta0 + scale * v
        d = t - theta0
        return d @ p_inv @ d + (z - np.exp(t[0] - t[1] * x) + t[2]) ** 2 / r

    best = theta0 + scale * minimize(cost, np.zeros(3), method="BFGS", options={"gtol": 1e-12}).x
    new = cl.update(state, {"gap": np.array([g]), "displacement": np.array([z])})["theta"][0]
    np.testing.assert_allclose(new, best, rtol=1e-6, atol=1e-12)
    one = law(iterations=1).update(state, {"gap": np.array([g]), "displacement": np.array([z])})["theta"][0]
    assert abs(one[0] - best[0]) > 10 * abs(new[0] - best[0])  # the plain EKF step stops short of it


def test_masked_trials_keep_their_estimate_and_the_rate_floor_holds():
    cl = law()
    state = cl.initial_state(3)
    # a displacement that grows with the gap would fit an increasing curve: b is held at its floor
    for _ in range(5):
        for g, z in ((380 * UM, 1 * UM), (650 * UM, 200 * UM)):
            state = cl.update_where(state, {"gap": np.full(3, g), "displacement": np.full(3, z)},
                                    np.array([True, False, True]))
            assert np.all(state["theta"][:, 1] >= cl.b_min)
    np.testing.assert_array_equal(state["theta"][1], cl.prior_mean)
    np.testing.assert_array_equal(state["cov"][1], cl.prior_cov)
    assert state["theta"][0, 1] == pytest.approx(cl.b_min)


def test_inversion_gives_the_asked_displacement_and_respects_the_contact_bound():
    cl = law()
    state = cl.initial_state(4)
    state["theta"] = state["theta"] + np.array([[0.0, 0.0, 0.0], [0.4, 0.5, 2 * UM], [-0.6, -0.5, -1 * UM],
                                                [0.1, 1.0, 5 * UM]])
    d_max = cl.displacement(state, MIN_GAP)
    d = np.linspace(0.2, 0.95, 7)[:, None] * d_max[None, :]
    for row in d:
        gap = cl.gap(state, row, MIN_GAP)
        assert np.all(gap > MIN_GAP)
        np.testing.assert_allclose(cl.displacement(state, gap), row, rtol=1e-12)
    # asking more than the bound gives the contact-threshold gap; asking ≤ −c a finite wide gap
    assert np.all(cl.gap(state, 2 * d_max, MIN_GAP) == MIN_GAP)
    far = cl.gap(state, -state["theta"][:, 2] - 1 * UM, MIN_GAP)
    assert np.all(np.isfinite(far)) and np.all(far > 600 * UM)


def test_prior_is_the_given_curve():
    prior = ExpSideModel()
    cl = law(prior=prior)
    state = cl.initial_state(1)
    gaps = np.array([370, 450, 500, 650]) * UM
    np.testing.assert_allclose([cl.displacement(state, np.array([g]))[0] for g in gaps],
                               prior.displacement(gaps), rtol=1e-12)
    assert cl.mobility(state, MIN_GAP)[0] == pytest.approx(1.0)
    assert cl.output(state, {})["y"][0] == 0.0


def test_noise_free_estimate_converges_to_a_curve_of_its_form():
    """Passes at random gaps on a plant exactly of the form (1.8 times eq 22's displacement, decaying 1.15 times
    more slowly): the learned curve approaches it, and the iterated update gets closer than the plain EKF."""
    truth = ScaledSideModel(scale=1.8, gap_scale=1.15)
    probe = np.array([380, 450, 550, 650]) * UM
    worst = {}
    for iterations in (1, 3):
        cl = law(prior=ExpSideModel(), drift_log_sigma=0.0, iterations=iterations)
        state = cl.initial_state(1)
        for g in np.random.default_rng(0).uniform(370, 700, 200) * UM:
            state = cl.update(state, {"gap": np.array([g]), "displacement": truth.displacement(np.array([g]))})
        worst[iterations] = np.max(np.abs(cl.displacement(state, probe) / truth.displacement(probe) - 1))
    assert worst[3] < 0.03
    assert worst[1] > 2 * worst[3]


def test_a_sticky_sphere_is_detected_in_three_passes():
    """A sphere at 20 % of the prior's mobility (a sticky patch, the robustness study's dirt): after three
    passes at the law's own gaps the estimated mobility at the contact threshold is within 0.05 of 0.2; a
    sphere as the prior stays at 1."""
    for scale in (0.2, 1.0):
        cl = law()
        plant = ScaledSideModel(base=side_model("exp-fit"), scale=scale)
        state, e = cl.initial_state(1), np.array([300 * UM])
        for _ in range(3):
            gap = cl.gap(state, np.minimum(e, cl.displacement(state, MIN_GAP)), MIN_GAP)
            d = plant.displacement(gap)
            state, e = cl.update(state, {"gap": gap, "displacement": d}), e - d
        assert cl.mobility(state, MIN_GAP)[0] == pytest.approx(scale, abs=0.05)


SCALES = np.array([0.3, 0.6, 1.0, 1.4, 2.0, 2.6, 3.0])


@pytest.mark.parametrize("gap_scale", [0.7, 1.0, 1.5])
def test_attempt_map_converges_over_plant_scales_where_eq18_does_not(gap_scale):
    """Nominal curve (eq 22 prior) against eq 22 scaled by ρ = 0.3–3 in displacement and 0.7–1.5 in gap: the
    learned law converges wherever the contact bound lets 30 passes reach the goal, within 5 attempts of the
    fewest passes that can (⌈(e₀ − ε_p)/D_s,act(min_gap)⌉). Eq 18 with the paper's K_s = 0.9 on the same
    prior diverges past ρ ≈ 2.25 (docs/push-control.md §4): with a tolerance it cannot hit by chance it never
    converges at ρ = 2.6 and 3."""
    e0, eps = 300 * UM, 7.5 * UM
    for rho in SCALES:
        plant = ScaledSideModel(scale=float(rho), gap_scale=gap_scale)
        fewest = int(np.ceil((e0 - eps) / plant.displacement(MIN_GAP)))
        run = S.side_attempt_map(0.0, e0, model="exp", plant=plant, law=law(prior=ExpSideModel()), max_attempts=30,
                                 min_gap=MIN_GAP)
        attempts = run["attempts"][0]
        if fewest > 30:
            assert attempts == -1
            continue
        assert fewest <= attempts <= fewest + 5, (rho, attempts, fewest)
        if gap_scale == 1.0 and rho > 2.25:
            paper = S.side_attempt_map(0.9, e0, model="exp", plant=plant, law=side_push_law(0.9), eps=0.05 * UM,
                                       max_attempts=100, min_gap=MIN_GAP)
            assert paper["attempts"][0] == -1, (rho, paper["attempts"][0])


def test_attempt_map_beats_eq18_under_mobility_and_pass_scatter():
    """Exp-fit prior and plant, 10 % mobility scatter between spheres and 10 % pass to pass (the issue's first
    measurement): fewer mean attempts than eq 23 lin-fit with K_s = 0.9, every trial within 10."""
    kw = dict(plant=side_model("exp-fit"), noise_rel=0.1, mobility_rel=0.1, seed=4)
    learned = S.side_attempt_map(0.0, np.full(400, 300 * UM), model="exp-fit", law=law(), **kw)["attempts"]
    paper = S.side_attempt_map(0.9, np.full(400, 300 * UM), model="lin-fit", **kw)["attempts"]
    assert np.all((learned > 0) & (learned <= 10))
    assert learned.mean() < paper[paper > 0].mean() - 0.5


def _standin_runs(scales, task, frames=9000):
    """``task`` round the stand-in plant with eq 22 scaled per trial, no release; the geometry of
    tests/stability/test_switched.py (repositioning round a 2.5 mm circle, passes from 3 mm behind to 3 mm
    ahead), so the passes are the only sphere motion. Returns the recorded status, attempt and final state."""
    r0, s0 = (-1e-3, 0.0), np.array([[0.0, 0.0]])
    dia = ideal_loop(task, r0, s0, v_max=3e-3, side_range=2.4e-3, release=False, side_scale=scales)
    n = task.name
    res = simulate(dia, frames, batch=len(scales), record=[f"{n}.status", f"{n}.attempt"])
    return res[f"{n}.status"][:, -1], res[f"{n}.attempt"][:, -1], res.final_state


def _side_task(prior, **kw):
    return SidePushTask(goal=(300 * UM, 0.0), law=law(prior=prior), model="exp", clearance=2.5e-3, behind=3e-3,
                        ahead=3e-3, pass_speed=3e-3, travel_speed=3e-3, max_attempts=30, **kw)


def _task_runs(scales, prior):
    """The 30 Hz side push with the curve law round the stand-in plant (eq 22 scaled per trial)."""
    status, attempts, _ = _standin_runs(scales, _side_task(prior, arrive_tol=0.1 * UM))
    return status, attempts


def test_attempt_map_and_30hz_task_agree():
    prior = ExpSideModel()
    status, attempts = _task_runs(SCALES, prior)
    for i, rho in enumerate(SCALES):
        run = S.side_attempt_map(0.0, 300 * UM, model="exp", plant=ScaledSideModel(scale=float(rho)),
                                 law=law(prior=prior))
        assert status[i] == Status.CONVERGED, (rho, status[i])
        assert abs(int(attempts[i]) - int(run["attempts"][0])) <= 1, (rho, attempts[i], run["attempts"][0])


def test_task_and_law_refuse_what_they_cannot_learn():
    with pytest.raises(MagctlError, match="learning='curve'.*exp-fit"):
        SidePushTask(learning="curve", model="lin")
    with pytest.raises(MagctlError, match="learning='quadratic' is not one of eq18, curve"):
        SidePushTask(learning="quadratic")
    with pytest.raises(MagctlError, match="eq 22's form"):
        CurveLearningLaw("law", LinSideModel(), **{k: 1.0 for k in (
            "reference_gap", "prior_log_sigma", "prior_rate_sigma", "prior_offset", "prior_offset_sigma",
            "pass_log_sigma", "measure_sigma", "drift_log_sigma", "rate_floor")})
    with pytest.raises(MagctlError, match="rate_floor"):
        law(rate_floor=1.5)
    with pytest.raises(MagctlError, match="unknown parameters"):
        law(gain=0.9)
    task = SidePushTask(learning="curve", model="exp-fit")
    assert isinstance(task.law, CurveLearningLaw) and task.kernel() is not None   # the curve law is compiled too


def _dirt_runs(scales, dirt_response):
    """The curve law's side push round the stand-in plant, eq 22 scaled per trial, a sticky sphere's release
    (flow-driven, so scaled with its mobility) taken as none; returns final status, attempts and front pushes
    started."""
    task = _side_task(ExpSideModel(), arrive_tol=1 * UM, dirt_response=dirt_response, min_gap=MIN_GAP)
    status, attempts, final = _standin_runs(scales, task)
    task_state = next(leaf for leaf in final["leaves"] if "d_des" in leaf)
    fronts = task_state["fronts"] if dirt_response == "front" else np.zeros(len(scales), dtype=int)
    return status, attempts, fronts


def test_a_stuck_sphere_gets_a_front_push_and_converges_sooner():
    """A sphere at 15 % of the prior's mobility, passes bounded at the paper's 370 µm: side passes alone need
    ⌈292.5/9.3⌉ = 32 passes (beyond the
    30-attempt limit); with the front push answering dirt it converges within 10 attempts. A sphere as the
    prior is never front-pushed, and converges as without the option."""
    scales = np.array([0.15, 1.0])
    status, attempts, fronts = _dirt_runs(scales, "front")
    assert list(status) == [Status.CONVERGED, Status.CONVERGED]
    assert attempts[0] <= 10 and fronts[0] >= 1 and fronts[1] == 0
    plain_status, plain_attempts, _ = _dirt_runs(scales, "none")
    assert plain_status[0] == Status.ATTEMPT_LIMIT
    assert plain_status[1] == Status.CONVERGED and plain_attempts[1] == attempts[1]


def test_dirt_response_is_checked():
    with pytest.raises(MagctlError, match="dirt_response='front' needs learning='curve'"):
        SidePushTask(dirt_response="front")
    with pytest.raises(MagctlError, match="dirt_response='wash' is not one of none, front"):
        SidePushTask(learning="curve", model="exp-fit", dirt_response="wash")
    from magctl.control.push.assembly import AssemblyTask

    with pytest.raises(MagctlError, match="assembly takes 'none'"):
        AssemblyTask(learning="curve", model="exp-fit", dirt_response="front")


def test_push_out_is_learned_and_the_pass_turned_against_it():
    """A pass that moved the sphere 50 µm along its line and 5 µm across it, away from the robot, gives a
    push-out ratio of 0.1 (the first measurement is taken whole, the next with push_out_weight); the next pass
    is turned by atan(0.1) towards the robot's side, so the sum of both motions points at the goal. Step by step
    in the numpy reference, then through one frame of the task that measures such a pass: its kernel and the
    reference give that ratio and that turn, and the same outputs and next state."""
    task = SidePushTask(goal=(300 * UM, 0.0), learning="curve", model="exp-fit", push_out_weight=0.5)
    ref = numpy_form(task)
    new = task.initial_state(1)
    u = np.array([[1.0, 0.0]])
    new["u"], new["p0"] = u, np.zeros((1, 2))
    new["start"] = np.array([[-task.behind, 400 * UM]])  # the robot passed on the +y side
    mask = np.array([True])
    ref._learn_push_out(new, mask, np.array([[50 * UM, -5 * UM]]))
    assert new["push_out"][0] == pytest.approx(0.1) and new["push_out_n"][0] == 1
    ref._learn_push_out(new, mask, np.array([[50 * UM, -15 * UM]]))
    assert new["push_out"][0] == pytest.approx(0.2)  # halfway to 0.3
    ref._learn_push_out(new, mask, np.array([[5 * UM, -5 * UM]]))  # too short a pass: no measurement
    assert new["push_out"][0] == pytest.approx(0.2) and new["push_out_n"][0] == 2
    # the next attempt, robot on the +y side of a sphere at the origin, goal along +x
    ref._begin(new, mask, np.array([[-1e-3, 0.5e-3]]), np.array([[[0.0, 0.0]]]))
    turn = np.arctan2(new["u"][0, 1], new["u"][0, 0])
    assert turn == pytest.approx(np.arctan(0.2))
    # a frame that measures the pass (settled at the end of its line, robot on the +y side) and begins the next
    state = task.initial_state(1)
    state["phase"][:], state["frames"][:] = SETTLE, task.settle_frames
    state["u"], state["p0"] = u, np.zeros((1, 2))
    state["gap"], state["d_des"] = np.array([400 * UM]), np.array([50 * UM])
    state["start"], state["end"] = np.array([[-task.behind, 400 * UM]]), np.array([[task.ahead, 400 * UM]])
    inputs = {"robot_est": state["end"].copy(), "spheres_est": np.array([[[50 * UM, -5 * UM]]]),
              "lost": np.zeros(1, dtype=bool)}
    out, nxt = task.step(state, inputs)
    ref_out, ref_nxt = ref.step(state, inputs)
    for got, want in ((nxt, ref_nxt), (nxt["law"], ref_nxt["law"]), (out, ref_out)):
        for key, value in want.items():
            if not isinstance(value, dict):
                np.testing.assert_allclose(got[key], value, rtol=1e-12, atol=1e-18, err_msg=key)
    assert nxt["attempt"][0] == 1 and nxt["phase"][0] == REPOSITION
    assert nxt["push_out"][0] == pytest.approx(0.1) and nxt["push_out_n"][0] == 1
    # the sphere now heads for the goal along (250, 5) µm: the pass is turned atan(0.1) from that, to the +y side
    assert np.arctan2(nxt["u"][0, 1], nxt["u"][0, 0]) == pytest.approx(np.arctan2(5, 250) + np.arctan(0.1), abs=1e-12)
    with pytest.raises(MagctlError, match="push_out_weight"):
        SidePushTask(learning="curve", model="exp-fit", push_out_weight=0.0)
