"""The figures the README and the rig guide quote most are the ones their committed results files hold, and every
``magctl.…`` dotted name the docs quote exists: a doc that falls behind the code fails here.

(The claims and benchmark tables are generated and checked by tests/test_readme_claims.py and
tests/test_readme_benchmarks.py.)
"""

from __future__ import annotations

import importlib
import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def results(name: str) -> dict:
    return json.loads((ROOT / "benchmarks" / "results" / name).read_text())


def spaced(x: float) -> str:
    """A whole number as the docs write it: thin groups of three (1 549)."""
    return f"{round(x):,}".replace(",", " ")


def test_the_readme_quotes_the_reproduce_times_of_its_results_file():
    text = (ROOT / "README.md").read_text()
    name = "2026-12-04-c5c061f77d.json"
    assert f"benchmarks/results/{name}" in text
    r = results(name)["reproduce"]
    assert f"{spaced(r['warm']['wall_s'])} s on 2 cores with a warm compile cache" in text
    assert f"{spaced(r['cold']['wall_s'])} s\ncold" in text or f"{spaced(r['cold']['wall_s'])} s cold" in text


def test_the_readme_quotes_the_first_result_benchmark():
    text = " ".join((ROOT / "README.md").read_text().split())
    name = "2026-12-05-b4c86ff046.json"
    assert f"benchmarks/results/{name}" in text
    r = results(name)["first_result"]
    first = next(s for s in r["steps"] if s["step"] != "magctl --help")
    assert f"compiles magctl's kernels once ({first['wall_s']:.0f} s)" in text
    assert f"took {r['total_s']:.0f} s with empty compile caches" in text


def test_the_rig_guide_quotes_the_live_views_benchmark():
    text = " ".join((ROOT / "docs" / "rig.md").read_text().split())
    name = "2026-12-05-06361b5949.json"
    assert f"benchmarks/results/{name}" in text
    v = results(name)["view"]
    p99 = {m: max(r["jitter_ms"]["99"] for r in v["runs"][m]) for m in ("with", "without")}
    jmax = {m: max(r["jitter_ms"]["max"] for r in v["runs"][m]) for m in ("with", "without")}
    overruns = {m: max(r["overruns"] for r in v["runs"][m]) for m in ("with", "without")}
    frames = [p for r in v["runs"]["with"] for p in (r["pages"]["messages_min"], r["pages"]["messages_max"])]
    assert f"{overruns['with']} overruns either way" in text.replace("0 overruns", f"{overruns['with']} overruns") \
        and overruns["with"] == overruns["without"]
    assert f"tick jitter p99 {p99['with']:.2g} ms with the pages and {p99['without']:.2g} ms without" in text
    assert f"max {jmax['with']:.3g} / {jmax['without']:.2g} ms" in text
    assert f"{min(frames)}–{max(frames)} of the {v['ticks']} frames" in text


DOTTED = re.compile(r"`(magctl(?:\.[A-Za-z_][A-Za-z0-9_]*)+)")


def resolves(dotted: str) -> bool:
    from magctl.rig.lab import ENTRY_POINT_GROUP

    if dotted == ENTRY_POINT_GROUP:     # the entry-point group lab adapters register in, not a module
        return True
    parts = dotted.split(".")
    for k in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:k]))
        except ImportError:
            continue
        for attr in parts[k:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


QUOTED = sorted({(page.relative_to(ROOT).as_posix(), m) for page in PAGES
                 for m in DOTTED.findall(page.read_text())})


@pytest.mark.parametrize("page, dotted", QUOTED, ids=[f"{p}:{d}" for p, d in QUOTED])
def test_every_dotted_name_the_docs_quote_exists(page, dotted):
    assert resolves(dotted), f"{page} quotes `{dotted}`, which magctl does not have"


def test_a_missing_name_is_caught():
    assert resolves("magctl.rig.log.read_log") and not resolves("magctl.rig.log.no_such_thing")
    assert not resolves("magctl.no_such_module")
    assert len(QUOTED) > 50


def test_the_release_maps_counts_are_the_ones_its_file_holds():
    import tomllib

    text = " ".join((ROOT / "docs" / "push-control.md").read_text().split())
    with open(ROOT / "models" / "front_release.toml", "rb") as fh:
        prov = {k: v["value"] for k, v in tomllib.load(fh)["provenance"].items()}
    assert (f"{spaced(prov['attempts_count'])} attempts, mean release {prov['release_mean_um']:.2f} ± "
            f"{prov['release_std_um']:.2f} µm, contact in {100 * prov['p_contact_later_1']:.0f} % of the attempts "
            f"after the first") in text


def test_the_identify_page_quotes_the_depths_of_its_results_file():
    text = " ".join((ROOT / "docs" / "identify.md").read_text().split())
    r = results("2026-12-05-08bf4ae18c.json")["identify"]
    shifts = ", ".join(f"{s:.3f}" for s in r["depth_shift_mm"][:-1]) + f" and {r['depth_shift_mm'][-1]:.3f} mm"
    sigmas = ", ".join(f"{s:.1f}" for s in r["depth_shift_in_sigma"][:-1]) + f" and {r['depth_shift_in_sigma'][-1]:.1f}"
    assert f"moved by {shifts} ({sigmas} times the larger of the two σ)" in text
    seed5 = r["depth_by_seed"]["5"]
    off = abs(seed5["value"] - 0.95) / seed5["uncertainty"]
    assert f"Seed 5's {seed5['value']:.3f} ± {seed5['uncertainty']:.3f} mm lies {off:.0f}σ from the truth" in text
    worst = {row["name"].split(", ")[-1]: row["value"] for row in r["rows"] if "worst of" in row["name"]}
    assert f"met the 0.1 mm target on the one rig ({min(worst.values()):.3f} mm)" in text
    assert f"missed it on the other ({max(worst.values()):.3f} mm)" in text
