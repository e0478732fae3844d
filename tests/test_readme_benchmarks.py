"""The benchmark tables (docs/benchmarks.md, docs/identify.md) are exactly what the committed results files they
name give."""

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _readme_module():
    spec = importlib.util.spec_from_file_location("bench_readme", ROOT / "benchmarks" / "readme.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("page", ["docs/benchmarks.md", "docs/identify.md"])
def test_the_benchmark_table_is_generated_from_committed_results(page):
    mod = _readme_module()
    text = (ROOT / page).read_text()
    files = mod.named_files(text)
    assert files, f"{page}'s benchmark section names no results file"
    for f in files:
        assert (ROOT / f).is_file(), f"{f} is named by {page} but not in the repository"
    section = mod.BEGIN + text.split(mod.BEGIN, 1)[1].split(mod.END, 1)[0] + mod.END
    assert section == mod.render(files, mod.named_only(text)), \
        f"{page}'s benchmark table differs from its results files: run python benchmarks/readme.py --into {page} " \
        + " ".join(map(str, files))


def test_a_changed_number_is_caught(tmp_path):
    import json

    mod = _readme_module()
    files = mod.named_files((ROOT / "docs" / "benchmarks.md").read_text())
    doc = json.loads((ROOT / files[0]).read_text())
    bench = next(k for k, v in doc.items() if isinstance(v, dict) and v.get("rows"))
    doc[bench]["rows"][0]["value"] *= 1.5
    original = mod.render(files)
    mod.ROOT = tmp_path
    (tmp_path / files[0]).parent.mkdir(parents=True, exist_ok=True)
    for f in files[1:]:
        (tmp_path / f).write_bytes((ROOT / f).read_bytes())
    (tmp_path / files[0]).write_text(json.dumps(doc))
    assert mod.render(files) != original


def test_a_page_limited_to_some_benchmarks_shows_their_rows_only():
    import json

    mod = _readme_module()
    text = (ROOT / "docs" / "identify.md").read_text()
    only = mod.named_only(text)
    assert only == ["identify"]
    (file,) = mod.named_files(text)
    benches = [k for k, v in json.loads((ROOT / file).read_text()).items() if isinstance(v, dict) and v.get("rows")]
    assert set(benches) > {"identify"}              # the file holds others, which the page leaves out
    shown, every = mod.render([file], only), mod.render([file])
    rows = [line for line in every.splitlines() if line.startswith("| ") and "`" in line]
    assert 0 < sum(line in shown for line in rows) < len(rows)
