"""``magctl study`` and ``magctl reproduce`` with small stand-in studies: one trial cache per
reproduce run, reuse only where declared, ``--no-figures``."""

from __future__ import annotations

import json
import textwrap

import pytest

from magctl.cli import main

PRODUCER = textwrap.dedent("""
    from magctl.studies.runner import Computed, PaperRow

    NAME, TITLE, ORDER = "producer", "stores trials", 1

    def compute(ctx):
        hit = ctx.trial_cache.lookup("trials", (ctx.study, *ctx.reuses))
        if hit is None:
            ctx.trial_cache.store("trials", ctx.study, [1.0, 2.0])
        return Computed({"value_um": 1.0})

    def draw(computed, ctx):
        from magctl.studies.figures import pyplot
        plt = pyplot()
        fig, ax = plt.subplots()
        ax.plot([0, 1], [0, computed.results["value_um"]])
        path = ctx.figure_path("producer")
        fig.savefig(path)
        plt.close(fig)
        return [path]

    def summarise(computed):
        return ["stored"], [PaperRow("q", "p", "m")]
""")

CONSUMER = textwrap.dedent("""
    from magctl.studies.runner import Computed

    NAME, TITLE, ORDER = "{name}", "reads trials", {order}
    REUSES = {reuses!r}

    def compute(ctx):
        hit = ctx.trial_cache.lookup("trials", (ctx.study, *ctx.reuses))
        if hit is None:
            ctx.trial_cache.store("trials", ctx.study, [1.0, 2.0])
            return Computed({{"trials_from_study": ctx.study}})
        return Computed({{"trials_from_study": hit[0]}})

    def draw(computed, ctx):
        return []

    def summarise(computed):
        return [f"trials from {{computed.results['trials_from_study']}}"], []
""")


@pytest.fixture
def stand_ins(tmp_path, monkeypatch):
    folder = tmp_path / "analysis"
    folder.mkdir()
    (folder / "producer.py").write_text(PRODUCER)
    (folder / "reuser.py").write_text(CONSUMER.format(name="reuser", reuses=("producer",), order=2))
    (folder / "loner.py").write_text(CONSUMER.format(name="loner", reuses=(), order=2))
    monkeypatch.setenv("MAGCTL_STUDIES", str(folder))
    return tmp_path


def test_reproduce_shares_one_cache_and_reuse_is_declared(stand_ins, capsys):
    out = stand_ins / "out"
    assert main(["reproduce", "--out", str(out), "--quiet"]) == 0
    doc = json.loads((out / "results.json").read_text())
    assert doc["studies"]["reuser"]["trials_from_study"] == "producer"
    assert doc["studies"]["loner"]["trials_from_study"] == "loner"  # did not declare it: ran its own
    assert (out / "producer" / "producer.png").stat().st_size > 0
    assert "trials from producer" in (out / "report.md").read_text()


def test_a_study_alone_computes_what_it_needs(stand_ins, capsys):
    assert main(["study", "reuser", "--json", "--out", str(stand_ins / "o")]) == 0
    assert json.loads(capsys.readouterr().out)["trials_from_study"] == "reuser"


def test_no_figures(stand_ins, capsys):
    out = stand_ins / "nf"
    assert main(["study", "producer", "--json", "--no-figures", "--out", str(out)]) == 0
    assert json.loads(capsys.readouterr().out)["figures"] == []
    assert main(["reproduce", "--out", str(out), "--quiet", "--no-figures"]) == 0
    assert not (out / "producer").exists() and (out / "report.md").exists()


def test_reproduce_refuses_a_reuse_of_a_later_study(stand_ins, capsys):
    (stand_ins / "analysis" / "early.py").write_text(CONSUMER.format(name="early", reuses=("producer",), order=0))
    assert main(["reproduce", "--out", str(stand_ins / "x"), "--quiet"]) != 0
    assert "runs after it" in capsys.readouterr().err
