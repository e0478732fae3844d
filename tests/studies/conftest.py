"""The cheap studies' compute steps, run once per session in a fresh interpreter.

The child imports every study module and runs ``compute`` (and ``summarise``) of the
studies that take seconds, recording every import statement that names matplotlib or
the drawing modules (``magctl.studies.figures``, ``magctl.studies.animate``) together
with the module that executed it, and pickles the results for the tests of this folder.
That checks the protocol's promise (numbers without matplotlib) and lets each study's
test read its results without recomputing them.

Every import statement passes through ``builtins.__import__``, even for a module already
in ``sys.modules``, so the record catches our code importing matplotlib after something
else loaded it: python-control (0.10) imports ``matplotlib.pyplot`` when it is imported,
so ``"matplotlib" in sys.modules`` alone cannot tell.
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

CHEAP = {"actuator": None, "stability": 2000, "servo": 4, "release": 16, "sidepush-curve": None}
"""Study name → trials for the studies whose compute step takes seconds."""

CHILD = textwrap.dedent("""
    import builtins, json, pickle, sys
    from pathlib import Path

    DRAWING = ("magctl.studies.figures", "magctl.studies.animate")
    imports = []                                   # (importing module, imported name)
    real_import = builtins.__import__

    def spy(name, globals=None, locals=None, fromlist=(), level=0):
        if level == 0:
            names = [name] + [f"{name}.{f}" for f in (fromlist or ())]
            hits = [n for n in names if n.split(".")[0] == "matplotlib" or n in DRAWING]
            if hits:
                imports.append(((globals or {}).get("__name__", "?"), hits[0]))
        return real_import(name, globals, locals, fromlist, level)

    builtins.__import__ = spy
    from magctl.studies import runner

    out, cheap = Path(sys.argv[1]), json.loads(sys.argv[2])
    found = runner.discover()                      # imports every study module
    n_after_import = len(imports)
    computed, summaries = {}, {}
    for name, trials in cheap.items():
        ctx = runner.StudyContext(out=out / name, trials=trials, seed=0, quiet=True, scheduler="serial")
        computed[name] = runner.compute(name, ctx)
        summaries[name] = found[name].summarise(computed[name])
    n_after_compute = len(imports)
    drawing_loaded = [m for m in DRAWING if m in sys.modules]
    found["actuator"].draw(computed["actuator"], runner.StudyContext(out=out / "draw-check"))  # must be seen
    builtins.__import__ = real_import
    with open(out / "computed.pkl", "wb") as f:
        pickle.dump({"computed": computed, "summaries": summaries, "studies": list(found),
                     "imports_at_import": imports[:n_after_import],
                     "imports_in_compute": imports[n_after_import:n_after_compute],
                     "imports_in_draw": imports[n_after_compute:], "drawing_modules_loaded": drawing_loaded}, f)
""")


@pytest.fixture(scope="session")
def cheap_studies(tmp_path_factory) -> dict:
    """``computed`` and ``summaries`` of the cheap studies (seed 0), the study names, the
    ``(importer, name)`` import statements of matplotlib or drawing modules while importing the
    studies, while computing and while drawing the actuator study afterwards (which must show up),
    and the drawing modules loaded before that drawing."""
    import json

    out = tmp_path_factory.mktemp("cheap_studies")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run([sys.executable, "-c", CHILD, str(out), json.dumps(CHEAP)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-4000:]
    with open(out / "computed.pkl", "rb") as f:
        return pickle.load(f)
