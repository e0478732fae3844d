"""SimResult at python-control's edge: ``to_control`` in python-control's axis order, checked against
python-control's own simulation of the exported linear loop; ``to_xarray`` labels; a short ``repr``."""

from __future__ import annotations

import control
import numpy as np
import pytest

from magctl.core import PI, Delay, Diagram, Integrator, Sum, simulate

T = 40


def _loop() -> Diagram:
    """The README's 30 Hz servo loop without the saturation (so python-control's linear model is exact)."""
    return Diagram(
        "servo",
        [Sum("error", "+-", shape=(2,), unit="m"),
         PI("pi", kp=1.5, ki=0.3, shape=(2,), in_unit="m", out_unit="m/s"),
         Integrator("robot", shape=(2,), in_unit="m/s", out_unit="m"),
         Delay("camera", 2, shape=(2,), unit="m")],
        [("error.y", "pi.e"), ("pi.u", "robot.u"), ("robot.y", "camera.u"), ("camera.y", "error.u1")],
        inputs={"target": "error.u0"},
        outputs={"position": "robot.y", "saturated": "pi.saturated"},
    )


@pytest.fixture(scope="module")
def run():
    targets = np.array([[1e-3, 0.5e-3], [-2e-4, 3e-4], [0.0, 1e-3]])   # one target per trial
    return simulate(_loop(), T, batch=3, seed=0, inputs={"target": targets}), targets


def test_to_control_is_python_controls_axis_order_and_its_own_simulation(run):
    res, targets = run
    resp = res.to_control()
    assert isinstance(resp, control.TimeResponseData)
    assert resp.outputs.shape == (2, 3, T)               # signal × trace × time
    assert resp.inputs.shape == (2, 3, T)
    assert resp.output_labels == ["position[0]", "position[1]"]   # the flag is not a signal
    assert resp.input_labels == ["target[0]", "target[1]"]
    np.testing.assert_array_equal(resp.time, res.t)
    sys = _loop().to_control()
    for k in range(3):
        u = np.repeat(targets[k][:, None], T, axis=1)
        ref = control.forced_response(sys, res.t, u)       # python-control simulating the exported model
        pos = [i for i, lbl in enumerate(sys.output_labels) if lbl.startswith("position")]
        np.testing.assert_allclose(resp.outputs[:, k], ref.outputs[pos], rtol=1e-10, atol=1e-15)
        np.testing.assert_allclose(resp.inputs[:, k], u)
    one = res.to_control(trial=2)
    assert one.outputs.shape == (2, T)
    np.testing.assert_array_equal(one.outputs, resp.outputs[:, 2])
    with pytest.raises(IndexError, match="trial 3 out of range"):
        res.to_control(trial=3)


def test_to_control_plots_in_python_control(run):
    """python-control draws the converted response: one line per channel and trace, carrying the data."""
    import matplotlib

    matplotlib.use("Agg")
    res, _ = run
    cplt = res.to_control().plot()
    assert cplt.lines.shape == (4, 3)      # rows: position[0], position[1], target[0], target[1]; a column a trial
    np.testing.assert_array_equal(cplt.lines[1, 2][0].get_ydata(), res.outputs["position"][2, :, 1])
    one = res.to_control(trial=1).plot()
    np.testing.assert_array_equal(one.lines[0, 0][0].get_ydata(), res.outputs["position"][1, :, 0])


def test_plot_draws_each_channel_with_its_unit(run):
    import matplotlib

    matplotlib.use("Agg")
    res, _ = run
    fig = res.plot()
    axes = fig.axes
    assert [ax.get_ylabel() for ax in axes] == ["position[0] (m)", "position[1] (m)"]   # the flag is not drawn
    assert axes[-1].get_xlabel() == "time (s)" and len(axes[0].lines) == 3
    np.testing.assert_array_equal(axes[1].lines[2].get_ydata(), res.outputs["position"][2, :, 1])
    assert len(res.plot(trial=0).axes[0].lines) == 1


def test_to_xarray_labels_trials_time_and_port_axes(run):
    pytest.importorskip("xarray")
    res, _ = run
    ds = res.to_xarray()
    assert ds["position"].dims == ("trial", "time", "position_dim0")
    assert list(ds["position_dim0"].values) == ["x", "y"]          # a vector in the plane of the slide
    assert ds["position"].attrs["units"] == "m" and ds["time"].attrs["units"] == "s"
    np.testing.assert_array_equal(ds["position"].sel(position_dim0="y", trial=2).values,
                                  res.outputs["position"][2, :, 1])
    assert list(ds["trial"].values) == [0, 1, 2]
    np.testing.assert_array_equal(ds["time"].values, res.t)
    np.testing.assert_array_equal(ds["position"].sel(trial=1).values, res.outputs["position"][1])
    full = res.to_xarray(signals=True)
    assert "pi.u" in full and "camera.y" in full


def test_repr_is_one_short_line(run):
    res, _ = run
    text = repr(res)
    assert text == "<SimResult servo: 3 trials × 40 steps of 0.03333 s; outputs: position (2,), saturated (); " \
                   "5 recorded signals>"
